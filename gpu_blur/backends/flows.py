"""The optical flows of interpolated averaging, computed once per sample on the host.

With ``blur.interpolation > 1`` the accumulate pass warps frames along the sequence's optical
flows (gpu_blur.reference.interpolate). The flows come from OpenCV on the host, once per
sample: the scheduler adds them to the sample's parameters before the first tile
(:func:`with_flows`), so every tile, every backend and the spot checks use the same flows, and
the blur halo (gpu_blur.reference.blur.blur_halo) covers them. A backend called without them
(a direct ``accumulate`` call) computes them itself from the whole frames.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur.imageio import unit_values
from gpu_blur.plan import Plan
from gpu_blur.reference.interpolate import sequence_flows
from gpu_blur.timings import timer


def interpolation_factor(plan: Plan) -> int:
    """The frame-rate factor of the plan's averaging: 1 for the frames as they are."""
    stage = plan["blur"]
    if not stage.kept or stage.variant != "average":
        return 1
    return int(stage.options.get("interpolation", 1))


class UnitFrames:
    """Frames as stored, read one at a time as float64 sRGB values in [0, 1].

    ``frames[i]`` is :func:`gpu_blur.imageio.unit_values` of the stored frame, made when asked
    and not kept (the reference then holds two frames at a time, not the sequence).
    """

    def __init__(self, frames: Sequence[np.ndarray]):
        self._frames = frames

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index: int) -> np.ndarray:
        return unit_values(self._frames[index])


def with_flows(plan: Plan, params: dict, frames: Sequence[np.ndarray]) -> dict:
    """``params`` with ``"flows"``, the sequence's optical flows, when the plan interpolates.

    Args:
        plan: the sample's plan (``blur`` options ``interpolation`` and ``flow``).
        params: its drawn parameters; returned as they are without interpolation or when they
            hold ``flows`` already.
        frames: the full-size input frames as stored (uint8/uint16 codes or float64 in [0, 1]).

    Returns:
        A new dict (the caller's is not changed: flows are no drawn value and stay out of the
        manifest) with ``flows`` of shape ``(n - 1) x 2 x H x W x 2`` float32
        (:func:`gpu_blur.reference.interpolate.sequence_flows`), computed here, timed as
        ``kernels`` (the accumulate pass's host part).
    """
    if interpolation_factor(plan) == 1 or params.get("flows") is not None:
        return params
    with timer("kernels"):
        flows = sequence_flows(UnitFrames(frames), plan["blur"].options["flow"])
    return {**params, "flows": flows}
