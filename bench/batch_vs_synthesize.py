"""Per-sample time of ``synthesize`` one sample at a time against ``Synthesizer`` batches.

Two example scenes at one size on one backend: RSBlur (9 uint8 frames) and RealBlur-J (a
float32 blurred image and its mask). Each path warms up once, then the median of ``--runs``
timings of ``--batch`` samples. With a gpu_blur that has no ``Synthesizer`` (an older
checkout on ``PYTHONPATH``) only ``synthesize`` is timed, so one script compares commits::

    PYTHONPATH=$PWD python bench/batch_vs_synthesize.py --backend opencl --json out.json

Prints ms per sample; ``--json`` writes them with the device named.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import numpy as np

import gpu_blur
from gpu_blur.backends import get_backend


def inputs(scene_name: str, batch: int, h: int, w: int) -> dict:
    rng = np.random.default_rng(0)
    if scene_name == "rsblur":
        return {"batch": rng.integers(0, 256, (batch, 9, h, w, 3), dtype=np.uint8)}
    images = rng.random((batch, h, w, 3), dtype=np.float32)
    return {"batch": images, "mask": (images > 0.97).astype(np.float32)}


def one_by_one(scene, given: dict, b: int, backend, index: int):
    if "mask" in given:
        sample = {"blurred": given["batch"][b], "mask": given["mask"][b]}
    else:
        sample = list(given["batch"][b])
    return gpu_blur.synthesize(sample, scene, seed=1, sample_index=index, backend=backend)


def median_ms(fn, runs: int, count: int) -> float:
    fn(0)
    times = []
    for r in range(runs):
        start = time.perf_counter()
        fn(r + 1)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times) / count


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", default="opencl", help="backend (default opencl)")
    p.add_argument("--size", default="1920x1200", help="WxH (default 1920x1200)")
    p.add_argument("--batch", type=int, default=4, help="samples per batch (default 4)")
    p.add_argument("--runs", type=int, default=3, help="timed repeats (default 3)")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    backend = get_backend(args.backend, "float32")
    results = {"device": backend.device, "cpu": platform.processor() or platform.machine(),
               "size": [w, h], "batch": args.batch, "runs": args.runs, "ms_per_sample": {}}
    for name in ("rsblur", "realblur_j"):
        scene = gpu_blur.load_scene(name)
        given = inputs(name, args.batch, h, w)
        row = {"synthesize": median_ms(
            lambda r, s=scene, g=given: [one_by_one(s, g, b, backend, r * 100 + b)
                                         for b in range(args.batch)], args.runs, args.batch)}
        if hasattr(gpu_blur, "Synthesizer"):
            synth = gpu_blur.Synthesizer(scene, backend=backend, seed=1)
            row["batch"] = median_ms(
                lambda r, g=given, s=synth: s(g["batch"], mask=g.get("mask"),
                                              first_index=r * 100),
                args.runs, args.batch)
            first = synth(given["batch"], mask=given.get("mask"))
            reused = [np.empty_like(first.blurred), np.empty_like(first.sharp)]
            row["batch, out="] = median_ms(
                lambda r, g=given, s=synth, o=reused: s(g["batch"], mask=g.get("mask"),
                                                        first_index=r * 100, out=o),
                args.runs, args.batch)
        results["ms_per_sample"][name] = row
        print(f"{name}: " + ", ".join(f"{k} {v:.1f} ms" for k, v in row.items()), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
