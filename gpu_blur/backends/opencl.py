"""The OpenCL backend: the plan's three passes as fused kernels (``kernels/opencl/*.cl``).

The passes' host logic is :mod:`gpu_blur.backends.kernel`'s; this module holds the device,
buffers, queues, launching, and the rendering of a pass configuration into ``-D`` defines.

Pass outputs stay on the device between passes. Frames upload in their stored dtype
(``-DGB_SOURCE_BITS``), from pinned host buffers on a second queue that overlaps the summing of
the previous frames.

Only the stages a plan keeps are compiled in (``-DGB_STAGE_<NAME>``); programs are built once
per (device, source, defines). ``float32`` by default; ``float64`` builds need cl_khr_fp64.
Random draws use Random123's Philox through pyopencl's bundled header and match
:mod:`gpu_blur.reference.rng` bit for bit.
"""

from __future__ import annotations

import atexit
import dataclasses
import functools
import os
import shutil
import stat
import sys
import tempfile
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from gpu_blur import caches, notices
from gpu_blur.backends import OnDevice, copy_values, fill_stack, pinned_stack
from gpu_blur.backends.kernel import Arg, KernelBackend, PassConfig, source_dtype
from gpu_blur.kernel_constants import opencl_header
from gpu_blur.planning import Pass
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

__all__ = ["CPU_RUNTIME_ORDER", "DeviceInfo", "FAST_MATH_RUNTIMES", "ICD_FOLDER_ENV",
           "NO_PLATFORM_HELP", "OpenCLBackend", "OpenCLError", "SOURCES", "SOURCE_BITS",
           "best_device", "config_defines", "device_rank", "kernel_dir", "opencl_devices",
           "private_folder", "register_cpu_runtimes", "select_device"]

NO_PLATFORM_HELP = (
    "no OpenCL platform found. For a CPU device: pip install intel-opencl-rt "
    "intel-cmplr-lib-rt (Intel's CPU runtime, which gpu_blur registers by itself), or PoCL "
    "(Debian/Ubuntu: apt-get install pocl-opencl-icd; elsewhere pip install "
    "pocl-binary-distribution); for a GPU, install its vendor's driver (NVIDIA: the CUDA "
    "driver ships OpenCL)"
)


class OpenCLError(RuntimeError):
    """An OpenCL device that cannot be used, or a kernel that does not build."""


#: The OpenCL runtimes whose ``native_`` functions the fast-math rows of gpu_blur.tolerances
#: were measured on. OpenCL leaves their accuracy to the runtime, so ``output.fast_math`` is refused
#: on any other, where no row can be stated.
FAST_MATH_RUNTIMES = ("Intel(R) OpenCL", "Portable Computing Language", "NVIDIA CUDA")


def kernel_dir() -> Path:
    """Folder of the OpenCL sources.

    ``gpu_blur/kernels/opencl`` in an installed wheel, else the source tree's ``kernels/opencl``.
    """
    here = Path(__file__).resolve().parent.parent
    for candidate in (here / "kernels" / "opencl", here.parent / "kernels" / "opencl"):
        if (candidate / "include" / "gb_common.h").is_file():
            return candidate
    raise OpenCLError(f"OpenCL kernel sources not found near {here}; reinstall gpu_blur")


#: Set beside ``OCL_ICD_VENDORS`` when gpu_blur made the vendor folder, so a child process
#: that inherits both can tell the folder is ours and check it before trusting it.
ICD_FOLDER_ENV = "GPU_BLUR_ICD_FOLDER"


def private_folder(path: Path) -> bool:
    """Whether ``path`` is a real folder (no symlink) owned by this user, closed to others.

    What a loader path must be before gpu_blur points the OpenCL ICD loader at it: anyone who
    can add a file there can have their library loaded into this process.
    """
    try:
        st = os.lstat(path)
    except OSError:
        return False
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and not st.st_mode & 0o077


def register_cpu_runtimes() -> None:
    """Let pyopencl's ICD loader see a CPU runtime installed from PyPI.

    Intel's runtime (``intel-opencl-rt``) installs ``<prefix>/lib/libintelocl.so`` but no
    usable vendor file. When ``OCL_ICD_VENDORS`` is not set and that library exists, write a
    vendor folder naming it (plus the system's ``/etc/OpenCL/vendors``) and point the loader
    at it. Must run before the process first asks for platforms; importing this module does.

    The folder is made by :func:`tempfile.mkdtemp` (a fresh, unpredictable name, mode 0700,
    owned by this user) and removed when the process exits. A child process inherits it
    (spawned workers); it is used only while :func:`private_folder` holds, else the child
    makes its own. Nothing is ever loaded from a folder another user could write.
    """
    inherited = os.environ.get(ICD_FOLDER_ENV)
    vendors = os.environ.get("OCL_ICD_VENDORS")
    if vendors and not (inherited and vendors == inherited):
        return  # the user's own choice of loader path
    if vendors and private_folder(Path(vendors)):
        return  # made by the process that started this one, still private
    lib = Path(sys.prefix) / "lib" / "libintelocl.so"
    if not lib.is_file():
        for name in ("OCL_ICD_VENDORS", ICD_FOLDER_ENV):
            os.environ.pop(name, None)  # an inherited folder that is gone or not private
        return
    folder = Path(tempfile.mkdtemp(prefix="gpu_blur-icd-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    entries = {"gpu_blur-intel-cpu.icd": f"{lib}\n"}
    system = Path("/etc/OpenCL/vendors")
    if system.is_dir():
        entries.update({p.name: p.read_text() for p in system.glob("*.icd")})
    for name, text in entries.items():
        (folder / name).write_text(text)
    os.environ["OCL_ICD_VENDORS"] = os.environ[ICD_FOLDER_ENV] = str(folder)


def _private_invoker_cache() -> None:
    """Keep pyopencl's store of generated argument-setting code in a private folder.

    ``pyopencl.invoker`` keeps that code (pickles, run when read back) in pytools' folder from
    platformdirs, which follows a relative ``XDG_CACHE_HOME`` or ``HOME`` into the current
    folder. It is imported with ``XDG_CACHE_HOME`` at gpu_blur's cache folder (its store is
    then ``<cache>/pytools``), and the store is made again there if it was imported before.
    """
    folder = caches.folder("pytools")
    if "pyopencl.invoker" not in sys.modules:
        saved = os.environ.get("XDG_CACHE_HOME")
        os.environ["XDG_CACHE_HOME"] = str(folder.parent)
        try:
            import pyopencl.invoker  # noqa: F401
        finally:
            if saved is None:
                del os.environ["XDG_CACHE_HOME"]
            else:
                os.environ["XDG_CACHE_HOME"] = saved
    from pyopencl import invoker

    store = getattr(invoker, "invoker_cache", None)  # None under PYOPENCL_NO_CACHE
    if store is not None and Path(store.container_dir) != folder:
        invoker.invoker_cache = type(store)(store.identifier, key_builder=store.key_builder,
                                            container_dir=str(folder), in_mem_cache_size=0,
                                            safe_sync=False)


register_cpu_runtimes()
caches.set_opencl_caches()  # before pyopencl loads the runtimes: PoCL reads POCL_CACHE_DIR then
import pyopencl as cl  # noqa: E402  (after the vendor folder is set)

_private_invoker_cache()


@dataclasses.dataclass(frozen=True)
class DeviceInfo:
    """One OpenCL device as ``gpu-blur devices`` lists it."""

    spec: str
    platform: str
    name: str
    kind: str
    fp64: bool
    memory_bytes: int
    usable: bool
    problem: str


def _kind(device) -> str:
    if device.type & cl.device_type.GPU:
        return "GPU"
    if device.type & cl.device_type.CPU:
        return "CPU"
    return "other"


@functools.cache
def _build_problem(platform_index: int, device_index: int) -> str:
    """'' when the device builds a trivial kernel, else the first line of why not."""
    device = cl.get_platforms()[platform_index].get_devices()[device_index]
    try:
        ctx = cl.Context([device])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            cl.Program(ctx, "__kernel void gb_probe(__global float *a) { a[0] = 1.0f; }").build(
                cache_dir=caches.pyopencl_cache(cl.VERSION_TEXT))
    except (cl.Error, RuntimeError) as e:
        lines = [x for x in str(e).splitlines() if "error" in x.lower()] or [str(e)]
        return lines[0].strip()
    return ""


def opencl_devices() -> list[DeviceInfo]:
    """Every OpenCL device, whether it can build kernels here, fp64 support and memory."""
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return []
    found = []
    for p, platform in enumerate(platforms):
        for d, device in enumerate(platform.get_devices()):
            problem = _build_problem(p, d)
            found.append(DeviceInfo(
                f"opencl:{p}:{d}", platform.name.strip(), device.name.strip(), _kind(device),
                "cl_khr_fp64" in device.extensions, int(device.global_mem_size), not problem,
                problem))
    return found


#: CPU runtimes by speed, fastest first (platform name fragments; others come after them).
#: PoCL takes several times Intel's time per sample, most on float frames (its pow):
#: docs/performance.md#opencl-cpu-runtimes.
CPU_RUNTIME_ORDER = ("Intel(R) OpenCL", "Portable Computing Language")


def device_rank(device: DeviceInfo) -> tuple[int, int]:
    """How ``opencl`` ranks a device, lower first.

    GPUs, then CPU runtimes by speed (:data:`CPU_RUNTIME_ORDER`), then the rest; platform
    order breaks ties.
    """
    if device.kind == "GPU":
        return (0, 0)
    known = [i for i, name in enumerate(CPU_RUNTIME_ORDER) if name in device.platform]
    return (1, known[0] if known else len(CPU_RUNTIME_ORDER))


def best_device(devices: list[DeviceInfo]) -> DeviceInfo:
    """The usable device that ranks first by :func:`device_rank` (platform order on ties).

    Raises:
        OpenCLError: naming each device and why it cannot build, when none can.
    """
    usable = [d for d in devices if d.usable]
    if not usable:
        why = "; ".join(f"{d.spec} ({d.name}): {d.problem}" for d in devices)
        raise OpenCLError(f"no OpenCL device can build kernels here: {why}. "
                          + NO_PLATFORM_HELP.replace("no OpenCL platform found. ", ""))
    return min(usable, key=device_rank)


def select_device(spec: str):
    """The cl.Device a backend name asks for.

    ``opencl``: :func:`best_device` (a GPU, else the fastest known CPU runtime; never a device
    that cannot build kernels).
    """
    devices = opencl_devices()
    if not devices:
        raise OpenCLError(NO_PLATFORM_HELP)
    if spec == "opencl":
        chosen = best_device(devices)
    else:
        chosen = next((d for d in devices if d.spec == spec), None)
        if chosen is None:
            raise OpenCLError(f"no OpenCL device {spec!r}; present: "
                              + ", ".join(f"{d.spec} ({d.name})" for d in devices))
        if not chosen.usable:
            raise OpenCLError(f"{spec} ({chosen.name}) cannot build kernels: {chosen.problem}")
    _, p, d = chosen.spec.split(":")
    return cl.get_platforms()[int(p)].get_devices()[int(d)], chosen


def config_defines(config: PassConfig) -> dict[str, str]:
    """A pass configuration as build-time defines: its kept stages and their options."""
    defines = {f"GB_STAGE_{name.upper()}": "1" for name in config.stages}
    if config.fast_math:
        # native_ functions in float builds (gb_math.h), every pass: only functions change,
        # never the arithmetic rules (no -cl-fast-relaxed-math), so compensated sums hold
        defines["GB_FAST_MATH"] = "1"
    if config.poisson_normal:
        defines["GB_POISSON_NORMAL"] = "1"
    if config.clip_camera:
        defines["GB_CLIP_CAMERA"] = "1"
    if config.demosaic:
        if config.demosaic == "bilinear":
            defines["GB_DEMOSAIC_BILINEAR"] = "1"
        if config.clip_demosaic:
            defines["GB_CLIP_DEMOSAIC"] = "1"
        defines["GB_ZERO_BORDER"] = "1" if config.zero_border else "0"
    if config.retone == "lookup":
        defines["GB_RETONE_LOOKUP"] = "1"
    if config.bits:
        defines["GB_QUANTIZE_BITS"] = str(config.bits)
    return defines


#: The OpenCL source of each pass's kernels.
SOURCES = {Pass.ACCUMULATE: "accumulate.cl", Pass.TO_RAW: "to_raw.cl", Pass.FINISH: "finish.cl"}


class OpenCLBackend(KernelBackend):
    """Runs a plan as OpenCL kernels on one device (see :mod:`gpu_blur.backends.kernel`).

    Args:
        spec: ``opencl`` (the best usable device, :func:`select_device`) or
            ``opencl:<platform>:<device>``.
        precision: the kernels' compute type, ``float32`` or ``float64`` (cl_khr_fp64).
        overlap: upload frames from pinned host buffers (``CL_MEM_ALLOC_HOST_PTR``, mapped)
            on a second queue while the previous stack of frames is summed, and move inputs
            put on the device and exported results through such buffers too (False:
            blocking copies from and to the caller's memory, to measure what this gains).
    """

    name = "opencl"

    def __init__(self, spec: str = "opencl", precision: str = "float32", *,
                 overlap: bool = True):
        super().__init__()
        self.cl_device, self.info = select_device(spec)
        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be float32 or float64, got {precision!r}")
        if precision == "float64" and not self.info.fp64:
            raise OpenCLError(f"{self.info.spec} ({self.info.name}) has no fp64 "
                              "(cl_khr_fp64); use output.precision = 'float32'")
        self.precision = precision
        self.real = self.np_real = np.float64 if precision == "float64" else np.float32
        self.position_dtype = np.float64 if self.info.fp64 else np.float32
        self.device = f"{self.info.spec} {self.info.name} ({self.info.platform}), {precision}"
        self.model = f"opencl {self.info.name} ({self.info.platform}), {precision}"
        self.ctx = cl.Context([self.cl_device])
        self.queue = cl.CommandQueue(self.ctx)
        self.overlap = bool(overlap)
        self.copy_queue = cl.CommandQueue(self.ctx) if self.overlap else self.queue
        self._programs: dict = {}
        self._kernel_cache: dict = {}
        self._staging: dict = {}  # slot -> (pinned buffer, its mapped host array)
        self._staged: dict = {}  # slot -> event: the last copy out of that staging buffer
        self._wait_for = None  # the upload the next launch waits for (_frame_stacks)
        self._launched = None  # the event of the last launch

    @property
    def uses_cuda(self) -> bool:
        """Whether the device is an NVIDIA GPU (NVIDIA's OpenCL runs on its CUDA driver)."""
        return self.info.kind == "GPU" and "NVIDIA" in self.info.platform

    # -- building ----------------------------------------------------------------------------
    def program(self, source: str, defines: dict[str, str]):
        """The built program of ``kernels/opencl/<source>`` with these defines (cached)."""
        key = (source, tuple(sorted(defines.items())))
        if key not in self._programs:
            text = (kernel_dir() / source).read_text()
            self._programs[key] = self.program_from_source(text, defines,
                                                           f"kernels/opencl/{source}")
        return self._programs[key]

    def program_from_source(self, text: str, defines: dict[str, str] | None = None,
                            name: str = "OpenCL source"):
        """Build OpenCL C text against the kernels' include folder, with the precision defines.

        Raises:
            OpenCLError: with the compiler log and the defines when the build fails.
        """
        defines = dict(defines or {})
        if self.precision == "float64":
            defines["GB_FP64"] = "1"
        if self.info.fp64:
            defines["GB_HAS_FP64"] = "1"
        flags = [f"-D{k}={v}" for k, v in sorted(defines.items())]
        options = ["-I", str(kernel_dir() / "include"), "-I",
                   str(Path(cl.__file__).parent / "cl"), *flags]
        if self.cl_device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
            # float division and sqrt rounded as in numpy (OpenCL otherwise allows 2.5 / 3 ulp,
            # which NVIDIA's OpenCL uses): mean counts k / n then match the reference exactly
            options.append("-cl-fp32-correctly-rounded-divide-sqrt")
        # the kernel constants from the Python values (kernel_constants), before the source;
        # #line keeps the compiler's line numbers those of the source
        text = f"{opencl_header()}#line 1\n{text}"
        try:
            with warnings.catch_warnings(), notices.building(name, self.info.spec):
                warnings.simplefilter("ignore", cl.CompilerWarning)  # a banner or warnings
                return cl.Program(self.ctx, text).build(
                    options=options, cache_dir=caches.pyopencl_cache(cl.VERSION_TEXT))
        except cl.RuntimeError as e:
            raise OpenCLError(f"building {name} for {self.device} failed.\n"
                              f"defines: {' '.join(flags) or '(none)'}\ncompiler log:\n{e}"
                              ) from None

    def kernels(self, source: str, defines: dict[str, str]) -> _Kernels:
        """The kernels of a built program, by name (each cl.Kernel retrieved once)."""
        return _Kernels(self.program(source, defines), self._kernel_cache)

    def _pass_kernels(self, config: PassConfig, source=None, interpolate: bool = False):
        if (config.fast_math and self.precision == "float32"
                and self.info.platform not in FAST_MATH_RUNTIMES):
            raise OpenCLError(
                f"output.fast_math on {self.info.spec} ({self.info.platform}): OpenCL leaves "
                "the accuracy of its native_ functions to the runtime, and this one's was "
                f"never measured (measured: {', '.join(FAST_MATH_RUNTIMES)}); set "
                "output.fast_math = false, or use --backend warp")
        defines = config_defines(config)
        if config.pass_ == Pass.ACCUMULATE:
            defines["GB_SOURCE_BITS"] = str(SOURCE_BITS.get(np.dtype(source), 0))
        return self.kernels("interpolate.cl" if interpolate else SOURCES[config.pass_],
                            defines)

    def _input_kernels(self, config: PassConfig | None, source):
        defines = {} if config is None else config_defines(config)
        defines["GB_SOURCE_BITS"] = str(SOURCE_BITS.get(np.dtype(source), 0))
        return self.kernels("inputs.cl", defines)

    def _launch(self, kernels, name: str, grid, *args):
        # (rows, columns) and (samples, rows, columns) go as OpenCL's (x, y[, z]): x the column
        grid = (grid,) if isinstance(grid, int) else tuple(int(g) for g in reversed(grid))
        wait_for, self._wait_for = self._wait_for, None
        self._launched = getattr(kernels, f"gb_{name}")(
            self.queue, grid, None, *(self._render(a) for a in args), wait_for=wait_for)
        return self._launched

    def _render(self, arg):
        """A kernel argument as OpenCL takes it (:class:`~gpu_blur.backends.kernel.Arg`)."""
        if not isinstance(arg, Arg):
            return arg
        return {"index": np.int64, "int": np.int32, "uint": np.uint32, "real": self.real,
                "position": self.position_dtype}[arg.kind](arg.value)

    def _timed(self, sync: bool = True):
        """Time launches as "kernels"; ``sync`` waits for them (``queue.finish()``) at the end.

        With ``sync_passes`` False nothing waits.
        """
        return timer("kernels", self.queue.finish if sync and self.sync_passes else None)

    def wait(self) -> None:
        """Wait for every launch and copy queued so far."""
        self.queue.finish()

    # -- buffers (uploads and downloads are timed as "copies", gpu_blur.timings) --------------
    def _upload(self, values, dtype=None) -> cl.Buffer:
        if isinstance(values, OnDevice):
            return values.data
        with timer("copies"):
            data = np.ascontiguousarray(values, dtype=dtype or self.real)
            return cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                             hostbuf=data)

    def _empty(self, count: int, dtype=None) -> cl.Buffer:
        nbytes = max(count, 1) * np.dtype(dtype or self.real).itemsize
        return cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)

    def _zeros(self, count: int, dtype=None) -> cl.Buffer:
        nbytes = max(count, 1) * np.dtype(dtype or self.real).itemsize
        buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)
        cl.enqueue_fill_buffer(self.queue, buf, np.zeros(1, dtype or self.real), 0, nbytes)
        return buf

    def _write(self, buffer, values: np.ndarray) -> None:
        with timer("copies"):  # waits for the launches that read the buffer before
            cl.enqueue_copy(self.queue, buffer, values)

    def _copy(self, into, values, count: int, offset: int = 0) -> None:
        size = np.dtype(self.real).itemsize
        cl.enqueue_copy(self.queue, into, values, byte_count=count * size,
                        dst_offset=offset * size)

    def _fill_zeros(self, buffer, count: int) -> None:
        cl.enqueue_fill_buffer(self.queue, buffer, np.zeros(1, self.real), 0,
                               count * np.dtype(self.real).itemsize)

    def _part(self, buffer, start: int, count: int, dtype) -> cl.Buffer:
        size = np.dtype(dtype or self.real).itemsize
        part = self._empty(count, dtype)
        cl.enqueue_copy(self.queue, part, buffer, src_offset=start * size,
                        byte_count=count * size)
        return part

    def _fetch(self, values: OnDevice, dtype) -> np.ndarray:
        with timer("copies"):
            out = np.empty(values.shape, dtype=values.dtype or self.real)
            cl.enqueue_copy(self.queue, out, values.data)
            return out.astype(dtype, copy=False)

    def _fetch_queued(self, buffer: cl.Buffer, into: np.ndarray) -> Callable[[], None]:
        return cl.enqueue_copy(self.queue, into, buffer, is_blocking=False).wait

    def _frame_stacks(self, frames: Sequence[np.ndarray], region: Region):
        """Yield (stack, count): device stacks of up to FRAMES_PER_LAUNCH frames.

        Two stacks take turns. With ``overlap``, a stack's frames go through a mapped pinned
        buffer and upload on the copy queue without blocking; the caller's next launch waits
        for the upload event, and the next upload into that stack waits for that launch.
        Without it, copies block on the compute queue.
        """
        dtype = source_dtype(frames[0], self.real)
        per, values, groups, stacks = self._stacks_for(frames, region, dtype)
        read = [None] * len(stacks)  # event: the launch that last read each stack
        for c, group in enumerate(groups):
            slot = c % len(stacks)
            with timer("copies"):
                if self.overlap:
                    staging = self._staging_buffer(slot, per * values, dtype)
                    fill_stack(staging, frames, group, region)
                    self._wait_for = [cl.enqueue_copy(
                        self.copy_queue, stacks[slot], staging[:len(group) * values],
                        is_blocking=False, wait_for=[read[slot]] if read[slot] else None)]
                    self._staged[slot] = self._wait_for[0]
                else:
                    host = np.empty(len(group) * values, dtype=dtype)
                    fill_stack(host, frames, group, region)
                    cl.enqueue_copy(self.queue, stacks[slot], host)
            yield stacks[slot], len(group)
            read[slot] = self._launched

    def put(self, image) -> OnDevice:
        """:meth:`KernelBackend.put` through a mapped pinned buffer (with ``overlap``).

        ``image``: an array, or a list of frames (copied one after another into the buffer:
        no stacked host copy). Threads copy it into one of two pinned buffers that take turns,
        and it uploads without blocking on the compute queue, so the launches that read it
        follow; filling the other buffer overlaps the upload. NVIDIA's OpenCL moves pinned
        memory at the bus's rate and the caller's pageable memory at a fraction of it.
        """
        stack = pinned_stack(image, self)  # frames staged in this backend's pinned memory
        if stack is not None:
            image = stack
        if self._direct(image):  # pinned(): no staging
            with timer("copies"):
                data = self._empty(image.size, image.dtype)
                # queued in a batch (its caller waits before image may change), else done
                cl.enqueue_copy(self.queue, data, image, is_blocking=self.sync_passes)
            return self._input(data, image.shape, image.dtype)
        if not self.overlap:
            return super().put(image)
        parts, shape, dtype, count, slot = self._staged_parts(image)
        with timer("copies"):
            staging = self._staging_buffer(slot, count, dtype)
            self._fill_staging(staging, parts)
            data = self._empty(count, dtype)
            self._staged[slot] = cl.enqueue_copy(self.queue, data, staging[:count],
                                                 is_blocking=False)
        return self._input(data, shape, dtype)

    def export(self, values: OnDevice, region: Region, into) -> None:
        """Copy ``region`` of a whole-image result into the host array ``into``.

        With ``overlap`` through a mapped pinned buffer, copied out by threads (see
        :meth:`put`); the copy waits for the launches queued before it.
        """
        count = int(np.prod(values.shape))
        direct = self._direct(into, values.dtype or self.np_real)  # pinned(): no staging
        if direct and into.size == count:
            with timer("copies"):  # unless every pass waits, the batch's caller waits
                cl.enqueue_copy(self.queue, into, values.data, is_blocking=self.sync_passes)
            return None
        if not self.overlap:
            return super().export(values, region, into)
        with timer("copies"):
            dtype = np.dtype(values.dtype or self.real)
            staging = self._staging_buffer(("export", dtype.str), count, dtype)
            cl.enqueue_copy(self.queue, staging[:count], values.data, is_blocking=True)
            copy_values(into, region.of(staging[:count].reshape(values.shape)))
        return None

    def _pinned_bytes(self, nbytes: int) -> tuple:
        held = self._mapped_host(nbytes, np.uint8)
        return held, held[1].ctypes.data

    def _mapped_host(self, count: int, dtype) -> tuple[cl.Buffer, np.ndarray]:
        """A pinned host buffer (``CL_MEM_ALLOC_HOST_PTR``) of ``count`` values and its mapping."""
        buffer = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.ALLOC_HOST_PTR,
                           count * np.dtype(dtype).itemsize)
        mapped, _ = cl.enqueue_map_buffer(self.copy_queue, buffer,
                                          cl.map_flags.READ | cl.map_flags.WRITE, 0, (count,),
                                          dtype, is_blocking=True)
        return buffer, mapped

    def _staging_buffer(self, slot, count: int, dtype) -> np.ndarray:
        """Mapped pinned host buffer ``slot`` for ``count`` values, once its last copy is done."""
        if slot in self._staged:
            self._staged.pop(slot).wait()
        held = self._staging.get(slot)
        if held is None or held[1].dtype != dtype or held[1].size < count:
            if held is not None:
                held[1].base.release()
            held = self._mapped_host(count, dtype)
            self._staging[slot] = held
        return held[1]


#: GB_SOURCE_BITS of the frames' stored dtype (0: the compute type).
SOURCE_BITS = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}


class _Kernels:
    """Attribute access to a program's kernels, each cl.Kernel made once and reused."""

    def __init__(self, program, cache: dict):
        self._program, self._cache = program, cache

    def __getattr__(self, name: str):
        key = (id(self._program), name)
        if key not in self._cache:
            self._cache[key] = cl.Kernel(self._program, name)
        return self._cache[key]
