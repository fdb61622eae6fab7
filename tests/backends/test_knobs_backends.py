"""The accuracy knobs through the passes, on every backend against the float64 reference.

``noise.poisson = "normal"`` in the to_raw pass, ``output.crf_table_size`` in the finish pass,
and ``output.fast_math`` through the whole pipeline (float32 kernel backends). The device
functions behind them are tested one by one in tests/backends/test_device_knobs.py.
"""

import numpy as np
import pytest
from conftest import BACKEND_SPECS, KERNEL_BACKEND_SPECS, make_backend, spec_backend, spec_dtype
from test_backends import REFERENCE, SAMPLE, SEED, sample

import gpu_blur
from gpu_blur.scene import scene_from_dict
from gpu_blur.testing import assert_close, mismatch, tolerance
from gpu_blur.tiling import Region

FLOAT32_KERNEL_SPECS = [s for s in KERNEL_BACKEND_SPECS if spec_dtype(s) == "float32"]


@pytest.fixture(scope="module")
def photo(coffee_rgb):
    """A 96 x 128 crop of the coffee photo around the spoon's clipped highlights."""
    return np.ascontiguousarray(coffee_rgb[220:316, 300:428])


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_to_raw_with_the_normal_approximation_agrees_with_the_reference(spec, photo):
    h, w = photo.shape[:2]
    linear = np.ascontiguousarray(photo ** 2.2)
    mask = np.zeros_like(photo)
    _, p, cam, params = sample({"noise": {"poisson": "normal", "normal_above": 300.0}}, (h, w))
    raw, _ = make_backend(spec).to_raw(p, params, cam, linear, mask, seed=SEED,
                                       sample_index=SAMPLE)
    ref, _ = REFERENCE.to_raw(p, params, cam, linear, mask, seed=SEED, sample_index=SAMPLE)
    _, allowed = tolerance("to_raw_noisy_outliers", spec_backend(spec), spec_dtype(spec))
    problem = mismatch(raw, ref, "to_raw", spec_backend(spec), spec_dtype(spec),
                       allowed_fraction=allowed)
    assert problem is None, problem
    # the knob took effect: the draws change where rates lie above 300 counts (the crop's
    # brighter 39 % of photosites), the others keep the exact sampler's
    _, exact_plan, _, _ = sample({}, (h, w))
    exact, _ = REFERENCE.to_raw(exact_plan, params, cam, linear, mask, seed=SEED,
                                sample_index=SAMPLE)
    assert 0.3 < np.mean(exact != ref) < 0.7


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("size", [256, 4096])
def test_finish_with_a_resampled_table_matches_the_reference(spec, size, photo):
    h, w = photo.shape[:2]
    settings = {"saturation": {"mode": "on"}, "noise": {"model": "none"},
                "isp": {"round_trip": "always"}, "output": {"bits": 0, "crf": "a7r3-lut"}}
    _, default_plan, cam, params = sample(settings, (h, w))
    settings["output"]["crf_table_size"] = size
    _, p, _, _ = sample(settings, (h, w))
    image, sat = REFERENCE.to_raw(p, params, cam, np.ascontiguousarray(photo ** 2.2),
                                  (photo >= 0.99).astype(np.float64), seed=SEED,
                                  sample_index=SAMPLE)
    view, out = Region.whole(h, w), Region(5, 6, h - 9, w - 13, h, w)
    got = make_backend(spec).finish(p, params, cam, image, sat, view, out, seed=SEED,
                                    sample_index=SAMPLE)
    ref = REFERENCE.finish(p, params, cam, image, sat, view, out, seed=SEED,
                           sample_index=SAMPLE)
    assert_close(got, ref, "finish", spec_backend(spec), spec_dtype(spec))
    authors = REFERENCE.finish(default_plan, params, cam, image, sat, view, out, seed=SEED,
                               sample_index=SAMPLE)
    assert_close(ref, authors, f"crf_table_{size}")
    assert not np.array_equal(ref, authors)


def fast_math_scene(noise: str, fast: bool):
    return scene_from_dict({"blur": {"mode": "trajectory"}, "saturation": {"mode": "on"},
                            "noise": {"model": noise}, "isp": {"round_trip": "always"},
                            "output": {"bits": 0, "fast_math": fast}})


@pytest.mark.parametrize("spec", FLOAT32_KERNEL_SPECS)
@pytest.mark.parametrize("noise", ["none", "gaussian"])
@pytest.mark.bits
def test_fast_math_pipeline_stays_within_its_row(spec, noise, coffee_rgb, record_property):
    photo = coffee_rgb[150:310, 250:450]
    backend = spec.split("/")[0]
    got = gpu_blur.synthesize([photo], fast_math_scene(noise, True), seed=SEED,
                              sample_index=SAMPLE, backend=backend).blurred
    ref = gpu_blur.synthesize([photo], fast_math_scene(noise, False), seed=SEED,
                              sample_index=SAMPLE).blurred
    error = float(np.abs(got.astype(np.float64) - ref).max())
    record_property(f"pipeline_fast_math_max_abs_error[{spec}, {noise}]", error)
    print(f"pipeline_fast_math_max_abs_error[{spec}, {noise}] = {error}")
    assert_close(got, ref, "pipeline_fast_math", spec_backend(spec), "float32")
    if noise == "gaussian":  # the fast normals run in float on every float32 kernel backend
        precise = gpu_blur.synthesize([photo], fast_math_scene(noise, False), seed=SEED,
                                      sample_index=SAMPLE, backend=backend).blurred
        assert not np.array_equal(got, precise)


def test_the_reference_ignores_fast_math(coffee_rgb):
    photo = coffee_rgb[150:230, 250:350]
    fast, precise = (gpu_blur.synthesize([photo], fast_math_scene("gaussian", f), seed=SEED,
                                         sample_index=SAMPLE).blurred for f in (True, False))
    assert np.array_equal(fast, precise)


OPENCL_FLOAT32 = [s for s in FLOAT32_KERNEL_SPECS if s.startswith("opencl")]


@pytest.mark.skipif(not OPENCL_FLOAT32, reason="no OpenCL device")
def test_opencl_refuses_fast_math_on_a_runtime_whose_accuracy_was_never_measured(coffee_rgb):
    import dataclasses

    from gpu_blur.backends.opencl import OpenCLBackend, OpenCLError

    backend = OpenCLBackend(OPENCL_FLOAT32[0].split("/")[0])
    backend.info = dataclasses.replace(backend.info, platform="Some Vendor's OpenCL")
    photo = coffee_rgb[150:182, 250:298]
    with pytest.raises(OpenCLError, match="output.fast_math on .*Some Vendor's OpenCL.*never "
                                          "measured.*output.fast_math = false"):
        gpu_blur.synthesize([photo], fast_math_scene("none", True), backend=backend)
    precise = gpu_blur.synthesize([photo], fast_math_scene("none", False), backend=backend)
    assert precise.blurred.shape == (32, 48, 3)  # the same device runs without fast maths
