"""The stages, declared once: their names, passes, reference functions and cost switches.

:data:`STAGES` holds one :class:`StageSpec` per :class:`StageName`, in data-flow order. What a
stage is, as opposed to whether a scene runs it, is read from here: :func:`gpu_blur.planning.plan`
takes each stage's pass, its place in the plan and its kernel values from its row (and decides
only kept or skipped, why, the variant and the options), and
:data:`gpu_blur.analysis.stage_cost.SWITCHES` groups the stages by their cost switch.
``tests/synthesis/test_stage_registry.py`` fails when a stage lacks a row or a row lacks a part.

This module imports nothing of the package: the reference functions are dotted names, which
that test resolves.
"""

from __future__ import annotations

import dataclasses
import enum

__all__ = ["PASSES", "Pass", "SIZE", "STAGES", "StageName", "StageSpec", "stage_values"]


class Pass(enum.StrEnum):
    """Where a stage runs: one of the three kernel passes, or the host after them."""

    ACCUMULATE = "accumulate"
    TO_RAW = "to_raw"
    FINISH = "finish"
    HOST = "host"


#: The kernel passes, in order (every backend runs these; :data:`Pass.HOST` stages run in
#: gpu_blur.synthesis on the passes' result).
PASSES = (Pass.ACCUMULATE, Pass.TO_RAW, Pass.FINISH)


class StageName(enum.StrEnum):
    """The stages, in data-flow order.

    The one spelling the reference, every backend and the scheduler use.
    """

    LINEARIZE = "linearize"
    BLUR = "blur"
    SATURATE = "saturate"
    VIGNETTING = "vignetting"
    LINEAR_TO_CAMERA = "linear_to_camera"
    MOSAIC = "mosaic"
    INVERSE_WHITE_BALANCE = "inverse_white_balance"
    POISSON_GAUSSIAN_NOISE = "poisson_gaussian_noise"
    WHITE_BALANCE = "white_balance"
    DEMOSAIC = "demosaic"
    CAMERA_TO_LINEAR = "camera_to_linear"
    TONE = "tone"
    GAUSSIAN_NOISE = "gaussian_noise"
    RESTORE_SATURATED = "restore_saturated"
    RETONE = "retone"
    QUANTIZE = "quantize"
    CROP = "crop"
    JPEG = "jpeg"


#: In :attr:`StageSpec.values`: the sample's (height, width) as the passes see it, two numbers
#: (``plan(scene, size=...)``; None each while the size is not known).
SIZE = "size"


@dataclasses.dataclass(frozen=True)
class StageSpec:
    """What a stage is, whatever the scene.

    Attributes:
        name: the stage.
        pass_: the :class:`Pass` that runs it.
        reference: the dotted names of the float64 functions it runs (one per variant where
            the variants differ): what the numpy backend calls and kernel backends match.
        switch: its cost switch (:data:`gpu_blur.analysis.stage_cost.SWITCHES`; stages that
            only run together share one), or None for a stage not timed on its own: the
            accumulate pass is timed whole, host stages are no kernel work.
        values: where its kernel values (:attr:`gpu_blur.planning.Stage.values`) come from, in
            order: scene keys (``"section.key"``, each one number) and :data:`SIZE` (two).
    """

    name: StageName
    pass_: Pass
    reference: tuple[str, ...]
    switch: str | None
    values: tuple[str, ...] = ()


_REF = "gpu_blur.reference."
S, P = StageName, Pass
_RAW = "raw round trip"

#: Every stage, in data-flow order (the order of :class:`StageName` and of a plan).
STAGES: tuple[StageSpec, ...] = (
    StageSpec(S.LINEARIZE, P.ACCUMULATE, (_REF + "transfer.image_to_linear",), None),
    StageSpec(S.BLUR, P.ACCUMULATE,
              (_REF + "average.FrameAccumulator", _REF + "interpolate.interpolated_average",
               _REF + "motion_kernel.convolve_kernel", _REF + "shake.shake_blur"), None),
    StageSpec(S.SATURATE, P.TO_RAW, (_REF + "saturation.synthesize_saturation",), "saturation"),
    StageSpec(S.VIGNETTING, P.TO_RAW, (_REF + "optics.vignette",), "vignetting",
              values=("optics.vignetting", SIZE)),
    StageSpec(S.LINEAR_TO_CAMERA, P.TO_RAW, (_REF + "color.apply_matrix",), _RAW),
    StageSpec(S.MOSAIC, P.TO_RAW, (_REF + "bayer.mosaic",), _RAW),
    StageSpec(S.INVERSE_WHITE_BALANCE, P.TO_RAW, (_REF + "bayer.inverse_white_balance",), _RAW),
    StageSpec(S.POISSON_GAUSSIAN_NOISE, P.TO_RAW, (_REF + "noise.add_poisson_gaussian",),
              "poisson_gaussian_noise"),
    StageSpec(S.WHITE_BALANCE, P.TO_RAW, (_REF + "bayer.white_balance",), _RAW),
    StageSpec(S.DEMOSAIC, P.FINISH,
              (_REF + "demosaic.demosaic_malvar2004", _REF + "demosaic.demosaic_bilinear"), _RAW),
    StageSpec(S.CAMERA_TO_LINEAR, P.FINISH, (_REF + "color.apply_matrix",), _RAW),
    StageSpec(S.TONE, P.FINISH, (_REF + "transfer.linear_to_srgb",), "tone"),
    StageSpec(S.GAUSSIAN_NOISE, P.FINISH, (_REF + "noise.add_gaussian_srgb",), "gaussian_noise"),
    StageSpec(S.RESTORE_SATURATED, P.FINISH, (_REF + "saturation.restore_saturated",),
              "saturation"),
    StageSpec(S.RETONE, P.FINISH, (_REF + "transfer.retone",), "retone"),
    StageSpec(S.QUANTIZE, P.FINISH, (_REF + "output.quantize",), "quantize"),
    StageSpec(S.CROP, P.HOST, (_REF + "output.crop_border",), None),
    StageSpec(S.JPEG, P.HOST, ("gpu_blur.outputs.jpeg_round_trip",), None),
)
del S, P


def stage_values(spec: StageSpec, scene, size: tuple[int, int] | None) -> tuple:
    """The numbers ``spec.values`` names, read from ``scene`` and ``size`` (floats, or None).

    Args:
        spec: the stage's row.
        scene: a :class:`gpu_blur.scene.Scene`.
        size: the sample's (height, width), or None when not known yet.
    """
    values = []
    for key in spec.values:
        if key == SIZE:
            values += [float(n) for n in size] if size else [None, None]
        else:
            section, name = key.split(".")
            values.append(float(getattr(getattr(scene, section), name)))
    return tuple(values)
