"""Synthesize training pairs on the fly inside a PyTorch loop, on the GPU it trains on.

The blurred image never leaves the GPU: ``synthesize(..., on_device=True)`` returns a Warp
array that ``torch.from_dlpack`` wraps without a copy. Run from the repository root:
``python bench/torch_on_the_fly.py [STEPS]``; prints samples per second and checks that the
tensor shares the Warp array's memory.
"""

from __future__ import annotations

import sys
import time

import cv2
import numpy as np
import torch

import gpu_blur
from gpu_blur.discovery import default_photo
from gpu_blur.scene import scene_from_dict


def batches(photo: np.ndarray, scene, batch: int, backend: str):
    """Endless (blurred, sharp) batches as CUDA tensors, one new draw per sample."""
    index = 0
    while True:
        blurred, sharp = [], []
        for _ in range(batch):
            result = gpu_blur.synthesize([photo], scene, seed=0, sample_index=index,
                                         backend=backend, on_device=True)
            tensor = torch.from_dlpack(result.blurred)  # zero copy
            assert tensor.data_ptr() == result.blurred.ptr
            blurred.append(tensor.permute(2, 0, 1))
            sharp.append(torch.from_numpy(result.sharp).permute(2, 0, 1))
            index += 1
        yield torch.stack(blurred), torch.stack(sharp).to(blurred[0].device)


def main() -> None:
    steps = int(sys.argv[1]) if len(sys.argv) > 1 else 20
    backend = "warp:cuda:0" if torch.cuda.is_available() else "warp:cpu"
    photo = cv2.imread(str(default_photo()))[:, :, ::-1].copy()
    scene = scene_from_dict({"blur": {"mode": "trajectory"}, "output": {"bits": 0}})
    net = torch.nn.Conv2d(3, 3, 3, padding=1).to("cuda" if "cuda" in backend else "cpu")
    opt = torch.optim.SGD(net.parameters(), lr=1e-3)
    loader = batches(photo, scene, batch=4, backend=backend)
    next(loader)  # warm-up: builds the kernels
    start = time.perf_counter()
    for _ in range(steps):
        blurred, sharp = next(loader)
        loss = torch.nn.functional.l1_loss(net(blurred), sharp)
        opt.zero_grad()
        loss.backward()
        opt.step()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    took = time.perf_counter() - start
    print(f"{backend}: {steps * 4 / took:.1f} samples/s in a training loop "
          f"({steps} steps of 4, 600 x 400), final loss {loss.item():.4f}")


if __name__ == "__main__":
    main()
