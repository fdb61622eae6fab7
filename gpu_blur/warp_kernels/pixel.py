"""Per-pixel maths of the pipeline as Warp device functions (``@wp.func``); no kernels.

The Warp port of kernels/opencl/include/gb_common.h, gb_pixel.h and gb_demosaic.h, function for
function, with the same maths, the same branch rules and the same order of summation. Each
function computes what its numpy float64 reference computes:

    reflect101, cfa_channel             gb_reflect101 / gb_cfa_channel (reference.demosaic's
                                        mirror, reference.bayer's cell)
    srgb_to_linear, linear_to_srgb      reference.transfer.srgb_to_linear / linear_to_srgb
    clip01                              np.clip(x, 0, 1)
    polynomial_crf, lookup_crf          reference.transfer.polynomial_crf / lookup_crf
    apply_matrix                        reference.color.apply_matrix
    quantize_code, quantize             reference.output.to_integers / quantize
    demosaic_malvar2004,                reference.demosaic.demosaic_malvar2004 /
    demosaic_bilinear                   demosaic_bilinear (border "reflect" or "zero")

NaN goes through every function as NaN (as in numpy), except quantize_code, where the code of a
NaN is undefined (numpy's cast of NaN to an integer is too).

Generic pattern (one source for float32 and float64). Real parameters are annotated
``typing.Any`` (arrays ``wp.array(dtype=Any)``); Warp makes one instance of the function per
concrete type it is called with, ``wp.float32`` or ``wp.float64`` (and the arrays and scalars of
one call must share that type). Inside, a literal of the compute type is written
``type(x)(0.055)`` (``raw.dtype(0.0)`` for an array's element type): Warp folds a literal under
a scalar constructor into one constant of the target type, so the generated code holds
``float64 v = 0.055`` (the double nearest 0.055) in the float64 instance and
``const float32 v = 0.055`` in the float32 one, which C++ rounds from that double; for every
constant here the float so obtained is the float nearest the decimal (checked: no double
rounding), i.e. OpenCL's ``0.055f``. A bare literal would be float32 in both instances: never
use one in arithmetic with a real. Where the two types need different constants (the sRGB decode
knee), or a native function (fma), there are two overloads of one function, annotated
``wp.float32`` and ``wp.float64``, and the generic code calls it by name. Three values come back
as a 3-vector ``wp.vector(r, g, b)``: ``wp.types.vector(length=3, dtype=T)`` of the compute type
(``wp.vec3f`` / ``wp.vec3d``).

Geometry is Warp ``int`` (int32), as Python ints of the host: coordinates, sizes and offsets
into a buffer view. An offset ``(gy - y0) * w + (gx - x0)`` must stay below 2^31, so a view
holds at most 2^31 pixels (and a flat RGB buffer 2^31 values, ~715 M pixels), and an axis of the
full image at most 2^30 pixels (reflect101's period 2 (n - 1)); beyond that, the offsets and
reflect101 would need wp.int64 (OpenCL's gb_offset uses long) and 64-bit array indexing.

Floating-point contraction: Warp builds with ``fuse_fp=True`` unless a module says otherwise;
CUDA then fuses ``a * b + c`` into one rounding, Warp's CPU build (clang) fuses nothing across
the statements it generates. Nothing here relies on either: quantize_code calls fma explicitly
and is exact both ways, bilinear's products are exact; the other stages differ by an ulp or so
(measured on both, gpu_blur/tolerances.py, section "Warp pixel stages").

Written against warp-lang 1.19 (``wp.where``, ``wp.func_native`` overloads, ``type(x)(...)``).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from gpu_blur import kernel_constants as constants
from gpu_blur.kernel_constants import (
    BILINEAR_TAP_WEIGHT,
    MALVAR2004_TAP_WEIGHT,
    SRGB_DECODE_KNEE,
    SRGB_DECODE_KNEE_FLOAT32,
    SRGB_ENCODE_KNEE,
    SRGB_GAMMA,
    SRGB_INV_GAMMA,
    SRGB_OFFSET,
    SRGB_SCALE,
    SRGB_SLOPE,
)

__all__ = [
    "BILINEAR_G",
    "BILINEAR_RB",
    "MALVAR2004_G_AT_RB",
    "MALVAR2004_RB_AT_BR",
    "MALVAR2004_RB_AT_G_COLUMN",
    "MALVAR2004_RB_AT_G_ROW",
    "SRGB_DECODE_KNEE_FLOAT32",
    "apply_matrix",
    "cfa_channel",
    "clip01",
    "demosaic_bilinear",
    "demosaic_malvar2004",
    "fma",
    "linear_to_srgb",
    "lookup_crf",
    "polynomial_crf",
    "quantize",
    "quantize_code",
    "reflect101",
    "srgb_decode_knee",
    "srgb_to_linear",
]


# -- geometry (gb_common.h) ---------------------------------------------------------------------


@wp.func
def reflect101(i: int, n: int) -> int:
    """Mirror index i into [0, n) without repeating the edge sample.

    As numpy "reflect" and OpenCV BORDER_REFLECT_101: period 2 (n - 1); keeps the Bayer phase.
    n == 1 gives 0.
    """
    if n == 1:
        return 0
    period = 2 * (n - 1)
    m = i % period  # C remainder: the sign of i
    if m < 0:
        m += period
    if m < n:
        return m
    return period - m


@wp.func
def cfa_channel(cfa: int, gx: int, gy: int) -> int:
    """Bayer colour (0 = R, 1 = G, 2 = B) at global (gx, gy).

    ``cfa`` packs the channels at the cell offsets (row, col) = (0,0), (0,1), (1,0), (1,1) in
    bits 0-1, 2-3, 4-5, 6-7 (gpu_blur.backends.opencl.cfa_bits). Negative coordinates keep their
    parity (two's complement), as the reflect border does.
    """
    site = ((gy & 1) << 1) | (gx & 1)
    return (cfa >> (2 * site)) & 3


# -- fused multiply-add: Warp has no built-in, so a native one per type -------------------------


@wp.func_native("return ::fmaf(a, b, c);")
def fma(a: wp.float32, b: wp.float32, c: wp.float32) -> wp.float32:
    """Fused multiply-add a * b + c, one rounding (C fmaf, on the CPU and in CUDA)."""


@wp.func_native("return ::fma(a, b, c);")
def fma(a: wp.float64, b: wp.float64, c: wp.float64) -> wp.float64:  # noqa: F811
    """Fused multiply-add a * b + c, one rounding (C fma, on the CPU and in CUDA)."""


# -- transfer curves, responses, clipping (gb_pixel.h) --------------------------------------------

# sRGB, IEC 61966-2-1: gpu_blur.reference.transfer's constants through kernel_constants, each a
# module-level float that Warp reads as a literal (``type(x)(SRGB_SLOPE)`` folds as
# ``type(x)(12.92)`` does). float32: the float nearest 0.04045 lies below it; the next float up
# (SRGB_DECODE_KNEE_FLOAT32, 0x1.4b5dcep-5) makes `a < knee` pick the float64 reference's branch
# for every float a. The float nearest 0.0031308 lies above it with no float in between, so the
# encode knee needs no such care.


@wp.func
def srgb_decode_knee(x: wp.float32) -> wp.float32:
    """The sRGB decode knee of x's type: the float32 next above 0.04045 (see above)."""
    return wp.float32(SRGB_DECODE_KNEE_FLOAT32)


@wp.func
def srgb_decode_knee(x: wp.float64) -> wp.float64:  # noqa: F811
    """The sRGB decode knee of x's type: 0.04045."""
    return wp.float64(SRGB_DECODE_KNEE)


@wp.func
def clip01(x: Any):
    """clip(x, 0, 1) as np.clip: NaN stays NaN (min/max would turn it into a bound)."""
    if x < type(x)(0.0):
        return type(x)(0.0)
    if x > type(x)(1.0):
        return type(x)(1.0)
    return x


@wp.func
def srgb_to_linear(x: Any):
    """The sRGB EOTF: sign(x) * (|x| / 12.92 if |x| < 0.04045 else ((|x| + 0.055) / 1.055)^2.4).

    The branch is chosen before the power, and the power only ever sees values >= the knee (the
    other lane is clamped), so 0 and denormals never reach pow. Odd extension for negative
    inputs, no clipping.
    """
    a = wp.abs(x)
    knee = srgb_decode_knee(x)
    low = a < knee
    curve = wp.where(low, knee, a)  # NaN stays NaN
    power = wp.pow((curve + type(x)(SRGB_OFFSET)) / type(x)(SRGB_SCALE), type(x)(SRGB_GAMMA))
    y = wp.where(low, a / type(x)(SRGB_SLOPE), power)
    return wp.copysign(y, x)


@wp.func
def linear_to_srgb(x: Any):
    """The sRGB OETF: sign(x) * (12.92 |x| if |x| < 0.0031308 else 1.055 |x|^(1/2.4) - 0.055).

    Same branch rule as srgb_to_linear; the IEC knees do not meet exactly (see transfer.py).
    1 / 2.4 is the float64 quotient, as in the reference and gb_pixel.h.
    """
    a = wp.abs(x)
    knee = type(x)(SRGB_ENCODE_KNEE)
    low = a < knee
    curve = wp.where(low, knee, a)
    power = type(x)(SRGB_SCALE) * wp.pow(curve, type(x)(SRGB_INV_GAMMA)) - type(x)(SRGB_OFFSET)
    y = wp.where(low, type(x)(SRGB_SLOPE) * a, power)
    return wp.copysign(y, x)


@wp.func
def polynomial_crf(x: Any, coefficients: wp.array(dtype=Any), n: int):
    """Polynomial camera response clip(sum_k c[k] x^k, 0, 1), as transfer.polynomial_crf.

    k = 0 .. n - 1 (ascending powers, n >= 1), by Horner's rule from the top coefficient down;
    ``coefficients`` holds the n values in x's type (A7R3: n = 8).
    """
    y = coefficients[n - 1]
    for k in range(n - 2, -1, -1):
        y = y * x + coefficients[k]
    return clip01(y)


@wp.func
def _lookup_node(i: int, n: int, step: Any):
    """Linear node i of a table of n nodes, as np.linspace(0, 1, n) computes it.

    That is i * (1 / (n - 1)), and exactly 1 at the last node.
    """
    if i == n - 1:
        return type(step)(1.0)
    return type(step)(i) * step


@wp.func
def lookup_crf(x: Any, rendered: wp.array(dtype=Any), n: int):
    """Camera response by piecewise-linear interpolation of a table, clipped to [0, 1].

    The nodes are linear = i / (n - 1), i = 0 .. n - 1 (n >= 2), ``rendered`` holds the n
    rendered values in [0, 1] in x's type (the host divides the x255 table by 255). Same as
    np.interp(x, linspace(0, 1, n), rendered) then np.clip, as transfer.lookup_crf: x <= 0 gives
    rendered[0], x >= 1 rendered[n - 1], a node gives its value, in between
    slope * (x - x_j) + rendered[j] with slope = (rendered[j + 1] - rendered[j]) / (x_{j+1} -
    x_j), x_j <= x < x_{j+1}.
    """
    if wp.isnan(x):
        return x
    if x <= type(x)(0.0):
        return clip01(rendered[0])
    if x >= type(x)(1.0):
        return clip01(rendered[n - 1])
    scale = type(x)(n - 1)
    step = type(x)(1.0) / scale
    # x > 0: truncation is floor; may be one off, fixed by the two loops
    j = wp.clamp(int(x * scale), 0, n - 2)
    while j > 0 and x < _lookup_node(j, n, step):
        j -= 1
    while j < n - 2 and x >= _lookup_node(j + 1, n, step):
        j += 1
    xj = _lookup_node(j, n, step)
    if x == xj:
        return clip01(rendered[j])
    xk = _lookup_node(j + 1, n, step)
    slope = (rendered[j + 1] - rendered[j]) / (xk - xj)
    return clip01(slope * (x - xj) + rendered[j])


@wp.func
def apply_matrix(m: wp.array(dtype=Any), v: Any):
    """Return M @ v for a row-major 3 x 3 M (column convention, as color.apply_matrix).

    ``m`` is a flat array of 9 values, m[3 r + c] = M[r][c], and ``v`` a 3-vector
    (``wp.vec3f`` / ``wp.vec3d``), both of one type; returns a 3-vector of that type. Each row
    sums left to right, as gb_apply_matrix.
    """
    return wp.vector(
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    )


@wp.func
def quantize_code(x: Any, bits: int) -> int:
    """Integer code of output.to_integers: floor(clip(x, 0, 1) * (2^bits - 1) + 0.5), bits <= 16.

    The floor is of the exact value: a first guess from one fma is corrected with the exact sign
    of c * top - (q -+ 0.5) (one fma, a single rounding, keeps the sign), so a float32 build
    gives the float64 reference's code for every float input, also next to the rounding
    boundaries (k + 0.5) / top; a float64 build gives the exactly rounded code.
    """
    top = type(x)((1 << bits) - 1)
    c = clip01(x)
    half = type(x)(0.5)
    q = wp.floor(fma(c, top, half))
    if fma(c, top, -(q - half)) < type(x)(0.0):
        q -= type(x)(1.0)
    elif fma(c, top, -(q + half)) >= type(x)(0.0):
        q += type(x)(1.0)
    return int(q)


@wp.func
def quantize(x: Any, bits: int):
    """output.quantize: the value k / (2^bits - 1) of the code k = quantize_code(x, bits)."""
    return type(x)(quantize_code(x, bits)) / type(x)((1 << bits) - 1)


# -- demosaicing (gb_demosaic.h) -----------------------------------------------------------------
#
# Both functions take a RAW buffer VIEW: `raw` holds global pixels [x0, x0 + w) x [y0, y0 + h)
# row-major with width w, and must contain every global pixel the stencil of (gx, gy) reads after
# the border rule: the pixels within the halo (2 for Malvar, 1 for bilinear) of (gx, gy), clipped
# to the image [0, full_w) x [0, full_h). The host guarantees it.
#
# Border rule, in GLOBAL coordinates (the full image's edges, never a tile's):
#   zero_border == 0  "reflect": a tap at global i reads reflect101(i, n) (mirror without
#                     repeating the edge sample, period 2 (n - 1), keeps the Bayer phase; for
#                     n = 2 it alternates x0 x1 x0 x1 as the reference's repeated mirroring);
#   zero_border != 0  "zero": taps outside the image read 0 (and are never loaded).
# `cfa` packs the channel of each cell site as cfa_channel reads it, for the full image's
# pattern (its (0, 0) at global (0, 0)). The output (R, G, B) is not clipped.

_mat55 = wp.types.matrix(shape=(5, 5), dtype=wp.float32)
_mat33 = wp.types.matrix(shape=(3, 3), dtype=wp.float32)

# Malvar, He, Cutler, "High-quality linear interpolation for demosaicing of Bayer-patterned color
# images", ICASSP 2004, Fig. 2: the four 5 x 5 filters times 8 (each sums to 8), rows dy = -2 .. 2
# (top to bottom), columns dx = -2 .. 2 (left to right). Weight = entry / 8. The entries are
# reference.demosaic's filters times 8 (kernel_constants), multiples of 1/2, exact in float32
# and in the compute type.

#: G at R sites and at B sites.
MALVAR2004_G_AT_RB = wp.constant(_mat55(*constants.MALVAR2004_G_AT_RB_X8))
#: R at a G site whose row holds R (B at a G site whose row holds B): same colour left and right.
MALVAR2004_RB_AT_G_ROW = wp.constant(_mat55(*constants.MALVAR2004_RB_AT_G_ROW_X8))
#: R at a G site whose column holds R (B likewise): the transpose, same colour above and below.
MALVAR2004_RB_AT_G_COLUMN = wp.constant(_mat55(*constants.MALVAR2004_RB_AT_G_COLUMN_X8))
#: R at B sites and B at R sites.
MALVAR2004_RB_AT_BR = wp.constant(_mat55(*constants.MALVAR2004_RB_AT_BR_X8))

# Bilinear, times 4, rows dy = -1 .. 1, columns dx = -1 .. 1; applied to the plane of one channel
# (zeros at the other channels' sites). Weight = entry / 4.

#: G: mean of the 4 axial neighbours.
BILINEAR_G = wp.constant(_mat33(*constants.BILINEAR_G_X4))
#: R or B: mean of the 2 neighbours at G sites, of the 4 diagonal neighbours at B or R sites.
BILINEAR_RB = wp.constant(_mat33(*constants.BILINEAR_RB_X4))


@wp.func
def _stencil_index(i: int, n: int, origin: int, zero_border: int) -> int:
    """Global position i along an axis of n pixels under the border rule, view-relative.

    An index relative to the view's origin (a column, or a row to be scaled by the width); -1
    for a tap outside the image under "zero" (the halo guarantee makes every other one >= 0).
    """
    if i >= 0 and i < n:
        return i - origin
    if zero_border != 0:
        return -1
    return reflect101(i, n) - origin


@wp.func
def _stencil_sample(raw: wp.array(dtype=Any), w: int, row: int, col: int):
    """One sample of the stencil at a view row and column; 0 outside the image (never loaded)."""
    if row < 0 or col < 0:
        return raw.dtype(0.0)
    return raw[row * w + col]


@wp.func
def _malvar2004_filter(raw: wp.array(dtype=Any), w: int, rows: Any, cols: Any, taps: Any):
    """Correlation with a 5 x 5 Malvar filter, as the reference's _correlate.

    The nonzero taps in row-major order, each adding (entry / 8) * sample to a sum that starts
    at 0.
    """
    total = raw.dtype(0.0)
    for i in range(5):
        for j in range(5):
            entry = taps[i, j]
            if entry != wp.float32(0.0):
                weight = raw.dtype(entry) * raw.dtype(MALVAR2004_TAP_WEIGHT)  # 1/8, exact: k/2
                total += weight * _stencil_sample(raw, w, rows[i], cols[j])
    return total


@wp.func
def demosaic_malvar2004(raw: wp.array(dtype=Any), x0: int, y0: int, w: int, full_w: int,
                        full_h: int, gx: int, gy: int, cfa: int, zero_border: int):
    """Malvar-He-Cutler demosaicing of the pixel at global (gx, gy) (demosaic_malvar2004).

    The site keeps its RAW value for its own channel; at a G site, the colour of the row (the one
    at (gx + 1, gy)) comes from the ROW filter and the other from the COLUMN filter; at an R or B
    site, G from G_AT_RB and the opposite colour from RB_AT_BR. Returns (R, G, B) as a 3-vector
    of raw's type. See the section comment for the view, the halo and the border rule.
    """
    rows = wp.vector(
        _stencil_index(gy - 2, full_h, y0, zero_border),
        _stencil_index(gy - 1, full_h, y0, zero_border),
        _stencil_index(gy, full_h, y0, zero_border),
        _stencil_index(gy + 1, full_h, y0, zero_border),
        _stencil_index(gy + 2, full_h, y0, zero_border),
    )
    cols = wp.vector(
        _stencil_index(gx - 2, full_w, x0, zero_border),
        _stencil_index(gx - 1, full_w, x0, zero_border),
        _stencil_index(gx, full_w, x0, zero_border),
        _stencil_index(gx + 1, full_w, x0, zero_border),
        _stencil_index(gx + 2, full_w, x0, zero_border),
    )
    own = cfa_channel(cfa, gx, gy)
    center = raw[(gy - y0) * w + (gx - x0)]
    if own == 1:
        in_row = cfa_channel(cfa, gx + 1, gy)  # R or B: shares this row
        along_row = _malvar2004_filter(raw, w, rows, cols, MALVAR2004_RB_AT_G_ROW)
        along_column = _malvar2004_filter(raw, w, rows, cols, MALVAR2004_RB_AT_G_COLUMN)
        if in_row == 0:
            return wp.vector(along_row, center, along_column)
        return wp.vector(along_column, center, along_row)
    green = _malvar2004_filter(raw, w, rows, cols, MALVAR2004_G_AT_RB)
    opposite = _malvar2004_filter(raw, w, rows, cols, MALVAR2004_RB_AT_BR)
    if own == 0:
        return wp.vector(center, green, opposite)
    return wp.vector(opposite, green, center)


@wp.func
def _bilinear_channel(raw: wp.array(dtype=Any), w: int, rows: Any, cols: Any, cfa: int, gx: int,
                      gy: int, channel: int, taps: Any):
    """Correlation of one channel's plane with a 3 x 3 bilinear filter.

    Taps in row-major order; taps on other channels' sites add nothing and are skipped. Reflect
    keeps the Bayer phase, so a tap's channel is that of its unreflected global position.
    """
    total = raw.dtype(0.0)
    for i in range(3):
        for j in range(3):
            entry = taps[i, j]
            if entry != wp.float32(0.0) and cfa_channel(cfa, gx + j - 1, gy + i - 1) == channel:
                weight = raw.dtype(entry) * raw.dtype(BILINEAR_TAP_WEIGHT)  # 1/4, exact
                total += weight * _stencil_sample(raw, w, rows[i], cols[j])
    return total


@wp.func
def demosaic_bilinear(raw: wp.array(dtype=Any), x0: int, y0: int, w: int, full_w: int,
                      full_h: int, gx: int, gy: int, cfa: int, zero_border: int):
    """Bilinear demosaicing of the pixel at global (gx, gy) (demosaic.demosaic_bilinear).

    The site keeps its RAW value for its own channel; each missing channel is the correlation of
    that channel's plane with BILINEAR_G or BILINEAR_RB. Returns (R, G, B) as a 3-vector of
    raw's type. Same view, halo (1) and border rule as demosaic_malvar2004.
    """
    rows = wp.vector(
        _stencil_index(gy - 1, full_h, y0, zero_border),
        _stencil_index(gy, full_h, y0, zero_border),
        _stencil_index(gy + 1, full_h, y0, zero_border),
    )
    cols = wp.vector(
        _stencil_index(gx - 1, full_w, x0, zero_border),
        _stencil_index(gx, full_w, x0, zero_border),
        _stencil_index(gx + 1, full_w, x0, zero_border),
    )
    own = cfa_channel(cfa, gx, gy)
    center = raw[(gy - y0) * w + (gx - x0)]
    if own == 0:
        return wp.vector(
            center,
            _bilinear_channel(raw, w, rows, cols, cfa, gx, gy, 1, BILINEAR_G),
            _bilinear_channel(raw, w, rows, cols, cfa, gx, gy, 2, BILINEAR_RB),
        )
    if own == 1:
        return wp.vector(
            _bilinear_channel(raw, w, rows, cols, cfa, gx, gy, 0, BILINEAR_RB),
            center,
            _bilinear_channel(raw, w, rows, cols, cfa, gx, gy, 2, BILINEAR_RB),
        )
    return wp.vector(
        _bilinear_channel(raw, w, rows, cols, cfa, gx, gy, 0, BILINEAR_RB),
        _bilinear_channel(raw, w, rows, cols, cfa, gx, gy, 1, BILINEAR_G),
        center,
    )
