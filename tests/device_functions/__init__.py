"""Device functions tested once for both kernel languages.

A test body takes a :class:`Target` (one kernel language on one device at one build) and runs
small probe kernels that call the device functions: ``target.run(name, n, args, outputs)``. The
probes exist in both languages under the same names with the same arguments, inputs first, then
outputs: ``<topic>.cl`` (OpenCL C) and ``<topic>_warp.py`` (Warp) in this folder. Arguments are
numpy arrays (copied to the device, flat) and numpy scalars; outputs are (shape, numpy dtype)
pairs, flat on the device and returned as numpy arrays of that shape.

Targets: the OpenCL device ``backend="opencl"`` picks (one, as the suite's time allows) and every
Warp device; with GPU_BLUR_BACKENDS set (e.g. ``opencl:1:0,warp:cpu``; ``opencl`` or ``warp``
alone for all of that language), the devices it names. A build name is the
tolerance table's dtype column (gpu_blur/tolerances.py), so a test names its rows with
``target.lang`` and ``target.build``.
"""

from __future__ import annotations

import functools
import importlib
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
INCLUDE = HERE.parents[1] / "kernels" / "opencl" / "include"

#: topic -> OpenCL build -> (real, wide, -D options). ``wide`` is the samplers' type (double
#: wherever the device has cl_khr_fp64: GB_HAS_FP64).
OPENCL_BUILDS = {
    "pixel": {
        "float32": (np.float32, np.float32, []),
        "float64": (np.float64, np.float64, ["-DGB_FP64"]),
    },
    "random": {
        "float32": (np.float32, np.float64, ["-DGB_HAS_FP64"]),
        "float64": (np.float64, np.float64, ["-DGB_HAS_FP64", "-DGB_FP64"]),
        "float32-nofp64": (np.float32, np.float32, []),
        "float32-fast": (np.float32, np.float64, ["-DGB_HAS_FP64", "-DGB_FAST_MATH"]),
        "float64-fast": (np.float64, np.float64, ["-DGB_HAS_FP64", "-DGB_FP64", "-DGB_FAST_MATH"]),
    },
}
#: topic -> Warp build -> (real, wide): the pixel functions are generic over the real type; the
#: samplers run in float64, the fast ones (random.pixel_normal_fast) in float32.
WARP_BUILDS = {
    "pixel": {"float32": (np.float32, np.float32), "float64": (np.float64, np.float64)},
    "random": {"float64": (np.float64, np.float64), "float32-fast": (np.float32, np.float64)},
}
#: The builds a topic's `target` fixture runs over (the others are asked for by name).
DEFAULT_BUILDS = {"pixel": ["float32", "float64"],
                  "random": ["float32", "float64", "float32-nofp64"]}


@dataclass(frozen=True)
class TargetSpec:
    """Which target: cheap, for parametrizing at collection time; :func:`target` opens it."""

    lang: str  # "opencl" or "warp": the tolerance table's backend column
    device: str  # "opencl:P:D", or Warp's alias ("cpu", "cuda:0")
    topic: str  # "pixel" or "random": the probe files and their builds
    build: str  # the tolerance table's dtype column

    def __str__(self) -> str:
        device = self.device if self.lang == "opencl" else f"warp:{self.device}"
        return f"{device}-{self.build}"


def _wanted() -> list[str] | None:
    wanted = os.environ.get("GPU_BLUR_BACKENDS")
    return wanted.split(",") if wanted else None


@functools.cache
def opencl_target_devices() -> tuple[tuple[str, bool], ...]:
    """(spec, has fp64) of the OpenCL devices the targets use; none without pyopencl."""
    try:
        from gpu_blur.backends.opencl import OpenCLError, opencl_devices, select_device
    except ImportError:
        return ()
    wanted = _wanted()
    if wanted is not None:
        return tuple((d.spec, d.fp64) for d in opencl_devices()
                     if d.usable and (d.spec in wanted or "opencl" in wanted))
    try:
        _, chosen = select_device("opencl")
    except OpenCLError:
        return ()
    return ((chosen.spec, chosen.fp64),)


@functools.cache
def warp_target_devices() -> tuple[str, ...]:
    """Warp's device aliases the targets use; none without Warp."""
    try:
        import warp as wp
    except ImportError:
        return ()
    wp.config.quiet = True
    aliases = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
    wanted = _wanted()
    if wanted is not None:
        aliases = [a for a in aliases if f"warp:{a}" in wanted or "warp" in wanted]
    return tuple(aliases)


def target_specs(topic: str, builds: list[str] | None = None,
                 langs: tuple[str, ...] = ("opencl", "warp")) -> list[TargetSpec]:
    """Every target of ``topic`` at ``builds`` (default: the topic's usual ones) that exists
    here: a build that needs cl_khr_fp64 only on a device that has it, and a build only in the
    language that has it."""
    builds = builds or DEFAULT_BUILDS[topic]
    specs = []
    if "opencl" in langs:
        for device, fp64 in opencl_target_devices():
            specs += [TargetSpec("opencl", device, topic, b) for b in builds
                      if b in OPENCL_BUILDS[topic] and (fp64 or not _needs_fp64(topic, b))]
    if "warp" in langs:
        for device in warp_target_devices():
            specs += [TargetSpec("warp", device, topic, b) for b in builds
                      if b in WARP_BUILDS[topic]]
    return specs


def _needs_fp64(topic: str, build: str) -> bool:
    real, wide, _ = OPENCL_BUILDS[topic][build]
    return np.dtype(real) == np.float64 or np.dtype(wide) == np.float64


def target_fixture(specs: list[TargetSpec]):
    """A module fixture over ``specs`` that gives each :class:`Target`; bind it to the name
    the tests ask for (``built = target_fixture(target_specs("pixel"))``). A test may narrow it
    with ``@pytest.mark.parametrize(name, other_specs, indirect=True)``."""

    @pytest.fixture(scope="module", params=specs, ids=str)
    def fixture(request):
        return target(request.param)

    return fixture


@functools.cache
def target(spec: TargetSpec) -> Target:
    """The target of ``spec``, built once per session."""
    return OpenCLTarget(spec) if spec.lang == "opencl" else WarpTarget(spec)


class Target:
    """One kernel language on one device at one build, running the topic's probes."""

    def __init__(self, spec: TargetSpec, real, wide):
        self.spec = spec
        self.lang, self.device, self.build = spec.lang, spec.device, spec.build
        self.real, self.wide = np.dtype(real), np.dtype(wide)

    def __repr__(self) -> str:
        return str(self.spec)

    def rounded(self, values) -> np.ndarray:
        """Values as the build holds them, back in float64 for the reference."""
        return np.asarray(values, dtype=np.float64).astype(self.real).astype(np.float64)

    def at(self, build: str) -> Target:
        """The same language and device at another build."""
        return target(replace(self.spec, build=build))

    def key(self, seed: int) -> list:
        """The Philox key of ``seed`` as the probes' two ``uint`` arguments."""
        from gpu_blur.reference import rng

        return [np.uint32(k) for k in rng.key_from_seed(seed)]

    def run(self, name: str, n: int, args: list, outputs: list) -> list[np.ndarray]:
        """Launch probe ``name`` over ``n`` work items (see the module docstring)."""
        raise NotImplementedError


class OpenCLTarget(Target):
    """The topic's ``.cl`` probes built with the build's defines on one OpenCL device."""

    def __init__(self, spec: TargetSpec):
        import pyopencl as cl

        from gpu_blur.backends.opencl import select_device

        real, wide, defines = OPENCL_BUILDS[spec.topic][spec.build]
        super().__init__(spec, real, wide)
        device, _ = select_device(spec.device)
        self.cl = cl
        # the context is kept: Intel's CPU runtime invalidates a context whose Python object is
        # gone even while a queue refers to it
        self.context = cl.Context([device])
        self.queue = cl.CommandQueue(self.context)
        source = (HERE / f"{spec.topic}.cl").read_text()
        options = ["-I", str(INCLUDE), "-I", str(Path(cl.__file__).parent / "cl"), *defines]
        with warnings.catch_warnings():  # the compiler's log of a successful build
            warnings.simplefilter("ignore", cl.CompilerWarning)
            program = cl.Program(self.context, source).build(options=options, cache_dir=False)
        self.kernels = {name: cl.Kernel(program, name) for name in program.kernel_names.split(";")}

    def run(self, name, n, args, outputs):
        cl = self.cl
        flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        inputs = [cl.Buffer(self.context, flags, hostbuf=np.ascontiguousarray(a).reshape(-1))
                  if isinstance(a, np.ndarray) else a for a in args]
        results = [np.empty(shape, dtype) for shape, dtype in outputs]
        buffers = [cl.Buffer(self.context, cl.mem_flags.WRITE_ONLY, max(r.nbytes, 1))
                   for r in results]
        self.kernels[name](self.queue, (n,), None, *inputs, *buffers)
        for out, buf in zip(results, buffers, strict=True):
            cl.enqueue_copy(self.queue, out, buf)
        self.queue.finish()
        return results


class WarpTarget(Target):
    """The topic's Warp probes (``<topic>_warp.py``) on one Warp device."""

    def __init__(self, spec: TargetSpec):
        import warp as wp

        real, wide = WARP_BUILDS[spec.topic][spec.build]
        super().__init__(spec, real, wide)
        self.wp = wp
        self.kernels = importlib.import_module(f"device_functions.{spec.topic}_warp").kernels(
            spec.build)
        self.types = {np.dtype(np.uint32): wp.uint32, np.dtype(np.int32): wp.int32,
                      np.dtype(np.float32): wp.float32, np.dtype(np.float64): wp.float64}

    def run(self, name, n, args, outputs):
        return self.launch(self.kernels[name], n, args, outputs)

    def launch(self, kernel, n, args, outputs):
        """:meth:`run` for a Warp kernel given itself, not by name."""
        wp = self.wp
        inputs = [wp.array(np.ascontiguousarray(a).reshape(-1), dtype=self.types[a.dtype],
                           device=self.device) if isinstance(a, np.ndarray) else
                  a.item() if isinstance(a, np.generic) else a for a in args]
        outs = [wp.empty(int(np.prod(shape)), dtype=self.types[np.dtype(dtype)],
                         device=self.device) for shape, dtype in outputs]
        wp.launch(kernel, dim=n, inputs=inputs + outs, device=self.device)
        return [o.numpy().reshape(shape) for o, (shape, _) in zip(outs, outputs, strict=True)]
