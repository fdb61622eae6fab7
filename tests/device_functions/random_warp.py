"""Warp probes of the draws and the accuracy knobs (gpu_blur/warp_kernels/random.py, pixel.py):
the twins of random.cl, same names and arguments.

This module is built with ``fuse_fp=False`` (no a * b + c contraction), as random.py asks of
modules that must repeat the reference's Poisson counts. The samplers run in float64; the build
"float32-fast" is the fast-maths kernels, each in a module built with Warp's ``fast_math``
option (CUDA's approximate float intrinsics; Warp's CPU compiler ignores the option).
"""

import warp as wp

from gpu_blur.warp_kernels import pixel as px
from gpu_blur.warp_kernels import random as wr

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

FAST = {"fast_math": True, "enable_backward": False}


@wp.kernel
def t_philox(counters: wp.array(dtype=wp.uint32), keys: wp.array(dtype=wp.uint32),
             out: wp.array(dtype=wp.uint32)):
    i = wp.tid()
    c = wp.vec4ui(counters[4 * i], counters[4 * i + 1], counters[4 * i + 2], counters[4 * i + 3])
    b = wr.philox4x32(c, keys[2 * i], keys[2 * i + 1])
    for j in range(4):
        out[4 * i + j] = b[j]


@wp.kernel
def t_pixel_uniforms(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                     stream: wp.uint32, round: wp.uint32, xs: wp.array(dtype=wp.uint32),
                     ys: wp.array(dtype=wp.uint32), bits: wp.array(dtype=wp.uint32),
                     u: wp.array(dtype=wp.float64)):
    i = wp.tid()
    b = wr.pixel_bits(key0, key1, sample_index, stream, xs[i], ys[i], round)
    for j in range(4):
        bits[4 * i + j] = b[j]
        u[4 * i + j] = wr.uniform(b[j])


@wp.kernel
def t_uniform(words: wp.array(dtype=wp.uint32), u: wp.array(dtype=wp.float64)):
    i = wp.tid()
    u[i] = wr.uniform(words[i])


@wp.kernel
def t_box_muller(words: wp.array(dtype=wp.uint32), z: wp.array(dtype=wp.float64)):
    i = wp.tid()
    pair = wr.box_muller(wr.uniform(words[2 * i]), wr.uniform(words[2 * i + 1]))
    z[2 * i] = pair[0]
    z[2 * i + 1] = pair[1]


@wp.kernel
def t_pixel_normals(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                    stream: wp.uint32, count: wp.uint32, xs: wp.array(dtype=wp.uint32),
                    ys: wp.array(dtype=wp.uint32), z: wp.array(dtype=wp.float64)):
    i = wp.tid()
    for j in range(int(count)):
        z[i * int(count) + j] = wr.pixel_normal(key0, key1, sample_index, stream, xs[i], ys[i],
                                                wp.uint32(j))


@wp.kernel
def t_log_factorial(k: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wr.log_factorial(k[i])


@wp.kernel
def t_poisson(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
              rates: wp.array(dtype=wp.float64), xs: wp.array(dtype=wp.uint32),
              ys: wp.array(dtype=wp.uint32), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wr.poisson(rates[i], key0, key1, sample_index, xs[i], ys[i])


@wp.kernel
def t_poisson_normal_above(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                           normal_above: wp.float64, rates: wp.array(dtype=wp.float64),
                           xs: wp.array(dtype=wp.uint32), ys: wp.array(dtype=wp.uint32),
                           out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wr.poisson_normal_above(rates[i], normal_above, key0, key1, sample_index, xs[i],
                                     ys[i])


def srgb_kernel(options: dict):
    """sRGB curves of float32 values in a module built with ``options``."""

    @wp.kernel(module="unique", module_options=options)
    def t_srgb(x: wp.array(dtype=wp.float32), linear: wp.array(dtype=wp.float32),
               encoded: wp.array(dtype=wp.float32)):
        i = wp.tid()
        linear[i] = px.srgb_to_linear(x[i])
        encoded[i] = px.linear_to_srgb(x[i])

    return t_srgb


@wp.kernel(module="unique", module_options=FAST)
def t_pixel_normals_fast(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                         stream: wp.uint32, count: wp.uint32, xs: wp.array(dtype=wp.uint32),
                         ys: wp.array(dtype=wp.uint32), z: wp.array(dtype=wp.float32)):
    i = wp.tid()
    for j in range(int(count)):
        z[i * int(count) + j] = wr.pixel_normal_fast(key0, key1, sample_index, stream, xs[i],
                                                     ys[i], wp.uint32(j))


#: The sRGB curves in float32 with and without fast maths.
T_SRGB_FAST = srgb_kernel(FAST)
T_SRGB = srgb_kernel({"enable_backward": False})

BUILDS = {
    "float64": {k.func.__name__: k for k in (t_philox, t_pixel_uniforms, t_uniform, t_box_muller,
                                             t_pixel_normals, t_log_factorial, t_poisson,
                                             t_poisson_normal_above)},
    "float32-fast": {"t_srgb": T_SRGB_FAST, "t_pixel_normals": t_pixel_normals_fast},
}


def kernels(build: str) -> dict:
    """The probes of ``build`` by name."""
    return BUILDS[build]
