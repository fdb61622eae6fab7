"""Realistic blur as a PyTorch transform on training batches (``pip install "gpu_blur[torch]"``).

:class:`RealisticBlur` is :class:`gpu_blur.Synthesizer` for a training loop: a batch of sharp
images or frame stacks (or, for blur mode none, blurred images and their masks) as tensors on
the CPU or a CUDA device, channels-first as torchvision has them or channels-last as the data
sets give them; blurred and sharp tensors back on the same device, in the same layout. A
sample's draws are fixed by (seed, epoch, index), so a run can be repeated and each epoch sees
new blur, noise and ISP draws. torch is imported only here.

The data sets of :mod:`gpu_blur.datasets` (the built-in photo, GoPro, RSBlur, RealBlur
layouts; seeded crops and flips) are re-exported here; they need no torch and run in
DataLoader workers. Their items batch as the transform takes them::

    data = Photos(samples_per_photo=8, crop=128)    # item: (index, 128 x 128 x 3 uint8)
    loader = DataLoader(data, batch_size=4)          # (B int64, B x 128 x 128 x 3 uint8)
    blur = RealisticBlur({"blur": {"mode": "kernel"}}, seed=1)
    for index, photos in loader:
        blurred, sharp = blur(photos, indices=index)  # B x 128 x 128 x 3 float32 each
"""

from __future__ import annotations

import importlib.util
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

__all__ = ["RealisticBlur", "WARP_MISSING", "batch_layout"]

#: What the default backend needs, and how to get it, in the words of this API.
WARP_MISSING = ("RealisticBlur(backend=None) runs on NVIDIA Warp (warp:cpu for CPU tensors, "
                "warp:cuda:<n> for CUDA ones), and its package warp-lang is not installed: "
                "pip install 'gpu_blur[torch]' brings it; or pass backend='numpy' (the float64 "
                "reference, on the CPU) or backend='opencl' (pip install 'gpu_blur[opencl]')")


def batch_layout(batch, channels_first: bool | None) -> bool:
    """Whether ``batch`` is channels-first: ``channels_first`` when given, else from its shape.

    Channels-first has its 3 colour channels on axis -3 (B x 3 x H x W, B x F x 3 x H x W),
    channels-last on axis -1 (B x H x W x 3, B x F x H x W x 3, as the data sets give them).

    Raises:
        ValueError: quoting the shape, when it has 3 on both axes or on neither.
    """
    if channels_first is not None:
        return channels_first
    shape = tuple(batch.shape)
    first, last = len(shape) >= 4 and shape[-3] == 3, len(shape) >= 4 and shape[-1] == 3
    if first != last:
        return first
    if first:
        raise ValueError(f"batch: shape {shape} reads as channels-first and as channels-last; "
                         "pass RealisticBlur(..., channels_first=True) or False to say which")
    raise ValueError(f"batch: takes B x 3 x H x W or B x H x W x 3 images (B x F x 3 x H x W or "
                     f"B x F x H x W x 3 frame stacks); got shape {shape}")


class RealisticBlur(torch.nn.Module):
    """Blur a training batch realistically, on the batch's own device.

    Args:
        scene: a scene, a TOML path or a built-in scene's name (default ``realblur_j``, the
            RSBlur authors' training-time chain).
        seed: the run's seed; with the epoch and each sample's index it fixes every draw.
        backend: a gpu_blur backend; by default Warp on the batch's device
            (``warp:cuda:<n>`` for CUDA tensors, ``warp:cpu`` otherwise; the ``torch`` extra
            installs it). ``"numpy"`` runs the float64 reference on the CPU.
        channels_first: True: tensors come and go as B x 3 x H x W (B x F x 3 x H x W for
            frames); False: as B x H x W x 3 (B x F x H x W x 3), the data sets' items; None
            (default): each batch's layout is read from its shape (the axis of length 3) and
            the results come back in it.
        with_mask: also return the blurred saturation masks.
        overrides: drawn parameters to fix for every sample (checked here).

    Example::

        blur = gpu_blur.torch.RealisticBlur("realblur_j", seed=1)
        for epoch in range(epochs):
            data.set_epoch(epoch)
            for index, blurred, mask, sharp in loader:   # a BlurredImages data set's batches
                noisy, target = blur(blurred.cuda(), mask.cuda(), sharp.cuda(), indices=index,
                                     epoch=epoch)        # B x H x W x 3 float32, on the GPU
    """

    def __init__(self, scene="realblur_j", *, seed: int = 0, backend: str | None = None,
                 channels_first: bool | None = None, with_mask: bool = False,
                 overrides: Mapping | None = None):
        super().__init__()
        check_overrides(overrides)
        self.scene, self.seed, self.backend = scene, seed, backend
        self.channels_first, self.with_mask, self.overrides = (channels_first, with_mask,
                                                               overrides)
        self._synthesizers: dict = {}
        self._counted = 0  # samples made without indices, for the next default index

    def synthesizer(self, device: torch.device, epoch: int,
                    channels_first: bool | None = None) -> Synthesizer:
        """The :class:`~gpu_blur.Synthesizer` of one device, epoch and layout (made once).

        ``channels_first`` None: the transform's own setting (channels-first when that is None).

        Raises:
            RuntimeError: the default backend's Warp is not installed, saying what to install
                or pass instead.
        """
        if self.backend is None and importlib.util.find_spec("warp") is None:
            raise RuntimeError(WARP_MISSING)
        backend = self.backend or (f"warp:cuda:{device.index or 0}" if device.type == "cuda"
                                   else "warp:cpu")
        if channels_first is None:
            channels_first = self.channels_first is not False
        key = (backend, epoch, channels_first)
        if key not in self._synthesizers:
            self._synthesizers = {k: v for k, v in self._synthesizers.items() if k[1] == epoch}
            self._synthesizers[key] = Synthesizer(
                self.scene, backend=backend, seed=epoch_seed(self.seed, epoch),
                overrides=self.overrides, channels_first=channels_first,
                with_mask=self.with_mask)
        return self._synthesizers[key]

    def forward(self, batch: torch.Tensor, mask: torch.Tensor | None = None,
                sharp: torch.Tensor | None = None, *, indices: Sequence[int] | None = None,
                epoch: int = 0, sequences: Sequence[int] | None = None):
        """(blurred, sharp), or (blurred, sharp, mask) with ``with_mask``.

        Args:
            batch: the sharp images (B x 3 x H x W or B x H x W x 3), frame stacks (B x F x 3
                x H x W or B x F x H x W x 3, blur mode average) or, for blur mode none, the
                blurred images; uint8, uint16 or float in [0, 1], RGB.
            mask: blur mode none: the saturation masks (optional), in the batch's layout.
            sharp: blur mode none: the sharp images (optional: the blurred ones).
            indices: each sample's index in the data set (an integer tensor or a sequence of
                ints); without them samples are numbered in call order from 0.
            epoch: the training epoch (>= 0).
            sequences: each sample's frame sequence index (an integer tensor or a sequence of
                ints; :meth:`gpu_blur.datasets.SharpSequences.window`), which a scene with
                ``blur.draws = "per-sequence"`` needs: the windows of one sequence then share
                their camera settings.

        Returns:
            Float tensors in [0, 1] (float32 with the default ``output.precision``) on the
            batch's device, in its layout: blurred and sharp images, B x 3 x H' x W' or B x
            H' x W' x 3, H' and W' after ``output.crop`` (and an odd last row or column cut
            for the RAW round trip); with ``with_mask`` also the blurred saturation masks.

        Raises:
            ValueError: a bad shape, dtype or value, naming the sample (``sample 3 of 16:
                mask: 1 NaN ...``): float inputs are checked where they lie (one reduction an
                input, read once the batch's passes are queued); nothing is returned.
        """
        check_dense(batch, "batch")  # before its device picks a backend
        if indices is None:
            indices = range(self._counted, self._counted + batch.shape[0])
            self._counted += batch.shape[0]
        elif isinstance(indices, torch.Tensor):
            indices = indices.tolist()
        if isinstance(sequences, torch.Tensor):
            sequences = sequences.tolist()
        first = batch_layout(batch, self.channels_first)
        out = self.synthesizer(batch.device, epoch, first)(batch, mask=mask, sharp=sharp,
                                                           indices=indices, sequences=sequences)
        return (out.blurred, out.sharp, out.mask) if self.with_mask else (out.blurred,
                                                                            out.sharp)
