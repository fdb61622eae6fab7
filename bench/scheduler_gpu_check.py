"""GPU validation of the scheduler (gpu_blur/scheduler.py), run from the project root.

1. Spot checks on clean runs: full-size photos, four scenes, two seeds, OpenCL and Warp CUDA
   in float32 and float64, every tile checked: no failure expected.
2. Planted faults (GPU_BLUR_TEST_FAULT) in each pass: each must be caught.
3. The memory budget against Warp's CUDA memory-pool high-water mark (one process per blur
   mode and precision, budgets ascending): the peak must stay under the budget.
   ``equal_to_cpu_whole`` compares with Warp's CPU device, whole image: equal in float64
   only (CUDA fuses a * b + c in float32); tiled against whole on one device is
   tests/synthesis/test_scheduler.py's job.

Writes $OUT/scheduler_gpu.json (bench/results/scheduler_gpu_h100.json came from an H100).
"""
import json
import os
import subprocess
import sys
import time

import cv2
import numpy as np

import gpu_blur
from gpu_blur.scene import scene_from_dict
from gpu_blur.scheduler import SpotCheckError
from gpu_blur.testhooks import TEST_FAULT

OUT = os.environ.get("OUT", "/tmp")


def budget_child(mode, precision):
    import warp as wp

    from gpu_blur.scheduler import Footprint

    rgb = cv2.cvtColor(cv2.imread("gpu_blur/data/coffee.png"), cv2.COLOR_BGR2RGB)
    big = cv2.resize(rgb, (1920, 1200))
    frames = [big, np.roll(big, 3, 1), np.roll(big, -2, 0)] if mode == "average" else [big]
    scene = scene_from_dict({"blur": {"mode": mode, "frames": 3},
                             "output": {"precision": precision, "bits": 0}})
    tiny = [f[:64, :64] for f in frames]
    gpu_blur.synthesize(tiny, scene, seed=1, sample_index=2, backend="warp:cuda:0")
    wp.synchronize_device("cuda:0")
    base = wp.get_mempool_used_mem_current("cuda:0")
    warm_high = wp.get_mempool_used_mem_high("cuda:0")
    whole = gpu_blur.synthesize(frames, scene, seed=1, sample_index=2, backend="warp:cpu")
    rows = []
    for budget in (8 << 20, 32 << 20, 128 << 20, 512 << 20):
        r = gpu_blur.synthesize(frames, scene, seed=1, sample_index=2, backend="warp:cuda:0",
                                max_device_memory=budget)
        wp.synchronize_device("cuda:0")
        high = wp.get_mempool_used_mem_high("cuda:0")
        fp = Footprint.of(r.plan, r.params, 1200, 1920, precision)
        rows.append({"mode": mode, "precision": precision, "budget": budget, "tiles": r.tiles,
                     "high": high, "base": base, "warm_high": warm_high,
                     "whole_peak_formula": fp.tile_bytes(1200, 1920),
                     "equal_to_cpu_whole": bool(np.array_equal(r.blurred, whole.blurred))})
    print(json.dumps(rows))


def clean_runs(results):
    """Every tile spot-checked on full-size photos: no failure expected."""
    rgb = cv2.cvtColor(cv2.imread("gpu_blur/data/coffee.png"), cv2.COLOR_BGR2RGB)
    rocket = cv2.cvtColor(cv2.imread("tests/data/rocket.jpg"), cv2.COLOR_BGR2RGB)[:426]
    failures = []
    t0 = time.time()
    for be in ["opencl", "warp:cuda:0"]:
        for prec in ["float32", "float64"]:
            fails = runs = 0
            for img in (rgb, rocket):
                for mode, extra in [("average", {}), ("trajectory", {}),
                                    ("kernel", {"output": {"bits": 16}}),
                                    ("trajectory", {"output": {"crf": "a7r3", "bits": 0},
                                                    "camera": {"name": "rsblur-0005"}})]:
                    for seed in range(2):
                        sd = {"blur": {"mode": mode, "frames": 2}, **extra}
                        sd["output"] = {**sd.get("output", {}), "precision": prec}
                        ins = [img, img[:, ::-1].copy()] if mode == "average" else [img]
                        runs += 1
                        try:
                            gpu_blur.synthesize(ins, scene_from_dict(sd), seed=seed,
                                                sample_index=9, backend=be, verify=1.0,
                                                tile=(200, 300))
                        except SpotCheckError as e:
                            fails += 1
                            failures.append(str(e)[:500])
            results[f"clean {be} {prec}"] = f"{fails} of {runs} failed"
    results["clean_failures"] = failures
    results["clean_seconds"] = time.time() - t0


def planted_faults(results):
    """A fault in each pass, on each GPU backend: each must be caught."""
    rgb = cv2.cvtColor(cv2.imread("gpu_blur/data/coffee.png"), cv2.COLOR_BGR2RGB)
    caught = {}
    for be in ["opencl", "warp:cuda:0"]:
        for fault in ["accumulate@100,100", "to_raw@250,400", "finish@399,599"]:
            os.environ[TEST_FAULT] = fault
            try:
                gpu_blur.synthesize([rgb], scene_from_dict({}), seed=1, sample_index=3,
                                    backend=be, verify=1.0, tile=(128, 128))
                caught[f"{be} {fault}"] = "NOT CAUGHT"
            except SpotCheckError as e:
                caught[f"{be} {fault}"] = str(e)[:160]
            del os.environ[TEST_FAULT]
    results["faults"] = caught


def main():
    results = {}
    clean_runs(results)
    planted_faults(results)
    budget = []  # one process per (mode, precision): the high-water mark never resets
    for mode in ["average", "trajectory", "kernel"]:
        for prec in ["float32", "float64"]:
            p = subprocess.run([sys.executable, __file__, mode, prec], capture_output=True,
                               text=True)
            line = [x for x in p.stdout.splitlines() if x.startswith("[")]
            budget += json.loads(line[-1]) if line else [{"mode": mode, "error": p.stderr[-800:]}]
    results["budget"] = budget
    with open(os.path.join(OUT, "scheduler_gpu.json"), "w") as f:
        json.dump(results, f, indent=1)
    for k, v in results.items():
        if k != "budget":
            print(k, v if not isinstance(v, dict) else json.dumps(v, indent=0))
    for row in budget:
        if "error" in row:
            print(row)
            continue
        print(f"{row['mode']:<10} {row['precision']} budget {row['budget'] >> 20:>4} MiB tiles "
              f"{row['tiles']:>4} high {row['high'] / 2**20:8.2f} MiB")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        budget_child(sys.argv[1], sys.argv[2])
    else:
        main()
