"""Blur by averaging frames (RSBlur "syn", GoPro_INTER_ABME; pipeline notes section 2A).

The blurred image is the plain, equally weighted mean of the linearised frames, and the
saturation mask is, per channel, the fraction of frames whose linear value is saturated
(neither "any channel" nor "all channels"). See :mod:`gpu_blur.reference.blur` for the
conventions shared by the blur kinds.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

__all__ = ["SATURATION_LEVEL", "FrameAccumulator", "average_frames", "saturation_indicator"]

#: Linear value at or above which a channel counts as saturated (RSBlur issue #6: 8-bit 255).
SATURATION_LEVEL = 1.0


def saturation_indicator(linear) -> np.ndarray:
    """Per-channel saturation indicator ``[x >= 1]``.

    Args:
        linear: linear values, any shape.

    Returns:
        float64 array of the same shape: 1.0 where the value is ``>= SATURATION_LEVEL`` (1.0),
        else 0.0 (NaN counts as unsaturated).
    """
    return (np.asarray(linear, dtype=np.float64) >= SATURATION_LEVEL).astype(np.float64)


class FrameAccumulator:
    """Running mean of linear frames and per-channel fraction of saturated frames.

    RSBlur issue #6 (pipeline notes section 2A): ``B = mean_t(frame_t)`` with equal weights and
    ``M = mean_t([frame_t >= 1])`` per channel. Frames are added one at a time and not kept, so
    65 (RSBlur) or 1,000 frames cost the memory of two images. The image sum is a plain float64
    sum (relative error ``<= (n - 1) * 2**-53`` for non-negative frames, ``< 1.2e-13`` at
    ``n = 1000``); the saturation counts are float64 sums, exact integers unless a frame brings
    its own fractional indicator (an interpolated frame, :mod:`gpu_blur.reference.interpolate`).

    Args:
        height: frame height ``H`` in pixels.
        width: frame width ``W`` in pixels.
        channels: channels per frame ``C`` (3 for RGB).
    """

    def __init__(self, height: int, width: int, channels: int = 3) -> None:
        if min(height, width, channels) < 1:
            raise ValueError(f"frame shape must be positive; got ({height}, {width}, {channels})")
        self.shape: tuple[int, int, int] = (int(height), int(width), int(channels))
        self._sum = np.zeros(self.shape, dtype=np.float64)
        self._saturated = np.zeros(self.shape, dtype=np.float64)
        self._count = 0

    @property
    def count(self):
        """Frames added so far, a weighted frame counting its weight.

        An int, or per pixel an ``H x W x 1`` int array once a frame came with per-pixel
        weights.
        """
        return self._count

    def add(self, frame_linear, saturated=None, weight=1) -> None:
        """Add one linear frame.

        Args:
            frame_linear: ``H x W x C`` linear values (any real dtype; summed in float64).
            saturated: ``H x W x C`` saturated fraction of each value in [0, 1], or ``None``
                for ``[frame_linear >= 1]``.
            weight: how many frames this one stands for: an integer >= 1 (a frame of an
                adaptively interpolated gap, :func:`gpu_blur.reference.interpolate.gap_weights`;
                1 adds it as every other frame, operation for operation), or per pixel an
                ``H x W`` array of integers >= 0 (regions of a gap with their own factors;
                0 leaves a pixel's sums as they are: ``+0.0`` is added).

        Raises:
            ValueError: if the frame's shape is not the accumulator's, it is not finite, or a
                weight is not an allowed integer.
        """
        frame = np.asarray(frame_linear, dtype=np.float64)
        if frame.shape != self.shape:
            raise ValueError(
                f"frame shape {frame.shape} does not match the accumulator's shape {self.shape}"
            )
        if not np.isfinite(frame).all():
            raise ValueError("frame must be finite (no NaN or inf)")
        indicator = (frame >= SATURATION_LEVEL if saturated is None
                     else np.asarray(saturated, dtype=np.float64))
        if np.ndim(weight):
            weight = np.asarray(weight)
            if (weight.shape != self.shape[:2] or weight.dtype.kind not in "iu"
                    or weight.min() < 0):
                raise ValueError(f"per-pixel frame weights must be a {self.shape[:2]} array "
                                 f"of integers >= 0; got {weight.dtype} {weight.shape}")
            weight = weight[:, :, None]
            frame, indicator = frame * weight, indicator * weight
        elif weight < 1 or weight != int(weight):
            raise ValueError(f"frame weight must be an integer >= 1; got {weight!r}")
        elif weight != 1:
            frame, indicator = frame * weight, indicator * weight
        self._sum += frame
        self._saturated += indicator
        self._count = self._count + (weight if np.ndim(weight) else int(weight))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(blurred, saturation_mask)``, both ``H x W x C`` float64.

        ``blurred`` is the mean of the frames; ``saturation_mask`` is, per pixel and channel,
        the mean of the frames' saturated fractions: the fraction of frames at or above
        :data:`SATURATION_LEVEL` (multiples of ``1 / n``) when every frame was tested by its
        value.

        Raises:
            ValueError: if no frame was added.
        """
        if np.any(np.asarray(self._count) == 0):
            raise ValueError("cannot average zero frames")
        return self._sum / self._count, self._saturated / self._count


def average_frames(frames: Iterable) -> tuple[np.ndarray, np.ndarray]:
    """Average linear frames: RSBlur's offline averaging step (issue #6).

    Args:
        frames: an iterable of ``H x W x C`` linear frames of one shape (consumed once, never
            held all at once).

    Returns:
        ``(blurred, saturation_mask)``, see :meth:`FrameAccumulator.result`.

    Raises:
        ValueError: for zero frames, frames that are not ``H x W x C``, or differing shapes.
    """
    acc: FrameAccumulator | None = None
    for frame in frames:
        frame = np.asarray(frame, dtype=np.float64)
        if acc is None:
            if frame.ndim != 3:
                raise ValueError(f"frames must be H x W x C; got {frame.shape}")
            acc = FrameAccumulator(*frame.shape)
        acc.add(frame)
    if acc is None:
        raise ValueError("cannot average zero frames")
    return acc.result()

