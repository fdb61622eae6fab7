"""What ``gpu-blur validate`` runs: each check of a device against the float64 reference.

A check runs one conformance case (:mod:`gpu_blur.conformance`) on a device at a precision and
gives one :class:`Outcome` per comparison: the measured error against the tolerance table's
row (:data:`gpu_blur.tolerances.TOLERANCES`, the rows the test suite uses) or bit for bit where
the claim is exact. :func:`validate` runs a list of checks and collects them.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import math
from collections.abc import Callable

import numpy as np

import gpu_blur
from gpu_blur import files, tolerances
from gpu_blur.backends import to_host
from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.cameras import get_camera
from gpu_blur.conformance import (
    A7R3_DIP_POINTS,
    A7R3_POLYNOMIAL_POINTS,
    OUT_OF_GAMUT,
    POSES_LEAVING_THE_IMAGE,
    SAMPLE,
    SEED,
    StreamedFrames,
    coffee,
    decode_on,
    finish_on,
    on_device,
    prepare,
    scene_for,
    seam_image,
    transfer_points,
)
from gpu_blur.params import draw_params
from gpu_blur.plan import plan
from gpu_blur.reference import bayer, rng, transfer
from gpu_blur.scene import SceneError, builtin_scenes
from gpu_blur.tiling import Region

REFERENCE = NumpyBackend()


# -- results -----------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Outcome:
    """One comparison of a check.

    Attributes:
        check: the check's name (``accumulate: blur mode kernel, photo``); :func:`run_check`
            fills it in.
        stage: what is compared: the tolerance row's stage, or a name for an exact claim.
        measured: the largest absolute error, or for outlier rows the fraction of values out
            of tolerance; None when the check did not run.
        tolerance: the claim in words (``rtol 0, atol 1e-06``, ``bit for bit``).
        row: the tolerance row ``"stage/backend/dtype"``, or None for an exact claim.
        source: where the row is (``gpu_blur/tolerances.py:231``) or why the claim is exact.
        passed: True, False, or None when skipped (``detail`` says why).
        detail: the first mismatch, or why the check was skipped.
    """

    check: str
    stage: str
    measured: float | None
    tolerance: str
    row: str | None
    source: str
    passed: bool | None
    detail: str = ""


@dataclasses.dataclass(frozen=True)
class Target:
    """A device under test at one precision: its backend and the table's backend column."""

    backend: object
    family: str  # numpy, opencl or warp: the tolerance table's backend column
    precision: str

    @property
    def kernels(self) -> bool:
        """Whether it is a kernel device (not the numpy reference)."""
        return self.family != "numpy"


@functools.cache
def row_sources() -> dict[tuple[str, str, str], tuple[int, str]]:
    """Each tolerance row's (line in gpu_blur/tolerances.py, comment stating its claim).

    Rows written one by one carry their own line; rows made by a comprehension carry the line
    of their stage in it. The claim is the row's end-of-line comment, else the comment block
    above it.
    """
    text = inspect.getsource(tolerances)
    lines = text.splitlines()
    tree = ast.parse(text)
    table = next(n.value for n in tree.body if isinstance(n, ast.AnnAssign)
                 and getattr(n.target, "id", "") == "TOLERANCES")
    found: dict = {}
    for key, value in zip(table.keys, table.values, strict=True):
        if key is not None:  # ("stage", "backend", "dtype"): (rtol, atol)
            found[ast.literal_eval(key)] = key.lineno
            continue
        namespace = vars(tolerances)
        for row in eval(compile(ast.Expression(value), "tolerances", "eval"), namespace):
            found[row] = _line_in(value, row)
    return {row: (line, _claim(lines, line)) for row, line in found.items()}


def _line_in(node: ast.AST, row: tuple[str, str, str]) -> int:
    """The line of ``row``'s stage inside a comprehension of the table (its own, else 1st)."""
    stage, _, dtype = row
    best = node.lineno
    for item in ast.walk(node):
        if isinstance(item, ast.Tuple) and all(isinstance(e, ast.Constant) for e in item.elts):
            values = [e.value for e in item.elts]
            if values[:1] == [stage] and (len(values) < 2 or values[-1] == dtype):
                return item.lineno
        if isinstance(item, ast.Constant) and item.value == stage:
            best = item.lineno
    return best


def _claim(lines: list[str], line: int) -> str:
    """The comment on ``line`` (1-based), else the block of comment lines above it."""
    own = lines[line - 1].partition("#")[2].strip()
    if own:
        return own
    above = []
    for text in reversed(lines[:line - 1]):
        if not text.strip().startswith("#"):
            break
        above.insert(0, text.strip().lstrip("#").strip())
    return " ".join(above)


def _row(stage: str, target: Target, dtype: str | None = None) -> tuple[str, str, str]:
    return (stage, target.family, dtype or target.precision)


def _tolerance_text(key) -> str:
    rtol, atol = tolerances.tolerance(*key)
    return f"rtol {rtol:g}, atol {atol:g}"


def _source(key) -> str:
    line, _ = row_sources().get(key, (0, ""))
    return f"gpu_blur/tolerances.py:{line}"


def within(stage: str, target: Target, actual, expected, *, outliers: str = "",
           accept=None, dtype: str | None = None) -> Outcome:
    """``actual`` against ``expected`` under the row ``(stage, target's backend, precision)``.

    Args:
        stage: the row's stage.
        target: the device; its backend and precision give the row's other columns.
        actual: the device's values.
        expected: the reference's values (same shape).
        outliers: a row whose atol is the fraction of values allowed outside the tolerance
            (``to_raw_noisy_outliers``); the measured number is then that fraction.
        accept: boolean array of values accepted whatever their error (a one-code change at a
            quantization boundary, counted under its own row by the caller).
        dtype: the row's dtype column when not the target's precision (``float32-fast``).
    """
    key = _row(stage, target, dtype)
    actual = np.asarray(to_host(actual), dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    rtol, atol = tolerances.tolerance(*key)
    tolerance = _tolerance_text(key)
    source = _source(key)
    if actual.shape != expected.shape:
        return Outcome("", stage, None, tolerance, "/".join(key), source, False,
                       f"shape {actual.shape} != reference {expected.shape}")
    finite = np.isfinite(actual)
    err = np.where(finite, np.abs(actual - expected), np.inf)
    bad = ~(err <= atol + rtol * np.abs(expected))
    if accept is not None:
        bad &= ~accept
    allowed = tolerances.tolerance(*_row(outliers, target, dtype))[1] if outliers else 0.0
    problem = tolerances.mismatch(actual, expected, *key, allowed_fraction=allowed, accept=accept)
    if not finite.all():
        problem = f"{int((~finite).sum())} values are not finite"
    if outliers:
        okey = _row(outliers, target, dtype)
        measured = float(bad.mean()) if bad.size else 0.0
        tolerance += f"; {allowed:g} of values may miss"
        source += f", {_source(okey).rpartition(':')[2]}"
    else:  # the largest error, leaving out values the caller accepts
        measured = float(np.max(err if accept is None else np.where(accept, 0.0, err),
                                initial=0.0))
    return Outcome("", stage, measured, tolerance, "/".join(key), source, problem is None,
                   problem or "")


def exact(stage: str, actual, expected, why: str) -> Outcome:
    """``actual`` equal to ``expected`` value for value (bit for bit): ``why`` the claim is."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    if actual.shape != expected.shape:
        return Outcome("", stage, None, "bit for bit", None, why, False,
                       f"shape {actual.shape} != {expected.shape}")
    differ = actual != expected
    if actual.dtype.kind == "f":
        differ &= ~(np.isnan(actual) & np.isnan(expected))
    measured = (float(np.max(np.abs(actual.astype(np.float64) - expected), initial=0.0))
                if actual.dtype.kind == "f" else float(differ.sum()))
    detail = ""
    if differ.any():
        i = np.unravel_index(np.argmax(differ), differ.shape)
        detail = (f"{int(differ.sum())} of {differ.size} values differ; first at {i}: "
                  f"{actual[i]!r} vs {expected[i]!r}")
    return Outcome("", stage, measured, "bit for bit", None, why, not differ.any(), detail)


def holds(ok: bool, claim: str, detail: str = "") -> Outcome:
    """An invariant of the case, ``claim`` in words (``monotone``), as the outcome's stage."""
    return Outcome("", claim, None, "holds", None, "invariant", bool(ok),
                   "" if ok else detail or f"does not hold: {claim}")


# -- checks ------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Check:
    """A conformance check: ``run(target)`` gives its outcomes.

    Attributes:
        name: what is checked, as the table shows it.
        run: the check on one device and precision.
        quick: part of ``validate --quick``.
        kernels_only: meaningless on the reference itself (numpy is skipped).
    """

    name: str
    run: Callable[[Target], list[Outcome]]
    quick: bool = False
    kernels_only: bool = False


CHECKS: list[Check] = []


def check(name: str, *, quick: bool = False, kernels_only: bool = False):
    """Register the decorated function as a :class:`Check`."""
    def register(run):
        CHECKS.append(Check(name, run, quick, kernels_only))
        return run
    return register


def _photo(rows=slice(220, 316), cols=slice(300, 428)) -> np.ndarray:
    """A crop of the coffee photograph (default: the spoon's clipped highlights)."""
    return np.ascontiguousarray(coffee()[rows, cols])


@check("accumulate: sRGB decode at 0, 1, knees, denormals", quick=True)
def _srgb_decode(t: Target) -> list[Outcome]:
    x = on_device(t.precision, transfer_points())
    got = decode_on(t.backend, x)
    return [within("srgb_to_linear", t, got, transfer.srgb_to_linear(x)),
            holds(np.all(np.diff(got) >= 0), "monotone"),
            holds(np.all(got[x == 1] == 1) and np.all(got[x == 0] == 0),
                  "0 and 1 stay exactly 0 and 1")]


@check("finish: sRGB encode at 0, 1, knees, denormals", quick=True)
def _srgb_encode(t: Target) -> list[Outcome]:
    x = on_device(t.precision, transfer_points())
    got = finish_on(t.backend, x)
    return [within("linear_to_srgb", t, got, np.clip(transfer.linear_to_srgb(x), 0, 1))]


@check("accumulate + finish: sRGB round trips")
def _srgb_round_trips(t: Target) -> list[Outcome]:
    x = on_device(t.precision, transfer_points())
    return [within("srgb_round_trip", t, decode_on(t.backend, finish_on(t.backend, x)), x),
            within("srgb_decode_encode", t, finish_on(t.backend, decode_on(t.backend, x)),
                   x)]


@check("finish: A7R3 polynomial clips outside [0, 1]")
def _a7r3_polynomial(t: Target) -> list[Outcome]:
    x = on_device(t.precision, A7R3_POLYNOMIAL_POINTS)
    got = finish_on(t.backend, x, crf="a7r3")
    return [within("finish_crf_polynomial", t, got, finish_on(REFERENCE, x, crf="a7r3")),
            holds(np.all(got[x <= 1e-6] == 0) and np.all(got[x >= 1] == 1),
                  "clips to exactly 0 and 1")]


@check("finish: A7R3 table near 0.86, where the polynomial dips")
def _a7r3_table(t: Target) -> list[Outcome]:
    x = on_device(t.precision, A7R3_DIP_POINTS)
    got = finish_on(t.backend, x, crf="a7r3-lut")
    return [within("finish", t, got, finish_on(REFERENCE, x, crf="a7r3-lut")),
            holds(np.all(np.diff(got) >= 0), "monotone")]


def _accumulate_mode(t: Target, mode: str) -> list[Outcome]:
    photo = _photo()
    h, w = photo.shape[:2]
    p, _, params = prepare(t.precision, {"blur": {"mode": mode, "frames": 3}}, (h, w))
    frames = [photo, np.roll(photo, 3, axis=1), np.roll(photo, -2, axis=0)]
    frames = frames if mode == "average" else frames[:1]
    mask = np.linspace(0, 1, h * w * 3).reshape(h, w, 3) if mode == "none" else None
    region = Region.whole(h, w)
    linear, sat = t.backend.accumulate(p, params, frames, mask, region)
    ref_linear, ref_sat = REFERENCE.accumulate(p, params, frames, mask, region)
    return [within("accumulate", t, linear, ref_linear),
            within("accumulate", t, sat, ref_sat)]


for _mode in ("trajectory", "average", "kernel", "none"):
    CHECKS.append(Check(f"accumulate: blur mode {_mode}, photo",
                        functools.partial(_accumulate_mode, mode=_mode),
                        quick=_mode == "trajectory"))


@check("accumulate: mean of 1,000 streamed frames")
def _long_average(t: Target) -> list[Outcome]:
    frames = StreamedFrames(1000)
    h, w = frames.shape[:2]
    p, _, params = prepare(t.precision, {"blur": {"mode": "average", "frames": 1000}}, (h, w))
    linear, mask = t.backend.accumulate(p, params, frames, None, Region.whole(h, w))
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, StreamedFrames(1000), None,
                                                Region.whole(h, w))
    return [within("accumulate_long_sum", t, linear, ref_linear),
            exact("saturation count", to_host(mask), on_device(t.precision, ref_mask),
                  "count / n rounded once to the compute type"),
            holds(frames.max_alive <= 1, "frames read one at a time")]


@check("accumulate: camera path of 1,000 poses")
def _long_path(t: Target) -> list[Outcome]:
    photo = _photo(slice(240, 272), slice(330, 362))
    settings = {"blur": {"mode": "trajectory", "steps": 1000, "extent": [6.0, 6.0]}}
    p, _, params = prepare(t.precision, settings, photo.shape[:2])
    region = Region.whole(*photo.shape[:2])
    linear, mask = t.backend.accumulate(p, params, [photo], None, region)
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, [photo], None, region)
    return [within("accumulate_long_sum", t, linear, ref_linear),
            within("accumulate_long_sum", t, mask, ref_mask)]


@check("accumulate: camera path leaving the image, in tiles")
def _path_leaving(t: Target) -> list[Outcome]:
    photo = _photo(slice(250, 274), slice(330, 362))
    h, w = photo.shape[:2]
    p, _, params = prepare(t.precision, {"blur": {"mode": "trajectory"}}, (h, w),
                           overrides={"homographies": POSES_LEAVING_THE_IMAGE})
    ref_linear, ref_mask = (to_host(a).reshape(h, w, 3) for a in REFERENCE.accumulate(
        p, params, [photo], None, Region.whole(h, w)))
    out = []
    for y0, x0, th, tw in [(0, 0, h, w), (10, 12, 14, 20)]:
        linear, mask = t.backend.accumulate(p, params, [photo], None, Region(y0, x0, th, tw, h, w))
        inside = (slice(y0, y0 + th), slice(x0, x0 + tw))
        out += [within("accumulate", t, to_host(linear).reshape(th, tw, 3),
                       ref_linear[inside]),
                within("accumulate", t, to_host(mask).reshape(th, tw, 3),
                       ref_mask[inside])]
    return out


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
    photo = _photo()
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
    photo = _photo(slice(220, 268), slice(300, 364))
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
    photo = _photo()
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


# -- random draws --------------------------------------------------------------------------------

#: OpenCL C that writes the noise stages' Philox words and uniforms of each pixel (the kernels'
#: own gb_pixel_bits and gb_uniform). The Warp twin is gpu_blur/conformance/warp_probe.py.
UNIFORM_PROBE_CL = """
#include "gb_random.h"
__kernel void gb_probe_uniforms(uint key0, uint key1, uint sample_index, uint stream,
                                uint width, __global uint *words, __global real *out)
{
    uint i = get_global_id(0);
    uint4 bits = gb_pixel_bits((uint2)(key0, key1), sample_index, stream, i % width,
                               i / width, 0u);
    vstore4(bits, i, words);
    out[4 * i] = gb_uniform(bits.x);
    out[4 * i + 1] = gb_uniform(bits.y);
    out[4 * i + 2] = gb_uniform(bits.z);
    out[4 * i + 3] = gb_uniform(bits.w);
}
"""

#: (seed, sample index, stream, width, height) of the uniforms compared: seeds beyond 32 bits,
#: the largest sample index.
UNIFORM_DRAW = (2**40 + 17, 2**32 - 5, rng.Stream.SHOT_NOISE, 97, 61)


def device_uniforms(backend) -> tuple[np.ndarray, np.ndarray]:
    """(words, uniforms) of :data:`UNIFORM_DRAW` on a kernel backend, pixel-major, 4 each."""
    seed, sample_index, stream, width, height = UNIFORM_DRAW
    key = rng.key_from_seed(seed)
    n = width * height
    args = (int(key[0]), int(key[1]), sample_index, int(stream))
    if backend.name == "opencl":
        import pyopencl as cl

        program = backend.program_from_source(UNIFORM_PROBE_CL, name="uniform probe")
        words = cl.Buffer(backend.ctx, cl.mem_flags.WRITE_ONLY, 4 * n * 4)
        values = cl.Buffer(backend.ctx, cl.mem_flags.WRITE_ONLY,
                           4 * n * np.dtype(backend.np_real).itemsize)
        program.gb_probe_uniforms(backend.queue, (n,), None, *map(np.uint32, args),
                                  np.uint32(width), words, values)
        got_words, got = np.empty(4 * n, np.uint32), np.empty(4 * n, backend.np_real)
        cl.enqueue_copy(backend.queue, got_words, words)
        cl.enqueue_copy(backend.queue, got, values)
        return got_words, got.astype(np.float64)
    import warp as wp

    from gpu_blur.conformance.warp_probe import pixel_uniforms

    device = backend.wp_device
    words = wp.zeros(4 * n, dtype=wp.uint32, device=device)
    values = wp.zeros(4 * n, dtype=wp.float64, device=device)
    wp.launch(pixel_uniforms, dim=n, device=device,
              inputs=[*(wp.uint32(a) for a in args), width, words, values])
    return words.numpy(), values.numpy()


def reference_uniforms() -> tuple[np.ndarray, np.ndarray]:
    """(words, uniforms) of :data:`UNIFORM_DRAW` from :mod:`gpu_blur.reference.rng`."""
    seed, sample_index, stream, width, height = UNIFORM_DRAW
    y, x = np.divmod(np.arange(width * height), width)
    words = rng.pixel_bits(seed, sample_index, stream, y, x)
    return words.reshape(-1), rng.uniform_from_bits(words).reshape(-1)


@check("random: Philox words and uniforms", quick=True, kernels_only=True)
def _uniforms(t: Target) -> list[Outcome]:
    words, uniforms = device_uniforms(t.backend)
    ref_words, ref_uniforms = reference_uniforms()
    why = "Philox4x32-10 words and their uniforms are exact"
    return [exact("philox words", words, ref_words, why),
            exact("uniforms", uniforms, ref_uniforms, why)]


def poisson_block(precision: str, rates, k: float, block: int = 24) -> np.ndarray:
    """A linear image of ``block`` x ``block`` pixels per rate, rate x ``k`` as devices hold it.

    A power-of-two ``k`` keeps ``value / k`` exact in either precision.
    """
    values = on_device(precision, np.asarray(rates, dtype=np.float64) * k)
    return np.repeat(np.repeat(values, block)[None, :, None], block, axis=0).repeat(3, 2)


def poisson_counts(t: Target, backend, rates, k: float = 0.125) -> np.ndarray:
    """The Poisson counts ``backend``'s to_raw pass draws at ``rates``, as float64.

    Identity camera, white balance gains 1, no read noise, no saturation: the RAW value is
    the count times ``k``.
    """
    linear = poisson_block(t.precision, rates, k)
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"}}
    p, cam, params = prepare(t.precision, settings, linear.shape[:2], camera="srgb",
                             overrides={"shot_noise_k": k, "read_noise_std": 0.0,
                                        "pattern": "RGGB"})
    raw, _ = backend.to_raw(p, params, cam, linear, np.zeros_like(linear), seed=SEED,
                            sample_index=SAMPLE)
    return to_host(raw) / k


#: Rates of the inversion sampler (< 10), where a count depends on the uniform alone.
LOW_RATES = [0.0, 1e-12, 0.3, 1.0, 2.5, 5.0, 9.99]
#: Rates through the switch to PTRS and beyond, up to 1e7.
HIGH_RATES = [10.01, 100.0, 1e4, 1e7]


def _float_samplers(t: Target) -> bool:
    """Whether the device samples in float (an OpenCL device without cl_khr_fp64)."""
    return t.family == "opencl" and not t.backend.info.fp64


@check("random: Poisson counts, rates 0 to 9.99 (inversion)", quick=True)
def _poisson_low(t: Target) -> list[Outcome]:
    got = poisson_counts(t, t.backend, LOW_RATES)
    ref = poisson_counts(t, REFERENCE, LOW_RATES)
    if _float_samplers(t):  # float cumulative sums: a count may move (its own row)
        return [within("poisson_agreement", t, np.mean(got != ref), 0.0,
                       dtype="float32-nofp64")]
    return [exact("poisson counts", got, ref,
                  "same uniforms, same inversion: the same counts (K = 1/8 keeps rates exact)")]


@check("random: Poisson counts, rates 10 to 1e7 (PTRS)")
def _poisson_high(t: Target) -> list[Outcome]:
    if _float_samplers(t):
        return [Outcome("", "poisson_agreement", None, "", None, "", None,
                        "float PTRS moves counts at large rates: the test suite checks their "
                        "statistics (tests/test_hard_cases.py)")]
    got = poisson_counts(t, t.backend, HIGH_RATES)
    ref = poisson_counts(t, REFERENCE, HIGH_RATES)
    if not t.kernels:
        return [exact("poisson counts", got, ref, "the reference itself")]
    # Warp samples in float64 whatever the caller's type: its float64 row
    dtype = "float64" if t.family == "warp" else None
    return [within("poisson_agreement", t, np.mean(got != ref), 0.0, dtype=dtype)]


# -- tiles ---------------------------------------------------------------------------------------

def _synthesize(t: Target, backend, inputs, settings: dict, **kwargs):
    scene = scene_for(t.precision, settings)
    return gpu_blur.synthesize(inputs, scene, seed=SEED, sample_index=SAMPLE, backend=backend,
                               **kwargs)


@check("tiles: tiled equals untiled, bit for bit", quick=True)
def _tiled(t: Target) -> list[Outcome]:
    photo = _photo(slice(230, 310), slice(320, 420))
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
    photo = _photo(slice(150, 310), slice(250, 450))
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
    photo = [_photo()]
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

#: Checks of one kernel device against another: ``run(a, b)`` with both at one precision.
AGAINST: list[Check] = []


def _against_uniforms(a: Target, b: Target) -> list[Outcome]:
    why = "both kernel languages draw the reference's Philox words and uniforms"
    (wa, ua), (wb, ub) = device_uniforms(a.backend), device_uniforms(b.backend)
    return [exact("philox words", wa, wb, why), exact("uniforms", ua, ub, why)]


def _against_poisson(a: Target, b: Target) -> list[Outcome]:
    return [exact("poisson counts",
                  poisson_counts(a, a.backend, LOW_RATES), poisson_counts(b, b.backend, LOW_RATES),
                  "same uniforms, same inversion: the same counts")]


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


AGAINST += [Check("random: Philox words and uniforms", _against_uniforms),
            Check("random: Poisson counts, rates 0 to 9.99", _against_poisson)]
AGAINST += [Check(f"pipeline: scene {s}, noise off, float output",
                  functools.partial(_against_scene, scene=s)) for s in builtin_scenes()]


# -- running ---------------------------------------------------------------------------------------

def family(name: str) -> str:
    """The tolerance table's backend column for a backend name (``opencl:1:0`` -> opencl)."""
    return name.split(":", 1)[0]


def run_check(item: Check, target: Target, other: Target | None = None) -> list[Outcome]:
    """One check on one target (against ``other`` for :data:`AGAINST`), names filled in.

    An exception becomes a failed outcome that names it.
    """
    if item.kernels_only and not target.kernels:
        return [Outcome(item.name, "-", None, "", None, "", None, "numpy is the reference")]
    try:
        outcomes = item.run(target) if other is None else item.run(target, other)
    except Exception as e:  # a device error is a result, not the end of the run
        return [Outcome(item.name, "-", None, "", None, "", False,
                        f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")]
    return [dataclasses.replace(o, check=item.name) for o in outcomes]


def selected(quick: bool) -> list[Check]:
    """The checks of a run: every one, or those marked quick."""
    return [c for c in CHECKS if c.quick or not quick]


def passed(outcomes: list[Outcome]) -> bool:
    """Whether no outcome failed (skipped ones do not fail a run)."""
    return all(o.passed is not False for o in outcomes)


def finite_or_none(x: float | None) -> float | None:
    """``x`` for JSON: infinities and NaN become None."""
    return None if x is None or not math.isfinite(x) else x
