/* finish.cl: pass 3 of the plan: "demosaic" (5 x 5 stencil), then pointwise
 * "camera_to_linear", "tone", "gaussian_noise", "restore_saturated", "retone", "quantize"
 * (each compiled in only when the plan keeps it). Reads the RAW mosaic and B_sat from a view
 * (first pixel (vx0, vy0), width vw) that holds the output region plus the demosaic halo, and
 * writes the output region (first pixel (ox0, oy0), size ow x oh), 3 reals per pixel, two
 * pixels (an even global column and the next) a work item.
 *
 * One launch runs a batch of samples of one plan, as gb_to_raw: the third grid index is the
 * sample, its values row b of sample_reals (gpu_blur.kernel_constants.SAMPLE_REALS) and
 * sample_words; each buffer holds a slot per sample, <buffer>_stride values apart.
 */
#include "gb_common.h"
#include "gb_pixel.h"
#include "gb_random.h"
#include "gb_demosaic.h"

/* The pixel at global (gx, gy) of sample `sample` into out[o .. o + 2]. */
static inline void gb_finish_pixel(__global const real *raw, __global const real *saturated,
                                   long vx0, long vy0, long vw, long full_w, long full_h,
                                   long gx, long gy, __global real *out, long o,
                                   gb_sample sample, real gaussian_std,
                                   __constant real *cam_to_lin, uint2 key,
                                   __constant real *crf_polynomial, int crf_polynomial_n,
                                   __global const real *crf_table, int crf_table_n)
{
    long v = 3 * gb_offset(gx, gy, vx0, vy0, vw);
    real rgb[3];
#ifdef GB_STAGE_DEMOSAIC
    real cam[3];
#ifdef GB_DEMOSAIC_BILINEAR
    gb_demosaic_bilinear(raw, vx0, vy0, vw, full_w, full_h, gx, gy, sample.cfa, GB_ZERO_BORDER,
                         cam);
#else
    gb_demosaic_malvar2004(raw, vx0, vy0, vw, full_w, full_h, gx, gy, sample.cfa,
                           GB_ZERO_BORDER, cam);
#endif
#ifdef GB_CLIP_DEMOSAIC
    for (int c = 0; c < 3; ++c) cam[c] = clamp(cam[c], GB_REAL(0.0), GB_REAL(1.0));
#endif
    gb_apply_matrix(cam_to_lin, cam, rgb); /* camera_to_linear */
#else
    for (int c = 0; c < 3; ++c) rgb[c] = saturated[v + c];
#endif
    for (int c = 0; c < 3; ++c) {
        real p = rgb[c];
#ifdef GB_STAGE_TONE
        p = gb_linear_to_srgb(p);
#endif
        p = clamp(p, GB_REAL(0.0), GB_REAL(1.0));
#ifdef GB_STAGE_GAUSSIAN_NOISE
        p += gaussian_std * gb_pixel_normal(key, sample.sample_index, GB_STREAM_SRGB_NOISE,
                                            (uint)gx, (uint)gy, (uint)c);
        p = clamp(p, GB_REAL(0.0), GB_REAL(1.0));
#endif
#ifdef GB_STAGE_RESTORE_SATURATED
        if (saturated[v + c] >= GB_REAL(1.0)) p = GB_REAL(1.0);
#endif
        out[o + c] = gb_retone_quantize(p, crf_polynomial, crf_polynomial_n, crf_table,
                                        crf_table_n);
    }
}

/* Two pixels a work item, GLOBAL columns 2 t' and 2 t' + 1, pairs from the even column at or
 * left of ox0 (the grid's first axis counts the pairs the output touches): at each of the two
 * steps every work item of a row is at a site of one Bayer colour, so the demosaic's branches
 * do not diverge, and a column is always done by the same step, in a tile as in the whole
 * image. */
__kernel void gb_finish(__global const real *raw, long raw_stride,
                        __global const real *saturated, long saturated_stride, long vx0,
                        long vy0, long vw, long full_w, long full_h, long ox0, long oy0, long ow,
                        long oh, __global const real *sample_reals,
                        __global const uint *sample_words, __constant real *cam_to_lin,
                        uint key_lo, uint key_hi, __constant real *crf_polynomial,
                        int crf_polynomial_n, __global const real *crf_table, int crf_table_n,
                        __global real *out, long out_stride)
{
    long t = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    long first = 2 * t - ox0 % 2; /* output column of the pair's even global column */
    if (first >= ow || y >= oh) return;
    real gaussian_std = sample_reals[GB_SAMPLE_REALS * b + 5];
    gb_sample sample = gb_sample_of(sample_words, b);
    raw += sample.slot * raw_stride;
    saturated += sample.slot * saturated_stride;
    out += sample.slot * out_stride;
    uint2 key = (uint2)(key_lo, key_hi);
    for (long x = max(first, 0L); x < first + 2 && x < ow; ++x)
        gb_finish_pixel(raw, saturated, vx0, vy0, vw, full_w, full_h, ox0 + x, oy0 + y, out,
                        3 * (y * ow + x), sample, gaussian_std, cam_to_lin, key, crf_polynomial,
                        crf_polynomial_n, crf_table, crf_table_n);
}
