"""Device buffers of the kernel backend: batch slots, inputs put on the device, pinned staging.

:class:`Slots` are a batch's buffers, one slot per sample. :class:`Buffers` declares the buffer
primitives a language supplies and holds the host logic over them: small constants, outputs,
slots and the per-sample tables, puts (through pinned staging or straight from
:meth:`~Buffers.pinned` memory), and inputs lying evenly spaced in one device buffer.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from gpu_blur.backends import (
    FRAMES_PER_LAUNCH,
    OnDevice,
    PinnedHost,
    Slots,
    copy_values,
    pinned_owner,
)
from gpu_blur.backends.kernel.config import Arg, Drawn, sample_tables, source_dtype
from gpu_blur.planning import Pass
from gpu_blur.testhooks import fault_planted, planted_fault
from gpu_blur.tiling import Region

__all__ = ["Buffers"]


def _check_slots(samples: Sequence[Drawn], buffers) -> None:
    """Refuse a batched launch whose slots could not hold what its kernel reads or writes.

    ``buffers``: (name, :class:`Slots`, values a slot must hold) each. The kernels index by
    slot and stride without bounds checks, so this is what keeps them inside the buffers.
    """
    used = [d.slot for d in samples]
    top = max(used, default=-1)
    for name, slots, needed in buffers:
        if slots.stride < needed or top >= slots.count or min(used, default=0) < 0:
            raise ValueError(f"batched launch: {name} has {slots.count} slot(s) of "
                             f"{slots.stride} values; its samples need slots 0..{top} of "
                             f"{needed} values (a gpu_blur bug: please report it)")


class Buffers:
    """The buffers of :class:`~gpu_blur.backends.kernel.KernelBackend`, one of its parts.

    A language supplies the primitives (``_upload``, ``_empty``, ``_zeros``, ``_write``,
    ``_fetch``, ``_fetch_queued``, ``_view``, ``_copy``, ``_fill_zeros``, ``_part``,
    ``_pinned_bytes``); the rest is written once over them.
    """

    # -- primitives a language supplies ----------------------------------------------------
    def _upload(self, values, dtype=None):
        """``values`` on the device, flat: an :class:`OnDevice` as it is, host data copied."""
        raise NotImplementedError

    def _empty(self, count: int, dtype=None):
        """An uninitialized flat device buffer of ``count`` values (compute type by default)."""
        raise NotImplementedError

    def _zeros(self, count: int, dtype=None):
        """A zeroed flat device buffer."""
        raise NotImplementedError

    def _write(self, buffer, values: np.ndarray) -> None:
        """Copy host ``values`` into the device buffer ``buffer`` (after earlier launches)."""
        raise NotImplementedError

    def _fetch(self, values: OnDevice, dtype) -> np.ndarray:
        """An output's host copy (timed as ``copies``)."""
        raise NotImplementedError

    def _fetch_queued(self, buffer, into: np.ndarray) -> Callable[[], None]:
        """Queue a copy of ``buffer``'s first ``into.size`` values into host ``into``.

        ``into``: this backend's :meth:`pinned` memory, of the buffer's dtype. The function
        returned waits for that copy alone, not for what is queued after it.
        """
        raise NotImplementedError

    def device_array(self, values: OnDevice):
        """A result's flat device buffer, as the backend holds it."""
        return values.data

    def _stacks_for(self, frames: Sequence[np.ndarray], region: Region, dtype):
        """How :meth:`_frame_stacks` splits ``frames`` into device stacks.

        Returns:
            (frames per stack, values per frame, each stack's frame indices, the two device
            stacks that take turns).
        """
        per = min(FRAMES_PER_LAUNCH, len(frames))
        values = region.h * region.w * 3
        groups = [range(i, min(i + per, len(frames))) for i in range(0, len(frames), per)]
        stacks = [self._empty(per * values, dtype) for _ in range(min(2, len(groups)))]
        return per, values, groups, stacks

    def _constant(self, values, dtype=None):
        """A small constant (matrix, polynomial, table) on the device, uploaded once."""
        data = np.ascontiguousarray(np.ravel(values), dtype=dtype or self.np_real)
        key = (data.tobytes(), data.dtype.str)
        if key not in self._constants:
            self._constants[key] = self._upload(data, data.dtype)
        return self._constants[key]

    def _out(self, buffer, shape, pass_: Pass, origin) -> OnDevice:
        """A pass's output, with the :data:`~gpu_blur.testhooks.TEST_FAULT` hook applied."""
        result = OnDevice(buffer, shape, self._fetch)
        if fault_planted(pass_):
            host = planted_fault(pass_, result.numpy(), origin)
            self._write(buffer, np.ascontiguousarray(host.ravel(), dtype=self.np_real))
        return result

    def _into_slots(self, slots: Sequence[Slots], b: int, count: int, fill) -> None:
        """``fill(buffers)`` writes the first ``count`` values of slot ``b`` of each of ``slots``.

        In place where the language has views of a buffer (Warp); else into new buffers, then
        copied into the slots (OpenCL: NVIDIA's sub-buffers cost several times the copy).
        """
        into = tuple(self._in_slot(s, b, count) for s in slots)
        if None not in into:
            fill(into)
            return
        into = tuple(self._empty(count) for _ in slots)
        fill(into)
        for s, values in zip(slots, into, strict=True):
            self._copy(s.buffer, values, count, b * s.stride)

    #: Whether :meth:`_view` gives views of a buffer (else slots are read and written by copies).
    slot_views = False

    def _view(self, buffer, start: int, count: int):
        """Values ``start .. start + count`` of a device buffer, as a buffer sharing its memory."""
        raise NotImplementedError

    def _in_slot(self, slots: Slots, b: int, count: int):
        """The first ``count`` values of slot ``b`` as a buffer sharing its memory, or None.

        A view where the language has them; slot 0 is the buffer itself (its first values).
        """
        if self.slot_views:
            return self._view(slots.buffer, b * slots.stride, count)
        return slots.buffer if b == 0 else None

    def slot_image(self, slots: Slots, b: int, shape) -> OnDevice:
        """Slot ``b`` of a batch buffer as an ``OnDevice`` image of ``shape``.

        A view where the language has them (and for slot 0), else a device copy.
        """
        size = int(np.prod(shape))
        data = self._in_slot(slots, b, size)
        if data is None:
            data = self._part(slots.buffer, b * slots.stride, size, None)
        return OnDevice(data, shape, self._fetch)

    def stacked(self, slots: Slots, shape) -> OnDevice:
        """Every slot of a batch buffer as one ``count x shape`` ``OnDevice`` stack."""
        return OnDevice(slots.buffer, (slots.count, *shape), self._fetch)

    def _copy(self, into, values, count: int, offset: int = 0) -> None:
        """Copy ``count`` values of ``values`` into ``into`` from value ``offset`` on.

        Both device buffers; queued after the launches before it.
        """
        raise NotImplementedError

    def _fill_zeros(self, buffer, count: int) -> None:
        """Set the first ``count`` values of a device buffer to zero, in queue order."""
        raise NotImplementedError

    def put(self, image) -> OnDevice:
        """An input on the device in its stored dtype, for :meth:`accumulate` and the checks.

        Args:
            image: ``H x W x 3`` (or an ``n x H x W x 3`` stack of frames, or a list of ``n``
                frames of one size and dtype) as stored: uint8 or uint16 codes go as they
                are, floats as the compute type; a host array is copied once.
        """
        if isinstance(image, (list, tuple)):
            image = np.stack(image)
        dtype = source_dtype(image, self.np_real)
        return self._input(self._upload(image, dtype), np.shape(image), dtype)

    def pinned(self, shape, dtype=np.float32) -> np.ndarray:
        """An uninitialized host array in page-locked memory this backend copies directly.

        An input batch filled in it (``np.stack(frames, out=...)``) uploads with no staging
        copy, and ``out=`` arrays made here receive the results straight from the device: the
        bus's rate instead of the host's copy rate. Page-locking is slow: make them once and
        reuse them.
        """
        dtype = np.dtype(dtype)
        nbytes = max(int(np.prod(shape)) * dtype.itemsize, 1)
        keep, address = self._pinned_bytes(nbytes)
        flat = np.asarray(PinnedHost(self, keep, address, nbytes))
        return flat[:int(np.prod(shape)) * dtype.itemsize].view(dtype).reshape(shape)

    def _pinned_bytes(self, nbytes: int) -> tuple:
        """(what holds it, its address): ``nbytes`` of page-locked host memory."""
        raise NotImplementedError

    def _direct(self, x, dtype=None) -> bool:
        """Whether ``x`` copies straight to or from the device (no staging).

        So it does when it is a host array in this backend's :meth:`pinned` memory,
        contiguous, in ``dtype`` (default: the dtype it travels in).
        """
        if not isinstance(x, np.ndarray):
            return False
        dtype = source_dtype(x, self.np_real) if dtype is None else np.dtype(dtype)
        return x.dtype == dtype and x.flags.c_contiguous and pinned_owner(x) is self

    def _input(self, data, shape, dtype) -> OnDevice:
        """An input put on the device, ``dtype`` recorded for codes (None: the compute type)."""
        return OnDevice(data, shape, self._fetch,
                        None if np.dtype(dtype) == np.dtype(self.np_real) else dtype)

    def _staged_parts(self, image) -> tuple:
        """A host input for a put through pinned staging (``overlap``), and the buffer it takes.

        ``image``: an array, or a list of frames of one size and dtype (copied one after
        another: no stacked host copy). Returns (parts, shape, dtype it travels in, values,
        slot): two pinned input buffers take turns, so filling one overlaps the other's upload.
        """
        frames = isinstance(image, (list, tuple))
        parts = list(image) if frames else [np.asarray(image)]
        shape = (len(parts), *parts[0].shape) if frames else parts[0].shape
        slot = ("put", self._put_turn)
        self._put_turn ^= 1
        return (parts, shape, source_dtype(parts[0], self.np_real), parts[0].size * len(parts),
                slot)

    @staticmethod
    def _fill_staging(host: np.ndarray, parts) -> None:
        """Copy ``parts`` one after another into the flat pinned array ``host`` (threads)."""
        copy_values(host[:parts[0].size * len(parts)], list(parts))

    def consecutive(self, images: Sequence[OnDevice]) -> OnDevice | None:
        """``images`` as one ``B x shape`` image, where they lie back to back in one buffer.

        Else None; see :meth:`spaced` (here the images are exactly their size apart).
        """
        spaced = self.spaced(images)
        size = int(np.prod(images[0].shape)) if images else 0
        if spaced is None or spaced[1] != size:
            return None
        return OnDevice(spaced[0], (len(images), *images[0].shape), self._fetch,
                        images[0].dtype)

    def spaced(self, images: Sequence[OnDevice]) -> tuple[object, int] | None:
        """(one flat buffer from the first image's first value, the values between images).

        Where ``images``, of one shape and dtype, lie evenly spaced in one device buffer (a
        torch or CuPy batch on a Warp device; the middle frames of a batch of frame stacks),
        batched launches read them at once; else None. Only a language with views of device
        memory (Warp) finds them (:meth:`_spaced_data`).
        """
        if not images or any(i.shape != images[0].shape or i.dtype != images[0].dtype
                             for i in images):
            return None
        return self._spaced_data([i.data for i in images])

    def _spaced_runs(self, images: Sequence[OnDevice]
                     ) -> list[tuple[list[OnDevice], tuple[object, int] | None]]:
        """``images`` cut, in order, into runs: each with its :meth:`spaced`, or None.

        A run of several images lies evenly spaced in one device buffer (a fixed number of
        values apart) and has its :meth:`spaced`; every other image is a run of its own, with
        None (so are those of a run :meth:`spaced` refuses as a whole).
        """
        runs: list[list[OnDevice]] = []
        stride = None  # the last run's spacing
        for image in images:
            last = runs[-1][-1] if runs else None
            gap = (self._gap(last.data, image.data) if last is not None
                   and (last.shape, last.dtype) == (image.shape, image.dtype) else None)
            if gap is not None and (len(runs[-1]) == 1 or gap == stride):
                runs[-1].append(image)
                stride = gap
            else:
                runs.append([image])
        found = []
        for run in runs:
            spaced = self.spaced(run) if len(run) > 1 else None
            found += [(run, spaced)] if spaced is not None else [([i], None) for i in run]
        return found

    def _spaced_data(self, buffers: Sequence) -> tuple[object, int] | None:
        """:meth:`spaced` of device buffers of one size and dtype."""
        return None

    def _gap(self, first, second) -> int | None:
        """Values from device buffer ``first``'s start to ``second``'s, or None.

        None unless both are alike (size, dtype, device, contiguous) and ``second`` starts
        at or after ``first``'s end: they are two of a run :meth:`spaced` finds.
        """
        return None

    def frame(self, stack: OnDevice, index: int) -> OnDevice:
        """Frame ``index`` of an ``n x H x W x 3`` stack :meth:`put` on the device."""
        n = int(np.prod(stack.shape[1:]))
        return OnDevice(self._part(stack.data, index * n, n, stack.dtype), stack.shape[1:],
                        self._fetch, stack.dtype)

    def _part(self, buffer, start: int, count: int, dtype):
        """Values ``start .. start + count`` of a device buffer (a view, or a device copy)."""
        raise NotImplementedError

    def export(self, values: OnDevice, region: Region, into) -> None:
        """Copy ``region`` of a whole-image device result into ``into``, a host array."""
        np.copyto(into, region.of(values.numpy(into.dtype)))

    def slots(self, count: int, values: int) -> Slots:
        """A new batch buffer of ``count`` slots of ``values`` values each, back to back."""
        return Slots(self._empty(count * values), count, values)

    def _tables(self, samples: Sequence[Drawn]) -> tuple:
        """:func:`sample_tables` on the device, as the kernels read them.

        The last upload is kept: the finish pass of the samples whose to_raw pass just ran
        reads the same tables (the buffers stay alive while the launches that read them run).
        """
        values, words = sample_tables(samples)
        values = values.astype(self.np_real)
        key = (values.tobytes(), words.tobytes())
        if self._last_tables is None or self._last_tables[0] != key:
            self._last_tables = (key, (self._rows(values), self._rows(words)))
        return self._last_tables[1]

    def _rows(self, table: np.ndarray):
        """A small host table (a sample's draws, its kernel taps) on the device, in its dtype.

        Flat where the language indexes by hand (OpenCL); Warp keeps its shape and, on CUDA,
        queues the copy instead of waiting for the device.
        """
        return self._upload(table, table.dtype)

    def _slots(self, slots: Slots) -> tuple:
        """A batch buffer as its kernels take it: (flat buffer, stride); Warp: a 2-D view.

        The stride is an ``extent`` (OpenCL steps by it); Warp's view is ``count x stride``.
        """
        return slots.buffer, Arg("index", slots.stride, extent=True)
