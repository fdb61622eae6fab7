/* Probes of the draws (gb_random.h) and of the accuracy knobs (gb_random.h, gb_pixel.h): one
 * pixel or one word per work item. The Warp twins are in random_warp.py, same names and
 * arguments; the key is two uints (rng.key_from_seed). */
#include "gb_random.h"
#include "gb_pixel.h"

__kernel void t_philox(__global const uint *counters, __global const uint *keys,
                       __global uint *out)
{
    const size_t i = get_global_id(0);
    vstore4(gb_philox(vload4(i, counters), vload2(i, keys)), i, out);
}

__kernel void t_pixel_uniforms(const uint key0, const uint key1, const uint sample_index,
                               const uint stream, const uint round, __global const uint *xs,
                               __global const uint *ys, __global uint *bits, __global real *u)
{
    const size_t i = get_global_id(0);
    const uint4 b = gb_pixel_bits((uint2)(key0, key1), sample_index, stream, xs[i], ys[i], round);
    vstore4(b, i, bits);
    u[4 * i] = gb_uniform(b.x);
    u[4 * i + 1] = gb_uniform(b.y);
    u[4 * i + 2] = gb_uniform(b.z);
    u[4 * i + 3] = gb_uniform(b.w);
}

__kernel void t_uniform(__global const uint *words, __global real *u)
{
    const size_t i = get_global_id(0);
    u[i] = gb_uniform(words[i]);
}

__kernel void t_box_muller(__global const uint *words, __global real *z)
{
    const size_t i = get_global_id(0);
    real z_cos, z_sin;
    gb_box_muller(gb_uniform(words[2 * i]), gb_uniform(words[2 * i + 1]), &z_cos, &z_sin);
    z[2 * i] = z_cos;
    z[2 * i + 1] = z_sin;
}

__kernel void t_pixel_normals(const uint key0, const uint key1, const uint sample_index,
                              const uint stream, const uint count, __global const uint *xs,
                              __global const uint *ys, __global real *z)
{
    const size_t i = get_global_id(0);
    for (uint j = 0; j < count; ++j)
        z[i * count + j] = gb_pixel_normal((uint2)(key0, key1), sample_index, stream, xs[i],
                                           ys[i], j);
}

__kernel void t_log_factorial(__global const gb_wide *k, __global gb_wide *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_log_factorial(k[i]);
}

__kernel void t_poisson(const uint key0, const uint key1, const uint sample_index,
                        __global const real *rate, __global const uint *xs,
                        __global const uint *ys, __global real *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_poisson(rate[i], (uint2)(key0, key1), sample_index, xs[i], ys[i]);
}

__kernel void t_poisson_normal_above(const uint key0, const uint key1, const uint sample_index,
                                     const real normal_above, __global const real *rate,
                                     __global const uint *xs, __global const uint *ys,
                                     __global real *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_poisson_normal_above(rate[i], normal_above, (uint2)(key0, key1), sample_index,
                                     xs[i], ys[i]);
}

__kernel void t_srgb(__global const real *x, __global real *linear, __global real *encoded)
{
    const size_t i = get_global_id(0);
    linear[i] = gb_srgb_to_linear(x[i]);
    encoded[i] = gb_linear_to_srgb(x[i]);
}
