"""Backends: how a plan runs. One protocol (:class:`Backend`), three implementations.

A backend carries out the plan's three passes under the stages' names, on the whole image or
on a region (a tile with its halo); :class:`Backend` lists what every backend offers and every
caller uses. ``numpy`` is the float64 reference (:mod:`gpu_blur.backends.numpy`); ``opencl``
and ``warp`` share one kernel backend (:mod:`gpu_blur.backends.kernel`) and differ only in
devices, buffers, launching and how a pass configuration becomes a kernel build.

Frames come as stored (:func:`gpu_blur.image_arrays.check_image`: uint8/uint16 codes or float64 in
[0, 1]). Kernel backends return their outputs as :class:`OnDevice` arrays, which the next pass
takes without a copy; ``np.asarray`` (or ``.numpy()``) brings one to the host as float64. The
numpy backend returns numpy arrays. Any pass also takes host arrays.

Names: ``numpy`` (float64 reference), ``opencl`` (a GPU, else Intel's CPU runtime, else
PoCL: ``opencl.best_device``), ``opencl:<platform>:<device>``, ``warp`` (CUDA if present,
else the CPU), ``warp:cpu``, ``warp:cuda:<n>``.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, NamedTuple, Protocol, runtime_checkable

import numpy as np

from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.reference.bayer import BayerPattern

if TYPE_CHECKING:
    from gpu_blur.cameras import Camera
    from gpu_blur.planning import Plan
    from gpu_blur.tiling import Region

__all__ = ["Backend", "COPY_THREADS", "Drawn", "FRAMES_PER_LAUNCH", "OnDevice",
           "PARALLEL_COPY_VALUES", "PinnedHost", "ResidentBackend", "Slots", "cfa_bits",
           "copy_values", "fill_stack", "get_backend", "is_resident", "pinned_owner",
           "pinned_stack", "to_host", "usable_devices"]

#: Frames summed per accumulate launch (blur mode average) on the kernel backends: a device
#: stack of this many frames fills (on a GPU, on a copy stream, while the previous stack is
#: summed on the compute stream) and one launch adds them to the running sums in registers.
#: Two stacks live at once (gpu_blur.scheduler's memory formula counts them).
FRAMES_PER_LAUNCH = 4


@runtime_checkable
class Backend(Protocol):
    """What every backend offers (numpy, OpenCL, Warp) and every caller uses.

    Attributes:
        name: the backend's family, ``numpy``, ``opencl`` or ``warp``.
        precision: the compute type, ``float32`` or ``float64``.
        device: the device in words, with its number on this host (``warp:cuda:1 NVIDIA
            H200, float32``): what a run opened (``run.json``, logs).
        model: the backend, device model and precision without that number (``warp NVIDIA
            H200, float32``): what decides a result's bits, so what a set's manifest line
            names (``Synthesis.device``; the same line whichever GPU of a model made it).
        uses_cuda: whether it runs on an NVIDIA GPU through CUDA's driver (Ray's GPU
            resource, gpu_blur.distributed).
        device_arrays: whether :meth:`device_array` gives a result as a device array other
            libraries take (Warp: ``torch.from_dlpack``), for ``synthesize(on_device=True)``.
    """

    name: str
    precision: str
    device: str
    model: str
    uses_cuda: bool
    device_arrays: bool

    def accumulate(self, plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region):
        """Linearize and blur: (linear, saturation mask) over ``region``.

        Frames are sent to the device a few at a time (never all in device memory at once).
        """

    def to_raw(self, plan, params: dict, camera, linear, mask, origin: tuple[int, int] = (0, 0),
               *, seed: int, sample_index: int):
        """Saturation to the noisy white-balanced RAW mosaic: (image, saturated)."""

    def finish(self, plan, params: dict, camera, image, saturated, view, out, *, seed: int,
               sample_index: int):
        """Demosaic to the final (quantized) image over the ``out`` region."""

    def device_array(self, values):
        """A result as the device holds it (see ``device_arrays``)."""


class Slots(NamedTuple):
    """A batch's device buffer: ``count`` slots ``stride`` values apart, one per sample.

    Made by :meth:`ResidentBackend.slots`; sample b's values start at ``b * stride``
    (:meth:`ResidentBackend.slot_image`).
    """

    buffer: object
    count: int
    stride: int


class Drawn(NamedTuple):
    """One sample of a batched to_raw or finish launch.

    Attributes:
        params: its drawn values (:func:`gpu_blur.params.draw_params`).
        sample_index: its index (with the seed, its random stream).
        slot: its row in the batch's buffers.
    """

    params: dict
    sample_index: int
    slot: int


class ResidentBackend(Backend, Protocol):
    """A backend that keeps a batch on its device: what the synthesis layer calls on one.

    The kernel backends (:class:`gpu_blur.backends.kernel.KernelBackend`, OpenCL and Warp)
    follow it; the device-resident path (``gpu_blur.synthesis.resident``) and the host path's
    device rendering are written against it, never against a concrete backend
    (tests/backends/test_backends_protocol.py holds both to it). Images on the device are
    :class:`OnDevice`; a batch's buffers are :class:`Slots`, one slot per sample.

    Attributes:
        sync_passes: whether each pass waits for its launches; a resident batch sets it False
            to queue every launch back to back, and True again after.
        wp_device: the Warp device (``cuda:0``, ``cpu``) on Warp, else None; a caller's
            array on it is taken where it lies (``device_arrays``).
    """

    sync_passes: bool
    wp_device: str | None

    def put(self, image) -> OnDevice:
        """An input as stored on the device: ``H x W x 3``, ``n x H x W x 3`` or a frame list."""

    def frame(self, stack: OnDevice, index: int) -> OnDevice:
        """Frame ``index`` (``H x W x 3``) of an ``n x H x W x 3`` stack :meth:`put` there."""

    def slots(self, count: int, values: int) -> Slots:
        """A new batch buffer of ``count`` slots of ``values`` compute-type values each."""

    def slot_image(self, slots: Slots, b: int, shape) -> OnDevice:
        """Slot ``b`` of a batch buffer as an image of ``shape`` (a view, or a device copy)."""

    def stacked(self, slots: Slots, shape) -> OnDevice:
        """Every slot of a batch buffer as one ``count x shape`` stack, no copy."""

    def export(self, values: OnDevice, region: Region, into) -> None:
        """Copy ``region`` (rows, columns) of a device image into ``into``, a host array."""

    def codes_buffer(self, count: int, bits: int):
        """A kept device buffer for ``count`` codes of ``bits`` (8 or 16) bits."""

    def to_codes(self, values: OnDevice, bits: int, into=None) -> OnDevice:
        """Device values in [0, 1] as their uint8 (``bits`` 8) or uint16 (16) codes there."""

    def inspect_queued(self, images: Sequence[OnDevice]) -> Callable[[], np.ndarray]:
        """The input checks' launches, queued; returns what reads their counts, a row each."""

    def accumulate_batch(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                         inputs: Sequence[tuple[OnDevice, OnDevice | None]], linear: Slots,
                         sat_mask: Slots) -> Slots:
        """Pass 1 of every sample into its ``h x w x 3`` slot; returns the masks' slots."""

    def to_raw_batch(self, plan: Plan, camera: Camera, samples: Sequence[Drawn], linear: Slots,
                     mask: Slots, saturated: Slots, raw: Slots, origin: tuple[int, int],
                     size: tuple[int, int], *, seed: int) -> None:
        """Pass 2 of samples of one plan in one launch: ``saturated`` and ``raw`` slots."""

    def finish_batch(self, plan: Plan, camera: Camera, samples: Sequence[Drawn], raw: Slots,
                     saturated: Slots, view: Region, out: Region, result: Slots, *,
                     seed: int) -> None:
        """Pass 3 of samples of one plan in one launch: ``out.h x out.w x 3`` results."""

    def render_sharp(self, plan: Plan, camera: Camera, image: OnDevice, out: Region,
                     into: tuple[Slots, int] | None = None) -> OnDevice:
        """The sharp reference over ``out`` (``out.h x out.w x 3``), rendered on the device."""

    def render_sharp_batch(self, plans: Sequence[Plan], camera: Camera,
                           images: Sequence[OnDevice], out: Region, into: Slots) -> None:
        """:meth:`render_sharp` of every sample b's ``images[b]`` into slot b of ``into``."""

    def pinned(self, shape, dtype=np.float32) -> np.ndarray:
        """An uninitialized host array of ``shape`` in page-locked memory it copies directly."""

    def wait(self) -> None:
        """Wait for every launch and copy queued so far."""

    def wait_for(self, stream) -> None:
        """Launches and copies queued from now on wait for the work queued on ``stream``."""

    def hand_to(self, stream) -> None:
        """Work queued on ``stream`` from now on waits for what this backend queued so far."""


def is_resident(backend) -> bool:
    """Whether ``backend`` is a kernel backend, a :class:`ResidentBackend`."""
    from gpu_blur.backends.kernel import KernelBackend

    return isinstance(backend, KernelBackend)


def to_host(values, dtype=np.float64) -> np.ndarray:
    """A pass's output on the host: :class:`OnDevice` downloaded, host arrays as they are."""
    if isinstance(values, OnDevice):
        return values.numpy(dtype)
    return np.asarray(values, dtype=dtype)


#: Values below which :func:`copy_values` copies in one piece (threads cost more than they
#: gain on small arrays).
PARALLEL_COPY_VALUES = 1 << 20


#: Most threads :func:`copy_values` copies on. One H200 host (16 cores, the device tool)
#: copied pageable numpy into pinned memory at 21, 35, 45 and 48 GB/s on 4, 8, 12 and 16
#: threads: a copy is bound by cores long before the memory's bandwidth.
COPY_THREADS = 16


@functools.cache
def _copy_threads():
    """(a thread pool, its size) for :func:`copy_values`: the host's cores, at most 16."""
    import concurrent.futures
    import os

    workers = min(COPY_THREADS, os.cpu_count() or 1)
    return concurrent.futures.ThreadPoolExecutor(workers, "gpu_blur-copy"), workers


def copy_values(into: np.ndarray, values) -> None:
    """``into[...] = values``: same size, any shapes, converted to ``into``'s dtype.

    ``values``: an array, or a list of arrays copied one after another (a sample's frames
    into one staging buffer). Large copies go in slices on up to :data:`COPY_THREADS`
    threads, all queued before the one wait: numpy copies without holding the GIL, so a
    copy to or from pinned staging memory runs at several cores' rate, and the caller
    wakes once however many parts there are. A strided ``into`` (a channels-first ``out=``
    array's view) takes one copy of one array in its own layout.
    """
    if not into.flags.c_contiguous:  # its reshape(-1) would be a copy, and the values lost
        np.copyto(into, np.reshape(values, into.shape), casting="same_kind")
        return
    dst = into.reshape(-1)
    sources = [np.ascontiguousarray(v).reshape(-1)
               for v in (values if isinstance(values, list) else [values])]
    pool, workers = _copy_threads()
    if dst.size < PARALLEL_COPY_VALUES or workers == 1:
        start = 0
        for src in sources:
            np.copyto(dst[start:start + src.size], src, casting="same_kind")
            start += src.size
        return
    slices = -(-workers // len(sources))  # per source, so the threads share every source
    parts, start = [], 0
    for src in sources:
        edges = np.linspace(0, src.size, slices + 1).astype(int)
        parts += [pool.submit(np.copyto, dst[start + a:start + b], src[a:b],
                              casting="same_kind")
                  for a, b in zip(edges[:-1], edges[1:], strict=True)]
        start += src.size
    for part in parts:
        part.result()


class PinnedHost:
    """Page-locked host memory a kernel backend allocated (:meth:`KernelBackend.pinned`).

    numpy arrays made over it end their ``.base`` chain here (:func:`pinned_owner`), so the
    backend that made it copies them to and from its device directly, with no staging copy.
    Holds the allocation (``keep``) for as long as any such array lives.
    """

    def __init__(self, owner, keep, address: int, nbytes: int):
        self.owner, self._keep = owner, keep
        self.__array_interface__ = {"shape": (nbytes,), "typestr": "|u1",
                                    "data": (address, False), "version": 3}


def pinned_owner(x):
    """The backend whose :class:`PinnedHost` memory ``x`` (a numpy array) lies in, else None."""
    base = x
    while isinstance(base, np.ndarray):
        base = base.base
    return base.owner if isinstance(base, PinnedHost) else None


def pinned_stack(frames, owner) -> np.ndarray | None:
    """Frames lying one after another in ``owner``'s pinned memory, as one stack; else None.

    ``frames``: a list of arrays of one shape and dtype, each C-contiguous, frame ``i`` at
    frame 0's address plus ``i`` frames' bytes, all in one :class:`PinnedHost` block of
    ``owner`` (the views of a stack made there, as ``gpu-blur generate``'s I/O threads stage
    a sample's frames): an ``n x H x W x 3`` view of that memory, which ``owner`` copies to
    its device at once. Anything else (other memory, gaps, another order): None.
    """
    if not isinstance(frames, (list, tuple)) or not frames or not all(
            isinstance(f, np.ndarray) for f in frames):
        return None
    first = frames[0]
    if any(f.shape != first.shape or f.dtype != first.dtype or not f.flags.c_contiguous
           for f in frames) or pinned_owner(first) is not owner:
        return None
    start, size = first.ctypes.data, first.nbytes
    if any(f.ctypes.data != start + i * size for i, f in enumerate(frames)):
        return None
    block = first
    while isinstance(block.base, np.ndarray):  # the array over the whole PinnedHost block
        block = block.base
    offset = start - block.ctypes.data
    if offset < 0 or offset + len(frames) * size > block.nbytes:
        return None
    flat = block.reshape(-1).view(np.uint8)
    return flat[offset:offset + len(frames) * size].view(first.dtype).reshape(
        (len(frames), *first.shape))


def fill_stack(host: np.ndarray, frames, indices: range, region) -> None:
    """Write ``region`` of frames ``indices`` one after another into the flat array ``host``.

    Frames are read one at a time (``frames[i]``) and dropped once copied, so a lazy sequence
    never has more than one frame alive.
    """
    values = region.h * region.w * 3
    for j, i in enumerate(indices):
        frame = frames[i]
        np.copyto(host[j * values:(j + 1) * values].reshape(region.h, region.w, 3),
                  region.of(frame), casting="same_kind")
        del frame


class OnDevice:
    """A pass's output left on a kernel backend's device.

    Attributes:
        data: the flat device buffer (a ``cl.Buffer`` or a 1-D ``wp.array``), row-major, 3
            values per pixel for RGB.
        shape: the image it holds, ``h x w x 3`` or ``h x w`` (the RAW mosaic); an input put
            on the device (:meth:`~gpu_blur.backends.kernel.KernelBackend.put`) may be a
            stack of frames, ``n x h x w x 3``.
        dtype: the values' numpy dtype; None for the backend's compute type (pass outputs).
    """

    __slots__ = ("data", "shape", "_fetch", "dtype")

    def __init__(self, data, shape: tuple[int, ...], fetch, dtype=None):
        self.data, self.shape, self._fetch = data, tuple(int(n) for n in shape), fetch
        self.dtype = None if dtype is None else np.dtype(dtype)

    @property
    def ndim(self) -> int:
        """Number of image dimensions (2 for a mosaic, 3 for RGB)."""
        return len(self.shape)

    def numpy(self, dtype=np.float64) -> np.ndarray:
        """A host copy, float64 unless asked otherwise (timed as ``copies``)."""
        return self._fetch(self, np.dtype(dtype))

    def __array__(self, dtype=None, copy=None):
        return self.numpy(np.float64 if dtype is None else dtype)


def cfa_bits(pattern: str | None) -> int:
    """The pattern's channels packed as gb_cfa_channel reads them.

    Channels at the cell offsets (0,0), (0,1), (1,0), (1,1), 2 bits each; 0 without a pattern
    (no RAW round trip).
    """
    if pattern is None:
        return 0
    return sum(c << (2 * i) for i, c in enumerate(BayerPattern(pattern).channels))


#: The optional packages a backend imports, as a user installs them.
_PACKAGES = {"warp": "NVIDIA Warp (package warp-lang)", "pyopencl": "pyopencl"}


@contextlib.contextmanager
def _extra(module: str, extra: str, backend: str):
    """Turn a missing optional dependency into a RuntimeError that says how to install it.

    In words that fit both the Python API (``backend="warp:cpu"``) and ``--backend``.
    """
    try:
        yield
    except ModuleNotFoundError as e:
        if e.name != module:
            raise
        raise RuntimeError(f"backend {backend!r} needs {_PACKAGES.get(module, module)}, which is "
                           f"not installed: pip install 'gpu_blur[{extra}]', or use the numpy "
                           "backend") from None


def usable_devices(kind: str, precision: str) -> tuple[list[str], dict[str, str]]:
    """The usable devices of a family (``numpy``, ``opencl``, ``warp``), and why not others.

    Names in the order the family's bare name picks from (Warp: GPUs first).

    Raises:
        ImportError: the family's library (pyopencl, warp-lang) is not installed.
    """
    if kind == "numpy":
        return ["numpy"], {}
    if kind == "opencl":
        from gpu_blur.backends.opencl import device_rank, opencl_devices

        found = sorted(opencl_devices(), key=device_rank)  # the order `opencl` picks in
        usable = [d for d in found if d.usable and (d.fp64 or precision != "float64")]
        unusable = {d.spec: (d.problem and f"cannot build kernels: {d.problem}")
                    or "has no fp64 (cl_khr_fp64), and output.precision is float64"
                    for d in found if d not in usable}
        return [d.spec for d in usable], unusable
    if kind == "warp":
        from gpu_blur.backends.warp import warp_devices

        found = warp_devices()
        return [d["spec"] for d in found if d["kind"] == "GPU"] + [
            d["spec"] for d in found if d["kind"] != "GPU"], {}
    raise ValueError(f"unknown backend {kind!r}")


@functools.cache
def get_backend(name: str, precision: str = "float32") -> Backend:
    """A backend by name; ``precision`` is the kernels' compute type.

    One instance per (name, precision) and process, so devices are opened and kernels built
    once however many samples run.
    """
    base = name.split(":", 1)[0]
    if base == "numpy":
        return NumpyBackend()
    if base == "opencl":
        with _extra("pyopencl", "opencl", name):
            from gpu_blur.backends.opencl import OpenCLBackend

        return OpenCLBackend(name, precision)
    if base == "warp":
        with _extra("warp", "warp", name):
            from gpu_blur.backends.warp import WarpBackend

        return WarpBackend(name, precision)
    raise ValueError(f"unknown backend {name!r}; available: numpy, opencl, "
                     "opencl:<platform>:<device>, warp, warp:cpu, warp:cuda:<n> (see gpu-blur "
                     "devices)")
