"""``synthesize``: one realistic blurred sample from sharp input, as a scene describes."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from gpu_blur.backends import get_backend, to_host
from gpu_blur.cameras import Camera, check_float32_response, get_camera
from gpu_blur.imageio import check_image, read_image, unit_values
from gpu_blur.params import draw_params
from gpu_blur.plan import Plan, StageName, plan, raw_round_trip
from gpu_blur.reference import transfer
from gpu_blur.reference.output import crop_border, quantize
from gpu_blur.scene import Scene, load_scene
from gpu_blur.scheduler import Schedule, run
from gpu_blur.timings import current, since, timer


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
            device on first use).
        params: every drawn value (see :data:`gpu_blur.params.DRAW_INDEX`).
        plan: the stages that ran.
        timings: seconds this call spent per :mod:`gpu_blur.timings` category (reading,
            copies, kernels, checks; writing is 0 here), plus ``other`` and ``total``.
        tiles: how many tiles the image ran in.
        spot_checks: how many of them were checked against the numpy reference.
        device: the device that made it, in words (the backend's ``device``).
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

    @property
    def mask(self) -> np.ndarray:
        """The blurred saturation mask, H x W x 3 float32 in [0, 1]."""
        if not isinstance(self._mask, np.ndarray):
            self._mask = crop_border(to_host(self._mask, np.float32), self.crop)
        return self._mask

    def __getstate__(self):  # a device array does not cross processes: fetch it first
        return {**self.__dict__, "_mask": self.mask}


def _as_scene(scene) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene)


def _load(item, what: str) -> np.ndarray:
    """An input as stored (uint8/uint16 codes, or float64 in [0, 1]), checked."""
    if isinstance(item, (str, Path)):
        return check_image(read_image(item), str(item))
    return check_image(np.asarray(item), what)


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
               max_device_memory: int | str | None = None, verify: float = 0.0) -> Synthesis:
    """Synthesize one realistic blurred image.

    Args:
        inputs: sharp sRGB input, H x W x 3 arrays in RGB order (OpenCV reads BGR: convert
            with ``cv2.cvtColor(x, cv2.COLOR_BGR2RGB)``; uint8, uint16 or float in [0, 1]) or
            image paths: a sequence of consecutive frames (blur mode ``average``; the middle
            one is the sharp reference), one photo (``kernel``, ``trajectory``), or for mode
            ``none`` a mapping ``{"blurred": ..., "mask": ... (optional), "sharp": ...}``.
        scene: a :class:`~gpu_blur.scene.Scene`, a path to a scene TOML, or None (defaults).
        seed: dataset seed (0 <= seed < 2**64).
        sample_index: index of this sample (0 <= index < 2**32); with ``seed`` it fixes every
            random draw.
        backend: ``"numpy"`` (the float64 reference), ``"opencl"`` (a GPU, else Intel's CPU
            runtime, else PoCL), ``"opencl:<platform>:<device>"``, ``"warp"`` (CUDA if
            present, else the CPU), ``"warp:cpu"`` or ``"warp:cuda:<n>"`` (see ``gpu-blur
            devices``), or a backend object from :func:`gpu_blur.backends.get_backend`.
        overrides: drawn parameters to fix instead (e.g. ``{"alpha": 1.0, "pattern": "RGGB"}``).
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

    Returns:
        A :class:`Synthesis`. Images whose RAW round trip needs even sizes lose their last
        row and/or column (the Bayer 2 x 2 cell rule).

    Raises:
        gpu_blur.scheduler.SpotCheckError: a spot-checked tile disagreed with the reference
            (a ``ValueError``), naming the sample, the tile and the error.
        ValueError: bad input or settings, naming the file or value.
    """
    start, before = time.perf_counter(), current().snapshot()
    if isinstance(tile, Schedule):
        if max_device_memory is not None or verify:
            raise ValueError("give max_device_memory and verify in the Schedule passed as "
                             "tile, or as arguments, not both")
        schedule = tile
    else:
        schedule = Schedule(tile, max_device_memory, verify)
    scene = _as_scene(scene)
    runner = (get_backend(backend, scene.output.precision) if isinstance(backend, str)
              else backend)
    camera = scene_camera(scene, runner.name)
    with timer("reading"):
        frames, mask, sharp = _gather(inputs, scene)

    h, w = frames[0].shape[:2]
    if raw_round_trip(scene):
        h, w = h - h % 2, w - w % 2
        if h < 2 or w < 2:
            raise ValueError(f"input of {frames[0].shape[:2]} is too small for the Bayer steps "
                             "(need at least 2 x 2)")
        frames = [f[:h, :w] for f in frames]
        sharp = sharp[:h, :w]
        mask = None if mask is None else mask[:h, :w]
    sample_plan = plan(scene, saturated=_reaches_clip_level(frames, mask), size=(h, w))

    # Every draw has a fixed index (gpu_blur.params), so a stage the sample skips (auto
    # saturation) never shifts another draw.
    if scene.saturation.mode == "auto" and not sample_plan.kept(StageName.SATURATE):
        # nothing to saturate in this sample: a fixed alpha has nothing to act on
        overrides = {k: v for k, v in (overrides or {}).items() if k != "alpha"}
    params = draw_params(scene, sample_plan, camera, seed=seed, sample_index=sample_index,
                         image_shape=(h, w), overrides=overrides)

    if on_device and (schedule.tile is not None or schedule.verify or scene.output.crop
                      or not runner.device_arrays):
        raise ValueError("on_device=True needs a backend that keeps results on a device "
                         "(warp), no tile, no verify and output.crop = 0")
    # how the passes run (tiles, halos, streamed frames, spot checks): gpu_blur.scheduler
    tiled = run(runner, sample_plan, params, camera, frames, mask, schedule, seed=seed,
                sample_index=sample_index, on_device=on_device)
    crop = scene.output.crop
    sharp_out = render_sharp(sample_plan, camera, crop_border(sharp, crop), runner)
    out = tiled.blurred if on_device else crop_border(tiled.blurred, crop)
    sat_mask = tiled.mask  # a backend's device array is fetched (and cropped) on first use
    if isinstance(sat_mask, np.ndarray):
        sat_mask = crop_border(sat_mask, crop).astype(np.float32, copy=False)
    return Synthesis(out, sharp_out, sat_mask, params,
                     sample_plan, since(before, time.perf_counter() - start), tiled.tiles,
                     tiled.checked, crop, runner.device)


def _reaches_clip_level(frames, mask) -> bool:
    """Whether any input pixel reaches the clip level (auto saturation runs only then)."""
    if mask is not None:
        return bool(np.any(np.asarray(mask) > 0))
    top = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}.get(frames[0].dtype, 1.0)
    return any(bool(np.any(f >= top)) for f in frames)


def render_sharp(sample_plan: Plan, camera: Camera, sharp: np.ndarray,
                 runner) -> np.ndarray:
    """The sharp reference as the output holds it: float32, quantized when the plan quantizes.

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
        runner: the backend (its host-side ``retone``).
    """
    coded = sharp.dtype in (np.uint8, np.uint16)
    values = unit_values(np.arange(np.iinfo(sharp.dtype).max + 1, dtype=sharp.dtype)
                         if coded else sharp)
    rendered = _render_values(sample_plan, camera, values, runner)
    if sample_plan.kept(StageName.QUANTIZE):
        rendered = quantize(rendered, sample_plan[StageName.QUANTIZE].options["bits"])
    rendered = rendered.astype(np.float32)
    return rendered[sharp] if coded else rendered


def _render_values(sample_plan: Plan, camera: Camera, values: np.ndarray,
                   runner) -> np.ndarray:
    """:func:`render_sharp`'s curve on float64 sRGB values in [0, 1], any shape."""
    if not sample_plan.kept(StageName.TONE):
        return np.clip(transfer.srgb_to_linear(values), 0.0, 1.0)
    return runner.retone(sample_plan, camera, values)


def _gather(inputs, scene: Scene):
    """(frames, mask, sharp), validated against the blur mode.

    Frames and sharp keep their stored dtype (uint8/uint16 codes, or float64 in [0, 1]; one
    dtype per sample: mixed inputs become float64); the mask is float64 in [0, 1].
    """
    mode = scene.blur.mode
    if mode == "none":
        if not isinstance(inputs, Mapping) or "blurred" not in inputs:
            raise ValueError("blur.mode = none takes a mapping {'blurred': image, 'mask': "
                             "optional mask, 'sharp': optional sharp image}")
        blurred = _load(inputs["blurred"], "blurred image")
        mask = None if inputs.get("mask") is None else _load(inputs["mask"], "mask")
        sharp = blurred if inputs.get("sharp") is None else _load(inputs["sharp"], "sharp")
        given = [(blurred, _name(inputs["blurred"], "blurred"))]
        given += [(x, _name(inputs[k], k)) for x, k in ((mask, "mask"), (sharp, "sharp"))
                  if inputs.get(k) is not None]
        _same_shape([x for x, _ in given], [n for _, n in given])
        return [blurred], None if mask is None else unit_values(mask), sharp
    if isinstance(inputs, (str, Path, np.ndarray)):
        inputs = [inputs]
    if not isinstance(inputs, Sequence) or len(inputs) == 0:
        raise ValueError(f"blur.mode = {mode} needs a non-empty list of images")
    if mode != "average" and len(inputs) != 1:
        raise ValueError(f"blur.mode = {mode} blurs one photo; got {len(inputs)} images")
    frames = [_load(x, f"frame {i}") for i, x in enumerate(inputs)]
    _same_shape(frames, [_name(x, f"frame {i}") for i, x in enumerate(inputs)])
    if len({f.dtype for f in frames}) > 1:
        frames = [unit_values(f) for f in frames]
    return frames, None, frames[len(frames) // 2]


def _same_shape(images, names):
    for img, name in zip(images[1:], names[1:], strict=True):
        if img.shape != images[0].shape:
            raise ValueError(f"{name} is {img.shape[1]} x {img.shape[0]} (width x height) but "
                             f"{names[0]} is {images[0].shape[1]} x {images[0].shape[0]}; all "
                             "inputs of a sample must have the same size: crop or resize the "
                             "odd one, or leave it out")
