/* accumulate.cl: pass 1 of the plan, stages "linearize" and "blur".
 *
 * Images are interleaved RGB (3 values per pixel), row-major; input frames are gb_source (their
 * stored dtype, gb_common.h). Sums stay on the device while the host streams frames (mode
 * average, a few per launch) or poses (mode trajectory, one per launch) through them.
 * Every kernel addresses pixels by global coordinates (see gb_common.h): a tile's output
 * equals the whole image's at the same pixels.
 */
#include "gb_common.h"
#include "gb_pixel.h"
#include "gb_sum.h" /* gb_add_compensated: the streamed sums */

/* linearize: sRGB -> linear (EOTF), and the saturation indicator [linear >= 1]. */
__kernel void gb_linearize(__global const gb_source *srgb, __global real *linear,
                           __global real *indicator)
{
    size_t i = get_global_id(0);
    real v = gb_srgb_to_linear(gb_source_value(srgb[i]));
    linear[i] = v;
    indicator[i] = v >= GB_SATURATION_LEVEL ? GB_REAL(1.0) : GB_REAL(0.0);
}

#if GB_SOURCE_BITS == 8
/* linearize for blur mode none, 8-bit codes, four a work item (one uchar4 load, one real4
 * store): each code's linear value from `table`, which gb_linearize made of codes 0..255 (the
 * same function, so the same bits, without a pow per value); no clip indicator, which mode
 * none's given mask replaces. */
__kernel void gb_linearize_codes(__global const uchar4 *quads, __global const real *table,
                                 __global real4 *linear)
{
    size_t q = get_global_id(0);
    uchar4 c = quads[q];
    linear[q] = (real4)(table[c.x], table[c.y], table[c.z], table[c.w]);
}
#endif

#if GB_SOURCE_BITS == 0
/* linearize for blur mode none, real values, four a work item (one real4 load, one real4
 * store): gb_linearize's function of each value, so the same bits; no clip indicator, which
 * mode none's given mask replaces. */
__kernel void gb_linearize_values(__global const real4 *values, __global real4 *linear)
{
    size_t q = get_global_id(0);
    real4 v = values[q];
    linear[q] = (real4)(gb_srgb_to_linear(v.x), gb_srgb_to_linear(v.y),
                        gb_srgb_to_linear(v.z), gb_srgb_to_linear(v.w));
}
#endif

/* The linear value of a stored frame value at frames[i]. 8-bit codes: a gather from `table`,
 * the value of each code that gb_linearize computed from codes 0..255 (the same function, so
 * the same bits, without a pow per value); other sources: the sRGB EOTF. */
#if GB_SOURCE_BITS == 8
#define GB_FRAME_LINEAR(frames, i, table) ((table)[(frames)[i]])
#else
#define GB_FRAME_LINEAR(frames, i, table) gb_srgb_to_linear(gb_source_value((frames)[i]))
#endif

/* blur, variant average: frames k = 0..count-1 of a device stack (frame k at k * stride, each
 * covering the region of the sums), linearized on the fly, join the running compensated sum in
 * registers (the same operations as gb_add_compensated) and the saturation counts. `first`
 * starts from zero instead of the state in sum/compensation/saturated; `mean_of` > 0 ends the
 * average: linear and mask get the mean over that many frames and the fraction of them
 * saturated, instead of the state going back. table: see GB_FRAME_LINEAR (unread unless the
 * frames are 8-bit codes). */
__kernel void gb_blur_average_add(__global const gb_source *frames, uint count, long stride,
                                  __global real *sum, __global real *compensation,
                                  __global uint *saturated, int first, uint mean_of,
                                  __global real *linear, __global real *mask,
                                  __global const real *table)
{
#pragma OPENCL FP_CONTRACT OFF
    size_t i = get_global_id(0);
    real s = GB_REAL(0.0), c = GB_REAL(0.0);
    uint n = 0;
    if (!first) {
        s = sum[i];
        c = compensation[i];
        n = saturated[i];
    }
    for (uint k = 0; k < count; ++k) {
        real v = GB_FRAME_LINEAR(frames, k * stride + i, table);
        real t = s + v;
        c += fabs(s) >= fabs(v) ? (s - t) + v : (v - t) + s;
        s = t;
        n += v >= GB_SATURATION_LEVEL ? 1u : 0u;
    }
    if (mean_of > 0) {
        linear[i] = (s + c) / (real)mean_of;
        mask[i] = (real)n / (real)mean_of;
    } else {
        sum[i] = s;
        compensation[i] = c;
        saturated[i] = n;
    }
}

#if GB_SOURCE_BITS == 8 && !defined(GB_FP64)
/* The two means of an exact sum of `count` units entries (gb_blur_average_exact): x the linear
 * value's, y the saturation mask's. */
static inline float2 gb_exact_means(ulong total, uint count)
{
    ulong saturated = total >> GB_EXACT_COUNT_SHIFT;
    float sum = (float)(total - (saturated << GB_EXACT_COUNT_SHIFT)) * GB_EXACT_UNIT;
    return (float2)(sum / (float)count, (float)saturated / (float)count);
}

/* blur, variant average, when all `count` 8-bit frames (at most EXACT_FRAMES_MAX of
 * gpu_blur.kernel_constants) join one launch in a float build: gb_blur_average_add's means, the
 * same bits (gb_sum.h), from an exact integer sum. units[code]: the code's linear value in
 * units of GB_EXACT_UNIT, plus 1 << GB_EXACT_COUNT_SHIFT where that value is saturated; so one
 * 64-bit add a frame sums both the value and the saturation count, and the sum rounds to float
 * once. Four values a work item: one uchar4 load a frame, four sums in flight, one float4
 * store of each mean. Sample b (the launch's second axis) reads its frames sample_stride quads
 * after sample b - 1's (frame k of it stride quads after frame k - 1) and writes its means
 * out_stride quads after sample b - 1's. */
__kernel void gb_blur_average_exact(__global const uchar4 *quads, uint count, long stride,
                                    long sample_stride, __global const ulong *units,
                                    __global float4 *linear, __global float4 *mask,
                                    long out_stride)
{
    size_t q = get_global_id(0);
    long b = get_global_id(1);
    __global const uchar4 *code = quads + b * sample_stride + q;
    ulong t0 = 0, t1 = 0, t2 = 0, t3 = 0;
    for (uint k = 0; k < count; ++k, code += stride) {
        uchar4 c = *code;
        t0 += units[c.x];
        t1 += units[c.y];
        t2 += units[c.z];
        t3 += units[c.w];
    }
    float2 m0 = gb_exact_means(t0, count), m1 = gb_exact_means(t1, count);
    float2 m2 = gb_exact_means(t2, count), m3 = gb_exact_means(t3, count);
    linear[b * out_stride + q] = (float4)(m0.x, m1.x, m2.x, m3.x);
    mask[b * out_stride + q] = (float4)(m0.y, m1.y, m2.y, m3.y);
}
#endif

/* blur, variant kernel, for a batch of samples (the third grid index b): the linear image `src`
 * and its saturation indicator `ind` convolved with the sample's kernel into `linear` and
 * `mask` (true convolution, the kernel normalized by the host), reflect-101 at the full image's
 * edges. Row b of kernel_words (gpu_blur.kernel_constants.KERNEL_WORDS) holds the kernel's first
 * tap in `taps`, its height and width, and the sample's slot: each buffer holds a slot per
 * sample, <buffer>_stride values apart. src and ind are views (first pixel (sx0, sy0), width
 * sw) that hold the output region plus the kernel's radius; linear and mask cover the output
 * region (first pixel (dx0, dy0), dw x dh). */
__kernel void gb_blur_kernel(__global const real *src, long src_stride, __global const real *ind,
                             long ind_stride, long sx0, long sy0, long sw, long full_w,
                             long full_h, __global const real *taps,
                             __global const uint *kernel_words, __global real *linear,
                             long linear_stride, __global real *mask, long mask_stride, long dx0,
                             long dy0, long dw, long dh)
{
    long x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= dw || y >= dh) return;
    __global const uint *row = kernel_words + GB_KERNEL_WORDS * b;
    __global const real *k = taps + row[0];
    int kh = (int)row[1], kw = (int)row[2];
    long slot = (long)row[3];
    src += slot * src_stride;
    ind += slot * ind_stride;
    linear += slot * linear_stride;
    mask += slot * mask_stride;
    long gx = dx0 + x, gy = dy0 + y;
    int ry = kh / 2, rx = kw / 2;
    real acc[3] = {0, 0, 0}, sat[3] = {0, 0, 0};
    for (int i = 0; i < kh; ++i) {
        long sy = gb_reflect101(gy + ry - i, full_h);
        for (int j = 0; j < kw; ++j) {
            real w = k[i * kw + j];
            long sx = gb_reflect101(gx + rx - j, full_w);
            long o = 3 * gb_offset(sx, sy, sx0, sy0, sw);
            for (int c = 0; c < 3; ++c) {
                acc[c] += w * src[o + c];
                sat[c] += w * ind[o + c];
            }
        }
    }
    long o = 3 * (y * dw + x);
    for (int c = 0; c < 3; ++c) {
        linear[o + c] = acc[c];
        mask[o + c] = sat[c];
    }
}

/* Channel c of the pixel at offset o of a view (gb_offset), 0 for o < 0: a tap outside the full
 * image, which the trajectory blur reads as nothing. */
static inline real gb_tap(__global const real *v, long o, int c)
{
    return o < 0 ? GB_REAL(0.0) : v[3 * o + c];
}

/* The share of the bilinear taps first and first + 1 (weights 1 - f and f) inside [0, n):
 * exactly 1 when both are. */
static inline real gb_inside_share(long first, real f, long n)
{
    int in0 = first >= 0 && first < n, in1 = first >= -1 && first < n - 1;
    return in0 && in1 ? GB_REAL(1.0) : in1 ? f : in0 ? GB_REAL(1.0) - f : GB_REAL(0.0);
}

/* blur, variant trajectory: add the linear image and its indicator warped by one pose to their
 * compensated sums, and the pose's weight to the weight's. Output pixel (gx, gy) samples src
 * bilinearly at H^-1 (gx, gy, 1) (hinv row-major), the image extended by zeros: taps outside
 * the full image read nothing, and the weight is the share of the bilinear weight on the image
 * (1 when every tap is inside), as gpu_blur.reference.shake.shake_blur ("Edges"). Positions are
 * computed in double where the device has it. src and ind are views holding every pixel of
 * the image the region's inverse mapping reads. The weights are one value per pixel. */
__kernel void gb_blur_trajectory_add(__global const real *src, __global const real *ind,
                                     long sx0, long sy0, long sw, long full_w, long full_h,
                                     __constant gb_pos *hinv, __global real *sum,
                                     __global real *sum_comp, __global real *sum_ind,
                                     __global real *sum_ind_comp, __global real *weight,
                                     __global real *weight_comp, long dx0, long dy0, long dw,
                                     long dh)
{
    long x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh) return;
    gb_pos gx = (gb_pos)(dx0 + x), gy = (gb_pos)(dy0 + y);
    gb_pos den = hinv[6] * gx + hinv[7] * gy + hinv[8];
    gb_pos px = (hinv[0] * gx + hinv[1] * gy + hinv[2]) / den;
    gb_pos py = (hinv[3] * gx + hinv[4] * gy + hinv[5]) / den;
    gb_pos fx0 = floor(px), fy0 = floor(py);
    real fx = (real)(px - fx0), fy = (real)(py - fy0);
    long xi = (long)fx0, yi = (long)fy0;
    int in_c0 = xi >= 0 && xi < full_w, in_c1 = xi >= -1 && xi < full_w - 1;
    int in_r0 = yi >= 0 && yi < full_h, in_r1 = yi >= -1 && yi < full_h - 1;
    long o00 = in_r0 && in_c0 ? gb_offset(xi, yi, sx0, sy0, sw) : -1;
    long o01 = in_r0 && in_c1 ? gb_offset(xi + 1, yi, sx0, sy0, sw) : -1;
    long o10 = in_r1 && in_c0 ? gb_offset(xi, yi + 1, sx0, sy0, sw) : -1;
    long o11 = in_r1 && in_c1 ? gb_offset(xi + 1, yi + 1, sx0, sy0, sw) : -1;
    long p = y * dw + x, o = 3 * p;
    for (int c = 0; c < 3; ++c) {
        real a = gb_tap(src, o00, c), b = gb_tap(src, o01, c);
        real top = a + (b - a) * fx;
        a = gb_tap(src, o10, c);
        b = gb_tap(src, o11, c);
        real bottom = a + (b - a) * fx;
        gb_add_compensated(sum, sum_comp, o + c, top + (bottom - top) * fy);
        a = gb_tap(ind, o00, c);
        b = gb_tap(ind, o01, c);
        top = a + (b - a) * fx;
        a = gb_tap(ind, o10, c);
        b = gb_tap(ind, o11, c);
        bottom = a + (b - a) * fx;
        gb_add_compensated(sum_ind, sum_ind_comp, o + c, top + (bottom - top) * fy);
    }
    gb_add_compensated(weight, weight_comp, p,
                       gb_inside_share(xi, fx, full_w) * gb_inside_share(yi, fy, full_h));
}

/* blur, variant trajectory: the sums over the poses divided by the pixel's total weight (the
 * pose count where every tap was inside); 0 where the weight is 0. */
__kernel void gb_blur_trajectory_finish(__global const real *sum, __global const real *sum_comp,
                                        __global const real *sum_ind,
                                        __global const real *sum_ind_comp,
                                        __global const real *weight,
                                        __global const real *weight_comp,
                                        __global real *linear, __global real *mask)
{
    size_t i = get_global_id(0);
    real w = weight[i / 3] + weight_comp[i / 3];
    linear[i] = w > GB_REAL(0.0) ? (sum[i] + sum_comp[i]) / w : GB_REAL(0.0);
    mask[i] = w > GB_REAL(0.0) ? (sum_ind[i] + sum_ind_comp[i]) / w : GB_REAL(0.0);
}
