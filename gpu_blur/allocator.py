"""glibc's malloc set for a process whose threads decode and encode large images.

Each 8-bit 1920 x 1200 PNG frame that ``generate`` decodes passes through two buffers of
6.9 MB (the inflated rows, then the pixels: :func:`gpu_blur.png_codecs.decode_png`), made
and freed by many I/O threads at once. With glibc's defaults a thread's heap hands memory
freed at its top back to the kernel once more than twice the largest block freed so far lies
there, so the next frame's pages are mapped and zeroed again. :data:`SETTINGS` keep freed
memory in the process instead, for the next frame: on one H200's 16-core host
(``bench/decode_threads.py``, 2,304 such frames through 16 threads, at 74843aa) a frame took
a thread 42.8 ms with glibc's own settings and 26.7 ms with these (medians of two rounds;
bench/results/decode_threads_h200.json); ``generate`` over 256 distinct windows gained less
(docs/performance.md, "Whole sets from disk"). The process keeps the most it held (which the
run's queues bound, :data:`gpu_blur.generate.QUEUE_PER_THREAD`) until it ends.

``gpu-blur generate`` and the device workers it starts call :func:`keep_freed_memory`;
``generate_set`` from Python leaves the calling process's allocator as it is. Set
``GPU_BLUR_MALLOC=glibc`` (or any ``MALLOC_*`` variable glibc reads) to keep glibc's own
settings. Pixels never depend on it.
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Mapping

__all__ = ["ENV", "SETTINGS", "keep_freed_memory"]

#: The environment variable that chooses: ``keep`` (the default) or ``glibc``.
ENV = "GPU_BLUR_MALLOC"
#: ``mallopt`` parameters, from glibc's malloc.h.
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
#: What :func:`keep_freed_memory` sets: blocks up to 32 MiB come from the heaps (a frame of
#: 16-bit 1920 x 1200 RGB is 13.8 MB), a heap returns memory to the kernel only past 1 GiB
#: free at its top, and grows 64 MiB more than it needs at a time. Setting any of them turns
#: off glibc's own adjustment of the first two (mallopt(3)).
SETTINGS = {M_MMAP_THRESHOLD: 32 << 20, M_TRIM_THRESHOLD: 1 << 30, M_TOP_PAD: 64 << 20}


def keep_freed_memory(environ: Mapping[str, str] = os.environ, libc=None) -> str:
    """Set :data:`SETTINGS` in this process where glibc's malloc runs it; say what was done.

    ``libc``: the C library to call (tests); by default this process's, if it is glibc.

    Returns:
        A line for the user: what the allocator now does.

    Raises:
        ValueError: :data:`ENV` holds something other than ``keep`` or ``glibc``.
    """
    choice = environ.get(ENV, "keep")
    if choice not in ("keep", "glibc"):
        raise ValueError(f"{ENV}={choice!r}: use keep (freed memory kept for the next "
                         "image, the default) or glibc (glibc's own settings)")
    if choice == "glibc":
        return f"malloc: glibc's own settings ({ENV}=glibc)"
    named = sorted(name for name in environ if name.startswith("MALLOC_"))
    if named:
        return f"malloc: as {', '.join(named)} set it"
    if libc is None:
        libc = _glibc()
    if libc is None:
        return "malloc: the C library's own (not glibc)"
    for parameter, value in SETTINGS.items():
        if libc.mallopt(parameter, value) != 1:
            return f"malloc: glibc refused mallopt({parameter}, {value}); its own settings"
    return "malloc: freed memory kept for the next image (glibc, mallopt)"


def _glibc():
    """The C library of this process if it is glibc (Linux), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return None
    if not hasattr(libc, "gnu_get_libc_version") or not hasattr(libc, "mallopt"):
        return None  # musl and others: their allocators take no such settings
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.mallopt.restype = ctypes.c_int
    return libc
