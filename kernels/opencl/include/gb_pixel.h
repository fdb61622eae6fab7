/* gb_pixel.h: per-pixel maths of the pipeline (transfer curves, camera responses, 3 x 3 colour
 * matrices, clipping and quantization) as device functions; no kernels.
 *
 * Each function computes what its numpy float64 reference computes, on `real` (float, or double
 * under GB_FP64):
 *   gb_srgb_to_linear, gb_linear_to_srgb  gpu_blur.reference.transfer.srgb_to_linear / linear_to_srgb
 *   gb_polynomial_crf                     gpu_blur.reference.transfer.polynomial_crf
 *   gb_lookup_crf                         gpu_blur.reference.transfer.lookup_crf
 *   gb_apply_matrix                       gpu_blur.reference.color.apply_matrix
 *   gb_clip01, gb_quantize(_code)         np.clip(x, 0, 1), gpu_blur.reference.output.quantize /
 *                                         to_integers
 *   gb_retone_quantize                    the finish pass's retone and quantize stages
 *                                         (gpu_blur.backends.numpy.retone, then quantize)
 * NaN goes through every function as NaN (as in numpy), except gb_quantize_code, where the code of
 * a NaN is undefined (numpy's cast of NaN to an integer is too).
 *
 * The sRGB curves' power is gb_pow (gb_math.h): pow, or native_powr in float builds with
 * GB_FAST_MATH, whose error the tolerance table's "fast" rows bound.
 */
#ifndef GB_PIXEL_H
#define GB_PIXEL_H

#include "gb_common.h"
#include "gb_math.h"

/* sRGB, IEC 61966-2-1: GB_SRGB_* of gb_constants.h (gpu_blur.reference.transfer). The decode
 * knee of float builds is the float just above 0.04045 (the nearest lies below it), so that
 * `a < knee` picks the float64 reference's branch for every float a (kernel_constants). */
#ifdef GB_FP64
#define GB_SRGB_DECODE_KNEE GB_SRGB_DECODE_KNEE_DOUBLE
#else
#define GB_SRGB_DECODE_KNEE GB_SRGB_DECODE_KNEE_FLOAT
#endif

/* clip(x, 0, 1) as np.clip: NaN stays NaN (fmin/fmax would turn it into a bound). */
static inline real gb_clip01(real x)
{
    return x < GB_REAL(0.0) ? GB_REAL(0.0) : (x > GB_REAL(1.0) ? GB_REAL(1.0) : x);
}

/* sRGB EOTF: sign(x) * (|x| / 12.92 if |x| < 0.04045 else ((|x| + 0.055) / 1.055)^2.4).
 * The branch is chosen before the power, and the power only ever sees values >= the knee (the
 * other lane is clamped), so 0 and denormals never reach pow even if the compiler evaluates both
 * sides. Odd extension for negative inputs, no clipping. */
static inline real gb_srgb_to_linear(real x)
{
    real a = fabs(x);
    int low = a < GB_SRGB_DECODE_KNEE;
    real curve = low ? GB_SRGB_DECODE_KNEE : a; /* NaN stays NaN */
    real y = low ? a / GB_SRGB_SLOPE : gb_pow((curve + GB_SRGB_OFFSET) / GB_SRGB_SCALE, GB_SRGB_GAMMA);
    return copysign(y, x);
}

/* sRGB OETF: sign(x) * (12.92 |x| if |x| < 0.0031308 else 1.055 |x|^(1/2.4) - 0.055).
 * Same branch rule as gb_srgb_to_linear; the IEC knees do not meet exactly (see transfer.py). */
static inline real gb_linear_to_srgb(real x)
{
    real a = fabs(x);
    int low = a < GB_SRGB_ENCODE_KNEE;
    real curve = low ? GB_SRGB_ENCODE_KNEE : a;
    real y = low ? GB_SRGB_SLOPE * a : GB_SRGB_SCALE * gb_pow(curve, GB_SRGB_INV_GAMMA) - GB_SRGB_OFFSET;
    return copysign(y, x);
}

/* Polynomial camera response clip(sum_k c[k] x^k, 0, 1), k = 0 .. n - 1 (ascending powers,
 * n >= 1), by Horner's rule from the top coefficient down, as transfer.polynomial_crf. The host
 * passes the coefficients (A7R3: n = 8) in a __constant buffer of `real`. */
static inline real gb_polynomial_crf(real x, __constant real *c, int n)
{
    real y = c[n - 1];
    for (int k = n - 2; k >= 0; --k) {
        y = y * x + c[k];
    }
    return gb_clip01(y);
}

/* Linear node i of a response table of n nodes, as np.linspace(0, 1, n) computes it:
 * i * (1 / (n - 1)), and exactly 1 at the last node. */
static inline real gb_lookup_node(int i, int n, real step)
{
    return i == n - 1 ? GB_REAL(1.0) : (real)i * step;
}

/* Camera response by piecewise-linear interpolation of a table, clipped to [0, 1]: the nodes are
 * linear = i / (n - 1), i = 0 .. n - 1 (n >= 2), `rendered` holds the rendered values in [0, 1]
 * (the host divides the x255 table by 255). Same as np.interp(x, linspace(0, 1, n), rendered)
 * then np.clip, as transfer.lookup_crf: x <= 0 gives rendered[0], x >= 1 rendered[n - 1], a node
 * gives its value, in between slope * (x - x_j) + rendered[j] with
 * slope = (rendered[j + 1] - rendered[j]) / (x_{j+1} - x_j), x_j <= x < x_{j+1}. */
static inline real gb_lookup_crf(real x, __global const real *rendered, int n)
{
    if (x != x) return x;
    if (x <= GB_REAL(0.0)) return gb_clip01(rendered[0]);
    if (x >= GB_REAL(1.0)) return gb_clip01(rendered[n - 1]);
    real scale = (real)(n - 1);
    real step = GB_REAL(1.0) / scale;
    int j = (int)(x * scale); /* x > 0: truncation is floor; may be one off, fixed below */
    j = clamp(j, 0, n - 2);
    while (j > 0 && x < gb_lookup_node(j, n, step)) --j;
    while (j < n - 2 && x >= gb_lookup_node(j + 1, n, step)) ++j;
    real xj = gb_lookup_node(j, n, step);
    if (x == xj) return gb_clip01(rendered[j]);
    real xk = gb_lookup_node(j + 1, n, step);
    real slope = (rendered[j + 1] - rendered[j]) / (xk - xj);
    return gb_clip01(slope * (x - xj) + rendered[j]);
}

/* out = M @ in for a row-major 3 x 3 M (column convention, as color.apply_matrix): M comes from a
 * __constant kernel argument (9 `real`, m[3 r + c] = M[r][c]); in and out are private 3-arrays
 * and may be the same array. */
static inline void gb_apply_matrix(__constant real *m, const real in[3], real out[3])
{
    real r0 = m[0] * in[0] + m[1] * in[1] + m[2] * in[2];
    real r1 = m[3] * in[0] + m[4] * in[1] + m[5] * in[2];
    real r2 = m[6] * in[0] + m[7] * in[1] + m[8] * in[2];
    out[0] = r0;
    out[1] = r1;
    out[2] = r2;
}

/* Integer code of output.to_integers: floor(clip(x, 0, 1) * (2^bits - 1) + 0.5), bits <= 16.
 * The floor is of the exact value: a first guess from one fma is corrected with the exact sign of
 * c * top - (q -+ 0.5) (one fma, a single rounding, keeps the sign), so a float build gives the
 * same code as the float64 reference for every float input, also next to the rounding
 * boundaries (k + 0.5) / top. */
static inline uint gb_quantize_code(real x, int bits)
{
    real top = (real)((1 << bits) - 1);
    real c = gb_clip01(x);
    real q = floor(fma(c, top, GB_REAL(0.5)));
    if (fma(c, top, -(q - GB_REAL(0.5))) < GB_REAL(0.0)) {
        q -= GB_REAL(1.0);
    } else if (fma(c, top, -(q + GB_REAL(0.5))) >= GB_REAL(0.0)) {
        q += GB_REAL(1.0);
    }
    return (uint)q;
}

/* output.quantize: the value k / (2^bits - 1) of the code k = gb_quantize_code(x, bits). */
static inline real gb_quantize(real x, int bits)
{
    return (real)gb_quantize_code(x, bits) / (real)((1 << bits) - 1);
}

/* The finish pass's last stages on an sRGB value p, as the build's defines keep them: "retone"
 * (GB_STAGE_RETONE: the camera response of its EOTF, by the polynomial or, with
 * GB_RETONE_LOOKUP, the table), then "quantize" (GB_STAGE_QUANTIZE, GB_QUANTIZE_BITS).
 * gb_finish and gb_render_sharp end with it; without those defines it returns p. */
static inline real gb_retone_quantize(real p, __constant real *crf_polynomial,
                                      int crf_polynomial_n, __global const real *crf_table,
                                      int crf_table_n)
{
#ifdef GB_STAGE_RETONE
#ifdef GB_RETONE_LOOKUP
    p = gb_lookup_crf(gb_srgb_to_linear(p), crf_table, crf_table_n);
#else
    p = gb_polynomial_crf(gb_srgb_to_linear(p), crf_polynomial, crf_polynomial_n);
#endif
#endif
#ifdef GB_STAGE_QUANTIZE
    p = gb_quantize(p, GB_QUANTIZE_BITS);
#endif
    return p;
}

#endif
