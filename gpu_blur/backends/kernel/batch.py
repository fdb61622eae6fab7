"""The batched passes of the kernel backend: a batch's accumulate, to_raw and finish.

Every intermediate image of a batch lies in batch buffers with one slot per sample
(:class:`~gpu_blur.backends.kernel.buffers.Slots`); the to_raw and finish kernels run once for
all samples of one plan, over a grid of (samples, rows, columns), and what differs per sample
reaches them as two small tables (:func:`~gpu_blur.backends.kernel.config.sample_tables`).
One sample's to_raw and finish are a batch of one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur.backends import OnDevice
from gpu_blur.backends.kernel.buffers import Slots, _check_slots
from gpu_blur.backends.kernel.config import (
    Arg,
    Drawn,
    PassConfig,
    _index,
    finish_args,
    to_raw_args,
)
from gpu_blur.cameras import Camera
from gpu_blur.kernel_constants import EXACT_FRAMES_MAX
from gpu_blur.planning import Pass, Plan, StageName
from gpu_blur.tiling import Region

__all__ = ["Batch", "S"]

S = StageName


class Batch:
    """The batched passes of :class:`~gpu_blur.backends.kernel.KernelBackend`, one of its parts."""

    def accumulate_into(self, plan: Plan, params: dict, frames: OnDevice,
                        mask: OnDevice | None, linear: Slots, sat_mask: Slots, b: int) -> None:
        """:meth:`accumulate` of whole inputs put on the device, into slot ``b`` of batch buffers.

        ``linear``, ``sat_mask``: slots of ``3 h w`` values (:meth:`slots`), as the batched
        to_raw pass reads them.
        """
        h, w = frames.shape[-3:-1]
        self._into_slots((linear, sat_mask), b, h * w * 3, lambda into: self._accumulate_put(
            plan, params, frames, mask, Region.whole(h, w), into))

    def accumulate_batch(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                         inputs: Sequence[tuple[OnDevice, OnDevice | None]], linear: Slots,
                         sat_mask: Slots) -> Slots:
        """:meth:`accumulate_into` for every sample of a batch, each into its slot.

        Returns the slots that hold the saturation masks: ``sat_mask``, or in blur mode none
        the given masks' own device buffer where they lie back to back in the compute type
        (:meth:`_linearize_batch`: nothing copied; the later passes only read it).

        Blur mode kernel takes two launches a sample fewer: each photo is linearized into its
        slot of two batch buffers made for the call (``3 h w`` values a sample each), then one
        launch convolves every sample with its own kernel (:meth:`_blur_kernels`). The other
        modes run sample by sample.

        Args:
            plans: each sample's plan.
            samples: each sample's draws, index and slot.
            inputs: each sample's (frames, mask) put on the device (:meth:`put`).
            linear: the batch's slots of ``3 h w`` values for the linear images.
            sat_mask: the same for the saturation masks.
        """
        masks = self._linearize_batch(plans, samples, inputs, linear, sat_mask)
        if masks is not None:
            return masks
        if self._averaged_at_once(plans, samples, [frames for frames, _ in inputs], linear,
                                  sat_mask):
            return sat_mask
        kernel_mode = [i for i, p in enumerate(plans) if p.variant(S.BLUR) == "kernel"]
        for p, drawn, (frames, mask) in zip(plans, samples, inputs, strict=True):
            if p.variant(S.BLUR) != "kernel":
                self.accumulate_into(p, drawn.params, frames, mask, linear, sat_mask, drawn.slot)
        if not kernel_mode:
            return sat_mask
        h, w = inputs[kernel_mode[0]][0].shape[-3:-1]
        n = h * w * 3
        src, ind = self.slots(linear.count, n), self.slots(linear.count, n)
        at_once = len(kernel_mode) == len(plans) and self._linearized_at_once(
            plans, samples, [photo for photo, _ in inputs], (src, ind))
        groups: dict = {}  # the samples of each accumulate configuration and source dtype
        for i in kernel_mode:
            photo = inputs[i][0]
            if photo.ndim != 3 or tuple(photo.shape[:2]) != (h, w):
                raise ValueError(f"blur.mode = kernel takes one {h} x {w} x 3 image per sample "
                                 f"on the device; got shape {photo.shape}")
            source = photo.dtype or np.dtype(self.np_real)
            config = self._of_plan(plans[i])[Pass.ACCUMULATE]
            k = self._pass_kernels(config, source)
            slot = samples[i].slot
            if not at_once:
                with self._timed(sync=False):
                    self._into_slots((src, ind), slot, n, lambda into, k=k, photo=photo:
                                     self._launch(k, "linearize", n, photo.data, *into))
            groups.setdefault((config, source.str), (k, []))[1].append(samples[i])
        whole = Region.whole(h, w)
        for k, drawn in groups.values():
            with self._timed():
                self._blur_kernels(k, drawn, src, ind, whole, whole, linear, sat_mask)
        return sat_mask

    def _linearize_batch(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                         inputs: Sequence[tuple[OnDevice, OnDevice | None]], linear: Slots,
                         sat_mask: Slots) -> Slots | None:
        """Blur mode none for a whole batch at once, where it can; else None.

        It can where :meth:`_linearized_at_once` can, and every mask, if any is given, lies
        back to back in one device buffer too: then its masks follow in one conversion
        (8/16-bit codes) or none at all (values of the compute type: their own buffer is
        returned), as :meth:`_accumulate_put` does it sample by sample. Returns the masks'
        slots.
        """
        if any((p.variant(S.BLUR) or "none") != "none" for p in plans):
            return None
        given = [m for _, m in inputs if m is not None]
        mask = self.consecutive(given) if given else None
        if given and (len(given) != len(inputs) or mask is None):
            return None
        if not self._linearized_at_once(plans, samples, [f for f, _ in inputs],
                                        (linear, sat_mask), indicator=False):
            return None
        n = linear.stride
        if mask is not None and self._stored_dtype(mask) == np.dtype(self.np_real):
            return Slots(mask.data, len(samples), n)
        self._mask_into(mask, len(samples) * n, sat_mask.buffer)
        return sat_mask

    def _averaged_at_once(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                          stacks: Sequence[OnDevice], linear: Slots, sat_mask: Slots) -> bool:
        """Blur mode average of every sample in one launch, where it can; whether it ran.

        It can where :meth:`_at_once` can and the frames sum exactly (``blur_average_exact``:
        8-bit codes, :meth:`_exact_units`, :meth:`_quads`).
        """
        if any(p.variant(S.BLUR) != "average" for p in plans):
            return False
        batch = self._at_once(plans, samples, stacks, (linear, sat_mask), frames=True)
        if batch is None:
            return False
        whole, config, n = batch
        count = whole.shape[1]
        units = self._exact_units(config, whole.dtype) if count <= EXACT_FRAMES_MAX else None
        quads = (self._quads((whole.data, linear.buffer, sat_mask.buffer), n)
                 if units is not None else None)
        if quads is None:
            return False
        k = self._pass_kernels(config, whole.dtype)
        with self._timed(sync=False):
            self._launch(k, "blur_average_exact", (len(samples), n // 4), quads[0],
                         Arg("uint", count), *_index(n // 4, count * n // 4), units,
                         *quads[1:], *_index(n // 4))
        return True

    def _linearized_at_once(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                            photos: Sequence[OnDevice], into: tuple[Slots, Slots], *,
                            indicator: bool = True) -> bool:
        """Every sample's photo linearized in one launch, where it can; whether it ran.

        Into its slots of ``into`` (linear values, clip indicators), where :meth:`_at_once`
        can; without ``indicator`` (blur mode none) the indicators' slots are left as they are.
        """
        batch = self._at_once(plans, samples, photos, into, frames=False)
        if batch is None:
            return False
        whole, config, n = batch
        source = whole.dtype or np.dtype(self.np_real)
        with self._timed(sync=False):
            if indicator:
                self._launch(self._pass_kernels(config, source), "linearize",
                             len(samples) * n, whole.data, into[0].buffer, into[1].buffer)
            else:
                self._linearize_unblurred(config, source, whole.data, len(samples) * n,
                                          into[0].buffer)
        return True

    def _at_once(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                 inputs: Sequence[OnDevice], slots: Sequence[Slots], *, frames: bool
                 ) -> tuple[OnDevice, PassConfig, int] | None:
        """(inputs as one, accumulate configuration, values a slot) for a one-launch batch.

        None where one accumulate launch cannot take the whole batch. It can when the inputs
        (frame stacks with ``frames``, else images) lie back to back in one device buffer
        (:meth:`consecutive`), fewer than 2^31 values (the kernels' indices), in slot order;
        each of ``slots`` holds exactly one image a slot; and the samples share one
        accumulate configuration.
        """
        whole = self.consecutive(inputs)
        configs = {self._of_plan(p)[Pass.ACCUMULATE] for p in plans}
        if (whole is None or whole.ndim != (5 if frames else 4) or len(configs) != 1
                or int(np.prod(whole.shape)) >= 2**31
                or [d.slot for d in samples] != list(range(len(samples)))):
            return None
        n = int(np.prod(whole.shape[2 if frames else 1:]))
        if any(s.stride != n or s.count < len(samples) for s in slots):
            return None
        return whole, configs.pop(), n

    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear, mask,
               origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[OnDevice, OnDevice]:
        """Saturation to noisy RAW on the device (see NumpyBackend.to_raw): a batch of one."""
        h, w = linear.shape[:2]
        n = h * w * 3
        saturated = self.slots(1, n)
        raw = self.slots(1, h * w if plan.raw_round_trip else 1)
        self.to_raw_batch(plan, camera, [Drawn(params, sample_index, 0)],
                          Slots(self._upload(linear), 1, n), Slots(self._upload(mask), 1, n),
                          saturated, raw, origin, (h, w), seed=seed)
        rgb = OnDevice(saturated.buffer, (h, w, 3), self._fetch)
        if not plan.raw_round_trip:
            return self._out(saturated.buffer, (h, w, 3), Pass.TO_RAW, origin), rgb
        return self._out(raw.buffer, (h, w), Pass.TO_RAW, origin), rgb

    def to_raw_batch(self, plan: Plan, camera: Camera, samples: Sequence[Drawn], linear: Slots,
                     mask: Slots, saturated: Slots, raw: Slots, origin: tuple[int, int],
                     size: tuple[int, int], *, seed: int) -> None:
        """The to_raw pass of samples of one plan in one launch, each in its slot.

        Args:
            plan: the samples' plan.
            camera: their camera.
            samples: each sample's draws, index and slot.
            linear: the accumulate pass's ``h x w x 3`` linear images, a slot per sample.
            mask: its saturation masks, the same way.
            saturated: takes each sample's ``h x w x 3`` saturated image.
            raw: takes each sample's ``h x w`` mosaic (the RAW round trip; else slots of one
                value, never written).
            origin: (row, column) of the buffers' first pixel in the whole image.
            size: (h, w).
            seed: the data set's seed.
        """
        k = self._pass_kernels(self._of_plan(plan)[Pass.TO_RAW])
        h, w = size
        _check_slots(samples, (("linear", linear, 3 * h * w), ("mask", mask, 3 * h * w),
                               ("saturated", saturated, 3 * h * w),
                               ("raw", raw, h * w if plan.raw_round_trip else 1)))
        tables = self._tables(samples)
        matrix = self._constant(camera.linear_to_camera)
        with self._timed():
            self._launch(k, "to_raw", (len(samples), h, w), *to_raw_args(
                plan, tables, origin, h, w, (self._slots(linear), self._slots(mask)), matrix,
                (self._slots(saturated), self._slots(raw)), seed=seed))

    def finish(self, plan: Plan, params: dict, camera: Camera, image, saturated, view: Region,
               out: Region, *, seed: int, sample_index: int) -> OnDevice:
        """Demosaic and finish on the device, over ``out`` (see NumpyBackend.finish).

        A batch of one.
        """
        raw = image if plan.raw_round_trip else np.zeros(1)
        n = out.h * out.w * 3
        result = self.slots(1, n)
        self.finish_batch(plan, camera, [Drawn(params, sample_index, 0)],
                          Slots(self._upload(raw), 1, int(np.prod(np.shape(raw)))),
                          Slots(self._upload(saturated), 1, view.h * view.w * 3), view, out,
                          result, seed=seed)
        return self._out(result.buffer, (out.h, out.w, 3), Pass.FINISH, out.origin)

    def finish_batch(self, plan: Plan, camera: Camera, samples: Sequence[Drawn], raw: Slots,
                     saturated: Slots, view: Region, out: Region, result: Slots, *,
                     seed: int) -> None:
        """The finish pass of samples of one plan in one launch, each in its slot.

        ``raw`` (``view.h x view.w`` a slot, or placeholders without the RAW round trip) and
        ``saturated`` (``view.h x view.w x 3``) are :meth:`to_raw_batch`'s outputs over
        ``view``; ``result`` takes each sample's ``out.h x out.w x 3`` image.
        """
        derived = self._of_plan(plan, camera)
        k = self._pass_kernels(derived[Pass.FINISH])
        polynomial, table = derived["curves"]
        pixels = view.h * view.w
        _check_slots(samples, (("raw", raw, pixels if plan.raw_round_trip else 1),
                               ("saturated", saturated, 3 * pixels),
                               ("result", result, 3 * out.h * out.w)))
        tables = self._tables(samples)
        matrix = self._constant(camera.camera_to_linear)
        pairs = (out.x0 % 2 + out.w + 1) // 2  # the kernel's column pairs (finish.cl)
        with self._timed():
            self._launch(k, "finish", (len(samples), out.h, pairs), *finish_args(
                plan, tables, view, out, (self._slots(raw), self._slots(saturated)), matrix,
                (self._constant(polynomial), polynomial.size),
                (self._constant(table), table.size), self._slots(result), seed=seed))
