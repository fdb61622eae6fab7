"""The public API: ``synthesize`` (a batch of one) and :class:`Synthesizer` (batches).

A Synthesizer holds the pieces of :mod:`gpu_blur.synthesis`: each sample's plan and draws
(:class:`~gpu_blur.synthesis.draws.Draws`), batch input and output
(:class:`~gpu_blur.synthesis.batches.BatchIO`), and the path its samples run on, the device
(:class:`~gpu_blur.synthesis.resident.ResidentPath`) or the host
(:class:`~gpu_blur.synthesis.host.HostPath`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from gpu_blur import arrays
from gpu_blur.backends import Backend, get_backend, is_resident, to_host
from gpu_blur.backends.flows import interpolation_factor
from gpu_blur.cameras import scene_camera
from gpu_blur.outputs import jpeg_round_trip, raw_metadata
from gpu_blur.params import check_overrides
from gpu_blur.planning import StageName, plan, raw_round_trip
from gpu_blur.reference.output import code_dtype, crop_border, to_integers
from gpu_blur.scene import Scene, load_scene
from gpu_blur.scheduler import Schedule
from gpu_blur.synthesis.batches import BatchIO, jpeg_stage, refuse_out_on_inputs
from gpu_blur.synthesis.draws import Draws
from gpu_blur.synthesis.host import HostPath
from gpu_blur.synthesis.inputs import (
    Inputs,
    check_codes,
    checked,
    checked_on_host,
    gather,
    kept_size,
    sample_indices,
)
from gpu_blur.synthesis.resident import ResidentPath
from gpu_blur.synthesis.results import Batch, Synthesis, inner
from gpu_blur.timings import current, since, timer

if TYPE_CHECKING:
    from gpu_blur.png_device import DevicePngs

__all__ = ["Synthesizer", "synthesize"]


def _as_scene(scene) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene)


def synthesize(inputs, scene=None, *, seed: int = 0, sample_index: int = 0,
               backend: str = "numpy", overrides: Mapping | None = None,
               tile: tuple[int, int] | Schedule | None = None, on_device: bool = False,
               max_device_memory: int | str | None = None, verify: float = 0.0,
               with_raw: bool = False, codes: bool = False,
               sequence_index: int | None = None) -> Synthesis:
    """Synthesize one realistic blurred image (a :class:`Synthesizer` batch of one).

    Args:
        inputs: sharp sRGB input, H x W x 3 arrays in RGB order (OpenCV reads BGR: convert
            with ``cv2.cvtColor(x, cv2.COLOR_BGR2RGB)``; uint8, uint16 or float in [0, 1]) or
            image paths: a sequence of consecutive frames (blur mode ``average``; the middle
            one is the sharp reference), one photo (``kernel``, ``trajectory``), or for mode
            ``none`` a mapping ``{"blurred": ..., "mask": ... (optional), "sharp": ...}``.
        scene: a :class:`~gpu_blur.scene.Scene`, a path to a scene TOML, a built-in scene's
            name, or None (defaults).
        seed: dataset seed (0 <= seed < 2**64).
        sample_index: index of this sample (0 <= index < 2**32); with ``seed`` it fixes every
            random draw.
        backend: ``"numpy"`` (the float64 reference), ``"opencl"`` (a GPU, else Intel's CPU
            runtime, else PoCL), ``"opencl:<platform>:<device>"``, ``"warp"`` (CUDA if
            present, else the CPU), ``"warp:cpu"`` or ``"warp:cuda:<n>"`` (see ``gpu-blur
            devices``), or a backend object from :func:`gpu_blur.backends.get_backend`.
        overrides: drawn parameters to fix instead (e.g. ``{"alpha": 1.0, "pattern": "RGGB"}``),
            each checked before any pass, whether or not its stage runs.
        tile: run the image in tiles of at most (rows, columns) pixels, each with its halo;
            the result does not depend on it. Wins over ``max_device_memory``. A
            :class:`~gpu_blur.scheduler.Schedule` gives tile, budget and ``verify`` at once
            (for job descriptions that carry one value).
        on_device: leave ``.blurred`` on the backend's device as an ``h x w x 3`` array
            (Warp backends: a ``wp.array`` that ``torch.from_dlpack`` takes without a copy).
            Needs whole-image runs (no ``tile``, a budget the image fits), no ``verify`` and
            ``output.crop = 0``.
        max_device_memory: device memory the passes of one tile may hold, in bytes or as
            ``"512M"``, ``"2G"``: the image runs in the largest tiles that fit (the formula is
            in :mod:`gpu_blur.scheduler`); the result does not depend on it.
        verify: fraction of tiles (0 to 1) recomputed with the numpy reference and compared
            pass by pass under the tolerance table (:mod:`gpu_blur.scheduler`).
        with_raw: also keep the noisy Bayer mosaic (``Synthesis.raw``, ``raw_info``).
        codes: return ``blurred`` and ``sharp`` as the output's integer codes (uint8 for
            ``output.bits = 8``, uint16 for 16: ``to_integers`` of the float results, bit
            for bit), made on a kernel backend's device: a quarter (a half) of the bytes to
            fetch and no conversion on the host (``gpu-blur generate`` writes them as they are).
        sequence_index: the index of the frame sequence this sample is a window of (0 <=
            index < 2**32). Under ``blur.draws = "per-sequence"`` the camera settings
            (white-balance gains, noise levels, alpha, Bayer pattern, JPEG quality) are drawn
            from (seed, sequence_index), the same for every window of the sequence, while the
            noise's pixels stay drawn from (seed, sample_index); required there, not used
            otherwise.

    Returns:
        A :class:`Synthesis`. Images whose RAW round trip needs even sizes lose their last
        row and/or column (the Bayer 2 x 2 cell rule).

    Raises:
        gpu_blur.scheduler.SpotCheckError: a spot-checked tile disagreed with the reference
            (a ``ValueError``), naming the sample, the tile and the error.
        ValueError: bad input or settings, naming the file or value.
    """
    if isinstance(tile, Schedule):
        if max_device_memory is not None or verify:
            raise ValueError("give max_device_memory and verify in the Schedule passed as "
                             "tile, or as arguments, not both")
        schedule = tile
    else:
        schedule = Schedule(tile, max_device_memory, verify)
    synthesizer = Synthesizer(scene, backend=backend, seed=seed, overrides=overrides,
                              schedule=schedule, with_raw=with_raw)
    return synthesizer.sample(inputs, sample_index, on_device=on_device, codes=codes,
                              sequence_index=sequence_index)


class Synthesizer:
    """Synthesize batches with one scene on one backend; kernels and buffers are reused.

    ``synthesize`` is a batch of one through the same path. On a kernel backend (OpenCL,
    Warp) a whole-image batch never touches its pixels on the host: inputs go to the device
    once (none at all for CUDA arrays on a Warp device), the value checks and auto
    saturation's clip test are device reductions, the sharp reference is toned by the same
    device code as the blurred image, and the crop is a device copy. Tiles, memory budgets,
    spot checks and interpolated averages run from host memory (:mod:`gpu_blur.scheduler`).

    Args:
        scene: a :class:`~gpu_blur.scene.Scene`, a TOML path, a built-in scene's name, or
            None (defaults).
        backend: as :func:`synthesize` takes it.
        seed: dataset seed (0 <= seed < 2**64).
        overrides: drawn parameters to fix for every sample (each checked here, whether or
            not its stage runs).
        schedule: tiles, memory budget and spot checks (:class:`~gpu_blur.scheduler.Schedule`).
        channels_first: batches come and go as B x 3 x H x W (torch's layout).
        with_mask: also return the blurred saturation masks.
        with_raw: also return the noisy Bayer mosaics before demosaicing, with what reading
            them needs (scenes with the RAW round trip).

    Example::

        synth = gpu_blur.Synthesizer("realblur_j", backend="warp")
        out = synth(blurred, mask=mask)        # B x H x W x 3 torch CUDA tensors
        out.blurred, out.sharp                 # torch CUDA tensors, cropped by 4 px
    """

    def __init__(self, scene=None, *, backend: str = "numpy", seed: int = 0,
                 overrides: Mapping | None = None, schedule: Schedule | None = None,
                 channels_first: bool = False, with_mask: bool = False,
                 with_raw: bool = False):
        self.scene = _as_scene(scene)
        if with_raw and not raw_round_trip(self.scene):
            where = f"scene file {self.scene.path}" if self.scene.path else "scene"
            raise ValueError(f"with_raw: {where} has no RAW round trip (noise.model = "
                             f"{self.scene.noise.model!r}, isp.round_trip = "
                             f"{self.scene.isp.round_trip!r}); set noise.model = "
                             "'poisson-gaussian' or isp.round_trip = 'always'")
        self.runner: Backend = (get_backend(backend, self.scene.output.precision)
                                if isinstance(backend, str) else backend)
        self.camera = scene_camera(self.scene, self.runner.name)
        check_overrides(overrides)  # each one, whether or not its stage runs
        self.seed, self.overrides = seed, overrides
        self.schedule = schedule or Schedule()
        self.channels_first, self.with_mask, self.with_raw = channels_first, with_mask, with_raw
        self.resident = (is_resident(self.runner)
                         and self.schedule == Schedule()
                         and interpolation_factor(plan(self.scene)) == 1)
        self._draws = Draws(self.scene, self.camera, seed, overrides)
        self._io = BatchIO(self.scene, self.runner, self.resident, channels_first, with_mask)
        paths = (self.runner, self.scene, self.camera, seed)
        self._host_path = HostPath(*paths, self.schedule, self._draws, self._io, with_mask,
                                   with_raw)
        self._resident_path = (ResidentPath(*paths, self._draws, self._io, with_mask, with_raw)
                               if self.resident else None)
        self._device_pngs: DevicePngs | None = None

    def pinned(self, shape, dtype=np.float32) -> np.ndarray:
        """An uninitialized numpy array in page-locked host memory, for batches and ``out=``.

        A kernel backend on a GPU copies such arrays to and from its device directly: a
        batch stacked into one (``np.stack(frames, out=...)``) uploads with no staging copy,
        and ``out=`` arrays made here receive the results at the bus's rate. Page-locking is
        slow: make them once and reuse them. The numpy backend returns a plain array.

        Example (RSBlur: 9 frames a sample, results cropped by 4 pixels a side)::

            frames = synth.pinned((16, 9, 1200, 1920, 3), np.uint8)
            shape = synth.result_shape(frames.shape)  # 16 x 1192 x 1912 x 3
            out = [synth.pinned(shape) for _ in range(2)]  # blurred, sharp
            np.stack(decoded, out=frames)
            synth(frames, out=out)
        """
        if is_resident(self.runner):
            return self.runner.pinned(tuple(shape), dtype)
        return np.empty(shape, dtype)

    def result_shape(self, batch_shape) -> tuple[int, ...]:
        """The shape of each result (blurred, sharp, mask) of a batch of ``batch_shape``.

        What ``out=`` arrays take: B x H' x W' x 3 (B x 3 x H' x W' with ``channels_first``),
        the inputs' size kept (even sides for the RAW round trip) less ``output.crop`` pixels
        a side. ``batch_shape``: the batch's, as :meth:`__call__` takes it.
        """
        shape = tuple(int(n) for n in batch_shape)
        size = (*shape[-2:], 3) if self.channels_first else shape[-3:]
        region = inner(kept_size(self.scene, size), self.scene.output.crop)
        return ((shape[0], 3, region.h, region.w) if self.channels_first
                else (shape[0], region.h, region.w, 3))

    def result_dtypes(self, codes: bool = False) -> list:
        """The dtype of each result (blurred, sharp, mask): what ``out=`` arrays take.

        float32, or with ``codes`` blurred and sharp as ``output.bits``' codes (uint8 or
        uint16); the mask (``with_mask``) float32.
        """
        check_codes(self.scene, codes)
        return self._io.result_dtypes(self.scene.output.bits if codes else 0)

    def sample(self, inputs, sample_index: int = 0, *, on_device: bool = False,
               codes: bool = False, sequence_index: int | None = None) -> Synthesis:
        """One sample from :func:`synthesize`'s ``inputs`` (arrays or paths)."""
        start, before = time.perf_counter(), current().snapshot()
        scene = self.scene
        if codes and on_device:
            raise ValueError("codes=True returns the output's 8- or 16-bit codes on the host; "
                             "leave out on_device=True")
        check_codes(scene, codes)
        if on_device and (self.schedule.tile is not None or self.schedule.verify
                          or scene.output.crop or not self.runner.device_arrays
                          or scene.output.jpeg_quality is not None):
            raise ValueError("on_device=True needs a backend that keeps results on a device "
                             "(warp), no tile, no verify, output.crop = 0 and no "
                             "output.jpeg_quality (a host stage)")
        with timer("reading"):
            item = gather(inputs, scene)
        (item,), check = self._prepared([item])
        crop = scene.output.crop
        if self.resident:
            made = self._resident_path.sample(item, sample_index, check, on_device=on_device,
                                              codes=codes, sequence_index=sequence_index)
        else:
            made = self._host_path.sample(item, sample_index, on_device=on_device,
                                          sequence_index=sequence_index)
        out, sharp, mask, raw, params, sample_plan, tiles, spot_checks = made
        if sample_plan.kept(StageName.JPEG):
            out = jpeg_round_trip(out, params["jpeg_quality"])
        if codes:  # what the device did not make: the same codes, made here
            out, sharp = (x if x.dtype == code_dtype(scene.output.bits)
                          else to_integers(x, scene.output.bits) for x in (out, sharp))
        return Synthesis(out, sharp, mask, params, sample_plan,
                         since(before, time.perf_counter() - start), tiles, spot_checks, crop,
                         self.runner.model, raw, self._raw_info(params))

    def _raw_info(self, params: dict) -> dict | None:
        """A sample's :func:`gpu_blur.outputs.raw_metadata` with ``with_raw``, else None."""
        return (raw_metadata(params, self.camera, self.scene.output.crop) if self.with_raw
                else None)

    def __call__(self, batch, *, mask=None, sharp=None, first_index: int = 0,
                 indices: Sequence[int] | None = None, out: Sequence | None = None,
                 codes: bool = False, sequences: Sequence[int] | None = None,
                 png: bool = False) -> Batch:
        """Synthesize a batch; sample b has sample index ``first_index + b``.

        Args:
            batch: blur mode average: B x F x H x W x 3 frames; kernel and trajectory:
                B x H x W x 3 photos; none: B x H x W x 3 blurred images. numpy, torch (CPU
                or CUDA), CuPy or ``wp.array``; uint8, uint16, float16, float32 or float64
                (floats: sRGB values in [0, 1]); RGB order.
            mask: mode none: the saturation masks, as ``batch`` (optional).
            sharp: mode none: the sharp images, as ``batch`` (optional: the blurred images).
            first_index: the first sample's index (0 <= index, index + B <= 2**32).
            indices: each sample's index instead (B ints, any order: a shuffled
                DataLoader's; a list, or a numpy or torch integer array), for ``first_index``.
            out: numpy batches, and batches on the backend's device (the results copied to
                the host): numpy arrays to write the results into, (blurred, sharp) or
                (blurred, sharp, mask) as ``with_mask`` asks, float32 (blurred and sharp in
                the codes' dtype with ``codes``), each of the result's shape (B x H' x W' x 3,
                or B x 3 x H' x W' with ``channels_first``), sharing no memory with each
                other or an input. Reusing them spares allocating (and page-faulting) fresh
                outputs for every batch.
            codes: blurred and sharp as the output's integer codes, uint8 (``output.bits``
                8) or uint16 (16), ``to_integers`` of the float results; on a kernel backend
                made on the device (a quarter or half of the float32 bytes to fetch), after
                the JPEG stage on the host. The mask stays float32.
            sequences: each sample's frame sequence index (B ints, as ``indices``), which
                keys its camera settings under ``blur.draws = "per-sequence"``
                (:func:`synthesize`'s ``sequence_index``); required there, not used otherwise.
            png: with ``codes``, for a scene of 8-bit ``output.png = "fast"`` PNGs on a Warp
                CUDA device whose results come to the host: each blurred and sharp image's PNG
                stream is also deflated on the device (:class:`gpu_blur.png_device.DevicePngs`,
                zlib's bytes), in :attr:`Batch.png`; elsewhere that stays None.

        Returns:
            A :class:`Batch`; sample b equals ``synthesize`` with ``sample_index =
            first_index + b`` (and ``sequence_index = sequences[b]``) bit for bit.

        Raises:
            ValueError: a bad shape, dtype or value, naming the sample (``sample 3 of 16``)
                and the input; nothing is returned for the batch.
        """
        start, before = time.perf_counter(), current().snapshot()
        check_codes(self.scene, codes)
        if isinstance(batch, (list, tuple)):
            raise ValueError("a batch is one array (B x H x W x 3, or B x F x H x W x 3 for "
                             "frames), every sample of one size: stack same-size samples "
                             "(np.stack, torch.stack), and call once per size for mixed sizes")
        refuse_out_on_inputs(out, {"batch": batch, "mask": mask, "sharp": sharp})
        lib = arrays.library(batch)
        self._io.check_out(out, batch, lib)
        with timer("reading"):
            items = self._io.split(batch, mask, sharp, lib)
        # a batch on the device is read only once written there, on the caller's stream
        caller = arrays.producer_stream(batch, lib) if self._io.reaches(batch, lib) else None
        if caller is not None:
            self.runner.wait_for(caller)
        indices = sample_indices(indices, first_index, len(items))
        if sequences is not None:
            sequences = sample_indices(sequences, 0, len(items), "sequences", "sequence index")
        # codes made on the device, or from the float results here (JPEG stage, host batches)
        device_codes = codes and self.resident and self.scene.output.jpeg_quality is None
        bits = self.scene.output.bits if device_codes else 0
        out_given, given = out, (None if codes and not device_codes else out)
        pngs = self._pngs() if png and device_codes else None
        if pngs is not None:
            pngs.start()
        if self.resident:
            out, params, plans, raws = self._resident_path.batch(items, indices, batch, lib,
                                                                 given, bits, sequences, pngs)
        else:
            items, _ = self._prepared(items)
            out, params, plans, raws = self._host_path.batch(items, indices, batch, lib, given,
                                                             sequences)
        jpeg_stage(out[0], plans, params)  # channels-last, as the backend wrote them
        if codes and not device_codes:
            out = self._io.codes_here(out, lib, out_given)
        if caller is not None:  # the caller's next work waits for these results, not the host
            self.runner.hand_to(caller)
        out = ([self._io.returned(o, lib, batch) for o in out] if out_given is None
               else list(out_given))
        raw = None
        if self.with_raw:
            crop = self.scene.output.crop
            raw = np.stack([crop_border(to_host(r, np.float32), crop) for r in raws])
        return Batch(out[0], out[1], out[2] if self.with_mask else None, params, plans,
                     since(before, time.perf_counter() - start), raw,
                     [self._raw_info(p) for p in params] if self.with_raw else None,
                     pngs.take() or None if pngs is not None else None)

    def _pngs(self) -> DevicePngs | None:
        """The :class:`~gpu_blur.png_device.DevicePngs` of these batches, made on first use.

        None where its scene and device do not take them (``DevicePngs.for_backend``).
        """
        if self._device_pngs is None and getattr(self.runner, "wp_device", None) is not None:
            from gpu_blur.png_device import DevicePngs  # imports Warp: a Warp backend's
            from gpu_blur.staging import LentResults

            if DevicePngs.for_backend(self.runner, self.scene):
                self._device_pngs = DevicePngs(self.runner, LentResults(self.runner).take)
        return self._device_pngs

    def _prepared(self, items: list[Inputs]) -> tuple[list[Inputs], Callable[[], None]]:
        """Inputs checked, with the clip test, and the function that ends their checks.

        On the device path put there and counted there
        (:meth:`~gpu_blur.synthesis.resident.ResidentPath.prepared`), which the caller calls
        before any result leaves; on the host path checked here, the function does nothing.
        """
        if self.resident:
            return self._resident_path.prepared(items)
        return [checked_on_host(self.scene, item) for item in items], checked
