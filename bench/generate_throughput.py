"""End-to-end throughput of 9-frame 1920 x 1200 samples, from PNG on disk and from frames in
memory, on numpy and every OpenCL and Warp device, with where the time goes.

Run from the repository root: ``python bench/generate_throughput.py [OUT.json] [SAMPLES]``
(default ``bench/results/generate_throughput_<host>.json``, 3 samples per configuration after
one warm-up sample). "disk" reads the 9 PNGs of each sample (``synthesize`` decodes them);
"memory" passes uint8 arrays already decoded. Writing outputs is not included. Numbers are
samples per second and mean seconds per sample per timing category (gpu_blur.timings).
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

import gpu_blur
from gpu_blur.scene import scene_from_dict

H, W, FRAMES = 1200, 1920, 9


def frames_on_disk(folder: Path) -> list[Path]:
    g = np.random.default_rng(0)
    base = (g.uniform(0, 1, (H, W, 3)) * 255).astype(np.uint8)
    base[100:140, 200:260] = 255  # a clipped highlight, so saturation runs
    paths = []
    for i in range(FRAMES):
        path = folder / f"{i:06d}.png"
        cv2.imwrite(str(path), np.roll(base, 2 * i, axis=1)[:, :, ::-1])
        paths.append(path)
    return paths


def measure(backend: str, precision: str, inputs, samples: int) -> dict:
    scene = scene_from_dict({"blur": {"mode": "average", "frames": FRAMES},
                             "output": {"bits": 8, "precision": precision}})
    gpu_blur.synthesize(inputs, scene, seed=1, sample_index=0, backend=backend)  # warm-up
    totals: dict[str, float] = {}
    start = time.perf_counter()
    for i in range(samples):
        result = gpu_blur.synthesize(inputs, scene, seed=1, sample_index=i + 1, backend=backend)
        for k, v in result.timings.items():
            totals[k] = totals.get(k, 0.0) + v
    wall = time.perf_counter() - start
    return {"backend": backend, "precision": precision, "samples": samples,
            "samples_per_s": round(samples / wall, 3),
            "seconds_per_sample": {k: round(v / samples, 4) for k, v in totals.items()}}


def main() -> None:
    from gpu_blur.backends.opencl import opencl_devices
    from gpu_blur.backends.warp import warp_devices

    samples = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    backends = [("numpy", "float64")]
    backends += [(d.spec, "float32") for d in opencl_devices() if d.usable]
    backends += [(d["spec"], "float32") for d in warp_devices()]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        paths = frames_on_disk(Path(tmp))
        in_memory = [cv2.imread(str(p))[:, :, ::-1].copy() for p in paths]
        for backend, precision in backends:
            for source, inputs in (("disk", paths), ("memory", in_memory)):
                row = measure(backend, precision, inputs, samples) | {"source": source}
                rows.append(row)
                parts = ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in
                                  row["seconds_per_sample"].items() if v)
                print(f"{backend:<12} {precision:<8} {source:<6} {row['samples_per_s']:6.2f} "
                      f"samples/s  ({parts})", flush=True)
    cpu = platform.processor()
    try:
        cpu = next(x.split(":", 1)[1].strip() for x in Path("/proc/cpuinfo").read_text()
                   .splitlines() if x.startswith("model name"))
    except (OSError, StopIteration):
        pass
    devices = {d.spec: f"{d.kind} {d.name} ({d.platform})" for d in opencl_devices()}
    devices |= {d["spec"]: f"{d['kind']} {d['name']} (Warp)" for d in warp_devices()}
    report = {"what": __doc__.strip().splitlines()[0] + " " + __doc__.strip().splitlines()[1],
              "host": platform.node(), "cpu": cpu, "devices": devices,
              "gpu_blur": gpu_blur.__version__, "results": rows}
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else (
        Path(__file__).parent / "results" / f"generate_throughput_{platform.node()}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
