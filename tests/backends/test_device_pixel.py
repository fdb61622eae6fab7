"""Per-pixel device functions against the numpy reference, in both kernel languages.

OpenCL: gb_common.h, gb_pixel.h, gb_demosaic.h, built with ``real`` = float and, where the device
has cl_khr_fp64, ``real`` = double (``-DGB_FP64``). Warp: gpu_blur/warp_kernels/pixel.py,
instantiated for wp.float32 and wp.float64 (Warp's default ``fuse_fp=True``). The probes are in
tests/device_functions/pixel.cl and pixel_warp.py. Inputs are rounded to the build's type first
and the float64 reference is fed the same rounded values; the constants the host passes (CRF
coefficients, lookup table, matrices) are rounded for the device but the reference keeps its
float64 ones, so their rounding counts in the error.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from device_functions import target_fixture, target_specs

from gpu_blur.backends import cfa_bits
from gpu_blur.cameras import get_camera
from gpu_blur.constants import A7R3_CRF_POLYNOMIAL, A7R3_CRF_TABLE_X255
from gpu_blur.reference import demosaic as reference_demosaic
from gpu_blur.reference.bayer import BayerPattern, mosaic
from gpu_blur.reference.color import apply_matrix
from gpu_blur.reference.demosaic import (
    HALO,
    _reflect_indices,
    demosaic_bilinear,
    demosaic_malvar2004,
)
from gpu_blur.reference.output import quantize, to_integers
from gpu_blur.reference.transfer import (
    SRGB_DECODE_KNEE,
    SRGB_ENCODE_KNEE,
    linear_to_srgb,
    lookup_crf,
    polynomial_crf,
    srgb_to_linear,
)
from gpu_blur.testing import assert_close

METHODS = {"malvar2004": (0, demosaic_malvar2004), "bilinear": (1, demosaic_bilinear)}
PATTERNS = list(BayerPattern)
BORDERS = {"reflect": 0, "zero": 1}


built = target_fixture(target_specs("pixel"))
built64 = target_fixture(target_specs("pixel", ["float64"]))


def map1(built, name, x, *extra, per_item: int = 1) -> np.ndarray:
    """Run probe ``name`` on x (rounded to the build's type), per_item values per work item;
    ``extra`` arguments follow x, the output comes last."""
    host = np.asarray(x, dtype=np.float64).astype(built.real)
    (y,) = built.run(name, host.size // per_item, [host, *extra], [(host.shape, built.real)])
    return y.astype(np.float64)


def device_array(built, values) -> np.ndarray:
    """A constant the host passes, in the build's type."""
    return np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(-1),
                                dtype=built.real)


def demosaic(built, view, x0, y0, full_shape, window, pattern, border, method) -> np.ndarray:
    """Demosaic the window (ox, oy, ow, oh) from the view whose first pixel is (x0, y0)."""
    ox, oy, ow, oh = window
    args = [x0, y0, view.shape[1], full_shape[1], full_shape[0], ox, oy, ow, cfa_bits(pattern),
            BORDERS[border], METHODS[method][0]]
    (out,) = built.run("t_demosaic", ow * oh, [device_array(built, view),
                                                *(np.int32(a) for a in args)],
                       [((oh, ow, 3), built.real)])
    return out.astype(np.float64)


def demosaic_whole(built, raw, pattern, border, method) -> np.ndarray:
    h, w = raw.shape
    return demosaic(built, raw, 0, 0, raw.shape, (0, 0, w, h), pattern, border, method)


# -- geometry ------------------------------------------------------------------------------------


def test_cfa_bits_match_gb_cfa_channel_layout():
    assert cfa_bits(BayerPattern.RGGB) == 0 | 1 << 2 | 1 << 4 | 2 << 6
    for pattern in PATTERNS:
        bits = cfa_bits(pattern)
        for row in range(3):
            for col in range(3):
                site = ((row & 1) << 1) | (col & 1)
                assert (bits >> (2 * site)) & 3 == pattern.channel_at(row, col)


def test_cfa_channel(built):
    """cfa_channel = the pattern's channel at any global position, negative ones included."""
    gy, gx = np.mgrid[-3:4, -3:4]
    gx, gy = gx.ravel().astype(np.int32), gy.ravel().astype(np.int32)
    for pattern in PATTERNS:
        (out,) = built.run("t_cfa_channel", gx.size, [gx, gy, np.int32(cfa_bits(pattern))],
                           [(gx.size, np.int32)])
        expected = [pattern.channel_at(int(r), int(c)) for r, c in zip(gy, gx, strict=True)]
        assert out.tolist() == expected, pattern


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7, 64])
def test_reflect101_is_the_reference_mirror(built, n):
    """reflect101 = the reference's repeated mirroring, tiny axes included."""
    pad = 2 * n + 5
    positions = np.arange(-pad, n + pad, dtype=np.int32)
    (out,) = built.run("t_reflect101", positions.size, [positions, np.int32(n)],
                       [(positions.size, np.int32)])
    assert np.array_equal(out, _reflect_indices(n, pad))


# -- transfer curves -----------------------------------------------------------------------------


def ulp_steps(values, dtype, steps=3) -> np.ndarray:
    """Each value and its `steps` nearest neighbours on each side in dtype, as float64."""
    v = np.asarray(values, dtype=dtype)
    out = [v]
    up, down = v.copy(), v.copy()
    for _ in range(steps):
        up = np.nextafter(up, np.asarray(np.inf, dtype))
        down = np.nextafter(down, np.asarray(-np.inf, dtype))
        out += [up, down]
    return np.concatenate(out).astype(np.float64)


def transfer_inputs(dtype) -> np.ndarray:
    """[-0.1, 1.1] densely, both knees and 1 to a few ulps, zeros and denormals, both signs."""
    tiny = np.finfo(dtype).smallest_subnormal
    specials = np.array(
        [0.0, -0.0, tiny, 3 * tiny, np.finfo(dtype).tiny, 1e-30, 1.0, SRGB_DECODE_KNEE,
         SRGB_ENCODE_KNEE, 12.92 * SRGB_ENCODE_KNEE, 0.5]
    )  # fmt: skip
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001), ulp_steps(specials, dtype)])
    return np.concatenate([x, -x])


@pytest.mark.parametrize(
    "name, stage, reference",
    [
        ("t_srgb_to_linear", "srgb_to_linear", srgb_to_linear),
        ("t_linear_to_srgb", "linear_to_srgb", linear_to_srgb),
    ],
)
def test_srgb_transfer(built, name, stage, reference):
    x = built.rounded(transfer_inputs(built.real))
    got = map1(built, name, x)
    expected = reference(x)
    assert_close(got, expected, stage, built.lang, built.build)
    # Odd extension and signed zero as np.copysign.
    assert np.array_equal(np.signbit(got), np.signbit(expected))
    assert np.isnan(map1(built, name, [np.nan]))[0]


def test_srgb_decode_knee(built):
    """The knee of each type makes `a < knee` pick the float64 reference's branch for every a of
    that type (gb_pixel.h: float32 needs the float next above 0.04045). The two branches agree
    to ~1e-10 there, so the transfer test alone could not tell a wrong branch.
    """
    knee = map1(built, "t_decode_knee", [0.5])[0]
    x = ulp_steps([SRGB_DECODE_KNEE], built.real, 8).astype(built.real)
    assert np.array_equal(x < built.real.type(knee), x.astype(np.float64) < SRGB_DECODE_KNEE)
    if built.real == np.float64:
        assert knee == SRGB_DECODE_KNEE
    else:
        assert knee == np.nextafter(np.float32(SRGB_DECODE_KNEE), np.float32(1.0))


# -- camera responses ----------------------------------------------------------------------------


def crf_inputs(dtype) -> np.ndarray:
    specials = np.array([0.0, 1e-3, 1.1e-3, 0.862, 1.0, 1.0 / 2550, 0.5])
    tiny = np.finfo(dtype).smallest_subnormal
    return np.concatenate(
        [np.linspace(-0.1, 1.1, 20001), ulp_steps(specials, dtype), [tiny, -tiny, -0.0]]
    )


def test_crf_polynomial(built):
    x = built.rounded(crf_inputs(built.real))
    coefficients = device_array(built, A7R3_CRF_POLYNOMIAL)
    n = np.int32(coefficients.size)
    got = map1(built, "t_polynomial_crf", x, coefficients, n)
    assert_close(got, polynomial_crf(x, A7R3_CRF_POLYNOMIAL), "crf_polynomial", built.lang,
                 built.build)  # fmt: skip
    assert got.min() >= 0.0 and got.max() <= 1.0
    assert np.isnan(map1(built, "t_polynomial_crf", [np.nan], coefficients, n))[0]


def test_crf_lookup(built):
    n = A7R3_CRF_TABLE_X255.size
    nodes = np.linspace(0.0, 1.0, n)
    midpoints = (nodes[:-1] + nodes[1:]) / 2
    x = np.concatenate(
        [crf_inputs(built.real), ulp_steps(nodes, built.real, 2), midpoints, [-1.0, 2.0]]
    )
    x = built.rounded(x)
    rendered = device_array(built, A7R3_CRF_TABLE_X255 / 255.0)
    got = map1(built, "t_lookup_crf", x, rendered, np.int32(n))
    expected = lookup_crf(x, A7R3_CRF_TABLE_X255)
    assert_close(got, expected, "crf_lookup", built.lang, built.build)
    # End behaviour: np.interp's end values (exactly the table's), then the clip; NaN stays.
    ends = map1(built, "t_lookup_crf", [-1.0, 0.0, 1.0, 3.0, np.nan], rendered, np.int32(n))
    assert ends[:4].tolist() == [rendered[0], rendered[0], rendered[-1], rendered[-1]]
    assert np.isnan(ends[4])


# -- colour matrices -----------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["camera_to_linear", "linear_to_camera"])
@pytest.mark.bits
def test_apply_matrix(built, which, coffee_rgb):
    matrix = getattr(get_camera("a7r3"), which)
    rng = np.random.default_rng(5)
    pixels = np.concatenate(
        [srgb_to_linear(coffee_rgb[::4, ::4]).reshape(-1, 3), rng.uniform(-0.1, 1.2, (4096, 3))]
    )
    pixels = built.rounded(pixels)
    got = map1(built, "t_apply_matrix", pixels, device_array(built, matrix), per_item=3)
    assert_close(got, apply_matrix(pixels, matrix), "apply_matrix", built.lang, built.build)


# -- quantization --------------------------------------------------------------------------------


def run_quantize(built, x, bits) -> tuple[np.ndarray, np.ndarray]:
    host = np.asarray(x).astype(built.real)
    codes, values = built.run("t_quantize", host.size, [host, np.int32(bits)],
                              [(host.size, np.int32), (host.size, built.real)])
    return codes, values.astype(np.float64)


@pytest.mark.parametrize("bits", [8, 16])
def test_quantize_codes_exact(built, bits):
    top = 2**bits - 1
    k = np.arange(top + 1, dtype=np.float64)
    # On the grid, on the rounding boundaries (k + 0.5) / top, a few float32 ulps around both,
    # and outside [0, 1]; float32 inputs, as the pipeline's output buffers hold.
    x = ulp_steps(np.concatenate([k / top, (k + 0.5) / top]), np.float32, 3)
    x = np.concatenate([x, [-1.0, -1e-30, -0.0, 1.0 + 2**-23, 2.0]]).astype(np.float32)
    x = x.astype(np.float64)
    codes, values = run_quantize(built, x, bits)
    expected = to_integers(x, bits).astype(np.int64)
    bad = np.flatnonzero(codes != expected)
    assert bad.size == 0, (
        f"{bad.size} codes differ, first x={x[bad[0]]!r}: {codes[bad[0]]} vs {expected[bad[0]]}"
    )
    # The values are the codes over top: exactly the reference in double; in float the one
    # division by top is the only rounding, so they still give the codes back.
    if built.real == np.float64:
        assert np.array_equal(values, quantize(x, bits))
    assert np.array_equal(np.rint(values * top), expected)


@pytest.mark.parametrize("bits", [8, 16])
def test_quantize_float64_inputs_exactly_rounded(built64, bits):
    """float64 inputs next to the boundaries (k + 0.5) / top, float64 build: the code is
    floor(x top + 1/2) of the exact product (the reference rounds x * top first and may differ
    there; float32 inputs make its product exact, see test_quantize_codes_exact).
    """
    top = 2**bits - 1
    k = np.random.default_rng(bits).choice(top, min(top, 300), replace=False).astype(np.float64)
    x = ulp_steps((k + 0.5) / top, np.float64, 4)
    codes, _ = run_quantize(built64, x, bits)
    exact = [int(Fraction(v) * top + Fraction(1, 2)) for v in x.tolist()]  # floor: x >= 0
    assert codes.tolist() == exact


# -- demosaicing ---------------------------------------------------------------------------------


def test_warp_filters_are_the_references():
    """The Warp filters (the paper's figures, times 8 or 4) are the reference's arrays."""
    px = pytest.importorskip("gpu_blur.warp_kernels.pixel")
    pairs = [
        (px.MALVAR2004_G_AT_RB, reference_demosaic.MALVAR2004_G_AT_RB, 8.0),
        (px.MALVAR2004_RB_AT_G_ROW, reference_demosaic.MALVAR2004_RB_AT_G_ROW, 8.0),
        (px.MALVAR2004_RB_AT_G_COLUMN, reference_demosaic.MALVAR2004_RB_AT_G_COLUMN, 8.0),
        (px.MALVAR2004_RB_AT_BR, reference_demosaic.MALVAR2004_RB_AT_BR, 8.0),
        (px.BILINEAR_G, reference_demosaic.BILINEAR_G, 4.0),
        (px.BILINEAR_RB, reference_demosaic.BILINEAR_RB, 4.0),
    ]
    for ours, theirs, scale in pairs:
        assert np.array_equal(np.array(ours, dtype=np.float64).reshape(theirs.shape) / scale,
                              theirs)


@pytest.fixture(scope="module")
def coffee_linear(coffee_rgb) -> np.ndarray:
    """A 64 x 96 crop of the photograph with edges and texture, linear sRGB."""
    return srgb_to_linear(coffee_rgb[150:214, 260:356])


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("border", list(BORDERS))
@pytest.mark.parametrize("pattern", PATTERNS, ids=[p.value for p in PATTERNS])
@pytest.mark.bits
def test_demosaic_photo(built, coffee_linear, pattern, border, method):
    raw = built.rounded(mosaic(coffee_linear, pattern))
    got = demosaic_whole(built, raw, pattern, border, method)
    expected = METHODS[method][1](raw, pattern, border=border)
    assert_close(got, expected, f"demosaic_{method}", built.lang, built.build)


@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (6, 2), (4, 4)])
@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("border", list(BORDERS))
def test_demosaic_tiny(built, shape, border, method):
    # Sizes below the stencil: the mirror is applied again and again (period 2 (n - 1)).
    rng = np.random.default_rng(shape[0] * 10 + shape[1])
    raw = built.rounded(rng.uniform(0.0, 1.0, shape))
    for pattern in PATTERNS:
        got = demosaic_whole(built, raw, pattern, border, method)
        expected = METHODS[method][1](raw, pattern, border=border)
        assert_close(got, expected, f"demosaic_{method}", built.lang, built.build)
    # A flat field stays flat under reflect, for every pattern (demosaic.py, "Tiny images").
    if border == "reflect":
        flat = np.full(shape, 0.375)
        for pattern in PATTERNS:
            assert np.array_equal(demosaic_whole(built, flat, pattern, border, method),
                                  np.full(shape + (3,), 0.375))  # fmt: skip


#: Windows (ox, oy, ow, oh) of the 64 x 96 crop: corners at the image edges, the interior, odd
#: offsets and sizes that cut the Bayer cell, a 1-px window at the far corner.
WINDOWS = [
    (0, 0, 9, 7),
    (13, 11, 10, 9),
    (16, 8, 12, 10),
    (87, 57, 9, 7),
    (95, 63, 1, 1),
    (1, 30, 3, 5),
    (40, 0, 7, 3),
]


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("border", list(BORDERS))
def test_demosaic_tile_view_bitwise(built, coffee_linear, border, method):
    """A view of a window plus the method's halo gives the whole-image values, bitwise."""
    halo = HALO[method]
    for pattern in (BayerPattern.GRBG, BayerPattern.BGGR):
        raw = built.rounded(mosaic(coffee_linear, pattern))
        full_h, full_w = raw.shape
        whole = demosaic_whole(built, raw, pattern, border, method)
        for ox, oy, ow, oh in WINDOWS:
            x0, y0 = max(ox - halo, 0), max(oy - halo, 0)
            x1, y1 = min(ox + ow + halo, full_w), min(oy + oh + halo, full_h)
            expected = whole[oy : oy + oh, ox : ox + ow]
            # Only the window and its halo (clipped to the image): a tight buffer.
            tight = demosaic(built, raw[y0:y1, x0:x1], x0, y0, raw.shape, (ox, oy, ow, oh),
                             pattern, border, method)  # fmt: skip
            assert np.array_equal(tight, expected), (pattern, (ox, oy, ow, oh))
            # The same view inside a NaN frame reaching past the image: any read outside the
            # halo (or outside the image) would show as NaN.
            frame = np.full((y1 - y0 + 6, x1 - x0 + 6), np.nan)
            frame[3:-3, 3:-3] = raw[y0:y1, x0:x1]
            framed = demosaic(built, frame, x0 - 3, y0 - 3, raw.shape, (ox, oy, ow, oh),
                              pattern, border, method)  # fmt: skip
            assert np.array_equal(framed, expected), (pattern, (ox, oy, ow, oh))
