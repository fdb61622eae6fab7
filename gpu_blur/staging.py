"""Page-locked host slots that ``gpu-blur generate``'s I/O threads fill with decoded samples.

A GPU backend copies page-locked ("pinned") host memory to the device at the bus's rate, and
pageable memory only through a staging copy of its own, made on the thread that makes the
samples. Here the I/O threads copy each decoded sample into a slot of :class:`PinnedStaging`,
beside the others of its batch, and the making thread hands the slot's batch to the device as
one array (``Synthesizer`` on a B x F x H x W x 3 pinned batch), or a sample's frames as views
of one stack (:func:`gpu_blur.backends.pinned_stack` finds it again). Only where a sample is
staged does anything change; the bytes made are the same either way
(tests/synthesis/test_generate_pipeline.py). docs/performance.md, "Whole sets from disk", has
the rates before and after.

The batch's results come back the same way: :class:`LentResults` lends it page-locked arrays
for ``out=``, which the device writes at the bus's rate, and takes each block back once the
I/O threads have written its samples and dropped their arrays.

Where samples share frames (overlapping windows of a sequence) on a Warp GPU,
:class:`DeviceFrames` keeps each shared frame on the device once and puts their batches
together there, so those frames cross neither the I/O threads' copies nor the bus again.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict

import numpy as np

from gpu_blur.arrays import WarpFrames
from gpu_blur.backends import PinnedHost
from gpu_blur.timings import timer

__all__ = ["DeviceFrames", "LENT_RESULTS_BYTES", "LentResults", "PinnedStaging"]

#: Page-locked bytes :class:`LentResults` holds at most: the results of the batches a run has
#: in flight (made, waiting to be written). 1 GiB holds 18 batches of four 1920 x 1200
#: samples' 8-bit blurred and sharp images; a run that needs more gets plain arrays past it.
LENT_RESULTS_BYTES = 1 << 30


class PinnedStaging:
    """Slots of page-locked host memory, each for a batch of up to ``batch`` samples.

    A slot's memory is allocated on the making thread when a sample first needs it
    (:meth:`release`; page-locking is slow, and device APIs want their own thread): until
    then, and for a sample larger than the slot's stride, :meth:`fill` hands the images back
    as they are. Sample ``p`` of a slot lies at ``p`` strides from its start.

    Args:
        backend: the kernel backend that makes the samples (its ``pinned``).
        slots: batches staged at once, ahead of the one being made.
        batch: samples per slot.
    """

    def __init__(self, backend, slots: int, batch: int):
        self.backend, self.batch = backend, batch
        #: page-locked arrays for the batches' results (``Synthesizer``'s ``out=``)
        self.results = LentResults(backend)
        self._buffers: list[np.ndarray | None] = [None] * slots
        self._stride = [0] * slots  # bytes a sample may take in each slot
        self._wanted = [0] * slots  # bytes a sample needed that its slot did not have
        self._lock = threading.Lock()
        self.free = list(range(slots))

    def fill(self, slot: int, position: int, images: tuple[np.ndarray, ...] | None
             ) -> tuple[np.ndarray, ...] | None:
        """``images`` copied to ``position`` of ``slot`` as one stack (in an I/O thread).

        They come back as views of the stack; images of several shapes or dtypes, and those
        the slot has no room for yet, come back as they are.
        """
        if not images or len({(i.shape, i.dtype) for i in images}) > 1:
            return images
        nbytes = sum(image.nbytes for image in images)
        buffer, stride = self._buffers[slot], self._stride[slot]
        if buffer is None or nbytes > stride:
            with self._lock:  # the making thread allocates it (:meth:`release`)
                self._wanted[slot] = max(self._wanted[slot], nbytes)
            return images
        at = position * stride
        stack = buffer[at:at + nbytes].view(images[0].dtype).reshape(
            (len(images), *images[0].shape))
        for into, image in zip(stack, images, strict=True):
            np.copyto(into, image)
        return tuple(stack)

    def batch_of(self, slot: int, samples: list, frames: bool) -> np.ndarray | None:
        """The slot's first ``len(samples)`` samples as one pinned batch, or None.

        ``samples``: what :meth:`fill` returned for positions 0, 1, ..., each staged there
        with one shape and dtype and filling its stride; ``frames``: each sample is a stack of
        frames (B x F x H x W x 3), else one image (B x H x W x 3).
        """
        buffer, stride = self._buffers[slot], self._stride[slot]
        if buffer is None or any(s is None for s in samples):
            return None
        first = samples[0]
        if len({(len(s), s[0].shape, s[0].dtype) for s in samples}) > 1 or (
                len(first) * first[0].nbytes != stride) or (not frames and len(first) != 1):
            return None
        start = buffer.ctypes.data
        if any(s[0].ctypes.data != start + p * stride for p, s in enumerate(samples)):
            return None
        shape = (len(first), *first[0].shape) if frames else first[0].shape
        return buffer[:len(samples) * stride].view(first[0].dtype).reshape(
            (len(samples), *shape))

    @property
    def sized(self) -> bool:
        """Whether every slot has memory yet."""
        return all(buffer is not None for buffer in self._buffers)

    def size_for(self, images: tuple[np.ndarray, ...]) -> None:
        """Give every free slot room for samples like ``images`` (on the making thread).

        Called with the first sample decoded, so that no batch goes one by one while its
        slot is allocated.
        """
        nbytes = sum(image.nbytes for image in images)
        for slot in self.free:
            with self._lock:
                self._wanted[slot] = max(self._wanted[slot], nbytes)
            self._grow(slot)

    def release(self, slot: int, failed: bool = False) -> None:
        """``slot`` free again once its samples are made (on the making thread).

        A made sample's results were fetched, so its upload is done; after a failure the
        device is waited for. The slot gets the bytes its samples wanted.
        """
        if failed:
            self.backend.wait()
        self._grow(slot)
        self.free.append(slot)

    def _grow(self, slot: int) -> None:
        if self._wanted[slot] > self._stride[slot]:
            self._buffers[slot] = None  # the old block is freed before the larger one is made
            self._stride[slot] = self._wanted[slot]
            self._buffers[slot] = self.backend.pinned((self.batch * self._wanted[slot],),
                                                      np.uint8)
        self._wanted[slot] = 0


class LentResults:
    """Page-locked arrays for a batch's results, each block lent until its arrays are gone.

    The device copies results into page-locked memory at the bus's rate; into plain arrays
    a backend copies them through its own staging on the making thread, slowly while the I/O
    threads keep the cores busy. Page-locking is slow too, so a block is locked once and lent
    again (docs/performance.md, "Lent results", has the times): :meth:`take` wraps it in a new
    :class:`~gpu_blur.backends.PinnedHost`, and when the last array over that wrapper is
    dropped (the I/O threads wrote its samples) a finalizer gives the block back. So nothing
    reads a block lent again: its arrays are gone. Nor does the device write into it late: a
    batch's results are waited for before they are returned, and a failed batch's copies run
    before any later batch's, in the order they were queued on the device.

    Args:
        backend: the kernel backend whose :meth:`pinned` memory it lends.
        limit: page-locked bytes held at most; past them :meth:`take` gives None.
    """

    def __init__(self, backend, limit: int = LENT_RESULTS_BYTES):
        self.backend, self.limit = backend, limit
        self._free: list[np.ndarray] = []  # blocks given back, flat uint8
        self._held = 0  # bytes page-locked, lent or free
        # reentrant: a wrapper in a reference cycle is finalized whenever the cyclic GC runs,
        # which may be inside take() on the thread that holds the lock
        self._lock = threading.RLock()

    def take(self, arrays: list[tuple[tuple[int, ...], object]]) -> list[np.ndarray] | None:
        """An uninitialized page-locked array per ``(shape, dtype)``, or None past the limit."""
        sizes = [int(np.prod(shape)) * np.dtype(dtype).itemsize for shape, dtype in arrays]
        blocks = []
        with self._lock:
            for nbytes in sizes:
                fits = [i for i, b in enumerate(self._free) if b.nbytes >= nbytes]
                if fits:
                    blocks.append(self._free.pop(min(fits, key=lambda i: self._free[i].nbytes)))
                else:
                    blocks.append(nbytes)  # to page-lock
            new = sum(b for b in blocks if isinstance(b, int))
            if self._held + new > self.limit:
                self._free += [b for b in blocks if not isinstance(b, int)]
                return None
            self._held += new
        try:
            blocks = [self.backend.pinned((b,), np.uint8) if isinstance(b, int) else b
                      for b in blocks]
        except BaseException:  # nothing lent: the free blocks back, the new ones unlocked
            with self._lock:
                self._held -= new
                self._free += [b for b in blocks if not isinstance(b, int)]
            raise
        return [self._lend(block, nbytes).view(dtype).reshape(shape)
                for block, nbytes, (shape, dtype) in zip(blocks, sizes, arrays, strict=True)]

    def _lend(self, block: np.ndarray, nbytes: int) -> np.ndarray:
        """The first ``nbytes`` of ``block`` over a new wrapper that gives it back when gone."""
        lent = PinnedHost(self.backend, block, block.ctypes.data, nbytes)
        weakref.finalize(lent, self._given_back, block).atexit = False
        return np.asarray(lent)

    def _given_back(self, block: np.ndarray) -> None:
        with self._lock:
            self._free.append(block)


class DeviceFrames:
    """Decoded frames kept on a Warp device for the samples that share them.

    Overlapping windows of a sequence use each frame in several samples. Each such frame is
    uploaded once from the frame cache's array (which every sample that reads the file gets,
    read-only), and a batch of those samples is put together on the device, one device copy
    a frame, for ``Synthesizer`` to read where it lies: no page-locked slot to fill, and the
    bus carries each frame once instead of once a sample. The bytes made are the same
    (tests/synthesis/test_generate_pipeline.py). On the making thread only; the copies are
    queued on the device's current stream, the one the backend launches on, so a batch's
    buffer is written again only after the launches that read it.

    Args:
        backend: the Warp backend that makes the samples (``device_arrays``).
        limit: bytes of frames kept on the device (and their host arrays kept alive) at
            most; the least recently used go first.
    """

    def __init__(self, backend, limit: int):
        self.backend, self.limit = backend, limit
        #: id(host frame) -> (the host frame, kept so that its id stays its own; flat copy)
        self._frames: OrderedDict[int, tuple[np.ndarray, object]] = OrderedDict()
        self._held = 0
        self._buffer = None  # the last batch's device buffer, flat, reused while it fits
        self.uploads = 0  # frames copied to the device

    def batch_of(self, samples: list[tuple[np.ndarray, ...] | None]) -> WarpFrames | None:
        """The samples' frames as one B x F x H x W x C batch on the device, or None.

        None where a sample has no frames (a failed decode), the frames differ in count,
        shape or dtype, or a side is odd (the RAW round trip would crop it): the caller then
        makes the samples one by one.
        """
        import warp as wp

        if not samples or any(not sample for sample in samples):
            return None
        first = samples[0][0]
        frames = [frame for sample in samples for frame in sample]
        if len({len(sample) for sample in samples}) > 1 or first.ndim != 3 or any(
                frame.shape != first.shape or frame.dtype != first.dtype for frame in frames
        ) or first.shape[0] % 2 or first.shape[1] % 2:
            return None
        dtype, size = wp.dtype_from_numpy(first.dtype), first.size
        count = len(frames) * size
        if (self._buffer is None or self._buffer.size < count
                or self._buffer.dtype != dtype):
            self._buffer = None  # freed before the larger one is made
            self._buffer = wp.empty(count, dtype=dtype, device=self.backend.wp_device)
        with timer("copies"):
            for k, frame in enumerate(frames):
                wp.copy(self._buffer, self._on_device(frame, dtype), dest_offset=k * size,
                        count=size)
        return WarpFrames(self._buffer[:count],
                          (len(samples), len(samples[0]), *first.shape))

    def _on_device(self, frame: np.ndarray, dtype):
        import warp as wp

        kept = self._frames.get(id(frame))
        if kept is not None and kept[0] is frame:
            self._frames.move_to_end(id(frame))
            return kept[1]
        on_device = wp.array(np.ascontiguousarray(frame).reshape(-1), dtype=dtype,
                             device=self.backend.wp_device)
        self.uploads += 1
        self._frames[id(frame)] = (frame, on_device)
        self._held += frame.nbytes
        while self._held > self.limit and len(self._frames) > 1:
            _, (old, _) = self._frames.popitem(last=False)
            self._held -= old.nbytes
        return on_device
