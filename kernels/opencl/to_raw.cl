/* to_raw.cl: pass 2 of the plan, pointwise from the linear blurred image to noisy RAW:
 * stages "saturate", "vignetting", "linear_to_camera", "mosaic", "inverse_white_balance",
 * "poisson_gaussian_noise", "white_balance" (each compiled in only when the plan keeps it,
 * GB_STAGE_<NAME>; with GB_POISSON_NORMAL, counts above the rate poisson_normal_above come from
 * the normal approximation, scene noise.poisson = "normal"). Writes B_sat (3 reals per pixel)
 * and, with the RAW round trip, the white-balanced mosaic (1 real per pixel). All buffers cover
 * the same region of the image, whose first pixel is global (x0, y0). The last arguments are
 * the plan's to_raw stage values (gpu_blur.backends.kernel.stage_values): vignetting's
 * strength and the whole image's height and width.
 *
 * One launch runs a batch of samples of one plan: the third grid index is the sample, whose
 * drawn values are row b of sample_reals (gpu_blur.kernel_constants.SAMPLE_REALS) and
 * sample_words (SAMPLE_WORDS: CFA pattern, sample index, slot). Each buffer holds a slot per
 * sample, <buffer>_stride values apart; a sample reads and writes its slot `slot`.
 */
#include "gb_common.h"
#include "gb_random.h"

__kernel void gb_to_raw(__global const real *linear, long linear_stride,
                        __global const real *mask, long mask_stride, long x0, long y0, long w,
                        long h, __global const real *sample_reals,
                        __global const uint *sample_words, __constant real *lin_to_cam,
                        real poisson_normal_above, uint key_lo, uint key_hi,
                        __global real *saturated, long saturated_stride, __global real *raw,
                        long raw_stride, real vignetting, real full_h, real full_w)
{
    long x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= w || y >= h) return;
    __global const real *drawn = sample_reals + GB_SAMPLE_REALS * b;
    real alpha = drawn[0], red_gain = drawn[1], blue_gain = drawn[2];
    real shot_noise_k = drawn[3], read_noise_std = drawn[4];
    gb_sample sample = gb_sample_of(sample_words, b);
    linear += sample.slot * linear_stride;
    mask += sample.slot * mask_stride;
    saturated += sample.slot * saturated_stride;
    raw += sample.slot * raw_stride;
    long i = y * w + x;
    real v[3];
#ifdef GB_STAGE_VIGNETTING
    /* 1 - s (r / r_corner)^2 about the image centre, as reference.optics.vignetting_gain */
    real cy = GB_REAL(0.5) * full_h, cx = GB_REAL(0.5) * full_w;
    real dy = ((real)(y0 + y) + GB_REAL(0.5)) - cy, dx = ((real)(x0 + x) + GB_REAL(0.5)) - cx;
    real shade = GB_REAL(1.0) - vignetting * ((dx * dx + dy * dy) / (cx * cx + cy * cy));
#endif
    for (int c = 0; c < 3; ++c) {
        v[c] = linear[3 * i + c];
#ifdef GB_STAGE_SATURATE
        v[c] = clamp(v[c] + alpha * mask[3 * i + c], GB_REAL(0.0), GB_REAL(1.0));
#endif
#ifdef GB_STAGE_VIGNETTING
        v[c] = v[c] * shade;
#endif
        saturated[3 * i + c] = v[c];
    }
#ifdef GB_STAGE_MOSAIC
    long gx = x0 + x, gy = y0 + y;
    int ch = gb_cfa_channel(sample.cfa, gx, gy);
    /* linear_to_camera, only the channel the mosaic keeps */
    real s = lin_to_cam[3 * ch] * v[0] + lin_to_cam[3 * ch + 1] * v[1]
             + lin_to_cam[3 * ch + 2] * v[2];
#ifdef GB_CLIP_CAMERA
    s = clamp(s, GB_REAL(0.0), GB_REAL(1.0));
#endif
    real gain = ch == 0 ? red_gain : (ch == 2 ? blue_gain : GB_REAL(1.0));
    s = s / gain; /* inverse_white_balance */
#ifdef GB_STAGE_POISSON_GAUSSIAN_NOISE
    uint2 key = (uint2)(key_lo, key_hi);
    real rate = fmax(s, GB_REAL(0.0)) / shot_noise_k;
#ifdef GB_POISSON_NORMAL
    real counts = gb_poisson_normal_above(rate, poisson_normal_above, key, sample.sample_index,
                                          (uint)gx, (uint)gy);
#else
    real counts = gb_poisson(rate, key, sample.sample_index, (uint)gx, (uint)gy);
#endif
    real z = gb_pixel_normal(key, sample.sample_index, GB_STREAM_READ_NOISE, (uint)gx, (uint)gy,
                             0u);
    s = shot_noise_k * counts + read_noise_std * z;
#endif
    raw[i] = s * gain; /* white_balance */
#endif
}
