"""Kernels over an input image as stored on the device, the Warp port of kernels/opencl/inputs.cl.

No value of the image is read on the host (gpu_blur.backends.kernel.KernelBackend.inspect and
render_sharp):

* :func:`inspect_kernel`: counts for the input checks and auto saturation's clip test;
* :func:`unit_values_kernel`: stored values as reals in [0, 1] (blur mode none's mask);
* :func:`render_sharp_kernel`: the sharp reference, toned like the output by the finish
  kernel's functions (gpu_blur.warp_kernels.pixel);
* :func:`gather_codes_kernel`: the same for 8/16-bit codes, from a table that
  ``render_sharp`` made of every code;
* :func:`to_codes_kernel`: output values as the set's 8/16-bit codes, for the host to fetch.

``source`` is how the image is stored: ``wp.uint8`` or ``wp.uint16`` codes, or values of the
compute type (:func:`gpu_blur.warp_kernels.passes.source_value_func`).
"""

import functools

import warp as wp

from gpu_blur.kernel_constants import INSPECT_LOADS
from gpu_blur.warp_kernels import pixel
from gpu_blur.warp_kernels.passes import (
    LEAN,
    SOURCE_TOP,
    _fast,
    code_at,
    retone_quantize_func,
    source_value_func,
)

__all__ = ["count_add", "counts6", "gather_codes_kernel", "inspect_kernel", "render_sharp_kernel",
           "to_codes_kernel", "unit_values_codes_kernel", "unit_values_kernel"]


@wp.func
def count_add(counts: wp.array(dtype=wp.uint32), i: int, add: wp.uint32):
    """counts[i] += add for a count held as two words, counts[i] low and counts[i + 1] high.

    32-bit atomics only, as gb_count_add: the addition that wraps the low word carries.
    """
    if add != wp.uint32(0):
        old = wp.atomic_add(counts, i, add)
        if old + add < old:
            wp.atomic_add(counts, i + 1, wp.uint32(1))


#: Six uint32 counts, in the column order of gb_inspect.
counts6 = wp.types.vector(length=6, dtype=wp.uint32)

@functools.cache
def inspect_kernel(source):
    """Counts over the ``n`` values of each image into a row of ``counts``, as gb_inspect.

    Image b (the launch's first axis) starts ``stride`` values after image b - 1 and counts
    into row ``row + b``.

    Six columns (NaN, infinite, below 0, above 1, at the clip level, above 0), each a 64-bit
    count as two words (:func:`count_add`); thread i of ``items`` counts values i, i + items,
    ... in registers, INSPECT_LOADS (4, as the body writes them out) loaded at a time, and
    adds each non-zero count once. The
    clip level is 1.0 for float values and the top code for 8/16-bit codes, which are never
    NaN, infinite, negative or above 1.
    """
    top = int(SOURCE_TOP.get(source, 0))  # 0: float values
    if INSPECT_LOADS != 4:
        raise NotImplementedError("inspect's body loads 4 values a round; INSPECT_LOADS changed")

    @wp.func
    def tally(v: source, c: counts6) -> counts6:
        one = wp.uint32(1)
        if wp.static(top > 0):
            if v == source(top):
                c[4] += one
            if v > source(0):
                c[5] += one
        else:
            if wp.isnan(v):
                c[0] += one
            if wp.isinf(v):
                c[1] += one
            if v < source(0.0):
                c[2] += one
            if v > source(1.0):
                c[3] += one
            if v >= source(1.0):
                c[4] += one
            if v > source(0.0):
                c[5] += one
        return c

    @wp.kernel(module="unique")
    def inspect(image: wp.array(dtype=source), n: int, items: int,
                counts: wp.array(dtype=wp.uint32), row: int, stride: int):
        b, t = wp.tid()
        base = b * stride
        c = counts6()
        for i in range(t, n, INSPECT_LOADS * items):
            # every load issued before any count (the pass is bound by loads in flight)
            v1 = source(0)
            v2 = source(0)
            v3 = source(0)
            v0 = image[base + i]
            if i + items < n:
                v1 = image[base + i + items]
            if i + 2 * items < n:
                v2 = image[base + i + 2 * items]
            if i + 3 * items < n:
                v3 = image[base + i + 3 * items]
            c = tally(v0, c)
            if i + items < n:
                c = tally(v1, c)
            if i + 2 * items < n:
                c = tally(v2, c)
            if i + 3 * items < n:
                c = tally(v3, c)
        for k in range(6):
            count_add(counts, 12 * (row + b) + 2 * k, c[k])

    return inspect


@functools.cache
def unit_values_kernel(real, source):
    """Stored values as reals in [0, 1], as gb_unit_values: a mask given in its stored dtype.

    Codes are divided by 2^bits - 1 as ``linearize`` divides them.
    """
    source_value = source_value_func(real, source)

    @wp.kernel(module="unique")
    def unit_values(stored: wp.array(dtype=source), values: wp.array(dtype=real)):
        i = wp.tid()
        values[i] = source_value(stored[i])

    return unit_values


@functools.cache
def unit_values_codes_kernel(real):
    """:func:`unit_values_kernel` for 8-bit codes, four a thread, as gb_unit_values_codes.

    Each thread reads one 32-bit word of the codes (passes.code_at) and writes one 4-vector.
    """
    source_value = source_value_func(real, wp.uint8)
    vec4 = wp.types.vector(length=4, dtype=real)

    @wp.func
    def value_at(word: wp.uint32, j: int) -> real:
        return source_value(wp.uint8(code_at(word, j)))

    @wp.kernel(module="unique", **LEAN)
    def unit_values_codes(words: wp.array(dtype=wp.uint32), values: wp.array(dtype=vec4)):
        q = wp.tid()
        word = words[q]
        values[q] = vec4(value_at(word, 0), value_at(word, 1), value_at(word, 2),
                         value_at(word, 3))

    return unit_values_codes


@functools.cache
def to_codes_kernel(real, code):
    """Values as their ``code`` (``wp.uint8`` or ``wp.uint16``) output codes, as gb_to_codes.

    pixel.quantize_code: the code gpu_blur.reference.output.to_integers gives every value.
    """
    bits = 8 if code == wp.uint8 else 16

    @wp.kernel(module="unique")
    def to_codes(values: wp.array(dtype=real), codes: wp.array(dtype=code)):
        i = wp.tid()
        codes[i] = code(pixel.quantize_code(values[i], bits))

    return to_codes


@functools.cache
def render_sharp_kernel(real, source, config):
    """The sharp reference over an output region, as gb_render_sharp.

    ``config`` is the finish pass's configuration (gpu_blur.backends.kernel.PassConfig) cut to
    the stages that act on the sharp image: each stored sRGB value p (a code divided as
    ``linearize`` does) becomes clip(EOTF(p), 0, 1) without the tone stage (output.crf = none),
    the finish kernel's re-toning of it with the retone stage (``config.retone``: "polynomial"
    or "lookup"), else p; then quantize (``config.bits`` > 0). ``fast_math`` as the finish
    kernel's.
    """
    tone = config.kept("tone")
    source_value = source_value_func(real, source)
    retone_quantize = retone_quantize_func(real, config.retone, config.bits)

    @wp.kernel(module="unique", module_options={"fast_math": _fast(real, config.fast_math)})
    def render_sharp(image: wp.array(dtype=source), iw: int, image_stride: int, ox0: int,
                     oy0: int, ow: int, crf_polynomial: wp.array(dtype=real),
                     crf_table: wp.array(dtype=real), out: wp.array(dtype=real),
                     out_stride: int):
        b, y, x = wp.tid()
        i = b * image_stride + 3 * ((oy0 + y) * iw + ox0 + x)
        o = b * out_stride + 3 * (y * ow + x)
        for c in range(3):
            p = source_value(image[i + c])
            if wp.static(not tone):
                p = pixel.clip01(pixel.srgb_to_linear(p))
            out[o + c] = retone_quantize(p, crf_polynomial, crf_table)

    return render_sharp


@functools.cache
def gather_codes_kernel(real, source):
    """``render_sharp``'s output region of an image of 8/16-bit codes, as gb_gather_codes.

    Values come from ``rendered``, ``render_sharp``'s values of the codes 0 .. 2^bits - 1 (the
    same function of the same codes, so the same bits, without a curve per value).
    """

    @wp.kernel(module="unique")
    def gather_codes(image: wp.array(dtype=source), iw: int, image_stride: int, ox0: int,
                     oy0: int, ow: int, rendered: wp.array(dtype=real), out: wp.array(dtype=real),
                     out_stride: int):
        b, y, x = wp.tid()
        i = b * image_stride + 3 * ((oy0 + y) * iw + ox0 + x)
        o = b * out_stride + 3 * (y * ow + x)
        for c in range(3):
            out[o + c] = rendered[int(image[i + c])]

    return gather_codes
