"""Warp test kernels for tests/test_cross_backend.py (Warp reads kernel source from files)."""

import warp as wp

from gpu_blur.warp_kernels import random


@wp.kernel
def pixel_uniforms(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                   stream: wp.uint32, width: int, out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    bits = random.pixel_bits(key0, key1, sample_index, stream, wp.uint32(i % width),
                             wp.uint32(i // width), wp.uint32(0))
    for w in range(4):
        out[4 * i + w] = random.uniform(bits[w])
