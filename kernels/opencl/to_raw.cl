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
 * With GB_POISSON_DEFER (GPUs), gb_to_raw finishes only the pixels whose Poisson count is quick
 * and lists the others (about one in five at rates of 1e3 and more), and gb_to_raw_deferred
 * finishes those with the whole sampler, so its rare logarithmic branch runs on packed pixels
 * instead of holding up whole warps; each count comes from its pixel's own words, so this
 * changes no bit. Without it (CPUs, where it only costs) gb_to_raw draws every count.
 *
 * One launch runs a batch of samples of one plan: the third grid index is the sample, whose
 * drawn values are row b of sample_reals (gpu_blur.kernel_constants.SAMPLE_REALS) and
 * sample_words (SAMPLE_WORDS: CFA pattern, sample index, slot). Each buffer holds a slot per
 * sample, <buffer>_stride values apart; a sample reads and writes its slot `slot`.
 */
#include "gb_common.h"
#include "gb_random.h"

/* The saturated RGB of pixel i of the sample's buffers (global column gx, row gy), written; with
 * the mosaic it returns the camera value the site keeps, white balance undone, and sets *gain to
 * that white balance's gain. */
static inline real gb_camera_value(__global const real *linear, __global const real *mask,
                                   __global real *saturated, __global const real *drawn,
                                   gb_sample sample, long i, long gx, long gy,
                                   __constant real *lin_to_cam, real vignetting, real full_h,
                                   real full_w, real *gain)
{
    real v[3];
#ifdef GB_STAGE_VIGNETTING
    /* 1 - s (r / r_corner)^2 about the image centre, as reference.optics.vignetting_gain */
    real cy = GB_REAL(0.5) * full_h, cx = GB_REAL(0.5) * full_w;
    real dy = ((real)gy + GB_REAL(0.5)) - cy, dx = ((real)gx + GB_REAL(0.5)) - cx;
    real shade = GB_REAL(1.0) - vignetting * ((dx * dx + dy * dy) / (cx * cx + cy * cy));
#endif
    for (int c = 0; c < 3; ++c) {
        v[c] = linear[3 * i + c];
#ifdef GB_STAGE_SATURATE
        v[c] = clamp(v[c] + drawn[0] * mask[3 * i + c], GB_REAL(0.0), GB_REAL(1.0));
#endif
#ifdef GB_STAGE_VIGNETTING
        v[c] = v[c] * shade;
#endif
        saturated[3 * i + c] = v[c];
    }
    real s = GB_REAL(0.0);
    *gain = GB_REAL(1.0);
#ifdef GB_STAGE_MOSAIC
    int ch = gb_cfa_channel(sample.cfa, gx, gy);
    /* linear_to_camera, only the channel the mosaic keeps */
    s = lin_to_cam[3 * ch] * v[0] + lin_to_cam[3 * ch + 1] * v[1] + lin_to_cam[3 * ch + 2] * v[2];
#ifdef GB_CLIP_CAMERA
    s = clamp(s, GB_REAL(0.0), GB_REAL(1.0));
#endif
    *gain = ch == 0 ? drawn[1] : (ch == 2 ? drawn[2] : GB_REAL(1.0));
    s = s / *gain; /* inverse_white_balance */
#endif
    return s;
}

/* The RAW value of pixel i from its camera value s, its Poisson counts (with the noise), and
 * its white balance gain. */
static inline void gb_write_raw(__global real *raw, long i, real s, real gain, real counts,
                                __global const real *drawn, uint2 key, gb_sample sample,
                                long gx, long gy)
{
#ifdef GB_STAGE_POISSON_GAUSSIAN_NOISE
    real z = gb_pixel_normal(key, sample.sample_index, GB_STREAM_READ_NOISE, (uint)gx, (uint)gy,
                             0u);
    s = drawn[3] * counts + drawn[4] * z;
#endif
    raw[i] = s * gain; /* white_balance */
}

/* The Poisson rate of camera value s: max(s, 0) / K. */
#define GB_SHOT_RATE(s, drawn) (fmax((s), GB_REAL(0.0)) / (drawn)[3])

/* Shot-noise counts (rate, threshold, key, sample index, x, y): the whole sampler, and what
 * gb_to_raw draws: with GB_POISSON_DEFER only the quick cases. */
#ifdef GB_POISSON_NORMAL
#define GB_WHOLE_COUNTS(r, above, key, n, x, y) gb_poisson_normal_above(r, above, key, n, x, y)
#define GB_QUICK_COUNTS(r, above, key, n, x, y) \
    gb_poisson_normal_above_quick(r, above, key, n, x, y)
#else
#define GB_WHOLE_COUNTS(r, above, key, n, x, y) gb_poisson(r, key, n, x, y)
#define GB_QUICK_COUNTS(r, above, key, n, x, y) gb_poisson_quick(r, key, n, x, y)
#endif
#ifdef GB_POISSON_DEFER
#define GB_COUNTS GB_QUICK_COUNTS
#else
#define GB_COUNTS GB_WHOLE_COUNTS
#endif

/* Every pixel; with GB_POISSON_DEFER, those whose Poisson count is not quick (gb_poisson_quick)
 * only go to `deferred` as their numbers (b h + y) w + x (in no particular order, counted in
 * deferred_count[0]) for gb_to_raw_deferred. */
__kernel void gb_to_raw(__global const real *linear, long linear_stride,
                        __global const real *mask, long mask_stride, long x0, long y0, long w,
                        long h, __global const real *sample_reals,
                        __global const uint *sample_words, __constant real *lin_to_cam,
                        real poisson_normal_above, uint key_lo, uint key_hi,
                        __global real *saturated, long saturated_stride, __global real *raw,
                        long raw_stride, real vignetting, real full_h, real full_w,
                        __global uint *deferred, __global uint *deferred_count)
{
    long x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    if (x >= w || y >= h) return;
    __global const real *drawn = sample_reals + GB_SAMPLE_REALS * b;
    gb_sample sample = gb_sample_of(sample_words, b);
    long i = y * w + x, gx = x0 + x, gy = y0 + y;
    real gain;
    real s = gb_camera_value(linear + sample.slot * linear_stride,
                             mask + sample.slot * mask_stride,
                             saturated + sample.slot * saturated_stride, drawn, sample, i, gx, gy,
                             lin_to_cam, vignetting, full_h, full_w, &gain);
#ifdef GB_STAGE_MOSAIC
    uint2 key = (uint2)(key_lo, key_hi);
    real counts = GB_REAL(0.0);
#ifdef GB_STAGE_POISSON_GAUSSIAN_NOISE
    counts = GB_COUNTS(GB_SHOT_RATE(s, drawn), poisson_normal_above, key, sample.sample_index,
                       (uint)gx, (uint)gy);
#ifdef GB_POISSON_DEFER
    if (counts == GB_POISSON_DEFERRED) {
        deferred[atomic_inc(deferred_count)] = (uint)((b * h + y) * w + x);
        return;
    }
#endif
#endif
    gb_write_raw(raw + sample.slot * raw_stride, i, s, gain, counts, drawn, key, sample, gx, gy);
#endif
}

/* The pixels gb_to_raw deferred, one a work item (the grid covers every pixel of the batch;
 * items past the count return), their counts by the whole sampler: the same words, so the
 * same count as one pass would give. */
__kernel void gb_to_raw_deferred(__global const real *linear, long linear_stride,
                                 __global const real *mask, long mask_stride, long x0, long y0,
                                 long w, long h, __global const real *sample_reals,
                                 __global const uint *sample_words, __constant real *lin_to_cam,
                                 real poisson_normal_above, uint key_lo, uint key_hi,
                                 __global real *saturated, long saturated_stride,
                                 __global real *raw, long raw_stride, real vignetting,
                                 real full_h, real full_w, __global const uint *deferred,
                                 __global const uint *deferred_count)
{
#if defined(GB_STAGE_MOSAIC) && defined(GB_STAGE_POISSON_GAUSSIAN_NOISE)
    size_t t = get_global_id(0);
    if (t >= deferred_count[0]) return;
    long number = deferred[t];
    long x = number % w, y = (number / w) % h, b = number / (w * h);
    __global const real *drawn = sample_reals + GB_SAMPLE_REALS * b;
    gb_sample sample = gb_sample_of(sample_words, b);
    long i = y * w + x, gx = x0 + x, gy = y0 + y;
    real gain;
    real s = gb_camera_value(linear + sample.slot * linear_stride,
                             mask + sample.slot * mask_stride,
                             saturated + sample.slot * saturated_stride, drawn, sample, i, gx, gy,
                             lin_to_cam, vignetting, full_h, full_w, &gain);
    uint2 key = (uint2)(key_lo, key_hi);
    real counts = GB_WHOLE_COUNTS(GB_SHOT_RATE(s, drawn), poisson_normal_above, key,
                                  sample.sample_index, (uint)gx, (uint)gy);
    gb_write_raw(raw + sample.slot * raw_stride, i, s, gain, counts, drawn, key, sample, gx, gy);
#endif
}
