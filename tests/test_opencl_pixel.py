"""OpenCL per-pixel device functions (gb_pixel.h, gb_demosaic.h) against the numpy reference.

Small test kernels call the device functions one value or one pixel per work item, built twice:
``real`` = float and, where the device has cl_khr_fp64, ``real`` = double (``-DGB_FP64``). Inputs
are rounded to the build's type first and the float64 reference is fed the same rounded values;
the constants the host passes (CRF coefficients, lookup table, matrices) are rounded for the
device but the reference keeps its float64 ones, so their rounding counts in the error.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from gpu_blur.cameras import get_camera
from gpu_blur.constants import A7R3_CRF_POLYNOMIAL, A7R3_CRF_TABLE_X255
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

opencl = pytest.importorskip("gpu_blur.backends.opencl")
cfa_bits = opencl.cfa_bits

INCLUDE = Path(__file__).resolve().parents[1] / "kernels" / "opencl" / "include"

TEST_KERNELS = r"""
#include "gb_common.h"
#include "gb_pixel.h"
#include "gb_demosaic.h"

__kernel void t_reflect101(__global const long *i, __global long *out, long n)
{
    size_t k = get_global_id(0);
    out[k] = gb_reflect101(i[k], n);
}

__kernel void t_srgb_to_linear(__global const real *x, __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = gb_srgb_to_linear(x[i]);
}

__kernel void t_linear_to_srgb(__global const real *x, __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = gb_linear_to_srgb(x[i]);
}

__kernel void t_polynomial_crf(__global const real *x, __global real *y, __constant real *c, int n)
{
    size_t i = get_global_id(0);
    y[i] = gb_polynomial_crf(x[i], c, n);
}

__kernel void t_lookup_crf(__global const real *x, __global real *y,
                           __global const real *rendered, int n)
{
    size_t i = get_global_id(0);
    y[i] = gb_lookup_crf(x[i], rendered, n);
}

__kernel void t_apply_matrix(__global const real *x, __global real *y, __constant real *m)
{
    size_t i = get_global_id(0);
    real v[3] = {x[3 * i], x[3 * i + 1], x[3 * i + 2]};
    gb_apply_matrix(m, v, v); /* in place: the documented aliasing */
    y[3 * i] = v[0];
    y[3 * i + 1] = v[1];
    y[3 * i + 2] = v[2];
}

__kernel void t_quantize(__global const real *x, __global uint *code, __global real *q, int bits)
{
    size_t i = get_global_id(0);
    code[i] = gb_quantize_code(x[i], bits);
    q[i] = gb_quantize(x[i], bits);
}

/* Demosaic the window [ox, ox + get_global_size(0)) x [oy, ...) of the full image from the
 * view (x0, y0, w) into out, H x W x 3 of the window. */
__kernel void t_demosaic(__global const real *raw, long x0, long y0, long w, long full_w,
                         long full_h, long ox, long oy, int cfa, int zero_border, int method,
                         __global real *out)
{
    long i = get_global_id(0), j = get_global_id(1), ow = get_global_size(0);
    real rgb[3];
    if (method == 0) {
        gb_demosaic_malvar2004(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa, zero_border,
                               rgb);
    } else {
        gb_demosaic_bilinear(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa, zero_border,
                             rgb);
    }
    for (int c = 0; c < 3; ++c) out[3 * (j * ow + i) + c] = rgb[c];
}
"""

METHODS = {"malvar2004": (0, demosaic_malvar2004), "bilinear": (1, demosaic_bilinear)}
PATTERNS = list(BayerPattern)
BORDERS = {"reflect": 0, "zero": 1}


def test_cfa_bits_match_gb_cfa_channel_layout():
    assert cfa_bits(BayerPattern.RGGB) == 0 | 1 << 2 | 1 << 4 | 2 << 6
    for pattern in PATTERNS:
        bits = cfa_bits(pattern)
        for row in range(3):
            for col in range(3):
                site = ((row & 1) << 1) | (col & 1)
                assert (bits >> (2 * site)) & 3 == pattern.channel_at(row, col)


@pytest.fixture(scope="module")
def opencl_device(opencl_queue):
    return opencl_queue


class Built:
    """A build of TEST_KERNELS for one precision, with helpers to run its kernels."""

    def __init__(self, cl, context, queue, dtype: str):
        self.cl, self.context, self.queue = cl, context, queue
        self.dtype = dtype
        self.real = np.dtype(dtype)
        options = ["-I", str(INCLUDE)] + (["-DGB_FP64"] if dtype == "float64" else [])
        try:
            with warnings.catch_warnings():  # the compiler's log of a successful build
                warnings.simplefilter("ignore", cl.CompilerWarning)
                self.program = cl.Program(context, TEST_KERNELS).build(options=options)
        except cl.Error as err:
            pytest.fail(f"the pixel headers failed to build ({dtype}):\n{err}")
        self.kernels: dict[str, object] = {}

    def kernel(self, name: str):
        """The kernel `name`, retrieved once."""
        if name not in self.kernels:
            self.kernels[name] = self.cl.Kernel(self.program, name)
        return self.kernels[name]

    def to_device(self, array) -> object:
        mf = self.cl.mem_flags
        host = np.ascontiguousarray(array)
        return self.cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=host)

    def rounded(self, values) -> np.ndarray:
        """Values as the build holds them, back in float64 for the reference."""
        return np.asarray(values, dtype=np.float64).astype(self.real).astype(np.float64)

    def map1(self, name: str, x, *extra, per_item: int = 1) -> np.ndarray:
        """Run a kernel on x (rounded to the build's type), per_item values per work item."""
        host = np.ascontiguousarray(np.asarray(x, dtype=np.float64).astype(self.real))
        out = np.empty_like(host)
        out_buf = self.cl.Buffer(self.context, self.cl.mem_flags.WRITE_ONLY, out.nbytes)
        kernel = self.kernel(name)
        items = host.size // per_item
        kernel(self.queue, (items,), None, self.to_device(host), out_buf, *extra)
        self.cl.enqueue_copy(self.queue, out, out_buf)
        return out.astype(np.float64)

    def demosaic(self, view, x0, y0, full_shape, window, pattern, border, method) -> np.ndarray:
        """Demosaic the window (ox, oy, ow, oh) from the view whose first pixel is (x0, y0)."""
        ox, oy, ow, oh = window
        view = np.ascontiguousarray(view, dtype=self.real)
        out = np.empty((oh, ow, 3), dtype=self.real)
        out_buf = self.cl.Buffer(self.context, self.cl.mem_flags.WRITE_ONLY, out.nbytes)
        i64 = np.int64
        self.kernel("t_demosaic")(
            self.queue, (ow, oh), None, self.to_device(view),
            i64(x0), i64(y0), i64(view.shape[1]), i64(full_shape[1]), i64(full_shape[0]),
            i64(ox), i64(oy), np.int32(cfa_bits(pattern)), np.int32(BORDERS[border]),
            np.int32(METHODS[method][0]), out_buf,
        )  # fmt: skip
        self.cl.enqueue_copy(self.queue, out, out_buf)
        return out.astype(np.float64)

    def demosaic_whole(self, raw, pattern, border, method) -> np.ndarray:
        h, w = raw.shape
        return self.demosaic(raw, 0, 0, raw.shape, (0, 0, w, h), pattern, border, method)


@pytest.fixture(scope="module", params=["float32", "float64"])
def built(request, opencl_device) -> Built:
    cl, context, queue = opencl_device
    device = context.devices[0]
    if request.param == "float64" and "cl_khr_fp64" not in device.extensions:
        pytest.skip(f"{device.name} has no cl_khr_fp64")
    return Built(cl, context, queue, request.param)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7, 64])
def test_reflect101_is_the_reference_mirror(built, n):
    """gb_reflect101 (gb_common.h) = the reference's repeated mirroring, tiny axes included."""
    pad = 2 * n + 5
    positions = np.arange(-pad, n + pad, dtype=np.int64)
    out = np.empty_like(positions)
    out_buf = built.cl.Buffer(built.context, built.cl.mem_flags.WRITE_ONLY, out.nbytes)
    built.kernel("t_reflect101")(
        built.queue, (positions.size,), None, built.to_device(positions), out_buf, np.int64(n)
    )
    built.cl.enqueue_copy(built.queue, out, out_buf)
    assert np.array_equal(out, _reflect_indices(n, pad))


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
    got = built.map1(name, x)
    expected = reference(x)
    assert_close(got, expected, stage, "opencl", built.dtype)
    # Odd extension and signed zero as np.copysign.
    assert np.array_equal(np.signbit(got), np.signbit(expected))
    assert np.isnan(built.map1(name, [np.nan]))[0]


def crf_inputs(dtype) -> np.ndarray:
    specials = np.array([0.0, 1e-3, 1.1e-3, 0.862, 1.0, 1.0 / 2550, 0.5])
    tiny = np.finfo(dtype).smallest_subnormal
    return np.concatenate(
        [np.linspace(-0.1, 1.1, 20001), ulp_steps(specials, dtype), [tiny, -tiny, -0.0]]
    )


def test_crf_polynomial(built):
    x = built.rounded(crf_inputs(built.real))
    coefficients = np.asarray(A7R3_CRF_POLYNOMIAL, dtype=built.real)
    got = built.map1(
        "t_polynomial_crf", x, built.to_device(coefficients), np.int32(coefficients.size)
    )
    assert_close(got, polynomial_crf(x, A7R3_CRF_POLYNOMIAL), "crf_polynomial", "opencl",
                 built.dtype)  # fmt: skip
    assert got.min() >= 0.0 and got.max() <= 1.0


def test_crf_lookup(built):
    n = A7R3_CRF_TABLE_X255.size
    nodes = np.linspace(0.0, 1.0, n)
    midpoints = (nodes[:-1] + nodes[1:]) / 2
    x = np.concatenate(
        [crf_inputs(built.real), ulp_steps(nodes, built.real, 2), midpoints, [-1.0, 2.0]]
    )
    x = built.rounded(x)
    rendered = np.asarray(A7R3_CRF_TABLE_X255 / 255.0, dtype=built.real)
    got = built.map1("t_lookup_crf", x, built.to_device(rendered), np.int32(n))
    expected = lookup_crf(x, A7R3_CRF_TABLE_X255)
    assert_close(got, expected, "crf_lookup", "opencl", built.dtype)
    # End behaviour: np.interp's end values (exactly the table's), then the clip.
    ends = built.map1("t_lookup_crf", [-1.0, 0.0, 1.0, 3.0], built.to_device(rendered), np.int32(n))
    assert ends.tolist() == [rendered[0], rendered[0], rendered[-1], rendered[-1]]


@pytest.mark.parametrize("which", ["camera_to_linear", "linear_to_camera"])
def test_apply_matrix(built, which, coffee_rgb):
    matrix = getattr(get_camera("a7r3"), which)
    rng = np.random.default_rng(5)
    pixels = np.concatenate(
        [srgb_to_linear(coffee_rgb[::4, ::4]).reshape(-1, 3), rng.uniform(-0.1, 1.2, (4096, 3))]
    )
    pixels = built.rounded(pixels)
    m = np.asarray(matrix, dtype=built.real)
    got = built.map1("t_apply_matrix", pixels.reshape(-1), built.to_device(m), per_item=3)
    got = got.reshape(-1, 3)
    expected = apply_matrix(pixels, matrix)
    assert_close(got, expected, "apply_matrix", "opencl", built.dtype)


@pytest.mark.parametrize("bits", [8, 16])
def test_quantize_codes_exact(built, bits):
    top = 2**bits - 1
    k = np.arange(top + 1, dtype=np.float64)
    # On the grid, on the rounding boundaries (k + 0.5) / top, a few float32 ulps around both,
    # and outside [0, 1]; float32 inputs, as the pipeline's output buffers hold.
    x = ulp_steps(np.concatenate([k / top, (k + 0.5) / top]), np.float32, 3)
    x = np.concatenate([x, [-1.0, -1e-30, -0.0, 1.0 + 2**-23, 2.0]]).astype(np.float32)
    x = x.astype(np.float64)
    cl = built.cl
    host = np.ascontiguousarray(x.astype(built.real))
    codes = np.empty(host.size, dtype=np.uint32)
    values = np.empty_like(host)
    codes_buf = cl.Buffer(built.context, cl.mem_flags.WRITE_ONLY, codes.nbytes)
    values_buf = cl.Buffer(built.context, cl.mem_flags.WRITE_ONLY, values.nbytes)
    built.kernel("t_quantize")(
        built.queue, (host.size,), None, built.to_device(host), codes_buf, values_buf,
        np.int32(bits),
    )  # fmt: skip
    cl.enqueue_copy(built.queue, codes, codes_buf)
    cl.enqueue_copy(built.queue, values, values_buf)
    expected = to_integers(x, bits).astype(np.uint32)
    bad = np.flatnonzero(codes != expected)
    assert bad.size == 0, (
        f"{bad.size} codes differ, first x={x[bad[0]]!r}: {codes[bad[0]]} vs {expected[bad[0]]}"
    )
    # The values are the codes over top: exactly the reference in double; in float the one
    # division by top is the only rounding, so they still give the codes back.
    if built.dtype == "float64":
        assert np.array_equal(values, quantize(x, bits))
    assert np.array_equal(np.rint(values.astype(np.float64) * top), expected)


@pytest.fixture(scope="module")
def coffee_linear(coffee_rgb) -> np.ndarray:
    """A 64 x 96 crop of the photograph with edges and texture, linear sRGB."""
    return srgb_to_linear(coffee_rgb[150:214, 260:356])


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("border", list(BORDERS))
@pytest.mark.parametrize("pattern", PATTERNS, ids=[p.value for p in PATTERNS])
def test_demosaic_photo(built, coffee_linear, pattern, border, method):
    raw = built.rounded(mosaic(coffee_linear, pattern))
    got = built.demosaic_whole(raw, pattern, border, method)
    expected = METHODS[method][1](raw, pattern, border=border)
    assert_close(got, expected, f"demosaic_{method}", "opencl", built.dtype)


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
        assert_close(got, expected, f"demosaic_{method}", "opencl", built.dtype)
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
    pattern_list = [BayerPattern.GRBG, BayerPattern.BGGR]
    for pattern in pattern_list:
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
