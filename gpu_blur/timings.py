"""Where a sample's time goes: cheap wall-clock timers by category, one collector per thread.

Backends and the scheduler wrap their work in :func:`timer`; :func:`gpu_blur.synthesize`
returns what its call added, per category, as ``Synthesis.timings`` (a plain dict, so an
executor in another process can send it back). Categories:

* ``reading``: decoding input images;
* ``copies``: host <-> device transfers (uploads, downloads and their dtype conversions);
* ``kernels``: the passes' compute, from launch to a synchronize at the end of each pass
  (``queue.finish()`` on OpenCL, ``wp.synchronize_device`` on Warp; the numpy backend's
  passes are its compute); a transfer a driver defers to the first kernel that uses the
  buffer is counted here too, and so is a kernel's build on its first use in a process
  (:mod:`gpu_blur.notices`);
* ``checks``: spot checks against the numpy reference (:mod:`gpu_blur.scheduler`);
* ``writing``: encoding outputs (measured by ``gpu-blur generate``, not by ``synthesize``).

With I/O threads (``gpu-blur generate --io-threads``) decoding and encoding run in a pool
beside synthesis: the run's ``reading`` and ``writing`` are then the time the driver thread
waited for them, and :class:`PoolTimes` holds the threads' own work.

Timers do not nest: inside a running timer another one records nothing, so the outermost
category gets the time (a spot check's reference passes count as ``checks``, not
``kernels``). Each timer costs about a microsecond.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["CATEGORIES", "HOST_COMPUTE", "MEANING", "PoolTimes", "RunTotals", "Timings", "current",
           "since", "timer"]

CATEGORIES = ("reading", "copies", "kernels", "checks", "writing")


class Timings:
    """Seconds spent per category by one thread (see :data:`CATEGORIES`)."""

    def __init__(self):
        self.seconds = dict.fromkeys(CATEGORIES, 0.0)
        self._running = False

    def timer(self, category: str, sync: Callable[[], object] | None = None) -> _Timer:
        """A context manager adding its wall time to ``category``.

        Args:
            category: one of :data:`CATEGORIES`.
            sync: called at the end of the timed block (e.g. a device synchronize), so the
                time includes work the block only queued.
        """
        if category not in self.seconds:
            raise ValueError(f"unknown timing category {category!r}; known: "
                             f"{', '.join(CATEGORIES)}")
        return _Timer(self, category, sync)

    def snapshot(self) -> dict[str, float]:
        """A copy of the totals so far."""
        return dict(self.seconds)


class _Timer:
    __slots__ = ("_owner", "_category", "_sync", "_start")

    def __init__(self, owner: Timings, category: str, sync):
        self._owner, self._category, self._sync = owner, category, sync
        self._start = None

    def __enter__(self):
        if not self._owner._running:  # the outermost timer counts
            self._owner._running = True
            self._start = time.perf_counter()
        return self

    def __exit__(self, kind, value, traceback):
        if self._sync is not None and kind is None:
            self._sync()
        if self._start is not None:
            self._owner.seconds[self._category] += time.perf_counter() - self._start
            self._owner._running = False
        return False


_local = threading.local()


def current() -> Timings:
    """The calling thread's collector (made on first use)."""
    timings = getattr(_local, "timings", None)
    if timings is None:
        timings = _local.timings = Timings()
    return timings


def timer(category: str, sync: Callable[[], object] | None = None) -> _Timer:
    """``current().timer(category, sync)``: time a block of this thread's work."""
    return current().timer(category, sync)


def since(before: dict[str, float], total: float) -> dict[str, float]:
    """Seconds per category added since ``before`` (a :meth:`Timings.snapshot`).

    Adds ``total`` (the wall time of the whole call) and ``other`` (total minus the
    categories, at least 0).
    """
    now = current().snapshot()
    spent = {k: max(now[k] - before.get(k, 0.0), 0.0) for k in CATEGORIES}
    spent["other"] = max(total - sum(spent.values()), 0.0)
    spent["total"] = total
    return spent


#: What "kernels" holds for the numpy backend, whose passes run on the host.
HOST_COMPUTE = "the passes on the CPU (numpy float64 reference)"

#: What each category of the run summary holds, in words.
MEANING = {
    "reading": "decoding input images",
    "copies": "host <-> device transfers",
    "kernels": "device compute, synchronized after each pass (with first use's kernel builds)",
    "checks": "spot checks against the numpy reference",
    "writing": "encoding and writing outputs",
    "other": "drawing parameters, the sharp reference, scheduling, bookkeeping",
}


class RunTotals:
    """Seconds per category summed over a run's samples (``gpu-blur generate``'s summary)."""

    def __init__(self):
        self.seconds = dict.fromkeys(CATEGORIES, 0.0)

    def add(self, spent: dict) -> None:
        """Add one sample's ``Synthesis.timings`` (or any category -> seconds mapping)."""
        for category in CATEGORIES:
            self.seconds[category] += float(spent.get(category, 0.0))

    def summary(self, wall: float, on_host: bool = False) -> list[str]:
        """Lines saying where ``wall`` seconds went: each category, then ``other``.

        ``other`` is the wall time the categories leave (at least 0). Workers in other
        processes or threads add their own time, so the categories may then exceed the wall
        time; a last line says so. ``on_host``: the passes ran on the CPU (numpy backend),
        so ``kernels`` is no device's compute.
        """
        spent = dict(self.seconds)
        counted = sum(spent.values())
        spent["other"] = max(wall - counted, 0.0)
        scale = max(wall, counted, 1e-12)
        lines = [f"where the time went ({wall:.2f} s):"]
        meaning = {**MEANING, "kernels": HOST_COMPUTE} if on_host else MEANING
        for category, seconds in spent.items():
            lines.append(f"  {category:<8} {seconds:9.3f} s {100 * seconds / scale:5.1f} %  "
                         f"{meaning[category]}")
        if counted > wall * 1.01:
            lines.append(f"  (parallel workers: {counted:.2f} s of work in {wall:.2f} s)")
        return lines

    def bound(self, wall: float, pool: PoolTimes | None = None, devices: int = 1) -> str:
        """Which stage bounded a run of ``wall`` seconds, as a summary line.

        The driver thread's time (these totals) splits into decoding inputs (``reading``),
        encoding and writing outputs (``writing``) and synthesis (the rest: copies, kernels,
        checks, and the host's part of a sample: draws, plans, launches). Run one after
        another (no ``pool``), the largest is the bound; with an I/O pool decoding and writing
        are the driver's waits for the pool, and the stage it waited on most is the bound,
        with the pool's own figure for it (:meth:`PoolTimes.ceiling`): what more cores give.
        With ``devices`` worker processes (``--devices``) each waits for its own inputs:
        ``reading`` holds their waits summed, and the bound takes their mean; so for
        ``writing`` where the workers wrote their samples' files (``pool.handoff["written"]``).
        """
        written = pool is not None and pool.handoff["written"] > 0
        spent = {"decode": self.seconds["reading"] / devices,
                 "encode/write": self.seconds["writing"] / (devices if written else 1)}
        spent["synthesis"] = max(wall - sum(spent.values()), 0.0)
        stage = max(spent, key=spent.get)
        share = 100 * spent[stage] / max(wall, 1e-12)
        if pool is None:
            return (f"bound by: {stage} ({share:.0f} % of the run; one thread decodes, "
                    "synthesizes and writes in turn)")
        how = {"decode": f"synthesis waited {share:.0f} % of the run for decoded inputs; "
                         f"{pool.ceiling('decode')}",
               "encode/write": f"synthesis waited {share:.0f} % of the run for writes; "
                               f"{pool.ceiling('write')}",
               "synthesis": f"synthesizing {share:.0f} % of the run, on the host and the "
                            "device"}[stage]
        return f"bound by: {stage} ({how}; I/O threads busy {pool.busy_share(wall):.0f} %)"


class PoolTimes:
    """Seconds a pool of I/O threads spent per stage, and what the driver waited for it.

    A ``--devices`` worker's pool crosses to the driver pickled (its figures, not its lock),
    where :meth:`add` counts it in the run's.

    Attributes:
        threads: the pool's threads.
        busy: seconds of ``decode`` (files decoded, samples' checks and staging) and
            ``write`` (a sample each) work, summed over the threads.
        calls: the counted tasks of each: files decoded, samples written.
        samples: samples whose inputs the pool decoded.
        waited_for_inputs: seconds the driver thread waited for decoded inputs (summed over
            the workers' threads that make samples, with ``--devices``).
        waited_for_writes: with ``--devices`` workers that write their samples' files, the
            seconds their making threads waited for those writes, summed.
        handoff: ``--devices`` results on their way to the driver: seconds the workers'
            making threads spent handing them over (``packing``: converting them and copying
            them into shared memory, a free block waited for), seconds the driver's thread
            spent taking them (``receiving``: the pipe read, the arrays copied out, the next
            sample sent) and waiting for any (``waiting``), the ``samples`` taken, and how
            many of them came whole through a pipe (``piped``: no shared memory to be had) or
            as a manifest line, their files written by the worker (``written``).
        deflated: PNG files whose streams the GPU deflated (gpu_blur.png_device), which the
            threads only put together and wrote.
    """

    def __init__(self, threads: int):
        self.threads = threads
        self.busy = {"decode": 0.0, "write": 0.0}
        self.calls = {"decode": 0, "write": 0}
        self.samples = 0
        self.waited_for_inputs = 0.0
        self.waited_for_writes = 0.0
        self.handoff = {"packing": 0.0, "receiving": 0.0, "waiting": 0.0, "samples": 0,
                        "piped": 0, "written": 0}
        self.deflated = 0
        self._lock = threading.Lock()

    def run(self, stage: str, work: Callable[..., Any], *args, counted: bool = True) -> Any:
        """``work(*args)`` in a pool thread, its time added to ``busy[stage]``.

        ``counted``: the task is one of ``calls[stage]`` (a file decoded, a sample written);
        a sample's checks or staging on their own are not.
        """
        start = time.perf_counter()
        try:
            return work(*args)
        finally:
            with self._lock:
                self.busy[stage] += time.perf_counter() - start
                self.calls[stage] += counted

    def add(self, other: PoolTimes) -> None:
        """Count another pool's threads, work and waits as this one's."""
        with self._lock:
            self.threads += other.threads
            for stage in self.busy:
                self.busy[stage] += other.busy[stage]
                self.calls[stage] += other.calls[stage]
            self.samples += other.samples
            self.waited_for_inputs += other.waited_for_inputs
            self.waited_for_writes += other.waited_for_writes
            self.deflated += other.deflated
            self._add_handoff(other.handoff)

    def add_handoff(self, **figures) -> None:
        """Add figures to :attr:`handoff` (``packing=...``, ``samples=...``)."""
        with self._lock:
            self._add_handoff(figures)

    def _add_handoff(self, figures: dict) -> None:  # with the lock held
        for key, value in figures.items():
            self.handoff[key] += value

    def __getstate__(self) -> dict:
        with self._lock:
            return {**self.__dict__, "busy": dict(self.busy), "calls": dict(self.calls),
                    "handoff": dict(self.handoff), "_lock": None}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _lock=threading.Lock())

    def ceiling(self, stage: str) -> str:
        """The samples a second these threads allow, in words, ``stage``'s time named first.

        Where the same threads decode a sample's files and encode and write its outputs (one
        process; ``--devices`` workers that write their samples' files), from the thread time
        a sample took at both: ``threads`` such threads make at most ``threads / (decode +
        write)`` samples a second, if the work scales with them (codecs that hold the GIL,
        or memory bandwidth, may not). Where the driver's threads write what workers decoded,
        from ``stage``'s time alone. ``stage``: ``decode`` or ``write``.
        """
        words = {"decode": ("decoding a sample's inputs", "decoding its inputs"),
                 "write": ("encoding and writing a sample", "encoding and writing it")}
        per = {s: self.busy[s] / n for s, n in (("decode", self.samples),
                                                  ("write", self.calls["write"]))
               if n and self.busy[s]}
        if self.handoff["samples"] and not self.handoff["written"]:  # other threads each
            per = {s: seconds for s, seconds in per.items() if s == stage}
        if stage not in per:
            return f"the threads {'decoded' if stage == 'decode' else 'wrote'} nothing"
        line = f"{words[stage][0]} took a thread {1e3 * per[stage]:.1f} ms"
        for other, seconds in per.items():
            if other != stage:
                line += f" and {words[other][1]} {1e3 * seconds:.1f} ms"
        return (f"{line}, so {self.threads} threads make at most "
                f"{self.threads / sum(per.values()):.1f} samples/s: more cores, more")

    def busy_share(self, wall: float) -> float:
        """Percent of the threads' time over ``wall`` seconds they spent working."""
        return 100 * sum(self.busy.values()) / max(self.threads * wall, 1e-12)

    def handoff_summary(self) -> str | None:
        """One line on ``--devices`` results handed to the driver (:attr:`handoff`), or None.

        Where the driver's thread takes results about as fast as they come (little
        waiting), it, not the devices, bounds the run.
        """
        h = self.handoff
        if not h["samples"]:
            return None
        each = 1e3 / h["samples"]
        if h["written"]:  # only manifest lines crossed (a run writes one way)
            return (f"hand-off: the workers wrote their samples' files; the driver's thread "
                    f"{h['receiving']:.2f} s ({h['receiving'] * each:.1f} ms a sample) taking "
                    f"their manifest lines and {h['waiting']:.2f} s waiting for the workers")
        line = (f"hand-off: the workers' making threads {h['packing']:.2f} s "
                f"({h['packing'] * each:.1f} ms a sample) handing results over, the driver's "
                f"thread {h['receiving']:.2f} s ({h['receiving'] * each:.1f} ms a sample) "
                f"taking them and {h['waiting']:.2f} s waiting for the workers")
        piped = h["piped"]
        if piped:  # slower: pickled through a pipe into the driver's one thread
            line += (f"; {piped} of {h['samples']} samples came through the workers' pipes, "
                     "no shared memory being had (a full or small /dev/shm? `df -h /dev/shm`; "
                     "in Docker, `--shm-size`)")
        return line

    def summary(self, wall: float) -> str:
        """One line: the threads, what they did, and how busy they were."""
        files = self.calls["decode"]
        each = f" ({files} files, {1e3 * self.busy['decode'] / files:.1f} ms each)" if files else ""
        gpu = f" ({self.deflated} PNG files deflated on the GPU)" if self.deflated else ""
        return (f"I/O threads ({self.threads}): decoding {self.busy['decode']:.2f} s{each}, "
                f"encoding and writing {self.busy['write']:.2f} s{gpu}; busy "
                f"{self.busy_share(wall):.0f} % of the run")
