/* interpolate.cl: frame interpolation inside pass 1 (stage "blur", variant average, with
 * blur.interpolation > 1).
 *
 * The maths is gpu_blur.reference.interpolate (module docstring, steps 2 to 4): the frame at
 * time t between two sRGB frames is blended from both frames warped backwards along the scaled
 * optical flows, with the forward-backward occlusion rule, then linearized and added to the
 * averaging sums like any frame. Intermediate frames are never stored: each work item computes
 * its pixel and adds it.
 *
 * Images are interleaved RGB (3 values per pixel), frames in their stored type (gb_source,
 * gb_common.h), flows interleaved (dx, dy) float32 (OpenCV's type, so read exactly in either
 * precision), all row-major. The host adds, in time order, each original frame
 * (gb_blur_interpolate_add_frame) and the intermediates after it (gb_blur_interpolate_add) to
 * one set of sums, each times its weight (1, or the frames it stands for under adaptive
 * interpolation: reference.interpolate, steps 6 and 7, M / f for a pixel whose region has
 * factor f), then takes the mean over the total weight (gb_blur_interpolate_finish). Each
 * gap's factors per region come as a uint table from map0 (rows of cols regions of side
 * pixels on a grid from the image's top-left pixel; side 0: one region); an intermediate at
 * step / factor is added only at pixels whose region's factor f makes step f / factor whole.
 * The frames and flows are views (first pixel (sx0, sy0), width sw) of one region that holds
 * the output region plus the halo of gpu_blur.reference.interpolate.interpolation_halo; the sums
 * cover the output region. Pixels are addressed by global coordinates (gb_common.h), so a tile
 * gives the whole image's values.
 * Positions, flows and the occlusion test are computed in gb_pos (double where the device has
 * it), as the reference's float64, so the test decides as the reference does.
 */
#include "gb_common.h"
#include "gb_pixel.h"
#include "gb_sum.h"

#pragma OPENCL FP_CONTRACT OFF

/* One sRGB value in [0, 1] of a frame (stored as gb_source), at offset o. */
#define GB_FRAME_VALUE(frame, o) gb_source_value((frame)[o])

/* Saturation indicator of one stored sRGB value: 1 at or above 1 (linear 1), else 0. */
#define GB_SATURATED(v) ((v) >= GB_SATURATION_LEVEL ? GB_REAL(1.0) : GB_REAL(0.0))

/* The factor of the region holding global pixel (gx, gy) in a gap's table (see above). */
static inline uint gb_region_factor(__global const uint *factors, long map0, long side,
                                    long cols, long gx, long gy)
{
    return factors[map0 + (side ? (gy / side) * cols + gx / side : 0)];
}

/* Bilinear sample of an RGB frame view at (px, py), reflect-101 neighbours, as
 * reference.sampling.bilinear_sample: a + f (b - a) along x, then along y. sat gets the same
 * sample of the frame's saturation indicator (reference.interpolate, module step 4). */
static inline void gb_interp_sample_rgb(__global const gb_source *frame, long sx0, long sy0, long sw,
                                        long full_w, long full_h, gb_pos px, gb_pos py,
                                        real out[3], real sat[3])
{
    gb_pos fx0 = floor(px), fy0 = floor(py);
    real fx = (real)(px - fx0), fy = (real)(py - fy0);
    long xi = (long)fx0, yi = (long)fy0;
    long c0 = gb_reflect101(xi, full_w), c1 = gb_reflect101(xi + 1, full_w);
    long r0 = gb_reflect101(yi, full_h), r1 = gb_reflect101(yi + 1, full_h);
    long o00 = 3 * gb_offset(c0, r0, sx0, sy0, sw), o01 = 3 * gb_offset(c1, r0, sx0, sy0, sw);
    long o10 = 3 * gb_offset(c0, r1, sx0, sy0, sw), o11 = 3 * gb_offset(c1, r1, sx0, sy0, sw);
    for (int c = 0; c < 3; ++c) {
        real a = GB_FRAME_VALUE(frame, o00 + c), b = GB_FRAME_VALUE(frame, o01 + c);
        real sa = GB_SATURATED(a), sb = GB_SATURATED(b);
        real top = a + (b - a) * fx, sat_top = sa + (sb - sa) * fx;
        a = GB_FRAME_VALUE(frame, o10 + c);
        b = GB_FRAME_VALUE(frame, o11 + c);
        sa = GB_SATURATED(a);
        sb = GB_SATURATED(b);
        real bottom = a + (b - a) * fx, sat_bottom = sa + (sb - sa) * fx;
        out[c] = top + (bottom - top) * fy;
        sat[c] = sat_top + (sat_bottom - sat_top) * fy;
    }
}

/* Bilinear sample of a flow view at (px, py) in gb_pos, reflect-101 neighbours (the order of
 * gb_interp_sample_rgb). */
static inline void gb_interp_sample_flow(__global const float *flow, long sx0, long sy0, long sw,
                                         long full_w, long full_h, gb_pos px, gb_pos py,
                                         gb_pos out[2])
{
    gb_pos fx0 = floor(px), fy0 = floor(py);
    gb_pos fx = px - fx0, fy = py - fy0;
    long xi = (long)fx0, yi = (long)fy0;
    long c0 = gb_reflect101(xi, full_w), c1 = gb_reflect101(xi + 1, full_w);
    long r0 = gb_reflect101(yi, full_h), r1 = gb_reflect101(yi + 1, full_h);
    long o00 = 2 * gb_offset(c0, r0, sx0, sy0, sw), o01 = 2 * gb_offset(c1, r0, sx0, sy0, sw);
    long o10 = 2 * gb_offset(c0, r1, sx0, sy0, sw), o11 = 2 * gb_offset(c1, r1, sx0, sy0, sw);
    for (int c = 0; c < 2; ++c) {
        gb_pos a = flow[o00 + c], b = flow[o01 + c];
        gb_pos top = a + (b - a) * fx;
        a = flow[o10 + c];
        b = flow[o11 + c];
        gb_pos bottom = a + (b - a) * fx;
        out[c] = top + (bottom - top) * fy;
    }
}

/* Whether `flow` at global (gx, gy) is confirmed by `reverse` (reference.interpolate.
 * flow_consistent): |w + w'|^2 <= relative (|w|^2 + |w'|^2) + absolute_px2, w' = reverse
 * sampled at (gx, gy) + w. */
static inline int gb_interp_consistent(__global const float *flow, __global const float *reverse,
                                       long sx0, long sy0, long sw, long full_w, long full_h,
                                       long gx, long gy, gb_pos relative, gb_pos absolute_px2)
{
    long o = 2 * gb_offset(gx, gy, sx0, sy0, sw);
    gb_pos wx = flow[o], wy = flow[o + 1];
    gb_pos back[2];
    gb_interp_sample_flow(reverse, sx0, sy0, sw, full_w, full_h, (gb_pos)gx + wx,
                          (gb_pos)gy + wy, back);
    gb_pos ex = wx + back[0], ey = wy + back[1];
    gb_pos norms = (wx * wx + wy * wy) + (back[0] * back[0] + back[1] * back[1]);
    return ex * ex + ey * ey <= relative * norms + absolute_px2;
}

/* blur, variant average with interpolation: add the frame at time t = step / factor in (0, 1)
 * between frame0 and frame1, linearized, to the compensated sums, and its saturated fractions
 * (the blend of the frames' sampled indicators) to saturated, each times M / f (most over the
 * pixel's region factor), where the region takes this time. flow_fw
 * maps frame0 to frame1, flow_bw frame1 to frame0 (pixels, OpenCV's convention); relative and
 * absolute_px2 are the occlusion test's constants (reference.interpolate.CONSISTENCY_*).
 * Launched over (dw, dh) work items or more (extra ones return). */
__kernel void gb_blur_interpolate_add(__global const gb_source *frame0,
                                      __global const gb_source *frame1,
                                      __global const float *flow_fw,
                                      __global const float *flow_bw, long sx0, long sy0, long sw,
                                      long full_w, long full_h, gb_pos t, gb_pos relative,
                                      gb_pos absolute_px2, uint step, uint factor,
                                      __global const uint *factors, long map0, long side,
                                      long cols, uint most, __global real *sum,
                                      __global real *compensation, __global real *saturated,
                                      long dx0, long dy0, long dw, long dh)
{
    long x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh) return;
    long gx = dx0 + x, gy = dy0 + y;
    uint own = gb_region_factor(factors, map0, side, cols, gx, gy);
    if ((step * own) % factor != 0) return; /* not one of this region's times */
    real weight = (real)(most / own);
    long o = 2 * gb_offset(gx, gy, sx0, sy0, sw);
    gb_pos fwx = flow_fw[o], fwy = flow_fw[o + 1];
    gb_pos bwx = flow_bw[o], bwy = flow_bw[o + 1];
    /* frame0's sample came along flow_bw, frame1's along flow_fw: each is trusted where the
     * flow that carried it passes the test against the other */
    int trust_a = gb_interp_consistent(flow_bw, flow_fw, sx0, sy0, sw, full_w, full_h, gx, gy,
                                       relative, absolute_px2);
    int trust_b = gb_interp_consistent(flow_fw, flow_bw, sx0, sy0, sw, full_w, full_h, gx, gy,
                                       relative, absolute_px2);
    real a[3], b[3], sat_a[3], sat_b[3];
    gb_interp_sample_rgb(frame0, sx0, sy0, sw, full_w, full_h, (gb_pos)gx + t * bwx,
                         (gb_pos)gy + t * bwy, a, sat_a);
    gb_interp_sample_rgb(frame1, sx0, sy0, sw, full_w, full_h, (gb_pos)gx + (1 - t) * fwx,
                         (gb_pos)gy + (1 - t) * fwy, b, sat_b);
    real wa = (real)(1 - t), wb = (real)t;
    long od = 3 * (y * dw + x);
    for (int c = 0; c < 3; ++c) {
        real v = trust_a == trust_b ? wa * a[c] + wb * b[c] : (trust_a ? a[c] : b[c]);
        real s = trust_a == trust_b ? wa * sat_a[c] + wb * sat_b[c]
                                    : (trust_a ? sat_a[c] : sat_b[c]);
        gb_add_compensated(sum, compensation, od + c, gb_srgb_to_linear(v) * weight);
        saturated[od + c] += s * weight;
    }
}

/* blur, variant average with interpolation: add an original frame, linearized, times M / f (f
 * the factor of the pixel's region in the gap it starts; 1 for the last frame) to the sums and
 * its saturated channels (M / f where the linear value is >= 1) to saturated. frame is a
 * view (first pixel (sx0, sy0), width sw) holding the output region (dx0, dy0, dw, dh). */
__kernel void gb_blur_interpolate_add_frame(__global const gb_source *frame, long sx0, long sy0,
                                            long sw, __global const uint *factors, long map0,
                                            long side, long cols, uint most,
                                            __global real *sum, __global real *compensation,
                                            __global real *saturated, long dx0, long dy0,
                                            long dw, long dh)
{
    long x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh) return;
    real weight = (real)(most / gb_region_factor(factors, map0, side, cols, dx0 + x, dy0 + y));
    long o = 3 * gb_offset(dx0 + x, dy0 + y, sx0, sy0, sw);
    long od = 3 * (y * dw + x);
    for (int c = 0; c < 3; ++c) {
        real lin = gb_srgb_to_linear(GB_FRAME_VALUE(frame, o + c));
        gb_add_compensated(sum, compensation, od + c, lin * weight);
        saturated[od + c] += lin >= GB_SATURATION_LEVEL ? weight : GB_REAL(0.0);
    }
}

/* blur, variant average with interpolation: the mean of the count frames (the compensated total
 * over the count) and the mean of their saturated fractions, per channel. */
__kernel void gb_blur_interpolate_finish(__global const real *sum,
                                         __global const real *compensation,
                                         __global const real *saturated, uint count,
                                         __global real *linear, __global real *mask)
{
    size_t i = get_global_id(0);
    linear[i] = (sum[i] + compensation[i]) / (real)count;
    mask[i] = saturated[i] / (real)count;
}
