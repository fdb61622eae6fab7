/* Probes of the per-pixel device functions (gb_common.h, gb_pixel.h, gb_demosaic.h): one value
 * or one pixel per work item. The Warp twins are in pixel_warp.py, same names and arguments. */
#include "gb_common.h"
#include "gb_pixel.h"
#include "gb_demosaic.h"

__kernel void t_reflect101(__global const int *i, int n, __global int *out)
{
    size_t k = get_global_id(0);
    out[k] = (int)gb_reflect101(i[k], n);
}

__kernel void t_cfa_channel(__global const int *gx, __global const int *gy, int cfa,
                            __global int *out)
{
    size_t k = get_global_id(0);
    out[k] = gb_cfa_channel(cfa, gx[k], gy[k]);
}

__kernel void t_srgb_to_linear(__global const real *x, __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = gb_srgb_to_linear(x[i]);
}

__kernel void t_linear_to_srgb(__global const real *x, __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = gb_linear_to_srgb(x[i]);
}

/* The build's decode knee, whatever x. */
__kernel void t_decode_knee(__global const real *x, __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = GB_SRGB_DECODE_KNEE;
}

__kernel void t_polynomial_crf(__global const real *x, __constant real *c, int n, __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = gb_polynomial_crf(x[i], c, n);
}

__kernel void t_lookup_crf(__global const real *x, __global const real *rendered, int n,
                           __global real *y)
{
    size_t i = get_global_id(0);
    y[i] = gb_lookup_crf(x[i], rendered, n);
}

__kernel void t_apply_matrix(__global const real *x, __constant real *m, __global real *y)
{
    size_t i = get_global_id(0);
    real v[3] = {x[3 * i], x[3 * i + 1], x[3 * i + 2]};
    gb_apply_matrix(m, v, v); /* in place: the documented aliasing */
    y[3 * i] = v[0];
    y[3 * i + 1] = v[1];
    y[3 * i + 2] = v[2];
}

__kernel void t_quantize(__global const real *x, int bits, __global int *code, __global real *q)
{
    size_t i = get_global_id(0);
    code[i] = (int)gb_quantize_code(x[i], bits);
    q[i] = gb_quantize(x[i], bits);
}

/* Demosaic the window [ox, ox + ow) x [oy, oy + n / ow) of the full image from the view
 * (x0, y0, w) into out, the window's rows x ow x 3. */
__kernel void t_demosaic(__global const real *raw, int x0, int y0, int w, int full_w, int full_h,
                         int ox, int oy, int ow, int cfa, int zero_border, int method,
                         __global real *out)
{
    long k = get_global_id(0), i = k % ow, j = k / ow;
    real rgb[3];
    if (method == 0) {
        gb_demosaic_malvar2004(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa, zero_border,
                               rgb);
    } else {
        gb_demosaic_bilinear(raw, x0, y0, w, full_w, full_h, ox + i, oy + j, cfa, zero_border,
                             rgb);
    }
    for (int c = 0; c < 3; ++c) out[3 * k + c] = rgb[c];
}
