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
import itertools
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future

import cv2
import numpy as np

from gpu_blur.discovery import SampleSpec
from gpu_blur.frame_cache import FrameCache
from gpu_blur.image_arrays import check_image
from gpu_blur.image_reading import opencv_reason, read_image
from gpu_blur.reference.output import to_integers
from gpu_blur.scene import Scene
from gpu_blur.scheduler import Schedule
from gpu_blur.synthesis import Synthesis, synthesize
from gpu_blur.timings import PoolTimes

__all__ = ["Job", "MAX_DEFAULT_IO_THREADS", "PinnedStaging", "QUEUE_PER_THREAD", "STAGED_SAMPLES",
           "WriteBehind", "checked_inputs", "decode", "default_io_threads", "for_driver",
           "make_sample", "pinned_staging", "read_input", "run_pipelined", "run_serial"]

#: Samples per I/O thread that may wait on each side of synthesis: decoded (or being decoded)
#: ahead of the sample being made, and made but not yet written behind it. With N threads at
#: most 2 N samples' inputs and 2 N samples' outputs are held, besides the one being made.
QUEUE_PER_THREAD = 2
#: The most I/O threads ``--io-threads`` takes by default, however many cores the host has:
#: enough to decode 9 PNG frames of 1920 x 1200 for a few hundred samples a second, while the
#: queues stay within a few GB (such a sample holds 62 MB of frames and 55 MB of outputs).
MAX_DEFAULT_IO_THREADS = 32
#: Samples copied into page-locked host memory ahead of the one being made, on a GPU
#: (:class:`PinnedStaging`): 4 slots of a 1920 x 1200 RSBlur sample hold 250 MB.
STAGED_SAMPLES = 4


def default_io_threads() -> int:
    """``--io-threads``' default: the cores this process may run on, at most 32."""
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
             else os.cpu_count())
    return max(1, min(cores or 1, MAX_DEFAULT_IO_THREADS))


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


class PinnedStaging:
    """Page-locked host slots that I/O threads copy a sample's decoded inputs into.

    A GPU backend copies page-locked memory to the device at the bus's rate and pageable
    memory through a staging copy of its own on the thread that makes the samples (a 1920 x
    1200 RSBlur sample's 9 frames, 62 MB, took that thread 8.6 ms an H200 sample at e7b24ae,
    bench/generate_gpu.py). Staged here by an I/O thread, a sample's frames go up with one
    copy the device's copy engine makes: ``make_sample`` gets them as views of one stack in a
    slot (:func:`gpu_blur.backends.pinned_stack` finds the stack again). The slots' memory is
    allocated on the making thread, as a sample first needs it (page-locking is slow and
    device APIs want their own thread); a sample that does not fit a slot yet goes as it is.

    Args:
        backend: the kernel backend that makes the samples (its ``pinned``).
        slots: samples staged at once, ahead of the one being made.
    """

    def __init__(self, backend, slots: int):
        self._backend = backend
        self._buffers: list[np.ndarray | None] = [None] * slots
        self._wanted = [0] * slots  # bytes a sample needed that its slot did not have
        self.free = list(range(slots))

    def fill(self, slot: int, images: tuple[np.ndarray, ...] | None
             ) -> tuple[np.ndarray, ...] | None:
        """``images`` copied into ``slot`` as one stack (in an I/O thread), or as they are.

        Only images of one shape and dtype are stacked; they come back as views of the stack.
        """
        if not images or len({(i.shape, i.dtype) for i in images}) > 1:
            return images
        nbytes = sum(image.nbytes for image in images)
        buffer = self._buffers[slot]
        if buffer is None or buffer.nbytes < nbytes:
            self._wanted[slot] = nbytes  # the making thread allocates it (:meth:`grow`)
            return images
        stack = buffer[:nbytes].view(images[0].dtype).reshape((len(images), *images[0].shape))
        for into, image in zip(stack, images, strict=True):
            np.copyto(into, image)
        return tuple(stack)

    def release(self, slot: int, failed: bool = False) -> None:
        """``slot`` free again once its sample is made (on the making thread).

        A made sample's results were fetched, so its upload is done; after a failed one the
        device is waited for. The slot gets the page-locked bytes its sample wanted.
        """
        if failed:
            self._backend.wait()
        if self._wanted[slot]:
            self._buffers[slot] = None  # the old block is freed before the larger one is made
            self._buffers[slot] = self._backend.pinned((self._wanted[slot],), np.uint8)
            self._wanted[slot] = 0
        self.free.append(slot)


def pinned_staging(job: Job) -> PinnedStaging | None:
    """:class:`PinnedStaging` for a job whose backend copies to a GPU, else None.

    So where the backend is a kernel backend on an NVIDIA GPU (Warp on CUDA, NVIDIA's
    OpenCL) and the job runs whole images on it (no tiles, budget or spot checks: those run
    on the host's copies).
    """
    from gpu_blur.backends import get_backend, is_resident

    if job.schedule is not None and job.schedule != Schedule():
        return None
    backend = get_backend(job.backend, job.scene.output.precision)
    if not (is_resident(backend) and backend.uses_cuda):
        return None
    return PinnedStaging(backend, STAGED_SAMPLES)


class _Inputs:
    """A sample's input files decoded in a pool, a task per file, then checked.

    The task that decodes the last file checks them all (:func:`checked_inputs`), so no
    thread waits on another's decode; :attr:`checked` then holds the arrays or None.
    :meth:`stage` has a slot of :class:`PinnedStaging` filled once they are checked.
    """

    def __init__(self, spec: SampleSpec, pool: Executor, times: PoolTimes,
                 cache: FrameCache | None):
        self.spec, self.checked, self.staged, self.slot = spec, Future(), None, None
        self._images: list = [None] * len(spec.inputs)
        self._left, self._lock = len(spec.inputs), threading.Lock()
        self.tasks = [] if spec.problem or not spec.inputs else [
            pool.submit(times.run, "decode", self._read, i, path, cache)
            for i, path in enumerate(spec.inputs)]
        if not self.tasks:
            self.checked.set_result(None)
        else:
            times.samples += 1  # on the making thread

    def _read(self, i: int, path, cache) -> None:
        try:
            image = read_input(path, cache)
        except Exception:  # synthesize meets it again, and says what it is
            image = None
        with self._lock:
            self._images[i] = image
            self._left -= 1
            last = self._left == 0
        if last:
            images = None if any(image is None for image in self._images) else self._images
            self.checked.set_result(checked_inputs(self.spec, images))

    def stage(self, staging: PinnedStaging, slot: int, pool: Executor, times: PoolTimes) -> None:
        """Copy the checked inputs into ``slot`` in the pool; :attr:`staged` holds the views."""
        self.slot, self.staged = slot, Future()

        def fill() -> None:
            self.staged.set_result(staging.fill(slot, self.checked.result()))

        def submit(_) -> None:
            try:
                pool.submit(times.run, "decode", fill)
            except RuntimeError:  # the pool is shut down: the run stopped
                self.staged.set_result(self.checked.result())

        self.checked.add_done_callback(submit)

    def result(self) -> tuple[np.ndarray, ...] | None:
        """The inputs for ``make_sample``: staged if they are, else as decoded."""
        return (self.staged or self.checked).result()

    def cancel(self) -> None:
        for task in self.tasks:
            task.cancel()


def run_pipelined(job: Job, specs: Iterable[SampleSpec], pool: Executor, times: PoolTimes,
                  depth: int, cache: FrameCache | None = None,
                  staging: PinnedStaging | None = None) -> Iterator[tuple]:
    """Make the samples in this thread, in order, while ``pool`` decodes the next ones' inputs.

    At most ``depth`` samples are decoded or being decoded ahead of the one being made, each
    file a task of its own (so the frames that overlapping windows share are decoded in
    parallel, not one after another by the first window's thread). With ``staging`` the pool
    also copies the next samples into its page-locked slots. The results are
    :func:`run_serial`'s; the time this thread waits for inputs is added to
    ``times.waited_for_inputs``, the pool's decoding and staging to ``times.busy["decode"]``.
    """
    rest = iter(specs)
    ahead: deque[_Inputs] = deque()
    try:
        while True:
            for spec in itertools.islice(rest, depth - len(ahead)):
                ahead.append(_Inputs(spec, pool, times, cache))
            if not ahead:
                return
            for waiting in ahead:  # the oldest samples not yet staged, while slots are free
                if staging is None or not staging.free:
                    break
                if waiting.staged is None:
                    waiting.stage(staging, staging.free.pop(), pool, times)
            start = time.perf_counter()
            inputs = ahead[0].result()
            times.waited_for_inputs += time.perf_counter() - start
            spec, slot = ahead[0].spec, ahead[0].slot
            ahead.popleft()
            made = make_sample(job, spec, inputs)
            if slot is not None:
                staging.release(slot, failed=made[2] is not None)
            yield made
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
