"""Where a batch's device time goes: each kernel and copy of ``gpu_blur.Synthesizer`` on CUDA.

Warp's CUDA activity timing (``wp.ScopedTimer(cuda_filter=wp.TIMING_ALL)``) records every
kernel and memory operation of one batch after a warm-up batch; printed summed by name,
largest first, with the batch's wall time beside them. On the GPU machine, from the
repository root::

    PYTHONPATH=$PWD python3 bench/profile_batch.py [--scene realblur_j] [--batch 16]
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np
import torch

import gpu_blur


def inputs(scene, batch: int, h: int, w: int) -> dict:
    """Random sRGB inputs of the scene's blur mode as torch CUDA tensors (uint8 frames)."""
    rng = np.random.default_rng(0)
    if scene.blur.mode == "average":
        frames = rng.integers(0, 256, (batch, scene.blur.frames, h, w, 3), dtype=np.uint8)
        return {"batch": torch.from_numpy(frames).cuda()}
    images = rng.random((batch, h, w, 3), dtype=np.float32)
    given = {"batch": torch.from_numpy(images).cuda()}
    if scene.blur.mode == "none":
        given["mask"] = torch.from_numpy((images > 0.95).astype(np.float32)).cuda()
    return given


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="realblur_j", help="scene name or TOML (default "
                   "realblur_j)")
    p.add_argument("--batch", type=int, default=16, help="samples per batch (default 16)")
    p.add_argument("--size", default="1920x1200", help="WxH (default 1920x1200)")
    args = p.parse_args(argv)
    import warp as wp

    w, h = (int(v) for v in args.size.split("x"))
    synth = gpu_blur.Synthesizer(args.scene, backend="warp:cuda:0")
    given = inputs(synth.scene, args.batch, h, w)
    synth(given["batch"], mask=given.get("mask"))
    torch.cuda.synchronize()
    start = time.perf_counter()
    with wp.ScopedTimer("batch", cuda_filter=wp.TIMING_ALL, print=False) as timer:
        synth(given["batch"], mask=given.get("mask"), first_index=args.batch)
        torch.cuda.synchronize()
    wall = time.perf_counter() - start
    totals: dict[str, float] = collections.defaultdict(float)
    counts: dict[str, int] = collections.defaultdict(int)
    for r in timer.timing_results:
        totals[r.name] += r.elapsed
        counts[r.name] += 1
    device = sum(totals.values())
    print(f"{args.scene}, {w} x {h}, batch {args.batch}: wall {1e3 * wall / args.batch:.3f} "
          f"ms per sample, device activity {device / args.batch:.3f} ms per sample")
    for name, ms in sorted(totals.items(), key=lambda kv: -kv[1]):
        print(f"  {ms / args.batch:8.4f} ms/sample  x{counts[name] // args.batch:<3} {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
