"""Warp against OpenCL directly: the same draws bit for bit, the same outputs within the table."""

import numpy as np
import pytest
from conftest import BACKEND_SPECS, make_backend, spec_dtype

import gpu_blur
from gpu_blur.conformance import random_checks
from gpu_blur.scene import scene_from_dict
from gpu_blur.testing import assert_close

OPENCL = [s for s in BACKEND_SPECS if s.startswith("opencl")]
WARP = [s for s in BACKEND_SPECS if s.startswith("warp")]
pytestmark = pytest.mark.skipif(not (OPENCL and WARP), reason="needs an OpenCL and a Warp device")

def test_warp_and_opencl_draw_bit_identical_uniforms():
    """The conformance probe's words and uniforms (gpu_blur.conformance.random_checks),
    device to device: seeds beyond 32 bits, the largest sample index."""
    opencl = make_backend(OPENCL[0].split("/")[0] + "/float64")
    warp = make_backend(WARP[0].split("/")[0] + "/float64")
    opencl_words, from_opencl = random_checks.device_uniforms(opencl)
    warp_words, from_warp = random_checks.device_uniforms(warp)
    assert np.array_equal(warp_words, opencl_words)
    assert np.array_equal(from_warp, from_opencl)


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
