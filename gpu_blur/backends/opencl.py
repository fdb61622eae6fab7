"""The OpenCL backend: the plan's three passes as fused kernels (``kernels/opencl/*.cl``).

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
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gpu_blur.backends import (
    FRAMES_PER_LAUNCH,
    OnDevice,
    cfa_bits,
    fill_stack,
)
from gpu_blur.backends.flows import interpolation_factor, with_flows
from gpu_blur.cameras import Camera
from gpu_blur.kernel_constants import opencl_header
from gpu_blur.plan import Plan
from gpu_blur.reference import blur
from gpu_blur.reference.interpolate import CONSISTENCY_ABSOLUTE_PX2, CONSISTENCY_RELATIVE
from gpu_blur.reference.rng import key_from_seed
from gpu_blur.reference.transfer import a7r3_lookup_table
from gpu_blur.testhooks import fault_planted, planted_fault
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

NO_PLATFORM_HELP = (
    "no OpenCL platform found. For a CPU device: pip install pocl-binary-distribution (PoCL), "
    "or pip install intel-opencl-rt intel-cmplr-lib-rt (Intel's CPU runtime, which gpu_blur "
    "registers by itself); for a GPU, install its vendor's driver (NVIDIA: the CUDA driver "
    "ships OpenCL)"
)


class OpenCLError(RuntimeError):
    """An OpenCL device that cannot be used, or a kernel that does not build."""


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


register_cpu_runtimes()
import pyopencl as cl  # noqa: E402  (after the vendor folder is set)


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
            cl.Program(ctx, "__kernel void gb_probe(__global float *a) { a[0] = 1.0f; }").build()
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


def select_device(spec: str):
    """The cl.Device a backend name asks for (``opencl`` = first usable, GPUs first)."""
    devices = opencl_devices()
    if not devices:
        raise OpenCLError(NO_PLATFORM_HELP)
    if spec == "opencl":
        usable = [d for d in devices if d.usable]
        if not usable:
            why = "; ".join(f"{d.spec} ({d.name}): {d.problem}" for d in devices)
            raise OpenCLError(f"no OpenCL device can build kernels here: {why}. "
                              + NO_PLATFORM_HELP.replace("no OpenCL platform found. ", ""))
        chosen = sorted(usable, key=lambda d: d.kind != "GPU")[0]
    else:
        chosen = next((d for d in devices if d.spec == spec), None)
        if chosen is None:
            raise OpenCLError(f"no OpenCL device {spec!r}; present: "
                              + ", ".join(f"{d.spec} ({d.name})" for d in devices))
        if not chosen.usable:
            raise OpenCLError(f"{spec} ({chosen.name}) cannot build kernels: {chosen.problem}")
    _, p, d = chosen.spec.split(":")
    return cl.get_platforms()[int(p)].get_devices()[int(d)], chosen


def pass_defines(plan: Plan, pass_: str) -> dict[str, str]:
    """The build-time defines of one pass: its kept stages and their options."""
    defines = {f"GB_STAGE_{s.name.upper()}": "1" for s in plan.stages
               if s.kept and s.pass_ == pass_}
    if plan.fast_math:
        # native_ functions in float builds (gb_math.h), every pass: only functions change,
        # never the arithmetic rules (no -cl-fast-relaxed-math), so compensated sums hold
        defines["GB_FAST_MATH"] = "1"
    if pass_ == "to_raw" and plan.kept("poisson_gaussian_noise"):
        if plan["poisson_gaussian_noise"].options["sampler"] == "normal":
            defines["GB_POISSON_NORMAL"] = "1"
    if pass_ == "to_raw" and plan.kept("linear_to_camera"):
        if plan["linear_to_camera"].options["clip"]:
            defines["GB_CLIP_CAMERA"] = "1"
    if pass_ == "finish":
        if plan.kept("demosaic"):
            options = plan["demosaic"].options
            if options["method"] == "bilinear":
                defines["GB_DEMOSAIC_BILINEAR"] = "1"
            if options["clip"]:
                defines["GB_CLIP_DEMOSAIC"] = "1"
            defines["GB_ZERO_BORDER"] = "1" if options["border"] == "zero" else "0"
        if plan.retone_curve == "lookup":
            defines["GB_RETONE_LOOKUP"] = "1"
        if plan.kept("quantize"):
            defines["GB_QUANTIZE_BITS"] = str(plan["quantize"].options["bits"])
    return defines


class OpenCLBackend:
    """Runs a plan as OpenCL kernels on one device (see :mod:`gpu_blur.backends`).

    Args:
        spec: ``opencl`` (first usable device, GPUs first) or ``opencl:<platform>:<device>``.
        precision: the kernels' compute type, ``float32`` or ``float64`` (cl_khr_fp64).
        overlap: upload frames from pinned host buffers (``CL_MEM_ALLOC_HOST_PTR``, mapped)
            on a second queue while the previous stack of frames is summed (False: blocking
            copies on the compute queue, to measure what the overlap gains).
    """

    name = "opencl"

    def __init__(self, spec: str = "opencl", precision: str = "float32", *,
                 overlap: bool = True):
        self.cl_device, self.info = select_device(spec)
        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be float32 or float64, got {precision!r}")
        if precision == "float64" and not self.info.fp64:
            raise OpenCLError(f"{self.info.spec} ({self.info.name}) has no fp64 "
                              "(cl_khr_fp64); use output.precision = 'float32'")
        self.precision = precision
        self.real = np.float64 if precision == "float64" else np.float32
        self.device = f"{self.info.spec} {self.info.name} ({self.info.platform}), {precision}"
        self.ctx = cl.Context([self.cl_device])
        self.queue = cl.CommandQueue(self.ctx)
        self.overlap = bool(overlap)
        self.copy_queue = cl.CommandQueue(self.ctx) if self.overlap else self.queue
        self._programs: dict = {}
        self._kernel_cache: dict = {}
        self._staging: dict = {}  # slot -> (pinned buffer, its mapped host array)
        self._staged: dict = {}  # slot -> event: the last copy out of that staging buffer
        self._constants: dict = {}  # (bytes, dtype) -> buffer of a small constant
        self._code_tables: dict = {}  # accumulate.cl's defines -> its 8-bit linear table

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
            with warnings.catch_warnings():  # a banner or warnings; failures raise below
                warnings.simplefilter("ignore", cl.CompilerWarning)
                return cl.Program(self.ctx, text).build(options=options)
        except cl.RuntimeError as e:
            raise OpenCLError(f"building {name} for {self.device} failed.\n"
                              f"defines: {' '.join(flags) or '(none)'}\ncompiler log:\n{e}"
                              ) from None

    def kernels(self, source: str, defines: dict[str, str]) -> _Kernels:
        """The kernels of a built program, by name (each cl.Kernel retrieved once)."""
        return _Kernels(self.program(source, defines), self._kernel_cache)

    # -- buffers (uploads and downloads are timed as "copies", gpu_blur.timings) --------------
    def _upload(self, array, dtype=None) -> cl.Buffer:
        """``array`` on the device: an :class:`OnDevice` as it is, host data copied."""
        if isinstance(array, OnDevice):
            return array.data
        with timer("copies"):
            data = np.ascontiguousarray(array, dtype=dtype or self.real)
            return cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                             hostbuf=data)

    def _constant(self, array, dtype=None) -> cl.Buffer:
        """A small constant (matrix, polynomial, table) on the device, uploaded once."""
        data = np.ascontiguousarray(np.ravel(array), dtype=dtype or self.real)
        key = (data.tobytes(), data.dtype.str)
        if key not in self._constants:
            self._constants[key] = self._upload(data, data.dtype)
        return self._constants[key]

    def _empty(self, count: int, dtype=None) -> cl.Buffer:
        nbytes = max(count, 1) * np.dtype(dtype or self.real).itemsize
        return cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)

    def _zeros(self, count: int, dtype=None) -> cl.Buffer:
        nbytes = max(count, 1) * np.dtype(dtype or self.real).itemsize
        buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)
        cl.enqueue_fill_buffer(self.queue, buf, np.zeros(1, dtype or self.real), 0, nbytes)
        return buf

    def _fetch(self, values: OnDevice, dtype) -> np.ndarray:
        with timer("copies"):
            out = np.empty(values.shape, dtype=self.real)
            cl.enqueue_copy(self.queue, out, values.data)
            return out.astype(dtype, copy=False)

    def _out(self, buf: cl.Buffer, shape, pass_: str, origin) -> OnDevice:
        """A pass's output, with the :data:`~gpu_blur.testhooks.TEST_FAULT` hook applied."""
        result = OnDevice(buf, shape, self._fetch)
        if fault_planted(pass_):
            host = planted_fault(pass_, result.numpy(), origin)
            cl.enqueue_copy(self.queue, buf, np.ascontiguousarray(host, dtype=self.real))
        return result

    def _kernels(self, sync: bool = True):
        """Time launches as "kernels"; ``sync`` waits for them (``queue.finish()``) at the end."""
        return timer("kernels", self.queue.finish if sync else None)

    @staticmethod
    def _grid(w: int, h: int) -> tuple[int, int]:
        return (int(w), int(h))

    def _source(self, frame: np.ndarray):
        """(numpy dtype, GB_SOURCE_BITS) a frame travels in: its codes, or the compute type."""
        return {np.dtype(np.uint8): (np.uint8, 8), np.dtype(np.uint16): (np.uint16, 16)}.get(
            np.dtype(frame.dtype), (self.real, 0))

    def _frame_stacks(self, frames: Sequence[np.ndarray], region: Region):
        """Yield (stack, count, upload event): device stacks of up to FRAMES_PER_LAUNCH frames.

        Two stacks take turns. With ``overlap``, a stack's frames go through a mapped pinned
        buffer and upload on the copy queue without blocking; the caller's launch waits for
        the upload event and returns its own event through ``send``, which the next upload
        into that stack waits for. Without it, copies block on the compute queue.
        """
        dtype = self._source(frames[0])[0]
        per = min(FRAMES_PER_LAUNCH, len(frames))
        values = region.h * region.w * 3
        groups = [range(i, min(i + per, len(frames))) for i in range(0, len(frames), per)]
        stacks = [self._empty(per * values, dtype) for _ in range(min(2, len(groups)))]
        read = [None] * len(stacks)  # event: the launch that last read each stack
        for c, group in enumerate(groups):
            slot = c % len(stacks)
            with timer("copies"):
                if self.overlap:
                    staging = self._staging_buffer(slot, per * values, dtype)
                    fill_stack(staging, frames, group, region)
                    event = cl.enqueue_copy(
                        self.copy_queue, stacks[slot], staging[:len(group) * values],
                        is_blocking=False, wait_for=[read[slot]] if read[slot] else None)
                    self._staged[slot] = event
                else:
                    host = np.empty(len(group) * values, dtype=dtype)
                    fill_stack(host, frames, group, region)
                    cl.enqueue_copy(self.queue, stacks[slot], host)
                    event = None
            read[slot] = yield stacks[slot], len(group), event

    def _staging_buffer(self, slot: int, count: int, dtype) -> np.ndarray:
        """Mapped pinned host buffer ``slot`` for ``count`` values, once its last copy is done."""
        if slot in self._staged:
            self._staged.pop(slot).wait()
        held = self._staging.get(slot)
        if held is None or held[1].dtype != dtype or held[1].size < count:
            if held is not None:
                held[1].base.release()
            buf = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.ALLOC_HOST_PTR,
                            count * np.dtype(dtype).itemsize)
            mapped, _ = cl.enqueue_map_buffer(self.copy_queue, buf, cl.map_flags.WRITE, 0,
                                              (count,), dtype, is_blocking=True)
            held = (buf, mapped)
            self._staging[slot] = held
        return held[1]

    # -- pass 1: accumulate ------------------------------------------------------------------
    def _code_table(self, prg, defines: dict[str, str]) -> cl.Buffer:
        """The linear value of every 8-bit code, from this build's own ``gb_linearize``.

        ``gb_blur_average_add`` gathers from it instead of evaluating the EOTF per value: the
        same function of the same 256 codes, so the same bits. Made once per build; a
        one-value placeholder when the frames are not 8-bit codes (the kernel does not read it).
        """
        key = tuple(sorted(defines.items()))
        if key not in self._code_tables:
            count = 256 if defines["GB_SOURCE_BITS"] == "8" else 1
            table, indicator = self._empty(count), self._empty(count)
            if count == 256:
                codes = self._upload(np.arange(256), np.uint8)
                with self._kernels():
                    prg.gb_linearize(self.queue, (count,), None, codes, table, indicator)
            self._code_tables[key] = table
        return self._code_tables[key]

    def accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region: Region) -> tuple[OnDevice, OnDevice]:
        """Linearize and blur on the device; (linear, mask) over ``region``, on the device."""
        dtype, bits = self._source(frames[0])
        defines = {**pass_defines(plan, "accumulate"), "GB_SOURCE_BITS": str(bits)}
        prg = self.kernels("accumulate.cl", defines)
        mode = plan.variant("blur") or "none"
        n = region.h * region.w * 3
        shape = (region.h, region.w, 3)
        linear, sat_mask = self._empty(n), self._empty(n)
        if mode == "average" and interpolation_factor(plan) > 1:
            self._interpolated_average(plan, params, frames, region, defines, linear, sat_mask)
            return self._linear_out(linear, sat_mask, shape, region)
        if mode == "average":
            # running compensated sums (sum, rounding errors, saturation counts) are only
            # needed between launches: one stack of frames is summed in registers
            sums = ((self._empty(n), self._empty(n), self._empty(n, np.uint32))
                    if len(frames) > FRAMES_PER_LAUNCH
                    else (linear, sat_mask, self._empty(1, np.uint32)))
            table = self._code_table(prg, defines)
            done, stacks = 0, self._frame_stacks(frames, region)
            stack, count, uploaded = next(stacks)
            while True:
                last = done + count == len(frames)
                with self._kernels(sync=last):
                    launched = prg.gb_blur_average_add(
                        self.queue, (n,), None, stack, np.uint32(count), np.int64(n), *sums,
                        np.int32(done == 0), np.uint32(len(frames) if last else 0), linear,
                        sat_mask, table, wait_for=[uploaded] if uploaded else None)
                done += count
                if last:
                    stacks.close()
                    break
                stack, count, uploaded = stacks.send(launched)
            return self._linear_out(linear, sat_mask, shape, region)
        if mode == "none":
            indicator = self._empty(n)
            source = self._upload(region.of(frames[0]), dtype)
            with self._kernels():
                prg.gb_linearize(self.queue, (n,), None, source, linear, indicator)
            del source
            given = np.zeros(shape) if mask is None else region.of(mask)
            return (self._out(linear, shape, "accumulate", region.origin),
                    OnDevice(self._upload(given), shape, self._fetch))
        view = region.expand(blur.blur_halo(mode, params, region.full_h, region.full_w))
        vn = view.h * view.w * 3
        src, indicator = self._empty(vn), self._empty(vn)
        source = self._upload(view.of(frames[0]), dtype)
        with self._kernels(sync=False):
            prg.gb_linearize(self.queue, (vn,), None, source, src, indicator)
        del source
        geometry = (np.int64(view.x0), np.int64(view.y0), np.int64(view.w),
                    np.int64(region.full_w), np.int64(region.full_h))
        out_geometry = (np.int64(region.x0), np.int64(region.y0), np.int64(region.w),
                        np.int64(region.h))
        grid = self._grid(region.w, region.h)
        if mode == "kernel":
            kernel = blur.normalize_kernel(params["kernel"])
            k = self._upload(np.ravel(kernel))
            kh, kw = (np.int32(s) for s in kernel.shape)
            with self._kernels():
                prg.gb_blur_kernel(self.queue, grid, None, src, *geometry, k, kh, kw, linear,
                                   *out_geometry)
                prg.gb_blur_kernel(self.queue, grid, None, indicator, *geometry, k, kh, kw,
                                   sat_mask, *out_geometry)
            return self._linear_out(linear, sat_mask, shape, region)
        # compensated sums of the image and of its indicator: (sum, compensation) each
        sums = [self._zeros(n) for _ in range(4)]
        pos = np.float64 if self.info.fp64 else np.float32
        hom = params["homographies"]
        inverses = [self._upload(np.ravel(np.linalg.inv(h)), pos) for h in hom]
        with self._kernels():
            for hinv in inverses:  # one pose at a time
                prg.gb_blur_trajectory_add(self.queue, grid, None, src, indicator, *geometry,
                                           hinv, *sums, *out_geometry)
            prg.gb_blur_trajectory_finish(self.queue, (n,), None, *sums, np.uint32(len(hom)),
                                          linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _interpolated_average(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                              region: Region, defines: dict, linear, sat_mask) -> None:
        """Mode average at ``blur.interpolation`` times the frame rate, into linear, sat_mask.

        One gap at a time, in time order: frame i+1 and the gap's two flows upload over the
        region plus the flows' halo (frame i stays from the gap before), then the original
        frame and the intermediates after it join one set of compensated sums
        (kernels/opencl/interpolate.cl); intermediate frames are never stored.
        """
        dtype = self._source(frames[0])[0]
        prg = self.kernels("interpolate.cl", defines)
        params = with_flows(plan, params, frames)
        flows, factor = params["flows"], interpolation_factor(plan)
        view = region.expand(blur.blur_halo("average", params, region.full_h, region.full_w))
        n = region.h * region.w * 3
        sums = (self._zeros(n), self._zeros(n), self._zeros(n))
        geometry = (np.int64(view.x0), np.int64(view.y0), np.int64(view.w))
        full = (np.int64(region.full_w), np.int64(region.full_h))
        out_geometry = (np.int64(region.x0), np.int64(region.y0), np.int64(region.w),
                        np.int64(region.h))
        pos = np.float64 if self.info.fp64 else np.float32
        test = (pos(CONSISTENCY_RELATIVE), pos(CONSISTENCY_ABSOLUTE_PX2))
        grid = self._grid(region.w, region.h)
        frame_bufs = [self._empty(view.h * view.w * 3, dtype) for _ in range(min(2, len(frames)))]
        flow_bufs = [self._empty(view.h * view.w * 2, np.float32) for _ in range(2)]
        for i in range(len(frames)):
            with timer("copies"):  # waits for the launches that read the buffer before
                cl.enqueue_copy(self.queue, frame_bufs[i % 2],
                                np.ascontiguousarray(view.of(frames[i]), dtype=dtype))
                if i > 0:
                    for buf, flow in zip(flow_bufs, flows[i - 1], strict=True):
                        cl.enqueue_copy(self.queue, buf, np.ascontiguousarray(view.of(flow)))
            with self._kernels(sync=False):
                for k in range(1, factor if i > 0 else 1):
                    prg.gb_blur_interpolate_add(
                        self.queue, grid, None, frame_bufs[(i - 1) % 2], frame_bufs[i % 2],
                        *flow_bufs, *geometry, *full, pos(k / factor), *test, *sums,
                        *out_geometry)
                prg.gb_blur_interpolate_add_frame(self.queue, grid, None, frame_bufs[i % 2],
                                                  *geometry, *sums, *out_geometry)
        with self._kernels():
            prg.gb_blur_interpolate_finish(self.queue, (n,), None, *sums,
                                           np.uint32((len(frames) - 1) * factor + 1), linear,
                                           sat_mask)

    def _linear_out(self, linear, sat_mask, shape, region: Region):
        """The accumulate pass's (linear, mask), left on the device."""
        return (self._out(linear, shape, "accumulate", region.origin),
                OnDevice(sat_mask, shape, self._fetch))

    # -- pass 2: to_raw ----------------------------------------------------------------------
    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear, mask,
               origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[OnDevice, OnDevice]:
        """Saturation to noisy RAW on the device (see NumpyBackend.to_raw)."""
        prg = self.kernels("to_raw.cl", pass_defines(plan, "to_raw"))
        h, w = linear.shape[:2]
        saturated = self._empty(h * w * 3)
        raw = self._empty(h * w if plan.raw_round_trip else 1)
        key = key_from_seed(seed)
        r = self.real
        inputs = (self._upload(linear), self._upload(mask))
        matrix = self._constant(camera.linear_to_camera)
        with self._kernels():
            prg.gb_to_raw(
                self.queue, self._grid(w, h), None, *inputs,
                np.int64(origin[1]), np.int64(origin[0]), np.int64(w), np.int64(h),
                r(params.get("alpha", 0.0)), matrix,
                np.int32(cfa_bits(params.get("pattern"))), r(params.get("red_gain", 1.0)),
                r(params.get("blue_gain", 1.0)), r(params.get("shot_noise_k", 1.0)),
                r(params.get("read_noise_std", 0.0)),
                r(plan["poisson_gaussian_noise"].options["normal_above"]), np.uint32(key[0]),
                np.uint32(key[1]), np.uint32(sample_index), saturated, raw)
        del inputs
        if not plan.raw_round_trip:
            return (self._out(saturated, (h, w, 3), "to_raw", origin),
                    OnDevice(saturated, (h, w, 3), self._fetch))
        return (self._out(raw, (h, w), "to_raw", origin),
                OnDevice(saturated, (h, w, 3), self._fetch))

    # -- pass 3: finish ----------------------------------------------------------------------
    def finish(self, plan: Plan, params: dict, camera: Camera, image, saturated, view: Region,
               out: Region, *, seed: int, sample_index: int) -> OnDevice:
        """Demosaic and finish on the device, over ``out`` (see NumpyBackend.finish)."""
        prg = self.kernels("finish.cl", pass_defines(plan, "finish"))
        # the kernel takes both curves; the one the plan does not use is never read
        polynomial = plan.retone_polynomial(camera)
        polynomial = np.zeros(1) if polynomial is None else polynomial
        table = a7r3_lookup_table(plan["retone"].options["table_size"]) / 255.0
        raw = image if plan.raw_round_trip else np.zeros(1)
        result = self._empty(out.h * out.w * 3)
        key = key_from_seed(seed)
        raw_buf, sat_buf = self._upload(raw), self._upload(saturated)
        matrix, polynomial_buf = (self._constant(camera.camera_to_linear),
                                  self._constant(polynomial))
        table_buf = self._constant(table)
        with self._kernels():
            prg.gb_finish(
                self.queue, self._grid(out.w, out.h), None, raw_buf, sat_buf,
                np.int64(view.x0), np.int64(view.y0), np.int64(view.w), np.int64(view.full_w),
                np.int64(view.full_h), np.int64(out.x0), np.int64(out.y0), np.int64(out.w),
                np.int64(out.h), np.int32(cfa_bits(params.get("pattern"))), matrix,
                self.real(params.get("gaussian_std", 0.0)), np.uint32(key[0]),
                np.uint32(key[1]), np.uint32(sample_index), polynomial_buf,
                np.int32(polynomial.size), table_buf, np.int32(table.size), result)
        del raw_buf, sat_buf
        return self._out(result, (out.h, out.w, 3), "finish", out.origin)

    def retone(self, plan: Plan, camera: Camera, image: np.ndarray) -> np.ndarray:
        """The output tone curve for the sharp reference (host side, float64)."""
        from gpu_blur.backends.numpy import NumpyBackend

        return NumpyBackend().retone(plan, camera, image)


class _Kernels:
    """Attribute access to a program's kernels, each cl.Kernel made once and reused."""

    def __init__(self, program, cache: dict):
        self._program, self._cache = program, cache

    def __getattr__(self, name: str):
        key = (id(self._program), name)
        if key not in self._cache:
            self._cache[key] = cl.Kernel(self._program, name)
        return self._cache[key]

