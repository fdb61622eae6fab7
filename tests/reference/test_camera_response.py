"""output.crf = "camera": synthesis re-tones with a calibrated camera's fitted response."""

import dataclasses

import numpy as np
import pytest
from conftest import BACKEND_SPECS, KERNEL_BACKEND_SPECS, make_backend, spec_backend, spec_dtype

import gpu_blur
from gpu_blur.analysis.calibrate import read_response
from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.cameras import get_camera, load_camera, preset_names
from gpu_blur.cli import main
from gpu_blur.constants import A7R3_CRF_POLYNOMIAL
from gpu_blur.params import draw_params
from gpu_blur.planning import plan
from gpu_blur.reference import transfer
from gpu_blur.reference.output import quantize
from gpu_blur.scene import scene_from_dict
from gpu_blur.testing import assert_close
from gpu_blur.tiling import Region

SEED, SAMPLE = 3, 9
#: A response unlike A7R3's: y = 1.4 x - 0.4 x^2, increasing on [0, 1] from 0 to 1.
GENTLE = np.array([0.0, 1.4, -0.4])


def camera_file(path, polynomial=None, response_text=None):
    """A camera file (identity colour) with ``[response] polynomial``, written exactly."""
    lines = ["[color]", "camera_to_linear = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
             "[white_balance]", "red = [1.8, 2.2]", "blue = 1.6"]
    if polynomial is not None:
        lines += ["[response]", "polynomial = [" + ", ".join(repr(float(c)) for c in polynomial)
                  + "]"]
    if response_text is not None:
        lines.append(response_text)
    path.write_text("\n".join(lines) + "\n")
    return path


def scene(folder, crf, camera="cam.toml", **output):
    return scene_from_dict({"camera": {"name": camera}, "blur": {"steps": 3},
                            "output": {"crf": crf, **output}}, path=folder / "scene.toml")


def same_params(a, b):
    """Whether two samples drew the same values (scalars and arrays such as homographies)."""
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def photo(coffee_rgb):
    """A 32 x 48 crop with clipped highlights (the spoon), as 8-bit codes."""
    return np.rint(coffee_rgb[250:282, 340:388] * 255).astype(np.uint8)


# -- the camera file ---------------------------------------------------------------------------

def test_load_camera_reads_the_response_polynomial_read_only(tmp_path):
    camera = load_camera(camera_file(tmp_path / "cam.toml", A7R3_CRF_POLYNOMIAL))
    assert camera.response.dtype == np.float64
    assert np.array_equal(camera.response, A7R3_CRF_POLYNOMIAL)
    assert not camera.response.flags.writeable
    assert camera.fitted_response() is camera.response
    assert load_camera(camera_file(tmp_path / "plain.toml")).response is None
    assert all(get_camera(name).response is None for name in preset_names())


@pytest.mark.parametrize("text, shown", [
    ("[response]\npolynomial = [0.5]", "response.polynomial = [0.5]"),
    ("[response]\npolynomial = [0.0, nan]", "response.polynomial = [0.0, nan]"),
    ("[response]\npolynomial = [0.0, inf, 1.0]", "response.polynomial = [0.0, inf, 1.0]"),
    ('[response]\npolynomial = ["0", "1"]', "response.polynomial = ['0', '1']"),
    ("[response]\npolynomial = [false, true]", "response.polynomial = [False, True]"),
    ("[response]\npolynomial = 1.0", "response.polynomial = 1.0"),
    ("[response]\nsource = 'no polynomial'", "response.polynomial = None"),
])
def test_load_camera_refuses_a_bad_response_naming_file_key_value_and_fix(tmp_path, text, shown):
    path = camera_file(tmp_path / "bad.toml", response_text=text)
    with pytest.raises(ValueError) as e:
        load_camera(path)
    message = str(e.value)
    assert str(path) in message and shown in message
    assert ">= 2 finite numbers" in message
    assert "rerun gpu-blur calibrate with --crf-linear and --crf-rendered" in message
    with pytest.raises(ValueError, match="response.polynomial"):
        read_response(path)


def test_a_response_that_is_not_a_table_is_refused(tmp_path):
    path = tmp_path / "flat.json"
    path.write_text('{"color": {"camera_to_linear": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, '
                    '"response": [0, 1]}')
    with pytest.raises(ValueError, match=r"flat.json: \[response\] = \[0, 1\] is invalid"):
        load_camera(path)


def test_read_response_shares_the_polynomial_with_load_camera(tmp_path):
    path = camera_file(tmp_path / "cam.toml", GENTLE,
                       response_text="inverse_linear = [0.0, 0.4, 1.0]")
    coefficients, table = read_response(path)
    assert np.array_equal(coefficients, load_camera(path).response)
    assert np.array_equal(table, [0.0, 0.4, 1.0])
    path = camera_file(tmp_path / "cam.toml", GENTLE,
                       response_text="inverse_linear = [0.0, 0.6, 0.4]")
    with pytest.raises(ValueError, match=r"response.inverse_linear = \[0.0, 0.6, 0.4\].*"
                                         "non-decreasing"):
        read_response(path)
    with pytest.raises(ValueError, match="no \\[response\\] table"):
        read_response(camera_file(tmp_path / "plain.toml"))


# -- the reference curve, the scene and the plan -------------------------------------------------

def test_retone_with_the_a7r3_coefficients_as_a_camera_is_the_a7r3_curve_bit_for_bit():
    x = np.linspace(0.0, 1.0, 4097)
    assert np.array_equal(transfer.retone(x, "camera", coefficients=A7R3_CRF_POLYNOMIAL),
                          transfer.retone(x, "a7r3"))
    assert np.array_equal(transfer.retone(x, "camera", coefficients=GENTLE),
                          np.clip(transfer.polynomial_crf(transfer.srgb_to_linear(x), GENTLE),
                                  0, 1))


@pytest.mark.parametrize("crf, coefficients, message", [
    ("camera", None, "needs the camera's fitted response"),
    ("camera", [1.0], ">= 2 finite numbers"),
    ("a7r3", GENTLE, "coefficients are for crf 'camera'"),
    ("a7r3-lut", GENTLE, "coefficients are for crf 'camera'"),
])
def test_retone_refuses_coefficients_that_do_not_fit_the_crf(crf, coefficients, message):
    with pytest.raises(ValueError, match=message):
        transfer.retone(np.zeros(3), crf, coefficients=coefficients)


def test_plan_keeps_retone_for_camera_and_names_the_cameras_fitted_response(tmp_path):
    p = plan(scene(tmp_path, "camera"))
    assert p.kept("retone") and p.retone_curve == "polynomial"
    assert "fitted response" in p["retone"].reason and "cam.toml" in p["retone"].reason
    camera = load_camera(camera_file(tmp_path / "cam.toml", GENTLE))
    assert np.array_equal(p.retone_polynomial(camera), GENTLE)
    assert plan(scene(tmp_path, "a7r3")).retone_polynomial(camera) is A7R3_CRF_POLYNOMIAL
    assert plan(scene(tmp_path, "a7r3-lut")).retone_curve == "lookup"
    assert plan(scene(tmp_path, "srgb")).retone_polynomial(camera) is None
    with pytest.raises(ValueError, match="output.crf_table_size = 256 needs output.crf = "
                                         "'a7r3-lut' \\(it is 'camera'\\)"):
        scene(tmp_path, "camera", crf_table_size=256)


# -- synthesis ----------------------------------------------------------------------------------

def test_camera_with_the_a7r3_polynomial_gives_the_a7r3_sample_bit_for_bit(tmp_path, photo):
    camera_file(tmp_path / "cam.toml", A7R3_CRF_POLYNOMIAL)
    for bits in (8, 0):
        runs = [gpu_blur.synthesize([photo], scene(tmp_path, crf, bits=bits), seed=SEED,
                                    sample_index=SAMPLE) for crf in ("camera", "a7r3")]
        assert np.array_equal(runs[0].blurred, runs[1].blurred)
        assert np.array_equal(runs[0].sharp, runs[1].sharp)
        assert same_params(runs[0].params, runs[1].params)


def test_another_fitted_response_tones_output_and_sharp_with_its_polynomial(tmp_path, photo):
    camera_file(tmp_path / "cam.toml", GENTLE)
    ours = gpu_blur.synthesize([photo], scene(tmp_path, "camera"), seed=SEED,
                               sample_index=SAMPLE)
    a7r3 = gpu_blur.synthesize([photo], scene(tmp_path, "a7r3"), seed=SEED, sample_index=SAMPLE)
    expected = quantize(transfer.polynomial_crf(transfer.srgb_to_linear(photo / 255.0), GENTLE),
                        8)
    assert np.array_equal(ours.sharp, expected.astype(np.float32))
    assert not np.array_equal(ours.sharp, a7r3.sharp)
    # the blurred image: the same draws, the other curve; y = 1.4 x - 0.4 x^2 lies below the
    # A7R3 curve (close to sRGB's) on (0.0014, 1), so the image darkens
    assert same_params(ours.params, a7r3.params)
    assert np.abs(ours.blurred - a7r3.blurred).max() > 0.05
    assert ours.blurred.mean() < a7r3.blurred.mean()


@pytest.mark.parametrize("camera", ["a7r3", "plain.toml"])
def test_camera_crf_without_a_fitted_response_fails_naming_the_camera_and_the_fix(
        tmp_path, photo, camera):
    camera_file(tmp_path / "plain.toml")
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([photo], scene(tmp_path, "camera", camera=camera))
    message = str(e.value)
    name = "plain" if camera == "plain.toml" else camera
    assert f"camera {name!r} has no fitted response" in message
    assert "gpu-blur calibrate with --crf-linear and --crf-rendered" in message
    assert "pick another output.crf (srgb, a7r3, a7r3-lut, none)" in message
    assert f"camera.name = {camera!r}" in message and "scene.toml" in message


def test_generate_refuses_camera_crf_without_a_response_before_writing(tmp_path, capsys):
    (tmp_path / "scene.toml").write_text('[output]\ncrf = "camera"\n')
    out = tmp_path / "set"
    assert main(["generate", "--output", str(out), "--scene", str(tmp_path / "scene.toml"),
                 "--limit", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "camera 'a7r3' has no fitted response" in err and "gpu-blur calibrate" in err
    assert not out.exists()


# -- kernel backends: the polynomial path with the camera's coefficients ------------------------

def finish_sample(spec, camera, crf, photo):
    """The finish pass of one sample on ``spec`` (no RAW noise, float output)."""
    settings = scene_from_dict({"saturation": {"mode": "on"}, "noise": {"model": "none"},
                                "isp": {"round_trip": "always"},
                                "output": {"bits": 0, "crf": crf}})
    h, w = photo.shape[:2]
    p = plan(settings, saturated=True)
    params = draw_params(settings, plan(settings), camera, seed=SEED, sample_index=SAMPLE,
                         image_shape=(h, w))
    linear = transfer.srgb_to_linear(photo / 255.0)
    mask = (photo >= 255).astype(np.float64)
    image, sat = NumpyBackend().to_raw(p, params, camera, linear, mask, seed=SEED,
                                       sample_index=SAMPLE)
    whole = Region.whole(h, w)
    return p, make_backend(spec).finish(p, params, camera, image, sat, whole, whole, seed=SEED,
                                        sample_index=SAMPLE)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("polynomial", ["a7r3", "gentle"])
def test_finish_pass_with_a_camera_response_matches_the_reference(spec, polynomial, photo):
    coefficients = A7R3_CRF_POLYNOMIAL if polynomial == "a7r3" else GENTLE
    camera = dataclasses.replace(get_camera("a7r3"), response=coefficients)
    _, got = finish_sample(spec, camera, "camera", photo)
    _, ref = finish_sample("numpy", camera, "camera", photo)
    assert_close(got, ref, "finish_crf_polynomial", spec_backend(spec), spec_dtype(spec))
    if polynomial == "a7r3":  # the same kernel path and coefficients as crf "a7r3"
        _, a7r3 = finish_sample(spec, camera, "a7r3", photo)
        assert np.array_equal(got, a7r3)
    else:
        _, a7r3 = finish_sample(spec, camera, "a7r3", photo)
        assert np.abs(got - a7r3).max() > 0.05


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_kernel_synthesis_with_a_camera_response_tones_sharp_on_the_host_and_passes_checks(
        spec, tmp_path, photo):
    camera_file(tmp_path / "cam.toml", GENTLE)
    backend = spec.split("/")[0]
    ref = gpu_blur.synthesize([photo], scene(tmp_path, "camera"), seed=SEED,
                              sample_index=SAMPLE)
    got = gpu_blur.synthesize([photo], scene(tmp_path, "camera", precision=spec_dtype(spec)),
                              seed=SEED, sample_index=SAMPLE, backend=backend)
    assert np.array_equal(got.sharp, ref.sharp)  # float64 on the host, as numpy
    # spot checks of every tile hold the polynomial row, with A7R3's coefficients too (their
    # float32 Horner error, up to 2.65e-5, lies far outside the plain "finish" row)
    camera_file(tmp_path / "cam.toml", A7R3_CRF_POLYNOMIAL)
    checked = gpu_blur.synthesize([photo], scene(tmp_path, "camera", bits=0,
                                                 precision=spec_dtype(spec)),
                                  seed=SEED, sample_index=SAMPLE, backend=backend,
                                  tile=(16, 24), verify=1.0)
    assert checked.tiles == 4 and checked.spot_checks == 4


#: A response whose coefficients sum to 1,999 in magnitude (an order-9 fit's size): too large
#: for float32 kernels (gpu_blur.cameras.FLOAT32_RESPONSE_MAX_ABS_SUM).
STEEP = np.array([0.0, 1000.0, -999.0])


@pytest.mark.parametrize("spec", [s for s in KERNEL_BACKEND_SPECS if s.endswith("float32")])
def test_float32_kernels_refuse_a_response_too_large_for_float32(tmp_path, photo, spec, capsys):
    camera_file(tmp_path / "cam.toml", STEEP)
    (tmp_path / "scene.toml").write_text('[camera]\nname = "cam.toml"\n[output]\ncrf = "camera"\n')
    backend = spec.split("/")[0]
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([photo], scene(tmp_path, "camera"), backend=backend)
    message = str(e.value)
    assert "sum to 1999" in message and "output.precision = 'float64'" in message
    assert "--crf-order" in message
    out = tmp_path / "set"
    assert main(["generate", "--output", str(out), "--scene", str(tmp_path / "scene.toml"),
                 "--backend", backend, "--limit", "1", "--quiet"]) == 2
    assert "sum to 1999" in capsys.readouterr().err and not out.exists()
    # float64 kernels and numpy evaluate it: no refusal
    gpu_blur.synthesize([photo], scene(tmp_path, "camera", precision="float64"), backend=backend)
    gpu_blur.synthesize([photo], scene(tmp_path, "camera"), backend="numpy")
