"""Decoded input frames shared by the samples that use them, within a memory budget.

Windows of one sequence overlap whenever a set asks for more windows than fit side by side
(``--samples-per-sequence``, a window stride shorter than the window): without a cache each
window decodes its frames again. :class:`FrameCache` decodes each file once while it stays
within the budget, least recently used first out. :meth:`FrameCache.claim` hands out a frame's
future without taking a thread: only the first sample to ask for a file gets the decode to run
(in an I/O thread); the others get the same future, so no thread waits on another's decode.

A cached frame is the reader's array made read-only (``writeable = False``), so no sample can
change what another sample reads. A file is known by its path and its ``os.stat`` identity
(device, inode, size, modification time): a file replaced during a run is decoded again.
"""

from __future__ import annotations

import collections
import os
import threading
from collections.abc import Callable
from concurrent.futures import CancelledError, Future
from dataclasses import astuple, dataclass, fields
from pathlib import Path

import numpy as np

__all__ = ["CacheCounts", "Decode", "FrameCache", "default_budget", "uncached"]

#: The share of the host's physical memory :func:`default_budget` gives the cache.
MEMORY_SHARE = 1 / 8
#: :func:`default_budget`'s ceiling, in bytes (1 GiB holds 150 decoded 1920 x 1200 8-bit frames).
MAX_DEFAULT_BYTES = 1 << 30


def default_budget() -> int:
    """Bytes of decoded frames a run keeps by default: 1/8 of physical memory, at most 1 GiB."""
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):  # not POSIX (Windows): the ceiling
        return MAX_DEFAULT_BYTES
    return int(min(MAX_DEFAULT_BYTES, physical * MEMORY_SHARE))


@dataclass(frozen=True)
class CacheCounts:
    """What a cache did.

    ``hits``: frames served decoded (waits on another thread's decode included); ``misses``:
    files decoded; ``evicted``: frames dropped to stay in the budget.
    """

    hits: int
    misses: int
    evicted: int

    def summary(self) -> str:
        """One line for a run's summary."""
        asked = self.hits + self.misses
        share = f" ({100 * self.hits / asked:.0f} % of {asked} reads)" if asked else ""
        return (f"frame cache: {self.misses} decoded, {self.hits} served decoded{share}, "
                f"{self.evicted} evicted")

    def __sub__(self, earlier: CacheCounts) -> CacheCounts:
        """What the cache did since it counted ``earlier``."""
        return CacheCounts(*(now - then for now, then in zip(astuple(self), astuple(earlier),
                                                             strict=True)))


class FrameCache:
    """Decoded frames by file, at most ``budget`` bytes of them; safe to share across threads.

    Args:
        budget: bytes of decoded frames kept; 0 keeps none (every read decodes, as before).
    """

    def __init__(self, budget: int):
        if budget < 0:
            raise ValueError(f"frame cache budget: {budget} bytes; give 0 or more")
        self.budget = budget
        self._frames: collections.OrderedDict[tuple, np.ndarray] = collections.OrderedDict()
        self._pending: dict[tuple, Future] = {}
        self._bytes = 0
        self._lock = threading.Lock()
        self._counts = dict.fromkeys((f.name for f in fields(CacheCounts)), 0)

    def read(self, path: str | Path, reader: Callable[[Path], np.ndarray]) -> np.ndarray:
        """``reader(path)``'s array, read-only, decoded once while it stays in the budget.

        :meth:`claim`'s frame, decoded here if no other thread is decoding it, else waited for.
        """
        future, decode = self.claim(path, reader)
        if decode is not None:
            decode()
        return future.result()

    def claim(self, path: str | Path, reader: Callable[[Path], np.ndarray]
              ) -> tuple[Future, Decode | None]:
        """(the future of ``path``'s frame, the decode that sets it or None).

        The future is done when the frame is cached; a frame being decoded gives that decode's
        future and None; else the caller gets the new future and its :class:`Decode` to run
        (in an I/O thread). Kept by file and reader: readers give different arrays of one file
        (a JPEG's checked bytes for nvJPEG, its pixels for everything else). A reader's
        exception is set on the future, for every sample waiting on that file, and nothing
        is kept.

        Raises:
            OSError: ``path`` cannot be looked at (``os.stat``).
        """
        path = Path(path)
        if self.budget == 0:
            with self._lock:
                self._counts["misses"] += 1
            return uncached(path, reader)
        key = (*_identity(path), reader)
        with self._lock:
            frame = self._frames.get(key)
            if frame is not None:
                self._frames.move_to_end(key)
                self._counts["hits"] += 1
                done = Future()
                done.set_result(frame)
                return done, None
            pending = self._pending.get(key)
            if pending is not None:
                self._counts["hits"] += 1
                return pending, None
            self._pending[key] = mine = Future()
            self._counts["misses"] += 1
        return mine, Decode(self, key, path, reader, mine)

    def counts(self) -> CacheCounts:
        """The hits, misses and evictions so far."""
        with self._lock:
            return CacheCounts(**self._counts)

    def add(self, counts: CacheCounts) -> None:
        """Count what a cache elsewhere did as this one's (``--devices``: each worker's share)."""
        with self._lock:
            for name in self._counts:
                self._counts[name] += getattr(counts, name)

    def _settled(self, key: tuple, frame: np.ndarray | None) -> None:
        """A decode of ``key`` ended: no longer pending, its frame (if any) kept."""
        with self._lock:
            del self._pending[key]
            if frame is not None:
                self._keep(key, frame)

    def _keep(self, key: tuple, frame: np.ndarray) -> None:
        """Keep ``frame``, dropping the least recently used ones past the budget (lock held)."""
        if frame.nbytes > self.budget:
            return
        self._frames[key] = frame
        self._bytes += frame.nbytes
        while self._bytes > self.budget:
            _, dropped = self._frames.popitem(last=False)
            self._bytes -= dropped.nbytes
            self._counts["evicted"] += 1


class Decode:
    """One file's decode for :meth:`FrameCache.claim`: run it once, or :meth:`abandon` it.

    Running it sets the future every sample of that file waits on (its array read-only and
    kept in the cache, or the reader's exception); with ``key`` None (a budget of 0) the array
    is the reader's, as it is, and nothing is kept (so too with no cache).
    """

    def __init__(self, cache: FrameCache | None, key: tuple | None, path: Path,
                 reader: Callable[[Path], np.ndarray], future: Future):
        self._cache, self._key, self._path = cache, key, path
        self._reader, self.future = reader, future

    def __call__(self) -> None:
        """Decode the file and settle the future (the reader's error goes on it, not up)."""
        try:
            frame = self._reader(self._path)
            if self._key is not None:
                frame.flags.writeable = False
        except BaseException as error:
            self._settle(None, error)
            if not isinstance(error, Exception):
                raise
            return
        self._settle(frame, None)

    def abandon(self) -> None:
        """The decode will not run (its task was cancelled): waiting samples see CancelledError."""
        self._settle(None, CancelledError(f"{self._path}: not decoded, the run stopped"))

    def _settle(self, frame: np.ndarray | None, error: BaseException | None) -> None:
        if self._key is not None:
            self._cache._settled(self._key, frame)
        if error is None:
            self.future.set_result(frame)
        else:
            self.future.set_exception(error)


def uncached(path: str | Path, reader: Callable[[Path], np.ndarray]) -> tuple[Future, Decode]:
    """(a future, the :class:`Decode` that sets it): one file's decode, kept nowhere.

    The reader's array as it is, for one sample alone (a cache of budget 0, or none).
    """
    future = Future()
    return future, Decode(None, None, Path(path), reader, future)


def _identity(path: Path) -> tuple:
    """A file's path and stat identity.

    A path that cannot be stat'ed is known by name only (its reader then says what is wrong).
    """
    try:
        stat = os.stat(path)
    except OSError:
        return (str(path),)
    return (str(path), stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
