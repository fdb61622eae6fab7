import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

import gpu_blur.file_writing
from gpu_blur.analysis import metrics
from gpu_blur.analysis.align import corner_displacement
from gpu_blur.cli import main
from gpu_blur.testing import assert_close

# gpu-blur compare --align, a 160 x 240 crop with 8-bit noise against the same scene with
# other noise and its first 3 columns cut: the homography's largest corner displacement from
# the 3 px shift, measured 0.012 to 0.059 px over 5 crops (smaller crops do worse: up to 0.6
# px at 128 x 192, and at 64 x 96 ECC's homography updates cycle without converging), and the
# PSNR over the scored pixels against that of the exact crop, measured -0.001 to +0.08 dB (the
# sub-pixel warp smooths a little noise).
COMPARE_ALIGN_CORNER_PX = 0.2
COMPARE_ALIGN_DB = 0.2
# noise_level against sqrt(sigma^2 + sigma_0^2), sigma_0 the level the photograph alone gives
# (its own noise and fine texture, 1.2 / 255 for coffee and 2.2 / 255 for rocket; independent
# variances add): over 8 noise draws on each photograph the relative error was at most 2.6 %
# for sigma 0.02, 1.0 % for 0.05 and 0.74 % for 0.1. Against sigma alone it was up to 8.8 % at
# 0.02 (the photographs' own noise), hence the quadrature.
NOISE_LEVEL_RTOL = 0.04
# noise_level of a flat grey 400 x 400 x 3 image with Gaussian noise (nothing but noise):
# the eigenvalues of pure noise spread (Marchenko-Pastur), their mean exceeds their median, so
# the rule drops the largest and runs low, less so the more patches: measured 0.02 % to 1.7 %
# low over 6 draws (1.0 % to 3.6 % at 256 x 256, 7 % to 14 % at 128 x 128).
NOISE_LEVEL_FLAT_RTOL = 0.03
# residual_kl of two independent draws of the same noise (sigma 0.02, 8-bit codes, the coffee
# photo, 720,000 samples): the histogram estimator's bias, measured 5.8e-5 to 8.1e-5 over 8
# draws; a 10 % sigma mismatch already gives 8.3e-3.
KL_SAME_SIGMA_MAX = 2e-4
# residual_kl against the closed form KL of two zero-mean Gaussians, log(s2 / s1) + s1^2 /
# (2 s2^2) - 1/2, unquantized residuals, bins of 1/255: binning can only lower a divergence
# and the add-one smoothing lowers the tails' terms, measured 0.7 % to 3.4 % below over 6
# draws for sigma pairs (0.02, 0.03), (0.02, 0.025), (0.03, 0.02).
KL_GAUSSIAN_RTOL = 0.05


def jpeg(image, quality):
    ok, data = cv2.imencode(".jpg", np.rint(image[:, :, ::-1] * 255).astype(np.uint8),
                            [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return cv2.imdecode(data, cv2.IMREAD_COLOR)[:, :, ::-1] / 255.0


DISTORTIONS = {
    "noise": lambda x: np.clip(x + np.random.default_rng(0).normal(0, 0.05, x.shape), 0, 1),
    "blur": lambda x: cv2.GaussianBlur(x, (0, 0), 2.0),
    "jpeg": lambda x: jpeg(x, 20),
    "shift": lambda x: np.roll(x, (1, -2), axis=(0, 1)),
    "darker": lambda x: 0.6 * x,
}


@pytest.fixture(params=["coffee", "rocket"])
def photo(request, coffee_rgb, rocket_rgb):
    return {"coffee": coffee_rgb, "rocket": rocket_rgb}[request.param]


@pytest.fixture(scope="module")
def photos_and_levels(coffee_rgb, rocket_rgb):
    """Each photograph with the noise level it has as it is (computed once)."""
    return {name: (image, metrics.noise_level(image))
            for name, image in (("coffee", coffee_rgb), ("rocket", rocket_rgb))}


def skimage_ssim(a, b):
    return structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False,
                                 channel_axis=-1 if a.ndim == 3 else None)


@pytest.mark.parametrize("distortion", sorted(DISTORTIONS))
def test_psnr_and_ssim_agree_with_scikit_image_on_distorted_photographs(photo, distortion):
    distorted = DISTORTIONS[distortion](photo)
    for a, b in ((photo, distorted), (photo[:, :, 1], distorted[:, :, 1])):
        assert_close(metrics.psnr(a, b), peak_signal_noise_ratio(a, b, data_range=1.0),
                     "psnr", "independent")
        assert_close(metrics.ssim(a, b), skimage_ssim(a, b), "ssim", "independent")


def test_ssim_takes_each_colour_channel_apart_and_averages_them(coffee_rgb):
    distorted = DISTORTIONS["jpeg"](coffee_rgb)
    per_channel = [metrics.ssim(coffee_rgb[:, :, c], distorted[:, :, c]) for c in range(3)]
    assert_close(metrics.ssim(coffee_rgb, distorted), np.mean(per_channel), "ssim",
                 "independent")


def test_ssim_over_a_mask_is_the_masked_mean_of_the_scikit_image_map(coffee_rgb):
    a, b = coffee_rgb[:, :, 0], DISTORTIONS["noise"](coffee_rgb)[:, :, 0]
    mask = np.zeros(a.shape, bool)
    mask[50:300, 100:420] = True
    mask[:3] = True  # within 5 px of the edge: outside the defined map, not counted
    _, full = structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, full=True)
    expected = full[50:300, 100:420].mean()
    assert_close(metrics.ssim(a, b, mask=mask), expected, "ssim", "independent")
    assert_close(metrics.psnr(a, b, mask=mask), peak_signal_noise_ratio(
        a[mask], b[mask], data_range=1.0), "psnr", "independent")


def test_identical_images_score_infinite_psnr_and_ssim_one(rocket_rgb):
    assert metrics.psnr(rocket_rgb, rocket_rgb) == math.inf
    assert metrics.ssim(rocket_rgb, rocket_rgb) == 1.0


def test_psnr_uses_the_data_range_for_8_bit_codes(coffee_rgb):
    a = np.rint(coffee_rgb * 255)
    b = np.rint(DISTORTIONS["blur"](coffee_rgb) * 255)
    assert_close(metrics.psnr(a, b, data_range=255), metrics.psnr(a / 255, b / 255), "psnr",
                 "independent")


@pytest.mark.parametrize("a, b, message", [
    (np.zeros((20, 20, 3)), np.zeros((20, 21, 3)), "a has shape (20, 20, 3) but b has shape"),
    (np.full((20, 20), 200, np.uint8), np.zeros((20, 20)), "pass data_range=255"),
    (np.full((20, 20), np.nan), np.zeros((20, 20)), "NaN or infinite"),
    (np.zeros((8, 8)), np.zeros((8, 8)), "smaller than the 11 x 11 Gaussian window"),
])
def test_metrics_refuse_bad_images_with_the_reason(a, b, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        metrics.ssim(a, b)


# -- noise level ---------------------------------------------------------------------------

@pytest.mark.parametrize("sigma", [0.02, 0.05, 0.1])
@pytest.mark.parametrize("name", ["coffee", "rocket"])
def test_noise_level_recovers_gaussian_noise_added_to_photographs(photos_and_levels, name,
                                                                  sigma):
    photo, own = photos_and_levels[name]
    noisy = photo + np.random.default_rng(7).normal(0.0, sigma, photo.shape)
    estimate = metrics.noise_level(noisy)
    assert abs(estimate / math.hypot(sigma, own) - 1) <= NOISE_LEVEL_RTOL


@pytest.mark.parametrize("sigma", [0.01, 0.03, 0.1])
def test_noise_level_of_pure_noise_is_its_sigma(sigma):
    image = 0.5 + np.random.default_rng(3).normal(0.0, sigma, (400, 400, 3))
    assert abs(metrics.noise_level(image) / sigma - 1) <= NOISE_LEVEL_FLAT_RTOL


def test_noise_level_is_in_the_units_of_the_image(rocket_rgb):
    crop = rocket_rgb[100:300, 200:500]
    noisy = crop + np.random.default_rng(1).normal(0.0, 0.03, crop.shape)
    assert_close(metrics.noise_level(255 * noisy), 255 * metrics.noise_level(noisy),
                 "noise_level_units", "numpy")


def test_noise_level_of_a_flat_image_is_zero():
    assert metrics.noise_level(np.full((40, 40), 0.25)) == 0.0


def test_noise_level_refuses_an_image_with_too_few_patches():
    with pytest.raises(ValueError, match="too few for their covariance"):
        metrics.noise_level(np.zeros((12, 12, 3)))


# -- residual KL divergence ------------------------------------------------------------------

@pytest.fixture(scope="module")
def coffee_codes(coffee_rgb):
    return np.rint(coffee_rgb * 255)


def noisy_codes(codes, sigma, seed):
    """8-bit codes of the photo plus Gaussian noise of sigma (in [0, 1] units), as [0, 1]."""
    noise = np.random.default_rng(seed).normal(0.0, 255 * sigma, codes.shape)
    return np.clip(np.rint(codes + noise), 0, 255) / 255.0


def test_residual_kl_of_identical_images_is_zero(coffee_codes):
    real = noisy_codes(coffee_codes, 0.02, 1)
    assert metrics.residual_kl(real, real, coffee_codes / 255) == 0.0


def test_residual_kl_of_the_same_noise_drawn_twice_is_near_zero(coffee_codes):
    real = noisy_codes(coffee_codes, 0.02, 1)
    assert 0 < metrics.residual_kl(real, noisy_codes(coffee_codes, 0.02, 2),
                                   coffee_codes / 255) <= KL_SAME_SIGMA_MAX


def test_residual_kl_grows_with_the_sigma_mismatch_either_way(coffee_codes):
    interp = coffee_codes / 255
    real = noisy_codes(coffee_codes, 0.02, 1)
    for factors in ([1.0, 1.1, 1.25, 1.5, 2.0, 3.0], [1.0, 0.9, 0.75, 0.5, 0.25]):
        kl = [metrics.residual_kl(real, noisy_codes(coffee_codes, 0.02 * f, 2), interp)
              for f in factors]
        assert np.all(np.diff(kl) > 0), kl


@pytest.mark.parametrize("s1, s2", [(0.02, 0.03), (0.02, 0.025), (0.03, 0.02)])
def test_residual_kl_matches_the_closed_form_for_gaussian_residuals(coffee_rgb, s1, s2):
    interp = 0.25 + 0.5 * coffee_rgb  # 12 sigma from 0 and 1: no clipping
    rng = np.random.default_rng(5)
    real = interp + rng.normal(0.0, s1, interp.shape)
    synth = interp + rng.normal(0.0, s2, interp.shape)
    exact = math.log(s2 / s1) + s1 ** 2 / (2 * s2 ** 2) - 0.5
    assert abs(metrics.residual_kl(real, synth, interp) / exact - 1) <= KL_GAUSSIAN_RTOL


def test_residual_kl_is_directed_from_real_to_synthesized(coffee_codes):
    interp = coffee_codes / 255
    narrow, wide = noisy_codes(coffee_codes, 0.02, 1), noisy_codes(coffee_codes, 0.04, 2)
    forward = metrics.residual_kl(narrow, wide, interp)
    backward = metrics.residual_kl(wide, narrow, interp)
    # Gaussians: D(N(0, 1) || N(0, 4)) = 0.318 < D(N(0, 4) || N(0, 1)) = 0.807 (ratio 2.5)
    assert backward > 2 * forward


def test_residual_kl_without_smoothing_is_infinite_on_an_empty_bin():
    interp = np.full((4, 4), 0.5)
    real = interp.copy()
    real[0, 0] = 0.6
    assert metrics.residual_kl(real, interp, interp, smoothing=0.0) == math.inf
    assert math.isfinite(metrics.residual_kl(real, interp, interp))


def test_residual_kl_refuses_a_bad_bin_count(coffee_rgb):
    with pytest.raises(ValueError, match="bins=0: must be a positive integer"):
        metrics.residual_kl(coffee_rgb, coffee_rgb, coffee_rgb, bins=0)


# -- gpu-blur compare ------------------------------------------------------------------------

def write_png(path, image):
    cv2.imwrite(str(path), np.rint(image[:, :, ::-1] * 255).astype(np.uint8))
    return str(path)


@pytest.fixture
def triple(tmp_path, coffee_codes):
    """Small real / synthesized / interpolated PNGs: a 160 x 240 crop with different noise."""
    crop = coffee_codes[100:260, 200:440]
    return {"real": write_png(tmp_path / "real.png", noisy_codes(crop, 0.01, 1)),
            "synth": write_png(tmp_path / "synth.png", noisy_codes(crop, 0.015, 2)),
            "interp": write_png(tmp_path / "interp.png", crop / 255)}


def read(path):
    return cv2.imread(path)[:, :, ::-1] / 255.0


def test_compare_prints_and_writes_the_metrics_of_the_files(tmp_path, triple, capsys):
    out = tmp_path / "scores.json"
    assert main(["compare", triple["real"], triple["synth"], "--interp", triple["interp"],
                 "--json", str(out)]) == 0
    real, synth, interp = (read(triple[k]) for k in ("real", "synth", "interp"))
    scores = json.loads(out.read_text())
    assert scores["size"] == [160, 240] and scores["alignment"] is None
    assert scores["psnr_db"] == metrics.psnr(real, synth)
    assert scores["ssim"] == metrics.ssim(real, synth)
    assert scores["noise_level"] == {"real": metrics.noise_level(real),
                                     "synth": metrics.noise_level(synth)}
    assert scores["residual_kl"] == metrics.residual_kl(real, synth, interp)
    assert scores["reference"]["kind"] == "interp"
    printed = capsys.readouterr().out
    assert f"PSNR   {scores['psnr_db']:.2f} dB" in printed
    assert f"{scores['residual_kl']:.4f} nats" in printed


def test_compare_aligns_a_cropped_synthesized_image_first(tmp_path, triple):
    real, synth = read(triple["real"]), read(triple["synth"])
    moved = write_png(tmp_path / "moved.png", synth[:, 3:])  # REAL pixel x is its x - 3
    out = tmp_path / "scores.json"
    assert main(["compare", triple["real"], moved, "--align", "--json", str(out)]) == 0
    scores = json.loads(out.read_text())
    assert scores["alignment"]["converged"]
    shift = np.array([[1, 0, -3], [0, 1, 0], [0, 0, 1]])
    assert corner_displacement(scores["alignment"]["homography"], shift,
                               real.shape) <= COMPARE_ALIGN_CORNER_PX
    assert scores["scored_fraction"] == pytest.approx(237 / 240, abs=0.01)
    assert abs(scores["psnr_db"] - metrics.psnr(real[:, 3:], synth[:, 3:])) < COMPARE_ALIGN_DB


def test_compare_refuses_images_of_different_sizes_naming_both(tmp_path, triple, capsys):
    small = write_png(tmp_path / "small.png", read(triple["synth"])[:150])
    assert main(["compare", triple["real"], small]) == 2
    err = capsys.readouterr().err
    assert "is 160 x 240 (H x W) but SYNTH" in err and "is 150 x 240" in err
    assert "crop or resize" in err and "--align" in err


def test_compare_names_a_missing_file(tmp_path, triple, capsys):
    assert main(["compare", triple["real"], str(tmp_path / "none.png")]) == 2
    err = capsys.readouterr().err
    assert "SYNTH" in err and "none.png: no such file" in err


@pytest.mark.parametrize("target", ["real", "synth", "interp", "link to real"])
def test_compare_refuses_a_json_file_that_is_one_of_its_inputs(tmp_path, triple, capsys,
                                                               target):
    path = triple.get(target)
    if target == "link to real":
        path = tmp_path / "scores.json"
        path.symlink_to(triple["real"])
    before = {k: Path(v).read_bytes() for k, v in triple.items()}
    assert main(["compare", triple["real"], triple["synth"], "--interp", triple["interp"],
                 "--json", str(path)]) == 2
    role = {"synth": "SYNTH", "interp": "--interp"}.get(target, "REAL")
    err = capsys.readouterr().err
    assert f"--json {path}: it would write {path}, which is {role} {triple[target.split()[-1]]}" \
           " (the same file)" in err and "give --json a new file name" in err
    assert {k: Path(v).read_bytes() for k, v in triple.items()} == before


def test_compare_json_is_written_whole_or_not_at_all(tmp_path, triple, monkeypatch):
    out = tmp_path / "scores.json"
    out.write_text("the scores of an earlier run\n")

    def write_half(path, data):  # a full disk: half the bytes, then the error
        with open(path, "wb") as f:
            f.write(data[:len(data) // 2])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(gpu_blur.file_writing, "write_new", write_half)
    assert main(["compare", triple["real"], triple["synth"], "--json", str(out)]) == 2
    monkeypatch.undo()
    assert out.read_text() == "the scores of an earlier run\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["interp.png", "real.png",
                                                          "scores.json", "synth.png"]


def test_compare_out_of_memory_is_an_error_message_not_a_traceback(triple, monkeypatch,
                                                                    capsys):
    def psnr(*args, **kwargs):
        raise MemoryError("Unable to allocate 9.3 GiB for an array")

    monkeypatch.setattr(metrics, "psnr", psnr)
    assert main(["compare", triple["real"], triple["synth"]]) == 2
    assert "gpu-blur: error: out of memory (Unable to allocate 9.3 GiB for an array)" \
           in capsys.readouterr().err
