"""Frame interpolation inside pass 1 as a Warp kernel: the port of kernels/opencl/interpolate.cl.

``blur_interpolate_add`` adds the frame at time ``t`` between two sRGB frames, linearized, to the
averaging sums, as ``gb_blur_interpolate_add``: the maths of gpu_blur.reference.interpolate
(both frames warped backwards along the scaled flows, bilinear with reflect-101 neighbours, the
forward-backward occlusion rule, blend ``(1 - t, t)``), the same operations in the same order.
Frames and flows are views of one region (first pixel ``(sx0, sy0)``, width ``sw``) holding the
output region plus the interpolation halo; the sums cover the output region; pixels are addressed
by global coordinates, so a tile gives the whole image's values. Flows are float32 (OpenCV's
type); positions, flows and the occlusion test are float64, as the reference, and the kernel is
built with ``fuse_fp=False`` so that CUDA fuses no ``a * b + c`` there and the test decides as
the reference does.

No ``from __future__ import annotations`` here: Warp reads the kernels' annotations, which name
the factory's local types.
"""

import functools

import warp as wp

from gpu_blur.kernel_constants import SATURATION_LEVEL
from gpu_blur.warp_kernels import pixel
from gpu_blur.warp_kernels.passes import add_compensated, source_value_func

__all__ = ["consistent", "interpolate_kernels", "region_factor", "sample_flow"]


@wp.func
def region_factor(factors: wp.array(dtype=wp.uint32), map0: int, side: int, cols: int, gx: int,
                  gy: int) -> wp.uint32:
    """The factor of the region holding global pixel ``(gx, gy)``: ``gb_region_factor``."""
    if side == 0:
        return factors[map0]
    return factors[map0 + (gy / side) * cols + gx / side]


@wp.func
def sample_flow(flow: wp.array(dtype=wp.float32), sx0: int, sy0: int, sw: int, full_w: int,
                full_h: int, px: wp.float64, py: wp.float64) -> wp.vec2d:
    """Bilinear sample of a flow view at ``(px, py)``, reflect-101 neighbours, in float64."""
    fx0 = wp.floor(px)
    fy0 = wp.floor(py)
    fx = px - fx0
    fy = py - fy0
    xi = int(fx0)
    yi = int(fy0)
    c0 = pixel.reflect101(xi, full_w) - sx0
    c1 = pixel.reflect101(xi + 1, full_w) - sx0
    r0 = (pixel.reflect101(yi, full_h) - sy0) * sw
    r1 = (pixel.reflect101(yi + 1, full_h) - sy0) * sw
    out = wp.vec2d()
    for c in range(2):
        a = wp.float64(flow[2 * (r0 + c0) + c])
        b = wp.float64(flow[2 * (r0 + c1) + c])
        top = a + (b - a) * fx
        a = wp.float64(flow[2 * (r1 + c0) + c])
        b = wp.float64(flow[2 * (r1 + c1) + c])
        bottom = a + (b - a) * fx
        out[c] = top + (bottom - top) * fy
    return out


@wp.func
def consistent(flow: wp.array(dtype=wp.float32), reverse: wp.array(dtype=wp.float32), sx0: int,
               sy0: int, sw: int, full_w: int, full_h: int, gx: int, gy: int,
               relative: wp.float64, absolute_px2: wp.float64) -> bool:
    """Whether ``flow`` at global ``(gx, gy)`` passes the test against ``reverse``.

    The forward-backward test of reference.interpolate.flow_consistent, in float64.
    """
    o = 2 * ((gy - sy0) * sw + (gx - sx0))
    wx = wp.float64(flow[o])
    wy = wp.float64(flow[o + 1])
    back = sample_flow(reverse, sx0, sy0, sw, full_w, full_h, wp.float64(gx) + wx,
                       wp.float64(gy) + wy)
    ex = wx + back[0]
    ey = wy + back[1]
    norms = (wx * wx + wy * wy) + (back[0] * back[0] + back[1] * back[1])
    return ex * ex + ey * ey <= relative * norms + absolute_px2


@functools.cache
def interpolate_kernels(real, source=None) -> dict:
    """The interpolated-averaging kernels for the compute type ``real``.

    ``source`` is how frames are stored on the device (passes.source_value_func; ``real``
    values in [0, 1] by default). The host adds, in time order, each original frame
    (``blur_interpolate_add_frame``) and the intermediates after it
    (``blur_interpolate_add``) to one set of compensated sums, then takes the mean
    (``blur_interpolate_finish``), as kernels/opencl/interpolate.cl.
    """
    source = real if source is None else source
    source_value = source_value_func(real, source)
    mat23 = wp.types.matrix(shape=(2, 3), dtype=real)

    @wp.func
    def frame_value(frame: wp.array(dtype=source), i: int) -> real:
        return source_value(frame[i])

    @wp.func
    def saturated_value(v: real) -> real:
        # the saturation indicator of a stored sRGB value: 1 at or above 1 (linear 1)
        if v >= real(SATURATION_LEVEL):
            return real(1.0)
        return real(0.0)

    @wp.func
    def sample_rgb(frame: wp.array(dtype=source), sx0: int, sy0: int, sw: int, full_w: int,
                   full_h: int, px: wp.float64, py: wp.float64) -> mat23:
        # as reference.sampling.bilinear_sample: a + f (b - a) along x, then along y; row 0 the
        # values, row 1 the same sample of the saturation indicator (reference step 4)
        fx0 = wp.floor(px)
        fy0 = wp.floor(py)
        fx = real(px - fx0)
        fy = real(py - fy0)
        xi = int(fx0)
        yi = int(fy0)
        c0 = pixel.reflect101(xi, full_w) - sx0
        c1 = pixel.reflect101(xi + 1, full_w) - sx0
        r0 = (pixel.reflect101(yi, full_h) - sy0) * sw
        r1 = (pixel.reflect101(yi + 1, full_h) - sy0) * sw
        out = mat23()
        for c in range(3):
            a = frame_value(frame, 3 * (r0 + c0) + c)
            b = frame_value(frame, 3 * (r0 + c1) + c)
            sa = saturated_value(a)
            sb = saturated_value(b)
            top = a + (b - a) * fx
            sat_top = sa + (sb - sa) * fx
            a = frame_value(frame, 3 * (r1 + c0) + c)
            b = frame_value(frame, 3 * (r1 + c1) + c)
            sa = saturated_value(a)
            sb = saturated_value(b)
            bottom = a + (b - a) * fx
            sat_bottom = sa + (sb - sa) * fx
            out[0, c] = top + (bottom - top) * fy
            out[1, c] = sat_top + (sat_bottom - sat_top) * fy
        return out

    @wp.kernel(module="unique", module_options={"fuse_fp": False})
    def blur_interpolate_add(frame0: wp.array(dtype=source), frame1: wp.array(dtype=source),
                             flow_fw: wp.array(dtype=wp.float32),
                             flow_bw: wp.array(dtype=wp.float32), sx0: int, sy0: int, sw: int,
                             full_w: int, full_h: int, t: wp.float64, relative: wp.float64,
                             absolute_px2: wp.float64, step: wp.uint32, factor: wp.uint32,
                             factors: wp.array(dtype=wp.uint32), map0: int, side: int,
                             cols: int, most: wp.uint32, total: wp.array(dtype=real),
                             compensation: wp.array(dtype=real),
                             saturated: wp.array(dtype=real), dx0: int, dy0: int, dw: int):
        # launched over (dh, dw); flow_fw maps frame0 to frame1, flow_bw frame1 to frame0; the
        # frame at t = step / factor joins where the pixel's region factor f makes step f /
        # factor whole, with the weight M / f (reference.interpolate, steps 6 and 7)
        y, x = wp.tid()
        gx = dx0 + x
        gy = dy0 + y
        own = region_factor(factors, map0, side, cols, gx, gy)
        if (step * own) % factor != wp.uint32(0):
            return
        weight = real(most / own)
        o = 2 * ((gy - sy0) * sw + (gx - sx0))
        fwx = wp.float64(flow_fw[o])
        fwy = wp.float64(flow_fw[o + 1])
        bwx = wp.float64(flow_bw[o])
        bwy = wp.float64(flow_bw[o + 1])
        # frame0's sample came along flow_bw, frame1's along flow_fw: each is trusted where the
        # flow that carried it passes the test against the other
        trust_a = consistent(flow_bw, flow_fw, sx0, sy0, sw, full_w, full_h, gx, gy, relative,
                             absolute_px2)
        trust_b = consistent(flow_fw, flow_bw, sx0, sy0, sw, full_w, full_h, gx, gy, relative,
                             absolute_px2)
        one = wp.float64(1.0)
        a = sample_rgb(frame0, sx0, sy0, sw, full_w, full_h, wp.float64(gx) + t * bwx,
                       wp.float64(gy) + t * bwy)
        b = sample_rgb(frame1, sx0, sy0, sw, full_w, full_h, wp.float64(gx) + (one - t) * fwx,
                       wp.float64(gy) + (one - t) * fwy)
        wa = real(one - t)
        wb = real(t)
        od = 3 * (y * dw + x)
        for c in range(3):
            v = wa * a[0, c] + wb * b[0, c]
            s = wa * a[1, c] + wb * b[1, c]
            if trust_a != trust_b:
                v = b[0, c]
                s = b[1, c]
                if trust_a:
                    v = a[0, c]
                    s = a[1, c]
            add_compensated(total, compensation, od + c, pixel.srgb_to_linear(v) * weight)
            saturated[od + c] = saturated[od + c] + s * weight

    @wp.kernel(module="unique")
    def blur_interpolate_add_frame(frame: wp.array(dtype=source), sx0: int, sy0: int, sw: int,
                                   factors: wp.array(dtype=wp.uint32), map0: int, side: int,
                                   cols: int, most: wp.uint32, total: wp.array(dtype=real),
                                   compensation: wp.array(dtype=real),
                                   saturated: wp.array(dtype=real), dx0: int, dy0: int,
                                   dw: int):
        # an original frame (a view holding the output region), as an intermediate is added,
        # weighing M / f, f the factor of the pixel's region in the gap it starts
        y, x = wp.tid()
        weight = real(most / region_factor(factors, map0, side, cols, dx0 + x, dy0 + y))
        o = 3 * ((dy0 + y - sy0) * sw + (dx0 + x - sx0))
        od = 3 * (y * dw + x)
        for c in range(3):
            lin = pixel.srgb_to_linear(frame_value(frame, o + c))
            add_compensated(total, compensation, od + c, lin * weight)
            if lin >= real(SATURATION_LEVEL):
                saturated[od + c] = saturated[od + c] + weight

    @wp.kernel(module="unique")
    def blur_interpolate_finish(total: wp.array(dtype=real), compensation: wp.array(dtype=real),
                                saturated: wp.array(dtype=real), count: int,
                                linear: wp.array(dtype=real), mask: wp.array(dtype=real)):
        i = wp.tid()
        linear[i] = (total[i] + compensation[i]) / real(count)
        mask[i] = saturated[i] / real(count)

    return {"blur_interpolate_add": blur_interpolate_add,
            "blur_interpolate_add_frame": blur_interpolate_add_frame,
            "blur_interpolate_finish": blur_interpolate_finish}
