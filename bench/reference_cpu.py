"""Time the numpy float64 reference, stage by stage, at 1920 x 1200 (the speed later kernel
backends are measured against), and the default ``gpu-blur generate`` job.

Run from the repository root: ``python bench/reference_cpu.py`` (writes
``bench/results/reference_cpu.json``; medians of 3 runs after one warm-up).
"""

from __future__ import annotations

import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import gpu_blur
from gpu_blur.analysis.bench.host import cpu_name
from gpu_blur.cameras import get_camera
from gpu_blur.reference import average, bayer, demosaic, motion_kernel, noise, rng, shake, transfer
from gpu_blur.reference.color import apply_matrix

OUT = Path(__file__).parent / "results" / "reference_cpu.json"
H, W = 1200, 1920


def median_time(fn, runs: int = 3) -> float:
    fn()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    g = np.random.default_rng(0)
    srgb = g.uniform(0, 1, (H, W, 3))
    frames = [g.uniform(0, 1, (H, W, 3)) for _ in range(9)]
    linear = transfer.srgb_to_linear(srgb)
    cam = get_camera("a7r3")
    raw = bayer.mosaic(apply_matrix(linear, cam.linear_to_camera), bayer.BayerPattern.RGGB)
    kernel = motion_kernel.random_motion_kernel(g.uniform(size=motion_kernel.KERNEL_UNIFORMS), 29)
    homographies = shake.camera_shake_homographies(g.uniform(size=shake.SHAKE_UNIFORMS), H, W,
                                                  17, 16.0, 0.5)

    def accumulate():
        acc = average.FrameAccumulator(H, W)
        for f in frames:
            acc.add(transfer.srgb_to_linear(f))
        acc.result()

    stages = {
        "srgb_to_linear": lambda: transfer.srgb_to_linear(srgb),
        "linear_to_srgb": lambda: transfer.linear_to_srgb(linear),
        "blur_average_9_frames": accumulate,
        "blur_kernel_29x29_with_mask": lambda: (motion_kernel.convolve_kernel(linear, kernel),
                                                motion_kernel.convolve_kernel(linear, kernel)),
        "blur_trajectory_17_poses": lambda: shake.shake_blur(linear, homographies),
        "linear_to_camera": lambda: apply_matrix(linear, cam.linear_to_camera),
        "mosaic": lambda: bayer.mosaic(linear, bayer.BayerPattern.RGGB),
        "poisson_gaussian_noise": lambda: noise.add_poisson_gaussian(
            raw, 8.8915e-5, 2.943e-5, seed=0, sample_index=0),
        "philox_uniforms_per_pixel": lambda: rng.pixel_uniforms(
            0, 0, rng.Stream.SHOT_NOISE, np.arange(H)[:, None], np.arange(W)[None, :]),
        "demosaic_malvar2004": lambda: demosaic.demosaic_malvar2004(raw, bayer.BayerPattern.RGGB),
        "demosaic_bilinear": lambda: demosaic.demosaic_bilinear(raw, bayer.BayerPattern.RGGB),
    }
    results = {name: median_time(fn) for name, fn in stages.items()}
    scene = gpu_blur.load_scene(Path(gpu_blur.__file__).parent / "data/scenes/rsblur.toml")
    results["synthesize_rsblur_scene_9_frames"] = median_time(
        lambda: gpu_blur.synthesize(frames, scene, seed=0))

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "gpu_blur.cli", "generate", "--output", tmp,
                        "--quiet", "--overwrite"], check=True, capture_output=True)
        generate_default = time.perf_counter() - t

    report = {
        "what": "numpy float64 reference, seconds per call at 1920 x 1200 (median of 3 after "
                "a warm-up); generate_default_4_samples is the wall time of `gpu-blur "
                "generate --output DIR` (built-in 600 x 400 photo, 4 samples, incl. start-up)",
        "device": f"CPU: {cpu_name()}, 2 cores",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "gpu_blur": gpu_blur.__version__,
        "seconds": {k: round(v, 4) for k, v in results.items()},
        "generate_default_4_samples_s": round(generate_default, 2),
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(report, indent=1) + "\n")
    width = max(map(len, results))
    for name, sec in results.items():
        print(f"{name:<{width}}  {sec * 1e3:9.1f} ms")
    print(f"{'generate (default, 4 samples)':<{width}}  {generate_default:9.1f} s")


if __name__ == "__main__":
    main()
