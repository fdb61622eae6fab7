"""The host path: samples run from host memory in tiles, within a memory budget, with spot checks.

:class:`HostPath` runs each sample's passes through :mod:`gpu_blur.scheduler` (tiles, halos,
streamed frames, spot checks; also interpolated averages and the numpy backend), and renders
the sharp reference: :func:`render_sharp` on the host in float64 (numpy), the device code in
bands otherwise.
"""

from __future__ import annotations

import numpy as np

from gpu_blur.backends import Backend, OnDevice, is_resident
from gpu_blur.backends.flows import scene_factors
from gpu_blur.backends.numpy import retone
from gpu_blur.cameras import Camera
from gpu_blur.image_arrays import unit_values
from gpu_blur.planning import Plan, StageName
from gpu_blur.reference import transfer
from gpu_blur.reference.output import crop_border, quantize
from gpu_blur.scene import Scene
from gpu_blur.scheduler import Schedule, run
from gpu_blur.synthesis.batches import BatchIO
from gpu_blur.synthesis.draws import Draws
from gpu_blur.synthesis.inputs import Inputs
from gpu_blur.synthesis.results import inner
from gpu_blur.tiling import Region, tiles

__all__ = ["HostPath", "render_sharp"]


class HostPath:
    """A Synthesizer's samples run from host memory (:mod:`gpu_blur.scheduler`).

    Args:
        runner: the backend (a :class:`~gpu_blur.backends.ResidentBackend` where
            :func:`~gpu_blur.backends.is_resident`: its device renders the sharp image).
        scene: the scene.
        camera: its camera.
        seed: dataset seed.
        schedule: tiles, memory budget and spot checks.
        draws: the samples' plans and draws.
        io: the Synthesizer's batch input and output.
        with_mask: the saturation masks are returned too.
        with_raw: the noisy mosaics are kept too.
    """

    def __init__(self, runner: Backend, scene: Scene, camera: Camera, seed: int,
                 schedule: Schedule, draws: Draws, io: BatchIO, with_mask: bool, with_raw: bool):
        self.runner, self.scene, self.camera, self.seed = runner, scene, camera, seed
        self.schedule, self.draws, self.io = schedule, draws, io
        self.with_mask, self.with_raw = with_mask, with_raw

    def sample(self, item: Inputs, sample_index: int, *, on_device: bool = False,
               sequence_index: int | None = None) -> tuple:
        """One checked sample.

        Returns (blurred, sharp, mask, raw, params, plan, tiles, spot checks): blurred left on
        the device with ``on_device``, else cropped on the host; sharp rendered and cropped;
        mask and raw cropped here, or fetched and cropped on first use where on a device.
        """
        crop = self.scene.output.crop
        blurred, mask, sharp, params, sample_plan, tiled = self.passes(
            item, sample_index, on_device=on_device, sequence_index=sequence_index)
        out = (self.runner.device_array(blurred) if on_device
               else crop_border(blurred, crop))
        if isinstance(mask, np.ndarray):  # a device mask is fetched (and cropped) on use
            mask = crop_border(mask, crop).astype(np.float32, copy=False)
        raw = tiled.raw  # the same way
        if isinstance(raw, np.ndarray):
            raw = crop_border(raw, crop).astype(np.float32, copy=False)
        return out, sharp, mask, raw, params, sample_plan, tiled.tiles, tiled.checked

    def batch(self, items: list[Inputs], indices, batch, lib: str, given, sequences=None):
        """A batch run sample by sample from host memory (tiles, budgets, spot checks).

        ``sequences``: each sample's sequence index (per-sequence draws), or None.
        """
        out, params, plans, raws = None, [], [], []
        crop = self.scene.output.crop
        for b, item in enumerate(items):
            blurred, sat_mask, sharp_out, drawn, sample_plan, tiled = self.passes(
                item, int(indices[b]),
                sequence_index=None if sequences is None else sequences[b])
            raws.append(tiled.raw)
            params.append(drawn)
            plans.append(sample_plan)
            # (values, the region of them that goes out): a sharp image is already cropped
            results = [(blurred, inner(blurred.shape, crop)),
                       (sharp_out, inner(sharp_out.shape, 0))]
            if self.with_mask:
                results.append((sat_mask, inner(sat_mask.shape, crop)))
            if out is None:
                out = self.io.outputs(len(items), results[0][1], batch, lib,
                                      [np.float32] * len(results), given)
            self._export(out, b, results)
        return out, params, plans, raws

    def passes(self, item: Inputs, sample_index: int, *, on_device: bool = False,
               sequence_index: int | None = None):
        """A prepared sample's passes from host memory (:mod:`gpu_blur.scheduler`).

        ``on_device``: leave the blurred image on the device (whole image, ``output.crop``
        0). ``sequence_index`` keys the draws under per-sequence draws; the noise stays keyed
        by ``sample_index``. Returns (blurred, mask, sharp, params, plan, tiled).
        """
        scene = self.scene
        frames = item.frames
        h, w = frames[0].shape[:2]
        # interpolation auto: each gap's factor, measured on the host frames
        measured = scene_factors(scene, frames)
        sample_plan, params = self.draws.drawn(item, sample_index, h, w, measured,
                                               sequence_index=sequence_index)
        # how the passes run (tiles, halos, streamed frames, spot checks): gpu_blur.scheduler
        crop = scene.output.crop
        tiled = run(self.runner, sample_plan, params, self.camera, frames, item.mask,
                    self.schedule, seed=self.seed, sample_index=sample_index,
                    on_device=on_device, keep_raw=self.with_raw)
        if is_resident(self.runner):
            sharp = self._rendered_in_bands(sample_plan, crop_border(item.sharp, crop))
        else:
            sharp = render_sharp(sample_plan, self.camera, crop_border(item.sharp, crop))
        return tiled.blurred, tiled.mask, sharp, params, sample_plan, tiled

    def _export(self, out: list, b: int, results: list) -> None:
        """Sample ``b``'s results, (values, region) each, into the batch's outputs."""
        for slot, (values, region) in zip(out, results, strict=True):
            if isinstance(values, OnDevice):
                self.runner.export(values, region, slot[b])
            else:
                np.copyto(slot[b], region.of(np.asarray(values)), casting="same_kind")

    def _rendered_in_bands(self, sample_plan: Plan, sharp: np.ndarray) -> np.ndarray:
        """A host sharp image rendered by the device code (as resident runs render it).

        In bands of the schedule's tile rows, so a tiled run holds no more on the device than
        a tile; the rendering is pointwise, so the bands do not change it.
        """
        h, w = sharp.shape[:2]
        rows = self.schedule.tile[0] if self.schedule.tile else h
        out = np.empty((h, w, 3), np.float32)
        for band in tiles(h, w, (rows, w)):
            image = self.runner.put(np.ascontiguousarray(band.of(sharp)))
            whole = Region.whole(band.h, band.w)
            rendered = self.runner.render_sharp(sample_plan, self.camera, image, whole)
            self.runner.export(rendered, whole, band.of(out))
        return out


def render_sharp(sample_plan: Plan, camera: Camera, sharp: np.ndarray) -> np.ndarray:
    """The sharp reference as the output holds it: float32, quantized when the plan quantizes.

    The numpy backend's, in float64; kernel backends render it with the finish pass's device
    functions (``KernelBackend.render_sharp``), bit for bit the same whatever the tiles.

    In the output's encoding: sRGB, linear, or re-toned.

    Every step is pointwise, so 8- and 16-bit codes are rendered through a table: the float64
    curve (and quantization) evaluated once per code (256 or 65,536 values instead of one per
    pixel) and gathered, the same values bit for bit and an order of magnitude faster
    (docs/performance.md#sharp-reference-by-table). 8-bit sRGB in and out gives the codes
    themselves, ``c / 255``.

    Args:
        sample_plan: the sample's plan.
        camera: its camera (``output.crf = "camera"`` re-tones with its fitted response).
        sharp: sRGB image as stored (:func:`gpu_blur.image_arrays.check_image`), H x W x 3.
    """
    coded = sharp.dtype in (np.uint8, np.uint16)
    values = unit_values(np.arange(np.iinfo(sharp.dtype).max + 1, dtype=sharp.dtype)
                         if coded else sharp)
    rendered = _render_values(sample_plan, camera, values)
    if sample_plan.kept(StageName.QUANTIZE):
        rendered = quantize(rendered, sample_plan[StageName.QUANTIZE].options["bits"])
    rendered = rendered.astype(np.float32)
    return rendered[sharp] if coded else rendered


def _render_values(sample_plan: Plan, camera: Camera, values: np.ndarray) -> np.ndarray:
    """:func:`render_sharp`'s curve on float64 sRGB values in [0, 1], any shape."""
    if not sample_plan.kept(StageName.TONE):
        return np.clip(transfer.srgb_to_linear(values), 0.0, 1.0)
    return retone(sample_plan, camera, values)
