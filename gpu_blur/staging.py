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

import numpy as np

__all__ = ["PinnedStaging"]


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
