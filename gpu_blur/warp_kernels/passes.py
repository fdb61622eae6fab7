"""The plan's three passes as Warp kernels, one factory per pass.

Each factory builds kernels for one compute type (``wp.float32`` or ``wp.float64``) and one
set of kept stages: the flags are Python constants captured by the kernel and tested with
``wp.static``, so a stage the plan skips is not in the generated code (Warp's counterpart of
the OpenCL ``-DGB_STAGE_<NAME>`` defines). Factories are cached, so each variant is generated
and compiled once per process (and Warp caches the binaries on disk).

Buffers are flat arrays: RGB images hold 3 values per pixel, row-major; the RAW mosaic 1.
Kernels address pixels by global coordinates, like kernels/opencl/, so a tile with its halo
gives the values of a whole-image launch. Geometry is Warp ``int`` (int32): up to 2^31 - 1
values per buffer, as Warp's array shapes (WarpBackend refuses larger buffers and names tiles);
Warp turns the indices into 64-bit byte offsets (tests/backends/test_hard_cases.py runs buffers
past 2^31 bytes). Streamed sums (frames, poses) are compensated, as in kernels/opencl/accumulate.cl.
"""


import functools
from typing import Any

import warp as wp

from gpu_blur.kernel_constants import EXACT_COUNT_SHIFT, EXACT_UNIT, SATURATION_LEVEL
from gpu_blur.warp_kernels import pixel, random

__all__ = ["LEAN", "SOURCE_TOP", "TO_RAW_REGISTERS", "accumulate_kernels", "add_compensated",
           "code_at", "finish_kernel", "retone_quantize_func", "sample_of", "source_value_func",
           "to_raw_kernel"]

# CUDA build options of the passes' kernels, each kept where it was faster on an H200
# (bench/gpu_targets.py; none changes a bit, nor the CPU build). LEAN: no grid-stride loop, a
# thread does one element and returns (to_raw and finish keep the loop); to_raw capped at 64
# registers. See docs/performance.md#warp-build-options.
LEAN = {"grid_stride": False}
TO_RAW_REGISTERS = {"cuda_max_registers": 64}


@wp.func
def code_at(word: wp.uint32, j: int) -> int:
    """Code j of a 32-bit word read from a buffer of 8-bit codes: bits 8j .. 8j + 7.

    The kernels that take four codes a thread read them this way (every Warp device is
    little-endian, so code j is byte j of the buffer).
    """
    return int((word >> wp.uint32(8 * j)) & wp.uint32(255))


@wp.func
def add_compensated(total: wp.array(dtype=Any), compensation: wp.array(dtype=Any), i: int,
                    v: Any):
    """total[i] += v, Neumaier's compensated sum, as gb_add_compensated (accumulate.cl).

    ``compensation`` collects the rounding errors of the additions; total + compensation is the
    sum of the terms within 2u |sum| + O(n u^2) sum |terms| (Higham, "Accuracy and Stability of
    Numerical Algorithms", 2nd ed., 4.3): about one rounding of the total, for any number of
    frames or poses in practice, where a plain float32 sum drifted 1.5e-5 over 1,000 equal
    frames. No products, so nothing is fused; Warp does not reassociate.
    """
    s = total[i]
    t = s + v
    if wp.abs(s) >= wp.abs(v):
        compensation[i] = compensation[i] + ((s - t) + v)
    else:
        compensation[i] = compensation[i] + ((v - t) + s)
    total[i] = t


@wp.func
def sample_of(sample_words: wp.array2d(dtype=wp.uint32), b: int):
    """Sample b of a batched launch, as gb_sample_of: (Bayer pattern, sample index, slot).

    Row b of ``sample_words`` (gpu_blur.kernel_constants.SAMPLE_WORDS).
    """
    return int(sample_words[b, 0]), sample_words[b, 1], int(sample_words[b, 2])


#: Largest code of a stored frame dtype (values are code / top); floats are values already.
SOURCE_TOP = {wp.uint8: 255.0, wp.uint16: 65535.0}


@functools.cache
def source_value_func(real, source):
    """``source_value(code) -> real``: a stored frame value as a value in [0, 1].

    ``source`` is how frames are stored on the device: ``wp.uint8`` or ``wp.uint16`` codes
    (value = code / (2^bits - 1), a correctly rounded division, equal to the host's float64
    quotient rounded to ``real`` for every code), or ``real`` values in [0, 1].
    """
    top = SOURCE_TOP.get(source, 0.0)

    @wp.func
    def source_value(code: source) -> real:
        if wp.static(top > 0.0):
            return real(code) / real(top)
        return real(code)

    return source_value


@functools.cache
def accumulate_kernels(real, source=None) -> dict:
    """Pass 1, stages "linearize" and "blur" (average, kernel, trajectory), for ``real``.

    ``source`` is how frames are stored on the device (:func:`source_value_func`; ``real``
    values in [0, 1] by default).
    """
    source = real if source is None else source
    source_value = source_value_func(real, source)
    coded8 = source == wp.uint8

    @wp.func
    def frame_linear(frames: wp.array(dtype=source), i: int, table: wp.array(dtype=real)) -> real:
        # 8-bit codes: a gather from ``table``, the linear value of each code that ``linearize``
        # computed from codes 0..255 (the same function, so the same bits, without a pow)
        if wp.static(coded8):
            return table[int(frames[i])]
        return pixel.srgb_to_linear(source_value(frames[i]))

    @wp.kernel(module="unique")
    def linearize(srgb: wp.array(dtype=source), linear: wp.array(dtype=real),
                  indicator: wp.array(dtype=real)):
        i = wp.tid()
        v = pixel.srgb_to_linear(source_value(srgb[i]))
        linear[i] = v
        indicator[i] = real(0.0)
        if v >= real(SATURATION_LEVEL):
            indicator[i] = real(1.0)

    vec2 = wp.types.vector(length=2, dtype=real)
    vec4 = wp.types.vector(length=4, dtype=real)

    @wp.kernel(module="unique", **LEAN)
    def linearize_codes(words: wp.array(dtype=wp.uint32), table: wp.array(dtype=real),
                        linear: wp.array(dtype=vec4)):
        # linearize for blur mode none, 8-bit codes, four a thread (one 32-bit word in, one
        # 4-vector out): each code's value from ``table`` (frame_linear: the same bits as
        # linearize); no clip indicator, which mode none's given mask replaces
        q = wp.tid()
        word = words[q]
        linear[q] = vec4(table[code_at(word, 0)], table[code_at(word, 1)],
                         table[code_at(word, 2)], table[code_at(word, 3)])

    @wp.kernel(module="unique", **LEAN)
    def linearize_values(values: wp.array(dtype=vec4), linear: wp.array(dtype=vec4)):
        # linearize for blur mode none, values of the compute type, four a thread (one
        # 4-vector in, one out): the same function as linearize, so the same bits; no clip
        # indicator, which mode none's given mask replaces
        q = wp.tid()
        v = values[q]
        linear[q] = vec4(pixel.srgb_to_linear(v[0]), pixel.srgb_to_linear(v[1]),
                         pixel.srgb_to_linear(v[2]), pixel.srgb_to_linear(v[3]))

    @wp.kernel(module="unique")
    def blur_average_add(frames: wp.array(dtype=source), count: int, stride: int,
                         total: wp.array(dtype=real), compensation: wp.array(dtype=real),
                         saturated: wp.array(dtype=wp.uint32), first: int, mean_of: int,
                         linear: wp.array(dtype=real), mask: wp.array(dtype=real),
                         table: wp.array(dtype=real)):
        # frames k = 0..count-1 of a device stack (frame k at k * stride) join the running
        # compensated sum in registers (Neumaier, as add_compensated); ``first`` starts from
        # zero, ``mean_of`` > 0 ends the average: linear and mask get the means over that many
        # frames instead of the running state going back to total/compensation/saturated;
        # ``table``: the linear value of each 8-bit code (frame_linear), else unread
        i = wp.tid()
        s = real(0.0)
        c = real(0.0)
        n = wp.uint32(0)
        if first == 0:
            s = total[i]
            c = compensation[i]
            n = saturated[i]
        for k in range(count):
            v = frame_linear(frames, k * stride + i, table)
            t = s + v
            if wp.abs(s) >= wp.abs(v):
                c = c + ((s - t) + v)
            else:
                c = c + ((v - t) + s)
            s = t
            if v >= real(SATURATION_LEVEL):
                n = n + wp.uint32(1)
        if mean_of > 0:
            linear[i] = (s + c) / real(mean_of)
            mask[i] = real(n) / real(mean_of)
        else:
            total[i] = s
            compensation[i] = c
            saturated[i] = n

    @wp.func
    def exact_means(total: wp.uint64, count: int) -> vec2:
        # an exact sum of ``count`` units entries (blur_average_exact): (linear, mask) means
        saturated = total >> wp.uint64(EXACT_COUNT_SHIFT)
        value = real(total - (saturated << wp.uint64(EXACT_COUNT_SHIFT))) * real(EXACT_UNIT)
        return vec2(value / real(count), real(saturated) / real(count))

    @wp.kernel(module="unique", **LEAN)
    def blur_average_exact(words: wp.array(dtype=wp.uint32), count: int, stride: int,
                           sample_stride: int, units: wp.array(dtype=wp.uint64),
                           linear: wp.array(dtype=vec4), mask: wp.array(dtype=vec4),
                           out_stride: int):
        # 8-bit frames, all in one launch, float32: blur_average_add's means, the same bits,
        # from an exact integer sum (gb_blur_average_exact in accumulate.cl says why);
        # ``units[code]``: the code's linear value in units of EXACT_UNIT, plus
        # 1 << EXACT_COUNT_SHIFT where it is saturated. Four values a thread: it reads one
        # 32-bit word of the frames' codes a frame (code_at), keeps four sums in flight and
        # writes one 4-vector of each mean. Sample b (the first axis) reads its frames
        # sample_stride words after sample b - 1's (frame k stride words after frame k - 1)
        # and writes its means out_stride 4-vectors after sample b - 1's
        b, q = wp.tid()
        first = b * sample_stride + q
        t0 = wp.uint64(0)
        t1 = wp.uint64(0)
        t2 = wp.uint64(0)
        t3 = wp.uint64(0)
        for k in range(count):
            word = words[first + k * stride]
            t0 = t0 + units[code_at(word, 0)]
            t1 = t1 + units[code_at(word, 1)]
            t2 = t2 + units[code_at(word, 2)]
            t3 = t3 + units[code_at(word, 3)]
        m0 = exact_means(t0, count)
        m1 = exact_means(t1, count)
        m2 = exact_means(t2, count)
        m3 = exact_means(t3, count)
        linear[b * out_stride + q] = vec4(m0[0], m1[0], m2[0], m3[0])
        mask[b * out_stride + q] = vec4(m0[1], m1[1], m2[1], m3[1])

    @wp.kernel(module="unique")
    def blur_kernel(src_slots: wp.array2d(dtype=real), ind_slots: wp.array2d(dtype=real),
                    sx0: int, sy0: int, sw: int, full_w: int, full_h: int,
                    taps: wp.array(dtype=real), kernel_words: wp.array2d(dtype=wp.uint32),
                    linear_slots: wp.array2d(dtype=real), mask_slots: wp.array2d(dtype=real),
                    dx0: int, dy0: int, dw: int):
        # a batch, as gb_blur_kernel: sample b convolves its slots of the linear image and its
        # saturation indicator with its kernel, row b of ``kernel_words`` (KERNEL_WORDS: first
        # tap in ``taps``, height, width, slot)
        b, y, x = wp.tid()
        first = int(kernel_words[b, 0])
        kh = int(kernel_words[b, 1])
        kw = int(kernel_words[b, 2])
        slot = int(kernel_words[b, 3])
        src = src_slots[slot]
        ind = ind_slots[slot]
        gx = dx0 + x
        gy = dy0 + y
        ry = kh // 2
        rx = kw // 2
        acc0 = real(0.0)
        acc1 = real(0.0)
        acc2 = real(0.0)
        sat0 = real(0.0)
        sat1 = real(0.0)
        sat2 = real(0.0)
        for i in range(kh):
            sy = pixel.reflect101(gy + ry - i, full_h)
            for j in range(kw):
                wt = taps[first + i * kw + j]
                sx = pixel.reflect101(gx + rx - j, full_w)
                o = 3 * ((sy - sy0) * sw + (sx - sx0))
                acc0 = acc0 + wt * src[o]
                acc1 = acc1 + wt * src[o + 1]
                acc2 = acc2 + wt * src[o + 2]
                sat0 = sat0 + wt * ind[o]
                sat1 = sat1 + wt * ind[o + 1]
                sat2 = sat2 + wt * ind[o + 2]
        o = 3 * (y * dw + x)
        linear = linear_slots[slot]
        mask = mask_slots[slot]
        linear[o] = acc0
        linear[o + 1] = acc1
        linear[o + 2] = acc2
        mask[o] = sat0
        mask[o + 1] = sat1
        mask[o + 2] = sat2

    @wp.func
    def tap(v: wp.array(dtype=real), o: int, c: int) -> real:
        # channel c of the pixel at view offset o, 0 for o < 0 (a tap outside the full image)
        if o < 0:
            return real(0.0)
        return v[3 * o + c]

    @wp.func
    def inside_share(first: int, f: real, n: int) -> real:
        # the share of taps first, first + 1 (weights 1 - f, f) inside [0, n): 1 when both are
        in0 = first >= 0 and first < n
        in1 = first >= -1 and first < n - 1
        if in0 and in1:
            return real(1.0)
        if in1:
            return f
        if in0:
            return real(1.0) - f
        return real(0.0)

    @wp.func
    def offset(inside: bool, gx: int, gy: int, sx0: int, sy0: int, sw: int) -> int:
        # a tap's pixel offset in the view, -1 outside the full image
        if inside:
            return (gy - sy0) * sw + (gx - sx0)
        return -1

    @wp.kernel(module="unique")
    def blur_trajectory_add(src: wp.array(dtype=real), ind: wp.array(dtype=real), sx0: int,
                            sy0: int, sw: int, full_w: int, full_h: int,
                            hinv: wp.array(dtype=wp.float64), total: wp.array(dtype=real),
                            total_comp: wp.array(dtype=real), total_ind: wp.array(dtype=real),
                            total_ind_comp: wp.array(dtype=real), weight: wp.array(dtype=real),
                            weight_comp: wp.array(dtype=real), dx0: int, dy0: int, dw: int):
        # bilinear sample at H^-1 (gx, gy, 1), positions in float64, of the image extended by
        # zeros, and the share of its weight on the image (reference.shake.shake_blur, "Edges")
        y, x = wp.tid()
        gx = wp.float64(dx0 + x)
        gy = wp.float64(dy0 + y)
        den = hinv[6] * gx + hinv[7] * gy + hinv[8]
        px = (hinv[0] * gx + hinv[1] * gy + hinv[2]) / den
        py = (hinv[3] * gx + hinv[4] * gy + hinv[5]) / den
        fx0 = wp.floor(px)
        fy0 = wp.floor(py)
        fx = real(px - fx0)
        fy = real(py - fy0)
        xi = int(fx0)
        yi = int(fy0)
        in_c0 = xi >= 0 and xi < full_w
        in_c1 = xi >= -1 and xi < full_w - 1
        in_r0 = yi >= 0 and yi < full_h
        in_r1 = yi >= -1 and yi < full_h - 1
        o00 = offset(in_r0 and in_c0, xi, yi, sx0, sy0, sw)
        o01 = offset(in_r0 and in_c1, xi + 1, yi, sx0, sy0, sw)
        o10 = offset(in_r1 and in_c0, xi, yi + 1, sx0, sy0, sw)
        o11 = offset(in_r1 and in_c1, xi + 1, yi + 1, sx0, sy0, sw)
        p = y * dw + x
        o = 3 * p
        for c in range(3):
            a = tap(src, o00, c)
            b = tap(src, o01, c)
            top = a + (b - a) * fx
            a = tap(src, o10, c)
            b = tap(src, o11, c)
            bottom = a + (b - a) * fx
            add_compensated(total, total_comp, o + c, top + (bottom - top) * fy)
            a = tap(ind, o00, c)
            b = tap(ind, o01, c)
            top = a + (b - a) * fx
            a = tap(ind, o10, c)
            b = tap(ind, o11, c)
            bottom = a + (b - a) * fx
            add_compensated(total_ind, total_ind_comp, o + c, top + (bottom - top) * fy)
        add_compensated(weight, weight_comp, p,
                        inside_share(xi, fx, full_w) * inside_share(yi, fy, full_h))

    @wp.kernel(module="unique")
    def blur_trajectory_finish(total: wp.array(dtype=real), total_comp: wp.array(dtype=real),
                               total_ind: wp.array(dtype=real),
                               total_ind_comp: wp.array(dtype=real),
                               weight: wp.array(dtype=real), weight_comp: wp.array(dtype=real),
                               linear: wp.array(dtype=real), mask: wp.array(dtype=real)):
        # the sums over the poses divided by the pixel's total weight; 0 where it is 0
        i = wp.tid()
        w = weight[i // 3] + weight_comp[i // 3]
        linear[i] = real(0.0)
        mask[i] = real(0.0)
        if w > real(0.0):
            linear[i] = (total[i] + total_comp[i]) / w
            mask[i] = (total_ind[i] + total_ind_comp[i]) / w

    return {
        "linearize": linearize, "linearize_codes": linearize_codes,
        "linearize_values": linearize_values,
        "blur_average_add": blur_average_add,
        "blur_average_exact": blur_average_exact, "blur_kernel": blur_kernel,
        "blur_trajectory_add": blur_trajectory_add,
        "blur_trajectory_finish": blur_trajectory_finish,
    }


def _fast(real, fast_math: bool) -> bool:
    """Whether a kernel of compute type ``real`` gets fast maths (float32 only, as gb_math.h)."""
    return bool(fast_math) and real == wp.float32


@functools.cache
def to_raw_kernel(real, config):
    """Pass 2 built for ``config`` (gpu_blur.backends.kernel.PassConfig), kept stages as flags.

    One launch over (samples, rows, columns) runs a batch of one plan, as gb_to_raw: sample b's
    drawn values are row b of ``sample_reals`` (kernel_constants.SAMPLE_REALS) and
    ``sample_words`` (SAMPLE_WORDS), and its buffers are row ``slot`` of each 2-D buffer.

    Stages: saturate, vignetting, linear_to_camera, mosaic, inverse_white_balance,
    poisson_gaussian_noise, white_balance; the last arguments are the plan's to_raw stage
    values (vignetting's strength, the whole image's height and width). ``poisson_normal``
    draws counts above the kernel's ``poisson_normal_above`` rate by the normal approximation
    (scene ``noise.poisson = "normal"``, the Warp side of -DGB_POISSON_NORMAL); ``fast_math``
    (scene ``output.fast_math``, float32 only) builds the module with Warp's fast_math option
    and draws the read noise with the float32 random.pixel_normal_fast. Poisson counts are
    never fast.
    """
    saturate, mosaic = config.kept("saturate"), config.kept("mosaic")
    vignetting_kept = config.kept("vignetting")
    clip_camera, noise = config.clip_camera, config.kept("poisson_gaussian_noise")
    poisson_normal, fast = config.poisson_normal, _fast(real, config.fast_math)

    @wp.kernel(module="unique", module_options={"fast_math": fast}, **TO_RAW_REGISTERS)
    def to_raw(linear_slots: wp.array2d(dtype=real), mask_slots: wp.array2d(dtype=real), x0: int,
               y0: int, w: int, sample_reals: wp.array2d(dtype=real),
               sample_words: wp.array2d(dtype=wp.uint32), lin_to_cam: wp.array(dtype=real),
               poisson_normal_above: real, key0: wp.uint32, key1: wp.uint32,
               saturated_slots: wp.array2d(dtype=real), raw_slots: wp.array2d(dtype=real),
               vignetting: real, full_h: real, full_w: real):
        b, y, x = wp.tid()
        alpha = sample_reals[b, 0]
        red_gain = sample_reals[b, 1]
        blue_gain = sample_reals[b, 2]
        shot_noise_k = sample_reals[b, 3]
        read_noise_std = sample_reals[b, 4]
        cfa, sample_index, slot = sample_of(sample_words, b)
        linear = linear_slots[slot]
        mask = mask_slots[slot]
        saturated = saturated_slots[slot]
        raw = raw_slots[slot]
        i = y * w + x
        v0 = linear[3 * i]
        v1 = linear[3 * i + 1]
        v2 = linear[3 * i + 2]
        if wp.static(saturate):
            v0 = wp.clamp(v0 + alpha * mask[3 * i], real(0.0), real(1.0))
            v1 = wp.clamp(v1 + alpha * mask[3 * i + 1], real(0.0), real(1.0))
            v2 = wp.clamp(v2 + alpha * mask[3 * i + 2], real(0.0), real(1.0))
        if wp.static(vignetting_kept):
            # 1 - s (r / r_corner)^2 about the image centre, as reference.optics.vignetting_gain
            cy = real(0.5) * full_h
            cx = real(0.5) * full_w
            dy = (real(y0 + y) + real(0.5)) - cy
            dx = (real(x0 + x) + real(0.5)) - cx
            shade = real(1.0) - vignetting * ((dx * dx + dy * dy) / (cx * cx + cy * cy))
            v0 = v0 * shade
            v1 = v1 * shade
            v2 = v2 * shade
        saturated[3 * i] = v0
        saturated[3 * i + 1] = v1
        saturated[3 * i + 2] = v2
        if wp.static(mosaic):
            gx = x0 + x
            gy = y0 + y
            ch = pixel.cfa_channel(cfa, gx, gy)
            # linear_to_camera, only the channel the mosaic keeps
            s = (lin_to_cam[3 * ch] * v0 + lin_to_cam[3 * ch + 1] * v1
                 + lin_to_cam[3 * ch + 2] * v2)
            if wp.static(clip_camera):
                s = wp.clamp(s, real(0.0), real(1.0))
            gain = real(1.0)
            if ch == 0:
                gain = red_gain
            if ch == 2:
                gain = blue_gain
            s = s / gain  # inverse_white_balance
            if wp.static(noise):
                rate = wp.max(s, real(0.0)) / shot_noise_k
                if wp.static(poisson_normal):
                    counts = random.poisson_normal_above(
                        wp.float64(rate), wp.float64(poisson_normal_above), key0, key1,
                        sample_index, wp.uint32(gx), wp.uint32(gy))
                else:
                    counts = random.poisson(wp.float64(rate), key0, key1, sample_index,
                                            wp.uint32(gx), wp.uint32(gy))
                if wp.static(fast):
                    z = real(random.pixel_normal_fast(
                        key0, key1, sample_index, wp.uint32(random.READ_NOISE), wp.uint32(gx),
                        wp.uint32(gy), wp.uint32(0)))
                else:
                    z = real(random.pixel_normal(
                        key0, key1, sample_index, wp.uint32(random.READ_NOISE), wp.uint32(gx),
                        wp.uint32(gy), wp.uint32(0)))
                s = shot_noise_k * real(counts) + read_noise_std * z
            raw[i] = s * gain  # white_balance

    return to_raw


@functools.cache
def retone_quantize_func(real, retone: str, bits: int):
    """``retone_quantize(p, crf_polynomial, crf_table) -> real``: the finish pass's last stages.

    As gb_retone_quantize: "retone" of an sRGB value ``p`` (the camera response of its EOTF by
    ``retone``, "polynomial" or "lookup"; "" keeps it), then "quantize" to ``bits`` (0: none).
    The finish kernel and the sharp reference (warp_kernels.inputs) end with it.
    """

    @wp.func
    def retone_quantize(p: real, crf_polynomial: wp.array(dtype=real),
                        crf_table: wp.array(dtype=real)) -> real:
        q = p
        if wp.static(retone == "polynomial"):
            q = pixel.polynomial_crf(pixel.srgb_to_linear(q), crf_polynomial,
                                     crf_polynomial.shape[0])
        if wp.static(retone == "lookup"):
            q = pixel.lookup_crf(pixel.srgb_to_linear(q), crf_table, crf_table.shape[0])
        if wp.static(bits > 0):
            q = pixel.quantize(q, bits)
        return q

    return retone_quantize


@functools.cache
def finish_kernel(real, config):
    """Pass 3 built for ``config`` (gpu_blur.backends.kernel.PassConfig), kept stages as flags.

    One launch over (samples, rows, the column pairs the output touches: two pixels a thread,
    pairs aligned to even global columns) runs a batch of one plan, as :func:`to_raw_kernel`
    (its ``gaussian_std``: column 5 of ``sample_reals``).

    Stages: demosaic ("" when there is no RAW round trip), camera_to_linear, tone,
    gaussian_noise, restore_saturated, retone (the plan's ``retone_curve``: "", "polynomial"
    with the coefficients the host passes, A7R3's or a camera's fitted response, or "lookup"
    with the table any size the host passes), quantize (bits 0: none). ``fast_math`` (float32
    only) builds the module with Warp's fast_math option and draws the sRGB noise with
    random.pixel_normal_fast.
    """
    demosaic, clip_demosaic = config.demosaic, config.clip_demosaic
    tone, gaussian_noise = config.kept("tone"), config.kept("gaussian_noise")
    restore = config.kept("restore_saturated")
    retone_quantize = retone_quantize_func(real, config.retone, config.bits)
    vec3 = wp.types.vector(length=3, dtype=real)
    border = 1 if config.zero_border else 0
    fast = _fast(real, config.fast_math)

    @wp.func
    def finish_pixel(raw: wp.array(dtype=real), saturated: wp.array(dtype=real), vx0: int,
                     vy0: int, vw: int, full_w: int, full_h: int, gx: int, gy: int,
                     out: wp.array(dtype=real), o: int, cfa: int, sample_index: wp.uint32,
                     gaussian_std: real, cam_to_lin: wp.array(dtype=real), key0: wp.uint32,
                     key1: wp.uint32, crf_polynomial: wp.array(dtype=real),
                     crf_table: wp.array(dtype=real)):
        # the pixel at global (gx, gy) into out[o], out[o + 1], out[o + 2]
        v = 3 * ((gy - vy0) * vw + (gx - vx0))
        rgb = vec3(saturated[v], saturated[v + 1], saturated[v + 2])
        if wp.static(demosaic != ""):
            if wp.static(demosaic == "bilinear"):
                cam = pixel.demosaic_bilinear(raw, vx0, vy0, vw, full_w, full_h, gx, gy, cfa,
                                              border)
            else:
                cam = pixel.demosaic_malvar2004(raw, vx0, vy0, vw, full_w, full_h, gx, gy,
                                                cfa, border)
            if wp.static(clip_demosaic):
                cam = vec3(pixel.clip01(cam[0]), pixel.clip01(cam[1]), pixel.clip01(cam[2]))
            rgb = vec3(  # camera_to_linear
                cam_to_lin[0] * cam[0] + cam_to_lin[1] * cam[1] + cam_to_lin[2] * cam[2],
                cam_to_lin[3] * cam[0] + cam_to_lin[4] * cam[1] + cam_to_lin[5] * cam[2],
                cam_to_lin[6] * cam[0] + cam_to_lin[7] * cam[1] + cam_to_lin[8] * cam[2])
        for c in range(3):
            p = rgb[c]
            if wp.static(tone):
                p = pixel.linear_to_srgb(p)
            p = pixel.clip01(p)
            if wp.static(gaussian_noise):
                if wp.static(fast):
                    z = real(random.pixel_normal_fast(
                        key0, key1, sample_index, wp.uint32(random.SRGB_NOISE), wp.uint32(gx),
                        wp.uint32(gy), wp.uint32(c)))
                else:
                    z = real(random.pixel_normal(
                        key0, key1, sample_index, wp.uint32(random.SRGB_NOISE), wp.uint32(gx),
                        wp.uint32(gy), wp.uint32(c)))
                p = pixel.clip01(p + gaussian_std * z)
            if wp.static(restore):
                if saturated[v + c] >= real(1.0):
                    p = real(1.0)
            out[o + c] = retone_quantize(p, crf_polynomial, crf_table)

    @wp.kernel(module="unique", module_options={"fast_math": fast})
    def finish(raw_slots: wp.array2d(dtype=real), saturated_slots: wp.array2d(dtype=real),
               vx0: int, vy0: int, vw: int, full_w: int, full_h: int, ox0: int, oy0: int,
               ow: int, sample_reals: wp.array2d(dtype=real),
               sample_words: wp.array2d(dtype=wp.uint32), cam_to_lin: wp.array(dtype=real),
               key0: wp.uint32, key1: wp.uint32, crf_polynomial: wp.array(dtype=real),
               crf_table: wp.array(dtype=real), out_slots: wp.array2d(dtype=real)):
        # two pixels a thread, GLOBAL columns 2 t' and 2 t' + 1 (pairs from the even column at
        # or left of ox0): at each of the two steps every thread of a row is at a site of one
        # Bayer colour, so the demosaic's branches do not diverge, and a column is always done
        # by the same step's code, in a tile as in the whole image (the compiler may contract
        # the two unrolled steps' products differently: so they give the same bits)
        b, y, t = wp.tid()
        cfa, sample_index, slot = sample_of(sample_words, b)
        for half in range(2):
            x = 2 * t + half - ox0 % 2
            if x >= 0 and x < ow:
                finish_pixel(raw_slots[slot], saturated_slots[slot], vx0, vy0, vw, full_w,
                             full_h, ox0 + x, oy0 + y, out_slots[slot], 3 * (y * ow + x), cfa,
                             sample_index, sample_reals[b, 5], cam_to_lin, key0, key1,
                             crf_polynomial, crf_table)

    return finish
