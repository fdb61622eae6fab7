"""Scene -> the ordered stages it calls for, each kept or skipped with its reason.

The stages follow the data flow of RSBlur's synthesis (Rim et al., ECCV 2022, supplementary
Fig. 7) and fall into three passes, which kernel backends fuse:

1. ``accumulate``: linearize the sRGB input and blur it (average frames, convolve a kernel, or
   warp along a camera-shake path), with the saturation mask;
2. ``to_raw``: saturation synthesis, lens vignetting, Lin2Cam, mosaic, inverse white balance,
   Poisson-Gaussian noise, white balance (pointwise);
3. ``finish``: demosaic (5 x 5 stencil), then pointwise Cam2Lin, tone curve, sRGB Gaussian
   noise, restore of saturated pixels, final re-toning and quantization.

After the passes the host crops the outputs (``crop``, :data:`Pass.HOST`): a cut of the
result, no kernel work; then, with ``output.jpeg_quality``, sends the blurred output through a
JPEG round trip (``jpeg``, :mod:`gpu_blur.outputs`), the same on every backend. Only kept
stages are run (and, in kernel backends, compiled). Stage and pass names are the
:class:`StageName` and :class:`Pass` constants (plain strings too, so a name from a scene or a
message compares equal). What a stage is (its pass, place, reference functions, cost switch and
values) is its row of :data:`gpu_blur.stages.STAGES`; :func:`plan` decides what the scene
makes of it: kept or skipped and why, the variant, the options.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from gpu_blur.constants import A7R3_CRF_TABLE_X255
from gpu_blur.reference.flow import INTERPOLATION_AUTO, MOTION_SCALE
from gpu_blur.reference.transfer import RETONE_CURVES, retone_polynomial
from gpu_blur.scene import FROM_NAME, Scene, load_scene
from gpu_blur.stages import PASSES, STAGES, Pass, StageName, stage_values

__all__ = ["PASSES", "Pass", "Plan", "Stage", "StageName", "plan", "raw_round_trip"]


@dataclasses.dataclass(frozen=True)
class Stage:
    """One step of the plan.

    Attributes:
        name: the stage's name, shared by the reference and every backend.
        pass_: the :class:`Pass` that runs it.
        kept: whether it runs.
        reason: why it is kept or skipped, in words.
        variant: which flavour runs (e.g. ``"malvar2004"``), or ``""``.
        options: the settings the stage reads (e.g. ``{"border": "reflect", "clip": False}``).
        values: scene numbers the pass's kernel takes as arguments for this stage, passed
            whether the stage runs or not (the kernel's signature does not change); they
            follow the kernel's own arguments in plan order
            (:func:`gpu_blur.backends.kernel.stage_values`). A new pointwise stage with a
            setting names its scene key in its row's
            :attr:`~gpu_blur.stages.StageSpec.values`, with no change to the backends.
    """

    name: str
    pass_: str
    kept: bool
    reason: str
    variant: str = ""
    options: dict = dataclasses.field(default_factory=dict)
    values: tuple[float, ...] = ()


@dataclasses.dataclass(frozen=True)
class Plan:
    """The ordered stages of a scene.

    Attributes:
        stages: the stages in data-flow order.
        fast_math: kernel backends may use fast float transcendentals (scene
            ``output.fast_math``): how the maths runs, not what it is, so no stage carries it
            and the reference ignores it.
    """

    stages: tuple[Stage, ...]
    fast_math: bool = False

    def kept(self, name: str) -> bool:
        """Whether stage ``name`` runs."""
        return self[name].kept

    def variant(self, name: str) -> str:
        """The variant of stage ``name``."""
        return self[name].variant

    def __getitem__(self, name: str) -> Stage:
        for stage in self.stages:
            if stage.name == name:
                return stage
        raise KeyError(f"no stage {name!r}; stages are {[s.name for s in self.stages]}")

    @property
    def raw_round_trip(self) -> bool:
        """Whether the image goes through camera RAW and back."""
        return self.kept(StageName.MOSAIC)

    @property
    def poisson_normal_above(self) -> float | None:
        """The Poisson rate above which shot-noise counts are a rounded normal, or None.

        None for ``noise.poisson = "exact"``; the ``normal_above`` argument of
        :func:`gpu_blur.reference.noise.add_poisson_gaussian`.
        """
        options = self[StageName.POISSON_GAUSSIAN_NOISE].options
        return options["normal_above"] if options["sampler"] == "normal" else None

    @property
    def retone_curve(self) -> str:
        """What the retone stage evaluates: ``"polynomial"``, ``"lookup"``, or ``""`` (skipped).

        ``output.crf`` ``"a7r3"`` and ``"camera"`` are polynomials, ``"a7r3-lut"`` a table
        (:data:`gpu_blur.reference.transfer.RETONE_CURVES`).
        """
        if not self.kept(StageName.RETONE):
            return ""
        return RETONE_CURVES[self[StageName.RETONE].options["crf"]]

    def retone_coefficients(self, camera) -> np.ndarray | None:
        """The camera's fitted response for ``output.crf = "camera"``, else None.

        The ``coefficients`` argument of :func:`gpu_blur.reference.transfer.retone`.

        Args:
            camera: the sample's :class:`gpu_blur.cameras.Camera`.

        Raises:
            ValueError: naming the camera and the fix when it has no fitted response.
        """
        if self.kept(StageName.RETONE) and self[StageName.RETONE].options["crf"] == "camera":
            return camera.fitted_response()
        return None

    def retone_polynomial(self, camera) -> np.ndarray | None:
        """c_0 ... c_K of the polynomial the retone stage evaluates, or None (no polynomial).

        The A7R3 fit for ``output.crf = "a7r3"``, the camera's fitted response for
        ``"camera"``: what kernel backends upload.
        """
        if self.retone_curve != "polynomial":
            return None
        return retone_polynomial(self[StageName.RETONE].options["crf"],
                                 self.retone_coefficients(camera))

    def __str__(self) -> str:
        width = max(len(s.name) for s in self.stages)
        vwidth = max(len(s.variant) for s in self.stages) + 2
        lines, current = [], None
        for s in self.stages:
            if s.pass_ != current:
                current = s.pass_
                lines.append(f"{current}:")
            mark = "run " if s.kept else "skip"
            variant = f"[{s.variant}]" if s.variant else ""
            lines.append(f"  {mark} {s.name:<{width}}  {variant:<{vwidth}}  {s.reason}")
        if self.fast_math:
            lines.append("kernels: fast float transcendentals (output.fast_math)")
        return "\n".join(lines)


def raw_round_trip(scene: Scene) -> bool:
    """Whether ``scene`` sends the image through camera RAW and back (:attr:`Plan.raw_round_trip`).

    Known before the sample's plan: its input is cut to even sizes first (the Bayer 2 x 2 cell).
    """
    return scene.noise.model == "poisson-gaussian" or scene.isp.round_trip == "always"


def plan(scene: Scene | str | Path | dict, *, saturated: bool | None = None,
         size: tuple[int, int] | None = None,
         interpolation_factors: tuple[int, ...] | None = None) -> Plan:
    """The stages ``scene`` calls for.

    Args:
        scene: validated settings, or what :func:`gpu_blur.scene.load_scene` takes (a TOML
            file, a built-in scene's name, a dict of sections).
        saturated: whether the sample's input reaches the clip level anywhere (its saturation
            mask is non-zero); ``None`` when not known yet. Only ``saturation.mode = "auto"``
            depends on it.
        size: the sample's (height, width) as the passes see it (after the even cut of the
            RAW round trip); ``None`` when not known yet. Vignetting is centred on it: a plan
            without it shows the stages but cannot run a kept vignetting stage.
        interpolation_factors: under ``blur.interpolation = "auto"``, each gap's factor
            measured on the sample (:func:`gpu_blur.backends.flows.scene_factors`); ``None``
            when not known yet. The blur stage shows them and carries them as its ``factors``.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    decided = {d[0]: d[1:] for d in (
        _decide(StageName.LINEARIZE, True, "sRGB input decoded with the sRGB EOTF"),
        _blur(scene.blur, interpolation_factors),
        *_saturation(scene.saturation.mode, saturated),
        _vignetting(float(scene.optics.vignetting)),
        *_raw_round_trip(scene),
        *_noise(scene.noise),
        *_output(scene),
    )}
    return Plan(tuple(Stage(spec.name, spec.pass_, *decided[spec.name],
                            values=stage_values(spec, scene, size)) for spec in STAGES),
                fast_math=scene.output.fast_math)


def _decide(name: str, kept, reason: str, variant: str = "", **options) -> tuple:
    """A stage's row of the plan as the scene decides it: (name, kept, reason, variant, options).

    Its pass, place and values come from its row of :data:`gpu_blur.stages.STAGES`.
    """
    return name, bool(kept), reason, variant, options


def _blur(b, interpolation_factors: tuple[int, ...] | None) -> tuple:
    """The blur stage for the scene's ``blur`` section."""
    blurring = b.mode != "none"
    named = b.frames == FROM_NAME  # yy of each sequence's name, GOPRxxxx_yy_zz
    frames = "yy" if named else b.frames
    if b.interpolation == INTERPOLATION_AUTO:
        average = (f"mean of {frames} linear frames and their saturation masks, each gap "
                   f"interpolated 1, 2, 4 or 8x ({b.flow} optical flow) to keep its motion, "
                   f"measured per sample at 1/{MOTION_SCALE} size, under "
                   f"{b.interpolation_tolerance:g} px a step"
                   + (f", in {b.interpolation_region} px squares that each get their own "
                      "factor (the gap's is their largest)" if b.interpolation_region else "")
                   + " (blur.interpolation = auto; the factors go to the sample's "
                   "interpolation_factors"
                   + (" and interpolation_regions)" if b.interpolation_region else ")"))
    elif b.interpolation > 1:
        total = (f"(yy - 1) x {b.interpolation} + 1" if named
                 else (b.frames - 1) * b.interpolation + 1)
        average = (f"mean of {total} linear frames and their "
                   f"saturation masks: {frames} frames and {b.interpolation - 1} interpolated "
                   f"in each gap ({b.interpolation}x frame rate, {b.flow} optical flow)")
    else:
        average = f"mean of {frames} linear frames and their saturation masks"
    if named:
        average += " (yy: each sequence's frames per blur, from its name GOPRxxxx_yy_zz)"
    options = {"interpolation": b.interpolation, "flow": b.flow} if b.mode == "average" else {}
    if options and b.interpolation == INTERPOLATION_AUTO:
        options["tolerance"] = float(b.interpolation_tolerance)
        options["region"] = int(b.interpolation_region)
        if interpolation_factors is not None:
            options["factors"] = tuple(int(f) for f in interpolation_factors)
            average += (f"; this sample's factors per gap: "
                        f"{', '.join(str(f) for f in options['factors'])}")
    return _decide(
        StageName.BLUR, blurring,
        {"average": average,
         "kernel": "one photo convolved with "
                   + (f"the kernel {b.kernel}" if b.kernel else "a random motion kernel"),
         "trajectory": "one photo warped along a camera-shake path of "
                       + (f"{b.steps} poses" if b.steps else "one pose per pixel of motion"),
         "none": "blur.mode = none: the input is already blurred"}[b.mode],
        b.mode if blurring else "", **options)


def _saturation(mode: str, saturated: bool | None) -> tuple[tuple, tuple]:
    """The saturate and restore_saturated stages for ``saturation.mode``.

    ``saturated`` is ``plan()``'s: the restore runs unless the input is known (``False``)
    not to reach the clip level.
    """
    if mode == "off":
        kept, reason = False, "saturation.mode = off"
    elif mode == "on":
        kept, reason = True, "saturation.mode = on"
    elif saturated is None:
        kept, reason = True, ("saturation.mode = auto: runs for samples with pixels at the clip "
                              "level")
    elif saturated:
        kept, reason = True, "saturation.mode = auto: input reaches the clip level"
    else:
        kept, reason = False, "saturation.mode = auto: no input pixel reaches the clip level"
    restore = mode == "on" or (mode == "auto" and saturated is not False)
    return (_decide(StageName.SATURATE, kept, reason),
            _decide(StageName.RESTORE_SATURATED, restore,
                    "channels saturated after synthesis set to exactly 1" if restore
                    else "no saturation stage"))


def _vignetting(strength: float) -> tuple:
    """The vignetting stage for ``optics.vignetting``."""
    return _decide(StageName.VIGNETTING, strength > 0,
                   f"linear image times 1 - {strength:g} (r / r_corner)^2 about the image centre"
                   if strength > 0 else "optics.vignetting = 0")


def _raw_round_trip(scene: Scene) -> tuple[tuple, ...]:
    """The RAW round trip's six stages (they run together), with the ``isp`` settings."""
    S, isp = StageName, scene.isp
    raw = raw_round_trip(scene)
    why = (("Poisson-Gaussian noise acts on the RAW mosaic"
            if scene.noise.model == "poisson-gaussian"
            else "isp.round_trip = always: demosaic artefacts asked for") if raw
           else f"noise.model = {scene.noise.model}: no RAW round trip")
    return (
        _decide(S.LINEAR_TO_CAMERA, raw, why, "clip" if raw and isp.clip_camera else "",
                clip=isp.clip_camera),
        _decide(S.MOSAIC, raw, why, isp.pattern if raw else ""),
        _decide(S.INVERSE_WHITE_BALANCE, raw, why),
        _decide(S.WHITE_BALANCE, raw, why),
        _decide(S.DEMOSAIC, raw, why,
                (isp.demosaic + (", clip" if isp.clip_demosaic else "")) if raw else "",
                method=isp.demosaic, border=isp.border, clip=isp.clip_demosaic),
        _decide(S.CAMERA_TO_LINEAR, raw, why),
    )


def _noise(n) -> tuple[tuple, tuple]:
    """The Poisson-Gaussian (RAW) and Gaussian (sRGB) noise stages for the ``noise`` section."""
    pg, normal = n.model == "poisson-gaussian", n.poisson == "normal"
    return (
        _decide(StageName.POISSON_GAUSSIAN_NOISE, pg,
                ("K * Poisson(x / K) + sigma_r * N(0, 1) on the mosaic"
                 + (f"; rates above {n.normal_above:g} drawn as a rounded normal"
                    if normal else "")) if pg else f"noise.model = {n.model}",
                f"normal above {n.normal_above:g}" if pg and normal else "",
                sampler=n.poisson, normal_above=float(n.normal_above)),
        _decide(StageName.GAUSSIAN_NOISE, n.model == "gaussian",
                "sRGB Gaussian noise, then clip" if n.model == "gaussian"
                else f"noise.model = {n.model}"),
    )


def _output(scene: Scene) -> tuple[tuple, ...]:
    """The tone, retone, quantize, crop and jpeg stages for the ``output`` section."""
    S, out = StageName, scene.output
    retone = out.crf in RETONE_CURVES
    nodes = out.crf_table_size or A7R3_CRF_TABLE_X255.size
    curve = {"a7r3": "the A7R3 polynomial",
             "a7r3-lut": f"the A7R3 lookup table ({nodes} nodes)",
             "camera": f"the fitted response (Eq. 6 polynomial, [response] of gpu-blur "
                       f"calibrate) of camera {scene.camera.name}"}.get(out.crf)
    quality = out.jpeg_quality
    return (
        _decide(S.TONE, out.crf != "none",
                "sRGB OETF, then clip to [0, 1]" if out.crf != "none"
                else "output.crf = none: output stays linear (clipped to [0, 1])"),
        _decide(S.RETONE, retone,
                f"output and sharp re-toned with {curve}" if retone
                else f"output.crf = {out.crf}: no re-toning",
                (out.crf + (f", {out.crf_table_size} nodes" if out.crf_table_size else ""))
                if retone else "",
                crf=out.crf, table_size=out.crf_table_size),
        _decide(S.QUANTIZE, out.bits > 0,
                f"{out.bits}-bit, round half up" if out.bits else "output.bits = 0: float output",
                bits=out.bits),
        _decide(S.CROP, out.crop > 0,
                f"{out.crop} px cut from every side of both outputs, on the host after the "
                "passes" if out.crop else "output.crop = 0"),
        _decide(S.JPEG, quality is not None,
                f"blurred output through a JPEG round trip (OpenCV, 4:2:0 chroma) at a quality "
                f"drawn in [{quality[0]}, {quality[1]}], on the host after the crop"
                if quality is not None else "output.jpeg_quality not set",
                "opencv, 4:2:0" if quality is not None else ""),
    )
