"""Backends: how the plan runs (numpy reference now; OpenCL and Warp kernels next).

A backend carries out the plan's three passes under the stages' names: ``accumulate`` (blur in
linear light, with the saturation mask), ``to_raw`` (saturation to noisy white-balanced RAW)
and ``finish`` (demosaic to the final image).
"""

from __future__ import annotations

from gpu_blur.backends.numpy import NumpyBackend

BACKENDS = {"numpy": NumpyBackend}


def get_backend(name: str):
    """A backend instance by name (``numpy``)."""
    base = name.split(":", 1)[0]
    if base not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; available: {', '.join(BACKENDS)}")
    return BACKENDS[base]()
