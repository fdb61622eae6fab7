"""The Warp backend: the plan's three passes as NVIDIA Warp kernels (gpu_blur/warp_kernels/).

The passes' host logic is :mod:`gpu_blur.backends.kernel`'s; this module holds the device,
buffers, streams, launching, and the choice of Warp kernels for a pass configuration.

Devices: ``warp`` (the first CUDA device if there is one, else the CPU), ``warp:cpu``,
``warp:cuda:N``. Only the stages a plan keeps are generated (``wp.static`` flags); float32 by
default, float64 on request. Random draws repeat :mod:`gpu_blur.reference.rng` bit for bit.
Pass outputs stay on the device between passes; :meth:`WarpBackend.device_array` gives the
result as a ``wp.array`` that ``torch.from_dlpack`` takes without a copy. Frames upload in their
stored dtype (8-bit frames: a quarter of a float32 copy), on CUDA from pinned host buffers on a
copy stream that overlaps the summing of the previous frames.
"""

from __future__ import annotations

import ctypes
import functools
import os
import sys
from collections.abc import Callable, Sequence

import numpy as np
import warp as wp

from gpu_blur import caches, notices
from gpu_blur.arrays import view_at
from gpu_blur.backends import OnDevice, copy_values, fill_stack, pinned_stack
from gpu_blur.backends.kernel import (
    Arg,
    KernelBackend,
    PassConfig,
    source_dtype,
)
from gpu_blur.planning import Pass, Plan, StageName
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

__all__ = ["DOWNLOAD_CHUNK", "Launches", "MAX_BUFFER_VALUES", "QUAD_VIEWS", "RECORDED_LAUNCHES",
           "ROW_TABLES", "ROW_TABLE_BYTES", "S", "WarpBackend", "warp_devices"]

S = StageName

wp.config.log_level = wp.LOG_WARNING  # no banner or per-module load lines
caches.set_warp_cache()  # a private kernel cache, before anything calls wp.init()

#: (kernel, device) pairs whose module this process has loaded (built or read from Warp's cache).
_LOADED: set = set()

#: The views of :meth:`WarpBackend._quads`, by a buffer's dtype: four values an element.
QUAD_VIEWS = {wp.uint8: wp.uint32, wp.float32: wp.vec4f, wp.float64: wp.vec4d}

#: Warp arrays have int32 shapes, and the kernels index with Warp ``int``: one buffer holds at
#: most this many values (an RGB region ~715 M pixels). OpenCL kernels index with 64 bits.
MAX_BUFFER_VALUES = 2**31 - 1

#: Values per piece of a download through pinned staging (:meth:`WarpBackend._download`):
#: 64 MB of float32: no slower than the whole result at once, and smaller pieces' thread
#: hand-offs cost more than the overlap gains (docs/performance.md#downloads).
DOWNLOAD_CHUNK = 1 << 24

#: Turns of the pinned ring that carries small tables (sample tables, kernel taps, a camera
#: path's poses) to a CUDA device, and the bytes of each (a larger table is copied directly).
ROW_TABLES = 64
ROW_TABLE_BYTES = 64 * 1024

#: Recorded launches a backend keeps (one per kernel and grid; the oldest goes first).
RECORDED_LAUNCHES = 64


class Launches:
    """Launches recorded once per (kernel, grid) and replayed with only the changed arguments.

    ``wp.launch`` packs every argument on every call (the passes have 20-odd); a sample's
    launches differ from the previous sample's in a few values (its draws, its buffers), so
    replaying a ``wp.Launch`` and re-packing those alone costs a fraction of it
    (docs/performance.md#launches). The same kernels run on the same arguments, so the same
    bits. Arrays are compared by what Warp packs of them (data pointer, shape, strides, dtype),
    reals by their bits, and no array is kept alive by a recorded launch.
    """

    def __init__(self, device: str):
        self.device = device
        self._recorded: dict = {}  # (kernel, grid) -> (wp.Launch, each argument's key)

    @staticmethod
    def _key(value):
        if isinstance(value, wp.array):
            return ("array", value.ptr, value.shape, value.strides, value.dtype)
        if isinstance(value, (float, np.floating)):  # by bits: -0.0 == 0.0, nan != nan
            return (type(value), np.asarray(value).tobytes())
        return (type(value), value)

    def launch(self, kernel, grid, inputs: list) -> None:
        """Launch ``kernel`` over ``grid`` on ``inputs`` (Warp's values) on the current stream."""
        keys = [self._key(v) for v in inputs]
        entry = self._recorded.pop((kernel, grid), None)
        if entry is None:
            if len(self._recorded) >= RECORDED_LAUNCHES:
                del self._recorded[next(iter(self._recorded))]
            command = wp.launch(kernel, dim=grid, inputs=inputs, device=self.device,
                                record_cmd=True)
            command.fwd_args = None  # what it packed are pointers: keep no array alive
        else:
            command, before = entry
            for i, (key, old) in enumerate(zip(keys, before, strict=True)):
                if key != old:
                    command.set_param_at_index(i, inputs[i])
        self._recorded[(kernel, grid)] = (command, keys)  # now the newest
        command.launch()


@functools.cache
def _init() -> None:
    """``wp.init()`` (once) without its notices on machines with no NVIDIA driver.

    Warp's native library prints "Warp CUDA warning: Could not find or load the NVIDIA CUDA
    driver" when there is none: on a CPU machine that is no news, so the process's standard
    output and error are closed to that one call (C's buffers flushed before they are opened
    again). Errors still raise (RuntimeError).
    """
    caches.set_warp_cache()  # checks the folder again: the caller may have set one since
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    saved = [os.dup(fd) for fd in (1, 2)]
    try:
        with open(os.devnull, "w") as devnull:
            for fd in (1, 2):
                os.dup2(devnull.fileno(), fd)
            try:
                wp.init()
            finally:
                ctypes.CDLL(None).fflush(None)
    finally:
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)


def warp_devices() -> list[dict]:
    """Warp's devices as ``gpu-blur devices`` lists them (memory: CUDA devices only)."""
    _init()
    found = []
    for d in wp.get_devices():
        memory = int(d.total_memory) if d.is_cuda else 0  # the CPU's needs psutil
        found.append({"spec": f"warp:{d.alias}", "name": d.name, "kind": "GPU" if d.is_cuda
                      else "CPU", "fp64": True, "memory_bytes": memory})
    return found


def _device(spec: str) -> str:
    _init()
    if spec == "warp":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    alias = spec.split(":", 1)[1]
    known = [d.alias for d in wp.get_devices()]
    if alias not in known:
        raise ValueError(f"no Warp device {spec!r}; present: "
                         + ", ".join(f"warp:{a}" for a in known))
    return alias


class WarpBackend(KernelBackend):
    """Runs a plan as Warp kernels on one device (see :mod:`gpu_blur.backends.kernel`).

    Args:
        spec: ``warp``, ``warp:cpu`` or ``warp:cuda:<n>``.
        precision: the kernels' compute type, ``float32`` or ``float64``.
        overlap: on CUDA, upload frames from pinned host buffers on a second stream while the
            previous stack of frames is summed (False: plain synchronous copies, to measure
            what the overlap gains; bench/generate_throughput.py).
    """

    name = "warp"
    device_arrays = True
    position_dtype = np.float64

    def __init__(self, spec: str = "warp", precision: str = "float32", *, overlap: bool = True):
        super().__init__()
        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be float32 or float64, got {precision!r}")
        self.wp_device = _device(spec)
        self.precision = precision
        self.real = wp.float64 if precision == "float64" else wp.float32
        self.np_real = np.float64 if precision == "float64" else np.float32
        device = wp.get_device(self.wp_device)
        self.device = f"warp:{self.wp_device} {device.name}, {precision}"
        self.model = f"warp {device.name}, {precision}"
        self.overlap = bool(overlap and device.is_cuda)
        self._copier = wp.Stream(self.wp_device) if self.overlap else None
        self._staging: dict = {}  # slot -> pinned host buffer (kept across samples)
        self._staged: dict = {}  # slot -> event: the last copy out of that staging buffer
        self._row_ring = None  # pinned host bytes: ROW_TABLES turns of ROW_TABLE_BYTES
        self._rows_turn = 0  # the turn that carries the next small table
        self._row_copies: dict = {}  # turn -> event: the copy out of its bytes
        self._launches = Launches(self.wp_device)

    @property
    def uses_cuda(self) -> bool:
        """Whether the device is a CUDA GPU."""
        return self.wp_device.startswith("cuda")

    # -- kernels -----------------------------------------------------------------------------
    def _pass_kernels(self, config: PassConfig, source=None, interpolate: bool = False):
        """The Warp kernels of ``config``, by name (the factories read their flags from it)."""
        from gpu_blur.warp_kernels.interpolate import interpolate_kernels
        from gpu_blur.warp_kernels.passes import accumulate_kernels, finish_kernel, to_raw_kernel

        if config.pass_ == Pass.ACCUMULATE:
            factory = interpolate_kernels if interpolate else accumulate_kernels
            return factory(self.real, self._wp_dtype(source))
        if config.pass_ == Pass.TO_RAW:
            return {"to_raw": to_raw_kernel(self.real, config)}
        return {"finish": finish_kernel(self.real, config)}

    def _input_kernels(self, config: PassConfig | None, source):
        """Warp's kernels over stored input images.

        ``inspect``, ``unit_values`` (and ``to_codes`` for 8/16-bit codes,
        ``unit_values_codes`` for 8-bit ones) with ``config`` None, else ``render_sharp``
        built for ``config`` (and ``gather_codes`` for codes).
        """
        from gpu_blur.warp_kernels import inputs

        source = self._wp_dtype(source)
        if config is None:
            kernels = {"inspect": inputs.inspect_kernel(source),
                       "unit_values": inputs.unit_values_kernel(self.real, source)}
            if source in (wp.uint8, wp.uint16):
                kernels["to_codes"] = inputs.to_codes_kernel(self.real, source)
            if source == wp.uint8:
                kernels["unit_values_codes"] = inputs.unit_values_codes_kernel(self.real)
            return kernels
        kernels = {"render_sharp": inputs.render_sharp_kernel(self.real, source, config)}
        if source != self.real:
            kernels["gather_codes"] = inputs.gather_codes_kernel(self.real, source)
        return kernels

    def _launch(self, kernels, name: str, grid, *args) -> None:
        inputs = [self._render(a) for a in args if not (isinstance(a, Arg) and a.extent)]
        kernel = kernels[name]
        if (kernel, self.wp_device) not in _LOADED:  # the first launch compiles or loads it
            with notices.building(f"the {name} kernel", f"warp:{self.wp_device}"):
                wp.load_module(kernel.module, device=self.wp_device)
            _LOADED.add((kernel, self.wp_device))
        self._launches.launch(kernel, grid, inputs)

    def _render(self, arg):
        """A kernel argument as Warp takes it (:class:`~gpu_blur.backends.kernel.Arg`)."""
        if not isinstance(arg, Arg):
            return arg
        if arg.kind == "real":
            return self.np_real(arg.value)
        if arg.kind == "position":
            return float(arg.value)
        return int(arg.value)  # index, int and uint: Warp converts to the declared type

    def _timed(self, sync: bool = True):
        """Time launches as "kernels"; ``sync`` waits for them (``wp.synchronize_device``).

        With ``sync_passes`` False nothing waits (the timings then hold launch times only),
        so the passes can be captured in a CUDA graph (bench/gpu_targets.py).
        """
        return timer("kernels", self._synchronize if sync and self.sync_passes else None)

    def wait(self) -> None:
        """Wait for every launch and copy queued so far."""
        self._synchronize()

    def wait_for(self, stream: wp.Stream | None) -> None:
        """Launches and copies queued from now on wait for the work queued on ``stream``."""
        if stream is not None:
            wp.get_stream(self.wp_device).wait_stream(stream)

    def hand_to(self, stream: wp.Stream) -> None:
        """Work queued on ``stream`` from now on waits for what this backend queued so far.

        Results handed over on the device: the caller's stream, not the host, waits.
        """
        stream.wait_stream(wp.get_stream(self.wp_device))

    def _synchronize(self) -> None:
        if self.overlap:  # the compute stream only: an upload may still be copying
            wp.synchronize_stream(wp.get_stream(self.wp_device))
        else:
            wp.synchronize_device(self.wp_device)

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

    def _wp_dtype(self, dtype):
        return self.real if dtype is None else wp.dtype_from_numpy(np.dtype(dtype))

    def _quads(self, buffers, n: int) -> tuple | None:
        """Views of the same memory: 8-bit codes as 32-bit words, reals as 4-vectors.

        See :meth:`KernelBackend._quads`; None unless each buffer is of a type in
        :data:`QUAD_VIEWS`, contiguous, on a boundary of its view's size (at most 16 bytes).
        """
        if n % 4:
            return None
        views = []
        for buffer in buffers:
            dtype = QUAD_VIEWS.get(buffer.dtype)
            if dtype is None:
                return None
            size = wp.types.type_size_in_bytes(dtype)
            if buffer.ptr % min(size, 16) or not buffer.is_contiguous:
                return None
            nbytes = buffer.size * wp.types.type_size_in_bytes(buffer.dtype)
            views.append(wp.array(ptr=buffer.ptr, dtype=dtype, shape=(nbytes // size,),
                                  device=buffer.device))
        return tuple(views)

    def _upload(self, values, dtype=None) -> wp.array:
        if isinstance(values, OnDevice):
            return values.data
        self._check_size(int(np.size(values)))
        with timer("copies"):
            data = np.ascontiguousarray(np.ravel(values), dtype=dtype or self.np_real)
            return wp.array(data, device=self.wp_device)

    def _zeros(self, count: int, dtype=None) -> wp.array:
        self._check_size(count)
        return wp.zeros(max(count, 1), dtype=self._wp_dtype(dtype), device=self.wp_device)

    def _empty(self, count: int, dtype=None) -> wp.array:
        self._check_size(count)
        return wp.empty(max(count, 1), dtype=self._wp_dtype(dtype), device=self.wp_device)

    def _rows(self, table: np.ndarray) -> wp.array:
        """A small table on the device; on CUDA through a ring of pinned host memory.

        ``wp.array(host)`` copies from pageable memory, which waits for every launch queued
        before it: the host would stop at each batched pass and each sample's kernel taps.
        From pinned memory the copy is queued like a launch; a turn of the ring is refilled
        once its copy is done.
        """
        table = np.ascontiguousarray(table)
        with timer("copies"):
            if not (self.uses_cuda and self.overlap) or table.nbytes > ROW_TABLE_BYTES:
                return wp.array(table, device=self.wp_device)
            if self._row_ring is None:  # one pinned allocation for every turn (they are slow)
                self._row_ring = wp.empty(ROW_TABLES * ROW_TABLE_BYTES, dtype=wp.uint8,
                                          device="cpu", pinned=True)
            turn = self._rows_turn
            self._rows_turn = (turn + 1) % ROW_TABLES
            if turn in self._row_copies:  # the copy out of this turn's bytes is done
                wp.synchronize_event(self._row_copies.pop(turn))
            dtype = wp.dtype_from_numpy(table.dtype)
            staging = wp.array(ptr=self._row_ring.ptr + turn * ROW_TABLE_BYTES, dtype=dtype,
                               shape=table.shape, device="cpu")
            staging.numpy()[...] = table
            rows = wp.empty(table.shape, dtype=dtype, device=self.wp_device)
            wp.copy(rows, staging)
            self._row_copies[turn] = wp.get_stream(self.wp_device).record_event()
            return rows

    @staticmethod
    def _slots(slots) -> tuple:
        buffer, size = slots.buffer, slots.count * slots.stride
        if buffer.size != size:  # (slicing a wp.array costs tens of microseconds)
            buffer = buffer[:size]
        return (buffer.reshape((slots.count, slots.stride)),)

    def _write(self, buffer, values: np.ndarray) -> None:
        with timer("copies"):
            wp.copy(buffer, wp.array(np.ravel(values), dtype=buffer.dtype, device="cpu"))

    @staticmethod
    def _fetch(values: OnDevice, dtype) -> np.ndarray:
        with timer("copies"):
            count = int(np.prod(values.shape))
            host = values.data.numpy()[:count].reshape(values.shape)
            # a CPU array's numpy() is a view of memory freed with the array: always copy
            return host.astype(dtype, copy=values.data.device.is_cpu)

    def _fetch_queued(self, buffer: wp.array, into: np.ndarray) -> Callable[[], None]:
        wp.copy(self._host_view(into), buffer, count=into.size)
        if not wp.get_device(self.wp_device).is_cuda:
            return lambda: None  # the CPU device copied it already
        copied = wp.get_stream(self.wp_device).record_event()
        return lambda: wp.synchronize_event(copied)

    def _frame_stacks(self, frames: Sequence[np.ndarray], region: Region):
        """Yield (stack, count): device stacks of up to FRAMES_PER_LAUNCH frames of ``region``.

        Two stacks take turns. On CUDA with ``overlap``, a stack's frames go through a pinned
        host buffer and upload on the copy stream; the compute stream waits for that copy,
        and the next upload into the stack waits for the launch that read it (the caller
        launches before asking for the next stack). Elsewhere copies are synchronous.
        """
        np_dtype = source_dtype(frames[0], self.np_real)
        wp_dtype = self._wp_dtype(np_dtype)
        per, values, groups, stacks = self._stacks_for(frames, region, np_dtype)
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

    @staticmethod
    def device_array(values: OnDevice) -> wp.array:
        """An output as an ``h x w x 3`` ``wp.array`` on the device (``torch.from_dlpack``)."""
        return values.data.reshape(values.shape)

    # -- inputs Warp reaches: wp.arrays (this device, pinned host memory) ----------------------
    def put(self, image) -> OnDevice:
        """:meth:`KernelBackend.put`; a ``wp.array`` on this device is taken as it is (no copy).

        A ``wp.array`` elsewhere (pinned host memory) is copied once, on the copy stream when
        overlapping.
        """
        if not isinstance(image, wp.array):
            stack = pinned_stack(image, self)  # frames staged in this backend's pinned memory
            if stack is not None:
                image = stack
            if self._direct(image):
                return self._put_pinned(image)
            if not self.overlap:
                return super().put(image)
            return self._put_through_staging(image)
        if not image.is_contiguous:
            raise ValueError(f"a wp.array input must be contiguous; got strides {image.strides} "
                             f"for shape {image.shape}: pass a contiguous copy")
        dtype = np.dtype(wp.dtype_to_numpy(image.dtype))
        if dtype not in (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(self.np_real)):
            raise ValueError(f"a wp.array input must hold uint8, uint16 or {self.precision} "
                             f"values (this backend's precision); got {dtype}")
        flat = image.flatten()
        if str(image.device) != str(wp.get_device(self.wp_device)):
            on_device = self._copy_target(flat.size, dtype)
            with timer("copies"):
                if self.overlap:
                    wp.copy(on_device, flat, stream=self._copier)
                    wp.get_stream(self.wp_device).wait_event(self._copier.record_event())
                else:
                    wp.copy(on_device, flat)
            flat = on_device
        return self._input(flat, image.shape, dtype)

    def _put_through_staging(self, image) -> OnDevice:
        """A host input to CUDA: copied by threads into a pinned buffer, then on the copy stream.

        ``image``: an array, or a list of frames (copied one after another into the buffer:
        no stacked host copy). Two pinned buffers take turns, so filling one overlaps the
        other's upload; the compute stream waits for the upload before any launch reads it.
        """
        parts, shape, dtype, count, slot = self._staged_parts(image)
        self._check_size(count)
        with timer("copies"):
            staging = self._staging_buffer(slot, count, self._wp_dtype(dtype))
            self._fill_staging(staging.numpy(), parts)
            data = self._copy_target(count, dtype)
            wp.copy(data, staging, count=count, stream=self._copier)
            self._staged[slot] = self._copier.record_event()
            wp.get_stream(self.wp_device).wait_event(self._staged[slot])
        return self._input(data, shape, dtype)

    def _put_pinned(self, image: np.ndarray) -> OnDevice:
        """A host input in this backend's :meth:`pinned` memory: one copy, no staging.

        On the copy stream with ``overlap`` (the compute stream waits for it). In a batch
        (``sync_passes`` off) the copy is only queued, and the caller waits for it before
        ``image`` may change (the Synthesizer waits for its batch); otherwise it is done on
        return.
        """
        count = image.size
        self._check_size(count)
        with timer("copies"):
            data = self._copy_target(count, image.dtype)
            source = self._host_view(image)
            if self.overlap:
                wp.copy(data, source, count=count, stream=self._copier)
                copied = self._copier.record_event()
                wp.get_stream(self.wp_device).wait_event(copied)
                if self.sync_passes:
                    wp.synchronize_event(copied)
            else:
                wp.copy(data, source, count=count)
        return self._input(data, image.shape, image.dtype)

    def _copy_target(self, count: int, dtype) -> wp.array:
        """A device buffer for the copy stream to fill (with ``overlap``), allocated there.

        Device memory is stream-ordered: a block freed on the compute stream may be handed at
        once to the next allocation on that stream, while launches queued before the free
        still read it, and the copy stream, which does not wait for them, would overwrite it.
        Allocated on the copy stream, a block comes back only once its release is done.
        """
        if not self.overlap:
            return self._empty(count, dtype)
        with wp.ScopedStream(self._copier, sync_enter=False):
            return self._empty(count, dtype)

    def _host_view(self, x: np.ndarray) -> wp.array:
        """A flat ``wp.array`` over the contiguous host array ``x`` (no copy)."""
        return wp.array(ptr=x.ctypes.data, dtype=self._wp_dtype(x.dtype), shape=(x.size,),
                        device="cpu")

    def _pinned_bytes(self, nbytes: int) -> tuple:
        # page-locked where a CUDA device copies it; on the CPU device plain memory serves
        pinned = wp.get_device(self.wp_device).is_cuda
        buffer = wp.empty(nbytes, dtype=wp.uint8, device="cpu", pinned=pinned)
        return buffer, buffer.ptr

    def accumulate(self, plan: Plan, params: dict, frames, mask, region: Region
                   ) -> tuple[OnDevice, OnDevice]:
        """Linearize and blur on the device; (linear, mask) over ``region``, on the device.

        Besides host frames and inputs put on the device (:meth:`KernelBackend.accumulate`),
        takes a ``wp.array`` (an ``n x H x W x 3`` stack for mode average).
        """
        if isinstance(frames, wp.array):
            frames = self.put(frames)
        return super().accumulate(plan, params, frames, mask, region)

    slot_views = True

    @staticmethod
    def _view(buffer, start: int, count: int) -> wp.array:
        return buffer if start == 0 and count == buffer.size else buffer[start:start + count]

    def _gap(self, first, second) -> int | None:
        if not (isinstance(first, wp.array) and isinstance(second, wp.array)
                and first.is_contiguous and second.is_contiguous
                and first.dtype == second.dtype and first.size == second.size
                and first.device == second.device):
            return None
        item = wp.types.type_size_in_bytes(first.dtype)
        step = second.ptr - first.ptr
        return step // item if step >= first.size * item and step % item == 0 else None

    def _spaced_data(self, buffers: Sequence) -> tuple[wp.array, int] | None:
        """One view from the first buffer's start over all of them, and their spacing.

        Pointers alone say the buffers are evenly spaced, not that they lie in one
        allocation: two separate ones also have a spacing, which may be anything. The view
        is only read at the buffers' own values, but its span must stay within the kernels'
        int32 indices (:data:`MAX_BUFFER_VALUES`): beyond it, None (the caller reads each
        buffer on its own).
        """
        first = buffers[0]
        stride = self._gap(first, buffers[1]) if len(buffers) > 1 else None
        if len(buffers) > 1 and stride is None:
            return None
        if stride is None:  # one buffer
            if not (isinstance(first, wp.array) and first.is_contiguous):
                return None
            stride = first.size
        if any(self._gap(a, b) != stride for a, b in zip(buffers[:-1], buffers[1:], strict=True)):
            return None
        span = (len(buffers) - 1) * stride + first.size
        if span > MAX_BUFFER_VALUES:
            return None
        return view_at(first.ptr, first.dtype, (span,), list(buffers)), stride

    @staticmethod
    def _part(buffer, start: int, count: int, dtype) -> wp.array:
        return WarpBackend._view(buffer, start, count)

    @staticmethod
    def _copy(into, values, count: int, offset: int = 0) -> None:
        wp.copy(into, values, dest_offset=offset, count=count)

    @staticmethod
    def _fill_zeros(buffer, count: int) -> None:
        buffer[:count].zero_()

    def export(self, values: OnDevice, region: Region, into) -> None:
        """Copy ``region`` of a whole-image result into ``into``.

        ``into``: a host array, or a ``wp.array`` of the compute type on this device (one
        strided copy, no trip through the host).
        """
        whole = values.data.reshape(values.shape)
        part = whole[region.y0:region.y0 + region.h, region.x0:region.x0 + region.w]
        if isinstance(into, wp.array):
            with timer("copies"):
                wp.copy(into, part)
            return None
        direct = self._direct(into, values.dtype or self.np_real) and into.size == part.size
        if not (self.overlap or direct):
            return super().export(values, region, into)
        with timer("copies"):
            if not part.is_contiguous:
                part = wp.clone(part)
            if direct:  # into pinned memory: straight from the device
                wp.copy(self._host_view(into), part.flatten(), count=part.size)
                if self.sync_passes:  # else the batch's caller waits (Synthesizer)
                    self._synchronize()
            else:
                self._download(part.flatten(), into)
        return None

    def _download(self, flat: wp.array, into: np.ndarray) -> None:
        """Contiguous device values into host ``into`` through two pinned buffers in turn.

        The device copies chunk i + 1 (:data:`DOWNLOAD_CHUNK` values) while threads copy
        chunk i out, so a large result leaves at about the slower of the two rates instead of
        their sum. Waits for these copies only: launches queued after them run on.
        """
        n = flat.size
        if n == 0:
            return
        chunk = DOWNLOAD_CHUNK if into.flags.c_contiguous else n  # a strided into: one piece
        stream = wp.get_stream(self.wp_device)
        pending = None
        for i, start in enumerate(range(0, n, chunk)):
            size = min(chunk, n - start)
            staging = self._staging_buffer(("export", flat.dtype, i % 2), size, flat.dtype)
            wp.copy(staging, flat, src_offset=start, count=size)
            ready = stream.record_event()
            if pending is not None:
                self._copied_out(into, *pending)
            pending = (staging, ready, start, size)
        self._copied_out(into, *pending)

    @staticmethod
    def _copied_out(into: np.ndarray, staging: wp.array, ready, start: int, size: int) -> None:
        """Values ``start .. start + size`` of a download, in ``staging`` once ``ready``."""
        wp.synchronize_event(ready)
        values = staging.numpy()[:size]
        if size == into.size:
            copy_values(into, values)
        else:
            copy_values(into.reshape(-1)[start:start + size], values)
