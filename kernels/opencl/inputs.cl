/* inputs.cl: kernels over an input image as stored on the device (gb_source, gb_common.h), so
 * that no value of it is read on the host (gpu_blur.backends.kernel.KernelBackend.inspect and
 * render_sharp):
 *   gb_inspect       counts for the input checks and auto saturation's clip test;
 *   gb_unit_values   stored values as reals in [0, 1] (blur mode none's mask; 8-bit codes four
 *                    a work item: gb_unit_values_codes);
 *   gb_render_sharp  the sharp reference, toned like the output by finish.cl's functions;
 *   gb_gather_codes  the same for 8/16-bit codes, from a table gb_render_sharp made of every code;
 *   gb_to_codes      output values as the set's 8/16-bit codes (gb_source), for the host to fetch.
 */
#include "gb_common.h"
#include "gb_pixel.h"

/* counts[0] += add for a count held as two uints, counts[0] the low word and counts[1] the high
 * one, with 32-bit atomics only (core OpenCL): the addition that wraps the low word carries. */
static inline void gb_count_add(__global volatile uint *counts, uint add)
{
    if (add == 0) return;
    uint old = atomic_add(counts, add);
    if (old + add < old) atomic_inc(counts + 1);
}

/* Adds one value to the six counts of gb_inspect, in its column order. */
static inline void gb_inspect_value(gb_source v, uint *c)
{
#if GB_SOURCE_BITS == 0
    c[0] += isnan(v) ? 1u : 0u;
    c[1] += isinf(v) ? 1u : 0u;
    c[2] += v < GB_REAL(0.0) ? 1u : 0u;
    c[3] += v > GB_REAL(1.0) ? 1u : 0u;
    c[4] += v >= GB_REAL(1.0) ? 1u : 0u;
    c[5] += v > GB_REAL(0.0) ? 1u : 0u;
#else
    c[4] += v == (gb_source)((1 << GB_SOURCE_BITS) - 1) ? 1u : 0u;
    c[5] += v > 0 ? 1u : 0u;
#endif
}

/* Counts over the n values of each image, into a row of `counts` per image: image b (the
 * launch's second axis) starts stride values after image b - 1 and counts into row row + b.
 * 6 columns (NaN, infinite, below 0, above 1, at the clip level, above 0;
 * KernelBackend.INSPECT_COLUMNS), each a 64-bit count as two uints (gb_count_add). Work item i
 * of `items` counts values i, i + items, ... in registers (items >= n / 2^32, so each of its
 * counts fits a uint), GB_INSPECT_LOADS of them (gb_constants.h) loaded at a time, and adds
 * each non-zero count once. The clip level is 1.0 for float values and the top code
 * (2^bits - 1) for codes; codes are never NaN, infinite, negative or above 1. */
__kernel void gb_inspect(__global const gb_source *image, long n, long items,
                         __global volatile uint *counts, long row, long stride)
{
    long b = get_global_id(1);
    __global const gb_source *values = image + b * stride;
    uint c[6] = {0u, 0u, 0u, 0u, 0u, 0u};
    for (long i = get_global_id(0); i < n; i += GB_INSPECT_LOADS * items) {
        gb_source v[GB_INSPECT_LOADS];
        for (int u = 0; u < GB_INSPECT_LOADS; ++u) /* every load issued before any count */
            v[u] = i + u * items < n ? values[i + u * items] : (gb_source)0;
        for (int u = 0; u < GB_INSPECT_LOADS; ++u)
            if (i + u * items < n) gb_inspect_value(v[u], c);
    }
    __global volatile uint *out = counts + 12 * (row + b);
    for (int k = 0; k < 6; ++k) gb_count_add(out + 2 * k, c[k]);
}

/* Stored values as reals in [0, 1] (codes / (2^bits - 1), as gb_linearize divides them): a mask
 * given in its stored dtype. */
__kernel void gb_unit_values(__global const gb_source *stored, __global real *values)
{
    size_t i = get_global_id(0);
    values[i] = gb_source_value(stored[i]);
}

#if GB_SOURCE_BITS == 8
/* gb_unit_values of 8-bit codes four a work item (one uchar4 load, one real4 store). */
__kernel void gb_unit_values_codes(__global const uchar4 *quads, __global real4 *values)
{
    size_t q = get_global_id(0);
    uchar4 c = quads[q];
    values[q] = (real4)(gb_source_value(c.x), gb_source_value(c.y), gb_source_value(c.z),
                        gb_source_value(c.w));
}
#endif

/* Values as their output codes (gb_source: uchar for GB_SOURCE_BITS 8, ushort for 16):
 * gb_quantize_code, the code gpu_blur.reference.output.to_integers gives every float value. */
__kernel void gb_to_codes(__global const real *values, __global gb_source *codes)
{
    size_t i = get_global_id(0);
    codes[i] = (gb_source)gb_quantize_code(values[i], GB_SOURCE_BITS);
}

/* The sharp reference over the output region (first pixel (ox0, oy0), size ow x oh) of images
 * of width iw, 3 values per pixel, image b (the launch's third axis) image_stride values after
 * image b - 1 and its output out_stride values after output b - 1: each stored sRGB value p (a
 * code divided as gb_linearize does) becomes, as gpu_blur.pipeline.render_sharp renders it on
 * the host,
 *   without GB_STAGE_TONE (output.crf = none): clip(EOTF(p), 0, 1);
 *   else p;
 * then gb_finish's own last stages, gb_retone_quantize (re-toning with GB_STAGE_RETONE,
 * quantization with GB_STAGE_QUANTIZE). The curves' arguments are gb_finish's. */
__kernel void gb_render_sharp(__global const gb_source *image, long iw, long image_stride,
                              long ox0, long oy0, long ow, long oh,
                              __constant real *crf_polynomial, int crf_polynomial_n,
                              __global const real *crf_table, int crf_table_n,
                              __global real *out, long out_stride)
{
    long x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= ow || y >= oh) return;
    long i = b * image_stride + 3 * ((oy0 + y) * iw + ox0 + x);
    long o = b * out_stride + 3 * (y * ow + x);
    for (int c = 0; c < 3; ++c) {
        real p = gb_source_value(image[i + c]);
#ifndef GB_STAGE_TONE
        p = gb_clip01(gb_srgb_to_linear(p));
#endif
        out[o + c] = gb_retone_quantize(p, crf_polynomial, crf_polynomial_n, crf_table,
                                        crf_table_n);
    }
}

#if GB_SOURCE_BITS != 0
/* gb_render_sharp's output regions from `rendered`, gb_render_sharp's values of the codes
 * 0 .. 2^bits - 1 (the same function of the same codes, so the same bits, without a curve
 * per value), as gpu_blur.pipeline.render_sharp renders codes on the host. */
__kernel void gb_gather_codes(__global const gb_source *image, long iw, long image_stride,
                              long ox0, long oy0, long ow, long oh,
                              __global const real *rendered, __global real *out,
                              long out_stride)
{
    long x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= ow || y >= oh) return;
    long i = b * image_stride + 3 * ((oy0 + y) * iw + ox0 + x);
    long o = b * out_stride + 3 * (y * ow + x);
    for (int c = 0; c < 3; ++c) out[o + c] = rendered[image[i + c]];
}
#endif
