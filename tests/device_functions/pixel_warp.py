"""Warp probes of the per-pixel device functions (gpu_blur/warp_kernels/pixel.py): the twins of
pixel.cl, same names and arguments. Generic over the real type, with the float32 and float64
instances declared before the first build (launching a new instance later rebuilds the module).
"""

from typing import Any

import warp as wp

from gpu_blur.warp_kernels import pixel as px

wp.set_module_options({"enable_backward": False})


@wp.kernel
def t_reflect101(i: wp.array(dtype=int), n: int, out: wp.array(dtype=int)):
    k = wp.tid()
    out[k] = px.reflect101(i[k], n)


@wp.kernel
def t_cfa_channel(gx: wp.array(dtype=int), gy: wp.array(dtype=int), cfa: int,
                  out: wp.array(dtype=int)):
    k = wp.tid()
    out[k] = px.cfa_channel(cfa, gx[k], gy[k])


@wp.kernel
def t_srgb_to_linear(x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.srgb_to_linear(x[i])


@wp.kernel
def t_linear_to_srgb(x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.linear_to_srgb(x[i])


@wp.kernel
def t_decode_knee(x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.srgb_decode_knee(x[i])


@wp.kernel
def t_polynomial_crf(x: wp.array(dtype=Any), c: wp.array(dtype=Any), n: int,
                     y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.polynomial_crf(x[i], c, n)


@wp.kernel
def t_lookup_crf(x: wp.array(dtype=Any), rendered: wp.array(dtype=Any), n: int,
                 y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = px.lookup_crf(x[i], rendered, n)


@wp.kernel
def t_apply_matrix(x: wp.array(dtype=Any), m: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    v = px.apply_matrix(m, wp.vector(x[3 * i], x[3 * i + 1], x[3 * i + 2]))
    y[3 * i] = v[0]
    y[3 * i + 1] = v[1]
    y[3 * i + 2] = v[2]


@wp.kernel
def t_quantize(x: wp.array(dtype=Any), bits: int, code: wp.array(dtype=int),
               q: wp.array(dtype=Any)):
    i = wp.tid()
    code[i] = px.quantize_code(x[i], bits)
    q[i] = px.quantize(x[i], bits)


@wp.kernel
def t_demosaic(raw: wp.array(dtype=Any), x0: int, y0: int, w: int, full_w: int, full_h: int,
               ox: int, oy: int, ow: int, cfa: int, zero_border: int, method: int,
               out: wp.array(dtype=Any)):
    k = wp.tid()
    i, j = k % ow, k // ow
    if method == 0:
        rgb = px.demosaic_malvar2004(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa,
                                     zero_border)
        for c in range(3):
            out[3 * k + c] = rgb[c]
    else:
        rgb = px.demosaic_bilinear(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa,
                                   zero_border)
        for c in range(3):
            out[3 * k + c] = rgb[c]


for _real in (wp.float32, wp.float64):
    _arr = wp.array(dtype=_real)
    for _kernel in (t_srgb_to_linear, t_linear_to_srgb, t_decode_knee):
        wp.overload(_kernel, [_arr, _arr])
    for _kernel in (t_polynomial_crf, t_lookup_crf):
        wp.overload(_kernel, [_arr, _arr, int, _arr])
    wp.overload(t_apply_matrix, [_arr, _arr, _arr])
    wp.overload(t_quantize, [_arr, int, wp.array(dtype=int), _arr])
    wp.overload(t_demosaic, [_arr] + [int] * 11 + [_arr])

KERNELS = {k.func.__name__: k for k in (t_reflect101, t_cfa_channel, t_srgb_to_linear,
                                        t_linear_to_srgb, t_decode_knee, t_polynomial_crf,
                                        t_lookup_crf, t_apply_matrix, t_quantize, t_demosaic)}


def kernels(build: str) -> dict:
    """The probes by name: one generic set for both builds."""
    return KERNELS
