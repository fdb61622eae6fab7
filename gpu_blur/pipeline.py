"""``Synthesizer``: realistic blurred samples from sharp input, as a scene describes, in batches.

``synthesize`` is a batch of one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from gpu_blur import arrays
from gpu_blur.backends import OnDevice, get_backend, pinned_owner, to_host
from gpu_blur.backends.flows import interpolation_factor, scene_factors, with_factors
from gpu_blur.backends.kernel import Drawn, KernelBackend, Slots
from gpu_blur.backends.numpy import retone
from gpu_blur.cameras import Camera, check_float32_response, get_camera
from gpu_blur.imageio import check_image, check_layout, read_image, unit_values
from gpu_blur.outputs import jpeg_round_trip, raw_metadata
from gpu_blur.params import batch_uniforms, check_overrides, draw_params
from gpu_blur.plan import Plan, StageName, plan, raw_round_trip
from gpu_blur.reference import transfer
from gpu_blur.reference.interpolate import RegionFactors
from gpu_blur.reference.output import code_dtype, crop_border, quantize, to_integers
from gpu_blur.scene import Scene, load_scene
from gpu_blur.scheduler import Schedule, run
from gpu_blur.tiling import Region, tiles
from gpu_blur.timings import current, since, timer

#: Samples per part of a batch in pinned memory (:meth:`Synthesizer._resident_batch`): the
#: device downloads one part's results while it uploads the next part's inputs.
STREAMED_SAMPLES = 4

#: Input bytes a sample needs for its batch to go in parts: below them the copies are short
#: and the parts' extra launches cost more (random-kernel 256 x 256 batches of 16 on one H200:
#: 1.37 ms a sample in parts, 1.16 in one).
STREAMED_BYTES = 1 << 22


@dataclasses.dataclass
class Synthesis:
    """One synthesized sample.

    Attributes:
        blurred: H x W x 3 float32 in [0, 1], RGB, the realistic blurred image: multiples of
            1/255 with the default ``output.bits = 8`` (1/65535 with 16; ``bits = 0`` keeps
            float values).
        sharp: H x W x 3 float32 in [0, 1], the reference frame (middle frame of an average,
            the photo itself otherwise), toned like ``blurred``.
        mask: H x W x 3 float32 in [0, 1], the blurred saturation mask (fetched from the
            device on first use); None in what a worker process sends for a set that does
            not save masks (:func:`gpu_blur.generate.for_driver`).
        raw: with ``Synthesizer(with_raw=True)``, H x W float32: the noisy white-balanced
            Bayer mosaic before demosaicing (the to_raw pass's output), cropped like the
            outputs (fetched on first use); else None.
        raw_info: with ``with_raw``, what reading it needs
            (:func:`gpu_blur.outputs.raw_metadata`: CFA pattern, levels, gains, matrix).
        params: every drawn value (see :data:`gpu_blur.params.DRAW_INDEX`).
        plan: the stages that ran.
        timings: seconds this call spent per :mod:`gpu_blur.timings` category (reading,
            copies, kernels, checks; writing is 0 here), plus ``other`` and ``total``.
        tiles: how many tiles the image ran in.
        spot_checks: how many of them were checked against the numpy reference.
        device: the model of device that made it, in words (the backend's ``model``:
            ``warp NVIDIA H200, float32``, without the device's number on this host, so a
            set's manifest is the same whichever GPU made each sample).

    A worker process of ``gpu-blur generate`` sends blurred and sharp as the set's integer
    codes instead (:func:`gpu_blur.generate.for_driver`).
    """

    blurred: np.ndarray
    sharp: np.ndarray
    _mask: object = dataclasses.field(repr=False)
    params: dict
    plan: Plan
    timings: dict = dataclasses.field(default_factory=dict)
    tiles: int = 1
    spot_checks: int = 0
    crop: int = 0
    device: str = ""
    _raw: object = dataclasses.field(default=None, repr=False)
    raw_info: dict | None = None

    @property
    def mask(self) -> np.ndarray | None:
        """The blurred saturation mask, H x W x 3 float32 in [0, 1]."""
        if self._mask is not None and not isinstance(self._mask, np.ndarray):
            self._mask = crop_border(to_host(self._mask, np.float32), self.crop)
        return self._mask

    @property
    def raw(self) -> np.ndarray | None:
        """The noisy white-balanced mosaic (``with_raw``), H x W float32, or None."""
        if self._raw is not None and not isinstance(self._raw, np.ndarray):
            self._raw = crop_border(to_host(self._raw, np.float32), self.crop)
        return self._raw

    def __getstate__(self):  # a device array does not cross processes: fetch it first
        return {**self.__dict__, "_mask": self.mask, "_raw": self.raw}


def _as_scene(scene) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene)


def _load(item, what: str) -> np.ndarray:
    """An input as stored (uint8/uint16 codes, or floats), its layout checked."""
    if isinstance(item, (str, Path)):
        return check_layout(read_image(item), str(item))
    arrays.check_dense(item, what)
    return check_layout(np.asarray(item), what)


def _name(item, what: str) -> str:
    """How messages name an input: its file, else its role (``frame 2``)."""
    return str(item) if isinstance(item, (str, Path)) else what


def scene_camera(scene: Scene, backend: str = "numpy") -> Camera:
    """The scene's camera (a preset or a camera file next to the scene).

    Args:
        scene: the scene.
        backend: the backend's name (``numpy``, ``opencl``, ``warp``): float32 kernels refuse a
            fitted response they cannot evaluate within tolerance
            (:func:`gpu_blur.cameras.check_float32_response`).

    Raises:
        ValueError: naming the scene's ``camera.name`` and the cameras there are; or, for
            ``output.crf = "camera"``, naming the camera when it has no fitted response or
            one too large for float32 kernels.
    """
    where = f"scene file {scene.path}" if scene.path else "scene"
    try:
        camera = get_camera(scene.camera.name, scene.base_dir)
    except ValueError as e:
        raise ValueError(f"{where}: camera.name = {scene.camera.name!r}: {e}") from None
    if scene.output.crf == "camera":
        try:
            camera.fitted_response()
            if backend != "numpy" and scene.output.precision == "float32":
                check_float32_response(camera)
        except ValueError as e:
            raise ValueError(f"{where}: camera.name = {scene.camera.name!r}: {e}") from None
    return camera


def synthesize(inputs, scene=None, *, seed: int = 0, sample_index: int = 0,
               backend: str = "numpy", overrides: Mapping | None = None,
               tile: tuple[int, int] | Schedule | None = None, on_device: bool = False,
               max_device_memory: int | str | None = None, verify: float = 0.0,
               with_raw: bool = False, codes: bool = False) -> Synthesis:
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
    return synthesizer.sample(inputs, sample_index, on_device=on_device, codes=codes)


@dataclasses.dataclass
class Batch:
    """What :class:`Synthesizer` returns for a batch of B samples.

    Attributes:
        blurred: B x H' x W' x 3 realistic blurred images in [0, 1], RGB, of the input's
            array type and device (B x 3 x H' x W' with ``channels_first``); H', W': the
            input's size less ``output.crop`` on each side (and an odd last row or column
            for the RAW round trip). float32 in host memory; on a device, the compute type;
            with ``codes=True`` the output's uint8 or uint16 codes.
        sharp: the sharp references, the same way.
        mask: the blurred saturation masks with ``with_mask=True``, else None.
        raw: with ``with_raw=True``, B x H' x W' float32 host array (numpy): the noisy
            white-balanced Bayer mosaics before demosaicing, cropped like the outputs; else
            None.
        raw_info: with ``with_raw``, each sample's :func:`gpu_blur.outputs.raw_metadata`.
        params: each sample's drawn values (:data:`gpu_blur.params.DRAW_INDEX`).
        plans: each sample's plan (auto saturation decides per sample).
        timings: seconds the batch spent per :mod:`gpu_blur.timings` category.
    """

    blurred: object
    sharp: object
    mask: object
    params: list
    plans: list
    timings: dict
    raw: np.ndarray | None = None
    raw_info: list | None = None


@dataclasses.dataclass
class _Resident:
    """A batch's results on the device (:meth:`Synthesizer._run_resident`).

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


@dataclasses.dataclass
class _Inputs:
    """One sample's inputs: frames (a stack for mode average), mask, sharp, and their names.

    Host arrays as stored (:func:`gpu_blur.imageio.check_layout`), or after
    :meth:`Synthesizer._put`, :class:`~gpu_blur.backends.OnDevice` values.
    """

    frames: object
    mask: object
    sharp: object
    names: dict
    label: str = ""
    saturated: bool = False


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
        self.runner = (get_backend(backend, self.scene.output.precision)
                       if isinstance(backend, str) else backend)
        self.camera = scene_camera(self.scene, self.runner.name)
        check_overrides(overrides)  # each one, whether or not its stage runs
        self.seed, self.overrides = seed, overrides
        self.schedule = schedule or Schedule()
        self.channels_first, self.with_mask, self.with_raw = channels_first, with_mask, with_raw
        self._plans: dict = {}
        self._buffers = None  # (shape key, buffers) of the last resident batch
        self.resident = (isinstance(self.runner, KernelBackend)
                         and self.schedule == Schedule()
                         and interpolation_factor(plan(self.scene)) == 1)

    def pinned(self, shape, dtype=np.float32) -> np.ndarray:
        """An uninitialized numpy array in page-locked host memory, for batches and ``out=``.

        A kernel backend on a GPU copies such arrays to and from its device directly: a
        batch stacked into one (``np.stack(frames, out=...)``) uploads with no staging copy,
        and ``out=`` arrays made here receive the results at the bus's rate. Page-locking is
        slow: make them once and reuse them. The numpy backend returns a plain array.

        Example (RSBlur: 9 frames a sample, results cropped by 4 pixels a side)::

            frames = synth.pinned((16, 9, 1200, 1920, 3), np.uint8)
            out = [synth.pinned((16, 1192, 1912, 3)) for _ in range(2)]  # blurred, sharp
            np.stack(decoded, out=frames)
            synth(frames, out=out)
        """
        if isinstance(self.runner, KernelBackend):
            return self.runner.pinned(tuple(shape), dtype)
        return np.empty(shape, dtype)

    # -- one sample (synthesize) -------------------------------------------------------------
    def sample(self, inputs, sample_index: int = 0, *, on_device: bool = False,
               codes: bool = False) -> Synthesis:
        """One sample from :func:`synthesize`'s ``inputs`` (arrays or paths)."""
        start, before = time.perf_counter(), current().snapshot()
        scene = self.scene
        if codes and on_device:
            raise ValueError("codes=True returns the output's 8- or 16-bit codes on the host; "
                             "leave out on_device=True")
        self._check_codes(codes)
        if on_device and (self.schedule.tile is not None or self.schedule.verify
                          or scene.output.crop or not self.runner.device_arrays
                          or scene.output.jpeg_quality is not None):
            raise ValueError("on_device=True needs a backend that keeps results on a device "
                             "(warp), no tile, no verify, output.crop = 0 and no "
                             "output.jpeg_quality (a host stage)")
        with timer("reading"):
            item = _gather(inputs, scene)
        (item,), check = self._prepared([item])
        crop, tiles, checked = scene.output.crop, 1, 0
        if self.resident:
            done = self._run_resident([item], [sample_index])
            check()
            runner, (h, w) = self.runner, done.size
            blurred = runner.slot_image(done.blurred, 0, (done.out.h, done.out.w, 3))
            # codes made on the device, unless the JPEG stage (on the host) is still to come
            device_codes = codes and not done.plans[0].kept(StageName.JPEG)
            out = (runner.device_array(blurred) if on_device
                   else self._host(blurred, _inner(blurred.shape, 0), device_codes))
            sharp = self._host(runner.slot_image(done.sharp, 0, blurred.shape),
                               _inner(blurred.shape, 0), codes)
            mask = runner.slot_image(done.mask, 0, (h, w, 3))  # fetched on first use
            raw = runner.slot_image(done.raw, 0, (h, w)) if self.with_raw else None
            params, sample_plan = done.params[0], done.plans[0]
        else:
            blurred, mask, sharp, params, sample_plan, tiled = self._run(
                item, sample_index, on_device=on_device)
            out = (self.runner.device_array(blurred) if on_device
                   else crop_border(blurred, crop))
            if isinstance(mask, np.ndarray):  # a device mask is fetched (and cropped) on use
                mask = crop_border(mask, crop).astype(np.float32, copy=False)
            raw = tiled.raw  # the same way
            if isinstance(raw, np.ndarray):
                raw = crop_border(raw, crop).astype(np.float32, copy=False)
            tiles, checked = tiled.tiles, tiled.checked
        if sample_plan.kept(StageName.JPEG):
            out = jpeg_round_trip(out, params["jpeg_quality"])
        if codes:  # what the device did not make: the same codes, made here
            out, sharp = (x if x.dtype == code_dtype(scene.output.bits)
                          else to_integers(x, scene.output.bits) for x in (out, sharp))
        return Synthesis(out, sharp, mask, params, sample_plan,
                         since(before, time.perf_counter() - start), tiles, checked, crop,
                         self.runner.model, raw, self._raw_info(params))

    def _check_codes(self, codes: bool) -> None:
        """Refuse ``codes=True`` for a scene without 8- or 16-bit output."""
        if codes and self.scene.output.bits not in (8, 16):
            raise ValueError(f"codes=True returns the output's 8- or 16-bit codes; this scene has "
                             f"output.bits = {self.scene.output.bits} (0 keeps float values): "
                             "set output.bits = 8 or 16, or leave codes out")

    def _raw_info(self, params: dict) -> dict | None:
        """A sample's :func:`gpu_blur.outputs.raw_metadata` with ``with_raw``, else None."""
        return (raw_metadata(params, self.camera, self.scene.output.crop) if self.with_raw
                else None)

    def _host(self, values, region: Region, codes: bool = False) -> np.ndarray:
        """``region`` of a device image on the host, float32.

        With ``codes``: the output's integer codes, made on the device
        (:meth:`~gpu_blur.backends.kernel.KernelBackend.to_codes`).
        """
        if codes:
            values = self._coded(values, self.scene.output.bits, kept=True)
        out = np.empty((region.h, region.w, 3), dtype=values.dtype or np.float32)
        self.runner.export(values, region, out)
        return out

    # -- a batch -----------------------------------------------------------------------------
    def __call__(self, batch, *, mask=None, sharp=None, first_index: int = 0,
                 indices: Sequence[int] | None = None, out: Sequence | None = None,
                 codes: bool = False) -> Batch:
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
            out: numpy batches: arrays to write the results into, (blurred, sharp) or
                (blurred, sharp, mask) as ``with_mask`` asks, float32 (blurred and sharp in
                the codes' dtype with ``codes``), each of the result's shape (B x H' x W' x 3,
                or B x 3 x H' x W' with ``channels_first``), sharing no memory with each
                other or an input. Reusing them spares allocating (and page-faulting) fresh
                outputs for every batch.
            codes: blurred and sharp as the output's integer codes, uint8 (``output.bits``
                8) or uint16 (16), ``to_integers`` of the float results; on a kernel backend
                made on the device (a quarter or half of the float32 bytes to fetch), after
                the JPEG stage on the host. The mask stays float32.

        Returns:
            A :class:`Batch`; sample b equals ``synthesize`` with ``sample_index =
            first_index + b`` bit for bit.

        Raises:
            ValueError: a bad shape, dtype or value, naming the sample (``sample 3 of 16``)
                and the input; nothing is returned for the batch.
        """
        start, before = time.perf_counter(), current().snapshot()
        self._check_codes(codes)
        if isinstance(batch, (list, tuple)):
            raise ValueError("a batch is one array (B x H x W x 3, or B x F x H x W x 3 for "
                             "frames), every sample of one size: stack same-size samples "
                             "(np.stack, torch.stack), and call once per size for mixed sizes")
        _refuse_out_on_inputs(out, {"batch": batch, "mask": mask, "sharp": sharp})
        lib = arrays.library(batch)
        with timer("reading"):
            items = self._split(batch, mask, sharp, lib)
        # a batch on the device is read only once written there, on the caller's stream
        caller = arrays.producer_stream(batch, lib) if self._reaches(batch, lib) else None
        if caller is not None:
            self.runner.wait_for(caller)
        indices = _sample_indices(indices, first_index, len(items))
        # codes made on the device, or from the float results here (JPEG stage, host batches)
        device_codes = codes and self.resident and self.scene.output.jpeg_quality is None
        bits = self.scene.output.bits if device_codes else 0
        out_given, given = out, (None if codes and not device_codes else out)
        if self.resident:
            out, params, plans, raws = self._resident_batch(items, indices, batch, lib, given,
                                                            bits)
        else:
            items, _ = self._prepared(items)
            out, params, plans, raws = self._host_batch(items, indices, batch, lib, given)
        _jpeg_stage(out[0], plans, params)  # channels-last, as the backend wrote them
        if codes and not device_codes:
            out = self._codes_here(out, lib, out_given)
        if caller is not None:  # the caller's next work waits for these results, not the host
            self.runner.hand_to(caller)
        out = ([self._returned(o, lib, batch) for o in out] if out_given is None
               else list(out_given))
        raw = None
        if self.with_raw:
            crop = self.scene.output.crop
            raw = np.stack([crop_border(to_host(r, np.float32), crop) for r in raws])
        return Batch(out[0], out[1], out[2] if self.with_mask else None, params, plans,
                     since(before, time.perf_counter() - start), raw,
                     [self._raw_info(p) for p in params] if self.with_raw else None)

    def _resident_batch(self, items: list[_Inputs], indices, batch, lib: str, given,
                        bits: int = 0):
        """A batch put on the device: its passes batched, its outputs exported once each.

        ``bits`` 8 or 16: blurred and sharp leave as their codes, made on the device.

        A batch of 8/16-bit codes in this backend's pinned memory (:meth:`pinned`), of at least
        :data:`STREAMED_BYTES` a sample, goes in parts of :data:`STREAMED_SAMPLES`, each
        exported as soon as its passes are queued: the device downloads one part's results
        while it uploads the next part's inputs (the two copy directions overlap). Codes have
        no values to refuse, so no part's results leave before a later part fails its checks;
        float inputs go in one part, their checks ended (:meth:`_prepared`) once the passes
        are queued and before any result leaves.

        Results handed over on the device return before the device has made them: the host
        waits only for the checks, and the next batch's host work overlaps this batch's passes
        (``__call__`` makes the caller's stream wait for them). Other results are waited for.

        Auto saturation's clip test is read once the passes are queued, too: every sample runs
        as if it clipped, and one that does not gets skipping's plan and draws afterwards
        (:meth:`_unclipped`), its output the same bits (on its zero mask the saturate and
        restore stages are identities). So the device never idles while the host draws and
        launches, at the cost of those two stages on samples that do not clip.
        """
        runner, count = self.runner, len(items)
        streamed = (not self.with_raw and isinstance(batch, np.ndarray)
                    and pinned_owner(batch) is runner and all(map(_codes_only, items))
                    and batch.nbytes >= STREAMED_BYTES * count)
        step = STREAMED_SAMPLES if streamed else count
        # a batch on the device gets the result buffers themselves (new ones each batch), or
        # their codes (new arrays: the buffers are kept)
        handed = given is None and step == count and self._reaches(batch, lib)
        clip_test = self.scene.saturation.mode == "auto"
        out, params, plans = None, [], []
        with self._queued():
            for start in range(0, count, step):
                part, check = self._prepared(items[start:start + step], clip_test_later=True)
                done = self._run_resident(part, indices[start:start + step], reuse=True,
                                          fresh_results=handed and not bits,
                                          as_clipped=clip_test)
                check()
                if clip_test:
                    self._unclipped(done, part)
                params += done.params
                plans += done.plans
                if handed:
                    out = self._handed_over(done, batch, lib, bits)
                    continue
                if out is None:
                    code = code_dtype(bits) if bits else np.float32
                    out = self._outputs(count, done.out, batch, lib,
                                        [code, code, np.float32][:3 if self.with_mask else 2],
                                        given)
                self._export_resident(done, out if step == count else
                                      [o[start:start + len(part)] for o in out], bits)
            if not handed:
                with timer("kernels"):
                    runner.wait()
        raws = ([runner.slot_image(done.raw, b, done.size) for b in range(count)]
                if self.with_raw else [])
        return out, params, plans, raws

    def _unclipped(self, done: _Resident, items: list[_Inputs]) -> None:
        """The plans and draws of ``done``'s samples run as if they clipped that did not.

        Their clip test, read after their passes were queued, says auto saturation skips
        them: skipping's plan, and their draws without alpha (its own draw slot: nothing
        else moves), as :meth:`_drawn` gives them.
        """
        for b, item in enumerate(items):
            if not item.saturated:
                done.plans[b] = self._plan(False, *done.size, None)
                done.params[b] = {k: v for k, v in done.params[b].items() if k != "alpha"}

    def _export_resident(self, done: _Resident, out: list, bits: int = 0) -> None:
        """A resident batch's results into ``out`` (blurred, sharp[, mask]), one per sample.

        ``bits`` 8 or 16: blurred and sharp as their codes, made on the device.
        """
        shape = (done.out.h, done.out.w, 3)
        self._export_slots(out[0], done.blurred, shape, bits)
        self._export_slots(out[1], done.sharp, shape, bits)
        if self.with_mask:
            self._export_masks(done, out[2])

    def _export_masks(self, done: _Resident, into) -> None:
        """The batch's saturation masks, cropped as the outputs are, into ``into`` (B x ...)."""
        masked = _inner((*done.size, 3), self.scene.output.crop)
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
            out += self._outputs(done.blurred.count, done.out, batch, lib, [np.float32])
            self._export_masks(done, out[2])
        return out

    def _host_batch(self, items: list[_Inputs], indices, batch, lib: str, given):
        """A batch run sample by sample from host memory (tiles, budgets, spot checks)."""
        out, params, plans, raws = None, [], [], []
        crop = self.scene.output.crop
        for b, item in enumerate(items):
            blurred, sat_mask, sharp_out, drawn, sample_plan, tiled = self._run(
                item, int(indices[b]))
            raws.append(tiled.raw)
            params.append(drawn)
            plans.append(sample_plan)
            # (values, the region of them that goes out): a sharp image is already cropped
            results = [(blurred, _inner(blurred.shape, crop)),
                       (sharp_out, _inner(sharp_out.shape, 0))]
            if self.with_mask:
                results.append((sat_mask, _inner(sat_mask.shape, crop)))
            if out is None:
                out = self._outputs(len(items), results[0][1], batch, lib,
                                    [np.float32] * len(results), given)
            self._export(out, b, results)
        return out, params, plans, raws

    def _export_slots(self, into, slots: Slots, shape, bits: int = 0) -> None:
        """Every sample's slot of a batch buffer into ``into`` (B x ``shape``), in one copy.

        ``bits`` 8 or 16: their codes, made on the device.
        """
        # a B x h x w x 3 stack's "region": every sample, every row
        self.runner.export(self._coded(self.runner.stacked(slots, shape), bits, kept=True),
                           Region.whole(slots.count, shape[0]), into)

    def _coded(self, values: OnDevice, bits: int, kept: bool = False) -> OnDevice:
        """Device values as their ``bits``-bit codes on the device (0: as they are).

        ``kept``: in the runner's kept buffer (codes fetched at once), else a new one.
        """
        if not bits:
            return values
        into = (self.runner.codes_buffer(int(np.prod(values.shape)), bits) if kept else None)
        return self.runner.to_codes(values, bits, into)

    def _codes_here(self, out: list, lib: str, given) -> list:
        """A batch's float blurred and sharp as their codes, made on the host.

        After the JPEG stage, and for batches run from host memory; into ``out=``'s arrays
        (checked here), else new ones. The mask as it is.
        """
        bits = self.scene.output.bits
        host = [x if isinstance(x, np.ndarray) else x.numpy() for x in out]
        made = [to_integers(x, bits) for x in host[:2]] + host[2:]
        if given is None:
            return made
        code = code_dtype(bits)
        views = self._given_outputs(given, made[0].shape, lib,
                                    [code, code, np.float32][:len(made)])
        for view, x in zip(views, made, strict=True):
            np.copyto(view, x)
        return views

    @contextlib.contextmanager
    def _queued(self):
        """Resident batches queue every launch without waiting between passes."""
        if not self.resident:
            yield
            return
        self.runner.sync_passes = False
        try:
            yield
        finally:
            self.runner.sync_passes = True

    def _export(self, out: list, b: int, results: list) -> None:
        """Sample ``b``'s results, (values, region) each, into the batch's outputs."""
        for slot, (values, region) in zip(out, results, strict=True):
            if isinstance(values, OnDevice):
                self.runner.export(values, region, slot[b])
            else:
                np.copyto(slot[b], region.of(np.asarray(values)), casting="same_kind")

    def _outputs(self, count: int, region: Region, batch, lib: str, dtypes: list,
                 given: Sequence | None = None) -> list:
        """The batch's output arrays, one per dtype: ``out=``'s (channels-last views), else new.

        On the device (Warp) in the compute type, where the batch lies there.
        """
        shape = (count, region.h, region.w, 3)
        if given is not None:
            return self._given_outputs(given, shape, lib, dtypes)
        if self._reaches(batch, lib):
            import warp as wp

            return [wp.empty(shape, dtype=self.runner.real, device=self.runner.wp_device)
                    for _ in dtypes]
        return [np.empty(shape, dtype) for dtype in dtypes]

    def _given_outputs(self, given: Sequence, shape: tuple, lib: str, dtypes: list) -> list:
        """``out=``'s arrays checked against the results they take, as channels-last views."""
        n = len(dtypes)
        names = ("blurred", "sharp", "mask")[:n]
        if lib != "numpy":
            raise ValueError(f"out= is for numpy batches (the results are {lib} arrays made "
                             "where the batch lives); leave it out for this batch")
        if not isinstance(given, (list, tuple)) or len(given) != n:
            raise ValueError(f"out= takes {n} arrays, ({', '.join(names)})"
                             + ("" if self.with_mask else "; with_mask=True adds the mask"))
        want = (shape[0], 3, *shape[1:3]) if self.channels_first else shape
        views = []
        for name, array, dtype in zip(names, given, dtypes, strict=True):
            if (not isinstance(array, np.ndarray) or array.dtype != dtype
                    or array.shape != want or not array.flags.writeable):
                got = (f"a {type(array).__name__}" if not isinstance(array, np.ndarray) else
                       f"{array.dtype} {array.shape}"
                       + ("" if array.flags.writeable else ", read-only"))
                raise ValueError(f"out= {name}: needs a writeable {np.dtype(dtype).name} numpy "
                                 f"array of shape {want}; got {got}")
            if _self_overlapping(array):
                raise ValueError(f"out= {name}: its elements overlap (strides {array.strides}); "
                                 "results would overwrite each other: pass a plain array "
                                 "(np.empty)")
            for other, earlier in zip(names, views, strict=False):
                if _overlap(array, earlier):
                    raise ValueError(f"out= {name} shares memory with out= {other}; one result "
                                     "would overwrite the other: pass an array of its own for "
                                     "each")
            views.append(np.moveaxis(array, 1, -1) if self.channels_first else array)
        return views

    def _returned(self, out, lib: str, like):
        """An output array as the batch's type and layout."""
        if isinstance(out, np.ndarray):
            result = arrays.from_numpy(out, lib, like)
        else:
            result = arrays.from_warp(out, lib, like)
        return arrays.channels_first(result, lib) if self.channels_first else result

    def _reaches(self, batch, lib: str) -> bool:
        """Whether the backend takes ``batch`` where it is (Warp, on its device): no copy."""
        return (self.resident and self.runner.device_arrays
                and arrays.on_warp_device(batch, lib, self.runner.wp_device))

    def _taken(self, x, lib: str, reached: bool):
        """One sample's input as the backend takes it: a ``wp.array`` view, or host memory."""
        if reached:
            return arrays.as_warp(x, lib)
        host = arrays.to_numpy(x, lib)
        return host if self.resident else np.ascontiguousarray(host)

    def _split(self, batch, mask, sharp, lib: str) -> list[_Inputs]:
        """The batch as per-sample inputs: views of device arrays, else host arrays."""
        mode = self.scene.blur.mode
        given = {"batch": batch, "mask": mask, "sharp": sharp}
        if mode != "none":
            for key in ("mask", "sharp"):
                if given[key] is not None:
                    raise ValueError(f"{key}= is for blur.mode = none; this scene blurs "
                                     f"(blur.mode = {mode})")
        parts = {}
        for key, x in given.items():
            if x is None:
                continue
            if arrays.library(x) != lib:
                raise ValueError(f"{key} is a {arrays.library(x)} array but the batch is "
                                 f"{lib}: pass both as the same type")
            arrays.check_dense(x, key)
            parts[key] = self._normalized(x, key, lib, frames=key == "batch"
                                          and mode == "average")
        if mode == "average":
            _frame_count(parts["batch"].shape[1], self.scene)
        count = parts["batch"].shape[0]
        for key, x in parts.items():
            if tuple(x.shape) != tuple(parts["batch"].shape):
                raise ValueError(f"{key} has shape {tuple(x.shape)} but the batch "
                                 f"{tuple(parts['batch'].shape)}: give one of each per sample")
        reached = self._reaches(parts["batch"], lib)
        samples = {key: (reached and arrays.warp_samples(x, lib))
                   or [self._taken(x[b], lib, reached) for b in range(count)]
                   for key, x in parts.items()}
        items = []
        for b in range(count):
            label = f"sample {b} of {count}: "
            x = samples["batch"][b]
            if mode == "average":
                names = {"frames": [f"frame {i}" for i in range(x.shape[0])]}
                items.append(_Inputs(x, None, None, names, label))
                continue
            m = samples["mask"][b] if "mask" in parts else None
            s = samples["sharp"][b] if "sharp" in parts else None
            name = "blurred" if mode == "none" else "photo"
            items.append(_Inputs([x], m, s, {"frames": [name], "mask": "mask",
                                           "sharp": "sharp"}, label))
        return items

    def _normalized(self, x, key: str, lib: str, *, frames: bool):
        """One batch input checked for layout, channels-last, a kernel dtype, even size."""
        if self.channels_first:
            if x.ndim < 4 or x.shape[-3] != 3:
                raise ValueError(f"{key}: channels_first takes B x 3 x H x W (B x F x 3 x H x "
                                 f"W for frames); got shape {tuple(x.shape)}")
            x = arrays.channels_last(x, lib)
        want = 5 if frames else 4
        layout = "B x F x H x W x 3" if frames else "B x H x W x 3"
        if x.ndim != want or x.shape[-1] != 3 or 0 in tuple(x.shape):
            raise ValueError(f"{key}: blur.mode = {self.scene.blur.mode} takes {layout} "
                             f"batches; got shape {tuple(x.shape)}")
        dtype = arrays.dtype_name(x)
        if dtype not in arrays.DTYPES:
            raise ValueError(f"{key}: unsupported dtype {dtype}; use one of "
                             f"{', '.join(arrays.DTYPES)} (floats in [0, 1])")
        if dtype.startswith("float") and dtype != self.runner.precision and self.resident:
            x = arrays.as_real(x, lib, self.runner.precision)  # on the array's own device
        h, w = self._kept_size(x.shape)
        if (h, w) != tuple(x.shape[-3:-1]):
            x = x[..., :h, :w, :]
            x = x.contiguous() if lib == "torch" else x
        return x

    # -- shared by both ----------------------------------------------------------------------
    def _prepared(self, items: list[_Inputs], *, clip_test_later: bool = False
                  ) -> tuple[list[_Inputs], Callable[[], None]]:
        """Inputs checked (and on a kernel backend put on its device), with the clip test.

        Returns the inputs and the function that ends their checks, which the caller calls
        before any result leaves. On a kernel backend the checks count on the device and the
        counts are read there, after the passes the caller queues in between (so the device
        never waits for the host's look at them), unless auto saturation's clip test needs
        them to plan the samples: then they are read here and the function does nothing.
        ``clip_test_later``: the caller plans the samples as if they clipped, and the function
        sets each input's ``saturated`` from its counts.
        """
        if not self.resident:
            return [self._checked_on_host(item) for item in items], _checked
        put = [self._put(item) for item in items]
        clip_test = self.scene.saturation.mode == "auto"
        # (sample, which, image): each input once (a default sharp is a frame); float values
        # are checked, 8/16-bit codes only looked at for the clip test. Listed input by input,
        # so a device batch's samples of one input (evenly spaced in its buffer) are counted
        # in one launch (KernelBackend.inspect_queued)
        images = [(i, key, getattr(p, key)) for key in ("frames", "mask", "sharp")
                  for i, (item, p) in enumerate(zip(items, put, strict=True))
                  if getattr(item, key) is not None and (
                      getattr(p, key).dtype is None or (clip_test and key != "sharp"))]
        with timer("checks"):
            counts = self.runner.inspect_queued([image for _, _, image in images])

        def check() -> None:
            with timer("checks"):
                rows = counts()
            for (i, key, image), row in zip(images, rows, strict=True):
                if row[:4].any():  # the host says exactly what is wrong, and where
                    _bad_values(image, put[i], key)
                if clip_test and key == "mask" and row[5]:
                    put[i].saturated = True
                if clip_test and key == "frames" and put[i].mask is None and row[4]:
                    put[i].saturated = True

        if clip_test and not clip_test_later:
            check()
            return put, _checked
        return put, check

    def _checked_on_host(self, item: _Inputs) -> _Inputs:
        names, label = item.names, item.label
        try:
            frames = [check_image(f, n) for f, n in zip(item.frames, names["frames"],
                                                        strict=True)]
            mask = None if item.mask is None else unit_values(check_image(item.mask,
                                                                          names["mask"]))
            sharp = (frames[len(frames) // 2] if item.sharp is None
                     else check_image(item.sharp, names["sharp"]))
        except ValueError as e:
            raise ValueError(f"{label}{e}") from None
        if len({f.dtype for f in frames}) > 1:
            frames = [unit_values(f) for f in frames]
        h, w = self._kept_size(frames[0].shape)
        frames = [f[:h, :w] for f in frames]
        sharp = sharp[:h, :w]
        mask = None if mask is None else mask[:h, :w]
        return _Inputs(frames, mask, sharp, names, label, _reaches_clip_level(frames, mask))

    def _kept_size(self, shape) -> tuple[int, int]:
        """The (height, width) of ``... x H x W x 3`` inputs that a sample keeps.

        The RAW round trip keeps even sides (the Bayer 2 x 2 cell), and refuses less than 2 x 2.
        """
        h, w = shape[-3:-1]
        if raw_round_trip(self.scene):
            h, w = h - h % 2, w - w % 2
            if h < 2 or w < 2:
                raise ValueError(f"input of {tuple(shape[-3:-1])} is too small for the Bayer "
                                 "steps (need at least 2 x 2)")
        return h, w

    def _put(self, item: _Inputs) -> _Inputs:
        """A sample's inputs on the kernel backend's device (frames: one stack in mode average)."""
        runner = self.runner
        frames = item.frames
        if isinstance(frames, (list, tuple)):  # synthesize's host frames, a stack when averaged
            frames = frames[0] if self.scene.blur.mode != "average" else list(frames)
        first = frames[0] if isinstance(frames, list) else frames
        h, w = self._kept_size(first.shape)
        if (h, w) != tuple(first.shape[-3:-1]):
            frames = ([f[:h, :w] for f in frames] if isinstance(frames, list)
                      else np.ascontiguousarray(frames[..., :h, :w, :]))
        stack = runner.put(frames)
        mask = None if item.mask is None else runner.put(_even(item.mask, stack))
        if item.sharp is not None:
            sharp = runner.put(_even(item.sharp, stack))
        elif stack.ndim == 4:
            sharp = runner.frame(stack, stack.shape[0] // 2)
        else:
            sharp = stack
        return _Inputs(stack, mask, sharp, item.names, item.label)

    def _run(self, item: _Inputs, sample_index: int, *, on_device: bool = False):
        """A prepared sample's passes from host memory (:mod:`gpu_blur.scheduler`).

        ``on_device``: leave the blurred image on the device (whole image, ``output.crop``
        0). Returns (blurred, mask, sharp, params, plan, tiled).
        """
        scene = self.scene
        frames = item.frames
        h, w = frames[0].shape[:2]
        # interpolation auto: each gap's factor, measured on the host frames
        measured = scene_factors(scene, frames)
        sample_plan, params = self._drawn(item, sample_index, h, w, measured)
        # how the passes run (tiles, halos, streamed frames, spot checks): gpu_blur.scheduler
        crop = scene.output.crop
        tiled = run(self.runner, sample_plan, params, self.camera, frames, item.mask,
                    self.schedule, seed=self.seed, sample_index=sample_index,
                    on_device=on_device, keep_raw=self.with_raw)
        if isinstance(self.runner, KernelBackend):
            sharp = self._rendered_in_bands(sample_plan, crop_border(item.sharp, crop))
        else:
            sharp = render_sharp(sample_plan, self.camera, crop_border(item.sharp, crop))
        return tiled.blurred, tiled.mask, sharp, params, sample_plan, tiled

    def _run_resident(self, items: list[_Inputs], indices: Sequence[int], *,
                      reuse: bool = False, fresh_results: bool = False,
                      as_clipped: bool = False) -> _Resident:
        """Samples put on the device, each pass launched once per plan for the whole batch.

        The samples' draws come first (their per-image uniforms at once), then the accumulate
        pass writes each sample's slot of the batch's buffers; then samples of one plan (auto
        saturation gives at most two, unless ``as_clipped``) run to_raw and finish in one
        launch each, finish writing the cropped output. Every buffer keeps one slot per sample.

        ``reuse``: take the buffers of the last batch of this size (the caller copies every
        result out before the next batch), sparing device allocations; the Synthesizer holds
        one batch's buffers between calls. ``fresh_results``: new blurred and sharp slots
        all the same (the caller hands them over as the outputs). ``as_clipped``: plan every
        sample as one whose input reaches the clip level (its clip test is still to be read).
        """
        runner, camera, crop = self.runner, self.camera, self.scene.output.crop
        h, w = items[0].frames.shape[-3:-1]
        count, whole = len(items), Region.whole(h, w)
        out = _inner((h, w), crop)
        buffers = self._batch_buffers(count, h, w, out, reuse, fresh_results)
        linear, sat_mask, saturated, raw, result, sharp_slots = buffers
        uniforms = batch_uniforms(self.scene, seed=self.seed, sample_indices=indices)
        groups: dict = {}  # id(plan) -> (plan, its samples as Drawn, in batch order)
        params, plans, samples = [], [], []
        for b, (item, index) in enumerate(zip(items, indices, strict=True)):
            sample_plan, drawn = self._drawn(item, int(index), h, w, None, uniforms[b],
                                             saturated=as_clipped or item.saturated)
            params.append(drawn)
            plans.append(sample_plan)
            samples.append(Drawn(drawn, int(index), b))
            # plans are cached per clip test and size (_drawn): one object per group
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

    def _plan(self, saturated: bool, h: int, w: int, factors) -> Plan:
        """The plan of a sample of this size, clip test and interpolation (made once)."""
        key = (saturated, h, w, factors)
        if key not in self._plans:  # a plan depends on the scene, the clip test and the size
            self._plans[key] = plan(self.scene, saturated=saturated, size=(h, w),
                                    interpolation_factors=factors)
        return self._plans[key]

    def _drawn(self, item: _Inputs, sample_index: int, h: int, w: int,
               measured: RegionFactors | None, uniforms: dict | None = None, *,
               saturated: bool | None = None):
        """A sample's plan and drawn values: (plan, params).

        ``measured``: the gaps' factors under interpolation auto (:func:`scene_factors`).
        ``uniforms``: the sample's row of :func:`gpu_blur.params.batch_uniforms`, else drawn.
        ``saturated``: the clip test's answer to plan by, for the input's own.
        """
        scene = self.scene
        frames = item.frames
        sample_plan = self._plan(item.saturated if saturated is None else saturated, h, w,
                                 measured.gaps if measured else None)
        # Every draw has a fixed index (gpu_blur.params), so a stage the sample skips (auto
        # saturation) never shifts another draw.
        overrides = self.overrides
        if scene.saturation.mode == "auto" and not sample_plan.kept(StageName.SATURATE):
            # nothing to saturate in this sample: a fixed alpha has nothing to act on
            overrides = {k: v for k, v in (overrides or {}).items() if k != "alpha"}
        params = draw_params(scene, sample_plan, self.camera, seed=self.seed,
                             sample_index=sample_index, image_shape=(h, w), overrides=overrides,
                             uniforms=uniforms)
        if measured is not None:  # the plan's factors, recorded in the manifest
            params = with_factors(sample_plan, params, frames, measured)
        return sample_plan, params

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


def _jpeg_stage(blurred, plans: list[Plan], params: list[dict]) -> None:
    """The JPEG stage, on the host, in place: a batch's blurred images (host or Warp array)."""
    chosen = [b for b, p in enumerate(plans) if p.kept(StageName.JPEG)]
    if not chosen:
        return
    host = blurred if isinstance(blurred, np.ndarray) else blurred.numpy()
    for b in chosen:
        host[b] = jpeg_round_trip(host[b], params[b]["jpeg_quality"])
    if host is not blurred:
        blurred.assign(host)


def _codes_only(item: _Inputs) -> bool:
    """Whether a sample's host inputs are all 8/16-bit codes (no values to check)."""
    inputs = [*item.frames] if isinstance(item.frames, list) else [item.frames]
    return all(x.dtype.kind == "u" for x in [*inputs, item.mask, item.sharp] if x is not None)


def _inner(shape, crop: int) -> Region:
    """The region of an ``h x w (x 3)`` image left after cutting ``crop`` pixels per side."""
    h, w = shape[:2]
    return Region(crop, crop, h - 2 * crop, w - 2 * crop, h, w)


def _even(image, like: OnDevice):
    """A host mask or sharp image cut to the frames' (even) size."""
    if isinstance(image, np.ndarray):
        h, w = like.shape[-3:-1]
        return np.ascontiguousarray(image[:h, :w])
    return image


def _checked() -> None:
    """Nothing left to check (:meth:`Synthesizer._prepared`)."""


def _bad_values(image: OnDevice, item: _Inputs, key: str):
    """Raise check_image's message for a device input whose counts found bad values."""
    names = item.names
    host = image.numpy(image.dtype)
    parts = [host] if host.ndim == 3 else list(host)
    labels = ([names["frames"][0]] if host.ndim == 3 else names["frames"]) \
        if key == "frames" else [names[key]]
    for part, name in zip(parts, labels, strict=True):
        try:
            check_image(part, name)
        except ValueError as e:
            raise ValueError(f"{item.label}{e}") from None
    raise ValueError(f"{item.label}{key}: values outside [0, 1] or not finite")


def _reaches_clip_level(frames, mask) -> bool:
    """Whether any input pixel reaches the clip level (auto saturation runs only then)."""
    if mask is not None:
        return bool(np.any(np.asarray(mask) > 0))
    top = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}.get(frames[0].dtype, 1.0)
    return any(bool(np.any(f >= top)) for f in frames)


def render_sharp(sample_plan: Plan, camera: Camera, sharp: np.ndarray) -> np.ndarray:
    """The sharp reference as the output holds it: float32, quantized when the plan quantizes.

    The numpy backend's, in float64; kernel backends render it with the finish pass's device
    functions (``KernelBackend.render_sharp``), bit for bit the same whatever the tiles.

    In the output's encoding: sRGB, linear, or re-toned.

    Every step is pointwise, so 8- and 16-bit codes are rendered through a table: the float64
    curve (and quantization) evaluated once per code (256 or 65,536 values instead of one per
    pixel) and gathered, the same values bit for bit (1920 x 1200 re-toned with the A7R3
    polynomial on a 2-core CPU: about 0.2 s directly, 13 ms by table). 8-bit sRGB in and out
    gives the codes themselves, ``c / 255``.

    Args:
        sample_plan: the sample's plan.
        camera: its camera (``output.crf = "camera"`` re-tones with its fitted response).
        sharp: sRGB image as stored (:func:`gpu_blur.imageio.check_image`), H x W x 3.
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


def _gather(inputs, scene: Scene) -> _Inputs:
    """:func:`synthesize`'s inputs, read, laid out as the blur mode wants, values unchecked.

    Frames keep their stored dtype (uint8/uint16 codes, or floats in [0, 1]).
    """
    mode = scene.blur.mode
    if mode == "none":
        if not isinstance(inputs, Mapping) or "blurred" not in inputs:
            raise ValueError("blur.mode = none takes a mapping {'blurred': image, 'mask': "
                             "optional mask, 'sharp': optional sharp image}")
        unknown = [k for k in inputs if k not in ("blurred", "mask", "sharp")]
        if unknown:
            raise ValueError(f"blur.mode = none: unknown input {unknown[0]!r}; the inputs are "
                             "'blurred', 'mask' (optional) and 'sharp' (optional)")
        given = [k for k in ("blurred", "mask", "sharp") if inputs.get(k) is not None]
        names = {k: _name(inputs[k], "blurred image" if k == "blurred" else k) for k in given}
        loaded = {k: _load(inputs[k], names[k]) for k in given}
        _same_shape(list(loaded.values()), [_name(inputs[k], k) for k in given])
        return _Inputs([loaded["blurred"]], loaded.get("mask"), loaded.get("sharp"),
                       {"frames": [names["blurred"]], "mask": names.get("mask"),
                        "sharp": names.get("sharp")})
    if isinstance(inputs, (str, Path, np.ndarray)):
        inputs = [inputs]
    if not isinstance(inputs, Sequence) or len(inputs) == 0:
        raise ValueError(f"blur.mode = {mode} needs a non-empty list of images")
    if mode != "average" and len(inputs) != 1:
        raise ValueError(f"blur.mode = {mode} blurs one photo; got {len(inputs)} images")
    if mode == "average":
        _frame_count(len(inputs), scene)
    names = [_name(x, f"frame {i}") for i, x in enumerate(inputs)]
    frames = [_load(x, n) for x, n in zip(inputs, names, strict=True)]
    _same_shape(frames, names)
    if len({f.dtype for f in frames}) > 1:  # one dtype per sample
        frames = [unit_values(check_image(f, n)) for f, n in zip(frames, names, strict=True)]
    return _Inputs(frames, None, None, {"frames": names})


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two numpy arrays share memory (a case too costly to decide counts as shared)."""
    try:
        return bool(np.shares_memory(a, b, max_work=1 << 20))
    except np.exceptions.TooHardError:
        return True


def _self_overlapping(a: np.ndarray) -> bool:
    """Whether elements of ``a`` may share bytes: an axis steps less than the axes within span."""
    span = a.itemsize
    for stride, n in sorted((abs(s), n) for s, n in zip(a.strides, a.shape, strict=True)
                            if n > 1):
        if stride < span:
            return True
        span += stride * (n - 1)
    return False


def _refuse_out_on_inputs(out, inputs: dict) -> None:
    """Refuse an ``out=`` array that shares memory with an input (numpy batches)."""
    if not isinstance(out, (list, tuple)):
        return  # Synthesizer._given_outputs says what out= takes
    for name, array in zip(("blurred", "sharp", "mask"), out, strict=False):
        for key, x in inputs.items():
            if isinstance(array, np.ndarray) and isinstance(x, np.ndarray) and _overlap(array, x):
                raise ValueError(f"out= {name} shares memory with the {key} input; results "
                                 "would overwrite the inputs they are made from: pass an "
                                 "array of its own")


def _whole(x) -> bool:
    """Whether ``x`` is an int (Python's or numpy's; a bool is not)."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def _sample_indices(indices, first_index, count: int) -> list[int]:
    """A batch's sample indices as Python ints, each checked: a float is refused, not cut."""
    if indices is None:
        if not _whole(first_index) or not 0 <= first_index <= 2**32 - count:
            raise ValueError(f"first_index = {first_index!r}: needs an int, 0 <= first_index "
                             f"and first_index + {count} (the batch) <= 2**32")
        return list(range(int(first_index), int(first_index) + count))
    if hasattr(indices, "tolist"):  # a numpy, torch or CuPy array: its values as Python's
        indices = indices.tolist()
    if isinstance(indices, str) or not isinstance(indices, Sequence):
        raise ValueError(f"indices: one sample index per sample, a list or 1-D array of ints; "
                         f"got {indices!r}")
    if len(indices) != count:
        raise ValueError(f"indices: {len(indices)} sample indices for a batch of {count}; "
                         "give one per sample")
    for b, index in enumerate(indices):
        if not _whole(index) or not 0 <= index < 2**32:
            raise ValueError(f"indices[{b}] = {index!r}: a sample index is an int in "
                             "[0, 2**32); pass ints (a float index is not rounded)")
    return [int(index) for index in indices]


def _frame_count(count: int, scene: Scene) -> None:
    """Refuse a sample of mode average whose frame count is not the scene's ``blur.frames``."""
    wanted = scene.blur.frames
    if count != wanted:
        where = f"scene file {scene.path}" if scene.path else "the scene"
        raise ValueError(f"blur.frames = {wanted} ({where}) but this sample has {count} "
                         f"frames: pass {wanted}, or set blur.frames = {count}")


def _same_shape(images, names):
    for img, name in zip(images[1:], names[1:], strict=True):
        if img.shape != images[0].shape:
            raise ValueError(f"{name} is {img.shape[1]} x {img.shape[0]} (width x height) but "
                             f"{names[0]} is {images[0].shape[1]} x {images[0].shape[0]}; all "
                             "inputs of a sample must have the same size: crop or resize the "
                             "odd one, or leave it out")
