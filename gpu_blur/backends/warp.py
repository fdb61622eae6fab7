"""The Warp backend: the plan's three passes as NVIDIA Warp kernels (gpu_blur/warp_kernels/).

Devices: ``warp`` (the first CUDA device if there is one, else the CPU), ``warp:cpu``,
``warp:cuda:N``. Only the stages a plan keeps are generated (``wp.static`` flags); float32 by
default, float64 on request. Random draws repeat :mod:`gpu_blur.reference.rng` bit for bit.
Pass outputs stay on the device between passes; :meth:`WarpBackend.device_array` gives the
result as a ``wp.array`` that ``torch.from_dlpack`` takes without a copy. Frames upload in their
stored dtype (8-bit frames: a quarter of a float32 copy), on CUDA from pinned host buffers on a
copy stream that overlaps the summing of the previous frames.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import warp as wp

from gpu_blur.backends import (
    FRAMES_PER_LAUNCH,
    OnDevice,
    cfa_bits,
    fill_stack,
)
from gpu_blur.backends.flows import interpolation_factor, with_flows
from gpu_blur.cameras import Camera
from gpu_blur.plan import Plan
from gpu_blur.reference import blur
from gpu_blur.reference.interpolate import CONSISTENCY_ABSOLUTE_PX2, CONSISTENCY_RELATIVE
from gpu_blur.reference.rng import key_from_seed
from gpu_blur.reference.transfer import a7r3_lookup_table
from gpu_blur.testhooks import fault_planted, planted_fault
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

wp.config.log_level = wp.LOG_WARNING  # no banner or per-module load lines

#: Warp arrays have int32 shapes, and the kernels index with Warp ``int``: one buffer holds at
#: most this many values (an RGB region ~715 M pixels). OpenCL kernels index with 64 bits.
MAX_BUFFER_VALUES = 2**31 - 1


def warp_devices() -> list[dict]:
    """Warp's devices as ``gpu-blur devices`` lists them."""
    wp.init()
    found = []
    for d in wp.get_devices():
        memory = int(getattr(d, "total_memory", 0) or 0)
        found.append({"spec": f"warp:{d.alias}", "name": d.name, "kind": "GPU" if d.is_cuda
                      else "CPU", "fp64": True, "memory_bytes": memory})
    return found


def _device(spec: str) -> str:
    wp.init()
    if spec == "warp":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    alias = spec.split(":", 1)[1]
    known = [d.alias for d in wp.get_devices()]
    if alias not in known:
        raise ValueError(f"no Warp device {spec!r}; present: "
                         + ", ".join(f"warp:{a}" for a in known))
    return alias


@dataclasses.dataclass(frozen=True)
class Prefetched:
    """Frames on their way to the device (:meth:`WarpBackend.prefetch`).

    Attributes:
        frames: the ``n x H x W x 3`` device stack.
        ready: the copy stream's event that marks the copy done (None: already done).
        slot: which of the backend's two prefetch stacks it is (None: its own).
    """

    frames: wp.array
    ready: object
    slot: int | None = None


class WarpBackend:
    """Runs a plan as Warp kernels on one device (see :mod:`gpu_blur.backends`).

    Args:
        spec: ``warp``, ``warp:cpu`` or ``warp:cuda:<n>``.
        precision: the kernels' compute type, ``float32`` or ``float64``.
        overlap: on CUDA, upload frames from pinned host buffers on a second stream while the
            previous stack of frames is summed (False: plain synchronous copies, to measure
            what the overlap gains; bench/generate_throughput.py).
    """

    name = "warp"

    def __init__(self, spec: str = "warp", precision: str = "float32", *, overlap: bool = True):
        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be float32 or float64, got {precision!r}")
        self.wp_device = _device(spec)
        self.precision = precision
        self.real = wp.float64 if precision == "float64" else wp.float32
        self.np_real = np.float64 if precision == "float64" else np.float32
        device = wp.get_device(self.wp_device)
        self.device = f"warp:{self.wp_device} {device.name}, {precision}"
        self.overlap = bool(overlap and device.is_cuda)
        self._copier = wp.Stream(self.wp_device) if self.overlap else None
        self._staging: dict = {}  # slot -> pinned host buffer (kept across samples)
        self._staged: dict = {}  # slot -> event: the last copy out of that staging buffer
        self._constants: dict = {}  # (bytes, dtype) -> device array of a small constant
        self._code_tables: dict = {}  # (compute type, source type) -> 8-bit linear table
        self.sync_passes = True
        self._prefetch_turn = 0
        self._prefetch_stacks: dict = {}  # slot -> device stack of prefetched frames
        self._prefetch_read: dict = {}  # slot -> event: the accumulate that read it

    # -- buffers (uploads and downloads are timed as "copies", gpu_blur.timings) --------------
    @staticmethod
    def _check_size(count: int) -> None:
        """Refuse, before any allocation, a buffer larger than Warp's int32 indices reach."""
        if count > MAX_BUFFER_VALUES:
            raise ValueError(
                f"a Warp buffer of {count:,} values: Warp indexes arrays with 32-bit integers "
                f"(at most {MAX_BUFFER_VALUES:,} values, about 715 M RGB pixels); run the "
                "image in tiles (synthesize(..., tile=(4096, 4096)), gpu-blur generate --tile "
                "4096 4096) or on an OpenCL backend")

    def _array(self, values, dtype=None) -> wp.array:
        """``values`` on the device, flat: an :class:`OnDevice` as it is, host data uploaded."""
        if isinstance(values, OnDevice):
            return values.data
        self._check_size(int(np.size(values)))
        with timer("copies"):
            data = np.ascontiguousarray(np.ravel(values), dtype=dtype or self.np_real)
            return wp.array(data, device=self.wp_device)

    def _constant(self, values, dtype=None) -> wp.array:
        """A small constant (matrix, polynomial, table) on the device, uploaded once."""
        data = np.ascontiguousarray(np.ravel(values), dtype=dtype or self.np_real)
        key = (data.tobytes(), data.dtype.str)
        if key not in self._constants:
            self._constants[key] = self._array(data, data.dtype)
        return self._constants[key]

    def _zeros(self, count: int, dtype=None) -> wp.array:
        self._check_size(count)
        return wp.zeros(max(count, 1), dtype=dtype or self.real, device=self.wp_device)

    def _empty(self, count: int, dtype=None) -> wp.array:
        self._check_size(count)
        return wp.empty(max(count, 1), dtype=dtype or self.real, device=self.wp_device)

    def _launch(self, kernel, dim, *args) -> None:
        wp.launch(kernel, dim=dim, inputs=list(args), device=self.wp_device)

    def _kernels(self, sync: bool = True):
        """Time launches as "kernels"; ``sync`` waits for them (``wp.synchronize_device``).

        With ``sync_passes`` False nothing waits (the timings then hold launch times only),
        so the passes can be captured in a CUDA graph (bench/gpu_targets.py).
        """
        return timer("kernels", self._synchronize if sync and self.sync_passes else None)

    def _synchronize(self) -> None:
        if self.overlap:  # the compute stream only: a prefetch may still be copying
            wp.synchronize_stream(wp.get_stream(self.wp_device))
        else:
            wp.synchronize_device(self.wp_device)

    def _out(self, array: wp.array, shape, pass_: str, origin) -> OnDevice:
        """A pass's output, with the :data:`~gpu_blur.testhooks.TEST_FAULT` hook applied."""
        result = OnDevice(array, shape, self._fetch)
        if fault_planted(pass_):
            host = planted_fault(pass_, result.numpy(), origin)
            wp.copy(array, wp.array(host.ravel().astype(self.np_real), device=self.wp_device))
        return result

    @staticmethod
    def _fetch(values: OnDevice, dtype) -> np.ndarray:
        with timer("copies"):
            count = int(np.prod(values.shape))
            host = values.data.numpy()[:count].reshape(values.shape)
            # a CPU array's numpy() is a view of memory freed with the array: always copy
            return host.astype(dtype, copy=values.data.device.is_cpu)

    def _source(self, frame: np.ndarray):
        """(numpy dtype, Warp dtype) a frame travels in: its codes, or the compute type."""
        return {np.dtype(np.uint8): (np.uint8, wp.uint8),
                np.dtype(np.uint16): (np.uint16, wp.uint16)}.get(
                    np.dtype(frame.dtype), (self.np_real, self.real))

    def _frame_stacks(self, frames: Sequence[np.ndarray], region: Region):
        """Yield (stack, count): device stacks of up to FRAMES_PER_LAUNCH frames of ``region``.

        Two stacks take turns. On CUDA with ``overlap``, a stack's frames go through a pinned
        host buffer and upload on the copy stream; the compute stream waits for that copy,
        and the next upload into the stack waits for the launch that read it (the caller
        launches before asking for the next stack). Elsewhere copies are synchronous.
        """
        np_dtype, wp_dtype = self._source(frames[0])
        per = min(FRAMES_PER_LAUNCH, len(frames))
        values = region.h * region.w * 3
        groups = [range(i, min(i + per, len(frames))) for i in range(0, len(frames), per)]
        stacks = [self._empty(per * values, wp_dtype) for _ in range(min(2, len(groups)))]
        compute = wp.get_stream(self.wp_device) if self.overlap else None
        read = [None] * len(stacks)  # event: the launch that last read each stack
        for c, group in enumerate(groups):
            slot = c % len(stacks)
            stack = stacks[slot]
            with timer("copies"):
                if self.overlap:
                    staging = self._staging_buffer(slot, per * values, wp_dtype)
                    fill_stack(staging.numpy(), frames, group, region)
                    if read[slot] is not None:
                        self._copier.wait_event(read[slot])
                    wp.copy(stack, staging, count=len(group) * values, stream=self._copier)
                    self._staged[slot] = self._copier.record_event()
                    compute.wait_event(self._staged[slot])
                elif self.wp_device == "cpu":
                    fill_stack(stack.numpy(), frames, group, region)  # host memory itself
                else:
                    host = np.empty(len(group) * values, dtype=np_dtype)
                    fill_stack(host, frames, group, region)
                    wp.copy(stack, wp.array(host, device="cpu"), count=host.size)
            yield stack, len(group)
            if self.overlap:
                read[slot] = compute.record_event()

    def _staging_buffer(self, slot: int, count: int, wp_dtype) -> wp.array:
        """Pinned host buffer ``slot`` for ``count`` values, once its last copy is done."""
        if slot in self._staged:
            wp.synchronize_event(self._staged.pop(slot))
        buffer = self._staging.get(slot)
        if buffer is None or buffer.dtype != wp_dtype or buffer.size < count:
            buffer = wp.empty(count, dtype=wp_dtype, device="cpu", pinned=True)
            self._staging[slot] = buffer
        return buffer

    def prefetch(self, frames: wp.array) -> Prefetched:
        """Start copying an ``n x H x W x 3`` stack of frames in pinned host memory to the device.

        The copy runs on the copy stream, beside whatever the device is computing (the
        previous sample's passes); :meth:`accumulate` takes the returned stack and waits for
        its copy first. Two device stacks take turns: a stack is reused (overwritten) by the
        prefetch after next, once the accumulate pass that read it is done. Without
        ``overlap`` the copy is synchronous into a new stack.
        """
        if not self.overlap:
            out = wp.empty(frames.shape, dtype=frames.dtype, device=self.wp_device)
            with timer("copies"):
                wp.copy(out, frames)
            return Prefetched(out, None)
        slot = self._prefetch_turn
        self._prefetch_turn ^= 1
        stack = self._prefetch_stacks.get(slot)
        if stack is None or stack.shape != frames.shape or stack.dtype != frames.dtype:
            stack = wp.empty(frames.shape, dtype=frames.dtype, device=self.wp_device)
            wp.synchronize_device(self.wp_device)  # allocated before the copy stream uses it
            self._prefetch_stacks[slot] = stack
        with timer("copies"):
            if slot in self._prefetch_read:
                self._copier.wait_event(self._prefetch_read.pop(slot))
            wp.copy(stack, frames, stream=self._copier)
            return Prefetched(stack, self._copier.record_event(), slot)

    @staticmethod
    def device_array(values: OnDevice) -> wp.array:
        """An output as an ``h x w x 3`` ``wp.array`` on the device (``torch.from_dlpack``)."""
        return values.data.reshape(values.shape)

    # -- pass 1: accumulate ------------------------------------------------------------------
    def _code_table(self, k: dict, source) -> wp.array:
        """The linear value of every 8-bit code, from these kernels' own ``linearize``.

        ``blur_average_add`` gathers from it instead of evaluating the EOTF per value: the
        same function of the same 256 codes, so the same bits. Made once per kernel set (so
        never inside a captured graph after a first run); a one-value placeholder when the
        frames are not 8-bit codes (the kernel does not read it).
        """
        key = (self.real, source)
        if key not in self._code_tables:
            count = 256 if source == wp.uint8 else 1
            table, indicator = self._empty(count), self._empty(count)
            if count == 256:
                codes = self._array(np.arange(256), np.uint8)
                with self._kernels():
                    self._launch(k["linearize"], count, codes, table, indicator)
            self._code_tables[key] = table
        return self._code_tables[key]

    def accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region: Region) -> tuple[OnDevice, OnDevice]:
        """Linearize and blur on the device; (linear, mask) over ``region``, on the device."""
        from gpu_blur.warp_kernels.passes import accumulate_kernels

        prefetched = frames if isinstance(frames, Prefetched) else None
        if prefetched is not None:
            if prefetched.ready is not None:
                wp.get_stream(self.wp_device).wait_event(prefetched.ready)
            frames = prefetched.frames
        stacked = isinstance(frames, wp.array)
        source = frames.dtype if stacked else self._source(frames[0])[1]
        k = accumulate_kernels(self.real, source)
        mode = plan.variant("blur") or "none"
        n = region.h * region.w * 3
        shape = (region.h, region.w, 3)
        linear, sat_mask = self._empty(n), self._empty(n)
        if mode == "average" and interpolation_factor(plan) > 1:
            self._interpolated_average(plan, params, frames, region, linear, sat_mask)
            return self._linear_out(linear, sat_mask, shape, region)
        if stacked:
            self._average_stack(k, plan, frames, region, linear, sat_mask,
                                self._code_table(k, source))
            if prefetched is not None and prefetched.slot is not None:  # the stack is free
                self._prefetch_read[prefetched.slot] = wp.get_stream(
                    self.wp_device).record_event()
            return self._linear_out(linear, sat_mask, shape, region)
        if mode == "average":
            # running compensated sums (sum, rounding errors, saturation counts) are only
            # needed between launches: one stack of frames is summed in registers
            sums = ((self._empty(n), self._empty(n), self._empty(n, wp.uint32))
                    if len(frames) > FRAMES_PER_LAUNCH
                    else (linear, sat_mask, self._empty(1, wp.uint32)))
            done, table = 0, self._code_table(k, source)
            for stack, count in self._frame_stacks(frames, region):
                last = done + count == len(frames)
                with self._kernels(sync=last):
                    self._launch(k["blur_average_add"], n, stack, count, n, *sums,
                                 int(done == 0), len(frames) if last else 0, linear, sat_mask,
                                 table)
                done += count
            return self._linear_out(linear, sat_mask, shape, region)
        if mode == "none":
            indicator = self._empty(n)
            source = self._array(region.of(frames[0]), self._source(frames[0])[0])
            with self._kernels():
                self._launch(k["linearize"], n, source, linear, indicator)
            del source
            given = (np.zeros(shape) if mask is None else region.of(mask))
            return (self._out(linear, shape, "accumulate", region.origin),
                    OnDevice(self._array(given), shape, self._fetch))
        view = region.expand(blur.blur_halo(mode, params, region.full_h, region.full_w))
        vn = view.h * view.w * 3
        src, indicator = self._empty(vn), self._empty(vn)
        source = self._array(view.of(frames[0]), self._source(frames[0])[0])
        with self._kernels(sync=False):
            self._launch(k["linearize"], vn, source, src, indicator)
        del source
        geometry = (view.x0, view.y0, view.w, region.full_w, region.full_h)
        grid = (region.h, region.w)
        if mode == "kernel":
            kernel = blur.normalize_kernel(params["kernel"])
            kw = self._array(kernel)
            kh, kwid = kernel.shape
            with self._kernels():
                for image, out in ((src, linear), (indicator, sat_mask)):
                    self._launch(k["blur_kernel"], grid, image, *geometry, kw, kh, kwid, out,
                                 region.x0, region.y0, region.w)
            return self._linear_out(linear, sat_mask, shape, region)
        # compensated sums of the image and of its indicator: (sum, compensation) each
        sums = [self._zeros(n) for _ in range(4)]
        hom = params["homographies"]
        inverses = [self._array(np.linalg.inv(h), np.float64) for h in hom]
        with self._kernels():
            for hinv in inverses:  # one pose at a time
                self._launch(k["blur_trajectory_add"], grid, src, indicator, *geometry, hinv,
                             *sums, region.x0, region.y0, region.w)
            self._launch(k["blur_trajectory_finish"], n, *sums, len(hom), linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _average_stack(self, k, plan: Plan, frames: wp.array, region: Region, linear,
                       sat_mask, table: wp.array) -> None:
        """Mode average over frames already in memory Warp reaches: one launch for them all.

        ``frames`` is an ``n x H x W x 3`` ``wp.array`` (uint8, uint16 or the compute type)
        on this device (no copy at all) or in pinned host memory (one asynchronous copy on the
        copy stream); whole images only.
        """
        if plan.variant("blur") != "average":
            raise ValueError("a wp.array stack of frames is for blur.mode = average")
        if frames.ndim != 4 or tuple(frames.shape[1:]) != (region.full_h, region.full_w, 3) \
                or (region.h, region.w) != (region.full_h, region.full_w):
            raise ValueError(f"a wp.array stack of frames must be n x H x W x 3 and run whole "
                             f"images (no tiles); got shape {frames.shape} for a "
                             f"{region.full_h} x {region.full_w} image")
        count, values = frames.shape[0], region.h * region.w * 3
        stack = frames.flatten()
        if str(frames.device) != str(wp.get_device(self.wp_device)):
            on_device = self._empty(count * values, frames.dtype)
            with timer("copies"):
                if self.overlap:
                    wp.copy(on_device, stack, stream=self._copier)
                    wp.get_stream(self.wp_device).wait_event(self._copier.record_event())
                else:
                    wp.copy(on_device, stack)
            stack = on_device
        spare = self._empty(1, wp.uint32)
        with self._kernels():
            self._launch(k["blur_average_add"], values, stack, count, values, linear, sat_mask,
                         spare, 1, count, linear, sat_mask, table)

    def _interpolated_average(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                              region: Region, linear, sat_mask) -> None:
        """Mode average at ``blur.interpolation`` times the frame rate, into linear, sat_mask.

        One gap at a time, in time order: frame i+1 and the gap's two flows upload over the
        region plus the flows' halo (frame i stays from the gap before), then the original
        frame and the intermediates after it join one set of compensated sums
        (gpu_blur/warp_kernels/interpolate.py); intermediate frames are never stored.
        """
        from gpu_blur.warp_kernels.interpolate import interpolate_kernels

        if isinstance(frames, wp.array):
            raise ValueError("blur.interpolation > 1 needs the frames in host memory (its "
                             "optical flows are computed there), not a wp.array stack")
        np_dtype, wp_dtype = self._source(frames[0])
        k = interpolate_kernels(self.real, wp_dtype)
        params = with_flows(plan, params, frames)
        flows, factor = params["flows"], interpolation_factor(plan)
        view = region.expand(blur.blur_halo("average", params, region.full_h, region.full_w))
        n = region.h * region.w * 3
        sums = (self._zeros(n), self._zeros(n), self._zeros(n))
        geometry = (view.x0, view.y0, view.w)
        out_geometry = (region.x0, region.y0, region.w)
        grid = (region.h, region.w)
        previous = None
        for i in range(len(frames)):
            current = self._array(view.of(frames[i]), np_dtype)
            gap = [self._array(view.of(f), np.float32) for f in flows[i - 1]] if i else []
            with self._kernels(sync=False):
                for step in range(1, factor if i else 1):
                    self._launch(k["blur_interpolate_add"], grid, previous, current, *gap,
                                 *geometry, region.full_w, region.full_h, step / factor,
                                 CONSISTENCY_RELATIVE, CONSISTENCY_ABSOLUTE_PX2, *sums,
                                 *out_geometry)
                self._launch(k["blur_interpolate_add_frame"], grid, current, *geometry, *sums,
                             *out_geometry)
            previous, gap = current, None  # frame i stays for the next gap; the flows go
        with self._kernels():
            self._launch(k["blur_interpolate_finish"], n, *sums, (len(frames) - 1) * factor + 1,
                         linear, sat_mask)

    def _linear_out(self, linear, sat_mask, shape, region: Region):
        """The accumulate pass's (linear, mask), left on the device."""
        return (self._out(linear, shape, "accumulate", region.origin),
                OnDevice(sat_mask, shape, self._fetch))

    # -- pass 2: to_raw ----------------------------------------------------------------------
    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear, mask,
               origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[OnDevice, OnDevice]:
        """Saturation to noisy RAW on the device (see NumpyBackend.to_raw)."""
        from gpu_blur.warp_kernels.passes import to_raw_kernel

        noise = plan["poisson_gaussian_noise"].options
        kernel = to_raw_kernel(
            self.real, plan.kept("saturate"), plan.kept("mosaic"),
            plan.kept("linear_to_camera") and plan["linear_to_camera"].options["clip"],
            plan.kept("poisson_gaussian_noise"), noise["sampler"] == "normal", plan.fast_math)
        h, w = linear.shape[:2]
        saturated = self._empty(h * w * 3)
        raw = self._empty(h * w) if plan.raw_round_trip else self._empty(1)
        key = key_from_seed(seed)
        r = self.np_real
        inputs = (self._array(linear), self._array(mask))
        matrix = self._constant(camera.linear_to_camera)
        with self._kernels():
            self._launch(
                kernel, (h, w), *inputs, origin[1], origin[0], w,
                r(params.get("alpha", 0.0)), matrix,
                cfa_bits(params.get("pattern")), r(params.get("red_gain", 1.0)),
                r(params.get("blue_gain", 1.0)), r(params.get("shot_noise_k", 1.0)),
                r(params.get("read_noise_std", 0.0)), r(noise["normal_above"]),
                wp.uint32(int(key[0])), wp.uint32(int(key[1])), wp.uint32(sample_index),
                saturated, raw)
        del inputs
        if not plan.raw_round_trip:
            return self._out(saturated, (h, w, 3), "to_raw", origin), OnDevice(
                saturated, (h, w, 3), self._fetch)
        return (self._out(raw, (h, w), "to_raw", origin),
                OnDevice(saturated, (h, w, 3), self._fetch))

    # -- pass 3: finish ----------------------------------------------------------------------
    def finish(self, plan: Plan, params: dict, camera: Camera, image, saturated, view: Region,
               out: Region, *, seed: int, sample_index: int) -> OnDevice:
        """Demosaic and finish on the device, over ``out`` (see NumpyBackend.finish)."""
        from gpu_blur.warp_kernels.passes import finish_kernel

        demosaic = plan["demosaic"].options if plan.raw_round_trip else None
        kernel = finish_kernel(
            self.real, demosaic["method"] if demosaic else "",
            bool(demosaic and demosaic["border"] == "zero"), bool(demosaic and demosaic["clip"]),
            plan.kept("tone"), plan.kept("gaussian_noise"), plan.kept("restore_saturated"),
            plan.retone_curve,
            plan["quantize"].options["bits"] if plan.kept("quantize") else 0, plan.fast_math)
        result = self._empty(out.h * out.w * 3)
        key = key_from_seed(seed)
        raw = image if plan.raw_round_trip else np.zeros(1)
        inputs = (self._array(raw), self._array(saturated))
        # the kernel takes both curves; the one the plan does not use is never read
        polynomial = plan.retone_polynomial(camera)
        constants = (self._constant(camera.camera_to_linear),
                     self._constant(np.zeros(1) if polynomial is None else polynomial),
                     self._constant(a7r3_lookup_table(plan["retone"].options["table_size"])
                                    / 255.0))
        with self._kernels():
            self._launch(
                kernel, (out.h, out.w), *inputs, view.x0, view.y0, view.w, view.full_w,
                view.full_h, out.x0, out.y0, out.w, cfa_bits(params.get("pattern")),
                constants[0], self.np_real(params.get("gaussian_std", 0.0)),
                wp.uint32(int(key[0])), wp.uint32(int(key[1])), wp.uint32(sample_index),
                constants[1], constants[2], result)
        return self._out(result, (out.h, out.w, 3), "finish", out.origin)

    def retone(self, plan: Plan, camera: Camera, image: np.ndarray) -> np.ndarray:
        """The output tone curve for the sharp reference (host side, float64)."""
        from gpu_blur.backends.numpy import NumpyBackend

        return NumpyBackend().retone(plan, camera, image)

