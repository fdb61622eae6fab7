"""Warp against OpenCL directly: the same draws bit for bit, the same outputs within the table."""

import numpy as np
import pytest
from conftest import BACKEND_SPECS, make_backend, spec_dtype

import gpu_blur
from gpu_blur.reference.rng import Stream, key_from_seed
from gpu_blur.scene import scene_from_dict
from gpu_blur.testing import assert_close

OPENCL = [s for s in BACKEND_SPECS if s.startswith("opencl")]
WARP = [s for s in BACKEND_SPECS if s.startswith("warp")]
pytestmark = pytest.mark.skipif(not (OPENCL and WARP), reason="needs an OpenCL and a Warp device")

UNIFORM_SOURCE = """
#include "gb_random.h"
__kernel void uniforms(uint key0, uint key1, uint sample_index, uint stream, uint width,
                       __global double *out)
{
    uint i = get_global_id(0);
    uint4 bits = gb_pixel_bits((uint2)(key0, key1), sample_index, stream, i % width, i / width,
                               0u);
    out[4 * i] = gb_uniform(bits.x);
    out[4 * i + 1] = gb_uniform(bits.y);
    out[4 * i + 2] = gb_uniform(bits.z);
    out[4 * i + 3] = gb_uniform(bits.w);
}
"""


def test_warp_and_opencl_draw_bit_identical_uniforms():
    import warp as wp
    from warp_cross_kernels import pixel_uniforms

    backend = make_backend(OPENCL[0].split("/")[0] + "/float64")
    cl = __import__("pyopencl")
    width, height = 97, 61
    n = width * height
    key = key_from_seed(2**40 + 17)
    args = (np.uint32(key[0]), np.uint32(key[1]), np.uint32(2**32 - 5),
            np.uint32(int(Stream.SHOT_NOISE)), np.uint32(width))
    program = backend.program_from_source(UNIFORM_SOURCE)
    out = cl.Buffer(backend.ctx, cl.mem_flags.WRITE_ONLY, 4 * n * 8)
    program.uniforms(backend.queue, (n,), None, *args, out)
    from_opencl = np.empty(4 * n)
    cl.enqueue_copy(backend.queue, from_opencl, out)

    device = make_backend(WARP[0]).wp_device
    result = wp.zeros(4 * n, dtype=wp.float64, device=device)
    wp.launch(pixel_uniforms, dim=n, device=device,
              inputs=[*(wp.uint32(int(a)) for a in args[:4]), width, result])
    assert np.array_equal(result.numpy(), from_opencl)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_warp_and_opencl_pipelines_agree_within_the_table(precision, coffee_rgb):
    scene = scene_from_dict({"blur": {"mode": "trajectory"}, "noise": {"model": "none"},
                             "isp": {"round_trip": "always"}, "saturation": {"mode": "on"},
                             "output": {"bits": 0, "precision": precision}})
    photo = coffee_rgb[150:310, 250:450]
    opencl = [s for s in OPENCL if spec_dtype(s) == precision]
    warp = [s for s in WARP if spec_dtype(s) == precision]
    if not (opencl and warp):
        pytest.skip(f"no {precision} build on both backends")
    a = gpu_blur.synthesize([photo], scene, seed=3, sample_index=9,
                            backend=opencl[0].split("/")[0]).blurred
    b = gpu_blur.synthesize([photo], scene, seed=3, sample_index=9,
                            backend=warp[0].split("/")[0]).blurred
    assert_close(a, b, "cross_backend", "kernels", precision)
