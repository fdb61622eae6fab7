"""What a synthesis returns: :class:`Synthesis` (one sample), :class:`Batch`, and their crop."""

from __future__ import annotations

import dataclasses

import numpy as np

from gpu_blur.backends import to_host
from gpu_blur.planning import Plan
from gpu_blur.reference.output import crop_border
from gpu_blur.tiling import Region

__all__ = ["Batch", "Synthesis", "inner"]


@dataclasses.dataclass
class Synthesis:
    """One synthesized sample.

    Attributes:
        blurred: H x W x 3 float32 in [0, 1], RGB, the realistic blurred image: multiples of
            1/255 with the default ``output.bits = 8`` (1/65535 with 16; ``bits = 0`` keeps
            float values).
        sharp: H x W x 3 float32 in [0, 1], the reference frame (middle frame of an average,
            the photo itself otherwise), toned like ``blurred``.
        mask: H x W x 3 float32 in [0, 1], the blurred saturation mask (fetched from the
            device on first use); None in what a worker process sends for a set that does
            not save masks (:func:`gpu_blur.generate.for_driver`).
        raw: with ``Synthesizer(with_raw=True)``, H x W float32: the noisy white-balanced
            Bayer mosaic before demosaicing (the to_raw pass's output), cropped like the
            outputs (fetched on first use); else None.
        raw_info: with ``with_raw``, what reading it needs
            (:func:`gpu_blur.outputs.raw_metadata`: CFA pattern, levels, gains, matrix).
        params: every drawn value (see :data:`gpu_blur.params.DRAW_INDEX`).
        plan: the stages that ran.
        timings: seconds this call spent per :mod:`gpu_blur.timings` category (reading,
            copies, kernels, checks; writing is 0 here), plus ``other`` and ``total``.
        tiles: how many tiles the image ran in.
        spot_checks: how many of them were checked against the numpy reference.
        device: the model of device that made it, in words (the backend's ``model``:
            ``warp NVIDIA H200, float32``, without the device's number on this host, so a
            set's manifest is the same whichever GPU made each sample).
        png: the blurred and sharp images' PNG streams deflated on the device, as
            :attr:`Batch.png` holds a sample's (``{"blurred": stream, "sharp": stream}``), or
            None: the files' encoder uses them instead of deflating the codes again.

    A worker process of ``gpu-blur generate`` sends blurred and sharp as the set's integer
    codes instead (:func:`gpu_blur.generate.for_driver`).
    """

    blurred: np.ndarray
    sharp: np.ndarray
    _mask: object = dataclasses.field(repr=False)
    params: dict
    plan: Plan
    timings: dict = dataclasses.field(default_factory=dict)
    tiles: int = 1
    spot_checks: int = 0
    crop: int = 0
    device: str = ""
    _raw: object = dataclasses.field(default=None, repr=False)
    raw_info: dict | None = None
    png: dict | None = dataclasses.field(default=None, repr=False)

    @property
    def mask(self) -> np.ndarray | None:
        """The blurred saturation mask, H x W x 3 float32 in [0, 1]."""
        if self._mask is not None and not isinstance(self._mask, np.ndarray):
            self._mask = crop_border(to_host(self._mask, np.float32), self.crop)
        return self._mask

    @property
    def raw(self) -> np.ndarray | None:
        """The noisy white-balanced mosaic (``with_raw``), H x W float32, or None."""
        if self._raw is not None and not isinstance(self._raw, np.ndarray):
            self._raw = crop_border(to_host(self._raw, np.float32), self.crop)
        return self._raw

    def __getstate__(self):  # a device array does not cross processes: fetch it first
        png = self.png and {k: (b"".join(parts),) for k, parts in self.png.items()}
        return {**self.__dict__, "_mask": self.mask, "_raw": self.raw, "png": png}


@dataclasses.dataclass
class Batch:
    """What :class:`~gpu_blur.synthesis.synthesizer.Synthesizer` returns for a batch of B samples.

    Attributes:
        blurred: B x H' x W' x 3 realistic blurred images in [0, 1], RGB, of the input's
            array type and device (B x 3 x H' x W' with ``channels_first``); H', W': the
            input's size less ``output.crop`` on each side (and an odd last row or column
            for the RAW round trip). float32 in host memory; on a device, the compute type;
            with ``codes=True`` the output's uint8 or uint16 codes.
        sharp: the sharp references, the same way.
        mask: the blurred saturation masks with ``with_mask=True``, else None.
        raw: with ``with_raw=True``, B x H' x W' float32 host array (numpy): the noisy
            white-balanced Bayer mosaics before demosaicing, cropped like the outputs; else
            None.
        raw_info: with ``with_raw``, each sample's :func:`gpu_blur.outputs.raw_metadata`.
        params: each sample's drawn values (:data:`gpu_blur.params.DRAW_INDEX`).
        plans: each sample's plan (auto saturation decides per sample).
        timings: seconds the batch spent per :mod:`gpu_blur.timings` category.
        png: with ``png=True`` where it applies, each sample's PNG streams deflated on the
            device, ``{"blurred": stream, "sharp": stream}`` (an image the device made none
            for, absent); a stream iterates over the consecutive parts of the zlib stream of
            its image's Sub-filtered rows, once the device made them
            (:class:`gpu_blur.png_device.PendingStream`); else None.
    """

    blurred: object
    sharp: object
    mask: object
    params: list
    plans: list
    timings: dict
    raw: np.ndarray | None = None
    raw_info: list | None = None
    png: list | None = None


def inner(shape, crop: int) -> Region:
    """The region of an ``h x w (x 3)`` image left after cutting ``crop`` pixels per side."""
    h, w = shape[:2]
    return Region(crop, crop, h - 2 * crop, w - 2 * crop, h, w)
