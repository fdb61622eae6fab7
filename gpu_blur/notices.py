"""Notices on standard error for the person running gpu-blur: kernel builds.

Kernels are built on first use in a process: an OpenCL program per device and plan variant
(``kernels/opencl/*.cl``), a Warp module per kernel and device. With nothing cached a build
compiles for seconds (about 3 s per Warp kernel on a 2-core CPU; the default scene's first
sample on ``warp:cpu`` took 8.8 s); afterwards it comes from a disk cache (pyopencl's and the
OpenCL runtime's, Warp's kernel cache) in milliseconds.

Verbosity, from the environment variable ``GPU_BLUR_VERBOSITY`` so that worker processes
(``--devices``) inherit it:

* ``0`` (:data:`QUIET`, the library's default): nothing;
* ``1`` (:data:`NORMAL`, ``gpu-blur``'s default): one line per device and process, printed
  once a build has run :data:`NOTICE_AFTER_S` (a cached build says nothing);
* ``2`` (:data:`VERBOSE`, ``gpu-blur --verbose``): also a line with each build's time.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time

from tqdm import tqdm

__all__ = ["ENV", "NOTICE_AFTER_S", "building", "say", "verbosity", "verbosity_set"]

QUIET, NORMAL, VERBOSE = 0, 1, 2
#: The environment variable that holds the verbosity.
ENV = "GPU_BLUR_VERBOSITY"
#: Seconds a build runs before the notice; 0 prints it as the build starts.
NOTICE_AFTER_S = 0.5

_announced: set[str] = set()  # devices whose notice this process printed
_lock = threading.Lock()


def verbosity() -> int:
    """The current level: ``GPU_BLUR_VERBOSITY`` (0, 1 or 2), else :data:`QUIET`."""
    text = os.environ.get(ENV, "")
    return int(text) if text in ("0", "1", "2") else QUIET


@contextlib.contextmanager
def verbosity_set(level: int):
    """Run a block (and the worker processes it starts) at ``level``, then restore."""
    before = os.environ.get(ENV)
    os.environ[ENV] = str(level)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = before


def say(line: str) -> None:
    """Print ``gpu-blur: <line>`` on standard error, clear of any progress bar.

    Nothing when there is no standard error (``sys.stderr`` is None: it was closed).
    """
    if sys.stderr is not None:
        tqdm.write(f"gpu-blur: {line}", file=sys.stderr)


def _announce(device: str) -> None:
    with _lock:
        if device in _announced:
            return
        _announced.add(device)
    say(f"compiling kernels for {device} on first use (seconds each; cached afterwards)")


@contextlib.contextmanager
def building(what: str, device: str):
    """Around a kernel build: the notices the verbosity asks for (see the module).

    Args:
        what: the build, as the verbose line names it (``kernels/opencl/to_raw.cl``,
            ``the to_raw kernel``).
        device: the device it is for (``opencl:0:0``, ``warp:cpu``).
    """
    level = verbosity()
    if level == QUIET:
        yield
        return
    timer = None
    if NOTICE_AFTER_S <= 0:
        _announce(device)
    else:
        timer = threading.Timer(NOTICE_AFTER_S, _announce, [device])
        timer.daemon = True
        timer.start()
    start = time.perf_counter()
    try:
        yield
    finally:
        if timer is not None:
            timer.cancel()
    if level >= VERBOSE:
        say(f"built {what} for {device} in {time.perf_counter() - start:.2f} s")
