"""Warp per-pixel device functions (gpu_blur/warp_kernels/pixel.py) against the numpy reference.

The Warp counterpart of tests/test_opencl_pixel.py, same cases. Small generic test kernels call
the device functions one value or one pixel per thread, instantiated for wp.float32 and
wp.float64, on Warp's "cpu" device and on "cuda:0" where CUDA is available. Inputs are rounded
to the instance's type first and the float64 reference is fed the same rounded values; the
constants the host passes (CRF coefficients, lookup table, matrices) are rounded for the device
but the reference keeps its float64 ones, so their rounding counts in the error.

The cfa packing is gpu_blur.backends.opencl.cfa_bits, copied below (one line) so that this file
needs no pyopencl; test_cfa_bits_layout checks the copy against the original where pyopencl
imports.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import numpy as np
import pytest

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

wp = pytest.importorskip("warp")
wp.config.quiet = True
px = pytest.importorskip("gpu_blur.warp_kernels.pixel")

# One build of this module per device, with every instance declared up front (wp.overload
# below): launching a new instance later would rebuild the module. No backward pass is needed.
wp.set_module_options({"enable_backward": False})

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
DTYPES = {"float32": wp.float32, "float64": wp.float64}
METHODS = {"malvar2004": (0, demosaic_malvar2004), "bilinear": (1, demosaic_bilinear)}
PATTERNS = list(BayerPattern)
BORDERS = {"reflect": 0, "zero": 1}


def cfa_bits(pattern) -> int:
    """gpu_blur.backends.opencl.cfa_bits, copied: channels at the cell sites, 2 bits each."""
    return sum(c << (2 * i) for i, c in enumerate(BayerPattern(pattern).channels))


# -- test kernels --------------------------------------------------------------------------------


@wp.kernel
def k_reflect101(i: wp.array(dtype=int), n: int, out: wp.array(dtype=int)):
    k = wp.tid()
    out[k] = px.reflect101(i[k], n)


@wp.kernel
def k_cfa_channel(gx: wp.array(dtype=int), gy: wp.array(dtype=int), cfa: int,
                  out: wp.array(dtype=int)):
    k = wp.tid()
    out[k] = px.cfa_channel(cfa, gx[k], gy[k])


@wp.kernel
def k_srgb_to_linear(x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.srgb_to_linear(x[i])


@wp.kernel
def k_decode_knee(x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.srgb_decode_knee(x[i])


@wp.kernel
def k_linear_to_srgb(x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.linear_to_srgb(x[i])


@wp.kernel
def k_polynomial_crf(x: wp.array(dtype=Any), y: wp.array(dtype=Any), c: wp.array(dtype=Any),
                     n: int):
    i = wp.tid()
    y[i] = px.polynomial_crf(x[i], c, n)


@wp.kernel
def k_lookup_crf(x: wp.array(dtype=Any), y: wp.array(dtype=Any), rendered: wp.array(dtype=Any),
                 n: int):
    i = wp.tid()
    y[i] = px.lookup_crf(x[i], rendered, n)


@wp.kernel
def k_apply_matrix(x: wp.array(dtype=Any), y: wp.array(dtype=Any), m: wp.array(dtype=Any)):
    i = wp.tid()
    v = px.apply_matrix(m, wp.vector(x[3 * i], x[3 * i + 1], x[3 * i + 2]))
    y[3 * i] = v[0]
    y[3 * i + 1] = v[1]
    y[3 * i + 2] = v[2]


@wp.kernel
def k_quantize(x: wp.array(dtype=Any), y: wp.array(dtype=Any), bits: int,
               code: wp.array(dtype=int)):
    i = wp.tid()
    code[i] = px.quantize_code(x[i], bits)
    y[i] = px.quantize(x[i], bits)


@wp.kernel
def k_demosaic(raw: wp.array(dtype=Any), out: wp.array(dtype=Any), x0: int, y0: int, w: int,
               full_w: int, full_h: int, ox: int, oy: int, ow: int, cfa: int, zero_border: int,
               method: int):
    """Demosaic the window [ox, ox + ow) x [oy, oy + oh) of the full image (launch dim (oh, ow))
    from the view (x0, y0, w) into out, oh x ow x 3 of the window.
    """
    j, i = wp.tid()
    o = 3 * (j * ow + i)
    if method == 0:
        rgb = px.demosaic_malvar2004(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa,
                                     zero_border)
        for c in range(3):
            out[o + c] = rgb[c]
    else:
        rgb = px.demosaic_bilinear(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa,
                                   zero_border)
        for c in range(3):
            out[o + c] = rgb[c]


def _declare_instances():
    """Every generic kernel's float32 and float64 instances, declared before the first build."""
    for real in DTYPES.values():
        arr = wp.array(dtype=real)
        for kernel in (k_srgb_to_linear, k_linear_to_srgb, k_decode_knee):
            wp.overload(kernel, [arr, arr])
        for kernel in (k_polynomial_crf, k_lookup_crf):
            wp.overload(kernel, [arr, arr, arr, int])
        wp.overload(k_apply_matrix, [arr, arr, arr])
        wp.overload(k_quantize, [arr, arr, int, wp.array(dtype=int)])
        wp.overload(k_demosaic, [arr, arr] + [int] * 11)


_declare_instances()


# -- host side -----------------------------------------------------------------------------------


class Build:
    """One device and one compute type, with helpers to run the test kernels."""

    def __init__(self, device: str, dtype: str):
        self.device = device
        self.dtype = dtype
        self.real = np.dtype(dtype)
        self.wp_real = DTYPES[dtype]

    def __repr__(self) -> str:
        return f"Build({self.device!r}, {self.dtype!r})"

    def array(self, values):
        """A flat device array of `values` in the build's type."""
        host = np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(-1))
        return wp.array(host.astype(self.real), dtype=self.wp_real, device=self.device)

    def rounded(self, values) -> np.ndarray:
        """Values as the build holds them, back in float64 for the reference."""
        return np.asarray(values, dtype=np.float64).astype(self.real).astype(np.float64)

    def map1(self, kernel, x, *extra, per_item: int = 1) -> np.ndarray:
        """Run kernel(x, y, *extra) on x (rounded to the build's type), per_item values each."""
        x_dev = self.array(x)
        y_dev = wp.empty_like(x_dev)
        wp.launch(kernel, dim=x_dev.shape[0] // per_item, inputs=[x_dev, y_dev, *extra],
                  device=self.device)
        return y_dev.numpy().astype(np.float64)

    def demosaic(self, view, x0, y0, full_shape, window, pattern, border, method) -> np.ndarray:
        """Demosaic the window (ox, oy, ow, oh) from the view whose first pixel is (x0, y0)."""
        ox, oy, ow, oh = window
        raw = self.array(view)
        out = wp.empty(oh * ow * 3, dtype=self.wp_real, device=self.device)
        wp.launch(k_demosaic, dim=(oh, ow), device=self.device, inputs=[
            raw, out, x0, y0, view.shape[1], full_shape[1], full_shape[0], ox, oy, ow,
            cfa_bits(pattern), BORDERS[border], METHODS[method][0]])  # fmt: skip
        return out.numpy().astype(np.float64).reshape(oh, ow, 3)

    def demosaic_whole(self, raw, pattern, border, method) -> np.ndarray:
        h, w = raw.shape
        return self.demosaic(raw, 0, 0, raw.shape, (0, 0, w, h), pattern, border, method)


@pytest.fixture(scope="module", params=[(d, t) for d in DEVICES for t in DTYPES],
                ids=lambda p: f"{p[0]}-{p[1]}")
def built(request) -> Build:
    return Build(*request.param)


@pytest.fixture(scope="module", params=DEVICES)
def device(request) -> str:
    return request.param


# -- geometry ------------------------------------------------------------------------------------


def test_cfa_bits_layout():
    assert cfa_bits(BayerPattern.RGGB) == 0 | 1 << 2 | 1 << 4 | 2 << 6
    try:
        from gpu_blur.backends.opencl import cfa_bits as opencl_cfa_bits
    except ImportError:
        opencl_cfa_bits = None
    for pattern in PATTERNS:
        bits = cfa_bits(pattern)
        for row in range(3):
            for col in range(3):
                site = ((row & 1) << 1) | (col & 1)
                assert (bits >> (2 * site)) & 3 == pattern.channel_at(row, col)
        if opencl_cfa_bits is not None:
            assert bits == opencl_cfa_bits(pattern.value)


def test_cfa_channel(device):
    """cfa_channel = the pattern's channel at any global position, negative ones included."""
    gy, gx = np.mgrid[-3:4, -3:4]
    gx, gy = gx.ravel().astype(np.int32), gy.ravel().astype(np.int32)
    for pattern in PATTERNS:
        out = wp.empty(gx.size, dtype=int, device=device)
        wp.launch(k_cfa_channel, dim=gx.size, device=device, inputs=[
            wp.array(gx, dtype=int, device=device), wp.array(gy, dtype=int, device=device),
            cfa_bits(pattern), out])  # fmt: skip
        expected = [pattern.channel_at(int(r), int(c)) for r, c in zip(gy, gx, strict=True)]
        assert out.numpy().tolist() == expected, pattern


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7, 64])
def test_reflect101_is_the_reference_mirror(device, n):
    """reflect101 = the reference's repeated mirroring, tiny axes included."""
    pad = 2 * n + 5
    positions = np.arange(-pad, n + pad, dtype=np.int32)
    out = wp.empty(positions.size, dtype=int, device=device)
    wp.launch(k_reflect101, dim=positions.size, device=device,
              inputs=[wp.array(positions, dtype=int, device=device), n, out])
    assert np.array_equal(out.numpy(), _reflect_indices(n, pad))


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
    "kernel, stage, reference",
    [
        (k_srgb_to_linear, "srgb_to_linear", srgb_to_linear),
        (k_linear_to_srgb, "linear_to_srgb", linear_to_srgb),
    ],
    ids=["srgb_to_linear", "linear_to_srgb"],
)
def test_srgb_transfer(built, kernel, stage, reference):
    x = built.rounded(transfer_inputs(built.real))
    got = built.map1(kernel, x)
    expected = reference(x)
    assert_close(got, expected, stage, "warp", built.dtype)
    # Odd extension and signed zero as np.copysign.
    assert np.array_equal(np.signbit(got), np.signbit(expected))
    assert np.isnan(built.map1(kernel, [np.nan]))[0]


def test_srgb_decode_knee(built):
    """The knee of each type makes `a < knee` pick the float64 reference's branch for every a of
    that type (gb_pixel.h: float32 needs the float next above 0.04045). The two branches agree
    to ~1e-10 there, so the transfer test alone could not tell a wrong branch.
    """
    knee = built.map1(k_decode_knee, [0.5])[0]
    x = ulp_steps([SRGB_DECODE_KNEE], built.real, 8).astype(built.real)
    assert np.array_equal(x < built.real.type(knee), x.astype(np.float64) < SRGB_DECODE_KNEE)
    if built.dtype == "float64":
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
    coefficients = built.array(A7R3_CRF_POLYNOMIAL)
    got = built.map1(k_polynomial_crf, x, coefficients, coefficients.shape[0])
    assert_close(got, polynomial_crf(x, A7R3_CRF_POLYNOMIAL), "crf_polynomial", "warp",
                 built.dtype)  # fmt: skip
    assert got.min() >= 0.0 and got.max() <= 1.0
    assert np.isnan(built.map1(k_polynomial_crf, [np.nan], coefficients, coefficients.shape[0]))[0]


def test_crf_lookup(built):
    n = A7R3_CRF_TABLE_X255.size
    nodes = np.linspace(0.0, 1.0, n)
    midpoints = (nodes[:-1] + nodes[1:]) / 2
    x = np.concatenate(
        [crf_inputs(built.real), ulp_steps(nodes, built.real, 2), midpoints, [-1.0, 2.0]]
    )
    x = built.rounded(x)
    rendered_host = np.asarray(A7R3_CRF_TABLE_X255 / 255.0, dtype=built.real)
    rendered = built.array(rendered_host)
    got = built.map1(k_lookup_crf, x, rendered, n)
    expected = lookup_crf(x, A7R3_CRF_TABLE_X255)
    assert_close(got, expected, "crf_lookup", "warp", built.dtype)
    # End behaviour: np.interp's end values (exactly the table's), then the clip; NaN stays.
    ends = built.map1(k_lookup_crf, [-1.0, 0.0, 1.0, 3.0, np.nan], rendered, n)
    assert ends[:4].tolist() == [rendered_host[0], rendered_host[0], rendered_host[-1],
                                 rendered_host[-1]]  # fmt: skip
    assert np.isnan(ends[4])


# -- colour matrices -----------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["camera_to_linear", "linear_to_camera"])
def test_apply_matrix(built, which, coffee_rgb):
    matrix = getattr(get_camera("a7r3"), which)
    rng = np.random.default_rng(5)
    pixels = np.concatenate(
        [srgb_to_linear(coffee_rgb[::4, ::4]).reshape(-1, 3), rng.uniform(-0.1, 1.2, (4096, 3))]
    )
    pixels = built.rounded(pixels)
    m = built.array(np.asarray(matrix).reshape(-1))
    got = built.map1(k_apply_matrix, pixels, m, per_item=3).reshape(-1, 3)
    assert_close(got, apply_matrix(pixels, matrix), "apply_matrix", "warp", built.dtype)


# -- quantization --------------------------------------------------------------------------------


def run_quantize(built, x, bits) -> tuple[np.ndarray, np.ndarray]:
    x_dev = built.array(x)
    values = wp.empty_like(x_dev)
    codes = wp.empty(x_dev.shape[0], dtype=int, device=built.device)
    wp.launch(k_quantize, dim=x_dev.shape[0], inputs=[x_dev, values, bits, codes],
              device=built.device)
    return codes.numpy(), values.numpy().astype(np.float64)


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
    if built.dtype == "float64":
        assert np.array_equal(values, quantize(x, bits))
    assert np.array_equal(np.rint(values * top), expected)


@pytest.mark.parametrize("bits", [8, 16])
def test_quantize_float64_inputs_exactly_rounded(device, bits):
    """float64 inputs next to the boundaries (k + 0.5) / top, float64 instance: the code is
    floor(x top + 1/2) of the exact product (the reference rounds x * top first and may differ
    there; float32 inputs make its product exact, see test_quantize_codes_exact).
    """
    built = Build(device, "float64")
    top = 2**bits - 1
    k = np.random.default_rng(bits).choice(top, min(top, 300), replace=False).astype(np.float64)
    x = ulp_steps((k + 0.5) / top, np.float64, 4)
    codes, _ = run_quantize(built, x, bits)
    exact = [int(Fraction(v) * top + Fraction(1, 2)) for v in x.tolist()]  # floor: x >= 0
    assert codes.tolist() == exact


# -- demosaicing ---------------------------------------------------------------------------------


def test_filters_are_the_references():
    """The Warp filters (the paper's figures, times 8 or 4) are the reference's arrays."""
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
def test_demosaic_photo(built, coffee_linear, border, method):
    for pattern in PATTERNS:
        raw = built.rounded(mosaic(coffee_linear, pattern))
        got = built.demosaic_whole(raw, pattern, border, method)
        expected = METHODS[method][1](raw, pattern, border=border)
        assert_close(got, expected, f"demosaic_{method}", "warp", built.dtype)


@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (6, 2), (4, 4)])
@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("border", list(BORDERS))
def test_demosaic_tiny(built, shape, border, method):
    # Sizes below the stencil: the mirror is applied again and again (period 2 (n - 1)).
    rng = np.random.default_rng(shape[0] * 10 + shape[1])
    raw = built.rounded(rng.uniform(0.0, 1.0, shape))
    for pattern in PATTERNS:
        got = built.demosaic_whole(raw, pattern, border, method)
        expected = METHODS[method][1](raw, pattern, border=border)
        assert_close(got, expected, f"demosaic_{method}", "warp", built.dtype)
    # A flat field stays flat under reflect, for every pattern (demosaic.py, "Tiny images").
    if border == "reflect":
        flat = np.full(shape, 0.375)
        for pattern in PATTERNS:
            assert np.array_equal(built.demosaic_whole(flat, pattern, border, method),
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
        whole = built.demosaic_whole(raw, pattern, border, method)
        for ox, oy, ow, oh in WINDOWS:
            x0, y0 = max(ox - halo, 0), max(oy - halo, 0)
            x1, y1 = min(ox + ow + halo, full_w), min(oy + oh + halo, full_h)
            expected = whole[oy : oy + oh, ox : ox + ow]
            # Only the window and its halo (clipped to the image): a tight buffer.
            tight = built.demosaic(raw[y0:y1, x0:x1], x0, y0, raw.shape, (ox, oy, ow, oh),
                                   pattern, border, method)  # fmt: skip
            assert np.array_equal(tight, expected), (pattern, (ox, oy, ow, oh))
            # The same view inside a NaN frame reaching past the image: any read outside the
            # halo (or outside the image) would show as NaN.
            frame = np.full((y1 - y0 + 6, x1 - x0 + 6), np.nan)
            frame[3:-3, 3:-3] = raw[y0:y1, x0:x1]
            framed = built.demosaic(frame, x0 - 3, y0 - 3, raw.shape, (ox, oy, ow, oh),
                                    pattern, border, method)  # fmt: skip
            assert np.array_equal(framed, expected), (pattern, (ox, oy, ow, oh))
