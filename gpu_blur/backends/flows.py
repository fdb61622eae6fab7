"""The optical flows of interpolated averaging, computed once per sample on the host.

With ``blur.interpolation > 1`` the accumulate pass warps frames along the sequence's optical
flows (gpu_blur.reference.flow). The flows come from OpenCV on the host, once per
sample: the scheduler adds them to the sample's parameters before the first tile
(:func:`with_flows`), so every tile, every backend and the spot checks use the same flows, and
the blur halo (gpu_blur.reference.blur.blur_halo) covers them. A backend called without them
(a direct ``accumulate`` call) computes them itself from the whole frames.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur.image_arrays import unit_values
from gpu_blur.planning import Plan
from gpu_blur.reference.flow import (
    INTERPOLATION_AUTO,
    INTERPOLATION_FACTORS,
    RegionFactors,
    gray8,
    region_factors,
    sequence_flows,
)
from gpu_blur.timings import timer

__all__ = ["FACTORS_KEY", "REGIONS_KEY", "UnitFrames", "gap_factors", "gap_regions",
           "interpolation_factor", "scene_factors", "with_factors", "with_flows"]

#: The parameter holding each gap's factor under ``blur.interpolation = "auto"`` (measured per
#: sample, recorded in the manifest).
FACTORS_KEY = "interpolation_factors"
#: The parameter holding each gap's factor per region (``blur.interpolation_region`` > 0): an
#: ``(n - 1) x BH x BW`` uint8 array (:class:`~gpu_blur.reference.flow.RegionFactors`),
#: saved with the sample's arrays.
REGIONS_KEY = "interpolation_regions"


def interpolation_factor(plan: Plan) -> int:
    """The frame-rate factor of the plan's averaging: 1 for the frames as they are.

    Under ``blur.interpolation = "auto"`` the most a gap may get (8): what memory is planned for.
    """
    stage = plan["blur"]
    if not stage.kept or stage.variant != "average":
        return 1
    factor = stage.options.get("interpolation", 1)
    return INTERPOLATION_FACTORS[-1] if factor == INTERPOLATION_AUTO else int(factor)


def scene_factors(scene, frames: Sequence[np.ndarray]) -> RegionFactors | None:
    """Each gap's factors under ``blur.interpolation = "auto"``, else ``None``.

    Measured once per sample from the host frames as stored, per region when
    ``blur.interpolation_region`` > 0 (:func:`gpu_blur.reference.flow.region_factors`,
    timed as ``kernels``).
    """
    b = scene.blur
    if b.mode != "average" or b.interpolation != INTERPOLATION_AUTO:
        return None
    with timer("kernels"):
        return region_factors(UnitFrames(frames), b.interpolation_tolerance,
                              b.interpolation_region, b.flow)


def with_factors(plan: Plan, params: dict, frames: Sequence[np.ndarray],
                 measured: RegionFactors | None = None) -> dict:
    """``params`` with the gaps' factors under interpolation auto.

    ``interpolation_factors`` (each gap's) and, with regions, ``interpolation_regions``:
    ``measured``'s, else without regions the plan's (:func:`gpu_blur.planning.plan`
    ``interpolation_factors``), else measured here from the host frames as
    :func:`scene_factors` does. ``params`` as they are for a fixed factor or when they hold
    the factors already.
    """
    stage = plan["blur"]
    if (interpolation_factor(plan) == 1 or FACTORS_KEY in params
            or stage.options["interpolation"] != INTERPOLATION_AUTO):
        return params
    planned = stage.options.get("factors")
    if measured is None and planned is not None and not stage.options["region"]:
        measured = RegionFactors.uniform(planned)
    if measured is None:
        with timer("kernels"):
            measured = region_factors(UnitFrames(frames), stage.options["tolerance"],
                                      stage.options["region"], stage.options["flow"])
    params = {**params, FACTORS_KEY: list(measured.gaps)}
    if measured.side:
        params[REGIONS_KEY] = measured.factors
    return params


def gap_factors(plan: Plan, params: dict, gaps: int) -> tuple[int, ...]:
    """Each of ``gaps`` gaps' frame-rate factor: the plan's, or the sample's measured ones.

    Raises:
        ValueError: under interpolation auto when ``params`` lack ``interpolation_factors``
            (:func:`with_factors` adds them) or hold a wrong number of them.
    """
    factor = interpolation_factor(plan)
    if factor == 1 or plan["blur"].options["interpolation"] != INTERPOLATION_AUTO:
        return (factor,) * gaps
    if FACTORS_KEY not in params:
        raise ValueError(f"blur.interpolation = auto needs params[{FACTORS_KEY!r}] (each gap's "
                         "factor, measured by gpu_blur.backends.flows.with_factors)")
    factors = tuple(int(f) for f in params[FACTORS_KEY])
    if len(factors) != gaps or any(f not in INTERPOLATION_FACTORS for f in factors):
        raise ValueError(f"params[{FACTORS_KEY!r}] = {list(factors)} must hold {gaps} factors "
                         f"(one per gap), each one of {INTERPOLATION_FACTORS}")
    return factors


def gap_regions(plan: Plan, params: dict, gaps: int) -> RegionFactors:
    """Each of ``gaps`` gaps' factors per region (one region per gap without regions).

    Raises:
        ValueError: as :func:`gap_factors`, or when ``interpolation_regions`` is missing under
            ``blur.interpolation_region`` > 0 or disagrees with ``interpolation_factors``.
    """
    factors = gap_factors(plan, params, gaps)
    options = plan["blur"].options
    if options.get("interpolation") != INTERPOLATION_AUTO or not options.get("region"):
        return RegionFactors.uniform(factors)
    if REGIONS_KEY not in params:
        raise ValueError(f"blur.interpolation_region > 0 needs params[{REGIONS_KEY!r}] (each "
                         "gap's factor per region, measured by "
                         "gpu_blur.backends.flows.with_factors)")
    regions = RegionFactors(options["region"], np.asarray(params[REGIONS_KEY]))
    if (regions.factors.dtype != np.uint8 or regions.factors.ndim != 3
            or not np.isin(regions.factors, INTERPOLATION_FACTORS).all()
            or regions.gaps != factors):
        raise ValueError(f"params[{REGIONS_KEY!r}] must be a uint8 array of {gaps} x rows x "
                         f"columns factors, each one of {INTERPOLATION_FACTORS}, whose "
                         f"largest per gap are params[{FACTORS_KEY!r}] = {list(factors)}")
    return regions


class UnitFrames:
    """Frames as stored, read one at a time as float64 sRGB values in [0, 1].

    ``frames[i]`` is :func:`gpu_blur.image_arrays.unit_values` of the stored frame, made when asked
    and not kept (the reference then holds two frames at a time, not the sequence).
    """

    def __init__(self, frames: Sequence[np.ndarray]):
        self._frames = frames

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index: int) -> np.ndarray:
        return unit_values(self._frames[index])

    def gray8(self, index: int) -> np.ndarray:
        """Frame ``index``'s :func:`~gpu_blur.reference.flow.gray8` (8-bit: its codes)."""
        stored = self._frames[index]
        return gray8(stored if stored.dtype == np.uint8 else unit_values(stored))


def with_flows(plan: Plan, params: dict, frames: Sequence[np.ndarray]) -> dict:
    """``params`` with ``"flows"``, the sequence's optical flows, when the plan interpolates.

    Under interpolation auto also with the gaps' factors (:func:`with_factors`); a gap with
    factor 1 gets zero flows, not computed.

    Args:
        plan: the sample's plan (``blur`` options ``interpolation`` and ``flow``).
        params: its drawn parameters; returned as they are without interpolation or when they
            hold ``flows`` already.
        frames: the full-size input frames as stored (uint8/uint16 codes or float64 in [0, 1]).

    Returns:
        A new dict (the caller's is not changed: flows are no drawn value and stay out of the
        manifest) with ``flows`` of shape ``(n - 1) x 2 x H x W x 2`` float32
        (:func:`gpu_blur.reference.flow.sequence_flows`), computed here, timed as
        ``kernels`` (the accumulate pass's host part).
    """
    if interpolation_factor(plan) == 1 or params.get("flows") is not None:
        return params
    params = with_factors(plan, params, frames)
    factors = gap_factors(plan, params, len(frames) - 1)
    with timer("kernels"):
        flows = sequence_flows(UnitFrames(frames), plan["blur"].options["flow"], factors)
    return {**params, "flows": flows}
