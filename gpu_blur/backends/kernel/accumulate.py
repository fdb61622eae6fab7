"""Pass 1 of one sample on the kernel backend: linearize and blur into (linear, mask).

Every blur mode: none (its given mask), average (stacks of frames summed with compensation, or
all at once exactly in integers through the 8-bit code table), the interpolated average
(optical flows; intermediate frames never stored), kernel (one launch for samples each with
its own kernel) and trajectory (a camera-shake path, one pose at a time).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur.backends import FRAMES_PER_LAUNCH, OnDevice
from gpu_blur.backends.flows import gap_regions, interpolation_factor, with_flows
from gpu_blur.backends.kernel.buffers import Slots, _check_slots
from gpu_blur.backends.kernel.config import (
    Arg,
    Drawn,
    PassConfig,
    _index,
    _out_geometry,
    _view_geometry,
    average_args,
    source_dtype,
)
from gpu_blur.kernel_constants import (
    EXACT_COUNT_SHIFT,
    EXACT_FRAMES_MAX,
    EXACT_UNIT,
    KERNEL_WORDS,
    SATURATION_LEVEL,
)
from gpu_blur.planning import Pass, Plan, StageName
from gpu_blur.reference import blur, fixedmath
from gpu_blur.reference.interpolate import (
    CONSISTENCY_ABSOLUTE_PX2,
    CONSISTENCY_RELATIVE,
    gap_weights,
)
from gpu_blur.tiling import Region

__all__ = ["Accumulate", "S"]

S = StageName


class Accumulate:
    """Pass 1 of :class:`~gpu_blur.backends.kernel.KernelBackend`, one of its parts."""

    def _linear_out(self, linear, sat_mask, shape, region: Region):
        """The accumulate pass's (linear, mask), left on the device."""
        return (self._out(linear, shape, Pass.ACCUMULATE, region.origin),
                OnDevice(sat_mask, shape, self._fetch))

    def _code_table(self, config: PassConfig, source):
        """The linear value of every 8-bit code, from these kernels' own linearize.

        The average's sum gathers from it instead of evaluating the EOTF per value: the same
        function of the same 256 codes, so the same bits. Made once per build; a one-value
        placeholder when the frames are not 8-bit codes (the kernel does not read it).
        """
        key = (config, np.dtype(source).str)
        if key not in self._code_tables:
            count = 256 if np.dtype(source) == np.uint8 else 1
            table, indicator = self._empty(count), self._empty(count)
            if count == 256:
                codes = self._upload(np.arange(256), np.uint8)
                with self._timed():
                    self._launch(self._pass_kernels(config, source), "linearize", count, codes,
                                 table, indicator)
            self._code_tables[key] = table
        return self._code_tables[key]

    def _exact_units(self, config: PassConfig, source):
        """Each 8-bit code's entry for the exact one-launch average, or None where it is not used.

        ``gb_blur_average_exact`` sums these (kernel_constants.EXACT_UNIT): the code table's
        value as a whole number of units, plus ``1 << EXACT_COUNT_SHIFT`` where it is saturated.
        None unless the frames are 8-bit codes in a float32 build whose table values are whole
        units in [0, 1] (the condition of gb_sum.h's proof, checked here on the values).
        """
        if np.dtype(source) != np.uint8 or np.dtype(self.np_real) != np.float32:
            return None
        key = ("exact", config)
        if key not in self._code_tables:
            table = OnDevice(self._code_table(config, source), (256,), self._fetch)
            values = table.numpy(np.float64)
            units = values / EXACT_UNIT
            whole = bool(np.all(units == np.floor(units)) and np.all((values >= 0)
                                                                     & (values <= 1)))
            saturated = values >= float(np.float32(SATURATION_LEVEL))
            entries = (units.astype(np.uint64)
                       + (saturated.astype(np.uint64) << np.uint64(EXACT_COUNT_SHIFT)))
            self._code_tables[key] = self._upload(entries, np.uint64) if whole else None
        return self._code_tables[key]

    def _sum_frames(self, k, config: PassConfig, source, stack, count: int, n: int, sums,
                    first: bool, mean_of: int, linear, sat_mask) -> None:
        """Launch the average's sum of ``count`` frames of ``n`` values each from ``stack``.

        Exactly in integers (``blur_average_exact``) when these are all the frames (``first``,
        ``mean_of == count``), at most EXACT_FRAMES_MAX 8-bit ones in a float32 build read four
        codes at a time (:meth:`_quads`); else the compensated sum (``blur_average_add``,
        :func:`average_args`). The same bits either way.
        """
        units = (self._exact_units(config, source)
                 if first and mean_of == count and count <= EXACT_FRAMES_MAX else None)
        quads = self._quads((stack, linear, sat_mask), n) if units is not None else None
        if quads is not None:
            self._launch(k, "blur_average_exact", (1, n // 4), quads[0], Arg("uint", count),
                         *_index(n // 4, 0), units, *quads[1:], *_index(0))
            return
        self._launch(k, "blur_average_add", n, *average_args(
            stack, count, n, sums, first, mean_of, linear, sat_mask,
            self._code_table(config, source)))

    def _quads(self, buffers, n: int):
        """Buffers of ``n`` values each as kernels taking four values a work item read them.

        8-bit codes as 4-byte words, reals as 4-vectors; None where they cannot: ``n`` must be
        a multiple of 4. The buffers themselves here (the OpenCL kernels declare
        ``uchar4`` and ``float4``); word and 4-vector views in Warp.
        """
        return tuple(buffers) if n % 4 == 0 else None

    def accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region: Region) -> tuple[OnDevice, OnDevice]:
        """Linearize and blur on the device; (linear, mask) over ``region``, on the device.

        ``frames``: host frames as stored (streamed a few at a time, any region), or inputs
        already on the device (:meth:`put`, whole images only): an ``n x H x W x 3`` stack
        for mode average, one ``H x W x 3`` image otherwise; ``mask`` likewise.
        """
        if isinstance(frames, OnDevice):
            return self._accumulate_put(plan, params, frames, mask, region)
        config = self._of_plan(plan)[Pass.ACCUMULATE]
        source = source_dtype(frames[0], self.np_real)
        k = self._pass_kernels(config, source)
        mode = plan.variant(S.BLUR) or "none"
        n = region.h * region.w * 3
        shape = (region.h, region.w, 3)
        linear = self._empty(n)
        sat_mask = None if mode == "none" else self._empty(n)  # mode none is given its mask
        if mode == "average" and interpolation_factor(plan) > 1:
            self._interpolated_average(plan, config, params, frames, region, linear, sat_mask)
        elif mode == "average":
            self._average(config, frames, region, linear, sat_mask)
        elif mode == "none":
            image = self._upload(region.of(frames[0]), source)
            with self._timed():
                self._linearize_unblurred(config, source, image, n, linear)
            del image
            given = np.zeros(shape) if mask is None else region.of(mask)
            return (self._out(linear, shape, Pass.ACCUMULATE, region.origin),
                    OnDevice(self._upload(given), shape, self._fetch))
        else:
            self._blur_photo(k, mode, params, frames[0], source, region, linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _accumulate_put(self, plan: Plan, params: dict, frames: OnDevice,
                        mask: OnDevice | None, region: Region,
                        into: tuple | None = None) -> tuple[OnDevice, OnDevice]:
        """:meth:`accumulate` of inputs on the device, over the whole image.

        ``into``: (linear, mask) device buffers of ``3 h w`` values to write (a batch's slots,
        :meth:`accumulate_into`), else new ones.
        """
        mode = plan.variant(S.BLUR) or "none"
        h, w = frames.shape[-3:-1]
        if (region.h, region.w) != (h, w) or region.origin != (0, 0):
            raise ValueError(f"inputs on the device run whole images; got the region {region} "
                             f"of a {h} x {w} image")
        if (frames.ndim == 4) != (mode == "average"):
            wanted = "an n x H x W x 3 stack of frames" if mode == "average" else "one image"
            raise ValueError(f"blur.mode = {mode} takes {wanted} on the device, got shape "
                             f"{frames.shape}")
        if mode == "average" and interpolation_factor(plan) > 1:
            raise ValueError("blur.interpolation > 1 needs the frames in host memory (its "
                             "optical flows are computed there)")
        config = self._of_plan(plan)[Pass.ACCUMULATE]
        source = frames.dtype or np.dtype(self.np_real)
        k = self._pass_kernels(config, source)
        n = h * w * 3
        shape = (h, w, 3)
        # mode none is given its mask (into a batch's slot, or as it is: _mask_values)
        linear, sat_mask = into or (self._empty(n), None if mode == "none" else self._empty(n))
        if mode == "average":  # one launch sums every frame of the stack
            count = frames.shape[0]
            spare = self._empty(1, np.uint32)
            with self._timed():
                self._sum_frames(k, config, source, frames.data, count, n,
                                 (linear, sat_mask, spare), True, count, linear, sat_mask)
        elif mode == "none":
            with self._timed(sync=False):
                self._linearize_unblurred(config, source, frames.data, n, linear)
            if into is None:
                return (self._out(linear, shape, Pass.ACCUMULATE, region.origin),
                        self._mask_values(mask, n, shape))
            self._mask_into(mask, n, sat_mask)
        else:
            self._blur_photo(k, mode, params, frames, source, region, linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _linearize_unblurred(self, config: PassConfig, source, image, count: int,
                             linear) -> None:
        """Blur mode none's linearize: ``count`` values of ``image`` into ``linear``.

        No clip indicator: mode none's given mask replaces it. Where the values come in fours,
        four a work item: 8-bit codes through the code table (``linearize_codes``), values of
        the compute type by the curve (``linearize_values``), the same bits as ``linearize``;
        else ``linearize``, its indicator into a spare buffer.
        """
        k = self._pass_kernels(config, source)
        kind = np.dtype(source)
        quads = (self._quads((image, linear), count)
                 if kind in (np.uint8, np.dtype(self.np_real)) else None)
        if quads is None:
            self._launch(k, "linearize", count, image, linear, self._empty(count))
        elif kind == np.uint8:
            self._launch(k, "linearize_codes", count // 4, quads[0],
                         self._code_table(config, source), quads[1])
        else:
            self._launch(k, "linearize_values", count // 4, *quads)

    def _unit_values(self, stored: OnDevice, count: int, into) -> None:
        """``count`` stored values (a mask in its stored dtype) as reals in [0, 1] into ``into``.

        8-bit codes where they come in fours go four a work item (``unit_values_codes``, the
        same bits).
        """
        source = self._stored_dtype(stored)
        k = self._input_kernels(None, source)
        quads = self._quads((stored.data, into), count) if source == np.uint8 else None
        with self._timed(sync=False):
            if quads is None:
                self._launch(k, "unit_values", count, stored.data, into)
            else:
                self._launch(k, "unit_values_codes", count // 4, *quads)

    def _mask_into(self, mask: OnDevice | None, n: int, into) -> None:
        """Mode none's given mask as compute-type values in the device buffer ``into``."""
        if mask is None:
            self._fill_zeros(into, n)
        elif self._stored_dtype(mask) == np.dtype(self.np_real):
            self._copy(into, mask.data, n)
        else:
            self._unit_values(mask, n, into)

    def _blur_kernels(self, k, samples: Sequence[Drawn], src: Slots, ind: Slots, view: Region,
                      region: Region, linear: Slots, sat_mask: Slots) -> None:
        """Blur mode kernel of samples in one launch, each sample in its slot.

        Each sample's linear image and saturation indicator (its slots of ``src`` and ``ind``,
        over ``view``) convolved with its ``params["kernel"]`` into its slots of ``linear`` and
        ``sat_mask`` (over ``region``).
        """
        kernels = [blur.normalize_kernel(d.params["kernel"]) for d in samples]
        need = region.expand(max(max(kern.shape) // 2 for kern in kernels))
        if not (view.y0 <= need.y0 and view.x0 <= need.x0 and need.y0 + need.h <= view.y0
                + view.h and need.x0 + need.w <= view.x0 + view.w):
            raise ValueError(f"blur kernels: the view {view} does not hold {need}, the region "
                             "and the largest kernel's radius (a gpu_blur bug: please report it)")
        _check_slots(samples, (("src", src, view.h * view.w * 3),
                               ("ind", ind, view.h * view.w * 3),
                               ("linear", linear, region.h * region.w * 3),
                               ("sat_mask", sat_mask, region.h * region.w * 3)))
        first = np.cumsum([0] + [kern.size for kern in kernels[:-1]])
        words = np.array([(f, *kern.shape, d.slot)
                          for f, kern, d in zip(first, kernels, samples, strict=True)],
                         dtype=np.uint32).reshape(len(samples), len(KERNEL_WORDS))
        taps = np.concatenate([kern.ravel() for kern in kernels]).astype(self.np_real)
        self._launch(k, "blur_kernel", (len(samples), region.h, region.w), *self._slots(src),
                     *self._slots(ind), *_view_geometry(view), self._rows(taps),
                     self._rows(words), *self._slots(linear), *self._slots(sat_mask),
                     *_out_geometry(region))

    def _mask_values(self, mask: OnDevice | None, n: int, shape) -> OnDevice:
        """Mode none's given mask as compute-type values on the device (zeros without one)."""
        if mask is None:
            return OnDevice(self._zeros(n), shape, self._fetch)
        source = self._stored_dtype(mask)
        if source == np.dtype(self.np_real):
            return OnDevice(mask.data, shape, self._fetch)
        values = self._empty(n)
        self._unit_values(mask, n, values)
        return OnDevice(values, shape, self._fetch)

    def _average(self, config: PassConfig, frames, region: Region, linear, sat_mask) -> None:
        """Mode average: the mean of the frames, a stack of frames per launch."""
        source = source_dtype(frames[0], self.np_real)
        k = self._pass_kernels(config, source)
        n = region.h * region.w * 3
        # running compensated sums (sum, rounding errors, saturation counts) are only
        # needed between launches: one stack of frames is summed in registers
        sums = ((self._empty(n), self._empty(n), self._empty(n, np.uint32))
                if len(frames) > FRAMES_PER_LAUNCH
                else (linear, sat_mask, self._empty(1, np.uint32)))
        done = 0
        for stack, count in self._frame_stacks(frames, region):
            last = done + count == len(frames)
            with self._timed(sync=last):
                self._sum_frames(k, config, source, stack, count, n, sums, done == 0,
                                 len(frames) if last else 0, linear, sat_mask)
            done += count

    def _blur_photo(self, k, mode: str, params: dict, photo, source, region: Region, linear,
                    sat_mask) -> None:
        """Modes kernel and trajectory: one photo, linearized over the blur's halo, blurred."""
        view = region.expand(blur.blur_halo(mode, params, region.full_h, region.full_w))
        vn = view.h * view.w * 3
        src, indicator = self._empty(vn), self._empty(vn)
        image = self._upload(photo if isinstance(photo, OnDevice) else view.of(photo), source)
        with self._timed(sync=False):
            self._launch(k, "linearize", vn, image, src, indicator)
        del image
        grid = (region.h, region.w)
        if mode == "kernel":  # a batch of one
            n = region.h * region.w * 3
            with self._timed():
                self._blur_kernels(k, [Drawn(params, 0, 0)], Slots(src, 1, vn),
                                   Slots(indicator, 1, vn), view, region, Slots(linear, 1, n),
                                   Slots(sat_mask, 1, n))
            return
        # compensated sums (sum, compensation) of the image and of its indicator, 3 values a
        # pixel, and of the poses' weights on the image, 1 a pixel (reference.shake, "Edges")
        pixels = region.h * region.w
        sums = ([self._zeros(3 * pixels) for _ in range(4)]
                + [self._zeros(pixels) for _ in range(2)])
        hom = params["homographies"]
        inverses = [self._rows(np.ravel(h).astype(self.position_dtype))  # as the reference:
                    for h in fixedmath.inverse3(hom)]  # the same bits on every host CPU
        with self._timed():
            for hinv in inverses:  # one pose at a time
                self._launch(k, "blur_trajectory_add", grid, src, indicator,
                             *_view_geometry(view), hinv, *sums, *_out_geometry(region))
            self._launch(k, "blur_trajectory_finish", 3 * pixels, *sums, linear, sat_mask)

    def _interpolated_average(self, plan: Plan, config: PassConfig, params: dict,
                              frames: Sequence[np.ndarray], region: Region, linear,
                              sat_mask) -> None:
        """Mode average at ``blur.interpolation`` times the frame rate, into linear, sat_mask.

        One gap at a time, in time order: frame i+1 and the gap's two flows upload over the
        region plus the flows' halo (frame i stays from the gap before), then the original
        frame and the intermediates after it join one set of compensated sums (the
        interpolate kernels); intermediate frames are never stored.
        """
        params = with_flows(plan, params, frames)
        regions = gap_regions(plan, params, len(frames) - 1)
        factors = regions.gaps
        if max(factors, default=1) == 1:  # interpolation auto, no gap moves: a plain average
            self._average(config, frames, region, linear, sat_mask)
            return
        # each gap's frames stand for M / f frames (reference.interpolate, steps 6 and 7), f
        # the factor of the pixel's region: all 1 for one factor everywhere, so a fixed factor
        # adds exactly what it always did
        most = max(factors)
        _, total = gap_weights(factors)
        # the gaps' region factors, then one region of M for the last frame (weight 1)
        per_gap, cols = regions.factors[0].size, regions.factors.shape[2]
        maps = self._empty(regions.factors.size + 1, np.uint32)
        self._write(maps, np.append(regions.factors.ravel(), most).astype(np.uint32))

        def weights(gap: int) -> tuple[Arg, ...]:  # a gap's factors per region, and M
            if gap == len(factors):
                return maps, *_index(regions.factors.size, 0, 1), Arg("uint", most)
            return maps, *_index(gap * per_gap, regions.side, cols), Arg("uint", most)

        source = source_dtype(frames[0], self.np_real)
        k = self._pass_kernels(config, source, interpolate=True)
        flows = params["flows"]
        view = region.expand(blur.blur_halo("average", params, region.full_h, region.full_w))
        n = region.h * region.w * 3
        sums = (self._zeros(n), self._zeros(n), self._zeros(n))
        geometry = _index(view.x0, view.y0, view.w)
        full = _index(region.full_w, region.full_h)
        test = (Arg("position", CONSISTENCY_RELATIVE), Arg("position", CONSISTENCY_ABSOLUTE_PX2))
        grid = (region.h, region.w)
        frame_bufs = [self._empty(view.h * view.w * 3, source) for _ in range(min(2, len(frames)))]
        flow_bufs = [self._empty(view.h * view.w * 2, np.float32) for _ in range(2)]
        for i in range(len(frames)):
            self._write(frame_bufs[i % 2], np.ascontiguousarray(view.of(frames[i]), source))
            factor = factors[i - 1] if i > 0 else 1
            if factor > 1:  # a gap without intermediates reads no flows
                for buf, flow in zip(flow_bufs, flows[i - 1], strict=True):
                    self._write(buf, np.ascontiguousarray(view.of(flow)))
            with self._timed(sync=False):
                for step in range(1, factor):
                    self._launch(k, "blur_interpolate_add", grid, frame_bufs[(i - 1) % 2],
                                 frame_bufs[i % 2], *flow_bufs, *geometry, *full,
                                 Arg("position", step / factor), *test,
                                 Arg("uint", step), Arg("uint", factor), *weights(i - 1),
                                 *sums, *_out_geometry(region))
                self._launch(k, "blur_interpolate_add_frame", grid, frame_bufs[i % 2],
                             *geometry, *weights(i), *sums, *_out_geometry(region))
        with self._timed():
            self._launch(k, "blur_interpolate_finish", n, *sums, Arg("uint", total), linear,
                         sat_mask)
