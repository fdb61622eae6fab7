"""The device-resident path: a kernel backend's whole-image batches, never on the host.

:class:`ResidentPath` puts a batch's inputs on the device once (none at all for arrays the
backend reaches), checks them by device reductions, runs every pass once per plan for the
whole batch into buffers of one slot per sample (:meth:`ResidentPath.run`), and exports or
hands over the results.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from gpu_blur.backends import Drawn, OnDevice, ResidentBackend, Slots, pinned_owner
from gpu_blur.cameras import Camera
from gpu_blur.params import batch_uniforms
from gpu_blur.planning import StageName, raw_round_trip
from gpu_blur.scene import Scene
from gpu_blur.synthesis.batches import BatchIO
from gpu_blur.synthesis.draws import Draws
from gpu_blur.synthesis.inputs import (
    Inputs,
    bad_values,
    checked,
    codes_only,
    even,
    kept_size,
)
from gpu_blur.synthesis.results import inner
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

if TYPE_CHECKING:
    from gpu_blur.png_device import DevicePngs

__all__ = ["ResidentPath", "STREAMED_BYTES", "STREAMED_SAMPLES"]

#: Samples per part of a batch in pinned memory (:meth:`ResidentPath.batch`): the
#: device downloads one part's results while it uploads the next part's inputs.
STREAMED_SAMPLES = 4

#: Input bytes a sample needs for its batch to go in parts: below them the copies are short
#: and the parts' extra launches cost more (docs/performance.md#batches-in-parts).
STREAMED_BYTES = 1 << 22


def _flags(row: np.ndarray) -> tuple[bool, bool, bool]:
    """(bad, clips, above 0) from an input's device counts (``INSPECT_COLUMNS``' order)."""
    return bool(row[:4].any()), bool(row[4]), bool(row[5])


@dataclasses.dataclass
class _Resident:
    """A batch's results on the device (:meth:`ResidentPath.run`).

    Attributes:
        blurred: the finish pass's outputs, a slot of ``out.h x out.w x 3`` per sample.
        mask: the saturation masks, a slot of ``h x w x 3`` (uncropped) per sample.
        raw: the noisy mosaics, a slot of ``h x w`` per sample (RAW round trip only).
        sharp: the rendered sharp references, a slot of ``out.h x out.w x 3`` per sample.
        params, plans: each sample's draws and plan.
        out: the region of the image the outputs hold (the image less ``output.crop``).
        size: (h, w), the inputs' size (the masks' and the mosaics').
    """

    blurred: Slots
    mask: Slots
    raw: Slots
    sharp: Slots
    params: list
    plans: list
    out: Region
    size: tuple


class ResidentPath:
    """A Synthesizer's batches on a kernel backend's device, whole images, no spot checks.

    Holds one batch's device buffers between calls (:meth:`run` with ``reuse``).

    Args:
        runner: the kernel backend (OpenCL or Warp), as :class:`ResidentBackend` declares it.
        scene: the scene.
        camera: its camera.
        seed: dataset seed.
        draws: the samples' plans and draws.
        io: the Synthesizer's batch input and output.
        with_mask: the saturation masks are returned too.
        with_raw: the noisy mosaics are kept too.
    """

    def __init__(self, runner: ResidentBackend, scene: Scene, camera: Camera, seed: int,
                 draws: Draws, io: BatchIO, with_mask: bool, with_raw: bool):
        self.runner, self.scene, self.camera, self.seed = runner, scene, camera, seed
        self.draws, self.io, self.with_mask, self.with_raw = draws, io, with_mask, with_raw
        self._buffers = None  # (shape key, buffers) of the last resident batch

    def sample(self, item: Inputs, sample_index: int, check: Callable[[], None], *,
               on_device: bool = False, codes: bool = False,
               sequence_index: int | None = None) -> tuple:
        """One prepared sample, a batch of one; ``check`` ends its input checks.

        Returns (blurred, sharp, mask, raw, params, plan, tiles, spot checks): blurred on the
        device with ``on_device``, else on the host (its codes with ``codes``, unless the JPEG
        stage is still to come), as sharp; mask and raw fetched on first use.
        """
        done = self.run([item], [sample_index], sequences=[sequence_index])
        check()
        runner, (h, w) = self.runner, done.size
        blurred = runner.slot_image(done.blurred, 0, (done.out.h, done.out.w, 3))
        # codes made on the device, unless the JPEG stage (on the host) is still to come
        device_codes = codes and not done.plans[0].kept(StageName.JPEG)
        out = (runner.device_array(blurred) if on_device
               else self._host(blurred, inner(blurred.shape, 0), device_codes))
        sharp = self._host(runner.slot_image(done.sharp, 0, blurred.shape),
                           inner(blurred.shape, 0), codes)
        mask = runner.slot_image(done.mask, 0, (h, w, 3))  # fetched on first use
        raw = runner.slot_image(done.raw, 0, (h, w)) if self.with_raw else None
        return out, sharp, mask, raw, done.params[0], done.plans[0], 1, 0

    def prepared(self, items: list[Inputs], *, clip_test_later: bool = False
                 ) -> tuple[list[Inputs], Callable[[], None]]:
        """Inputs put on the device and checked there, with the clip test.

        Returns the inputs and the function that ends their checks, which the caller calls
        before any result leaves. The checks count on the device and the counts are read
        there, after the passes the caller queues in between (so the device never waits for
        the host's look at them), unless auto saturation's clip test needs
        them to plan the samples: then they are read here and the function does nothing.
        ``clip_test_later``: the caller plans the samples as if they clipped, and the function
        sets each input's ``saturated`` from its counts.
        """
        put = [self.put(item) for item in items]
        clip_test = self.scene.saturation.mode == "auto"
        # (sample, which, image, measured): each input once (a default sharp is a frame), input
        # by input, so the first bad one named is the same whoever looks; float values are
        # checked, 8/16-bit codes only looked at for the clip test. Inputs the batch measured
        # where it lies (Inputs.ranges) are read from there; the others are counted on the
        # device, a device batch's samples of one input (evenly spaced in its buffer) in one
        # launch (ResidentBackend.inspect_queued)
        images = []
        for key in ("frames", "mask", "sharp"):
            for i, (item, p) in enumerate(zip(items, put, strict=True)):
                image = getattr(p, key)
                measured = item.ranges is not None and key in item.ranges[0].keys
                if getattr(item, key) is not None and (
                        measured or image.dtype is None or (clip_test and key != "sharp")):
                    images.append((i, key, image, item.ranges if measured else None))
        with timer("checks"):
            counts = self.runner.inspect_queued([image for _, _, image, ranges in images
                                                 if ranges is None])

        def check() -> None:
            with timer("checks"):
                rows = iter(counts())
                # (bad, clips, above 0) of each input, from its counts or its ranges
                flags = [ranges[0].flags(key, ranges[1]) if ranges is not None
                         else _flags(next(rows)) for _, key, _, ranges in images]
            for (i, key, image, _), (bad, clips, above_0) in zip(images, flags, strict=True):
                if bad:  # the host says exactly what is wrong, and where
                    bad_values(image, put[i], key)
                if clip_test and key == "mask" and above_0:
                    put[i].saturated = True
                if clip_test and key == "frames" and put[i].mask is None and clips:
                    put[i].saturated = True

        if clip_test and not clip_test_later:
            check()
            return put, checked
        return put, check

    def put(self, item: Inputs) -> Inputs:
        """A sample's inputs on the kernel backend's device (frames: one stack in mode average)."""
        runner = self.runner
        frames = item.frames
        if isinstance(frames, (list, tuple)):  # synthesize's host frames, a stack when averaged
            frames = frames[0] if self.scene.blur.mode != "average" else list(frames)
        first = frames[0] if isinstance(frames, list) else frames
        h, w = kept_size(self.scene, first.shape)
        if (h, w) != tuple(first.shape[-3:-1]):
            frames = ([f[:h, :w] for f in frames] if isinstance(frames, list)
                      else np.ascontiguousarray(frames[..., :h, :w, :]))
        stack = runner.put(frames)
        mask = None if item.mask is None else runner.put(even(item.mask, stack))
        if item.sharp is not None:
            sharp = runner.put(even(item.sharp, stack))
        elif stack.ndim == 4:
            sharp = runner.frame(stack, stack.shape[0] // 2)
        else:
            sharp = stack
        return Inputs(stack, mask, sharp, item.names, item.label)

    def batch(self, items: list[Inputs], indices, batch, lib: str, given, bits: int = 0,
              sequences=None, pngs: DevicePngs | None = None):
        """A batch put on the device: its passes batched, its outputs exported once each.

        ``bits`` 8 or 16: blurred and sharp leave as their codes, made on the device.
        ``sequences``: each sample's sequence index (per-sequence draws), or None.
        ``pngs``: exported codes are also deflated there (:meth:`DevicePngs.queue`).

        A batch of 8/16-bit codes in this backend's pinned memory (``Synthesizer.pinned``), of
        at least :data:`STREAMED_BYTES` a sample, goes in parts of :data:`STREAMED_SAMPLES`,
        each exported as soon as its passes are queued: the device downloads one part's results
        while it uploads the next part's inputs (the two copy directions overlap). Codes have
        no values to refuse, so no part's results leave before a later part fails its checks;
        float inputs go in one part, their checks ended (:meth:`prepared`) once the passes
        are queued and before any result leaves.

        Results handed over on the device return before the device has made them: the host
        waits only for the checks, and the next batch's host work overlaps this batch's passes
        (``Synthesizer.__call__`` makes the caller's stream wait for them). Other results are
        waited for.

        Auto saturation's clip test is read once the passes are queued, too: every sample runs
        as if it clipped, and one that does not gets skipping's plan and draws afterwards
        (:meth:`_unclipped`), its output the same bits (on its zero mask the saturate and
        restore stages are identities). So the device never idles while the host draws and
        launches, at the cost of those two stages on samples that do not clip.
        """
        runner, count = self.runner, len(items)
        streamed = (not self.with_raw and isinstance(batch, np.ndarray)
                    and pinned_owner(batch) is runner and all(map(codes_only, items))
                    and batch.nbytes >= STREAMED_BYTES * count)
        step = STREAMED_SAMPLES if streamed else count
        # a batch on the device gets the result buffers themselves (new ones each batch), or
        # their codes (new arrays: the buffers are kept)
        handed = given is None and step == count and self.io.reaches(batch, lib)
        clip_test = self.scene.saturation.mode == "auto"
        out, params, plans = None, [], []
        with self._queued():
            for start in range(0, count, step):
                part, check = self.prepared(items[start:start + step], clip_test_later=True)
                done = self.run(part, indices[start:start + step], reuse=True,
                                fresh_results=handed and not bits, as_clipped=clip_test,
                                sequences=None if sequences is None
                                else sequences[start:start + step])
                check()
                if clip_test:
                    self._unclipped(done, part)
                params += done.params
                plans += done.plans
                if handed:
                    out = self._handed_over(done, batch, lib, bits)
                    continue
                if out is None:
                    out = self.io.outputs(count, done.out, batch, lib,
                                          self.io.result_dtypes(bits), given)
                self._export(done, out if step == count else
                             [o[start:start + len(part)] for o in out], bits, pngs)
            if not handed:
                with timer("kernels"):
                    runner.wait()
        raws = ([runner.slot_image(done.raw, b, done.size) for b in range(count)]
                if self.with_raw else [])
        return out, params, plans, raws

    def _unclipped(self, done: _Resident, items: list[Inputs]) -> None:
        """The plans and draws of ``done``'s samples run as if they clipped that did not.

        Their clip test, read after their passes were queued, says auto saturation skips
        them: skipping's plan, and their draws without alpha (its own draw slot: nothing
        else moves), as :meth:`Draws.drawn` gives them.
        """
        for b, item in enumerate(items):
            if not item.saturated:
                done.plans[b] = self.draws.plan(False, *done.size, None)
                done.params[b] = {k: v for k, v in done.params[b].items() if k != "alpha"}

    def _export(self, done: _Resident, out: list, bits: int = 0,
                pngs: DevicePngs | None = None) -> None:
        """A resident batch's results into ``out`` (blurred, sharp[, mask]), one per sample.

        ``bits`` 8 or 16: blurred and sharp as their codes, made on the device; ``pngs``:
        those codes deflated there too.
        """
        shape = (done.out.h, done.out.w, 3)
        for name, into, slots in (("blurred", out[0], done.blurred),
                                  ("sharp", out[1], done.sharp)):
            coded = self._export_slots(into, slots, shape, bits)
            if pngs is not None:
                pngs.queue(name, coded, slots.count)
        if self.with_mask:
            self._export_masks(done, out[2])

    def _export_masks(self, done: _Resident, into) -> None:
        """The batch's saturation masks, cropped as the outputs are, into ``into`` (B x ...)."""
        masked = inner((*done.size, 3), self.scene.output.crop)
        for b in range(len(into)):
            self.runner.export(self.runner.slot_image(done.mask, b, (*done.size, 3)), masked,
                               into[b])

    def _handed_over(self, done: _Resident, batch, lib: str, bits: int = 0) -> list:
        """A device batch's outputs: its blurred and sharp slots as they are, and its masks.

        Nothing is copied but the masks (cropped into a new array). ``bits`` 8 or 16: the
        slots' codes instead, made on the device.
        """
        runner, shape = self.runner, (done.out.h, done.out.w, 3)
        out = [runner.device_array(self._coded(runner.stacked(slots, shape), bits))
               for slots in (done.blurred, done.sharp)]
        if self.with_mask:
            out += self.io.outputs(done.blurred.count, done.out, batch, lib, [np.float32])
            self._export_masks(done, out[2])
        return out

    def _export_slots(self, into, slots: Slots, shape, bits: int = 0) -> OnDevice:
        """Every sample's slot of a batch buffer into ``into`` (B x ``shape``), in one copy.

        ``bits`` 8 or 16: their codes, made on the device. Returns what was copied (valid
        until the next export asks for the kept codes buffer).
        """
        coded = self._coded(self.runner.stacked(slots, shape), bits, kept=True)
        # a B x h x w x 3 stack's "region": every sample, every row
        self.runner.export(coded, Region.whole(slots.count, shape[0]), into)
        return coded

    def _coded(self, values: OnDevice, bits: int, kept: bool = False) -> OnDevice:
        """Device values as their ``bits``-bit codes on the device (0: as they are).

        ``kept``: in the runner's kept buffer (codes fetched at once), else a new one.
        """
        if not bits:
            return values
        into = (self.runner.codes_buffer(int(np.prod(values.shape)), bits) if kept else None)
        return self.runner.to_codes(values, bits, into)

    @contextlib.contextmanager
    def _queued(self):
        """Resident batches queue every launch without waiting between passes."""
        self.runner.sync_passes = False
        try:
            yield
        finally:
            self.runner.sync_passes = True

    def _host(self, values, region: Region, codes: bool = False) -> np.ndarray:
        """``region`` of a device image on the host, float32.

        With ``codes``: the output's integer codes, made on the device
        (:meth:`~gpu_blur.backends.ResidentBackend.to_codes`).
        """
        if codes:
            values = self._coded(values, self.scene.output.bits, kept=True)
        out = np.empty((region.h, region.w, 3), dtype=values.dtype or np.float32)
        self.runner.export(values, region, out)
        return out

    def run(self, items: list[Inputs], indices: Sequence[int], *, reuse: bool = False,
            fresh_results: bool = False, as_clipped: bool = False,
            sequences: Sequence[int | None] | None = None) -> _Resident:
        """Samples put on the device, each pass launched once per plan for the whole batch.

        The samples' draws come first (their per-image uniforms at once), then the accumulate
        pass writes each sample's slot of the batch's buffers; then samples of one plan (auto
        saturation gives at most two, unless ``as_clipped``) run to_raw and finish in one
        launch each, finish writing the cropped output. Every buffer keeps one slot per sample.

        ``reuse``: take the buffers of the last batch of this size (the caller copies every
        result out before the next batch), sparing device allocations; this path holds one
        batch's buffers between calls. ``fresh_results``: new blurred and sharp slots
        all the same (the caller hands them over as the outputs). ``as_clipped``: plan every
        sample as one whose input reaches the clip level (its clip test is still to be read).
        ``sequences``: each sample's sequence index, which keys its per-image draws under
        ``blur.draws = "per-sequence"``; the noise's pixels stay keyed by ``indices`` (each
        :class:`~gpu_blur.backends.Drawn`'s sample index), so windows of one sequence share
        their camera settings and differ in their noise.
        """
        runner, camera, crop = self.runner, self.camera, self.scene.output.crop
        h, w = items[0].frames.shape[-3:-1]
        count, whole = len(items), Region.whole(h, w)
        out = inner((h, w), crop)
        buffers = self._batch_buffers(count, h, w, out, reuse, fresh_results)
        linear, sat_mask, saturated, raw, result, sharp_slots = buffers
        sequences = [None] * count if sequences is None else list(sequences)
        uniforms = batch_uniforms(self.scene, seed=self.seed, sample_indices=indices,
                                  sequence_indices=sequences)
        groups: dict = {}  # id(plan) -> (plan, its samples as Drawn, in batch order)
        params, plans, samples = [], [], []
        for b, (item, index) in enumerate(zip(items, indices, strict=True)):
            sample_plan, drawn = self.draws.drawn(item, int(index), h, w, None, uniforms[b],
                                                  saturated=as_clipped or item.saturated,
                                                  sequence_index=sequences[b])
            params.append(drawn)
            plans.append(sample_plan)
            samples.append(Drawn(drawn, int(index), b))
            # plans are cached per clip test and size (Draws.drawn): one object per group
            groups.setdefault(id(sample_plan), (sample_plan, []))[1].append(samples[-1])
        sat_mask = runner.accumulate_batch(plans, samples,
                                           [(item.frames, item.mask) for item in items],
                                           linear, sat_mask)
        for sample_plan, drawn in groups.values():
            runner.to_raw_batch(sample_plan, camera, drawn, linear, sat_mask, saturated, raw,
                                (0, 0), (h, w), seed=self.seed)
            runner.finish_batch(sample_plan, camera, drawn, raw, saturated, whole, out, result,
                                seed=self.seed)
        runner.render_sharp_batch(plans, camera, [item.sharp for item in items], out,
                                  sharp_slots)
        return _Resident(result, sat_mask, raw, sharp_slots, params, plans, out, (h, w))

    def _batch_buffers(self, count: int, h: int, w: int, out: Region, reuse: bool,
                       fresh_results: bool = False) -> tuple:
        """A resident batch's device buffers: (linear, mask, saturated, raw, blurred, sharp).

        With ``reuse`` the last batch's, where it had this count and size; with
        ``fresh_results`` new blurred and sharp slots whatever ``reuse`` says.
        """
        key = (count, h, w, out)
        if fresh_results:
            held = self._batch_buffers(count, h, w, out, reuse)
            return (*held[:4], *(self.runner.slots(count, out.h * out.w * 3) for _ in range(2)))
        if reuse and self._buffers is not None and self._buffers[0] == key:
            return self._buffers[1]
        if reuse:
            self._buffers = None  # one batch's buffers at a time
        slots, n = self.runner.slots, h * w * 3
        buffers = (slots(count, n), slots(count, n), slots(count, n),
                   slots(count, h * w if raw_round_trip(self.scene) else 1),
                   slots(count, out.h * out.w * 3), slots(count, out.h * out.w * 3))
        if reuse:
            self._buffers = (key, buffers)
        return buffers
