"""One sample's three Warp passes on the GPU, for a profiler: ``ncu`` sees each pass's kernel.

The sample of ``bench/gpu_targets.py`` (9 uint8 frames of 1920 x 1200 already on the device,
RSBlur-like plan, float32): a first sample builds the kernels and the 8-bit table, then
``--samples`` more run for the profiler. On the GPU machine, from the repository root::

    PYTHONPATH=$PWD ncu --kernel-name regex:"blur_average_add|to_raw|finish" --launch-skip 3 \\
        --launch-count 3 --section SpeedOfLight --section ComputeWorkloadAnalysis \\
        --section MemoryWorkloadAnalysis python3 bench/profile_passes.py
"""

from __future__ import annotations

import argparse
import sys

from gpu_targets import FRAMES, SCENE, H, W, make_frames, prepared  # bench/ is on sys.path

from gpu_blur.tiling import Region


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=1, help="samples after the first (default 1)")
    p.add_argument("--device", default="cuda:0", help="Warp device (default cuda:0)")
    args = p.parse_args(argv)
    import warp as wp

    from gpu_blur.backends.warp import WarpBackend

    wp.config.quiet = True
    _, plan, camera, params = prepared(SCENE)
    backend = WarpBackend(f"warp:{args.device}", "float32")
    region = Region.whole(H, W)
    stack = wp.array(make_frames(), dtype=wp.uint8, device=args.device)
    for _ in range(1 + args.samples):
        linear, mask = backend.accumulate(plan, params, stack, None, region)
        image, saturated = backend.to_raw(plan, params, camera, linear, mask, (0, 0), seed=1,
                                          sample_index=0)
        backend.finish(plan, params, camera, image, saturated, region, region, seed=1,
                       sample_index=0)
    wp.synchronize_device(args.device)
    print(f"ran {1 + args.samples} samples of {FRAMES} frames, {W} x {H}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
