"""Realistic blur as a PyTorch transform on training batches (``pip install "gpu_blur[torch]"``).

:class:`RealisticBlur` is :class:`gpu_blur.Synthesizer` for a training loop: a batch of sharp
images or frame stacks (or, for blur mode none, blurred images and their masks) as tensors on
the CPU or a CUDA device, channels-first as torchvision has them; blurred and sharp tensors
back on the same device. A sample's draws are fixed by (seed, epoch, index), so a run can be
repeated and each epoch sees new blur, noise and ISP draws. torch is imported only here.

The data sets of :mod:`gpu_blur.datasets` (GoPro, RSBlur, RealBlur layouts; seeded crops and
flips) are re-exported here; they need no torch and run in DataLoader workers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from gpu_blur.arrays import check_dense
from gpu_blur.datasets import (  # noqa: F401  (re-exported: the data side of the transform)
    BlurredImages,
    Photos,
    RealBlurPairs,
    SharpSequences,
    epoch_seed,
)
from gpu_blur.params import check_overrides
from gpu_blur.synthesis import Synthesizer


class RealisticBlur(torch.nn.Module):
    """Blur a training batch realistically, on the batch's own device.

    Args:
        scene: a scene, a TOML path or a built-in scene's name (default ``realblur_j``, the
            RSBlur authors' training-time chain).
        seed: the run's seed; with the epoch and each sample's index it fixes every draw.
        backend: a gpu_blur backend; by default Warp on the batch's device
            (``warp:cuda:<n>`` for CUDA tensors, ``warp:cpu`` otherwise).
        channels_first: tensors come and go as B x 3 x H x W (B x F x 3 x H x W for frames).
        with_mask: also return the blurred saturation masks.
        overrides: drawn parameters to fix for every sample (checked here).

    Example::

        blur = gpu_blur.torch.RealisticBlur("realblur_j", seed=1)
        for epoch in range(epochs):
            for index, blurred, mask in loader:          # CUDA tensors, B x 3 x H x W
                noisy, sharp = blur(blurred, mask, indices=index, epoch=epoch)
    """

    def __init__(self, scene="realblur_j", *, seed: int = 0, backend: str | None = None,
                 channels_first: bool = True, with_mask: bool = False,
                 overrides: Mapping | None = None):
        super().__init__()
        check_overrides(overrides)
        self.scene, self.seed, self.backend = scene, seed, backend
        self.channels_first, self.with_mask, self.overrides = (channels_first, with_mask,
                                                               overrides)
        self._synthesizers: dict = {}
        self._counted = 0  # samples made without indices, for the next default index

    def synthesizer(self, device: torch.device, epoch: int) -> Synthesizer:
        """The :class:`~gpu_blur.Synthesizer` of one device and epoch (made once)."""
        backend = self.backend or (f"warp:cuda:{device.index or 0}" if device.type == "cuda"
                                   else "warp:cpu")
        key = (backend, epoch)
        if key not in self._synthesizers:
            self._synthesizers = {k: v for k, v in self._synthesizers.items() if k[1] == epoch}
            self._synthesizers[key] = Synthesizer(
                self.scene, backend=backend, seed=epoch_seed(self.seed, epoch),
                overrides=self.overrides, channels_first=self.channels_first,
                with_mask=self.with_mask)
        return self._synthesizers[key]

    def forward(self, batch: torch.Tensor, mask: torch.Tensor | None = None,
                sharp: torch.Tensor | None = None, *, indices: Sequence[int] | None = None,
                epoch: int = 0):
        """(blurred, sharp), or (blurred, sharp, mask) with ``with_mask``.

        Args:
            batch: the sharp images (B x 3 x H x W), frame stacks (B x F x 3 x H x W, blur
                mode average) or, for blur mode none, the blurred images; uint8, uint16 or
                float in [0, 1], RGB.
            mask: blur mode none: the saturation masks (optional).
            sharp: blur mode none: the sharp images (optional: the blurred ones).
            indices: each sample's index in the data set (an integer tensor or a sequence of
                ints); without them samples are numbered in call order from 0.
            epoch: the training epoch (>= 0).
        """
        check_dense(batch, "batch")  # before its device picks a backend
        if indices is None:
            indices = range(self._counted, self._counted + batch.shape[0])
            self._counted += batch.shape[0]
        elif isinstance(indices, torch.Tensor):
            indices = indices.tolist()
        out = self.synthesizer(batch.device, epoch)(batch, mask=mask, sharp=sharp,
                                                    indices=indices)
        return (out.blurred, out.sharp, out.mask) if self.with_mask else (out.blurred,
                                                                            out.sharp)
