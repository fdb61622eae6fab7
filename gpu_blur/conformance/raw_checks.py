"""Checks of the to_raw and finish passes: camera colour, mosaic, noise, demosaics, curves.

Registered into :data:`gpu_blur.conformance.checks.CHECKS` on import, in the order
``gpu-blur validate`` runs them.
"""

from __future__ import annotations

import functools

import numpy as np

from gpu_blur.backends import to_host
from gpu_blur.cameras import get_camera
from gpu_blur.conformance import (
    OUT_OF_GAMUT,
    SAMPLE,
    SEED,
    coffee,
    coffee_crop,
    on_device,
    prepare,
    scene_for,
)
from gpu_blur.conformance.checks import (
    CHECKS,
    REFERENCE,
    Check,
    Outcome,
    Target,
    check,
    holds,
    within,
)
from gpu_blur.params import draw_params
from gpu_blur.planning import plan
from gpu_blur.reference import bayer
from gpu_blur.tiling import Region

__all__ = ["FINISH_CASES"]


def _to_raw(t: Target, settings, linear, mask, *, camera="a7r3", overrides=None, origin=(0, 0)):
    """(device, reference) outputs of the to_raw pass: ((raw, sat), (raw, sat))."""
    p, cam, params = prepare(t.precision, settings, linear.shape[:2], camera=camera,
                             overrides=overrides)
    run = dict(seed=SEED, sample_index=SAMPLE)
    got = t.backend.to_raw(p, params, cam, linear, mask, origin, **run)
    ref = REFERENCE.to_raw(p, params, cam, linear, mask, origin, **run)
    return tuple(map(to_host, got)), tuple(map(to_host, ref))


@check("to_raw: Lin2Cam, mosaic, WB, saturation (no noise)", quick=True)
def _to_raw_quiet(t: Target) -> list[Outcome]:
    photo = coffee_crop()
    out = []
    for camera, clip in (("a7r3", False), ("rsblur-0005", True)):
        settings = {"noise": {"model": "none"}, "saturation": {"mode": "on"},
                    "isp": {"round_trip": "always", "clip_camera": clip}}
        (raw, sat), (ref_raw, ref_sat) = _to_raw(
            t, settings, photo ** 2.2, (photo >= 0.99).astype(np.float64), camera=camera,
            origin=(3, 5))
        out += [within("to_raw", t, raw, ref_raw), within("saturate", t, sat, ref_sat),
                holds(np.array_equal(sat >= 1, ref_sat >= 1),
                      "the restore decision agrees")]
    return out


@check("to_raw: vignetting")
def _vignetting(t: Target) -> list[Outcome]:
    photo = coffee_crop(slice(220, 268), slice(300, 364))
    settings = {"optics": {"vignetting": 0.6}, "saturation": {"mode": "on"},
                "noise": {"model": "none"}, "isp": {"round_trip": "always"}}
    h, w = photo.shape[:2]
    scene = scene_for(t.precision, settings)
    p = plan(scene, saturated=True, size=(h + 9, w + 14))
    cam = get_camera("a7r3")
    params = draw_params(scene, p, cam, seed=SEED, sample_index=SAMPLE, image_shape=(h, w))
    linear, mask = photo ** 2.2, (photo >= 0.99).astype(np.float64)
    run = dict(seed=SEED, sample_index=SAMPLE)
    raw, sat = map(to_host, t.backend.to_raw(p, params, cam, linear, mask, (3, 5), **run))
    ref_raw, ref_sat = REFERENCE.to_raw(p, params, cam, linear, mask, (3, 5), **run)
    return [within("to_raw", t, raw, ref_raw), within("saturate", t, sat, ref_sat)]


@check("to_raw: negative camera values (out-of-gamut colours)")
def _negative_camera(t: Target) -> list[Outcome]:
    linear = on_device(t.precision, np.tile(OUT_OF_GAMUT, (4, 2, 1)).reshape(8, 6, 3))
    out = []
    for clip in (False, True):
        settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                    "noise": {"model": "none"},
                    "isp": {"round_trip": "always", "clip_camera": clip}}
        (raw, _), (ref, _) = _to_raw(t, settings, linear, np.zeros_like(linear),
                                     overrides={"pattern": "GRBG"})
        out.append(within("to_raw", t, raw, ref))
    return out


@check("to_raw: white balance cancels (identity camera)")
def _white_balance(t: Target) -> list[Outcome]:
    linear = on_device(t.precision, np.random.default_rng(3).uniform(0, 1.2, (6, 8, 3)))
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                "noise": {"model": "none"}, "isp": {"round_trip": "always"}}
    out = []
    for pattern, red, blue, origin in (("RGGB", 0.25, 8.0, (0, 0)), ("GBRG", 3.7, 0.61, (1, 2)),
                                       ("BGGR", 1.9, 1.5, (3, 3))):
        (raw, _), _ = _to_raw(t, settings, linear, np.zeros_like(linear), camera="srgb",
                              origin=origin, overrides={"pattern": pattern, "red_gain": red,
                                                        "blue_gain": blue})
        out.append(within("white_balance_round_trip", t, raw,
                          bayer.mosaic(linear, bayer.BayerPattern(pattern), origin)))
    return out


@check("to_raw: Poisson-Gaussian noise on a photo", quick=True)
def _to_raw_noisy(t: Target) -> list[Outcome]:
    # the whole photo: a row allowing 1e-4 of values needs many values to be a fraction
    photo = np.ascontiguousarray(coffee())
    (raw, _), (ref, _) = _to_raw(t, {}, np.ascontiguousarray(photo ** 2.2), np.zeros_like(photo))
    return [within("to_raw", t, raw, ref, outliers="to_raw_noisy_outliers")]


#: Finish-pass settings, one case each: the demosaics, borders, curves, noise and quantization.
FINISH_CASES = [
    ("Malvar, reflect border", {"isp": {"demosaic": "malvar2004", "border": "reflect"}}),
    ("Malvar, zero border, clipped",
     {"isp": {"demosaic": "malvar2004", "border": "zero", "clip_demosaic": True}}),
    ("bilinear, A7R3 polynomial", {"isp": {"demosaic": "bilinear"}, "output": {"crf": "a7r3"}}),
    ("A7R3 table", {"output": {"crf": "a7r3-lut"}}),
    ("no curve", {"output": {"crf": "none"}}),
    ("sRGB Gaussian noise", {"noise": {"model": "gaussian"}}),
    ("8 bits", {"output": {"bits": 8}}),
    ("16 bits, A7R3 table", {"output": {"bits": 16, "crf": "a7r3-lut"}}),
]


def _finish_case(t: Target, extra: dict) -> list[Outcome]:
    photo = coffee_crop()
    h, w = photo.shape[:2]
    settings = {"saturation": {"mode": "on"}, "noise": {"model": "none"},
                "isp": {"round_trip": "always"}, "output": {"bits": 0}}
    for section, values in extra.items():
        settings.setdefault(section, {}).update(values)
    p, cam, params = prepare(t.precision, settings, (h, w))
    linear = np.ascontiguousarray(photo ** 2.2)
    image, sat = REFERENCE.to_raw(p, params, cam, linear, (photo >= 0.99).astype(np.float64),
                                  seed=SEED, sample_index=SAMPLE)
    view, out = Region.whole(h, w), Region(5, 6, h - 9, w - 13, h, w)
    run = dict(seed=SEED, sample_index=SAMPLE)
    got = to_host(t.backend.finish(p, params, cam, image, sat, view, out, **run))
    ref = to_host(REFERENCE.finish(p, params, cam, image, sat, view, out, **run))
    if p.kept("quantize"):
        top = 2 ** p["quantize"].options["bits"] - 1
        moved = np.abs(np.rint(got * top) - np.rint(ref * top))
        return [within("quantize_code_changes", t, (moved > 0).mean(), 0.0),
                holds(moved.max() <= 1, "at most one code apart",
                      f"codes differ by up to {moved.max():g}")]
    polynomial = p.kept("retone") and p["retone"].options["crf"] == "a7r3"
    return [within("finish_crf_polynomial" if polynomial else "finish", t, got, ref)]


for _label, _extra in FINISH_CASES:
    CHECKS.append(Check(f"finish: {_label}",
                        functools.partial(_finish_case, extra=_extra),
                        quick=_label in ("Malvar, reflect border", "8 bits")))


@check("to_raw + finish: a flat colour comes back flat")
def _flat_field(t: Target) -> list[Outcome]:
    out = []
    for colour, red, blue, pattern, method in (((0.2, 0.5, 0.9), 2.1, 1.7, "RGGB", "malvar2004"),
                                               ((0.9, 0.01, 0.4), 0.6, 3.9, "GRBG", "bilinear")):
        shape = (6, 8)
        flat = np.broadcast_to(on_device(t.precision, colour), (*shape, 3)).copy()
        settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                    "noise": {"model": "none"},
                    "isp": {"round_trip": "always", "demosaic": method},
                    "output": {"bits": 0, "crf": "none"}}
        p, cam, params = prepare(t.precision, settings, shape, camera="srgb", overrides={
            "pattern": pattern, "red_gain": red, "blue_gain": blue})
        run = dict(seed=SEED, sample_index=SAMPLE)
        raw, sat = t.backend.to_raw(p, params, cam, flat, np.zeros_like(flat), **run)
        whole = Region.whole(*shape)
        got = t.backend.finish(p, params, cam, raw, sat, whole, whole, **run)
        out.append(within("flat_field_passes", t, got, flat))
    return out
