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
"""

from __future__ import annotations

import threading
from concurrent.futures import Future

import numpy as np

__all__ = ["PinnedStaging"]


class PinnedStaging:
    """Slots of page-locked host memory, each for a batch of up to ``batch`` samples.

    The slots' first memory is allocated by a thread of their own while the first samples
    are decoded (:meth:`size_for`; page-locking 250 MB takes ~100 ms on an H100's host),
    later growth on the making thread (:meth:`release`).
    :meth:`fill` waits for its slot's first memory; for a sample larger than the slot's
    stride it hands the images back as they are. Sample ``p`` of a slot lies at ``p``
    strides from its start.

    Args:
        backend: the kernel backend that makes the samples (its ``pinned``).
        slots: batches staged at once, ahead of the one being made.
        batch: samples per slot.
    """

    def __init__(self, backend, slots: int, batch: int):
        self.backend, self.batch = backend, batch
        self._buffers: list[np.ndarray | None] = [None] * slots
        self._stride = [0] * slots  # bytes a sample may take in each slot
        self._wanted = [0] * slots  # bytes a sample needed that its slot did not have
        self._lock = threading.Lock()
        self._first: list[Future] | None = None  # each slot's first memory (size_for)
        self.free = list(range(slots))

    def fill(self, slot: int, position: int, images: tuple[np.ndarray, ...] | None
             ) -> tuple[np.ndarray, ...] | None:
        """``images`` copied to ``position`` of ``slot`` as one stack (in an I/O thread).

        They come back as views of the stack; images of several shapes or dtypes, and those
        the slot has no room for yet, come back as they are.
        """
        if not images or len({(i.shape, i.dtype) for i in images}) > 1:
            return images
        if self._first is not None and self._first[slot].exception() is not None:
            return images  # the making thread raises it (:meth:`batch_of`, :meth:`release`)
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
        self._allocated(slot)
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
        """Whether the slots' first memory is allocated or being allocated (:meth:`size_for`)."""
        return self._first is not None

    def size_for(self, nbytes: int) -> None:
        """Start allocating every slot's room for samples of ``nbytes`` (making thread).

        Called before the first sample is decoded (its size from its files' headers) or
        with it, so that no batch goes one by one while its slot is allocated. A thread of
        its own allocates them, slot after slot, under the backend's device (its
        ``pinned``); an allocation that fails is raised on the making thread
        (:meth:`batch_of`, :meth:`release`), its slot's samples left unstaged.
        """
        self._first = [Future() for _ in self._buffers]
        for slot in range(len(self._buffers)):
            self._wanted[slot] = max(self._wanted[slot], nbytes)
        threading.Thread(target=self._allocate_first, name="gpu-blur-pinned",
                         daemon=True).start()

    def _allocate_first(self) -> None:
        for slot, done in enumerate(self._first):
            try:
                self._grow(slot)
            except Exception as error:  # raised on the making thread
                done.set_exception(error)
            else:
                done.set_result(None)

    def _allocated(self, slot: int) -> None:
        """Wait for ``slot``'s first memory, if it is being allocated; raise its failure."""
        if self._first is not None:
            self._first[slot].result()

    def release(self, slot: int, failed: bool = False) -> None:
        """``slot`` free again once its samples are made (on the making thread).

        A made sample's results were fetched, so its upload is done; after a failure the
        device is waited for. The slot gets the bytes its samples wanted.
        """
        if failed:
            self.backend.wait()
        self._allocated(slot)
        self._grow(slot)
        self.free.append(slot)

    def _grow(self, slot: int) -> None:
        if self._wanted[slot] > self._stride[slot]:
            self._buffers[slot] = None  # the old block is freed before the larger one is made
            self._stride[slot] = self._wanted[slot]
            self._buffers[slot] = self.backend.pinned((self.batch * self._wanted[slot],),
                                                      np.uint8)
        self._wanted[slot] = 0
