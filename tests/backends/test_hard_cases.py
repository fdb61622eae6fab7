"""Hard cases stay numerically stable (issue 5): each case runs on every backend.

Every test feeds crafted inputs through the backends' passes (or the whole pipeline) and checks
against the float64 reference (the numpy backend): all outputs finite, within their row of
gpu_blur.testing (section "hard cases" for the rows added with this file), and the invariant
the test's name states. Kernel backends round their inputs to their compute type; where a check
is about the kernels' arithmetic, the reference is fed the same rounded values.

Covered elsewhere, not repeated here: uniforms never reach a log as exactly 0 or 1
(tests/reference/test_rng.py::test_uniforms_are_never_0_or_1_even_at_extreme_words for the
reference, test_uniform_is_exact_for_every_23_bit_value_and_both_ends in
tests/backends/test_device_random.py for the kernels of both languages, at the words 0 and
2^32 - 1); fp32 and fp64 compute within their rows (tests/backends/test_backends.py);
near-singular matrices refused by the reference (tests/reference/test_color.py); the reference's
knees and round trips (tests/reference/test_transfer.py).

The tests marked ``slow`` are this file's heaviest (``-m "not slow"`` leaves them out; CI runs
every test). The one with buffers of more than 2^29 values runs a small form by default, so that
CI stays quick. ``GPU_BLUR_HEAVY=1`` gives the float32 kernel backends the full size, 179 M
pixels in one launch: about 12 GB of host memory and half a minute per backend on Intel's CPU
OpenCL runtime and Warp's CPU device (float64 builds keep the small form: twice the memory, the
same index code).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from conftest import BACKEND_SPECS, KERNEL_BACKEND_SPECS, make_backend, spec_backend, spec_dtype
from hypothesis import given, settings
from hypothesis import strategies as st

import gpu_blur
from gpu_blur import conformance
from gpu_blur.backends import OnDevice
from gpu_blur.backends.kernel import pass_config
from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.cameras import get_camera
from gpu_blur.conformance import (
    A7R3_DIP_POINTS,
    A7R3_POLYNOMIAL_POINTS,
    BIG,
    DESATURATING,
    NEAR_SINGULAR,
    OUT_OF_GAMUT,
    POSES_LEAVING_THE_IMAGE,
    PRIMARIES,
    RATES,
    SAMPLE,
    SEED,
    BigFrame,
    StreamedFrames,
    big_pattern,
    seam_image,
    tall_thin_linear,
    transfer_points,
)
from gpu_blur.constants import A7R3_CRF_TABLE_X255
from gpu_blur.kernel_constants import EXACT_FRAMES_MAX, EXACT_UNIT
from gpu_blur.planning import Pass
from gpu_blur.reference import bayer, transfer
from gpu_blur.reference.color import apply_matrix
from gpu_blur.scene import PATTERNS
from gpu_blur.testing import assert_close, tolerance, z_mean, z_var
from gpu_blur.tiling import Region

REFERENCE = NumpyBackend()
HEAVY = os.environ.get("GPU_BLUR_HEAVY") == "1"


# -- helpers -----------------------------------------------------------------------------------

def backend_name(spec: str) -> str:
    """The backend argument of gpu_blur.synthesize for a spec ('opencl:0:0/float32' -> ...)."""
    return spec.partition("/")[0]


def on_device(spec: str, values) -> np.ndarray:
    return conformance.on_device(spec_dtype(spec), values)


def rows(stage: str, spec: str) -> tuple[float, float]:
    return tolerance(stage, spec_backend(spec), spec_dtype(spec))


def check(stage: str, spec: str, actual, expected) -> None:
    """Finite, and within the table's row for the spec."""
    actual = np.asarray(actual, dtype=np.float64)
    bad = int(np.sum(~np.isfinite(actual)))
    assert bad == 0, f"{stage} on {spec}: {bad} values are not finite"
    assert_close(actual, expected, stage, spec_backend(spec), spec_dtype(spec))


def scene_for(spec: str, settings: dict):
    return conformance.scene_for(spec_dtype(spec), settings)


def prepare(spec: str, settings: dict, shape, camera: str = "a7r3", overrides=None):
    return conformance.prepare(spec_dtype(spec), settings, shape, camera, overrides)


def decode_on(spec: str, srgb: np.ndarray) -> np.ndarray:
    return conformance.decode_on(make_backend(spec), srgb)


def finish_on(spec: str, linear: np.ndarray, crf: str = "srgb") -> np.ndarray:
    return conformance.finish_on(make_backend(spec), linear, crf)


# -- transfer functions ----------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_srgb_decode_at_zero_one_knees_and_denormals_is_finite_and_monotone(spec):
    x = on_device(spec, transfer_points())
    got = decode_on(spec, x)
    check("srgb_to_linear", spec, got, transfer.srgb_to_linear(x))
    assert np.all(np.diff(got) >= 0), "the EOTF must be monotone"
    assert np.all(got[x == 0] == 0) and not np.signbit(got[x == 0]).any()  # not -0
    assert np.all(got[x == 1] == 1)  # pow(1, 2.4) of exactly 1: white stays white


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_srgb_encode_at_zero_one_knees_and_denormals_steps_down_only_at_the_iec_knee(spec):
    x = on_device(spec, transfer_points())
    got = finish_on(spec, x)
    ref = np.clip(transfer.linear_to_srgb(x), 0, 1)
    check("linear_to_srgb", spec, got, ref)
    assert np.all(got[x == 0] == 0) and np.all((got >= 0) & (got <= 1))
    # (1.055 - 0.055 rounds below 1: OETF(1) is 1 - 2^-53 in the reference, 1 - 2^-24 in
    # float32; white comes out exactly 1 through the saturated restore, tested below)
    # IEC 61966-2-1's knees disagree: the exact OETF steps down 3.1e-8 from the last value
    # below 0.0031308 to the first at or above it (tests/reference/test_transfer.py pins it for the
    # reference). The kernels take the same branch for every input (float32: no float lies
    # between 0.0031308 and the float nearest it) and keep the same step, to their row.
    rtol, atol = rows("linear_to_srgb", spec)
    knee = transfer.SRGB_ENCODE_KNEE
    for i in np.flatnonzero(np.diff(got) < 0):
        assert x[i] < knee <= x[i + 1], f"the OETF steps down at {x[i]!r}, not at the knee"
        step = ref[i] - ref[i + 1]
        assert 0 < step < 3.2e-8
        assert got[i] - got[i + 1] <= step + 2 * (atol + rtol * ref[i])


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_srgb_round_trips_through_the_accumulate_and_finish_passes(spec):
    x = on_device(spec, transfer_points())
    # linear -> sRGB -> linear: the knees' mismatch costs 2.3e-9 just above the encode knee
    check("srgb_round_trip", spec, decode_on(spec, finish_on(spec, x)), x)
    # sRGB -> linear -> sRGB: values just below the decode knee 0.04045 decode to linear
    # values just above the encode knee 0.0031308, which the curve encodes up to 3.0e-8 low
    check("srgb_decode_encode", spec, finish_on(spec, decode_on(spec, x)), x)


# -- A7R3 camera response ----------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_a7r3_polynomial_clips_outside_0_1_and_stays_within_its_horner_bound(spec):
    x = on_device(spec, A7R3_POLYNOMIAL_POINTS)
    got = finish_on(spec, x, crf="a7r3")
    ref = finish_on("numpy", x, crf="a7r3")
    check("finish_crf_polynomial", spec, got, ref)  # the 3e-5 row: float32 Horner cancels
    assert np.all((got >= 0) & (got <= 1))
    # P(0) = -0.0095 and P(1) = 1.022: both ends clip, to exactly 0 and 1 on every backend
    assert np.all(got[x <= 1e-6] == 0.0)
    assert np.all(got[x >= 1] == 1.0)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_a7r3_lookup_table_is_monotone_near_0_86_where_the_polynomial_is_not(spec):
    x = on_device(spec, A7R3_DIP_POINTS)
    got = finish_on(spec, x, crf="a7r3-lut")
    check("finish", spec, got, finish_on("numpy", x, crf="a7r3-lut"))
    assert np.all(np.diff(got) >= 0)
    polynomial = finish_on("numpy", x, crf="a7r3")
    assert np.any(np.diff(polynomial) < 0)  # the fitted polynomial dips there (by 1e-8 / step)


def test_a7r3_lookup_inverse_is_monotone_near_0_86_and_inverts_the_table_there():
    # The inverse response exists only in the reference (the pipeline never applies it).
    x = np.linspace(0.85, 0.875, 5001)
    rendered = transfer.lookup_crf(x, A7R3_CRF_TABLE_X255)
    y = np.linspace(rendered[0], rendered[-1], 20001)
    inverse = transfer.inverse_lookup_crf(y, A7R3_CRF_TABLE_X255)
    assert np.all(np.diff(inverse) > 0)  # strictly: the table is strictly increasing
    assert_close(transfer.inverse_lookup_crf(rendered, A7R3_CRF_TABLE_X255), x,
                 "crf_polynomial", "independent")


# -- frames ------------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("n", [1, 2, 65, 1000])
def test_average_of_1_to_1000_frames_stays_within_the_stated_bound(spec, n):
    frames = StreamedFrames(n)
    h, w = frames.shape[:2]
    p, _, params = prepare(spec, {"blur": {"mode": "average", "frames": n}}, (h, w))
    region = Region.whole(h, w)
    linear, mask = make_backend(spec).accumulate(p, params, frames, None, region)
    # each frame is read, copied into a device stack and dropped before the next is read
    assert frames.max_alive <= 1, "frames must be read one at a time"
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, StreamedFrames(n), None, region)
    # Kernels sum frames with compensation: float32 within 1e-6 at any count (a plain float32
    # sum was 1.5e-5 off at 1,000 frames); float64 within the reference's own error.
    check("accumulate_long_sum", spec, linear, ref_linear)
    # the saturated fraction is count / n, rounded once to the compute type
    assert np.array_equal(mask, on_device(spec, ref_mask))
    assert np.any(ref_mask > 0)  # saturated frames were counted


def compensated_sum_float32(terms: np.ndarray) -> np.ndarray:
    """gb_blur_average_add's sum of ``terms`` (count x n float32), one float32 op at a time."""
    s = np.zeros(terms.shape[1], np.float32)
    c = np.zeros_like(s)
    for v in terms:
        t = s + v
        c = c + np.where(np.abs(s) >= np.abs(v), (s - t) + v, (v - t) + s)
        s = t
    return s + c


def exact_sum_float32(table: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """The exact sum of ``table[codes]`` over frames (axis 0), rounded once to float32."""
    units = (table.astype(np.float64) / EXACT_UNIT).astype(np.int64)
    return units[codes].sum(axis=0).astype(np.float32) * np.float32(EXACT_UNIT)


def frame_codes(count: int, n: int, seed: int) -> np.ndarray:
    """count x n 8-bit codes: random, then columns of all 255 and of codes near black/white."""
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 256, (count, n), dtype=np.uint8)
    codes[:, :64] = 255
    codes[:, 64:4096] = rng.choice(np.array([0, 1, 2, 127, 128, 253, 254, 255], np.uint8),
                                   (count, 4096 - 64))
    return codes


@pytest.mark.parametrize("count", [3, 9, 65, EXACT_FRAMES_MAX])
def test_compensated_float32_sum_of_8bit_frames_is_the_exactly_rounded_sum(count):
    """gb_sum.h's proof, checked: for up to EXACT_FRAMES_MAX frames of 8-bit linear values the
    compensated float32 sum is the exact sum rounded once, which the integer sum gives."""
    table = transfer.srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)
    units = table.astype(np.float64) / EXACT_UNIT
    assert np.all(units == np.floor(units)) and units.max() <= 2**35  # whole units
    codes = frame_codes(count, 3 * 8192, count)
    exact = exact_sum_float32(table, codes)
    assert np.array_equal(compensated_sum_float32(table[codes]).view(np.uint32),
                          exact.view(np.uint32))
    # the cases are not trivial: a plain float32 sum misses the rounded sum on many of them
    plain = np.zeros(codes.shape[1], np.float32)
    for v in table[codes]:
        plain = plain + v
    assert np.count_nonzero(plain != exact) > 100


def launch_names(backend, monkeypatch) -> list[str]:
    """The names of the kernels ``backend`` launches from now on, in order (a list it fills)."""
    names: list[str] = []
    launch = backend._launch
    monkeypatch.setattr(backend, "_launch",
                        lambda k, name, *a: names.append(name) or launch(k, name, *a))
    return names


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("count", [3, 9, EXACT_FRAMES_MAX])
@pytest.mark.parametrize("shape", [(32, 64), (31, 63)], ids=["codes_in_words", "odd_size"])
def test_frames_on_the_device_average_to_the_bits_of_streamed_frames(spec, count, shape,
                                                                      monkeypatch):
    """8-bit frames put on the device are summed in one launch (float32: exactly, in integers,
    gb_blur_average_exact, four codes a work item, where the image's values come in fours;
    else by the compensated sum); frames streamed from the host a few per launch, by
    compensated sums. All give the same bits, and float32's are the exact sum rounded once."""
    h, w = shape
    codes = frame_codes(count, h * w * 3, 7)
    frames = [c.reshape(h, w, 3) for c in codes]
    p, _, params = prepare(spec, {"blur": {"mode": "average", "frames": count}}, (h, w))
    region = Region.whole(h, w)
    backend = make_backend(spec)
    launched = launch_names(backend.backend, monkeypatch)
    on_dev = backend.accumulate(p, params, backend.put(np.stack(frames)), None, region)
    exact = spec_dtype(spec) == "float32" and h * w * 3 % 4 == 0
    assert ("blur_average_exact" in launched) == exact
    streamed = backend.accumulate(p, params, frames, None, region)
    for a, b in zip(on_dev, streamed, strict=True):
        assert np.array_equal(a, b)
    if spec_dtype(spec) == "float32":
        config = pass_config(p, Pass.ACCUMULATE)
        table = OnDevice(backend.backend._code_table(config, np.uint8), (256,),
                         backend.backend._fetch).numpy(np.float32)
        mean = exact_sum_float32(table, codes) / np.float32(count)
        assert np.array_equal(on_dev[0].ravel(), mean.astype(np.float64))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("shape", [(32, 64), (31, 63)], ids=["codes_in_words", "odd_size"])
def test_8bit_image_and_mask_in_mode_none_give_the_bits_of_their_float_values(spec, shape,
                                                                            monkeypatch):
    """Blur mode none takes an 8-bit image and mask on the device four codes a work item (the
    image through the code table, linearize_codes; the mask by unit_values_codes) where the
    values come in fours: the same bits as the same values given as floats (code / 255), from
    the device and from the host."""
    h, w = shape
    codes = frame_codes(2, h * w * 3, 11)
    image, mask = (c.reshape(h, w, 3) for c in codes)
    p, _, params = prepare(spec, {"blur": {"mode": "none"}}, (h, w))
    region = Region.whole(h, w)
    backend = make_backend(spec)
    launched = launch_names(backend.backend, monkeypatch)
    coded = backend.accumulate(p, params, backend.put(image), backend.put(mask), region)
    quads = h * w * 3 % 4 == 0
    assert ("linearize_codes" in launched) == quads
    assert ("unit_values_codes" in launched) == quads
    real = np.dtype(spec_dtype(spec))
    as_values = [(a / np.float64(255.0)).astype(real) for a in (image, mask)]
    for got in (backend.accumulate(p, params, [image], as_values[1], region),
                backend.accumulate(p, params, *(backend.put(a) for a in as_values), region)):
        for a, b in zip(coded, got, strict=True):
            assert np.array_equal(a, b)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_float_image_in_mode_none_goes_four_values_a_work_item_with_linearizes_bits(
        spec, monkeypatch):
    """Blur mode none takes an image of the compute type four values a work item by the curve
    (linearize_values, no clip indicator) where the values come in fours: the same bits as
    linearize's one value a work item, at the curve's knee, near 0 and 1 and in between."""
    h, w = 32, 64
    real = np.dtype(spec_dtype(spec))
    rng = np.random.default_rng(5)
    values = rng.random(h * w * 3).astype(real)
    knee = np.float64(0.04045)
    hard = np.array([0.0, 1.0, knee, np.nextafter(knee, 0), np.nextafter(knee, 1), 1e-30,
                     np.finfo(real).tiny, np.nextafter(real.type(1), real.type(0)), 0.5])
    values[:hard.size] = hard.astype(real)
    image = values.reshape(h, w, 3)
    p, _, params = prepare(spec, {"blur": {"mode": "none"}}, (h, w))
    region = Region.whole(h, w)
    backend = make_backend(spec)
    launched = launch_names(backend.backend, monkeypatch)
    fours, _ = backend.accumulate(p, params, backend.put(image), None, region)
    assert "linearize_values" in launched and "linearize" not in launched
    launched.clear()
    monkeypatch.setattr(backend.backend, "_quads", lambda buffers, n: None)
    ones, _ = backend.accumulate(p, params, backend.put(image), None, region)
    assert "linearize" in launched and "linearize_values" not in launched
    assert np.array_equal(fours, ones)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_camera_path_of_1000_poses_stays_within_the_stated_bound(spec, coffee_rgb):
    photo = np.ascontiguousarray(coffee_rgb[240:272, 330:362])
    settings = {"blur": {"mode": "trajectory", "steps": 1000, "extent": [6.0, 6.0]}}
    p, _, params = prepare(spec, settings, photo.shape[:2])
    region = Region.whole(*photo.shape[:2])
    linear, mask = make_backend(spec).accumulate(p, params, [photo], None, region)
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, [photo], None, region)
    check("accumulate_long_sum", spec, linear, ref_linear)
    check("accumulate_long_sum", spec, mask, ref_mask)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_camera_path_leaving_the_image_reads_only_the_image(spec, coffee_rgb):
    """Poses that move the content past every edge, by whole and fractional pixels, two of them
    so far right that the first 4 columns see no image: every backend and tile gives the
    reference's edge rule (reference.shake.shake_blur, "Edges"), 0 where nothing is seen."""
    photo = np.ascontiguousarray(coffee_rgb[250:274, 330:362])
    h, w = photo.shape[:2]
    hom = POSES_LEAVING_THE_IMAGE
    p, _, params = prepare(spec, {"blur": {"mode": "trajectory"}}, (h, w),
                           overrides={"homographies": hom})
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, [photo], None, Region.whole(h, w))
    ref_linear = np.asarray(ref_linear).reshape(h, w, 3)
    assert np.all(ref_linear[:, :4] == 0.0) and np.all(ref_linear[:, 4:] > 0.0)
    backend = make_backend(spec)
    for y0, x0, th, tw in [(0, 0, h, w), (0, 0, 10, 12), (10, 12, 14, 20)]:
        region = Region(y0, x0, th, tw, h, w)
        linear, mask = backend.accumulate(p, params, [photo], None, region)
        inside = (slice(y0, y0 + th), slice(x0, x0 + tw))
        check("accumulate", spec, np.asarray(linear).reshape(th, tw, 3), ref_linear[inside])
        check("accumulate", spec, np.asarray(mask).reshape(th, tw, 3),
              np.asarray(ref_mask).reshape(h, w, 3)[inside])


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("crf", ["srgb", "a7r3"])
def test_all_white_frames_give_exactly_white(spec, crf):
    scene = scene_for(spec, {"blur": {"extent": [2.0, 8.0]}, "output": {"bits": 0, "crf": crf}})
    result = gpu_blur.synthesize([np.ones((16, 24, 3))], scene, seed=SEED, sample_index=SAMPLE,
                                 backend=backend_name(spec))
    assert result.plan.kept("restore_saturated") and result.plan.kept("poisson_gaussian_noise")
    # every channel saturates, so the restore sets it to exactly 1 through noise and re-toning
    assert np.all(result.blurred == 1.0) and np.all(result.mask == 1.0)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("noise", ["none", "poisson-gaussian"])
def test_all_black_frames_give_black_or_pure_read_noise(spec, noise):
    black = np.zeros((16, 24, 3))
    scene = scene_for(spec, {"blur": {"extent": [2.0, 8.0]}, "noise": {"model": noise},
                             "isp": {"round_trip": "always"}, "output": {"bits": 0}})
    got = gpu_blur.synthesize([black], scene, seed=SEED, sample_index=SAMPLE,
                              backend=backend_name(spec)).blurred
    assert np.all(np.isfinite(got)) and np.all((got >= 0) & (got <= 1))
    if noise == "none":
        assert np.all(got == 0.0)
        return
    ref = gpu_blur.synthesize([black], scene, seed=SEED, sample_index=SAMPLE).blurred
    assert np.any(got > 0)  # read noise, clipped below at 0
    rtol, atol = rows("pipeline_noisy", spec)
    bad = np.abs(got.astype(np.float64) - ref) > atol + rtol * np.abs(ref)
    assert bad.mean() <= rows("pipeline_noisy_outliers", spec)[1]


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("case", ["corner", "seams"])
def test_saturated_pixels_on_tile_seams_and_corners_tile_bit_for_bit(spec, case):
    tile = 16
    image = seam_image(case, tile)
    settings = {"blur": {"extent": [3.0, 6.0]}, "saturation": {"mode": "on"},
                "output": {"bits": 0}}
    scene = scene_for(spec, settings)
    run = dict(seed=SEED, sample_index=SAMPLE, backend=backend_name(spec))
    whole = gpu_blur.synthesize([image], scene, **run)
    tiled = gpu_blur.synthesize([image], scene, tile=(tile, tile), **run)
    assert np.array_equal(tiled.blurred, whole.blurred) and np.array_equal(tiled.mask, whole.mask)
    if case == "corner":  # the blurred spot spreads over tiles that meet there
        quarters = [whole.mask[rows, cols] for rows in (slice(0, tile), slice(tile, 2 * tile))
                    for cols in (slice(0, tile), slice(tile, 2 * tile))]
        assert sum(bool(np.any(q > 0)) for q in quarters) >= 2
    else:
        assert np.any(whole.blurred == 1.0)  # the restore happened, across the seams
    quiet = scene_for(spec, {**settings, "noise": {"model": "none"},
                             "isp": {"round_trip": "always"}})
    got = gpu_blur.synthesize([image], quiet, tile=(tile, tile), **run)
    ref = gpu_blur.synthesize([image], quiet, seed=SEED, sample_index=SAMPLE)
    check("pipeline", spec, got.blurred, ref.blurred)
    assert np.array_equal(got.blurred == 1.0, ref.blurred == 1.0)


# -- saturation --------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("alpha", [0.25, 1.75])
@pytest.mark.parametrize("mask_value", [0.0, 1.0])
def test_saturated_channels_are_exactly_one_for_extreme_alpha_and_masks(spec, alpha, mask_value):
    codes = np.random.default_rng(11).integers(0, 256, (12, 16, 3))
    codes[2:4, 3:6] = 255
    blurred = codes / 255.0
    linear = transfer.srgb_to_linear(blurred)
    saturated = linear + alpha * mask_value >= 1.0
    # no 8-bit code lands within float32 rounding of the clip level but the exact ones
    assert np.all(np.abs(linear + alpha * mask_value - 1.0)[~saturated] > 1e-4)
    mask = np.full_like(blurred, mask_value)
    for noise in ("poisson-gaussian", "none"):
        scene = scene_for(spec, {"blur": {"mode": "none"}, "saturation": {"mode": "on"},
                                 "noise": {"model": noise}, "isp": {"round_trip": "always"},
                                 "output": {"bits": 0, "crf": "a7r3-lut"}})
        inputs = {"blurred": blurred, "mask": mask}
        got = gpu_blur.synthesize(inputs, scene, seed=SEED, sample_index=SAMPLE,
                                  backend=backend_name(spec), overrides={"alpha": alpha})
        assert np.all(np.isfinite(got.blurred))
        assert np.all(got.blurred[saturated] == 1.0)
        if noise == "none":
            ref = gpu_blur.synthesize(inputs, scene, seed=SEED, sample_index=SAMPLE,
                                      overrides={"alpha": alpha})
            check("pipeline", spec, got.blurred, ref.blurred)
    if alpha == 1.75 and mask_value == 1.0:
        assert saturated.all()


# -- noise -------------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("k", [1e-9, 0.125])
def test_poisson_rates_from_0_to_1e7_through_the_to_raw_pass(spec, k):
    block = 48  # rows x columns of one rate
    k_dev = float(on_device(spec, k))
    values = on_device(spec, np.array(RATES) * k)
    linear = np.repeat(np.repeat(values, block)[None, :, None], block, axis=0).repeat(3, 2)
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"}}
    p, cam, params = prepare(spec, settings, linear.shape[:2], camera="srgb",
                             overrides={"shot_noise_k": k, "read_noise_std": 0.0,
                                        "pattern": "RGGB"})
    raw, _ = make_backend(spec).to_raw(p, params, cam, linear, np.zeros_like(linear),
                                       seed=SEED, sample_index=SAMPLE)
    assert np.all(np.isfinite(raw)) and raw.min() >= 0
    counts = raw / k_dev
    assert np.all(np.abs(counts - np.rint(counts)) <= 1e-6 * np.maximum(counts, 1))
    counts = np.rint(counts)
    for j, value in enumerate(values):
        rate = value / k_dev  # the device's rate (its own rounding is ~1e-7 relative)
        c = counts[:, j * block:(j + 1) * block]
        assert abs(z_mean(c, rate, rate)) < 5, f"rate {rate:g}: mean {c.mean():g}"
        assert abs(z_var(c, rate, rate * (1 + 3 * rate))) < 5, f"rate {rate:g}: var {c.var():g}"
    assert np.all(counts[:, :block] == 0)  # rate 0
    if spec_dtype(spec) == "float64" and spec != "numpy":
        ref, _ = REFERENCE.to_raw(p, params, cam, linear, np.zeros_like(linear), seed=SEED,
                                  sample_index=SAMPLE)
        _, allowed = tolerance("poisson_agreement", spec_backend(spec), "float64")
        assert np.mean(raw != ref) <= allowed


# -- colour ------------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("source", ["out-of-gamut linear", "camera file"])
@pytest.mark.parametrize("clip", [False, True])
def test_negative_camera_values_are_clamped_where_the_pipeline_says(spec, source, clip,
                                                                     tmp_path):
    if source == "camera file":
        path = tmp_path / "desaturating.toml"
        path.write_text(f"[color]\ncamera_to_linear = {DESATURATING}\n")
        camera, colours = get_camera(str(path)), PRIMARIES
    else:
        camera, colours = get_camera("a7r3"), OUT_OF_GAMUT
    linear = on_device(spec, np.tile(colours, (4, 2, 1)).reshape(8, 6, 3))
    cam = apply_matrix(linear, camera.linear_to_camera)
    negative = bayer.mosaic(cam, bayer.BayerPattern("GRBG")) < -1e-3
    assert negative.sum() >= 6  # the case: camera values well below 0 at mosaic sites
    # saturation synthesis clips linear values to [0, 1] first: off, so negatives get through
    quiet = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
             "noise": {"model": "none"}, "isp": {"round_trip": "always", "clip_camera": clip}}
    p, _, params = prepare(spec, quiet, linear.shape[:2], overrides={"pattern": "GRBG"})
    zeros = np.zeros_like(linear)
    raw, _ = make_backend(spec).to_raw(p, params, camera, linear, zeros, seed=SEED,
                                       sample_index=SAMPLE)
    ref, _ = REFERENCE.to_raw(p, params, camera, linear, zeros, seed=SEED, sample_index=SAMPLE)
    check("to_raw", spec, raw, ref)
    if clip:  # isp.clip_camera: camera values clipped to [0, 1] before the mosaic
        assert raw.min() >= 0 and np.all(raw[negative] == 0)
    else:  # kept negative without noise ...
        assert np.all(raw[negative] < 0)
    # ... and with noise the Poisson rate is clamped at 0: no shot noise, only read noise (0)
    noisy = {**quiet, "noise": {"model": "poisson-gaussian"}}
    p, _, params = prepare(spec, noisy, linear.shape[:2],
                           overrides={"pattern": "GRBG", "read_noise_std": 0.0})
    raw, _ = make_backend(spec).to_raw(p, params, camera, linear, zeros, seed=SEED,
                                       sample_index=SAMPLE)
    assert np.all(np.isfinite(raw)) and np.all(raw[negative] == 0) and raw.min() >= 0


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_identity_camera_puts_linear_values_straight_into_the_mosaic(spec, coffee_rgb):
    linear = on_device(spec, coffee_rgb[100:124, 200:236] ** 2.2)
    camera = get_camera("srgb")
    assert np.array_equal(camera.linear_to_camera, np.eye(3))
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                "noise": {"model": "none"}, "isp": {"round_trip": "always"}}
    for pattern in PATTERNS:
        p, _, params = prepare(spec, settings, linear.shape[:2], camera="srgb",
                               overrides={"pattern": pattern})
        assert params["red_gain"] == params["blue_gain"] == 1.0
        raw, _ = make_backend(spec).to_raw(p, params, camera, linear, np.zeros_like(linear),
                                           origin=(3, 5), seed=SEED, sample_index=SAMPLE)
        # 1 * v + 0 * v' + 0 * v'' is v exactly, in any precision
        assert np.array_equal(raw, bayer.mosaic(linear, bayer.BayerPattern(pattern), (3, 5)))


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("key", ["camera_to_linear", "xyz_to_camera", "ccm_xyz"])
@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_near_singular_matrix_in_a_camera_file_is_refused(spec, key, suffix, tmp_path):
    path = tmp_path / f"near-singular{suffix}"
    if suffix == ".json":
        path.write_text(json.dumps({"color": {key: NEAR_SINGULAR}}))
    else:
        path.write_text(f"[color]\n{key} = {NEAR_SINGULAR}\n")
    with pytest.raises(ValueError, match=r"near-singular.*condition number 1e\+07"):
        get_camera(str(path))
    scene = scene_for(spec, {"camera": {"name": str(path)}})
    with pytest.raises(ValueError, match="condition number"):
        gpu_blur.synthesize([np.full((8, 8, 3), 0.5)], scene, backend=backend_name(spec))


# -- shapes and input types --------------------------------------------------------------------

@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("shape", [(2, 2), (2, 9), (3, 2), (7, 5), (5, 8)])
def test_tiny_and_odd_shapes_follow_the_even_crop_rule(spec, shape, coffee_rgb):
    image = coffee_rgb[200:200 + shape[0], 330:330 + shape[1]]
    settings = {"blur": {"mode": "kernel", "kernel_size": [5, 9]}, "noise": {"model": "none"},
                "saturation": {"mode": "on"}, "output": {"bits": 0}}
    run = dict(seed=SEED, sample_index=SAMPLE)
    for round_trip, expected in (("always", (shape[0] - shape[0] % 2, shape[1] - shape[1] % 2)),
                                 ("auto", shape)):
        scene = scene_for(spec, {**settings, "isp": {"round_trip": round_trip}})
        got = gpu_blur.synthesize([image], scene, backend=backend_name(spec), **run)
        ref = gpu_blur.synthesize([image], scene, **run)
        # the RAW round trip keeps whole 2 x 2 Bayer cells: odd sizes lose the last row/column
        assert got.blurred.shape == got.sharp.shape == got.mask.shape == (*expected, 3)
        check("pipeline", spec, got.blurred, ref.blurred)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_an_image_without_a_whole_bayer_cell_is_refused(spec):
    scene = scene_for(spec, {})
    with pytest.raises(ValueError, match="(?i)too small|bayer|2 x 2"):
        gpu_blur.synthesize([np.full((1, 6, 3), 0.5)], scene, backend=backend_name(spec))


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_memory_layouts_and_input_dtypes_give_the_same_result(spec, coffee_rgb):
    codes = np.round(coffee_rgb[220:244, 330:362] * 255).astype(np.uint8)
    scene = scene_for(spec, {"blur": {"extent": [2.0, 6.0]}, "output": {"bits": 0}})
    run = dict(seed=SEED, sample_index=SAMPLE, backend=backend_name(spec))
    base = gpu_blur.synthesize([codes], scene, **run).blurred
    wide = np.zeros((48, 96, 3), np.uint8)
    wide[::2, ::3] = codes
    same = {
        "Fortran order": np.asfortranarray(codes),
        "strided view": wide[::2, ::3],
        "negative strides": np.ascontiguousarray(codes[::-1, :, ::-1])[::-1, :, ::-1],
        "uint16 (257 x the 8-bit code)": codes.astype(np.uint16) * 257,
        "float64": codes / 255.0,
    }
    for what, image in same.items():
        got = gpu_blur.synthesize([image], scene, **run).blurred
        assert np.array_equal(got, base), f"{what} gives another result"
    # float32 input is the same image rounded to float32: the same result to that rounding
    quiet = scene_for(spec, {"blur": {"extent": [2.0, 6.0]}, "noise": {"model": "none"},
                             "isp": {"round_trip": "always"}, "output": {"bits": 0}})
    got = gpu_blur.synthesize([(codes / 255.0).astype(np.float32)], quiet, **run).blurred
    check("input_float32", spec, got, gpu_blur.synthesize([codes], quiet, **run).blurred)


# -- index arithmetic at large coordinates -----------------------------------------------------

@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)  # the reference needs whole frames
def test_kernel_blur_reflects_at_the_far_edges_of_a_huge_image(spec):
    kernel = np.random.default_rng(3).uniform(0, 1, (11, 15))
    settings = {"blur": {"mode": "kernel"}}
    crop = 64  # the reference's image: the last crop x crop pixels of the big one
    p, _, params = prepare(spec, settings, (BIG, BIG), overrides={"kernel": kernel})
    region = Region(BIG - 16, BIG - 20, 16, 20, BIG, BIG)
    linear, mask = make_backend(spec).accumulate(p, params, [BigFrame(BIG, BIG)], None, region)
    y = np.arange(BIG - crop, BIG)[:, None]
    x = np.arange(BIG - crop, BIG)[None, :]
    local = Region(crop - 16, crop - 20, 16, 20, crop, crop)  # far from the crop's top/left
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, [big_pattern(y, x)], None, local)
    check("accumulate", spec, linear, ref_linear)
    check("accumulate", spec, mask, ref_mask)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_to_raw_and_finish_at_the_corner_of_a_huge_image_match_the_reference(spec):
    view = Region(BIG - 24, BIG - 32, 24, 32, BIG, BIG)
    gen = np.random.default_rng(5)
    linear = on_device(spec, gen.uniform(0, 0.3, (*view.shape, 3)))
    mask = on_device(spec, gen.uniform(0, 1, (*view.shape, 3)) ** 8)
    # K = 1/8 (a power of two: the rate is exact) keeps the rates below 10 (inversion), where
    # float32 rounding cannot move a count, and the RAW values near 1: the draws at these
    # counters are compared value for value
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "on"},
                "noise": {"model": "poisson-gaussian"}}
    p, cam, params = prepare(spec, settings, (BIG, BIG),
                             overrides={"shot_noise_k": 0.125, "read_noise_std": 0.01})
    backend = make_backend(spec)
    raw, sat = backend.to_raw(p, params, cam, linear, mask, view.origin, seed=SEED,
                              sample_index=SAMPLE)
    ref_raw, ref_sat = REFERENCE.to_raw(p, params, cam, linear, mask, view.origin, seed=SEED,
                                        sample_index=SAMPLE)
    check("to_raw", spec, raw, ref_raw)
    check("saturate", spec, sat, ref_sat)
    assert np.unique(np.round(ref_raw / 0.125)).size > 4  # counts 0, 1, 2, ... were drawn
    # finish with reflect-101 at the image's far edges and sRGB noise at the same counters
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "on"},
                "noise": {"model": "gaussian"}, "isp": {"round_trip": "always"},
                "output": {"bits": 0}}
    p, cam, params = prepare(spec, settings, (BIG, BIG))
    out = Region(BIG - 20, BIG - 26, 20, 26, BIG, BIG)
    image, sat = REFERENCE.to_raw(p, params, cam, linear, mask, view.origin, seed=SEED,
                                  sample_index=SAMPLE)
    got = backend.finish(p, params, cam, image, sat, view, out, seed=SEED, sample_index=SAMPLE)
    ref = REFERENCE.finish(p, params, cam, image, sat, view, out, seed=SEED,
                           sample_index=SAMPLE)
    check("finish", spec, got, ref)


@pytest.mark.slow
@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_buffers_of_more_than_2_29_values_are_indexed_right_to_the_last_pixel(spec):
    heavy = HEAVY and spec_dtype(spec) == "float32"
    # heavy: 3 x 2^29 / 6 + 2^12 rows of 2 pixels: every RGB buffer holds more than 2^29 values
    # (its byte offsets pass 2^31 in float32); small: the same code on 4,096 rows
    height = 2**29 // 6 + 2**12 if heavy else 2**12
    linear = tall_thin_linear(height)
    assert not heavy or linear.size > 2**29
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "on"}}
    p, cam, params = prepare(spec, settings, linear.shape[:2],
                             overrides={"shot_noise_k": 0.125, "read_noise_std": 0.01})
    raw, sat = make_backend(spec).to_raw(p, params, cam, linear, linear, seed=SEED,
                                         sample_index=SAMPLE)
    # rows around the one whose values pass index 2^29 (and 2^31 bytes), and the last rows
    for y0 in sorted({min(2**29 // 6 - 32, height - 64) // 2 * 2, height - 64}):
        part = linear[y0:y0 + 64].astype(np.float64)
        ref_raw, ref_sat = REFERENCE.to_raw(p, params, cam, part, part, (y0, 0), seed=SEED,
                                            sample_index=SAMPLE)
        check("to_raw", spec, raw[y0:y0 + 64], ref_raw)
        check("saturate", spec, sat[y0:y0 + 64], ref_sat)


@pytest.mark.parametrize("spec", [s for s in KERNEL_BACKEND_SPECS if spec_backend(s) == "warp"])
def test_warp_refuses_buffers_beyond_its_32_bit_indices_and_names_tiles(spec):
    from gpu_blur.backends.warp import MAX_BUFFER_VALUES

    # Warp arrays have int32 shapes (Warp itself refuses larger ones), so each of the
    # kernels' int32 offsets stays below its buffer's size; the backend refuses first, saying
    # what to do. A zero-stride view stands for the 26,800 x 26,800 image: nothing is allocated.
    linear = np.broadcast_to(np.float32(0.5), (26_800, 26_800, 3))
    assert linear.size > MAX_BUFFER_VALUES
    p, cam, params = prepare(spec, {"blur": {"mode": "none"}}, linear.shape[:2])
    with pytest.raises(ValueError, match=r"32-bit.*tile=\(4096, 4096\)"):
        make_backend(spec).to_raw(p, params, cam, linear, linear, seed=SEED,
                                  sample_index=SAMPLE)


# -- properties --------------------------------------------------------------------------------

unit_floats = st.floats(0.0, 1.0, allow_nan=False, allow_subnormal=True)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@settings(max_examples=20, deadline=None)
@given(values=st.lists(unit_floats, min_size=1, max_size=40))
def test_srgb_decode_property_on_every_backend(spec, values):
    x = np.sort(on_device(spec, values))
    got = decode_on(spec, x)
    check("srgb_to_linear", spec, got, transfer.srgb_to_linear(x))
    assert np.all(np.diff(got) >= 0)


@settings(max_examples=300, deadline=None)
@given(a=st.floats(0.0, 2.0, allow_nan=False), b=st.floats(0.0, 2.0, allow_nan=False))
def test_reference_transfer_functions_are_odd_monotone_and_finite(a, b):
    lo, hi = min(a, b), max(a, b)
    decode, encode = transfer.srgb_to_linear, transfer.linear_to_srgb
    for f in (decode, encode):
        assert np.isfinite(f(hi)) and f(-lo) == -f(lo) and f(-hi) == -f(hi)
    assert decode(lo) <= decode(hi)
    drop = encode(lo) - encode(hi)
    if lo < transfer.SRGB_ENCODE_KNEE <= hi:
        assert drop < 3.2e-8  # the IEC step, the one place the OETF goes down
    else:
        assert drop <= 0


@pytest.mark.slow
@pytest.mark.parametrize("spec", BACKEND_SPECS)
@settings(max_examples=12, deadline=None)
@given(colour=st.tuples(*[st.floats(0.001, 1.0)] * 3), red=st.floats(0.5, 4.0),
       blue=st.floats(0.5, 4.0), pattern=st.sampled_from(PATTERNS),
       method=st.sampled_from(["malvar2004", "bilinear"]), half=st.tuples(st.integers(1, 6),
                                                                          st.integers(1, 6)))
def test_flat_colour_survives_mosaic_white_balance_and_demosaic(spec, colour, red, blue,
                                                                pattern, method, half):
    shape = (2 * half[0], 2 * half[1])
    flat = np.broadcast_to(on_device(spec, colour), (*shape, 3)).copy()
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                "noise": {"model": "none"}, "isp": {"round_trip": "always", "demosaic": method},
                "output": {"bits": 0, "crf": "none"}}
    p, cam, params = prepare(spec, settings, shape, camera="srgb",
                             overrides={"pattern": pattern, "red_gain": red, "blue_gain": blue})
    backend = make_backend(spec)
    raw, sat = backend.to_raw(p, params, cam, flat, np.zeros_like(flat), seed=SEED,
                              sample_index=SAMPLE)
    whole = Region.whole(*shape)
    out = backend.finish(p, params, cam, raw, sat, whole, whole, seed=SEED, sample_index=SAMPLE)
    check("flat_field_passes", spec, out, flat)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@settings(max_examples=12, deadline=None)
@given(red=st.floats(0.25, 8.0), blue=st.floats(0.25, 8.0), pattern=st.sampled_from(PATTERNS),
       origin=st.tuples(st.integers(0, 3), st.integers(0, 3)), seed=st.integers(0, 2**32 - 1))
def test_white_balance_cancels_on_every_backend(spec, red, blue, pattern, origin, seed):
    linear = on_device(spec, np.random.default_rng(seed).uniform(0, 1.2, (6, 8, 3)))
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                "noise": {"model": "none"}, "isp": {"round_trip": "always"}}
    p, cam, params = prepare(spec, settings, linear.shape[:2], camera="srgb",
                             overrides={"pattern": pattern, "red_gain": red, "blue_gain": blue})
    raw, _ = make_backend(spec).to_raw(p, params, cam, linear, np.zeros_like(linear), origin,
                                       seed=SEED, sample_index=SAMPLE)
    # inverse white balance, then white balance: x / g * g, two roundings
    check("white_balance_round_trip", spec, raw,
          bayer.mosaic(linear, bayer.BayerPattern(pattern), origin))


_untiled: dict = {}


@pytest.mark.slow
@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@settings(max_examples=5, deadline=None)
@given(tile=st.tuples(st.integers(16, 30), st.integers(16, 30)))  # scheduler.MIN_TILE up
def test_tiling_invariance_property(spec, tile, coffee_rgb):
    photo = np.ascontiguousarray(coffee_rgb[236:260, 330:370])  # spoon highlights: saturated
    scene = scene_for(spec, {"blur": {"extent": [2.0, 6.0]}, "saturation": {"mode": "on"},
                             "output": {"bits": 0}})
    run = dict(seed=SEED, sample_index=SAMPLE, backend=backend_name(spec))
    if spec not in _untiled:
        _untiled[spec] = gpu_blur.synthesize([photo], scene, **run)
    whole = _untiled[spec]
    tiled = gpu_blur.synthesize([photo], scene, tile=tile, **run)
    assert np.array_equal(tiled.blurred, whole.blurred)
    assert np.array_equal(tiled.mask, whole.mask)
