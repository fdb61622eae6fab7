"""Checks of whole samples: tiled against untiled, and each built-in scene through the pipeline.

Registered into :data:`gpu_blur.conformance.checks.CHECKS` (and, one device against another,
:data:`~gpu_blur.conformance.checks.AGAINST`) on import, in the order ``gpu-blur validate``
runs them.
"""

from __future__ import annotations

import functools

import numpy as np

import gpu_blur
from gpu_blur import files
from gpu_blur.conformance import SAMPLE, SEED, coffee, coffee_crop, scene_for, seam_image
from gpu_blur.conformance.checks import (
    AGAINST,
    CHECKS,
    REFERENCE,
    Check,
    Outcome,
    Target,
    check,
    exact,
    holds,
    within,
)
from gpu_blur.scene import SceneError, builtin_scenes

__all__: list[str] = []

# -- tiles ---------------------------------------------------------------------------------------

def _synthesize(t: Target, backend, inputs, settings: dict, **kwargs):
    scene = scene_for(t.precision, settings)
    return gpu_blur.synthesize(inputs, scene, seed=SEED, sample_index=SAMPLE, backend=backend,
                               **kwargs)


@check("tiles: tiled equals untiled, bit for bit", quick=True)
def _tiled(t: Target) -> list[Outcome]:
    photo = coffee_crop(slice(230, 310), slice(320, 420))
    settings = {"blur": {"mode": "trajectory"}, "output": {"bits": 0}}
    whole = _synthesize(t, t.backend, [photo], settings)
    out = []
    for tile in ((17, 19), (33, 50)):
        tiled = _synthesize(t, t.backend, [photo], settings, tile=tile)
        why = f"every pass computes each pixel from global coordinates (tile {tile})"
        out += [exact("blurred", tiled.blurred, whole.blurred, why),
                exact("mask", tiled.mask, whole.mask, why)]
    return out


@check("tiles: saturated pixels on tile seams and corners")
def _seams(t: Target) -> list[Outcome]:
    out = []
    for case in ("corner", "seams"):
        image = seam_image(case, 16)
        settings = {"blur": {"extent": [3.0, 6.0]}, "saturation": {"mode": "on"},
                    "output": {"bits": 0}}
        whole = _synthesize(t, t.backend, [image], settings)
        tiled = _synthesize(t, t.backend, [image], settings, tile=(16, 16))
        why = f"saturation spreads across tiles ({case}), each pixel from global coordinates"
        out += [exact("blurred", tiled.blurred, whole.blurred, why),
                exact("mask", tiled.mask, whole.mask, why)]
    return out


# -- whole pipeline ------------------------------------------------------------------------------

def _scene_settings(name: str) -> dict:
    path = builtin_scenes()[name]
    return files.read_settings(path, f"scene file {path}")


def _scene_inputs(settings: dict):
    """Inputs for a scene's blur mode: a photo, shifted crops of it (average) or it blurred.

    Mode ``none`` takes the photo as its already blurred image.
    """
    photo = coffee_crop(slice(150, 310), slice(250, 450))
    mode = settings.get("blur", {}).get("mode")
    if mode == "none":
        return {"blurred": photo}
    if mode != "average":
        return [photo]
    n = settings["blur"].get("frames", 9)
    return [np.roll(photo, (i - n // 2, 2 * (i - n // 2)), axis=(0, 1)) for i in range(n)]


def _pipeline(t: Target, settings: dict, noisy: bool) -> list[Outcome]:
    inputs = _scene_inputs(settings)
    got = _synthesize(t, t.backend, inputs, settings).blurred
    ref = _synthesize(t, REFERENCE, inputs, settings).blurred
    bits = settings.get("output", {}).get("bits", 8)
    if noisy:
        return [within("pipeline_noisy", t, got, ref, outliers="pipeline_noisy_outliers")]
    # The A7R3 polynomial's float32 Horner sum dominates the pipeline's error where a scene
    # re-tones with it: its finish-pass row is the claim there.
    stage = "finish_crf_polynomial" if settings.get("output", {}).get("crf") == "a7r3" \
        else "pipeline"
    if not bits:
        return [within(stage, t, got, ref)]
    top = 2**bits - 1
    moved = np.abs(np.rint(got * top) - np.rint(ref * top))
    return [within(stage, t, got, ref, accept=moved == 1),
            within("quantize_code_changes", t, (moved > 0).mean(), 0.0)]


def _scene_check(t: Target, scene: str, noisy: bool) -> list[Outcome]:
    settings = _scene_settings(scene)
    if not noisy:
        settings["noise"] = {"model": "none"}
    return _pipeline(t, settings, noisy)


for _scene in builtin_scenes():
    for _noisy in (False, True):
        CHECKS.append(Check(
            f"pipeline: scene {_scene}" + (", as shipped" if _noisy else ", noise off"),
            functools.partial(_scene_check, scene=_scene, noisy=_noisy),
            quick=_scene == "minimal" and not _noisy))


@check("pipeline: output.fast_math within its row", kernels_only=True)
def _fast_math(t: Target) -> list[Outcome]:
    """The fast sRGB curves and normals: their accuracy is the runtime's (OpenCL native_)."""
    settings = {"blur": {"mode": "trajectory"}, "saturation": {"mode": "on"},
                "noise": {"model": "gaussian"}, "isp": {"round_trip": "always"},
                "output": {"bits": 0, "fast_math": True}}
    if t.precision != "float32":
        try:
            scene_for(t.precision, settings)
        except SceneError:
            return [holds(True, "refused: fast functions exist for float only")]
        return [holds(False, "refused: fast functions exist for float only")]
    photo = [coffee_crop()]
    got = _synthesize(t, t.backend, photo, settings).blurred
    settings["output"]["fast_math"] = False
    ref = _synthesize(t, REFERENCE, photo, settings).blurred
    return [within("pipeline_fast_math", t, got, ref)]


@check("pipeline: all-white frames give exactly white")
def _white(t: Target) -> list[Outcome]:
    out = []
    for crf in ("srgb", "a7r3"):
        got = _synthesize(t, t.backend, [np.ones((16, 24, 3))],
                          {"blur": {"extent": [2.0, 8.0]}, "output": {"bits": 0, "crf": crf}})
        out.append(holds(np.all(got.blurred == 1.0),
                         f"all exactly 1 (crf {crf})"))
    return out


@check("pipeline: odd and tiny image sizes")
def _odd_shapes(t: Target) -> list[Outcome]:
    out = []
    for shape in ((2, 2), (7, 5), (5, 8)):
        image = coffee()[200:200 + shape[0], 330:330 + shape[1]]
        settings = {"blur": {"mode": "kernel", "kernel_size": [5, 9]},
                    "noise": {"model": "none"}, "saturation": {"mode": "on"},
                    "isp": {"round_trip": "always"}, "output": {"bits": 0}}
        got = _synthesize(t, t.backend, [image], settings).blurred
        ref = _synthesize(t, REFERENCE, [image], settings).blurred
        out.append(within("pipeline", t, got, ref))
    return out


# -- one device against another (validate --against) --------------------------------------------

def _against_scene(a: Target, b: Target, scene: str) -> list[Outcome]:
    settings = _scene_settings(scene)
    settings["noise"] = {"model": "none"}
    settings.setdefault("output", {})["bits"] = 0  # values, not codes: the row is on values
    inputs = _scene_inputs(settings)
    got = _synthesize(a, a.backend, inputs, settings).blurred
    other = _synthesize(b, b.backend, inputs, settings).blurred
    cross = Target(a.backend, "kernels", a.precision)  # the table's "kernels" column
    polynomial = settings.get("output", {}).get("crf") == "a7r3"
    return [within("cross_backend_crf_polynomial" if polynomial else "cross_backend", cross,
                   got, other)]


AGAINST.extend(Check(f"pipeline: scene {s}, noise off, float output",
                     functools.partial(_against_scene, scene=s)) for s in builtin_scenes())
