"""Optical flow for frame interpolation, and the motion measure that picks each gap's factor.

The host side of :mod:`gpu_blur.reference.interpolate`: OpenCV's flows (DIS or Farneback) on
8-bit grayscale of the sRGB frames (its step 1: :func:`optical_flow`, :func:`sequence_flows`),
and, for ``blur.interpolation = "auto"``, each gap's motion measured on shrunk frames and the
factor it needs, for the whole frame or per square region (its steps 6 and 7:
:func:`gap_motion`, :func:`region_motion`, :func:`gap_factor`, :func:`adaptive_factors`,
:func:`region_factors`, :class:`RegionFactors`). "Module step N" below names a step of
:mod:`gpu_blur.reference.interpolate`'s docstring, which also gives the sources.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from gpu_blur.reference import fixedmath

__all__ = [
    "FLOW_METHODS",
    "FLOW_MIN_SIDE",
    "INTERPOLATION_AUTO",
    "INTERPOLATION_FACTORS",
    "MOTION_SCALE",
    "REGION_STEP",
    "RegionFactors",
    "adaptive_factors",
    "check_flow_size",
    "gap_factor",
    "gap_motion",
    "gray8",
    "optical_flow",
    "region_factors",
    "region_motion",
    "sequence_flows",
]

#: Frame-rate factors offered: powers of two, so every time ``k / f`` is exact in binary.
INTERPOLATION_FACTORS = (1, 2, 4, 8)
#: ``blur.interpolation`` value that picks a factor per gap from the measured motion (step 6).
INTERPOLATION_AUTO = "auto"
#: Adaptive factor: the frames' motion is measured at 1 / MOTION_SCALE of their size (fewer
#: times where a side would drop under MOTION_MIN_SIDE), at about 1 / 16 of a full flow's cost.
MOTION_SCALE = 4
#: Smallest side, pixels, of the shrunk frames the motion is measured on.
MOTION_MIN_SIDE = 32
#: Percentile of the flow magnitude taken as a gap's motion: the fast part of the frame, not
#: a handful of wrong vectors.
MOTION_PERCENTILE = 99.0
#: ``blur.interpolation_region`` is a multiple of this many pixels: a region is then whole
#: pixels of the motion measure's shrunk frames at every shrink factor (step 7).
REGION_STEP = 16
#: Optical-flow methods: OpenCV's DIS (preset MEDIUM) or Farneback.
FLOW_METHODS = ("dis", "farneback")

#: Farneback parameters of OpenCV's optical-flow tutorial and ``samples/python/opt_flow.py``:
#: pyramid scale, levels, window size, iterations, polynomial neighbourhood and its sigma.
FARNEBACK_PARAMETERS = {"pyr_scale": 0.5, "levels": 3, "winsize": 15, "iterations": 3,
                        "poly_n": 5, "poly_sigma": 1.2}
#: Smallest frame side, pixels, each flow method is given. DIS matches 8 x 8 patches over an
#: image pyramid whose depth OpenCV picks from the frame size (modules/video/src/dis_flow.cpp):
#: a side under 8, or both under 12, raises cv2.error, and a side of 8 to 15 with the other
#: side 40 or more crashes the process (OpenCV 5.0.0: the depth it then picks from the width
#: alone leaves fewer rows than a patch). Both sides from 16 up ran on every size tried, up
#: to 8000. Farneback runs on any size, 1 x 1 included.
FLOW_MIN_SIDE = {"dis": 16, "farneback": 1}


def _check_frame(frame, name: str) -> np.ndarray:
    """``frame`` as a float64 ``H x W x C`` array of finite values."""
    arr = np.asarray(frame, dtype=np.float64)
    if arr.ndim != 3 or min(arr.shape) < 1:
        raise ValueError(f"{name} must be H x W x C with H, W, C >= 1; got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return arr


def gray8(frame: np.ndarray) -> np.ndarray:
    """8-bit grayscale of an sRGB frame, the image the flows and the motion measure see.

    Values in [0, 1] are rounded to 8-bit codes (uint8 codes are taken as they are: the same
    codes), then OpenCV's BT.601 weights combine RGB; a one-channel frame is its codes.
    """
    import cv2

    frame = np.asarray(frame)
    codes = (frame if frame.dtype == np.uint8
             else np.rint(np.clip(frame, 0.0, 1.0) * 255.0).astype(np.uint8))
    if codes.shape[2] == 1:
        return np.ascontiguousarray(codes[:, :, 0])
    return cv2.cvtColor(np.ascontiguousarray(codes[:, :, :3]), cv2.COLOR_RGB2GRAY)


class _Grays:
    """The :func:`gray8` of each frame of a sequence, made once.

    ``frames`` may offer ``gray8(i)`` (:class:`gpu_blur.backends.flows.UnitFrames`: straight
    from the stored codes); otherwise each frame is checked and converted. Grays are checked
    for one shape and for the flow method's smallest size.
    """

    def __init__(self, frames: Sequence, method: str):
        self._frames, self._method, self._kept = frames, method, {}

    def __getitem__(self, index: int) -> np.ndarray:
        if index not in self._kept:
            made = getattr(self._frames, "gray8", None)
            gray = (made(index) if made is not None
                    else gray8(_check_frame(self._frames[index], f"frame {index}")))
            for other in self._kept.values():
                if other.shape != gray.shape:
                    raise ValueError(f"frames must have one shape; frame {index} is "
                                     f"{gray.shape[0]} x {gray.shape[1]}, the one before "
                                     f"{other.shape[0]} x {other.shape[1]}")
            check_flow_size(gray.shape, self._method)
            self._kept = {k: v for k, v in self._kept.items() if abs(k - index) == 1}
            self._kept[index] = gray
        return self._kept[index]


def _flow_gray(g0: np.ndarray, g1: np.ndarray, method: str) -> np.ndarray:
    """OpenCV's flow between two 8-bit grayscale images (see :func:`optical_flow`)."""
    import cv2

    if method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        return dis.calc(g0, g1, None)
    return cv2.calcOpticalFlowFarneback(g0, g1, None, flags=0, **FARNEBACK_PARAMETERS)


def optical_flow(frame_from, frame_to, method: str = "dis") -> np.ndarray:
    """Dense optical flow from one sRGB frame to the next, with OpenCV on the host.

    Args:
        frame_from: ``H x W x C`` sRGB values in [0, 1] (RGB, or one channel).
        frame_to: the frame the flow points into, same shape.
        method: ``"dis"`` (DIS, preset MEDIUM) or ``"farneback"`` (:data:`FARNEBACK_PARAMETERS`).

    Returns:
        ``H x W x 2`` float32 ``(dx, dy)`` in pixels: ``frame_from(x) ~ frame_to(x + F(x))``.

    Raises:
        ValueError: for an unknown method, frames of different shapes, frames too small for
            the method (:func:`check_flow_size`) or non-finite values.
    """
    if method not in FLOW_METHODS:
        raise ValueError(f"flow method {method!r} is unknown; use one of {FLOW_METHODS}")
    a, b = _frame_pair(frame_from, frame_to, ("frame_from", "frame_to"), "for optical flow",
                       method)
    return _flow(gray8(a), gray8(b), method)


def _flow(g0: np.ndarray, g1: np.ndarray, method: str) -> np.ndarray:
    """:func:`optical_flow` of two frames' grays, as contiguous float32."""
    return np.ascontiguousarray(_flow_gray(g0, g1, method), dtype=np.float32)


def _frame_pair(frame0, frame1, names: tuple[str, str], purpose: str, method: str):
    """Two frames checked (:func:`_check_frame`), of one shape and large enough for ``method``."""
    a = _check_frame(frame0, names[0])
    b = _check_frame(frame1, names[1])
    if a.shape != b.shape:
        raise ValueError(f"frames must have one shape {purpose}; got {a.shape} and {b.shape}")
    check_flow_size(a.shape[:2], method)
    return a, b


def gap_motion(frame0, frame1, method: str = "dis") -> float:
    """How far a gap's frames move, pixels: module step 6's cheap measure.

    Args:
        frame0: ``H x W x C`` sRGB frame in [0, 1].
        frame1: the next frame, same shape.
        method: the flow method (:data:`FLOW_METHODS`).

    Returns:
        The :data:`MOTION_PERCENTILE` th percentile of ``|F|`` from frame0 to frame1, with
        ``F`` measured on the frames' grayscale shrunk by up to :data:`MOTION_SCALE` (OpenCV's
        area average) and multiplied back by the shrink factor. 0 for identical frames.
    """
    return float(region_motion(frame0, frame1, 0, method)[0, 0])


def region_motion(frame0, frame1, side: int, method: str = "dis") -> np.ndarray:
    """:func:`gap_motion` of each ``side x side`` region of the frames (module step 7).

    Args:
        frame0: ``H x W x C`` sRGB frame in [0, 1].
        frame1: the next frame, same shape.
        side: region side, pixels, a multiple of :data:`REGION_STEP`; 0 for the whole frame.
        method: the flow method (:data:`FLOW_METHODS`).

    Returns:
        ``ceil(H / side) x ceil(W / side)`` float64 (``1 x 1`` for side 0), pixels: the
        percentile over the shrunk flow's pixels lying in each region; a region past the
        shrunk frame's last whole pixel (a sliver under the shrink factor wide) takes its
        neighbour's. All 0 for identical frames.
    """
    a, b = _frame_pair(frame0, frame1, ("frame0", "frame1"), "to measure motion", method)
    return _region_motion(gray8(a), gray8(b), side, method)


def _region_motion(g0: np.ndarray, g1: np.ndarray, side: int, method: str) -> np.ndarray:
    """:func:`region_motion` of two frames' grays."""
    import cv2

    if side < 0 or side % REGION_STEP:
        raise ValueError(f"region side must be 0 or a multiple of {REGION_STEP} px; "
                         f"got {side!r}")
    h, w = g0.shape
    shape = (-(-h // side), -(-w // side)) if side else (1, 1)
    if np.array_equal(g0, g1):
        return np.zeros(shape)
    scale = MOTION_SCALE
    while scale > 1 and min(h, w) // scale < max(MOTION_MIN_SIDE, FLOW_MIN_SIDE[method]):
        scale //= 2
    if scale > 1:
        size = (w // scale, h // scale)
        g0 = cv2.resize(g0, size, interpolation=cv2.INTER_AREA)
        g1 = cv2.resize(g1, size, interpolation=cv2.INTER_AREA)
    flow = _flow_gray(g0, g1, method).astype(np.float64)
    magnitude = fixedmath.hypot(flow[:, :, 0], flow[:, :, 1])
    step = side // scale if side else max(magnitude.shape)
    motion = _block_percentiles(magnitude, step, MOTION_PERCENTILE) * scale
    # regions past the shrunk frame (its size rounded down) take their neighbour's
    return np.pad(motion, [(0, n - m) for n, m in zip(shape, motion.shape, strict=True)],
                  mode="edge")


def _block_percentiles(values: np.ndarray, step: int, percentile: float) -> np.ndarray:
    """The percentile of each ``step x step`` block of a 2-D array (the last ones partial)."""
    h, w = values.shape
    out = np.empty((-(-h // step), -(-w // step)))
    full_h, full_w = h // step * step, w // step * step
    rows = [(0, full_h, step)] + ([(full_h, h, h - full_h)] if h > full_h else [])
    cols = [(0, full_w, step)] + ([(full_w, w, w - full_w)] if w > full_w else [])
    for r0, r1, rh in rows:
        for c0, c1, cw in cols:
            if r1 == r0 or c1 == c0:
                continue
            nr, nc = (r1 - r0) // rh, (c1 - c0) // cw
            blocks = values[r0:r1, c0:c1].reshape(nr, rh, nc, cw).swapaxes(1, 2)
            out[r0 // step:r0 // step + nr, c0 // step:c0 // step + nc] = np.percentile(
                blocks.reshape(nr, nc, rh * cw), percentile, axis=-1)
    return out


def gap_factor(motion_px: float, tolerance_px: float) -> int:
    """The fewest frames a gap needs: module step 6's factor for its motion.

    The smallest of :data:`INTERPOLATION_FACTORS` whose step ``motion_px / f`` is at most
    ``tolerance_px``; the largest when none is.
    """
    if not tolerance_px > 0:
        raise ValueError(f"interpolation tolerance must be > 0 px; got {tolerance_px!r}")
    for factor in INTERPOLATION_FACTORS:
        if motion_px / factor <= tolerance_px:
            return factor
    return INTERPOLATION_FACTORS[-1]


def adaptive_factors(frames: Sequence, tolerance_px: float,
                     method: str = "dis") -> tuple[int, ...]:
    """Each gap's factor for ``blur.interpolation = "auto"`` without regions (module step 6).

    The gap's motion by :func:`gap_motion`, its factor by :func:`gap_factor`.

    Args:
        frames: ``n >= 1`` sRGB frames ``H x W x C`` in [0, 1]; read by index, two at a time.
        tolerance_px: the largest step allowed between consecutive averaged frames, pixels.
        method: the flow method the motion is measured with.

    Returns:
        ``n - 1`` factors, one per gap, in time order.
    """
    return region_factors(frames, tolerance_px, 0, method).gaps


@dataclasses.dataclass(frozen=True)
class RegionFactors:
    """Each gap's factor in each square region of the frame (module step 7).

    Attributes:
        side: the regions' side, pixels, on a grid from the image's top-left corner; 0 for
            one region covering the frame.
        factors: ``(n - 1) x BH x BW`` uint8, one of :data:`INTERPOLATION_FACTORS` per gap and
            region (``BH = ceil(H / side)``, ``BW = ceil(W / side)``; 1 x 1 for side 0).
    """

    side: int
    factors: np.ndarray

    @classmethod
    def uniform(cls, factors: Sequence[int]) -> RegionFactors:
        """One region per gap with the gap's factor: steps 5 and 6 as they are."""
        return cls(0, np.asarray(factors, dtype=np.uint8).reshape(-1, 1, 1))

    @property
    def gaps(self) -> tuple[int, ...]:
        """Each gap's factor: the largest of its regions'."""
        return tuple(int(f) for f in self.factors.max(axis=(1, 2), initial=1))

    def of_pixels(self, gap: int, height: int, width: int) -> np.ndarray:
        """Gap ``gap``'s factor at every pixel of a ``height x width`` frame, int64."""
        f = self.factors[gap].astype(np.int64)
        if not self.side:
            return np.broadcast_to(f[0, 0], (height, width))
        return np.repeat(np.repeat(f, self.side, 0), self.side, 1)[:height, :width]


def region_factors(frames: Sequence, tolerance_px: float, side: int,
                   method: str = "dis") -> RegionFactors:
    """Each gap's factor per region for ``blur.interpolation = "auto"`` (module step 7).

    Each region's motion by :func:`region_motion`, its factor as :func:`gap_factor` picks it.

    Args:
        frames: ``n >= 1`` sRGB frames ``H x W x C`` in [0, 1]; read by index, two at a time.
        tolerance_px: the largest step allowed between consecutive averaged frames, pixels.
        side: region side, pixels (a multiple of :data:`REGION_STEP`), 0 for whole frames.
        method: the flow method the motion is measured with.
    """
    if not tolerance_px > 0:
        raise ValueError(f"interpolation tolerance must be > 0 px; got {tolerance_px!r}")
    maps = []
    grays = _Grays(frames, method)
    pairs = [(grays[i - 1], grays[i]) for i in range(1, len(frames))]
    for motion in _in_threads(lambda p: _region_motion(*p, side, method), pairs):
        factor = np.full(motion.shape, INTERPOLATION_FACTORS[-1], dtype=np.uint8)
        for f in reversed(INTERPOLATION_FACTORS):  # the smallest that keeps the step wins
            factor[motion / f <= tolerance_px] = f
        maps.append(_with_neighbours(factor))
    return RegionFactors(side, np.stack(maps) if maps else np.ones((0, 1, 1), np.uint8))


def _with_neighbours(factors: np.ndarray) -> np.ndarray:
    """Each region's factor raised to the largest of its eight neighbours' (module step 7).

    A pixel's inserted frames sample the frames along its motion, so near a moving neighbour
    they carry that neighbour's content; at its own, lower factor a still region's border
    would show the neighbour's content in steps (measured: 15 codes against 8x at 480 x 320
    beside a moving object, 4 with this rule).
    """
    h, w = factors.shape
    padded = np.pad(factors, 1, mode="edge")
    return np.max([padded[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)], axis=0)


def check_flow_size(shape: tuple[int, int], method: str) -> None:
    """Refuse frames of ``shape`` (H, W) smaller than the flow method takes (:data:`FLOW_MIN_SIDE`).

    Raises:
        ValueError: naming the size, the minimum and the ways out.
    """
    side = FLOW_MIN_SIDE[method]
    if min(shape) < side:
        raise ValueError(
            f"frames of {shape[0]} x {shape[1]} pixels (H x W) are too small for blur.flow = "
            f"{method!r}, which needs at least {side} x {side} (OpenCV's DIS matches 8 x 8 "
            "patches over an image pyramid): use larger frames, blur.flow = 'farneback' or "
            "blur.interpolation = 1")


def sequence_flows(frames: Sequence, method: str = "dis",
                   factors: Sequence[int] | None = None) -> np.ndarray:
    """Forward and backward flow of every consecutive pair of a sequence.

    Args:
        frames: ``n >= 1`` sRGB frames ``H x W x C`` in [0, 1], one shape; read by index, two
            at a time (a lazy sequence never has more than two alive; their 8-bit grays are
            kept, one byte a pixel), or anything offering ``gray8(i)`` besides.
        method: see :func:`optical_flow`.
        factors: each gap's factor (module step 6), or ``None`` for flows in every gap; a gap
            with factor 1 inserts no frame and gets zero flows, not computed.

    Returns:
        ``(n - 1) x 2 x H x W x 2`` float32: ``[i, 0]`` the forward flow from frame i to
        i + 1, ``[i, 1]`` the backward flow from i + 1 to i. The flows are computed in threads
        (:func:`_in_threads`: 16 flows of 960 x 600 on a 16-core host 488 -> 158 ms with 8).
    """
    if len(frames) < 1:
        raise ValueError("sequence_flows needs at least one frame")
    if method not in FLOW_METHODS:
        raise ValueError(f"flow method {method!r} is unknown; use one of {FLOW_METHODS}")
    grays = _Grays(frames, method)  # each frame's gray made once, for both its gaps
    h, w = grays[0].shape
    flows = np.empty((len(frames) - 1, 2, h, w, 2), dtype=np.float32)
    pairs = {}  # (gap, direction) -> (from, to) grays
    for i in range(1, len(frames)):
        if factors is not None and factors[i - 1] == 1:
            flows[i - 1] = 0.0
            continue
        pairs[i - 1, 0] = grays[i - 1], grays[i]
        pairs[i - 1, 1] = grays[i], grays[i - 1]
    for key, flow in zip(pairs, _in_threads(lambda p: _flow(*p, method), pairs.values()),
                         strict=True):
        flows[key] = flow
    return flows


def _in_threads(work, items) -> list:
    """``[work(x) for x in items]`` in up to one thread per core.

    OpenCV's calls release the GIL, and each flow is its own computation: the results do not
    depend on the threads.
    """
    items = list(items)
    if len(items) < 2:
        return [work(x) for x in items]
    with ThreadPoolExecutor(min(len(items), os.cpu_count() or 1)) as pool:
        return list(pool.map(work, items))
