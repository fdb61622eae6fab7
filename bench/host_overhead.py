"""Host milliseconds per ``Synthesizer`` call on a tiny scene, where the device has little to do.

The training benchmark's random-kernel scene (``blur.mode = "kernel"``, output bits 0, crop 0;
bench/user_paths.py's ``kernel_256``) at ``--size`` (default 64 x 64), batches of ``--batch``
from numpy and torch (CPU tensors, and CUDA tensors where the backend runs on CUDA), uint8 and
float32. Each input warms up once; reported: the median over ``--runs`` of a call's wall time,
the device synchronized, per batch and per sample. On a GPU a tiny scene's call is nearly all
host work (draws, checks, launches), so two commits compare by it; on ``warp:cpu`` the kernels
themselves dominate. The same script runs against any
commit with a ``Synthesizer``; from the repository root of each tree::

    PYTHONPATH=$PWD python3 bench/host_overhead.py --backend warp:cuda:0 --json $OUT/host.json
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
from gpu_blur.scene import scene_from_dict

SCENE = {"blur": {"mode": "kernel"}, "output": {"bits": 0, "crop": 0}}


def batches(backend, size: int, count: int) -> dict:
    """{name: batch}: the same random image as uint8 codes and float32 values, numpy and torch."""
    codes = np.random.default_rng(0).integers(0, 256, (count, size, size, 3), np.uint8)
    values = (codes / np.float32(255)).astype(np.float32)
    out = {"numpy uint8": codes, "numpy float32": values}
    try:
        import torch
    except ImportError:
        return out
    out.update({"torch cpu uint8": torch.from_numpy(codes),
                "torch cpu float32": torch.from_numpy(values)})
    if getattr(backend, "uses_cuda", False) and torch.cuda.is_available():
        out.update({"torch cuda uint8": torch.from_numpy(codes).cuda(),
                    "torch cuda float32": torch.from_numpy(values).cuda()})
    return out


def synchronize(backend) -> None:
    """Wait for the backend's device and, where torch has CUDA, for torch's."""
    if hasattr(backend, "wait"):
        backend.wait()
    try:
        import torch
    except ImportError:
        return
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--backend", default="warp:cpu")
    p.add_argument("--size", type=int, default=64, help="image side (pixels)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    backend = get_backend(args.backend)
    synth = gpu_blur.Synthesizer(scene_from_dict(SCENE), backend=backend, seed=1)
    rows = []
    for name, batch in batches(backend, args.size, args.batch).items():
        synth(batch)  # warm-up: first launches compile
        synchronize(backend)
        spent = []
        for _ in range(args.runs):
            start = time.perf_counter()
            synth(batch)
            synchronize(backend)
            spent.append(time.perf_counter() - start)
        ms = statistics.median(spent) * 1e3
        rows.append({"input": name, "batch_ms": ms, "sample_ms": ms / args.batch})
    print(f"{'input':20} {'ms a batch':>11} {'ms a sample':>12}   ({backend.device}, "
          f"{args.size} x {args.size}, batches of {args.batch})")
    for row in rows:
        print(f"{row['input']:20} {row['batch_ms']:11.2f} {row['sample_ms']:12.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": str(backend.device), "host": platform.node(),
                       "processor": platform.processor(), "size": args.size,
                       "batch": args.batch, "runs": args.runs, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
