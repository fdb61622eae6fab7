"""Frame interpolation before averaging: more frames per exposure from optical flow.

RSBlur raises the frame rate of its sharp sequences before averaging them: the supplementary
material (section 6) increases it 8 times with a frame interpolation network (ABME, Park et
al., ICCV 2021), and the authors' issue #4 describes ABME applied three times to 9 frames,
giving 65 (pipeline notes, section 2A). This module replaces the network by classical optical
flow, computed on the host with OpenCV, and a warp-and-blend of the two neighbouring frames:

1. **Flow.** For each consecutive pair ``(i, i + 1)``: the forward flow ``F_fw`` (frame i to
   i + 1) and the backward flow ``F_bw`` (i + 1 to i), from OpenCV's DIS (Kroeger et al.,
   "Fast Optical Flow using Dense Inverse Search", ECCV 2016; preset MEDIUM) or Farneback
   ("Two-Frame Motion Estimation Based on Polynomial Expansion", SCIA 2003), on 8-bit grayscale
   of the sRGB frames. A flow ``F`` from frame a to frame b is ``H x W x 2`` float32 ``(dx, dy)``
   in pixels with ``a(x) ~ b(x + F(x))``, OpenCV's convention.
2. **Intermediate frame** at time ``t`` in (0, 1) between frames i and i + 1: both frames are
   warped backwards along the scaled flows, flows taken at the intermediate pixel itself
   (exact for a uniform motion; Jiang et al., "Super SloMo", CVPR 2018, section 3.1, make the
   same approximation)::

       a = frame_i    (x + t F_bw(x))          b = frame_i+1  (x + (1 - t) F_fw(x))
       I_t(x) = (1 - t) a + t b

   with bilinear sampling and reflect-101 outside the image, as
   :func:`gpu_blur.reference.shake.warp_homography`.
3. **Occlusions**: a sample is trusted when the flow that carried it is confirmed by the flow
   in the other direction. The forward-backward test of Sundaram, Brox and Keutzer ("Dense
   Point Trajectories by GPU-accelerated Large Displacement Optical Flow", ECCV 2010, section
   4.1; also Meister et al., "UnFlow", AAAI 2018) accepts a flow ``w`` at ``x`` against the
   reverse flow ``w'`` when::

       |w(x) + w'(x + w(x))|^2 <= 0.01 (|w(x)|^2 + |w'(x + w(x))|^2) + 0.5 px^2

   (``w'`` sampled bilinearly, reflect-101). ``a`` came along ``F_bw``, so it is trusted when
   ``F_bw`` passes against ``F_fw``; ``b`` when ``F_fw`` passes against ``F_bw``. Where exactly
   one of the two is trusted, ``I_t(x)`` is that sample alone; where both or neither are, the
   blend above. This is Super SloMo's visibility-weighted blend (their Eq. 2,
   ``((1 - t) V_0 a + t V_1 b) / ((1 - t) V_0 + t V_1)``) with binary visibilities from the
   test instead of learned ones, and equal visibilities when neither is trusted.
4. **Which values are warped**: the sRGB frames, as stored. RSBlur interpolates its sRGB
   frames with ABME and linearises the network's sRGB output before averaging (issue #6), so
   an intermediate frame's values are linearised like an original frame's.
   **Saturation** of an intermediate frame is not tested on its blended value: it is the same
   warp and blend applied to the frames' saturation indicators ``[frame >= 1]`` (per channel,
   sRGB 1 being linear 1), so an intermediate value counts as saturated in proportion to the
   weights of its saturated neighbours. This is how trajectory blur makes its mask
   (:func:`gpu_blur.reference.shake.shake_blur` warps the indicator) and it is continuous in
   the sample position: a value a hair under 1 (``1 - 1e-8``, a saturated region sampled a
   millionth of a pixel into an unsaturated neighbour) would count 0 in float64 and 1 once
   rounded to float32, so a test on the blended value makes backends of different precisions
   disagree by whole frames. The mask is "the mean of the frames' saturated fractions": 0 or 1
   for an original frame, a blend of its neighbours' 0s and 1s for an intermediate.
5. **Average** with factor ``f`` over ``n`` frames: the ``n`` originals and ``f - 1``
   intermediates (``t = k / f``, ``k = 1 .. f - 1``) between each consecutive pair,
   ``(n - 1) f + 1`` frames in all (9 frames at ``f = 8``: RSBlur's 65), added in time order
   to :class:`gpu_blur.reference.average.FrameAccumulator`. With ``f = 1`` this is plain averaging,
   operation for operation.

6. **Adaptive factor** (``blur.interpolation = "auto"``, tolerance ``tol`` px): per gap, the
   motion ``m`` is the 99th percentile of the flow magnitude from frame i to i + 1, measured on
   grayscale frames shrunk by :data:`MOTION_SCALE` (area average) and scaled back
   (:func:`gap_motion`); the gap's factor is the smallest of :data:`INTERPOLATION_FACTORS`
   with ``m / f <= tol``, 8 at most (:func:`gap_factor`). A gap with factor 1 gets no frames
   and no flows. **Weights** (:func:`gap_weights`): with ``M`` the largest factor of the
   sample, each frame of a gap with factor ``f`` (the original frame starting it and its
   ``f - 1`` intermediates) stands for ``M / f`` frames (an exact power of two), so every gap
   covers the same time, ``M``, as at the fixed factor ``M``; the last frame counts 1. The
   mean divides by ``(n - 1) M + 1``. With one factor ``f`` in every gap, every weight is 1 and
   the average is the fixed factor ``f``'s, operation for operation.
7. **Regions** (``blur.interpolation_region = s`` px, 0 for none): the frame is cut into
   ``s x s`` squares on a grid fixed to the image (so tiles do not move it), and each square
   gets its own factor per gap from the same measure over its part of the shrunk flow
   (:func:`region_motion`), raised to the largest of its eight neighbours' (content moving
   in from a neighbour is sampled at the neighbour's rate); the gap's factor is its squares'
   largest. A pixel of a square with
   factor ``f`` in a gap of factor ``F`` joins the intermediates at ``t = k / F`` whose ``k f``
   is a multiple of ``F`` (its own times ``j / f``), each with the weight ``M / f``, as does
   its original frame: per pixel, exactly the average of step 6 with the square's factors
   (the others are not added: :class:`FrameAccumulator` adds ``+0.0``). A still part of a
   moving sequence then inserts no frames; a uniform pan gets one factor everywhere and the
   operations of step 6.

Limits: flows taken at the intermediate pixel are right for uniform motion and blur the edges
of a moving object against a differently moving background (the occlusion rule keeps one
frame's sample there); motion larger than the flow method can track gives ghosts, as it
would with a plain average. OpenCV's flows are deterministic for one OpenCV build; another
OpenCV version may move them slightly.

The flows and the motion measure (steps 1, 6 and 7: :func:`optical_flow`,
:func:`sequence_flows`, :func:`gap_motion`, :func:`region_motion`, :func:`gap_factor`,
:class:`RegionFactors`, :data:`MOTION_SCALE`, :data:`INTERPOLATION_FACTORS`) are
:mod:`gpu_blur.reference.flow`'s; this module warps, blends and averages.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gpu_blur.reference.average import SATURATION_LEVEL, FrameAccumulator
from gpu_blur.reference.flow import (
    INTERPOLATION_FACTORS,
    RegionFactors,
    _check_frame,
    sequence_flows,
)
from gpu_blur.reference.sampling import bilinear_sample
from gpu_blur.reference.transfer import srgb_to_linear

__all__ = [
    "flow_consistent",
    "gap_weights",
    "interpolate_frame",
    "interpolated_average",
    "interpolation_halo",
    "interpolation_times",
]

#: Forward-backward consistency test (Sundaram et al., ECCV 2010, section 4.1): relative part
#: of the squared bound, times ``|w|^2 + |w'|^2``.
CONSISTENCY_RELATIVE = 0.01
#: Absolute part of the squared bound, px^2 (same source).
CONSISTENCY_ABSOLUTE_PX2 = 0.5


def _check_flow(flow, shape: tuple[int, int], name: str) -> np.ndarray:
    """``flow`` as a float64 ``H x W x 2`` array of finite values for frames of ``shape``."""
    arr = np.asarray(flow, dtype=np.float64)
    if arr.shape != (*shape, 2):
        raise ValueError(f"{name} must be H x W x 2 = {(*shape, 2)} for these frames; "
                         f"got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return arr


def gap_weights(factors: Sequence[int]) -> tuple[tuple[int, ...], int]:
    """The weight of each gap's frames and the total (module step 6).

    Args:
        factors: each gap's factor (:data:`INTERPOLATION_FACTORS`).

    Returns:
        ``(weights, total)``: ``weights[i] = M / factors[i]`` with ``M`` the largest factor
        (1 without gaps), the weight of gap i's original frame and of each of its
        intermediates; ``total = len(factors) M + 1``, the last frame weighing 1. All weights
        are 1 when every gap has one factor.
    """
    for f in factors:
        if f not in INTERPOLATION_FACTORS:
            raise ValueError(f"interpolation factor must be one of {INTERPOLATION_FACTORS}; "
                             f"got {f!r}")
    most = max(factors, default=1)
    return tuple(most // f for f in factors), len(factors) * most + 1


def _sample(image: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``H x W x C`` ``image`` at ``H x W`` positions, reflect-101."""
    h, w, c = image.shape
    return bilinear_sample(image.reshape(h * w, c), h, w, px, py)


def _grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates ``(x, y)``, each ``H x W`` float64."""
    ys, xs = np.meshgrid(np.arange(height, dtype=np.float64),
                         np.arange(width, dtype=np.float64), indexing="ij")
    return xs, ys


def flow_consistent(flow, reverse) -> np.ndarray:
    """Where a flow is confirmed by the reverse flow (forward-backward test, module step 3).

    Args:
        flow: ``H x W x 2`` flow ``w`` from frame a to frame b (pixels).
        reverse: ``H x W x 2`` flow ``w'`` from frame b to frame a.

    Returns:
        ``H x W`` bool: ``|w + w''|^2 <= 0.01 (|w|^2 + |w''|^2) + 0.5`` with ``w''`` the reverse
        flow sampled bilinearly (reflect-101) at ``x + w(x)``.
    """
    f = np.asarray(flow, dtype=np.float64)
    if f.ndim != 3 or f.shape[2] != 2:
        raise ValueError(f"flow must be H x W x 2; got shape {f.shape}")
    f = _check_flow(f, f.shape[:2], "flow")
    r = _check_flow(reverse, f.shape[:2], "reverse")
    xs, ys = _grid(*f.shape[:2])
    back = _sample(r, xs + f[:, :, 0], ys + f[:, :, 1])
    ex = f[:, :, 0] + back[:, :, 0]
    ey = f[:, :, 1] + back[:, :, 1]
    norms = ((f[:, :, 0] * f[:, :, 0] + f[:, :, 1] * f[:, :, 1])
             + (back[:, :, 0] * back[:, :, 0] + back[:, :, 1] * back[:, :, 1]))
    return ex * ex + ey * ey <= CONSISTENCY_RELATIVE * norms + CONSISTENCY_ABSOLUTE_PX2


def _trust(fw: np.ndarray, bw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Module step 3's decisions for one gap, ``H x W x 1`` bool each.

    frame0's sample (carried by ``F_bw``) and frame1's (by ``F_fw``). They do not depend on
    ``t``: one test serves every time of the gap.
    """
    return flow_consistent(bw, fw)[:, :, None], flow_consistent(fw, bw)[:, :, None]


def _interpolate(f0: np.ndarray, f1: np.ndarray, fw: np.ndarray, bw: np.ndarray, t: float,
                 trust: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Module steps 2 and 3 on checked float64 images: the blend of the two warped samples.

    ``f0`` and ``f1`` may carry any channels (values, indicators); each is sampled at the same
    positions and blended with the same trust decisions (:func:`_trust`).
    """
    h, w = f0.shape[:2]
    xs, ys = _grid(h, w)
    a = _sample(f0, xs + t * bw[:, :, 0], ys + t * bw[:, :, 1])
    b = _sample(f1, xs + (1.0 - t) * fw[:, :, 0], ys + (1.0 - t) * fw[:, :, 1])
    trust_a, trust_b = trust
    blend = (1.0 - t) * a + t * b
    return np.where(trust_a == trust_b, blend, np.where(trust_a, a, b))


def _frame_with_saturation(f0: np.ndarray, f1: np.ndarray, fw: np.ndarray, bw: np.ndarray,
                           t: float, trust) -> tuple[np.ndarray, np.ndarray]:
    """Values and saturated fractions of the frame at ``t`` (checked float64 inputs).

    Values and indicators ``[frame >= 1]`` go side by side through one sampling and one set of
    trust decisions (module step 4).
    """
    c = f0.shape[2]
    both = _interpolate(np.concatenate([f0, f0 >= SATURATION_LEVEL], axis=2),
                        np.concatenate([f1, f1 >= SATURATION_LEVEL], axis=2), fw, bw, t, trust)
    return both[:, :, :c], both[:, :, c:]


def interpolate_frame(frame0, frame1, flow_fw, flow_bw, t: float,
                      saturation: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The frame at time ``t`` between two sRGB frames (module steps 2 and 3).

    Args:
        frame0: ``H x W x C`` sRGB frame at time 0, values in [0, 1].
        frame1: ``H x W x C`` sRGB frame at time 1.
        flow_fw: ``H x W x 2`` flow from frame0 to frame1 (pixels, OpenCV convention).
        flow_bw: ``H x W x 2`` flow from frame1 to frame0.
        t: time in the open interval (0, 1).
        saturation: also return the frame's saturated fractions (module step 4).

    Returns:
        ``H x W x C`` float64 sRGB values: ``(1 - t) a + t b`` with ``a = frame0(x + t F_bw)``
        and ``b = frame1(x + (1 - t) F_fw)``, or the one trusted sample where only one is.
        With ``saturation``, ``(values, saturated)``: ``saturated`` is ``H x W x C`` in
        [0, 1], the same blend of the frames' indicators ``[frame >= 1]``.

    Raises:
        ValueError: for frames or flows of wrong shapes, non-finite values, or ``t`` outside
            (0, 1).
    """
    f0 = _check_frame(frame0, "frame0")
    f1 = _check_frame(frame1, "frame1")
    if f0.shape != f1.shape:
        raise ValueError(f"frame0 and frame1 must have one shape; got {f0.shape} and {f1.shape}")
    if not 0.0 < t < 1.0:
        raise ValueError(f"t must lie in the open interval (0, 1); got {t!r}")
    h, w = f0.shape[:2]
    fw = _check_flow(flow_fw, (h, w), "flow_fw")
    bw = _check_flow(flow_bw, (h, w), "flow_bw")
    if saturation:
        return _frame_with_saturation(f0, f1, fw, bw, t, _trust(fw, bw))
    return _interpolate(f0, f1, fw, bw, t, _trust(fw, bw))


def interpolation_times(factor: int) -> tuple[float, ...]:
    """Times ``k / factor``, ``k = 1 .. factor - 1``, of the frames inserted in each gap."""
    if factor not in INTERPOLATION_FACTORS:
        raise ValueError(f"interpolation factor must be one of {INTERPOLATION_FACTORS}; "
                         f"got {factor!r}")
    return tuple(k / factor for k in range(1, factor))


def interpolated_average(frames: Sequence, factor: int | Sequence[int] | RegionFactors,
                         flows=None, method: str = "dis") -> tuple[np.ndarray, np.ndarray]:
    """Average a sequence at ``factor`` times its frame rate (module steps 5 to 7).

    Args:
        frames: ``n >= 1`` sRGB frames ``H x W x C`` in [0, 1], one shape; read by index, two
            at a time.
        factor: 1, 2, 4 or 8 (1 is plain averaging), or one such factor per gap
            (``n - 1`` of them: adaptive interpolation, weighted by :func:`gap_weights`), or
            each gap's factors per region (:class:`RegionFactors`, step 7).
        flows: ``(n - 1) x 2 x H x W x 2`` from :func:`sequence_flows`, or ``None`` to compute
            them with ``method`` (unused when every factor is 1).
        method: flow method when ``flows`` is ``None``.

    Returns:
        ``(blurred, saturation_mask)``, both ``H x W x C`` float64 linear, over the
        ``(n - 1) factor + 1`` frames (see :class:`~gpu_blur.reference.average.FrameAccumulator`).
    """
    if len(frames) < 1:
        raise ValueError("cannot average zero frames")
    if isinstance(factor, RegionFactors):
        regions = factor
    elif isinstance(factor, (int, np.integer)):
        regions = RegionFactors.uniform((factor,) * (len(frames) - 1))
    else:
        regions = RegionFactors.uniform(tuple(factor))
    factors = regions.gaps
    if len(factors) != len(frames) - 1:
        raise ValueError(f"{len(factors)} interpolation factors for {len(frames) - 1} gaps; "
                         "give one per gap")
    weights, _ = gap_weights(factors)
    most = max(factors, default=1)
    current = _check_frame(frames[0], "frame 0")
    h, w = current.shape[:2]
    interpolating = any(f > 1 for f in factors)
    if interpolating and flows is None:
        flows = sequence_flows(frames, method, factors)
    if interpolating:
        expected = (len(frames) - 1, 2, h, w, 2)
        if np.shape(flows) != expected:
            raise ValueError(f"flows must be (n - 1) x 2 x H x W x 2 = {expected}; got "
                             f"{np.shape(flows)}")

    def weight(gap: int, step: int = 0):
        """The weight of gap ``gap``'s frame at ``step / factors[gap]``: an int, or per pixel."""
        if not regions.side:
            return weights[gap]
        own = regions.of_pixels(gap, h, w)  # a pixel's own factor f joins where k f / F is whole
        return np.where(step * own % factors[gap] == 0, most // own, 0)

    acc = FrameAccumulator(*current.shape)
    acc.add(srgb_to_linear(current), weight=weight(0) if factors else 1)
    for i in range(1, len(frames)):
        previous, current = current, _check_frame(frames[i], f"frame {i}")
        times = interpolation_times(factors[i - 1])
        if times:  # the gap's trust decisions serve all its times
            fw = _check_flow(flows[i - 1, 0], current.shape[:2], "flow_fw")
            bw = _check_flow(flows[i - 1, 1], current.shape[:2], "flow_bw")
            trust = _trust(fw, bw)
        for step, t in enumerate(times, start=1):
            values, saturated = _frame_with_saturation(previous, current, fw, bw, t, trust)
            acc.add(srgb_to_linear(values), saturated, weight(i - 1, step))
        acc.add(srgb_to_linear(current), weight=weight(i) if i < len(factors) else 1)
    return acc.result()


def interpolation_halo(flows) -> int:
    """Pixels the interpolation reads beyond a tile on each side, for these flows.

    A pixel reads the frames within ``t |F|`` or ``(1 - t) |F|`` of itself and the reverse flow
    at ``x + F(x)``, each with its bilinear neighbour: ``ceil(max |F component|) + 1`` covers
    all of them. As for the other blurs, the halo comes from the full image's mirrored
    extension, so a tile with it gives the whole image's values.

    Args:
        flows: flows of any shape ending in 2 (e.g. from :func:`sequence_flows`); none gives 0.

    Returns:
        The halo in pixels, an int (0 for no flows).
    """
    f = np.asarray(flows)
    if f.size == 0:
        return 0
    if f.dtype.kind != "f":
        f = f.astype(np.float64)
    # in the flows' own type: a largest and a smallest value are exact in any float type, and
    # a NaN or inf shows in them (a sample's flows: 74 MB of float32 at 960 x 600, 8 gaps)
    top, bottom = float(f.max()), float(f.min())
    if not (math.isfinite(top) and math.isfinite(bottom)):
        raise ValueError("flows must be finite (no NaN or inf)")
    return math.ceil(max(top, -bottom)) + 1
