"""One test body per pass and stage, run on every backend against the float64 reference."""

import dataclasses

import numpy as np
import pytest
from conftest import BACKEND_SPECS, KERNEL_BACKEND_SPECS, make_backend, spec_backend, spec_dtype

import gpu_blur
from gpu_blur.backends import Backend
from gpu_blur.backends.kernel import Arg, pass_config, stage_values, to_raw_args
from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.cameras import get_camera
from gpu_blur.distributed import uses_cuda
from gpu_blur.params import draw_params
from gpu_blur.planning import Pass, plan
from gpu_blur.planning import StageName as S
from gpu_blur.reference.optics import vignette, vignetting_gain
from gpu_blur.scene import SceneError, scene_from_dict
from gpu_blur.scheduler import Footprint
from gpu_blur.testing import assert_close, mismatch, tolerance
from gpu_blur.tiling import Region

REFERENCE = NumpyBackend()
SEED, SAMPLE = 11, 7


def sample(scene_dict, shape, saturated=True, camera="a7r3", overrides=None):
    scene = scene_from_dict(scene_dict)
    p = plan(scene, saturated=saturated)
    cam = get_camera(camera)
    params = draw_params(scene, plan(scene), cam, seed=SEED, sample_index=SAMPLE,
                         image_shape=shape, overrides=overrides)
    return scene, p, cam, params


@pytest.fixture(scope="module")
def photo(coffee_rgb):
    """A 96 x 128 crop of the coffee photo around the spoon's clipped highlights."""
    return np.ascontiguousarray(coffee_rgb[220:316, 300:428])


def check(stage, spec, actual, expected):
    assert_close(actual, expected, stage, spec_backend(spec), spec_dtype(spec))


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("mode", ["average", "kernel", "trajectory", "none"])
def test_accumulate_pass_matches_the_reference(spec, mode, photo):
    h, w = photo.shape[:2]
    _, p, _, params = sample({"blur": {"mode": mode, "frames": 3}}, (h, w))
    frames = [photo, np.roll(photo, 3, axis=1), np.roll(photo, -2, axis=0)]
    frames = frames if mode == "average" else frames[:1]
    mask = np.linspace(0, 1, h * w * 3).reshape(h, w, 3) if mode == "none" else None
    region = Region.whole(h, w)
    linear, sat = make_backend(spec).accumulate(p, params, frames, mask, region)
    ref_linear, ref_sat = REFERENCE.accumulate(p, params, frames, mask, region)
    check("accumulate", spec, linear, ref_linear)
    check("accumulate", spec, sat, ref_sat)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("camera", ["a7r3", "rsblur-0005"])
@pytest.mark.parametrize("clip", [False, True])
def test_to_raw_pass_without_noise_matches_the_reference(spec, camera, clip, photo):
    h, w = photo.shape[:2]
    _, p, cam, params = sample({"noise": {"model": "none"},
                                "isp": {"round_trip": "always", "clip_camera": clip},
                                "saturation": {"mode": "on"}}, (h, w), camera=camera)
    mask = (photo >= 0.99).astype(np.float64)
    raw, sat = make_backend(spec).to_raw(p, params, cam, photo ** 2.2, mask, (3, 5),
                                         seed=SEED, sample_index=SAMPLE)
    ref_raw, ref_sat = REFERENCE.to_raw(p, params, cam, photo ** 2.2, mask, (3, 5), seed=SEED,
                                        sample_index=SAMPLE)
    check("to_raw", spec, raw, ref_raw)
    check("saturate", spec, sat, ref_sat)
    assert np.array_equal(sat >= 1.0, ref_sat >= 1.0)  # the restore decision agrees


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_to_raw_pass_noise_agrees_with_the_reference_on_almost_every_pixel(spec, photo):
    h, w = photo.shape[:2]
    _, p, cam, params = sample({}, (h, w))
    linear = np.ascontiguousarray(photo ** 2.2)
    mask = np.zeros_like(photo)
    raw, _ = make_backend(spec).to_raw(p, params, cam, linear, mask, seed=SEED,
                                       sample_index=SAMPLE)
    ref_raw, _ = REFERENCE.to_raw(p, params, cam, linear, mask, seed=SEED, sample_index=SAMPLE)
    _, allowed = tolerance("to_raw_noisy_outliers", spec_backend(spec), spec_dtype(spec))
    problem = mismatch(raw, ref_raw, "to_raw", spec_backend(spec), spec_dtype(spec),
                       allowed_fraction=allowed)
    assert problem is None, problem


# The finish pass against the reference, case by case (demosaics, borders, curves, noise,
# quantization): gpu_blur.conformance.raw_checks.FINISH_CASES, run on every backend by
# tests/cli/test_validate.py.


@pytest.fixture(scope="module")
def made():
    """Results the cases of one test share (the reference's, an untiled run's), by key."""
    return {}


def once(made, key, make):
    """``made[key]``, made by ``make()`` on first use."""
    if key not in made:
        made[key] = make()
    return made[key]


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("which", ["coffee", "rocket"])
def test_whole_pipeline_without_noise_is_within_2e_4_of_the_reference(spec, which, coffee_rgb,
                                                                        rocket_rgb, made):
    photo = {"coffee": coffee_rgb[150:310, 250:450], "rocket": rocket_rgb[100:260, 200:400]}
    scene = scene_from_dict({"blur": {"mode": "trajectory"}, "saturation": {"mode": "on"},
                             "noise": {"model": "none"}, "isp": {"round_trip": "always"},
                             "output": {"bits": 0,
                                        "precision": spec_dtype(spec)}})
    got = gpu_blur.synthesize([photo[which]], scene, seed=SEED, sample_index=SAMPLE,
                              backend=spec.split("/")[0])
    ref = once(made, ("no noise", which, spec_dtype(spec)), lambda: gpu_blur.synthesize(
        [photo[which]], scene, seed=SEED, sample_index=SAMPLE))
    check("pipeline", spec, got.blurred, ref.blurred)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_whole_pipeline_with_noise_is_within_2e_4_on_all_but_1e_5_of_pixels(spec, coffee_rgb,
                                                                            made):
    scene = scene_from_dict({"blur": {"mode": "trajectory"},
                             "output": {"bits": 0, "precision": spec_dtype(spec)}})
    photo = coffee_rgb[100:356, 200:456]
    got = gpu_blur.synthesize([photo], scene, seed=SEED, sample_index=SAMPLE,
                              backend=spec.split("/")[0]).blurred
    ref = once(made, ("noise", spec_dtype(spec)), lambda: gpu_blur.synthesize(
        [photo], scene, seed=SEED, sample_index=SAMPLE)).blurred
    rtol, atol = tolerance("pipeline_noisy", spec_backend(spec), spec_dtype(spec))
    bad = np.abs(got.astype(np.float64) - ref) > atol + rtol * np.abs(ref)
    _, allowed = tolerance("pipeline_noisy_outliers", spec_backend(spec), spec_dtype(spec))
    assert bad.mean() <= allowed, f"{bad.mean():.2e} of values outside the tolerance"


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("tile", [(17, 19), (16, 16), (33, 50)])
def test_tiled_equals_untiled(spec, tile, coffee_rgb, made):
    # the crop holds the spoon's saturated highlights, so tiles cut through them
    photo = coffee_rgb[230:310, 320:420]
    scene = scene_from_dict({"blur": {"mode": "trajectory"},
                             "output": {"bits": 0, "precision": spec_dtype(spec)}})
    backend = spec.split("/")[0]
    whole = once(made, ("untiled", spec), lambda: gpu_blur.synthesize(
        [photo], scene, seed=SEED, sample_index=SAMPLE, backend=backend))
    tiled = gpu_blur.synthesize([photo], scene, seed=SEED, sample_index=SAMPLE, backend=backend,
                                tile=tile)
    assert whole.plan.kept("restore_saturated")
    # every pass computes each pixel from global coordinates: bit for bit, on every backend
    assert np.array_equal(tiled.blurred, whole.blurred)
    assert np.array_equal(tiled.mask, whole.mask)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_memory_budget_tiled_and_streamed_equals_untiled(spec, coffee_rgb):
    # blur.mode average streams the frames; the budget fits some tiles but not the image
    photo = coffee_rgb[230:310, 320:420]
    frames = [photo, np.roll(photo, 2, axis=1), np.roll(photo, -3, axis=0)]
    scene = scene_from_dict({"blur": {"mode": "average", "frames": 3},
                             "output": {"bits": 0, "precision": spec_dtype(spec)}})
    backend = spec.split("/")[0]
    whole = gpu_blur.synthesize(frames, scene, seed=SEED, sample_index=SAMPLE, backend=backend)
    footprint = Footprint.of(whole.plan, whole.params, *whole.blurred.shape[:2],
                             make_backend(spec).precision)
    budget = footprint.tile_bytes(40, 40)  # a quarter of the image or so
    assert budget < footprint.tile_bytes(*whole.blurred.shape[:2])
    tiled = gpu_blur.synthesize(frames, scene, seed=SEED, sample_index=SAMPLE, backend=backend,
                                max_device_memory=budget)
    assert whole.tiles == 1 and tiled.tiles >= 4
    assert np.array_equal(tiled.blurred, whole.blurred)
    assert np.array_equal(tiled.mask, whole.mask)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("level", [0.0, 0.01, 0.2, 0.6])
def test_device_noise_has_the_model_mean_and_variance(spec, level):
    h = w = 256
    _, p, cam, params = sample({"saturation": {"mode": "off"}}, (h, w), camera="srgb",
                               saturated=False, overrides={"shot_noise_k": 1e-4,
                                                           "read_noise_std": 9e-4})
    flat = np.full((h, w, 3), level)
    raw, _ = make_backend(spec).to_raw(p, params, cam, flat, np.zeros_like(flat), seed=SEED,
                                       sample_index=SAMPLE)
    n = raw.size
    variance = 1e-4 * level + 9e-4 ** 2
    # 5 standard errors of the sample mean and of the sample variance (normal approximation)
    assert abs(raw.mean() - level) <= 5 * np.sqrt(variance / n)
    assert abs(raw.var() - variance) <= 5 * variance * np.sqrt(2 / n)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("mode", ["average", "trajectory"])
def test_frames_sent_as_8_bit_codes_equal_frames_sent_as_floats(spec, mode, photo):
    # kernels divide codes by 255 on the device (correctly rounded), as the host's float64
    # code / 255 rounded to the compute type: the same linear image, bit for bit
    gen = np.random.default_rng(2)
    base = np.round(photo * 255).astype(int)  # the photo's 8-bit codes
    codes = [np.clip(base + gen.integers(-9, 10, photo.shape), 0, 255).astype(np.uint8)
             for _ in range(7)]
    frames = codes if mode == "average" else codes[:1]
    _, p, _, params = sample({"blur": {"mode": mode, "frames": len(frames)}}, photo.shape[:2])
    region = Region(5, 7, 60, 90, *photo.shape[:2])
    backend = make_backend(spec)
    from_codes = backend.accumulate(p, params, frames, None, region)
    from_floats = backend.accumulate(p, params, [f / 255.0 for f in frames], None, region)
    for got, expected in zip(from_codes, from_floats, strict=True):
        assert np.array_equal(got, expected)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_overlapped_and_serial_frame_copies_give_the_same_sample(spec, photo):
    # 9 frames: three stacks of up to FRAMES_PER_LAUNCH, uploaded from pinned buffers on a
    # copy queue or stream while the previous stack is summed, or with blocking copies
    from gpu_blur.backends import get_backend

    name, _, precision = spec.partition("/")
    cls = type(get_backend(name, precision))
    gen = np.random.default_rng(4)
    base = np.round(photo * 255).astype(int)  # the photo's 8-bit codes
    frames = [np.clip(base + gen.integers(-20, 21, photo.shape), 0, 255).astype(np.uint8)
              for _ in range(9)]
    scene = scene_from_dict({"blur": {"mode": "average", "frames": 9},
                             "saturation": {"mode": "on"}, "noise": {"model": "none"},
                             "isp": {"round_trip": "always"},
                             "output": {"bits": 0, "precision": precision}})
    results = [gpu_blur.synthesize(frames, scene, seed=SEED, sample_index=SAMPLE,
                                   backend=cls(name, precision, overlap=overlap))
               for overlap in (True, False)]
    assert np.array_equal(results[0].blurred, results[1].blurred)
    assert np.array_equal(results[0].mask, results[1].mask)
    reference = gpu_blur.synthesize(frames, scene, seed=SEED, sample_index=SAMPLE)
    assert_close(results[0].blurred, reference.blurred, "pipeline", spec_backend(spec),
                 spec_dtype(spec))


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_every_backend_implements_the_backend_protocol(spec):
    # the backend itself, not the tests' HostOutputs wrapper: from Python 3.12 isinstance
    # looks protocol members up statically, past a wrapper's __getattr__
    backend = make_backend(spec).backend
    assert isinstance(backend, Backend)
    assert backend.name == spec_backend(spec) and isinstance(backend.uses_cuda, bool)
    assert uses_cuda(backend) is backend.uses_cuda


def test_pass_config_carries_each_pass_its_kept_stages_and_options():
    scene = scene_from_dict({"isp": {"demosaic": "bilinear", "border": "zero"},
                             "noise": {"poisson": "normal"},
                             "output": {"crf": "a7r3-lut", "bits": 16, "crop": 4}})
    p = plan(scene, saturated=False)
    to_raw = pass_config(p, Pass.TO_RAW)
    assert to_raw.stages == (S.LINEAR_TO_CAMERA, S.MOSAIC, S.INVERSE_WHITE_BALANCE,
                             S.POISSON_GAUSSIAN_NOISE, S.WHITE_BALANCE)
    assert to_raw.poisson_normal and not to_raw.clip_camera
    finish = pass_config(p, Pass.FINISH)
    assert (finish.demosaic, finish.zero_border, finish.retone, finish.bits) == (
        "bilinear", True, "lookup", 16)
    assert S.CROP not in finish.stages  # the host crops after the passes


def test_crop_and_jpeg_are_host_stages_after_the_passes():
    p = plan(scene_from_dict({"output": {"crop": 4}}))
    assert p[S.CROP].kept and p[S.CROP].pass_ == Pass.HOST
    assert [s.name for s in p.stages[-2:]] == [S.CROP, S.JPEG]  # the JPEG of the cropped image
    assert all(s.pass_ != Pass.HOST for s in p.stages if s.name not in (S.CROP, S.JPEG))


def test_reference_to_raw_is_sensor_raw_then_noisy_raw(photo):
    h, w = photo.shape[:2]
    _, p, cam, params = sample({}, (h, w))
    linear, mask = REFERENCE.accumulate(p, params, [photo], None, Region.whole(h, w))
    image, sat = REFERENCE.to_raw(p, params, cam, linear, mask, (2, 4), seed=SEED,
                                  sample_index=SAMPLE)
    raw, sensor_sat = REFERENCE.sensor_raw(p, params, cam, linear, mask, (2, 4))
    noisy = REFERENCE.noisy_raw(p, params, raw, (2, 4), seed=SEED, sample_index=SAMPLE)
    np.testing.assert_array_equal(noisy, image)
    np.testing.assert_array_equal(sensor_sat, sat)


def test_a_stage_s_values_close_its_pass_kernel_s_arguments():
    p = plan(scene_from_dict({}))
    stages = tuple(dataclasses.replace(s, values=(0.25, 2.0)) if s.name == S.WHITE_BALANCE
                   else s for s in p.stages)
    p = dataclasses.replace(p, stages=stages)
    args = to_raw_args(p, ("reals", "words"), (0, 0), 4, 4, (("linear", 48), ("mask", 48)),
                       "matrix", (("sat", 48), ("raw", 16)), seed=SEED)
    # before WB in the plan; skipped here (strength 0), its unknown image size passed as 0
    vignetting = (Arg("real", 0.0),) * 3
    assert p[S.VIGNETTING].values == (0.0, None, None)
    assert args[-9:] == ("sat", 48, "raw", 16, *vignetting, Arg("real", 0.25), Arg("real", 2.0))
    assert stage_values(p, Pass.FINISH) == ()


# -- vignetting (scene optics.vignetting), a pointwise stage of the to_raw pass ------------
def test_gain_is_one_minus_strength_times_squared_radius_over_corner_radius():
    # a 4 x 6 image: centre (2, 3), corner radius^2 = 2^2 + 3^2 = 13; pixel centres at +1/2
    gain = vignetting_gain(0.4, 4, 6, np.arange(4)[:, None], np.arange(6)[None, :])
    assert gain[0, 0] == pytest.approx(1 - 0.4 * (2.5 ** 2 + 1.5 ** 2) / 13, abs=1e-15)
    assert gain[1, 2] == pytest.approx(1 - 0.4 * (0.5 ** 2 + 0.5 ** 2) / 13, abs=1e-15)
    assert gain[3, 5] == gain[0, 0]  # symmetric about the centre
    assert np.all(gain > 1 - 0.4) and np.all(gain <= 1)


def test_a_tile_of_the_reference_is_the_whole_images_tile():
    image = np.random.default_rng(0).random((10, 12, 3))
    whole = vignette(image, 0.7, 10, 12)
    assert np.array_equal(vignette(image[3:8, 5:11], 0.7, 10, 12, (3, 5)), whole[3:8, 5:11])


def test_plan_skips_vignetting_at_strength_zero_and_compiles_it_only_when_kept():
    off = plan(scene_from_dict({}))
    assert not off.kept(S.VIGNETTING) and off[S.VIGNETTING].reason == "optics.vignetting = 0"
    assert S.VIGNETTING not in pass_config(off, Pass.TO_RAW).stages
    on = plan(scene_from_dict({"optics": {"vignetting": 0.3}}), size=(20, 30))
    assert on.kept(S.VIGNETTING) and on[S.VIGNETTING].values == (0.3, 20.0, 30.0)
    assert S.VIGNETTING in pass_config(on, Pass.TO_RAW).stages


@pytest.mark.parametrize("value", [-0.1, 1.5, float("nan")])
def test_scene_refuses_a_strength_outside_zero_to_one(value):
    with pytest.raises(SceneError, match="optics.vignetting"):
        scene_from_dict({"optics": {"vignetting": value}})


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("raw", [False, True])
def test_to_raw_pass_with_vignetting_matches_the_reference(spec, raw, coffee_rgb):
    photo = np.ascontiguousarray(coffee_rgb[220:268, 300:364]) / 255.0
    h, w = photo.shape[:2]
    settings = {"optics": {"vignetting": 0.6}, "saturation": {"mode": "on"},
                "noise": {"model": "none"}, "isp": {"round_trip": "always" if raw else "auto"}}
    scene = scene_from_dict(settings)
    # a tile at (3, 5) of a larger image: the gain follows the whole image's centre
    p = plan(scene, saturated=True, size=(h + 9, w + 14))
    cam = get_camera("a7r3")
    params = draw_params(scene, p, cam, seed=SEED, sample_index=SAMPLE, image_shape=(h, w))
    linear, mask = photo ** 2.2, (photo >= 0.99).astype(np.float64)
    image, sat = make_backend(spec).to_raw(p, params, cam, linear, mask, (3, 5), seed=SEED,
                                           sample_index=SAMPLE)
    ref_image, ref_sat = REFERENCE.to_raw(p, params, cam, linear, mask, (3, 5), seed=SEED,
                                               sample_index=SAMPLE)
    unshaded = plan(scene_from_dict({**settings, "optics": {}}), saturated=True)
    _, plain = REFERENCE.to_raw(unshaded, params, cam, linear, mask, (3, 5), seed=SEED,
                                     sample_index=SAMPLE)
    assert not np.allclose(ref_sat, plain)  # the stage acts
    assert_close(sat, ref_sat, "saturate", spec_backend(spec), spec_dtype(spec))
    assert_close(image, ref_image, "to_raw", spec_backend(spec), spec_dtype(spec))


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_tiled_vignetting_equals_untiled_bit_for_bit(spec, coffee_rgb):
    photo = coffee_rgb[230:290, 320:400]
    scene = scene_from_dict({"blur": {"mode": "kernel"}, "optics": {"vignetting": 0.5},
                             "output": {"bits": 0, "precision": spec_dtype(spec)}})
    backend = spec.split("/")[0]
    whole = gpu_blur.synthesize([photo], scene, seed=SEED, sample_index=SAMPLE, backend=backend)
    tiled = gpu_blur.synthesize([photo], scene, seed=SEED, sample_index=SAMPLE, backend=backend,
                                tile=(17, 23))
    assert whole.plan.kept(S.VIGNETTING)
    assert np.array_equal(tiled.blurred, whole.blurred)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_a_vignetting_plan_without_the_image_size_is_refused_not_run(spec):
    backend = make_backend(spec)
    scene = scene_from_dict({"optics": {"vignetting": 0.5}, "noise": {"model": "none"},
                             "saturation": {"mode": "off"}})
    linear = np.full((4, 6, 3), 0.5)
    with pytest.raises(ValueError, match="size"):
        backend.to_raw(plan(scene), {}, get_camera("srgb"), linear, np.zeros_like(linear),
                       seed=0, sample_index=0)
