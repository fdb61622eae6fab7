"""Making a set's samples in parallel: one process per device of this host, or a Ray cluster.

Both executors keep the contract of :func:`gpu_blur.generate.run_serial`: they take a
:class:`~gpu_blur.generate.Job` and the samples' specs and yield ``(spec, result, error)`` as
samples finish, in any order; the driver (``gpu-blur generate``) writes the files and the
manifest, except that device workers making a set of PNG files write their samples' files
themselves and send the manifest lines (:func:`run_devices`' ``writes``). A sample depends
only on (seed, index, scene), so the files are those of a serial run, byte for byte,
whichever worker makes which sample (on devices of one model: two GPU models, or a GPU and a
CPU, may differ in a float32 last bit).

What crosses a process boundary: the job (a few hundred bytes, once per worker), each
:class:`~gpu_blur.discovery.SampleSpec` (index, name, input paths) and each result (the
:class:`~gpu_blur.synthesis.Synthesis` with only what the set writes,
:func:`~gpu_blur.generate.for_driver`: blurred and sharp as the set's integer codes, the mask
and the RAW mosaic if saved, the drawn parameters and the plan; 14 MB for a 1920 x 1200 sample
at 8 bits). A device worker on this host that does not write the files writes a result's
arrays into shared memory and sends the rest through its pipe (:mod:`gpu_blur.shared_results`:
a pipe took 31 such samples a second into the driver's one receiving thread); a Ray task
returns its results through Ray's object store. Workers read the inputs themselves from the
spec's paths, so on a Ray cluster the inputs (and gpu_blur, in the same version) must be at
the same paths on every node.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import wait

from gpu_blur import caches, testhooks
from gpu_blur.backends import usable_devices
from gpu_blur.dataset import FolderWrites
from gpu_blur.discovery import SampleSpec
from gpu_blur.frame_cache import CacheCounts, FrameCache
from gpu_blur.generate import (
    QUEUE_PER_THREAD,
    Job,
    Saved,
    WriteBehind,
    default_io_threads,
    for_driver,
    make_sample,
    pinned_staging,
    run_pipelined,
    run_serial,
    usable_cores,
)
from gpu_blur.shared_results import ASK, Blocks, Outbox, send
from gpu_blur.timings import PoolTimes

__all__ = ["DEVICE_DEPTH", "DRIVER_SIGNALS", "GPU_BATCH", "PARENT_CHECK_S", "RAY_INSTALL",
           "RUN_SAMPLES", "DeviceWorkers", "all_devices", "family", "import_ray", "parse_devices",
           "pick_executor", "run_devices", "run_ray", "uses_cuda"]

RAY_INSTALL = "pip install 'gpu_blur[ray]'"
#: Samples per Ray task on GPUs. Ray starts a fresh worker process for every GPU task (its
#: default ``max_calls=1``, which pins the process to the GPU Ray assigned and frees that
#: GPU's memory afterwards), so each task pays a process start, imports and the backend's
#: set-up: 0.6 to 0.9 s on 2 CPU cores (numpy, OpenCL, Warp CPU), more with a CUDA context;
#: a batch spreads that over its samples. CPU tasks reuse their worker processes, where a
#: task costs about 6 ms more than the sample itself, round trip, and one sample per task
#: keeps the load balanced and a retry small.
GPU_BATCH = 32
#: Samples handed to one local device worker ahead of the one it makes, so it never waits,
#: besides two per decoding thread (they decode ahead).
DEVICE_DEPTH = 2
#: The most consecutive samples that share input files (overlapping windows of a sequence,
#: draws of one photo) a device worker is sent in a row: its frame cache decodes a frame they
#: share once. A longer run decodes fewer frames twice (a run of 16 windows of 7 frames, one
#: frame apart, decodes 22 frames instead of 112) but keeps more of the driver's manifest
#: lines waiting for an earlier sample, and more samples on one worker at the end of a set.
RUN_SAMPLES = 16
#: Seconds between a device worker's checks that the driver process is still its parent.
PARENT_CHECK_S = 0.5


def family(backend: str) -> str:
    """The backend family of a device name: ``numpy``, ``opencl`` or ``warp``."""
    return backend.split(":", 1)[0]


# -- device names --------------------------------------------------------------------------

def all_devices(backend: str, precision: str = "float32") -> list[str]:
    """What ``--devices all`` stands for with a backend.

    numpy: a worker per core this process may run on (:func:`usable_cores`); opencl: every
    usable OpenCL GPU, or every usable OpenCL device when there is no GPU (a CPU runtime
    beside GPUs would be slow, share the driver's cores and round float32 differently); warp:
    every CUDA device, else ``warp:cpu``.
    """
    kind = family(backend)
    if kind == "numpy":
        return ["numpy"] * usable_cores()
    names, unusable = usable_devices(kind, precision)
    if kind == "opencl":
        gpus = [n for n in names if _is_opencl_gpu(n)]
        names = gpus or names
    if kind == "warp":
        names = [n for n in names if n.startswith("warp:cuda")] or ["warp:cpu"]
    if not names:
        why = "; ".join(f"{n}: {p}" for n, p in unusable.items()) or "none found"
        raise ValueError(f"--devices all: no usable {kind} device here ({why}); see "
                         "`gpu-blur devices`")
    return names


def counted_devices(backend: str) -> list[str] | None:
    """What ``--devices all`` will most likely stand for, counted without opening a runtime.

    For starting the workers early (:func:`gpu_blur.generation.early_workers`), before
    :func:`all_devices` (which opens Warp or OpenCL, a second or so) says what it stands for.
    numpy: :func:`all_devices`' list. warp: ``warp:cuda:N`` for each device the CUDA driver
    counts (libcuda's ``cuDeviceGetCount``, ``CUDA_VISIBLE_DEVICES`` applied); None where
    it counts none or cannot be loaded (``warp:cpu`` then, found late). opencl: None (no
    count without the runtime). Workers started for a list :func:`all_devices` does not
    confirm are stopped, and the right ones started.
    """
    kind = family(backend)
    if kind == "numpy":
        return all_devices(backend)
    if kind != "warp":
        return None
    count = _cuda_device_count()
    return [f"warp:cuda:{i}" for i in range(count)] if count else None


def _cuda_device_count() -> int | None:
    """CUDA devices the NVIDIA driver counts for this process, or None without a driver."""
    import ctypes

    try:
        cuda = ctypes.CDLL("nvcuda.dll" if os.name == "nt" else "libcuda.so.1")
    except OSError:
        return None
    count = ctypes.c_int(0)
    if cuda.cuInit(0) != 0 or cuda.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return None  # CUDA_SUCCESS is 0 (cuda.h)
    return count.value


def _is_opencl_gpu(name: str) -> bool:
    from gpu_blur.backends.opencl import opencl_devices

    return any(d.spec == name and d.kind == "GPU" for d in opencl_devices())


def parse_devices(text: str, backend: str, precision: str = "float32") -> list[str]:
    """The worker devices of ``--devices``: ``all`` or a comma list (a name may repeat).

    Every device must belong to ``--backend``'s family (samples of different backends differ
    in their last bits, and the manifest names one backend) and be usable here.

    Raises:
        ValueError: naming the device, what is wrong and the devices present.
    """
    kind = family(backend)
    if text.strip() == "all":
        return all_devices(backend, precision)
    names = [n.strip() for n in text.split(",")]
    if not all(names):
        raise ValueError(f"--devices {text!r}: an empty device name; give 'all' or names "
                         "separated by commas, e.g. opencl:0:0,opencl:1:0")
    present, unusable = usable_devices(kind, precision)
    aliases = [kind] if kind != "numpy" else []
    for name in names:
        listed = ", ".join(present + aliases) or "none"
        if family(name) != kind:
            raise ValueError(f"--devices {name}: not a {kind} device (--backend {backend}); "
                             "one set is made with one backend, whose samples differ from "
                             f"another's in the last bits; {kind} devices here: {listed} "
                             "(or pass the --backend that device belongs to)")
        if name in unusable:
            raise ValueError(f"--devices {name}: {unusable[name]}")
        if name not in present and name not in aliases:
            raise ValueError(f"--devices {name}: no such device; {kind} devices here: "
                             f"{listed} (see `gpu-blur devices`)")
    return names


def uses_cuda(backend) -> bool:
    """Whether a backend object runs on an NVIDIA GPU (Warp on CUDA, OpenCL on NVIDIA's GPU)."""
    return backend.uses_cuda


# -- one worker process per device of this host ---------------------------------------------

@contextlib.contextmanager
def _children_skip_cwd():
    """While it holds, the Pythons multiprocessing starts do not import from the current folder.

    ``spawn`` starts a worker (and multiprocessing's resource tracker) as ``python -c ...``,
    which puts the current folder first on ``sys.path`` before it imports ``multiprocessing``:
    a ``multiprocessing`` package (or any module imported that early) in the folder gpu-blur
    runs from would run in every worker. Python 3.11+: ``PYTHONSAFEPATH=1`` in the environment
    they inherit. Otherwise (3.10, or ``-E``, which the children repeat) they start in
    gpu_blur's private cache folder, and each worker goes back to the driver's folder
    (:func:`_device_worker`'s ``cwd``).
    """
    if getattr(sys.flags, "safe_path", False) or sys.flags.isolated:
        yield  # -P or -I: the children get the same flag
    elif sys.version_info >= (3, 11) and not sys.flags.ignore_environment:
        saved = os.environ.get("PYTHONSAFEPATH")
        os.environ["PYTHONSAFEPATH"] = "1"
        try:
            yield
        finally:
            if saved is None:
                del os.environ["PYTHONSAFEPATH"]
            else:
                os.environ["PYTHONSAFEPATH"] = saved
    else:
        here = os.getcwd()
        os.chdir(caches.root())
        try:
            yield
        finally:
            os.chdir(here)


def _device_worker(job: Job, driver: int, conn, threads: int = 1,
                   cwd: str | None = None) -> None:
    """A device worker process: open the device, then make each sample the driver sends.

    Once the device is open the driver sends the run's part that was not known when the
    worker started (:meth:`DeviceWorkers.open`): ``("setup", (shared, cache_bytes, writes))``.

    With ``threads`` > 1 the worker runs the one-device pipeline
    (:func:`gpu_blur.generate.run_pipelined`, as a run on one device does): that many
    threads decode the input files of the samples waiting in the pipe while the device makes
    the current ones, and on a GPU stage them in page-locked memory for batches of
    :data:`gpu_blur.generate.BATCH`; the samples are made and sent in the order they came.
    ``cache_bytes`` > 0: the files are decoded through a frame cache of that many bytes of
    this worker's own (:class:`~gpu_blur.frame_cache.FrameCache`), so windows of a sequence
    that overlap decode a frame once. With ``writes`` the worker writes each made sample's
    files itself, in the same threads (:class:`~gpu_blur.generate.WriteBehind`, as a run on
    one device does), and sends the driver only the manifest line.

    Messages to the driver: ``("open", device description)`` or ``("error", why)`` first,
    then per sample ``("sample", (spec, result, error, layout, counts, times))`` (``result``
    as :func:`~gpu_blur.generate.for_driver` leaves it, or with ``writes`` a
    :class:`~gpu_blur.generate.Saved`; with ``shared`` its arrays are in
    the shared-memory block ``layout`` names, :class:`gpu_blur.shared_results.Outbox`, else
    ``layout`` is None; ``counts``: the frame cache's counts since the last message, or None;
    ``times``: the decoding threads' :class:`~gpu_blur.timings.PoolTimes` so far, with the
    hand-off's packing, none for a worker that decodes in turn)
    or ``("error", traceback)`` for an exception that is no fault of the sample (a bug: the
    driver stops the run with it). The driver closing its end of the pipe ends the worker.
    ``cwd``: the driver's folder, where relative paths lead (a worker may start elsewhere:
    :func:`_children_skip_cwd`).
    """
    if cwd is not None and os.getcwd() != cwd:
        os.chdir(cwd)
    # Ctrl-C and a closed terminal reach the whole process group: the driver handles them
    # and stops the workers (SIGTERM, which they obey); blocked since the start
    # (_driver_signals_blocked), so that none came while importing
    for s in DRIVER_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, DRIVER_SIGNALS)
    held: list[Outbox] = []  # what to unlink if the driver dies
    threading.Thread(target=_exit_without, args=(driver, held), daemon=True).start()
    from gpu_blur.backends import get_backend

    try:
        opened = ("open", get_backend(job.backend, job.scene.output.precision).device)
    except Exception as e:  # any reason the device cannot be opened
        opened = ("error", str(e))
    try:
        send(conn, opened)
    except EOFError:  # the driver is gone
        return
    if opened[0] == "error":
        return
    try:
        _, (shared, cache_bytes, writes) = conn.recv()
    except EOFError:  # the run ended before it began (a set-up error, nothing to make)
        return
    pool = ThreadPoolExecutor(threads, "gpu-blur-decode") if threads > 1 else None
    # its decoding threads' times (none without a pool) and its hand-off's
    times = PoolTimes(threads if pool is not None else 0)
    cache = FrameCache(cache_bytes) if cache_bytes > 0 else None
    arrived: deque[SampleSpec] = deque()  # samples sent, not yet taken by the pipeline
    outbox = Outbox(conn, arrived.append) if shared else None
    if outbox is not None:
        held.append(outbox)

    def receive(wait: bool) -> bool:
        """Take the driver's messages: those waiting, or (``wait``) until a sample came.

        False once the driver closed its end (the run is over).
        """
        try:
            while (wait and not arrived) or conn.poll():
                message = conn.recv()
                if outbox is None or not outbox.take(message):
                    arrived.append(message)
        except EOFError:
            return False
        return True

    counted = CacheCounts(0, 0, 0)  # the frame cache's counts sent so far

    def sent(spec, result, error, layout=None) -> None:
        nonlocal counted
        counts = None
        if cache is not None:  # what the driver's summary has not counted yet
            now = cache.counts()
            counts, counted = now - counted, now
        send(conn, ("sample", (spec, result, error, layout, counts, times)))

    behind = (WriteBehind(functools.partial(_write_made, writes, driver), pool,
                          QUEUE_PER_THREAD * threads, times) if writes is not None else None)

    def written(waiting: Iterator[tuple]) -> None:
        """Send the samples ``behind`` hands back written, timing this thread's wait."""
        start = time.perf_counter()
        for spec, error, saved in waiting:
            times.waited_for_writes += time.perf_counter() - start
            sent(spec, saved, error)
            start = time.perf_counter()
        times.waited_for_writes += time.perf_counter() - start

    def more() -> bool:
        """Wait for the driver's next sample; False once it closed its end."""
        if behind is not None:  # it sends one for each it gets: those written go first
            written(behind.drain())
        return receive(True) and bool(arrived)

    try:
        if pool is not None:  # this device's one-device pipeline (batches, staging on a GPU)
            samples = run_pipelined(job, _Arrived(arrived, receive), pool, times,
                                    worker_depth(threads), cache, pinned_staging(job),
                                    more=more)
        else:
            samples = run_serial(job, iter(lambda: arrived.popleft() if more() else None,
                                           None), cache)
        for spec, result, error in samples:
            if behind is not None:  # its files written here: the line goes to the driver
                written(behind.put(spec, result, error))
                continue
            start = time.perf_counter()
            result, layout = for_driver(job, result), None
            if outbox is not None:
                result, layout = outbox.pack(result)
            times.add_handoff(packing=time.perf_counter() - start)
            sent(spec, result, error, layout)
        if behind is not None:
            written(behind.drain())
    except EOFError:  # the driver closed its end (or was killed): the run is over
        return
    except Exception:  # no fault of a sample (make_sample returns those): a bug, reported
        with contextlib.suppress(EOFError):  # the driver is gone: no one to report it to
            send(conn, ("error", traceback.format_exc()))
    finally:
        if outbox is not None:
            outbox.close()
        if pool is not None:
            pool.shutdown(cancel_futures=True)


def _write_made(writes: FolderWrites, driver: int, spec: SampleSpec, result) -> Saved:
    """A made sample's files, written in a worker (an I/O thread); what the driver gets.

    Each file is renamed into place only while ``driver`` is this process's parent: a worker
    whose driver was killed (which released the folder's lock) leaves no file behind it.
    """
    def driver_alive(_temporary) -> None:
        if os.getppid() != driver:
            raise OSError("the driver process is gone: the folder is no longer this run's")

    try:
        return Saved(writes.write(spec, result, driver_alive), result.timings)
    except OSError as e:  # a full disk, a folder gone: the driver stops the run with it
        return Saved(None, result.timings, e)


class _Arrived:
    """The samples a device worker was sent, as far as they came.

    It ends (for now) when none is waiting; :func:`~gpu_blur.generate.run_pipelined` then
    asks its ``more`` when it has nothing ahead.
    """

    def __init__(self, arrived: deque, receive: Callable[[bool], bool]):
        self._arrived, self._receive = arrived, receive

    def __iter__(self):
        return self

    def __next__(self) -> SampleSpec:
        if not self._receive(False) or not self._arrived:
            raise StopIteration
        return self._arrived.popleft()


def worker_depth(threads: int, writing: bool = False) -> int:
    """Samples sent ahead to a device worker with ``threads`` I/O threads.

    ``writing``: the worker writes its samples' files (``writes``): in threads, up to
    :data:`~gpu_blur.generate.QUEUE_PER_THREAD` a thread wait behind the one it makes.
    """
    if threads == 1:  # it decodes, makes and writes in turn
        return DEVICE_DEPTH
    return DEVICE_DEPTH + 2 * threads + (QUEUE_PER_THREAD * threads if writing else 0)


#: Signals a device worker ignores: Ctrl-C and a closed terminal, which the driver handles.
DRIVER_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGHUP")
                       if hasattr(signal, name))


@contextlib.contextmanager
def _driver_signals_blocked():
    """Block :data:`DRIVER_SIGNALS` in this thread while a worker process starts.

    The worker inherits the blocked set, so a Ctrl-C while it still imports (before it
    ignores the signals, :func:`_device_worker`) prints no KeyboardInterrupt traceback; one
    sent meanwhile reaches the driver once the block ends.
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, DRIVER_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _exit_without(driver: int, held: list | None = None) -> None:
    """End this worker process once the driver is no longer its parent (killed, crashed).

    ``held``: the worker's :class:`~gpu_blur.shared_results.Outbox`, if any: the shared-memory
    blocks it holds are unlinked first (the driver, which made them, cannot any more).
    """
    while os.getppid() == driver:
        time.sleep(PARENT_CHECK_S)
    for outbox in held or ():
        outbox.abandon()
    os._exit(1)


class DeviceWorkers:
    """The worker processes of a ``--devices`` run, one per device, each opening its device.

    Started as soon as the job is known, so that their imports and devices open while the
    driver sets up the run (:func:`gpu_blur.generation.generate_set` does, for a list of
    devices), and handed to :func:`run_devices`. Each decodes (and, writing a set of files,
    writes) in ``io_threads // len(devices)`` threads, at least one (default
    :func:`default_io_threads`). :meth:`stop` ends them whenever the run ends, however.
    """

    def __init__(self, job: Job, devices: list[str], io_threads: int | None = None):
        self.job, self.devices = job, list(devices)
        self.threads = max(1, (io_threads or default_io_threads()) // len(self.devices))
        self.processes: list = []
        self.conns: list = []
        context = multiprocessing.get_context("spawn")
        cwd = os.getcwd()
        try:
            for device in self.devices:
                conn, child = context.Pipe()
                worker = context.Process(target=_device_worker, daemon=True, args=(
                    dataclasses.replace(job, backend=device), os.getpid(), child,
                    self.threads, cwd))
                with _children_skip_cwd(), _driver_signals_blocked():
                    worker.start()
                child.close()  # the worker's end is the worker's: its death closes the pipe
                self.processes.append(worker)
                self.conns.append(conn)
        except BaseException:
            self.stop()
            raise

    def open(self, shared: bool, cache_bytes: int, writes: FolderWrites | None) -> None:
        """Wait until every worker has opened its device, then send it the run's set-up.

        Raises:
            RuntimeError: naming a device that could not be opened, or whose worker died.
        """
        for device, conn in zip(self.devices, self.conns, strict=True):
            try:
                kind, value = conn.recv()
            except (EOFError, OSError):
                raise RuntimeError(f"--devices {device}: its worker process died while "
                                   "opening the device") from None
            if kind != "open":
                raise RuntimeError(f"--devices {device}: {value}")
        for conn in self.conns:
            conn.send(("setup", (shared, cache_bytes, writes)))

    def stop(self, finished: bool = False) -> None:
        """End the workers (safe to call again).

        An idle worker ends when its pipe closes; unless ``finished`` each is terminated,
        the samples it was making dropped.
        """
        for conn in self.conns:
            conn.close()
        for worker in self.processes:
            if not finished:
                worker.terminate()
            worker.join()


def run_devices(job: Job, specs: Iterable[SampleSpec], devices: list[str],
                frame_cache: FrameCache | None = None,
                pool_times: PoolTimes | None = None, writes: FolderWrites | None = None,
                io_threads: int | None = None,
                workers: DeviceWorkers | None = None) -> Iterator[tuple]:
    """Make the samples in one worker process per entry of ``devices``, yielding as they finish.

    Workers are started with ``spawn`` (OpenCL and CUDA contexts do not survive a fork),
    each builds its backend once (``job`` with its device as the backend) and takes the
    next sample when it finishes one, so faster devices make more. Samples whose input files
    overlap (windows of a sequence, draws of one photo) go to one worker in runs of up to
    :data:`RUN_SAMPLES` consecutive ones; with ``frame_cache`` each worker decodes through a
    cache of its own, an equal share of ``frame_cache.budget``, so a frame is decoded once per
    worker, and the workers' counts are added to ``frame_cache``'s. The workers' decoding
    threads, their work and waits are added to ``pool_times`` when the run ends, with what
    handing the samples to this thread cost both sides (``PoolTimes.handoff``).

    ``workers``: the :class:`DeviceWorkers` started for ``job`` and ``devices`` (else they
    are started here); each decodes in ``io_threads // len(devices)`` threads (default
    :func:`default_io_threads`, at least one), so the workers together use about as many as
    the host has cores, besides their main threads (which drive the devices).

    With ``writes`` (a set of files, :meth:`gpu_blur.dataset.DatasetWriter.folder_writes`)
    each worker writes the files of the samples it makes in those threads too, as a run on
    one device does, and yields ``(spec, Saved, error)``: a sample's images never cross to
    the driver, which only writes the manifest lines (on the H200 pair, handing 14 MB
    samples over took the workers' making threads 7 ms and the driver's one thread 5 ms a
    sample, a ceiling of about 200 samples/s however many GPUs). Temporary files bear the
    driver's process id (the one the folder's lock records); those of samples still being
    made when the run stops are removed once the workers are gone.

    Without ``writes`` a worker writes each result's arrays into shared memory and the
    driver copies them out (:mod:`gpu_blur.shared_results`), to encode and store them in
    its own pool (a container format); every block is unlinked when the run ends, however
    it ends. A device that cannot be opened stops the run before any sample. When the run stops
    early (Ctrl-C, SIGTERM, an error, the caller closing this generator) the workers are
    terminated, not waited for; a worker whose driver dies exits by itself within
    :data:`PARENT_CHECK_S`.

    Raises:
        RuntimeError: a device that cannot be opened, a worker that died (killed, out of
            memory), naming the device and the sample, or a worker's error that is no fault
            of its sample, with its traceback.
    """
    if not devices:
        raise ValueError("run_devices needs at least one device")
    if workers is not None and (workers.job != job or workers.devices != list(devices)):
        raise ValueError("run_devices: the workers were started for another job or devices")
    return _device_results(job, list(specs), list(devices), frame_cache, pool_times, writes,
                           io_threads, workers)


class _Runs:
    """The samples still to send, in runs: consecutive samples that share an input file.

    A worker is sent the rest of its run before another run. A run holds up to
    :data:`RUN_SAMPLES` samples, so that the driver's manifest lines, written in order, wait
    for few, and no more than an equal share of the set, so that every worker gets some.
    """

    def __init__(self, specs: list[SampleSpec], workers: int):
        longest = max(1, min(RUN_SAMPLES, -(-len(specs) // workers)))
        runs: deque[deque[SampleSpec]] = deque()
        for spec in specs:
            last = runs[-1] if runs else None
            if last and len(last) < longest and set(last[-1].inputs) & set(spec.inputs):
                last.append(spec)
            else:
                runs.append(deque([spec]))
        self._runs = runs
        self._current: list[deque[SampleSpec]] = [deque() for _ in range(workers)]

    def next(self, worker: int) -> SampleSpec | None:
        """The next sample for ``worker``: its run's next, else the next run's first; None."""
        if not self._current[worker]:
            if not self._runs:
                return None
            self._current[worker] = self._runs.popleft()
        return self._current[worker].popleft()


def _device_results(job: Job, todo: list[SampleSpec], devices: list[str],
                    frame_cache: FrameCache | None = None,
                    pool_times: PoolTimes | None = None, writes: FolderWrites | None = None,
                    io_threads: int | None = None, workers: DeviceWorkers | None = None):
    if not todo:
        if workers is not None:
            workers.stop(finished=True)
        return
    runs = _Runs(todo, len(devices))
    blocks = Blocks()
    finished = False
    queued: list[deque[SampleSpec]] = [deque() for _ in devices]
    share = frame_cache.budget // len(devices) if frame_cache is not None else 0
    try:
        if workers is None:
            workers = DeviceWorkers(job, devices, io_threads)
        conns, threads = workers.conns, workers.threads
        depth = worker_depth(threads, writes is not None)
        workers.open(writes is None, share, writes)
        # each worker's decoding threads as it last sent them, from the start: a worker sent
        # no sample has them too (with one thread, none: it decodes in turn)
        pools = [PoolTimes(threads if threads > 1 else 0) for _ in devices]

        def feed(worker: int) -> None:
            spec = runs.next(worker)
            if spec is None:
                return
            try:
                conns[worker].send(spec)
            except OSError:  # its end of the pipe is closed
                raise RuntimeError(f"the worker on {devices[worker]} died (killed, or out of "
                                   "memory?); the samples finished so far are kept: run the "
                                   "same command with --resume") from None
            queued[worker].append(spec)

        for worker in range(len(devices)):
            for _ in range(depth):
                feed(worker)
        # the driver's thread: waiting for the workers, and taking their results
        waiting = receiving = 0.0
        taken = piped = saved = 0
        while any(queued):
            start = time.perf_counter()
            ready = wait([c for c, q in zip(conns, queued, strict=True) if q])
            waiting += time.perf_counter() - start
            for conn in ready:
                start = time.perf_counter()
                worker = conns.index(conn)
                try:
                    kind, value = conn.recv()
                except (EOFError, OSError):  # OSError: reset, with messages it had not read
                    spec = queued[worker][0]
                    raise RuntimeError(
                        f"the worker on {devices[worker]} died while making sample "
                        f"{spec.index} ({spec.name}): killed, or out of memory? The samples "
                        "finished so far are kept: run the same command with --resume"
                    ) from None
                if kind == ASK:  # a shared-memory block for its results
                    blocks.answer(conn, *value)
                    receiving += time.perf_counter() - start
                    continue
                spec = queued[worker].popleft()
                if kind != "sample":
                    raise RuntimeError(f"the worker on {devices[worker]} failed on sample "
                                       f"{spec.index} ({spec.name}), not for a fault of the "
                                       f"sample:\n{value}")
                _, result, error, layout, counts, times = value
                pools[worker] = times
                if layout is not None:  # copied out of the block, which goes back
                    result = blocks.receive(conn, result, layout)
                elif isinstance(result, Saved):  # its files written by the worker
                    saved += 1
                elif result is not None:  # whole through the pipe: no block to be had
                    piped += 1
                if counts is not None and frame_cache is not None:
                    frame_cache.add(counts)
                feed(worker)
                receiving += time.perf_counter() - start
                taken += 1
                yield spec, result, error  # the driver's own spec object
        if pool_times is not None:
            for times in pools:
                pool_times.add(times)
            pool_times.add_handoff(receiving=receiving, waiting=waiting, samples=taken,
                                   piped=piped, written=saved)
        finished = True
    finally:
        if workers is not None:  # stopped early: the samples still being made are dropped
            workers.stop(finished)
        blocks.close()  # once no worker can attach any more
        if writes is not None:  # what the stopped workers were writing: gone with them
            for spec in (spec for sent in queued for spec in sent):
                for temporary in writes.files.temporaries(spec):
                    with contextlib.suppress(OSError):
                        temporary.unlink(missing_ok=True)


# -- Ray ------------------------------------------------------------------------------------

def import_ray():
    """The ``ray`` module, or a RuntimeError that says how to install it."""
    try:
        import ray
    except ImportError:
        raise RuntimeError(f"--ray needs Ray, which is not installed: {RAY_INSTALL}") from None
    return ray


def _ray_make(job: Job, specs: list[SampleSpec], cwd: str, fail_once) -> list[tuple]:
    """One Ray task: make a few samples (runs on a cluster node)."""
    if os.getcwd() != cwd and os.path.isdir(cwd):
        os.chdir(cwd)  # relative inputs and scene paths mean what they mean to the driver
    testhooks.fail_once(fail_once, [s.index for s in specs])
    made = [make_sample(job, spec) for spec in specs]
    return [(spec, for_driver(job, result), error) for spec, result, error in made]


def run_ray(job: Job, specs: Iterable[SampleSpec], address: str = "auto",
            gpus_per_task: float | None = None, retries: int = 3,
            batch: int | None = None) -> Iterator[tuple]:
    """Make the samples as tasks on a Ray cluster, yielding them as tasks complete.

    Args:
        job: what every task makes its samples with.
        specs: the samples.
        address: ``"auto"``: an initialized Ray, else the cluster in ``RAY_ADDRESS`` or the
            one ``ray start`` last started on this machine, else a new local instance on
            this machine's cores and GPUs (shut down at the end); any other value is passed
            to ``ray.init(address=...)`` (``host:6379``, ``ray://host:10001``).
        gpus_per_task: GPUs each task asks for (fractions share a GPU); default 1 when the
            backend runs on an NVIDIA GPU (tasks then use the GPU Ray assigns), else 0.
        retries: how many times a failed task (a worker or node lost, an exception that is
            not bad input) is run again before the run stops.
        batch: samples per task (default 1 on CPUs, :data:`GPU_BATCH` on GPUs).

    Tasks return the samples' results (arrays and parameters, not files); at most two tasks
    per cluster slot (CPU, or GPU share) are in flight, which bounds what waits in the object
    store. Unless ``gpus_per_task`` is 0, the driver opens ``job.backend`` to tell whether it
    runs on an NVIDIA GPU.

    Raises:
        RuntimeError: Ray missing, a cluster without the GPUs asked for, or a task that
            failed ``retries + 1`` times.
    """
    ray = import_ray()
    if retries < 0:
        raise ValueError(f"--retries {retries}: must be >= 0")
    if gpus_per_task is not None and gpus_per_task < 0:
        raise ValueError(f"--gpus-per-task {gpus_per_task}: must be >= 0")
    if batch is not None and batch < 1:
        raise ValueError(f"--ray-batch {batch}: must be >= 1")
    return _ray_results(ray, job, list(specs), address, gpus_per_task, retries, batch)


def _ray_results(ray, job, specs, address, gpus_per_task, retries, batch):
    from gpu_blur.backends import get_backend

    if not specs:
        return
    cuda = gpus_per_task != 0 and uses_cuda(get_backend(job.backend,
                                                         job.scene.output.precision))
    gpus = (1 if cuda else 0) if gpus_per_task is None else gpus_per_task
    if gpus and cuda:  # the task sees only the GPU Ray gave it, as device 0
        job = dataclasses.replace(job, backend="warp:cuda:0" if family(job.backend) == "warp"
                                  else "opencl")
    batch = batch or (GPU_BATCH if gpus else 1)
    ours = not ray.is_initialized()
    if ours:
        ray.init(address=None if address == "auto" else address, include_dashboard=False)
    pending: dict = {}
    try:
        have = ray.cluster_resources()
        if gpus and have.get("GPU", 0) < gpus:
            raise RuntimeError(
                f"the Ray cluster offers {have.get('GPU', 0):g} GPU(s) and each task asks for "
                f"{gpus:g} (--gpus-per-task); its tasks would wait forever: add GPU nodes, or "
                "pass --gpus-per-task 0 with a backend that runs on CPUs")
        slots = int(have.get("GPU", 0) / gpus) if gpus else int(have.get("CPU", 1))
        window = max(4, 2 * slots)
        task = ray.remote(num_gpus=gpus, max_retries=retries, retry_exceptions=True)(_ray_make)
        job_ref, cwd, hook = ray.put(job), os.getcwd(), testhooks.fail_once_setting()
        chunks = iter([specs[i:i + batch] for i in range(0, len(specs), batch)])

        def submit() -> None:
            chunk = next(chunks, None)
            if chunk is not None:
                pending[task.remote(job_ref, chunk, cwd, hook)] = chunk

        for _ in range(window):
            submit()
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            chunk = pending.pop(ready[0])
            try:
                items = ray.get(ready[0])
            except ray.exceptions.RayError as e:
                what = (f"sample {chunk[0].index} ({chunk[0].name})" if len(chunk) == 1 else
                        f"samples {chunk[0].index} to {chunk[-1].index}")
                cause = getattr(e, "cause", None) or e  # an exception raised in the task
                why = (str(cause).strip().splitlines() or [""])[0]
                raise RuntimeError(
                    f"{what}: the Ray task failed {retries + 1} time(s) (--retries {retries}): "
                    f"{type(cause).__name__}: {why}; the samples finished so far are kept: "
                    "run the same command with --resume") from None
            submit()
            for original, (_, result, error) in zip(chunk, items, strict=True):
                yield original, result, error  # the driver's own spec (its paths as given)
    finally:
        for ref in pending:
            ray.cancel(ref)
        if ours:
            ray.shutdown()


# -- the CLI's choice -----------------------------------------------------------------------

def pick_executor(args, precision: str) -> Callable[[Job, list[SampleSpec]], Iterator[tuple]]:
    """The executor ``gpu-blur generate`` runs (serial, ``--devices`` or ``--ray``).

    Checks the options before any work: device names, Ray installed, option combinations.
    """
    devices = getattr(args, "devices", None)
    address = getattr(args, "ray", None)
    gpus = getattr(args, "gpus_per_task", None)
    retries = getattr(args, "retries", None)
    batch = getattr(args, "ray_batch", None)
    if address is None and (gpus is not None or retries is not None or batch is not None):
        raise ValueError("--gpus-per-task, --retries and --ray-batch apply to --ray")
    if devices is not None:
        return functools.partial(run_devices, devices=parse_devices(devices, args.backend,
                                                                    precision))
    if address is not None:
        import_ray()
        if (retries is not None and retries < 0) or (gpus is not None and gpus < 0) or (
                batch is not None and batch < 1):
            raise ValueError("--retries and --gpus-per-task must be >= 0, --ray-batch >= 1")
        return functools.partial(run_ray, address=address, gpus_per_task=gpus,
                                 retries=3 if retries is None else retries, batch=batch)
    return run_serial
