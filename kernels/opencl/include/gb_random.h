/* gb_random.h: counter-based random draws for the kernels, the device side of
 * gpu_blur/reference/rng.py and gpu_blur/reference/poisson_counts.py.
 *
 * Provides Philox4x32-10 (gb_philox, from pyopencl's bundled Random123 philox.cl), the per-pixel
 * words (gb_pixel_bits), uniforms (gb_uniform), Box-Muller normals (gb_box_muller,
 * gb_pixel_normal), log(k!) (gb_log_factorial), the Poisson sampler (gb_poisson) and its normal
 * approximation above a threshold rate (gb_poisson_normal_above, scene noise.poisson = "normal").
 *
 * The contract is the module docstrings of rng.py and poisson_counts.py, repeated here
 * operation for operation:
 *   key      (seed & 0xFFFFFFFF, seed >> 32), passed as a uint2
 *   counter  (x, y, sample_index, (stream << 24) | round), x and y the pixel's GLOBAL column
 *            and row, round in [0, 2^24) numbering blocks of four words of one pixel
 *   uniform  ((bits >> 9) + 0.5) * 2^-23: exact in float and in double
 *   normals  4 per round: (cos, sin) of Box-Muller on words (0, 1), then on words (2, 3)
 *   Poisson  stream SHOT_NOISE; inversion on word 0 of round 0 below rate 10, PTRS at 10 and
 *            above, attempt 2r on words (0, 1) and attempt 2r + 1 on words (2, 3) of round r;
 *            the normal approximation on the cos normal of words (0, 1) of round 0
 *
 * Precision rule. Where the device has fp64 (GB_HAS_FP64, or GB_FP64) the Poisson sampler,
 * log(k!) and Box-Muller compute in double even in a float build, and round once to `real` at
 * the end: float PTRS arithmetic flips floor() on ~0.1 % of pixels at rates ~1e4 (0.35 %
 * measured at 1e4, 15 % at 1e7), and float Box-Muller misses the 1e-6 target for normals
 * (measured 1.5e-6 with cos((2 pi)_f u2); ulp(4) is already 4.8e-7). Without fp64 the same
 * code runs in float (type gb_wide) and agrees with the reference less closely: Poisson counts
 * are then right in distribution, not pixel for pixel, at rates >= 10. The measured agreement
 * is in gpu_blur/tolerances.py (section "OpenCL random").
 *
 * Fast maths (GB_FAST_MATH in a float build, gb_math.h): the normals of gb_box_muller run in float
 * with native_ functions; the Poisson samplers are unchanged.
 *
 * Floating-point contraction is switched off inside the functions below (the reference rounds
 * every product and sum); do not build with -cl-mad-enable, -cl-unsafe-math-optimizations or
 * -cl-fast-relaxed-math.
 *
 * The build passes -I <pyopencl package>/cl so that Random123's header is found.
 */
#ifndef GB_RANDOM_H
#define GB_RANDOM_H

#include "gb_common.h"
#include "gb_math.h"
#include <pyopencl-random123/philox.cl>

/* The wide type of the samplers: double where the device has it, float otherwise. */
#if defined(GB_HAS_FP64) || defined(GB_FP64)
#define GB_RANDOM_WIDE_IS_DOUBLE 1
typedef double gb_wide;
#define GB_WIDE(x) (x)
#else
/* No cl_khr_fp64: float throughout. Poisson counts then differ from the float64 reference on
 * a small fraction of pixels (mostly PTRS floor() boundaries at large rates). */
typedef float gb_wide;
#define GB_WIDE(x) (x##f)
#endif

/* From gpu_blur.reference.rng and .poisson_counts, in gb_constants.h: the stream numbers
 * GB_STREAM_<NAME> (rng.Stream; SPOT_CHECK is host only), GB_STREAM_SHIFT and GB_ROUND_LIMIT
 * (2^24 rounds below the stream byte), GB_UNIFORM_SHIFT and GB_UNIFORM_SCALE, 2 pi
 * (GB_TWO_PI_DOUBLE, GB_TWO_PI_FLOAT), log(k!) (GB_LOG_FACTORIAL_TABLE, GB_HALF_LOG_TWO_PI),
 * GB_POISSON_PTRS_MIN_RATE, GB_POISSON_INVERSION_MAX_K and PTRS's GB_PTRS_<NAME>
 * (poisson_counts.PTRS_<NAME>). */

/* Philox4x32-10 block function: four 32-bit words of counter under a two-word key. */
static inline uint4 gb_philox(uint4 counter, uint2 key)
{
    philox4x32_ctr_t c = {{counter.x, counter.y, counter.z, counter.w}};
    philox4x32_key_t k = {{key.x, key.y}};
    philox4x32_ctr_t r = philox4x32_R(10, c, k);
    return (uint4)(r.v[0], r.v[1], r.v[2], r.v[3]);
}

/* The four words of pixel (x, y), round `round` (< 2^24), stream `stream` (< 256). */
static inline uint4 gb_pixel_bits(uint2 key, uint sample_index, uint stream, uint x, uint y,
                                  uint round)
{
    return gb_philox((uint4)(x, y, sample_index, (stream << GB_STREAM_SHIFT) | round), key);
}

/* A word as a uniform in (0, 1): an odd multiple of 2^-24, exact in float and double. */
static inline real gb_uniform(uint bits)
{
    return ((real)(bits >> GB_UNIFORM_SHIFT) + GB_REAL(0.5)) * GB_UNIFORM_SCALE;
}

/* Box-Muller in gb_wide: r = sqrt(-2 log u1), t = (2 pi) u2; (r cos t, r sin t). */
static inline void gb_box_muller_wide(gb_wide u1, gb_wide u2, gb_wide *z_cos, gb_wide *z_sin)
{
#pragma OPENCL FP_CONTRACT OFF
    const gb_wide radius = sqrt(GB_WIDE(-2.0) * log(u1));
#ifdef GB_RANDOM_WIDE_IS_DOUBLE
    /* 2 * pi rounded to double, as numpy's 2.0 * math.pi. */
    const gb_wide angle = GB_TWO_PI_DOUBLE * u2;
    *z_cos = radius * cos(angle);
    *z_sin = radius * sin(angle);
#else
    /* In float, (2 pi)_f * u2 misplaces the angle by up to 4.1e-7 rad (times |z| <= 5.8);
     * 2 * u2 is exact, so cospi / sinpi see the reference's angle. */
    const float half_turns = 2.0f * u2;
    *z_cos = radius * cospi(half_turns);
    *z_sin = radius * sinpi(half_turns);
#endif
}

/* Box-Muller of the normals (rng.box_muller), rounded once to `real`. With GB_NATIVE_MATH
 * (gb_math.h) it runs in float on native_ functions instead, the angle moved into [-pi, pi),
 * where native sin and cos are most accurate: t' = (2 pi)_f (u2 - 0.5) (u2 - 0.5 is exact) and
 * cos t = -cos t', sin t = -sin t'. */
static inline void gb_box_muller(real u1, real u2, real *z_cos, real *z_sin)
{
#pragma OPENCL FP_CONTRACT OFF
#ifdef GB_NATIVE_MATH
    const float radius = gb_sqrt(-2.0f * gb_log(u1));
    const float angle = GB_TWO_PI_FLOAT * (u2 - 0.5f);
    *z_cos = -radius * gb_cos(angle);
    *z_sin = -radius * gb_sin(angle);
#else
    gb_wide c, s;
    gb_box_muller_wide((gb_wide)u1, (gb_wide)u2, &c, &s);
    *z_cos = (real)c;
    *z_sin = (real)s;
#endif
}

/* Normal number `index` of pixel (x, y): round index / 4; within it, normals 0, 1 are
 * Box-Muller (cos, sin) of words (0, 1) and normals 2, 3 of words (2, 3). */
static inline real gb_pixel_normal(uint2 key, uint sample_index, uint stream, uint x, uint y,
                                   uint index)
{
    const uint4 bits = gb_pixel_bits(key, sample_index, stream, x, y, index >> 2);
    const uint j = index & 3u;
    const uint w1 = j < 2u ? bits.x : bits.z;
    const uint w2 = j < 2u ? bits.y : bits.w;
    real z_cos, z_sin;
    gb_box_muller(gb_uniform(w1), gb_uniform(w2), &z_cos, &z_sin);
    return (j & 1u) ? z_sin : z_cos;
}

/* log(k!) for k = 0..15, the float64 values of poisson_counts.LOG_FACTORIAL_TABLE
 * (gb_constants.h). */
__constant gb_wide gb_log_factorial_table[GB_LOG_FACTORIAL_TABLE_SIZE] = GB_LOG_FACTORIAL_TABLE;

/* log(k!) for integer-valued k >= 0 (poisson_counts.log_factorial): the table below 16 (its
 * size), else Stirling:
 *   r = 1/k;  s = r (1/12 - r^2 (1/360 - r^2 (1/1260 - r^2 / 1680)))
 *   log k! = (k + 0.5) log k - k + 0.5 log(2 pi) + s */
static inline gb_wide gb_log_factorial(gb_wide k)
{
#pragma OPENCL FP_CONTRACT OFF
    if (k < (gb_wide)GB_LOG_FACTORIAL_TABLE_SIZE) return gb_log_factorial_table[(int)k];
    const gb_wide r = GB_WIDE(1.0) / k;
    const gb_wide r2 = r * r;
    const gb_wide series =
        r * (GB_WIDE(1.0) / GB_WIDE(12.0) -
             r2 * (GB_WIDE(1.0) / GB_WIDE(360.0) -
                   r2 * (GB_WIDE(1.0) / GB_WIDE(1260.0) - r2 / GB_WIDE(1680.0))));
    return (k + GB_WIDE(0.5)) * log(k) - k + GB_HALF_LOG_TWO_PI + series;
}

/* One Poisson count at pixel (x, y) of stream SHOT_NOISE (poisson_counts.poisson), as a real.
 * The rate is clamped at 0 (negative rates give 0). The reference refuses non-finite rates; here
 * NaN gives NaN and +inf gives +inf, so that the PTRS loop never runs on them. In a float build
 * counts above 2^24 round to the nearest float. */
static inline real gb_poisson(real rate_in, uint2 key, uint sample_index, uint x, uint y)
{
#pragma OPENCL FP_CONTRACT OFF
    const gb_wide rate_raw = (gb_wide)rate_in;
    if (isnan(rate_raw)) return rate_in;
    const gb_wide rate = rate_raw > GB_WIDE(0.0) ? rate_raw : GB_WIDE(0.0);
    if (isinf(rate)) return (real)INFINITY;

    if (rate < GB_POISSON_PTRS_MIN_RATE) {
        /* Inversion by sequential search on word 0 of round 0. */
        const uint4 bits = gb_pixel_bits(key, sample_index, GB_STREAM_SHOT_NOISE, x, y, 0u);
        const gb_wide u = (gb_wide)gb_uniform(bits.x);
        gb_wide k = GB_WIDE(0.0);
        gb_wide p = exp(-rate);
        gb_wide cdf = p;
        int step = 0;
        while (u > cdf && step < GB_POISSON_INVERSION_MAX_K) {
            step += 1;
            k = (gb_wide)step;
            p = p * (rate / k);
            cdf = cdf + p;
        }
        return (real)k;
    }

    /* PTRS (Hoermann 1993), mu = rate. */
    const gb_wide mu = rate;
    const gb_wide log_mu = log(mu);
    const gb_wide b = GB_PTRS_B0 + GB_PTRS_B1 * sqrt(mu);
    const gb_wide a = GB_PTRS_A0 + GB_PTRS_A1 * b;
    const gb_wide inv_alpha = GB_PTRS_IA0 + GB_PTRS_IA1 / (b - GB_PTRS_IA2);
    const gb_wide v_r = GB_PTRS_VR0 - GB_PTRS_VR1 / (b - GB_WIDE(2.0));
    for (uint round = 0u; round < GB_ROUND_LIMIT; ++round) {
        const uint4 bits = gb_pixel_bits(key, sample_index, GB_STREAM_SHOT_NOISE, x, y, round);
        for (int attempt = 0; attempt < 2; ++attempt) {
            const uint word_u = attempt == 0 ? bits.x : bits.z;
            const uint word_v = attempt == 0 ? bits.y : bits.w;
            const gb_wide big_u = (gb_wide)gb_uniform(word_u) - GB_WIDE(0.5);
            const gb_wide v = (gb_wide)gb_uniform(word_v);
            const gb_wide us = GB_WIDE(0.5) - fabs(big_u);
            /* k stays floating: a rejected candidate can lie far outside the int range. */
            const gb_wide k =
                floor((GB_WIDE(2.0) * a / us + b) * big_u + mu + GB_PTRS_K_SHIFT);
            if (us >= GB_PTRS_US_SQUEEZE && v <= v_r) return (real)k;
            if (k < GB_WIDE(0.0) || (us < GB_PTRS_US_TAIL && v > us)) continue;
            const gb_wide lhs = log(v * inv_alpha / (a / (us * us) + b));
            const gb_wide rhs = -mu + k * log_mu - gb_log_factorial(k);
            if (lhs <= rhs) return (real)k;
        }
    }
    return (real)NAN; /* unreachable: each attempt accepts with probability > 0.9 */
}

/* A Poisson count by the normal approximation (poisson_counts.poisson_normal_approximation)
 * for a finite rate >= 0, in gb_wide: z the cos normal of Box-Muller on words 0 and 1 of round 0
 * of stream SHOT_NOISE (the words PTRS's first attempt reads), then
 *   count = max(0, floor(rate + sqrt(rate) z + 0.5))      (rounded half up, clamped at 0)
 * with every operation rounded once, as the reference. Never fast maths: see gb_math.h. */
static inline gb_wide gb_poisson_normal_count(gb_wide rate, uint2 key, uint sample_index, uint x,
                                              uint y)
{
#pragma OPENCL FP_CONTRACT OFF
    const uint4 bits = gb_pixel_bits(key, sample_index, GB_STREAM_SHOT_NOISE, x, y, 0u);
    gb_wide z, z_sin;
    gb_box_muller_wide((gb_wide)gb_uniform(bits.x), (gb_wide)gb_uniform(bits.y), &z, &z_sin);
    const gb_wide count = floor(rate + sqrt(rate) * z + GB_WIDE(0.5));
    return count > GB_WIDE(0.0) ? count : GB_WIDE(0.0);
}

/* poisson_counts.poisson with normal_above: rates strictly above `normal_above` (>= 0, the
 * host checks it) take gb_poisson_normal_count, all others gb_poisson, so counts at or below the
 * threshold are gb_poisson's bit for bit. NaN and +inf go to gb_poisson (NaN and +inf out). The
 * threshold is a `real`, rounded as the rate is. */
static inline real gb_poisson_normal_above(real rate_in, real normal_above, uint2 key,
                                           uint sample_index, uint x, uint y)
{
    const gb_wide rate = (gb_wide)rate_in;
    if (rate > (gb_wide)normal_above && !isinf(rate))
        return (real)gb_poisson_normal_count(rate, key, sample_index, x, y);
    return gb_poisson(rate_in, key, sample_index, x, y);
}

#endif
