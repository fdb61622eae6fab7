"""Backends: how a plan runs. One small protocol, three implementations.

A backend carries out the plan's three passes under the stages' names, on the whole image or
on a region (a tile with its halo), and returns host arrays:

* ``accumulate(plan, params, frames, mask, region) -> (linear, mask)``: linearize and blur,
  frames read one at a time (never all in device memory at once);
* ``to_raw(plan, params, camera, linear, mask, origin, *, seed, sample_index)
  -> (image, saturated)``: saturation to the noisy white-balanced RAW mosaic;
* ``finish(plan, params, camera, image, saturated, view, out, *, seed, sample_index)
  -> rgb``: demosaic to the final (quantized) image over the ``out`` region;
* ``retone(plan, image)``: the output tone curve, also applied to the sharp reference.

Names: ``numpy`` (float64 reference), ``opencl`` (first usable OpenCL device, GPUs first),
``opencl:<platform>:<device>``, ``warp`` (CUDA if present, else the CPU), ``warp:cpu``,
``warp:cuda:<n>``.
"""

from __future__ import annotations

import functools
import os

import numpy as np

from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.reference.bayer import BayerPattern

#: Test hook, not an option: with ``GPU_BLUR_TEST_FAULT=<pass>`` or ``<pass>@<row>,<col>`` in
#: the environment (``pass`` one of accumulate, to_raw, finish), the kernel backends (OpenCL,
#: Warp) corrupt that pass's host output at global pixel (row, col) (default 0, 0) by 0.25,
#: in every tile whose output holds the pixel, so a test can check that spot checks
#: (``--verify``) catch a wrong kernel (tests/test_scheduler.py). Never set it otherwise.
TEST_FAULT = "GPU_BLUR_TEST_FAULT"


def cfa_bits(pattern: str | None) -> int:
    """The pattern's channels packed as gb_cfa_channel reads them.

    Channels at the cell offsets (0,0), (0,1), (1,0), (1,1), 2 bits each; 0 without a pattern
    (no RAW round trip).
    """
    if pattern is None:
        return 0
    return sum(c << (2 * i) for i, c in enumerate(BayerPattern(pattern).channels))


def planted_fault(pass_: str, values: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """Apply the :data:`TEST_FAULT` test hook to a pass's output (in place); returns it.

    Args:
        pass_: the pass that made ``values``.
        values: its host output, ``h x w`` or ``h x w x 3``, writable.
        origin: global (row, column) of ``values[0, 0]``.
    """
    fault = os.environ.get(TEST_FAULT)
    if not fault:
        return values
    name, _, at = fault.partition("@")
    if name.strip() != pass_:
        return values
    y, x = (int(v) for v in at.split(",")) if at else (0, 0)
    ly, lx = y - origin[0], x - origin[1]
    if 0 <= ly < values.shape[0] and 0 <= lx < values.shape[1]:
        v = values[ly, lx]
        values[ly, lx] = np.where(v < 0.5, v + 0.25, v - 0.25)
    return values


@functools.cache
def get_backend(name: str, precision: str = "float32"):
    """A backend by name; ``precision`` is the kernels' compute type.

    One instance per (name, precision) and process, so devices are opened and kernels built
    once however many samples run.
    """
    base = name.split(":", 1)[0]
    if base == "numpy":
        return NumpyBackend()
    if base == "opencl":
        from gpu_blur.backends.opencl import OpenCLBackend

        return OpenCLBackend(name, precision)
    if base == "warp":
        from gpu_blur.backends.warp import WarpBackend

        return WarpBackend(name, precision)
    raise ValueError(f"unknown backend {name!r}; available: numpy, opencl, "
                     "opencl:<platform>:<device>, warp, warp:cpu, warp:cuda:<n> (see gpu-blur "
                     "devices)")
