"""The host-side scheduler: how a sample's three passes run over its image.

:func:`gpu_blur.synthesize` decides *what* runs (the scene's plan, the drawn parameters, the
inputs); this module decides *how*:

* **tiles with halos**: the image runs in tiles of an explicit size (``tile``), or of the
  largest size whose device buffers fit a memory budget (``max_device_memory``), or whole.
  Each tile's view carries the demosaic halo (aligned to the Bayer cell) and the backends add
  the blur halo; every draw uses global coordinates, so the output is bit for bit that of
  the whole image.
* **streaming frames**: a sample's frames are decoded once into host memory; for each tile
  the accumulate pass sends them to the device one at a time (at most two in flight: one
  summed while the next uploads), so device memory does not grow with ``blur.frames``.
* **spot checks** (``verify``): a fraction of the tiles, chosen from (seed, sample index),
  is recomputed pass by pass with the numpy float64 reference and compared under the
  tolerance table of :mod:`gpu_blur.tolerances`; a disagreement raises :class:`SpotCheckError`.

Memory budget
-------------
A tile of ``r x c`` output pixels holds, in the pass that holds most (passes run one after
another and free their buffers; constants are small and listed per pass):

* ``V = (r + 2 d + a) (c + 2 d + a)`` pixels of view, ``d`` the demosaic halo (2 Malvar,
  1 bilinear, 0 without the RAW round trip) and ``a = 2`` for the Bayer-cell alignment with
  the RAW round trip (else 0);
* ``S = (r + 2 d + a + 2 b) (c + 2 d + a + 2 b)`` pixels of blur source, ``b`` the blur halo
  (kernel radius, the camera path's largest displacement, or the largest optical-flow
  component + 1 for interpolated averaging; 0 for plain average and none);
* each side clipped to the image; ``s`` bytes per value (4 float32, 8 float64), RGB values;
  ``b`` bytes per value of a frame as stored (1 uint8, 2 uint16, ``s`` float input);
* ``F`` frames (mode average), ``P = min(F, FRAMES_PER_LAUNCH)`` summed per launch.

========== ============================================================================
pass       bytes
========== ============================================================================
accumulate average, ``F <= P``: ``3 V (F b + 2 s)`` (one stack of frames, the linear
           image and mask); ``F > P``: ``3 V (2 P b + 4 s + 4)`` (two stacks taking
           turns, the compensated sum: sum, compensation, uint32 counts; linear, mask);
           average with ``blur.interpolation > 1``: ``6 S b + 16 S + 3 V (4 s + 4)``
           (two frames and a gap's two float32 flows over the source, which holds the
           flows' halo; the compensated sum, linear, mask);
           none: ``3 V (b + 3 s)`` (frame, linear, indicator, mask);
           kernel: ``3 (S b + 2 S s + 2 V s) + kh kw s`` (source upload, linear source
           and its saturation indicator, linear image and mask, the kernel);
           trajectory: ``3 (S b + 2 S s + 6 V s) + 72 n`` (as kernel, plus four
           compensated sums; ``n`` poses' float64 3 x 3 inverses)
to_raw     ``10 V s + 9 s`` (linear image, mask, saturated image, RAW mosaic, Lin2Cam)
finish     ``(10 V + 3 r c) s + 2,568 s`` (the accumulate pass's linear image and mask,
           kept for the spot checks and the mask; RAW mosaic, saturated image, result;
           Cam2Lin, the A7R3 polynomial and its 2,551-node table)
========== ============================================================================

Pass outputs stay on the device for the next pass (nothing returns to the host between
passes). The formula assumes a buffer a pass drops is only released when its kernels finish
(as OpenCL may do). Warp's peaks on an H100 stayed under it when last checked
(bench/scheduler_gpu_check.py; docs/performance.md#scheduler-memory-formula).

The budget gives the largest square tile whose peak fits, then widens it (columns, then
rows) as far as the budget allows; the whole image when it fits. The smallest tile is
:data:`MIN_TILE` x :data:`MIN_TILE` (or the image's side, when smaller); a budget below that
tile's peak is an error naming the minimum. The numpy backend
keeps the float64 reference's whole-image accumulate pass whatever the budget (it is the
truth, not a memory saver), run once per sample and cut for each tile; the budget still sets
its tiles.

Spot checks
-----------
Tile ``i`` of a sample is checked when ``u_i < verify``, ``u`` the per-image uniforms of
stream ``SPOT_CHECK`` of (seed, sample index) (:func:`gpu_blur.reference.rng.image_uniforms`):
about that fraction of all tiles over a run, the same tiles on every machine and backend for
the same tiling, every tile at ``verify = 1``. A checked tile's passes are recomputed by the
numpy backend from the same inputs each pass got on the device (the reference accumulate
pass runs once per sample, on the whole image):

* accumulate: linear image and mask against rows ``accumulate``;
* to_raw: the RAW mosaic against ``to_raw``. With Poisson-Gaussian noise a value is also
  accepted when the reference draws it itself for a RAW value within the ``to_raw`` row of
  its own (a count is a step function of its rate: float32 rates land on the other side of a
  step on about 4e-5 of values, by one count or a flipped PTRS rejection); beyond those at
  most the ``to_raw_noisy_outliers`` fraction may lie outside. The saturated image against
  ``saturate``;
* finish: against ``finish`` (``finish_crf_polynomial`` when re-toning with a polynomial:
  A7R3's or the camera's fitted response); a
  quantized value may differ by one code exactly where the reference's value before
  rounding lies within that row's tolerance of the rounding boundary.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np

from gpu_blur.backends import FRAMES_PER_LAUNCH, Backend, OnDevice, to_host
from gpu_blur.backends.flows import interpolation_factor, with_flows
from gpu_blur.planning import Plan, StageName
from gpu_blur.reference import blur, rng
from gpu_blur.reference.demosaic import halo as demosaic_halo
from gpu_blur.reference.output import quantize
from gpu_blur.tiling import Region, tiles
from gpu_blur.timings import timer
from gpu_blur.tolerances import mismatch, tolerance

__all__ = ["Footprint", "MIN_TILE", "S", "SPOT_CHECK_FAILED", "Schedule", "SpotCheckError", "Tiled",
           "check_budget", "check_tile", "format_bytes", "parse_bytes", "run", "spot_check_tiles"]

S = StageName

#: The smallest tile side, given (``tile``, ``--tile``) or from a memory budget (smaller images
#: use their own side). Each tile costs a fixed overhead of milliseconds
#: (docs/performance.md#scheduler-smallest-tile), and its view grows by the demosaic halo and
#: the Bayer alignment, 2 + 2 px per side with Malvar: at 16 x 16 the view is under twice the
#: tile.
MIN_TILE = 16
#: How a spot-check failure's message begins (``gpu-blur generate --strict`` looks for it).
SPOT_CHECK_FAILED = "spot check failed"
#: Values of the finish pass's constants: Cam2Lin 3 x 3, the A7R3 polynomial (8) and table.
_FINISH_CONSTANTS = 9 + 8 + 2551

_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_bytes(value) -> int:
    """A byte count from an int or a size such as ``512M``, ``2G``, ``1.5GiB``, ``65536``.

    Suffixes K, M, G, T are binary (``512M`` = 512 MiB); ``B``/``iB`` after them are allowed.

    Raises:
        ValueError: naming the value and the accepted forms.
    """
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        count = int(value)
    else:
        m = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*(?:([KMGT])(?:I?B)?|B)?\s*", str(value).upper())
        if m is None:
            raise ValueError(f"{value!r} is not a memory size: give bytes, or a number with K, "
                             "M, G or T (binary units), e.g. 512M or 2G")
        count = int(float(m[1]) * _UNITS[m[2] or ""])
    if count <= 0:
        raise ValueError(f"memory size {value!r}: must be positive")
    return count


def format_bytes(count: int) -> str:
    """``count`` in bytes and in binary units, e.g. ``'1,050,000 bytes (1.0 MiB)'``."""
    unit, scale = next(((u, f) for u, f in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10))
                        if count >= f), ("B", 1))
    return f"{count:,} bytes ({count / scale:.1f} {unit})" if scale > 1 else f"{count:,} bytes"


@dataclasses.dataclass(frozen=True)
class Schedule:
    """How a sample runs; never what it gives (picklable, so a job can carry it).

    Attributes:
        tile: run in tiles of at most (rows, columns); wins over ``max_device_memory``.
        max_device_memory: bytes of device memory a tile's passes may hold (an int, or a size
            such as ``"512M"``): tiles are sized to fit (see the module docstring).
        verify: the fraction of tiles spot-checked against the numpy reference, in [0, 1].
    """

    tile: tuple[int, int] | None = None
    max_device_memory: int | str | None = None
    verify: float = 0.0

    def __post_init__(self):
        if self.tile is not None:
            object.__setattr__(self, "tile", check_tile(self.tile))
        if self.max_device_memory is not None:
            object.__setattr__(self, "max_device_memory", parse_bytes(self.max_device_memory))
        verify = float(self.verify)
        if not 0.0 <= verify <= 1.0:
            raise ValueError(f"verify = {self.verify!r}: the fraction of tiles to spot-check "
                             "must lie in [0, 1]")
        object.__setattr__(self, "verify", verify)


def check_tile(tile, name: str = "tile") -> tuple[int, int]:
    """A tile size (rows, columns), checked: two integers >= :data:`MIN_TILE`.

    Args:
        tile: the size as given.
        name: how messages name it (``--tile`` for the command line).

    Raises:
        ValueError: naming ``name``, the size, the minimum and why.
    """
    try:
        sides = tuple(tile)
    except TypeError:  # one number
        sides = (tile,)
    if len(sides) != 2 or not all(isinstance(t, (int, np.integer)) and not isinstance(t, bool)
                                  for t in sides):
        raise ValueError(f"{name} {tile!r}: give two integers, rows and columns")
    if min(sides) < MIN_TILE:
        raise ValueError(
            f"{name} {sides[0]} {sides[1]}: rows and columns must be >= {MIN_TILE}: each tile "
            "costs a fixed overhead (~2 ms on a CPU: 1 x 1 tiles of a 1920 x 1200 image would "
            "take over an hour) and reads a halo of up to 4 pixels per side; a tile larger "
            "than the image runs the whole image")
    return int(sides[0]), int(sides[1])


class SpotCheckError(ValueError):
    """A spot-checked tile disagreed with the numpy reference beyond the tolerance table.

    A ``ValueError``, so ``gpu-blur generate`` records the sample as failed and goes on (or
    stops, with ``--strict``). The message names the sample, the tile and the error.

    Attributes:
        sample_index: the sample.
        region: the tile (global coordinates).
        pass_: the pass that disagreed, with the output compared.
    """

    def __init__(self, message: str, *, sample_index: int | None = None,
                 region: Region | None = None, pass_: str | None = None):
        super().__init__(message)
        self.sample_index, self.region, self.pass_ = sample_index, region, pass_


@dataclasses.dataclass(frozen=True)
class Footprint:
    """What one sample's passes hold on the device, to size its tiles.

    Attributes:
        height, width: the image's size.
        mode: blur variant (average, kernel, trajectory, none).
        raw_round_trip: whether the RAW passes (mosaic, demosaic) run.
        demosaic_halo: pixels the demosaic reads on each side (0 without RAW).
        blur_halo: pixels the blur reads on each side.
        itemsize: bytes per value (4 float32, 8 float64).
        blur_constants: bytes of the blur's constants (kernel taps, pose inverses).
        frames: frames summed (mode average).
        source_itemsize: bytes per value of a frame as stored (1 uint8, 2 uint16; 0: as
            ``itemsize``, float input).
        interpolation: the frame-rate factor of mode average (1: frames as they are).
    """

    height: int
    width: int
    mode: str
    raw_round_trip: bool
    demosaic_halo: int
    blur_halo: int
    itemsize: int
    blur_constants: int = 0
    frames: int = 1
    source_itemsize: int = 0
    interpolation: int = 1

    @classmethod
    def of(cls, sample_plan: Plan, params: dict, height: int, width: int, precision: str,
           frames: int = 1, source_dtype=None) -> Footprint:
        """The footprint of a sample (its plan and drawn parameters) at a precision.

        ``frames`` and ``source_dtype``: how many input frames and their stored dtype
        (uint8/uint16 codes; float input travels in the compute type).
        """
        mode = sample_plan.variant(S.BLUR) or "none"
        raw = sample_plan.raw_round_trip
        itemsize = np.dtype(precision).itemsize
        constants = 0
        if mode == "kernel":
            constants = int(np.size(params["kernel"])) * itemsize
        elif mode == "trajectory":
            constants = len(params["homographies"]) * 9 * 8
        stored = np.dtype(source_dtype) if source_dtype is not None else None
        source = stored.itemsize if stored is not None and stored.kind == "u" else 0
        return cls(height, width, mode, raw,
                   demosaic_halo(sample_plan[S.DEMOSAIC].options["method"]) if raw else 0,
                   blur.blur_halo(mode, params, height, width), itemsize, constants,
                   max(int(frames), 1), source, interpolation_factor(sample_plan))

    def pass_bytes(self, rows: int, cols: int) -> dict[str, int]:
        """Device bytes each pass holds for a tile of ``rows x cols`` output pixels."""
        s, b = self.itemsize, self.source_itemsize or self.itemsize
        rows, cols = min(rows, self.height), min(cols, self.width)
        pad = 2 * self.demosaic_halo + (2 if self.raw_round_trip else 0)
        vh, vw = min(rows + pad, self.height), min(cols + pad, self.width)
        sh = min(vh + 2 * self.blur_halo, self.height)
        sw = min(vw + 2 * self.blur_halo, self.width)
        view, source = vh * vw, sh * sw
        per = min(self.frames, FRAMES_PER_LAUNCH)
        average = (3 * view * (self.frames * b + 2 * s) if self.frames <= per
                   else 3 * view * (2 * per * b + 4 * s + 4))
        if self.interpolation > 1:
            average = 6 * source * b + 16 * source + 3 * view * (4 * s + 4)
        accumulate = {
            "average": average,
            "none": 3 * view * (b + 3 * s),
            "kernel": 3 * (source * b + 2 * source * s + 2 * view * s),
            # + the weight each output pixel's poses give the image, and its compensation
            "trajectory": 3 * (source * b + 2 * source * s + 6 * view * s) + 2 * view * s,
        }[self.mode] + self.blur_constants
        return {"accumulate": accumulate, "to_raw": 10 * view * s + 9 * s,
                "finish": (10 * view + 3 * rows * cols + _FINISH_CONSTANTS) * s}

    def tile_bytes(self, rows: int, cols: int) -> int:
        """The peak device bytes of a tile: the largest pass."""
        return max(self.pass_bytes(rows, cols).values())

    def tile_for_budget(self, budget: int, sample_index: int = 0) -> tuple[int, int] | None:
        """The tile size a budget gives: None for the whole image, else (rows, columns).

        Raises:
            ValueError: when even the smallest tile does not fit, naming what it needs.
        """
        h, w = self.height, self.width
        if self.tile_bytes(h, w) <= budget:
            return None
        r0, c0 = min(MIN_TILE, h), min(MIN_TILE, w)
        need = self.tile_bytes(r0, c0)
        if need > budget:
            halos = f"demosaic halo {self.demosaic_halo} px, blur halo {self.blur_halo} px"
            size = (f"{math.ceil(need / 2**10)}K" if need < 2**20
                    else f"{math.ceil(need / 2**20)}M")
            raise ValueError(
                f"max_device_memory = {format_bytes(budget)} is too small for sample "
                f"{sample_index}: its smallest tile, {r0} x {c0} pixels with its halos "
                f"({halos}), needs {format_bytes(need)} of device memory at "
                f"{8 * self.itemsize}-bit precision; allow at least that "
                f"(--max-device-memory {size})")

        def largest(fits, lo: int, hi: int) -> int:  # largest n in [lo, hi] with fits(n)
            while lo < hi:
                mid = (lo + hi + 1) // 2
                lo, hi = (mid, hi) if fits(mid) else (lo, mid - 1)
            return lo

        side = largest(lambda t: self.tile_bytes(min(t, h), min(t, w)) <= budget,
                       MIN_TILE, max(h, w))
        rows, cols = min(side, h), min(side, w)
        cols = largest(lambda c: self.tile_bytes(rows, c) <= budget, cols, w)
        rows = largest(lambda r: self.tile_bytes(r, cols) <= budget, rows, h)
        return rows, cols


def check_budget(budget, scene_plan: Plan, precision: str) -> int:
    """Refuse, before any sample, a budget below what the smallest tile of any image needs.

    The floor: a :data:`MIN_TILE` x :data:`MIN_TILE` image, no blur halo (samples with a
    blur halo need more, and say so when they run).

    Args:
        budget: bytes, or a size such as ``"512M"``.
        scene_plan: the scene's plan (:func:`gpu_blur.planning.plan`).
        precision: the backend's precision (float32, float64).

    Returns:
        The budget in bytes.

    Raises:
        ValueError: naming the budget and the floor.
    """
    count = parse_bytes(budget)
    raw = scene_plan.raw_round_trip
    factor = interpolation_factor(scene_plan)
    floor = Footprint(MIN_TILE, MIN_TILE, scene_plan.variant(S.BLUR) or "none", raw,
                      demosaic_halo(scene_plan[S.DEMOSAIC].options["method"]) if raw else 0, 0,
                      np.dtype(precision).itemsize,
                      interpolation=factor).tile_bytes(MIN_TILE, MIN_TILE)
    if count < floor:
        raise ValueError(f"--max-device-memory {budget}: {format_bytes(count)} is less than "
                         f"the smallest tile ({MIN_TILE} x {MIN_TILE} pixels) of this scene "
                         f"needs at {8 * np.dtype(precision).itemsize}-bit precision, "
                         f"{format_bytes(floor)} (more with a blur halo); allow at least "
                         f"{math.ceil(floor / 2**10)}K")
    return count


def spot_check_tiles(seed: int, sample_index: int, count: int, fraction: float) -> list[int]:
    """Indices of the tiles a spot check recomputes: tile ``i`` when ``u_i < fraction``.

    ``u`` are the per-image uniforms of stream SPOT_CHECK of (seed, sample index), so the
    choice depends on nothing else (machine, backend, worker).
    """
    if fraction <= 0.0 or count == 0:
        return []
    u = rng.image_uniforms(seed, sample_index, rng.Stream.SPOT_CHECK, count)
    return [i for i in range(count) if u[i] < fraction]


@dataclasses.dataclass
class Tiled:
    """What :func:`run` returns.

    Attributes:
        blurred: ``h x w x 3`` float32 (with ``on_device``, the result as the backend left it:
            an :class:`~gpu_blur.backends.OnDevice` for kernel backends).
        mask: ``h x w x 3``, the blurred saturation mask: float32, or for a whole-image run
            what the backend returned (:func:`gpu_blur.backends.to_host` fetches it).
        tiles: how many tiles ran.
        checked: how many of them were spot-checked.
        raw: with ``keep_raw``, the to_raw pass's noisy white-balanced ``h x w`` mosaic:
            float32, or for a whole-image run what the backend returned; else None.
    """

    blurred: object
    mask: np.ndarray
    tiles: int
    checked: int
    raw: object = None


def run(runner: Backend, sample_plan: Plan, params: dict, camera, frames, mask,
        schedule: Schedule, *, seed: int, sample_index: int, on_device: bool = False,
        keep_raw: bool = False) -> Tiled:
    """Run a sample's three passes on ``runner`` over tiles, with spot checks.

    Args:
        runner: a backend (:mod:`gpu_blur.backends`).
        sample_plan: the sample's plan.
        params: its drawn parameters.
        camera: its camera.
        frames: the input frames, ``H x W x 3`` as stored (uint8/uint16 codes, or float64
            in [0, 1]; :func:`gpu_blur.image_arrays.check_image`), in host memory; or inputs a
            kernel backend put on its device (``put``: whole images only).
        mask: blur mode none: the given saturation mask, or None.
        schedule: tile size, memory budget and spot-check fraction.
        seed: dataset seed.
        sample_index: the sample's index.
        on_device: leave the result on the backend's device (one tile only, no checks).
        keep_raw: also return the RAW mosaic (:attr:`Tiled.raw`; plans with the round trip).

    Raises:
        SpotCheckError: a checked tile disagreed with the reference.
        ValueError: the budget is too small for the smallest tile, or ``on_device`` with
            several tiles or spot checks.
    """
    if isinstance(frames, OnDevice):  # inputs put on the device: whole images, as they are
        h, w = frames.shape[-3:-1]
    else:
        params = with_flows(sample_plan, params, frames)  # once per sample, for every tile
        h, w = frames[0].shape[:2]
    raw = sample_plan.raw_round_trip
    halo = demosaic_halo(sample_plan[S.DEMOSAIC].options["method"]) if raw else 0
    tile = schedule.tile
    if tile is None and schedule.max_device_memory is not None:
        footprint = Footprint.of(sample_plan, params, h, w,
                                 runner.precision, len(frames),
                                 frames[0].dtype)
        tile = footprint.tile_for_budget(schedule.max_device_memory, sample_index)
    regions = list(tiles(h, w, tile))
    chosen = set(spot_check_tiles(seed, sample_index, len(regions), schedule.verify))
    if on_device and (len(regions) > 1 or chosen):
        raise ValueError(f"on_device=True needs the whole image in one tile and no spot "
                         f"checks; this schedule gives {len(regions)} tile(s) and checks "
                         f"{len(chosen)}")
    # numpy's accumulate pass is the whole image's whatever the region: once for every tile,
    # and it is the spot checks' reference pass too
    whole = (runner.accumulate(sample_plan, params, frames, mask, Region.whole(h, w))
             if runner.name == "numpy" and len(regions) > 1 else None)
    check = _SpotCheck(runner, sample_plan, params, camera, frames, mask, seed=seed,
                       sample_index=sample_index, accumulated=whole) if chosen else None
    if len(regions) == 1:  # the whole image: results stay where the backend left them
        region = regions[0]
        view = region.expand(halo).aligned(2 if raw else 1)
        linear, view_mask, image, saturated, result = _passes(
            runner, sample_plan, params, camera, frames, mask, view, region, seed, sample_index)
        if chosen:
            with timer("checks"):
                check.tile("tile 1 of 1", region, view, linear, view_mask, image, saturated,
                           result)
        blurred = result if on_device else to_host(result, np.float32)
        return Tiled(blurred, view_mask, 1, len(chosen), image if keep_raw else None)
    out = np.empty((h, w, 3), dtype=np.float32)
    sat_mask = np.empty((h, w, 3), dtype=np.float32)
    raw_out = np.empty((h, w), dtype=np.float32) if keep_raw else None
    for i, region in enumerate(regions):
        view = region.expand(halo).aligned(2 if raw else 1)
        linear, view_mask, image, saturated, result = _passes(
            runner, sample_plan, params, camera, frames, mask, view, region, seed, sample_index,
            whole)
        if i in chosen:
            with timer("checks"):
                check.tile(f"tile {i + 1} of {len(regions)}", region, view, linear, view_mask,
                           image, saturated, result)
        region.of(out)[...] = to_host(result, np.float32)
        region.of(sat_mask)[...] = to_host(view_mask, np.float32)[region.within(view)]
        if keep_raw:
            region.of(raw_out)[...] = to_host(image, np.float32)[region.within(view)]
    return Tiled(out, sat_mask, len(regions), len(chosen), raw_out)


def _passes(runner: Backend, sample_plan, params, camera, frames, mask, view: Region,
            region: Region, seed: int, sample_index: int, whole=None):
    """One tile's three passes: (linear, mask, image, saturated, result).

    Outputs are as the backend leaves them: on its device for kernel backends. ``whole``: the
    whole image's accumulate pass (linear, mask), cut to the view instead of running it.
    """
    linear, view_mask = ((view.of(whole[0]), view.of(whole[1])) if whole is not None
                         else runner.accumulate(sample_plan, params, frames, mask, view))
    image, saturated = runner.to_raw(sample_plan, params, camera, linear, view_mask,
                                     view.origin, seed=seed, sample_index=sample_index)
    result = runner.finish(sample_plan, params, camera, image, saturated, view, region,
                           seed=seed, sample_index=sample_index)
    return linear, view_mask, image, saturated, result


def _without(sample_plan: Plan, stage: str) -> Plan:
    """The plan with ``stage`` skipped."""
    return Plan(tuple(dataclasses.replace(s, kept=False) if s.name == stage else s
                      for s in sample_plan.stages))


class _SpotCheck:
    """Recomputes checked tiles with the numpy reference and compares pass by pass."""

    def __init__(self, runner: Backend, sample_plan: Plan, params: dict, camera, frames, mask, *,
                 seed: int, sample_index: int, accumulated=None):
        """``accumulated``: the reference's whole-image accumulate pass, when already run."""
        from gpu_blur.backends.numpy import NumpyBackend

        self.runner, self.plan, self.params, self.camera = runner, sample_plan, params, camera
        self.frames, self.mask, self.seed, self.sample_index = frames, mask, seed, sample_index
        self.reference = NumpyBackend()
        self.backend, self.dtype = runner.name, runner.precision
        if sample_plan.fast_math and self.dtype == "float32":
            self.dtype = "float32-fast"  # the rows of fast maths (gpu_blur.tolerances)
        self._accumulated = accumulated

    def _whole_accumulate(self):
        """The reference accumulate pass over the whole image, once per sample."""
        if self._accumulated is None:
            h, w = self.frames[0].shape[:2]
            self._accumulated = self.reference.accumulate(self.plan, self.params, self.frames,
                                                          self.mask, Region.whole(h, w))
        return self._accumulated

    def tile(self, name: str, region: Region, view: Region, linear, view_mask, image,
             saturated, result) -> None:
        """Compare one tile's pass outputs with the reference's from the same inputs."""
        linear, view_mask, image, saturated, result = (
            to_host(x) for x in (linear, view_mask, image, saturated, result))
        p, ref = self.plan, self.reference
        kw = {"seed": self.seed, "sample_index": self.sample_index}

        def compare(what, stage, actual, expected, **options):
            problem = mismatch(actual, expected, stage, self.backend, self.dtype, **options)
            if problem:
                y1, x1 = region.y0 + region.h - 1, region.x0 + region.w - 1
                device = self.runner.device
                raise SpotCheckError(
                    f"{SPOT_CHECK_FAILED}: sample {self.sample_index}, {name} (rows "
                    f"{region.y0}..{y1}, columns {region.x0}..{x1}): the {what} from {device} "
                    f"disagrees with the numpy reference: {problem}. The device or its driver "
                    "computed wrong values; rerun on another device or backend",
                    sample_index=self.sample_index, region=region, pass_=what)

        whole_linear, whole_mask = self._whole_accumulate()
        compare("accumulate pass's linear image", "accumulate", linear, view.of(whole_linear))
        compare("accumulate pass's saturation mask", "accumulate", view_mask,
                view.of(whole_mask))
        ref_image, ref_sat = ref.to_raw(p, self.params, self.camera, linear, view_mask,
                                        view.origin, **kw)
        if p.raw_round_trip:
            outliers, rounded = 0.0, None
            if p.kept(S.POISSON_GAUSSIAN_NOISE):
                outliers = tolerance("to_raw_noisy_outliers", self.backend, self.dtype)[1]
                rounded = self._rate_rounding(image, ref_image, linear, view_mask, view)
            compare("to_raw pass's RAW mosaic", "to_raw", image, ref_image,
                    allowed_fraction=outliers, accept=rounded)
        compare("to_raw pass's saturated image", "saturate", saturated, ref_sat)
        unquantized = ref.finish(_without(p, S.QUANTIZE), self.params, self.camera, image,
                                 saturated, view, region, **kw)
        stage = "finish_crf_polynomial" if p.retone_curve == "polynomial" else "finish"
        if not p.kept(S.QUANTIZE):
            compare("finish pass's image", stage, result, unquantized)
            return
        bits = p[S.QUANTIZE].options["bits"]
        top = 2**bits - 1
        exact = np.clip(unquantized, 0.0, 1.0)
        ref_codes = np.floor(exact * top + 0.5)
        got_codes = np.rint(np.asarray(result, dtype=np.float64) * top)
        rtol, atol = tolerance(stage, self.backend, self.dtype)
        boundary = (np.minimum(ref_codes, got_codes) + 0.5) / top
        at_boundary = ((np.abs(got_codes - ref_codes) == 1)
                       & (np.abs(exact - boundary) <= atol + rtol * exact))
        compare(f"finish pass's {bits}-bit image", stage, result, quantize(unquantized, bits),
                accept=at_boundary)

    def _rate_rounding(self, image, ref_image, linear, view_mask, view: Region):
        """RAW values the reference draws itself for a rate within the to_raw row's tolerance.

        A Poisson count is a step function of its rate: where the device's noiseless RAW value
        is within the ``to_raw`` row of the reference's (its float rounding) but on the other
        side of a step, the count differs by one (or, in PTRS, a rejection decision flips). A
        value is accepted when the reference, drawing the same pixel's count at ``x - delta``
        or ``x + delta`` (``delta`` the row's bound at ``x``), gives the device's value. None
        when every value is within the row anyway.
        """
        rtol, atol = tolerance("to_raw", self.backend, self.dtype)
        if np.all(np.abs(image - ref_image) <= atol + rtol * np.abs(ref_image)):
            return None
        params, origin = self.params, view.origin
        kw = {"seed": self.seed, "sample_index": self.sample_index}
        raw, _ = self.reference.sensor_raw(self.plan, params, self.camera, linear, view_mask,
                                           origin)
        delta = atol + rtol * np.abs(raw)
        accepted = np.zeros(image.shape, dtype=bool)
        for sign in (-1.0, 1.0):
            drawn = self.reference.noisy_raw(self.plan, params,
                                             np.maximum(raw + sign * delta, 0.0), origin, **kw)
            accepted |= np.abs(image - drawn) <= atol + rtol * np.abs(drawn)
        return accepted
