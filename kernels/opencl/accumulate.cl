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

/* unit_values: stored values as reals in [0, 1] (codes / (2^bits - 1)): a mask given in its
 * stored dtype. */
__kernel void gb_unit_values(__global const gb_source *stored, __global real *values)
{
    size_t i = get_global_id(0);
    values[i] = gb_source_value(stored[i]);
}

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

/* blur, variant kernel: out = src convolved with k (true convolution, k normalized by the host),
 * reflect-101 at the full image's edges. src is a view (first pixel (sx0, sy0), width sw) that
 * holds the output region plus the kernel's radius; dst covers the output region. */
__kernel void gb_blur_kernel(__global const real *src, long sx0, long sy0, long sw,
                             long full_w, long full_h, __constant real *k, int kh, int kw,
                             __global real *dst, long dx0, long dy0, long dw, long dh)
{
    long x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh) return;
    long gx = dx0 + x, gy = dy0 + y;
    int ry = kh / 2, rx = kw / 2;
    real acc0 = 0, acc1 = 0, acc2 = 0;
    for (int i = 0; i < kh; ++i) {
        long sy = gb_reflect101(gy + ry - i, full_h);
        for (int j = 0; j < kw; ++j) {
            real w = k[i * kw + j];
            long sx = gb_reflect101(gx + rx - j, full_w);
            long o = 3 * gb_offset(sx, sy, sx0, sy0, sw);
            acc0 += w * src[o];
            acc1 += w * src[o + 1];
            acc2 += w * src[o + 2];
        }
    }
    long o = 3 * (y * dw + x);
    dst[o] = acc0;
    dst[o + 1] = acc1;
    dst[o + 2] = acc2;
}

/* blur, variant trajectory: add the linear image and its indicator warped by one pose to their
 * compensated sums. Output pixel (gx, gy) samples src bilinearly at H^-1 (gx, gy, 1) (hinv
 * row-major), with reflect-101 neighbours, as gpu_blur.reference.shake.warp_homography.
 * Positions are computed in double where the device has it. src and ind are views holding every
 * pixel the region's inverse mapping reads. */
__kernel void gb_blur_trajectory_add(__global const real *src, __global const real *ind,
                                     long sx0, long sy0, long sw, long full_w, long full_h,
                                     __constant gb_pos *hinv, __global real *sum,
                                     __global real *sum_comp, __global real *sum_ind,
                                     __global real *sum_ind_comp, long dx0, long dy0, long dw,
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
    long c0 = gb_reflect101(xi, full_w), c1 = gb_reflect101(xi + 1, full_w);
    long r0 = gb_reflect101(yi, full_h), r1 = gb_reflect101(yi + 1, full_h);
    long o00 = 3 * gb_offset(c0, r0, sx0, sy0, sw), o01 = 3 * gb_offset(c1, r0, sx0, sy0, sw);
    long o10 = 3 * gb_offset(c0, r1, sx0, sy0, sw), o11 = 3 * gb_offset(c1, r1, sx0, sy0, sw);
    long o = 3 * (y * dw + x);
    for (int c = 0; c < 3; ++c) {
        real top = src[o00 + c] + (src[o01 + c] - src[o00 + c]) * fx;
        real bottom = src[o10 + c] + (src[o11 + c] - src[o10 + c]) * fx;
        gb_add_compensated(sum, sum_comp, o + c, top + (bottom - top) * fy);
        real itop = ind[o00 + c] + (ind[o01 + c] - ind[o00 + c]) * fx;
        real ibottom = ind[o10 + c] + (ind[o11 + c] - ind[o10 + c]) * fx;
        gb_add_compensated(sum_ind, sum_ind_comp, o + c, itop + (ibottom - itop) * fy);
    }
}

/* blur, variant trajectory: the means over the poses (compensated totals over the count). */
__kernel void gb_blur_trajectory_finish(__global const real *sum, __global const real *sum_comp,
                                        __global const real *sum_ind,
                                        __global const real *sum_ind_comp, uint count,
                                        __global real *linear, __global real *mask)
{
    size_t i = get_global_id(0);
    linear[i] = (sum[i] + sum_comp[i]) / (real)count;
    mask[i] = (sum_ind[i] + sum_ind_comp[i]) / (real)count;
}
