"""Digests of whole-pipeline outputs, to prove a refactoring changes no bit.

Each case is a scene (the example scenes, and variants that switch on every stage variant the
kernels compile) run on small inputs through :func:`gpu_blur.synthesize`; its digest is the
SHA-256 of the blurred image, the sharp reference, the mask and the drawn parameters. Digests
are recorded per device as the backend names it (``Synthesis.device``; float32 kernels of two
devices may differ in a last bit), in ``tests/data/golden_outputs.json``:

    python tests/golden.py --write tests/data/golden_outputs.json   # record (this machine)
    python tests/golden.py --check tests/data/golden_outputs.json   # compare, list changes

``tests/test_golden_outputs.py`` runs the check for every backend present whose device was
recorded. The record holds the CPU devices of the development machine (recorded at 40370a5;
Debian's PoCL 3.1 at 430b3ee) and an NVIDIA H100 (OpenCL and Warp CUDA, recorded at 430b3ee,
whose outputs on those CPU devices are 40370a5's), all before the kernel backends were
written once (issue 14); and the CPU devices of an Intel Xeon (Skylake) development machine,
PoCL and Intel's runtime, recorded by a9a79b6's code (before to_raw and finish ran batched). When the
draws and the reference moved to :mod:`gpu_blur.reference.fixedmath` (issue 35: the same bits
on every CPU), the cases whose draws changed (minimal, default, kernel_lut16, gaussian_noise,
isp_variants, fast_math, default@40x56) were re-recorded for numpy and Warp's CPU device only;
the other devices' entries for them still hold the old draws until re-recorded there.
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
    """A device as ``Backend.model`` names it, without its number on the host (an OpenCL
    platform number shifts when another runtime is installed: Debian's PoCL put itself before
    Intel's runtime). Records made before ``Synthesis.device`` named the model hold
    ``opencl:0:0 ...`` and ``warp:cuda:0 ...``: both map to the model."""
    return re.sub(r"^(opencl|warp):\S+ ", r"\1 ", device)


def by_device(record: dict) -> dict:
    """A record's entries keyed by :func:`device_key`."""
    return {device_key(device): cases for device, cases in record.items()}


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
    """(digest, device) of one case on one backend spec, or None where the case does not exist."""
    from gpu_blur import synthesize

    backend, _, precision = spec.partition("/")
    scene = scene_for(case, precision or "float32")
    if scene is None:
        return None
    r = synthesize(_inputs(CASES[case][2]), scene, seed=7, sample_index=3, backend=backend,
                   tile=tile)
    return digest(r), r.device


def run_cases(spec: str) -> tuple[str, dict[str, str]]:
    """(device, ``{case[@tile]: digest}``) for one backend spec (e.g. ``numpy``)."""
    out, device = {}, ""
    runs = [(c, None) for c in CASES] + list(TILED.items())
    for case, tile in runs:
        got = run_case(case, spec, tile)
        if got is not None:
            out[case if tile is None else f"{case}@{tile[0]}x{tile[1]}"], device = got
    return device, out


def main(argv=None) -> int:
    """Record or check the digests of every backend present (narrow with GPU_BLUR_BACKENDS)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from conftest import BACKEND_SPECS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--write", type=Path, help="record this machine's digests into this file "
                   "(other devices' records in it are kept)")
    p.add_argument("--check", type=Path, help="compare with this record")
    args = p.parse_args(argv)
    found = dict(run_cases(spec) for spec in BACKEND_SPECS)
    if args.write:
        record = json.loads(args.write.read_text()) if args.write.is_file() else {}
        rerun = {device_key(device) for device in found}  # under its platform number now
        record = {device: cases for device, cases in record.items()
                  if device_key(device) not in rerun}
        record.update(found)
        args.write.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.write}: {', '.join(found)}")
    if args.check:
        recorded = by_device(json.loads(args.check.read_text()))
        changed = [f"{device}: {case}" for device, got in found.items()
                   for case, value in recorded.get(device_key(device), {}).items()
                   if got.get(case) != value]
        unrecorded = [device for device in found if device_key(device) not in recorded]
        print("\n".join(changed) or "every recorded digest is unchanged")
        if unrecorded:
            print(f"not recorded, not compared: {', '.join(unrecorded)}")
        return 1 if changed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
