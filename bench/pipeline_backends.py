"""Full-pipeline time per megapixel: 9 frames of 1920 x 1200 on numpy, every OpenCL device and
every Warp device.

Run from the repository root: ``python bench/pipeline_backends.py [OUT.json]`` (default
``bench/results/pipeline_backends_<host>.json``). Frames start in host memory (float64 in [0, 1]);
the time covers ``gpu_blur.synthesize`` end to end: uploads, the three passes, downloads.
Medians of 5 runs after one warm-up (the warm-up builds the kernels); every pass ends with a
blocking read, so the device is synchronized before the clock stops.
"""

from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import gpu_blur
from gpu_blur.analysis.bench.host import cpu_name
from gpu_blur.scene import scene_from_dict

H, W, FRAMES, RUNS = 1200, 1920, 9, 5


def time_backend(backend: str, precision: str, frames, scene) -> dict:
    times = []
    for i in range(RUNS + 1):
        t = time.perf_counter()
        result = gpu_blur.synthesize(frames, scene, seed=1, sample_index=i, backend=backend)
        if i:
            times.append(time.perf_counter() - t)
    median = statistics.median(times)
    return {"backend": backend, "precision": precision, "median_s": round(median, 5),
            "s_per_megapixel": round(median / (H * W / 1e6), 6),
            "runs_s": [round(t, 5) for t in times], "output_mean": float(result.blurred.mean())}


def main() -> None:
    from gpu_blur.backends.opencl import opencl_devices
    from gpu_blur.backends.warp import warp_devices

    g = np.random.default_rng(0)
    base = g.uniform(0, 1, (H, W, 3))
    base[100:140, 200:260] = 1.0  # a clipped highlight, so saturation runs
    frames = [np.roll(base, 2 * i, axis=1) for i in range(FRAMES)]
    rows = []
    for precision in ("float32", "float64"):
        scene = scene_from_dict({"blur": {"mode": "average", "frames": FRAMES},
                                 "output": {"bits": 8, "precision": precision}})
        if precision == "float32":
            rows.append(time_backend("numpy", "float64", frames, scene) | {
                "device": f"numpy float64 on {cpu_name()}"})
        for d in opencl_devices():
            if d.usable and (precision == "float32" or d.fp64):
                row = time_backend(d.spec, precision, frames, scene)
                rows.append(row | {"device": f"{d.kind} {d.name} ({d.platform})"})
        for d in warp_devices():
            row = time_backend(d["spec"], precision, frames, scene)
            rows.append(row | {"device": f"{d['kind']} {d['name']} (Warp)"})
    report = {
        "what": "gpu_blur.synthesize end to end, 9 frames of 1920 x 1200 in host memory, scene "
                "average + saturation + A7R3 RAW round trip with Poisson-Gaussian noise + "
                "Malvar + sRGB, 8-bit output; median of 5 after a warm-up",
        "host": platform.node(), "cpu": cpu_name(), "python": platform.python_version(),
        "gpu_blur": gpu_blur.__version__, "results": rows,
    }
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else (
        Path(__file__).parent / "results" / f"pipeline_backends_{platform.node()}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")
    for r in rows:
        print(f"{r['backend']:<12} {r['device'][:48]:<48} {r['precision']:<8} "
              f"{r['median_s'] * 1e3:9.1f} ms  "
              f"{r['s_per_megapixel'] * 1e3:8.2f} ms/MP")


if __name__ == "__main__":
    main()
