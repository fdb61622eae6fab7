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
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from gpu_blur.backends import PinnedHost

__all__ = ["LENT_RESULTS_BYTES", "LentResults", "PinnedStaging"]

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
