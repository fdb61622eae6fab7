"""Digests of whole-pipeline outputs, to prove a refactoring changes no bit.

Each case is a scene (the example scenes, and variants that switch on every stage variant the
kernels compile) run on small inputs through :func:`gpu_blur.synthesize`; its digest is the
SHA-256 of the blurred image, the sharp reference, the mask and the drawn parameters. A digest
is recorded under what its bits depend on (:func:`record_key`), in
``tests/data/golden_outputs.json``:

- numpy: nothing else. Its arithmetic is IEEE operations in a fixed order
  (:mod:`gpu_blur.reference.fixedmath`), the same bits on every CPU.
- a kernel device: its model, its runtime's version and (CPU runtimes) the instruction set the
  runtime compiles for; a compiler may contract ``a * b + c`` or call another ``pow``, so a
  digest recorded for one runtime is never asserted against another.
- interpolated cases, on every backend, also OpenCV's version and the SIMD paths it dispatches
  to: its optical flows (DIS) give other last bits on another instruction set.

    python tests/golden.py --write tests/data/golden_outputs.json   # record (this machine)
    python tests/golden.py --check tests/data/golden_outputs.json   # compare, list changes

``tests/synthesis/test_golden_outputs.py`` runs the check for every backend present whose key was
recorded. The record holds this project's development machine (an Intel Xeon with AVX-512:
numpy, PoCL 3.1, Intel's CPU runtime, Warp's CPU device) and its GPU machine, recorded when the
draws moved to fixedmath (issue 35): NVIDIA OpenCL and Warp CUDA on an H200 (driver 580.159.04);
and an AMD EPYC with AVX2 only (2026-11-28), whose digests equal the Xeon's under the same target:
Warp's CPU device and PoCL alike for AVX2 and AVX-512, Intel's runtime like its core-avx2 build;
with its SSE4.2 keys (.ci/run's second pass there), where the interpolated case's flows and
Intel's float32 builds for corei7 give other digests.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path

import numpy as np

SCENES = Path(__file__).resolve().parents[1] / "gpu_blur" / "data" / "scenes"

#: case -> (base scene file or None, changes, input kind)
CASES: dict[str, tuple[str | None, dict, str]] = {
    "minimal": ("minimal.toml", {}, "photo"),
    "rsblur": ("rsblur.toml", {}, "frames"),
    "realblur_j": ("realblur_j.toml", {}, "blurred"),
    "default": (None, {}, "photo"),
    "kernel_lut16": (None, {"blur": {"mode": "kernel"}, "saturation": {"mode": "on"},
                            "output": {"crf": "a7r3-lut", "bits": 16}}, "photo"),
    "interpolated": (None, {"blur": {"mode": "average", "frames": 9, "interpolation": 2},
                            "output": {"crf": "none", "bits": 0}}, "frames"),
    "gaussian_noise": (None, {"noise": {"model": "gaussian"}, "isp": {"round_trip": "always"},
                              "output": {"crf": "a7r3"}}, "photo"),
    "isp_variants": (None, {"isp": {"demosaic": "bilinear", "border": "zero", "pattern": "GBRG",
                                    "clip_camera": True, "clip_demosaic": True},
                            "noise": {"poisson": "normal", "normal_above": 10.0},
                            "saturation": {"mode": "on"}}, "photo"),
    "fast_math": (None, {"output": {"fast_math": True}}, "photo"),
}
#: Cases also run in tiles (rows, columns), as the scheduler streams them.
TILED = {"default": (40, 56), "rsblur": (40, 56)}


def _inputs(kind: str):
    import cv2

    path = SCENES.parent / "coffee.png"
    rgb = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    crop = np.ascontiguousarray(rgb[150:246, 200:328])  # 96 x 128, the spoon's highlights
    if kind == "photo":
        return [crop]
    frames = [np.ascontiguousarray(rgb[150 + i:246 + i, 200 + 2 * i:328 + 2 * i])
              for i in range(9)]
    if kind == "frames":
        return frames
    blurred = np.mean([f.astype(np.float32) / 255 for f in frames], axis=0, dtype=np.float32)
    mask = np.mean([(f == 255).astype(np.float32) for f in frames], axis=0, dtype=np.float32)
    return {"blurred": blurred, "mask": mask, "sharp": frames[4]}


def scene_for(case: str, precision: str):
    """The case's scene at ``precision`` (None when the case does not exist at it)."""
    from gpu_blur.scene import scene_from_dict, toml_loads

    base, changes, _ = CASES[case]
    data = toml_loads((SCENES / base).read_text()) if base else {}
    for section, values in changes.items():
        data.setdefault(section, {}).update(values)
    if precision == "float64" and data.get("output", {}).get("fast_math"):
        return None
    data.setdefault("output", {})["precision"] = precision
    return scene_from_dict(data)


def device_key(device: str) -> str:
    """A device as ``Synthesis.device`` names it, without its number on the host (an OpenCL
    platform number shifts when another runtime is installed)."""
    return re.sub(r"^(opencl|warp):\S+ ", r"\1 ", device)


def host_isa() -> str:
    """The widest x86-64 vector extension this CPU has (what CPU compilers target), or the
    machine's name elsewhere."""
    import platform

    try:
        flags = set(open("/proc/cpuinfo").read().split())
    except OSError:
        flags = set()
    for flag, name in (("avx512f", "AVX-512"), ("avx2", "AVX2")):
        if flag in flags:
            return f"x86-64 {name}"
    return platform.machine()


def runtime_key(spec: str) -> str:
    """What a kernel backend's bits depend on beyond its model: runtime version, target."""
    import os

    backend = spec.partition("/")[0]
    if backend.startswith("opencl"):
        from gpu_blur.backends.opencl import cl  # after gpu_blur registers its runtimes

        p, d = (int(i) for i in backend.split(":")[1:3])
        platform = cl.get_platforms()[p]
        device = platform.get_devices()[d]
        key = f"{platform.version.strip()}; driver {device.driver_version.strip()}"
        if "Intel" in platform.name and device.type & cl.device_type.CPU:  # can be told a
            key += f"; {os.environ.get('CL_CONFIG_CPU_TARGET_ARCH') or host_isa()}"  # target
        elif device.type & cl.device_type.CPU:  # PoCL names its target in the device's name
            key += f"; {host_isa()}"
        return key
    if backend.startswith("warp"):
        import warp as wp

        if "cuda" in backend:
            return f"warp {wp.__version__}; CUDA driver {wp.get_cuda_driver_version()}"
        return f"warp {wp.__version__}; {host_isa()}"
    return ""


def flows_key() -> str:
    """OpenCV's version and the SIMD paths it dispatches to (``OPENCV_CPU_DISABLE`` honoured)."""
    import cv2

    paths = [f.lstrip("*") for f in cv2.getCPUFeaturesLine().split()
             if f.startswith("*") and not f.endswith("?")]
    return f"OpenCV {cv2.__version__} {'+'.join(paths) or 'baseline'}"


def record_key(spec: str, device: str, case: str) -> str:
    """The record's key for ``case`` run on ``spec`` (whose ``Synthesis.device`` is ``device``)."""
    parts = [device_key(device), runtime_key(spec)]
    if CASES[case.partition("@")[0]][1].get("blur", {}).get("interpolation"):
        parts.append(flows_key())
    return " | ".join(p for p in parts if p)


def digest(result) -> str:
    """SHA-256 of a Synthesis: blurred, sharp, mask (float32 bytes) and parameters."""
    h = hashlib.sha256()
    for a in (result.blurred, result.sharp, result.mask):
        h.update(np.ascontiguousarray(a, dtype=np.float32).tobytes())
    params = {k: (np.asarray(v, np.float64).tobytes().hex() if isinstance(v, np.ndarray)
                  else repr(v)) for k, v in sorted(result.params.items())}
    h.update(json.dumps(params, sort_keys=True).encode())
    return h.hexdigest()


def run_case(case: str, spec: str, tile=None):
    """(digest, record key) of one case on one backend spec, or None where the case does not
    exist."""
    from gpu_blur import synthesize

    backend, _, precision = spec.partition("/")
    scene = scene_for(case, precision or "float32")
    if scene is None:
        return None
    r = synthesize(_inputs(CASES[case][2]), scene, seed=7, sample_index=3, backend=backend,
                   tile=tile)
    return digest(r), record_key(spec, r.device, case)


def run_cases(spec: str) -> dict[str, dict[str, str]]:
    """``{record key: {case[@tile]: digest}}`` for one backend spec (e.g. ``numpy``)."""
    out: dict[str, dict[str, str]] = {}
    runs = [(c, None) for c in CASES] + list(TILED.items())
    for case, tile in runs:
        got = run_case(case, spec, tile)
        if got is not None:
            out.setdefault(got[1], {})[case if tile is None else f"{case}@{tile[0]}x{tile[1]}"] \
                = got[0]
    return out


def main(argv=None) -> int:
    """Record or check the digests of every backend present (narrow with GPU_BLUR_BACKENDS)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from conftest import BACKEND_SPECS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--write", type=Path, help="record this machine's digests into this file "
                   "(entries under other keys are kept)")
    p.add_argument("--check", type=Path, help="compare with this record")
    args = p.parse_args(argv)
    found: dict[str, dict[str, str]] = {}
    for spec in BACKEND_SPECS:
        for key, cases in run_cases(spec).items():
            found.setdefault(key, {}).update(cases)
    if args.write:
        record = json.loads(args.write.read_text()) if args.write.is_file() else {}
        for key, cases in found.items():
            record.setdefault(key, {}).update(cases)
        args.write.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.write}: {', '.join(found)}")
    if args.check:
        recorded = json.loads(args.check.read_text())
        changed = [f"{key}: {case}" for key, got in found.items()
                   for case, value in got.items()
                   if case in recorded.get(key, {}) and recorded[key][case] != value]
        unrecorded = [key for key in found if key not in recorded]
        print("\n".join(changed) or "every recorded digest is unchanged")
        if unrecorded:
            print("not recorded, not compared: " + "; ".join(unrecorded))
        return 1 if changed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
