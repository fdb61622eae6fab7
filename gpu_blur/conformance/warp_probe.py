"""A Warp kernel that exposes the noise stages' random words and uniforms, for ``validate``.

Warp reads kernel source from files, so the probe lives in its own importable module (imported
only when a Warp device is validated). The OpenCL twin is ``random_checks.UNIFORM_PROBE_CL``.
"""

import warp as wp

from gpu_blur import caches
from gpu_blur.warp_kernels import random

__all__ = ["pixel_uniforms"]

caches.set_warp_cache()  # a private kernel cache (Warp is normally started by then: checked)


@wp.kernel
def pixel_uniforms(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                   stream: wp.uint32, width: int, words: wp.array(dtype=wp.uint32),
                   out: wp.array(dtype=wp.float64)):
    """The 4 Philox words of pixel ``(i // width, i % width)`` and their uniforms."""
    i = wp.tid()
    bits = random.pixel_bits(key0, key1, sample_index, stream, wp.uint32(i % width),
                             wp.uint32(i // width), wp.uint32(0))
    for w in range(4):
        words[4 * i + w] = bits[w]
        out[4 * i + w] = random.uniform(bits[w])
