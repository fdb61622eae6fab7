"""Making the samples of a set: one job description, and executors that run it.

The driver (``gpu-blur generate``) owns the output folder and the manifest; executors only
make samples and hand them back as ``(spec, result, error)``, in any order. A sample's output
depends only on (seed, sample index, scene) and, under ``blur.draws = "per-sequence"``, its
sequence's index (the spec's), so any executor, worker or device gives the same files.

On one device the driver runs a pipeline (``--io-threads``): a pool of threads decodes the
next samples' input files (:func:`run_pipelined`) and encodes and writes the finished ones
(:class:`WriteBehind`) while this thread synthesizes; OpenCV's decoders and encoders, zlib and
file I/O release the GIL, so those threads run beside synthesis. Queues of
:data:`QUEUE_PER_THREAD` samples per thread on each side bound the memory.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future

import cv2
import numpy as np

from gpu_blur.arrays import WarpFrames
from gpu_blur.discovery import SampleSpec
from gpu_blur.frame_cache import Decode, FrameCache, uncached
from gpu_blur.gpu_jpeg import JpegBatches
from gpu_blur.image_arrays import check_image
from gpu_blur.image_reading import opencv_reason, read_image
from gpu_blur.reference.output import to_integers
from gpu_blur.scene import Scene
from gpu_blur.scheduler import Schedule
from gpu_blur.staging import DeviceFrames, LentResults, PinnedStaging
from gpu_blur.synthesis import Synthesis, Synthesizer, synthesize
from gpu_blur.timings import PoolTimes

__all__ = ["BATCH", "Job", "MAX_DEFAULT_IO_THREADS", "QUEUE_PER_THREAD", "STAGED_BATCHES",
           "Saved", "WriteBehind", "checked_inputs", "decode", "default_io_threads", "for_driver",
           "make_batch", "make_sample", "pinned_staging", "read_input", "run_pipelined",
           "run_serial", "usable_cores"]

#: Samples per I/O thread that may wait on each side of synthesis: decoded (or being decoded)
#: ahead of the sample being made, and made but not yet written behind it. With N threads at
#: most 2 N samples' inputs and 2 N samples' outputs are held, besides the one being made.
QUEUE_PER_THREAD = 2
#: The most I/O threads ``--io-threads`` takes by default, however many cores the host has:
#: enough to decode 9 PNG frames of 1920 x 1200 for a few hundred samples a second, while the
#: queues stay within a few GB (such a sample holds 62 MB of frames and 55 MB of outputs).
MAX_DEFAULT_IO_THREADS = 32
#: Samples a GPU makes at once in a run on one device (:func:`make_batch`), from one slot of
#: page-locked memory the I/O threads fill (:class:`~gpu_blur.staging.PinnedStaging`).
BATCH = 4
#: Such slots, filled ahead of the batch being made: two of four 1920 x 1200 RSBlur samples
#: (9 frames of 8 bits) hold 500 MB of page-locked host memory.
STAGED_BATCHES = 2


def usable_cores() -> int:
    """The cores this process may run on.

    Its CPU affinity where the system keeps one (a container's or ``taskset``'s share), else
    every core of the host.
    """
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
             else os.cpu_count())
    return max(1, cores or 1)


def default_io_threads() -> int:
    """``--io-threads``' default: the cores this process may run on, at most 32."""
    return min(usable_cores(), MAX_DEFAULT_IO_THREADS)


@dataclasses.dataclass(frozen=True)
class Job:
    """Everything a worker needs to make any sample of a set (picklable)."""

    scene: Scene
    seed: int
    backend: str
    schedule: Schedule | None = None  # tiles, memory budget, spot checks
    with_raw: bool = False  # keep each sample's RAW mosaic (generate --save raw)
    bits: int = 0  # the set's PNG bits: workers in other processes send these codes
    with_mask: bool = True  # the set saves masks (generate --save mask)


@dataclasses.dataclass(frozen=True)
class Saved:
    """A made sample whose files a ``--devices`` worker wrote itself, as the driver gets it.

    ``line``: its manifest line (:meth:`gpu_blur.dataset.FolderWrites.write`), None when
    writing failed with ``error`` (the OSError, for the driver to report and stop on);
    ``timings``: the :class:`~gpu_blur.synthesis.Synthesis`' seconds per step.
    """

    line: dict | None
    timings: dict
    error: OSError | None = None


def for_driver(job: Job, result: Synthesis | None) -> Synthesis | None:
    """A made sample as a worker process sends it: only what the set's files need.

    Blurred and sharp go as the set's codes (:func:`make_sample` has them made for 8/16-bit
    sets; float32 results are converted here with :func:`to_integers`; ``job.bits`` 0 keeps
    float32) and the mask is left out unless the set saves it, so the files are byte for byte
    the same while a 1920 x 1200 sample crosses the pipe as 14 MB of 8-bit codes instead of
    83 MB of float32 (300 ms through a multiprocessing pipe on a 2-core EPYC).
    """
    if result is None:
        return None

    def shrink(image):
        return to_integers(image, job.bits) if job.bits and image.dtype == np.float32 else image

    return dataclasses.replace(result, blurred=shrink(result.blurred),
                               sharp=shrink(result.sharp),
                               _mask=result.mask if job.with_mask else None)


def make_sample(job: Job, spec: SampleSpec, inputs: tuple[np.ndarray, ...] | None = None
                ) -> tuple[SampleSpec, Synthesis | None, str | None]:
    """One sample: ``(spec, result, None)``, or ``(spec, None, reason)`` for bad input.

    ``inputs`` are the sample's files already decoded (:func:`decode`), else its paths are
    read here. In blur mode none they go to ``synthesize`` as the mapping its ``roles`` name
    (``{"blurred": ..., "mask": ..., "sharp": ...}``). A window of a sequence goes with its
    sequence's index, which keys its draws under ``blur.draws = "per-sequence"``.

    What fails only this sample (the reason goes to the manifest and the run goes on) is what
    this sample's inputs and size cause: ValueError (a check refused an input or a value),
    OSError (a file could not be read), cv2.error (OpenCV refused the sample's data, e.g. its
    size) and MemoryError (the sample needs more host memory than there is). Anything else
    is a fault of gpu_blur or of the device and would fail every sample alike, so it stops
    the run with its traceback (TypeError, AttributeError, a backend's RuntimeError), as do
    KeyboardInterrupt and SystemExit.
    """
    try:
        if spec.problem:
            raise ValueError(spec.problem)
        given = list(spec.inputs if inputs is None else inputs)
        if spec.roles:
            given = dict(zip(spec.roles, given, strict=True))
        # a set of 8/16-bit PNGs takes the codes, made on the device (a quarter or a half of
        # the float32 bytes to fetch, no conversion on the host)
        result = synthesize(given, job.scene,
                            seed=job.seed, sample_index=spec.index, backend=job.backend,
                            tile=job.schedule, with_raw=job.with_raw, codes=bool(job.bits),
                            sequence_index=spec.window and spec.window.sequence_index)
    except (ValueError, OSError) as e:
        return spec, None, str(e)
    except cv2.error as e:
        return spec, None, f"OpenCV refused this sample's data: {opencv_reason(e)}"
    except MemoryError as e:
        detail = str(e) or "no detail"
        return spec, None, (f"out of memory ({detail}): this sample needs more host memory "
                            "than there is; make it smaller (frames, blur.steps, "
                            "blur.interpolation) or free memory")
    return spec, result, None


def run_serial(job: Job, specs: Iterable[SampleSpec], cache: FrameCache | None = None
               ) -> Iterator[tuple]:
    """Make the samples one after another in this process.

    ``cache``: their input files are decoded through it (:func:`decode`).
    """
    for spec in specs:
        yield make_sample(job, spec, None if cache is None else decode(spec, cache))


def decode(spec: SampleSpec, cache: FrameCache | None = None) -> tuple[np.ndarray, ...] | None:
    """A sample's input files as ``synthesize`` reads them, or None when one fails a check.

    Each file goes through :func:`~gpu_blur.image_reading.read_image` and
    :func:`~gpu_blur.image_arrays.check_image` (named by its path), and all must have one size; the
    arrays are read_image's, as ``synthesize`` gets them from a path (a mode none mask's 8-bit
    codes, like its image's, become value / 255 there, as the RSBlur authors read them). When
    anything fails, the sample is made from its paths instead, so ``synthesize`` reads them
    again and refuses them in its own words, naming the file: a bad sample is read twice, a
    good one once. With ``cache`` a file that other samples read too is decoded once while it
    stays in the cache (its arrays read-only).
    """
    if spec.problem:
        return None
    try:
        images = [read_input(path, cache) for path in spec.inputs]
    except Exception:  # synthesize meets it again, and says what it is
        return None
    return checked_inputs(spec, images)


def read_input(path, cache: FrameCache | None = None) -> np.ndarray:
    """One input file decoded (through ``cache`` if given), as ``synthesize`` reads it."""
    return read_image(path) if cache is None else cache.read(path, read_image)


def checked_inputs(spec: SampleSpec, images: list[np.ndarray] | None
                   ) -> tuple[np.ndarray, ...] | None:
    """:func:`decode`'s checks of a sample's decoded files: the arrays, or None."""
    if images is None:
        return None
    try:
        for path, image in zip(spec.inputs, images, strict=True):
            check_image(image, str(path))
    except Exception:  # synthesize meets it again, and says what it is
        return None
    if len({image.shape for image in images}) > 1:
        return None
    return tuple(images)


def pinned_staging(job: Job) -> PinnedStaging | None:
    """:class:`~gpu_blur.staging.PinnedStaging` for a job that runs on a GPU, else None.

    So where the backend is a kernel backend on an NVIDIA GPU (Warp on CUDA, NVIDIA's
    OpenCL) and the job runs whole images there (no tiles, budget or spot checks, no frame
    interpolation: those run on the host's copies): :data:`STAGED_BATCHES` slots of
    :data:`BATCH` samples.
    """
    from gpu_blur.backends import get_backend, is_resident
    from gpu_blur.backends.flows import interpolation_factor
    from gpu_blur.planning import plan

    if (job.schedule is not None and job.schedule != Schedule()) or interpolation_factor(
            plan(job.scene)) != 1:
        return None
    backend = get_backend(job.backend, job.scene.output.precision)
    if not (is_resident(backend) and backend.uses_cuda):
        return None
    return PinnedStaging(backend, STAGED_BATCHES, BATCH)


def device_frames(job: Job, staging: PinnedStaging | None,
                  cache: FrameCache | None) -> DeviceFrames | None:
    """:class:`~gpu_blur.staging.DeviceFrames` for a staged run of cached frames, or None.

    So where the scene averages frames, the frame cache keeps some, and the backend takes
    batches on its device (Warp on CUDA); it keeps as many bytes as the frame cache.
    """
    if (staging is None or cache is None or not cache.budget
            or job.scene.blur.mode != "average" or not staging.backend.device_arrays):
        return None
    return DeviceFrames(staging.backend, cache.budget)


def make_batch(job: Job, synthesizer: Synthesizer, specs: list[SampleSpec],
               batch: np.ndarray | WarpFrames, results: LentResults | None = None
               ) -> list[tuple] | None:
    """Samples made as one batch: :func:`make_sample`'s tuples, or None if the batch failed.

    ``batch``: their inputs, B x F x H x W x 3 (mode average) or B x H x W x 3, in the
    synthesizer's pinned memory or on its device (:class:`~gpu_blur.staging.DeviceFrames`);
    ``results``: where the results go (page-locked arrays lent for ``out=``; None: new
    arrays). A batch's sample is ``synthesize``'s, bit for bit
    (:class:`~gpu_blur.synthesis.Synthesizer`); so is each sample of a batch that fails,
    made again on its own by the caller, whose reason then names its file.
    """
    windows = [spec.window for spec in specs]
    try:
        out = None
        if results is not None:
            shape = synthesizer.result_shape(batch.shape)
            out = results.take([(shape, dtype)
                                for dtype in synthesizer.result_dtypes(codes=bool(job.bits))])
        made = synthesizer(batch, indices=[spec.index for spec in specs], codes=bool(job.bits),
                           sequences=([w.sequence_index for w in windows] if all(windows)
                                      else None), out=out, png=bool(job.bits))
    except (ValueError, OSError, cv2.error, MemoryError):
        return None
    share = {category: seconds / len(specs) for category, seconds in made.timings.items()}
    return [(spec, Synthesis(made.blurred[b], made.sharp[b],
                             None if made.mask is None else made.mask[b], made.params[b],
                             made.plans[b], dict(share), crop=job.scene.output.crop,
                             device=synthesizer.runner.model,
                             _raw=None if made.raw is None else made.raw[b],
                             raw_info=None if made.raw_info is None else made.raw_info[b],
                             png=None if made.png is None else made.png[b]),
             None) for b, spec in enumerate(specs)]


class _Inputs:
    """A sample's input files decoded in a pool, then checked.

    Each file is claimed from the frame cache when the sample is queued
    (:meth:`~gpu_blur.frame_cache.FrameCache.claim`): only a file that no earlier sample asked
    for gets a decode task, so no I/O thread waits on another's decode. The thread that brings
    the last file checks them all (:func:`checked_inputs`), or a task where every file was
    decoded already; :attr:`checked` then holds the arrays or None. :meth:`stage` has them
    copied to a position of a :class:`PinnedStaging` slot. With ``jpeg``, a sample of JPEG
    files is read and checked for the GPU instead (:attr:`jpeg`).
    """

    def __init__(self, spec: SampleSpec, pool: Executor, times: PoolTimes,
                 cache: FrameCache | None, jpeg: JpegBatches | None = None):
        self.spec, self.checked, self.staged = spec, Future(), None
        self.jpeg = jpeg if jpeg is not None and jpeg.takes(spec) else None
        self.slot: int | None = None
        self.position = 0
        #: some file of it was claimed by an earlier sample (a frame it shares)
        self.shared = False
        #: made from frames kept on the device (:class:`~gpu_blur.staging.DeviceFrames`)
        self.on_device = False
        self.reads = not spec.problem and bool(spec.inputs)
        self._images: list = [None] * len(spec.inputs)
        self._left, self._lock = len(spec.inputs), threading.Lock()
        self._claiming = True
        #: (pool task, its decode) of the files this sample decodes
        self.tasks: list[tuple[Future, Decode]] = []
        if not self.reads:
            self.checked.set_result(None)
            return
        times.samples += 1  # on the making thread
        reader = read_image if self.jpeg is None else self.jpeg.read
        for i, path in enumerate(spec.inputs):
            frame, decode = _claim(path, reader, cache)
            self.shared |= decode is None  # without a cache every file has its own decode
            if decode is not None:
                try:
                    self.tasks.append((pool.submit(times.run, "decode", decode), decode))
                except RuntimeError:  # the pool is shut down: no sample waits for this file
                    decode.abandon()
                    raise
            frame.add_done_callback(functools.partial(self._arrived, i))
        with self._lock:
            self._claiming = False
            ready = self._left == 0
        if ready:  # every file was decoded already: checked in a task
            try:
                pool.submit(times.run, "decode", self._check, counted=False)
            except RuntimeError:  # the pool is shut down: the run stopped
                self.checked.set_result(None)

    @property
    def batchable(self) -> bool:
        """Whether it may go in a batch: files to read, no problem, no roles (mode none)."""
        return self.reads and not self.spec.roles and self.jpeg is None

    def _arrived(self, i: int, frame: Future) -> None:
        """File ``i`` decoded (or failed: None), in the thread that decoded it (or here)."""
        image = None if frame.cancelled() or frame.exception() is not None else frame.result()
        with self._lock:
            self._images[i] = image
            self._left -= 1
            last = self._left == 0 and not self._claiming
        if last:
            self._check()

    def _check(self) -> None:
        images = None if any(image is None for image in self._images) else self._images
        try:
            checked = (checked_inputs(self.spec, images) if self.jpeg is None
                       else self.jpeg.checked(self.spec, images, checked_inputs))
        except Exception:  # synthesize meets it again, and says what it is
            checked = None
        self.checked.set_result(checked)

    def stage(self, staging: PinnedStaging, slot: int, position: int, pool: Executor,
              times: PoolTimes) -> None:
        """Copy the checked inputs to ``position`` of ``slot`` (:attr:`staged`).

        In the I/O thread that checks them, once they are; in a task of their own if they
        are checked already.
        """
        self.slot, self.position, self.staged = slot, position, Future()
        making = threading.current_thread()

        def fill(checked: Future) -> None:
            self.staged.set_result(staging.fill(slot, position, checked.result()))

        def filled(checked: Future) -> None:
            if threading.current_thread() is not making:  # the thread that checked them
                fill(checked)
                return
            try:
                pool.submit(times.run, "decode", fill, checked, counted=False)
            except RuntimeError:  # the pool is shut down: the run stopped
                self.staged.set_result(checked.result())

        self.checked.add_done_callback(filled)

    def result(self) -> tuple[np.ndarray, ...] | None:
        """The inputs for ``make_sample``: staged if they are, else as decoded."""
        return (self.staged or self.checked).result()

    def cancel(self) -> None:
        """Decode nothing more for this sample; samples waiting on its files see them fail."""
        for task, decode in self.tasks:
            if task.cancel():
                decode.abandon()


def _claim(path, reader: Callable, cache: FrameCache | None) -> tuple[Future, Decode | None]:
    """:meth:`~gpu_blur.frame_cache.FrameCache.claim` of a file, or its own decode (no cache).

    A file that cannot be looked at gives a future holding that error.
    """
    if cache is None:
        return uncached(path, reader)
    try:
        return cache.claim(path, reader)
    except OSError as error:
        failed = Future()
        failed.set_exception(error)
        return failed, None


def _synthesizer(job: Job) -> Synthesizer:
    """The Synthesizer that makes a run's batches (:func:`make_batch`)."""
    return Synthesizer(job.scene, backend=job.backend, seed=job.seed, schedule=job.schedule,
                       with_mask=job.with_mask, with_raw=job.with_raw)


def _next_group(ahead: deque[_Inputs], staging: PinnedStaging | None) -> list[_Inputs]:
    """The samples at the head of ``ahead`` made next, together where they can be.

    A staged slot's samples; a run of samples made from frames on the device, at most a
    slot's worth; a run of JPEG samples, at most :data:`BATCH`; else the first alone.
    """
    first = ahead[0]
    if first.slot is not None:
        return [w for w in itertools.islice(ahead, staging.batch) if w.slot == first.slot]
    if first.on_device:
        return list(itertools.takewhile(lambda w: w.on_device,
                                        itertools.islice(ahead, staging.batch)))
    if first.jpeg:
        return list(itertools.takewhile(lambda w: w.jpeg, itertools.islice(ahead, BATCH)))
    return [first]


def _stage(ahead: deque[_Inputs], staging: PinnedStaging, pool: Executor,
           times: PoolTimes) -> None:
    """Give free slots to the oldest runs of batchable samples not yet staged."""
    run: list[_Inputs] = []
    for waiting in [*ahead, None]:
        stageable = (waiting is not None and waiting.slot is None and waiting.batchable
                     and not waiting.on_device)
        if stageable and len(run) < staging.batch:
            run.append(waiting)
            continue
        if run:
            if not staging.free:
                return
            slot = staging.free.pop()
            for position, member in enumerate(run):
                member.stage(staging, slot, position, pool, times)
            run = []
        if stageable:
            run.append(waiting)  # the next run starts where a full one ended


def run_pipelined(job: Job, specs: Iterable[SampleSpec], pool: Executor, times: PoolTimes,
                  depth: int, cache: FrameCache | None = None,
                  staging: PinnedStaging | None = None,
                  more: Callable[[], bool] | None = None,
                  jpeg: JpegBatches | None = None) -> Iterator[tuple]:
    """Make the samples in this thread, in order, while ``pool`` decodes the next ones' inputs.

    At most ``depth`` samples are decoded or being decoded ahead of the one being made, each
    file a task of its own, and a file that an earlier sample already asked for none (so the
    frames that overlapping windows share are decoded once, in parallel, and no thread waits
    for another's decode: :class:`_Inputs`). With ``staging`` (a GPU) the pool also copies
    the next samples into its page-locked slots, a batch to a slot, and a slot's samples are
    made as one batch (:func:`make_batch`; one by one where they cannot be), into
    page-locked arrays it lends (``staging.results``). A sample that shares a file with an
    earlier one (overlapping windows) is not staged where :func:`device_frames` keeps frames
    on the device: runs of such samples are made as batches put together there. The results
    are :func:`run_serial`'s, in order; the time this thread waits for inputs is added to
    ``times.waited_for_inputs``, the pool's decoding and staging to ``times.busy["decode"]``.
    ``more``: for samples that arrive while the run goes (a device worker's): ``specs`` ends
    when none is waiting, and ``more()`` waits for the next one when nothing is ahead (False:
    there are no more).
    ``jpeg``: samples of JPEG files are read as bytes and decoded in groups of :data:`BATCH`
    on the GPU (``--jpeg-decoder gpu``).
    """
    rest = iter(specs)
    ahead: deque[_Inputs] = deque()
    synthesizer = None
    frames = device_frames(job, staging, cache)
    try:
        while True:
            for spec in itertools.islice(rest, depth - len(ahead)):
                waiting = _Inputs(spec, pool, times, cache, jpeg)
                waiting.on_device = frames is not None and waiting.shared and waiting.batchable
                ahead.append(waiting)
            if not ahead:
                if more is not None and more():
                    continue
                return
            if staging is not None:
                if not staging.sized and ahead[0].batchable:  # its size is the slots' stride
                    first = ahead[0].checked.result()
                    if first:
                        staging.size_for(first)
                _stage(ahead, staging, pool, times)
            slot = ahead[0].slot
            group = _next_group(ahead, staging)
            start = time.perf_counter()
            inputs = [waiting.result() for waiting in group]
            times.waited_for_inputs += time.perf_counter() - start
            for _ in group:
                ahead.popleft()
            specs_made = [waiting.spec for waiting in group]
            made = None
            if group[0].jpeg:
                synthesizer = synthesizer or _synthesizer(job)
                made = jpeg.make(specs_made, inputs,
                                 functools.partial(make_batch, job, synthesizer),
                                 functools.partial(make_sample, job))
            elif group[0].on_device:
                batch = frames.batch_of(inputs)
                if batch is not None:
                    synthesizer = synthesizer or _synthesizer(job)
                    made = make_batch(job, synthesizer, specs_made, batch, staging.results)
            elif len(group) > 1:
                batch = staging.batch_of(slot, inputs, job.scene.blur.mode == "average")
                if batch is not None:
                    synthesizer = synthesizer or _synthesizer(job)
                    made = make_batch(job, synthesizer, specs_made, batch, staging.results)
            if made is None:
                made = [make_sample(job, spec, given)
                        for spec, given in zip(specs_made, inputs, strict=True)]
            times.deflated += sum(len(result.png or {}) for _, result, _ in made if result)
            if slot is not None:
                staging.release(slot, failed=any(error is not None for *_, error in made))
            yield from made
    finally:  # stopped early: nothing more is decoded
        for waiting in ahead:
            waiting.cancel()


class WriteBehind:
    """Writes made samples in a pool while the next ones are made; hands them back in order.

    Args:
        save: ``save(spec, result)`` writes a made sample's files and returns its manifest
            line (in a pool thread).
        pool: the I/O threads, or None to save each sample at once in this thread.
        depth: how many samples may wait for or be in writing; :meth:`put` waits for the
            oldest beyond that.
        times: where the pool's writing time is added (with a pool).
    """

    def __init__(self, save: Callable[[SampleSpec, Synthesis], dict],
                 pool: Executor | None = None, depth: int = 1, times: PoolTimes | None = None):
        self._save, self._pool, self._depth, self._times = save, pool, depth, times
        self._queue: deque[tuple[SampleSpec, str | None, object]] = deque()

    def put(self, spec: SampleSpec, result: Synthesis | None,
            error: str | None) -> Iterator[tuple]:
        """Queue an executor's ``(spec, result, error)``; returns the samples now written.

        They come as ``(spec, error, line)``, oldest first (``line`` None for a failed
        sample): those at the head of the queue whose files are written, and the oldest
        ones, waited for, while more than ``depth`` wait. A failed write raises its error.
        Only the pool holds a result, until its files are written.
        """
        if error is not None:
            saving = None
        elif self._pool is None:
            saving = self._save(spec, result)
        else:
            saving = self._pool.submit(self._times.run, "write", self._save, spec, result)
        self._queue.append((spec, error, saving))
        return self._written()

    def _written(self) -> Iterator[tuple]:
        while self._queue and (len(self._queue) > self._depth or _ready(self._queue[0][2])):
            yield self._next()

    def drain(self) -> Iterator[tuple]:
        """Yields every sample still queued, as :meth:`put` does, waiting for its files."""
        while self._queue:
            yield self._next()

    def _next(self) -> tuple:
        spec, error, saving = self._queue[0]
        line = saving.result() if isinstance(saving, Future) else saving
        self._queue.popleft()  # only once written: a stop while waiting keeps it queued
        return spec, error, line


def _ready(saving) -> bool:
    return not isinstance(saving, Future) or saving.done()
