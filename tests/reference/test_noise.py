"""RAW Poisson-Gaussian noise, sRGB Gaussian noise and the per-image noise-level draw."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpu_blur.reference import noise, poisson_counts, rng
from gpu_blur.reference.rng import Stream

SEED = 20220724

# (K, sigma_r) per data set: RSBlur pipeline reference §5.5 (beta1, beta2 as a std).
REALBLUR_LEVELS = (8.8915e-5, 2.9430e-5)
RSBLUR_LEVELS = (1.0e-4, 9.1504e-4)

FLAT_SHAPE = (400, 500)  # 200,000 photosites per patch


def poisson_gaussian_moments(x: float, k: float, sigma_r: float) -> tuple[float, float]:
    """Variance and fourth central moment of K * Poisson(x / K) + sigma_r * N(0, 1)."""
    lam = x / k
    var_shot = k * k * lam  # = K x
    mu4_shot = k**4 * lam * (1.0 + 3.0 * lam)
    var_read = sigma_r * sigma_r
    var = var_shot + var_read
    mu4 = mu4_shot + 6.0 * var_shot * var_read + 3.0 * var_read * var_read
    return var, mu4


@pytest.mark.parametrize("levels", [REALBLUR_LEVELS, RSBLUR_LEVELS], ids=["realblur", "rsblur"])
@pytest.mark.parametrize("x", [0.0, 5e-4, 0.01, 0.2, 0.6])
def test_poisson_gaussian_flat_patch_mean_and_variance(levels, x):
    k, sigma_r = levels
    out = noise.add_poisson_gaussian(
        np.full(FLAT_SHAPE, x), k, sigma_r, seed=SEED, sample_index=int(x * 1e4)
    )
    var, mu4 = poisson_gaussian_moments(x, k, sigma_r)
    n = out.size
    # Five standard errors of each estimator at this sample size.
    assert abs(out.mean() - x) <= 5.0 * math.sqrt(var / n), f"mean {out.mean()!r} vs {x}"
    sample_var = out.var(ddof=1)
    assert abs(sample_var - var) <= 5.0 * math.sqrt((mu4 - var * var) / n), (
        f"variance {sample_var!r} vs K x + sigma_r^2 = {var!r}"
    )


def test_poisson_gaussian_is_k_times_counts_plus_read_noise_from_documented_streams():
    gen = np.random.default_rng(3)
    raw = gen.uniform(-0.01, 0.8, (24, 31))
    k, sigma_r = RSBLUR_LEVELS
    out = noise.add_poisson_gaussian(raw, k, sigma_r, seed=SEED, sample_index=4, origin=(6, 10))
    y = np.arange(6, 30)[:, None]
    x = np.arange(10, 41)[None, :]
    counts = poisson_counts.poisson(np.maximum(raw, 0.0) / k, SEED, 4, y, x,
                                    stream=Stream.SHOT_NOISE)
    z = rng.pixel_normals(SEED, 4, Stream.READ_NOISE, y, x, count=1)[..., 0]
    np.testing.assert_array_equal(out, k * counts + sigma_r * z)


def test_poisson_gaussian_tile_equals_whole_image():
    gen = np.random.default_rng(4)
    raw = gen.uniform(0.0, 1.0, (48, 64))
    k, sigma_r = REALBLUR_LEVELS
    whole = noise.add_poisson_gaussian(raw, k, sigma_r, seed=SEED, sample_index=9)
    tile = noise.add_poisson_gaussian(
        raw[17:40, 5:33], k, sigma_r, seed=SEED, sample_index=9, origin=(17, 5)
    )
    np.testing.assert_array_equal(tile, whole[17:40, 5:33])
    shifted = noise.add_poisson_gaussian(raw[17:40, 5:33], k, sigma_r, seed=SEED, sample_index=9)
    assert not np.array_equal(shifted, tile)  # the origin, not the tile, picks the draws


def test_poisson_gaussian_draws_change_with_seed_and_sample_index():
    raw = np.full((32, 32), 0.3)
    k, sigma_r = RSBLUR_LEVELS
    base = noise.add_poisson_gaussian(raw, k, sigma_r, seed=SEED, sample_index=0)
    for seed, sample in ((SEED + 1, 0), (SEED, 1)):
        other = noise.add_poisson_gaussian(raw, k, sigma_r, seed=seed, sample_index=sample)
        assert np.count_nonzero(other == base) <= 2


def test_poisson_gaussian_clamps_negative_signal_and_keeps_negative_output():
    k, sigma_r = RSBLUR_LEVELS
    at_zero = noise.add_poisson_gaussian(np.zeros((64, 64)), k, sigma_r, seed=SEED, sample_index=2)
    below = noise.add_poisson_gaussian(
        np.full((64, 64), -0.05), k, sigma_r, seed=SEED, sample_index=2
    )
    np.testing.assert_array_equal(below, at_zero)  # shot noise saw max(x, 0) = 0
    assert (at_zero < 0).mean() > 0.4  # no clipping: the read noise goes below zero


def test_poisson_gaussian_without_read_noise_is_whole_multiples_of_k():
    k = 0.01
    out = noise.add_poisson_gaussian(np.full((50, 50), 0.05), k, 0.0, seed=SEED, sample_index=6)
    counts = out / k
    np.testing.assert_allclose(counts, np.round(counts), rtol=0, atol=1e-9)
    assert np.unique(np.round(counts)).size > 5


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"shot_noise_k": 0.0}, "shot-noise gain in units of the \\[0, 1\\] signal"),
        ({"shot_noise_k": -1e-4}, "got -0.0001"),
        ({"shot_noise_k": float("nan")}, "shot_noise_k"),
        ({"read_noise_std": -1e-3}, "read_noise_std"),
        ({"raw": np.zeros((2, 2, 3))}, "shape \\(2, 2, 3\\)"),
        ({"raw": np.array([[0.1, np.nan]])}, "NaN or infinite"),
        ({"origin": (-1, 0)}, "origin"),
    ],
)
def test_poisson_gaussian_rejects_bad_arguments(kwargs, message):
    args = {"raw": np.zeros((2, 2)), "shot_noise_k": 1e-4, "read_noise_std": 1e-3}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        noise.add_poisson_gaussian(**args, seed=SEED, sample_index=0)


def test_gaussian_srgb_mean_std_and_channel_independence():
    std = 1.3 * noise.SRGB_GAUSSIAN_BASE_STD
    image = np.full((250, 300, 3), 0.5)
    out = noise.add_gaussian_srgb(image, std, seed=SEED, sample_index=12)
    residual = (out - image).reshape(-1, 3)
    n = residual.shape[0]
    for c in range(3):
        channel = residual[:, c]
        assert abs(channel.mean()) <= 5.0 * std / math.sqrt(n), f"channel {c}: mean"
        # Var of the sample variance of a normal: 2 sigma^4 / (n - 1).
        assert abs(channel.var(ddof=1) - std * std) <= 5.0 * std * std * math.sqrt(2.0 / (n - 1))
    corr = np.corrcoef(residual, rowvar=False)
    assert np.max(np.abs(corr - np.eye(3))) <= 5.0 / math.sqrt(n)


def test_gaussian_srgb_uses_normals_0_1_2_of_srgb_stream_at_global_coordinates():
    gen = np.random.default_rng(8)
    image = gen.uniform(0, 1, (20, 26, 3))
    out = noise.add_gaussian_srgb(image, 0.02, seed=SEED, sample_index=3, origin=(100, 7))
    z = rng.pixel_normals(
        SEED, 3, Stream.SRGB_NOISE, np.arange(100, 120)[:, None], np.arange(7, 33)[None, :], 3
    )
    np.testing.assert_array_equal(out, image + 0.02 * z)
    whole = noise.add_gaussian_srgb(
        np.zeros((130, 40, 3)), 0.02, seed=SEED, sample_index=3, origin=(0, 0)
    )
    np.testing.assert_array_equal(whole[100:120, 7:33], 0.02 * z)  # tile draws = whole draws


def test_gaussian_srgb_does_not_clip():
    out = noise.add_gaussian_srgb(np.ones((40, 40, 3)), 0.05, seed=SEED, sample_index=1)
    assert out.max() > 1.0 and out.min() < 1.0


@pytest.mark.parametrize(
    ("image", "std", "message"),
    [(np.zeros((4, 4)), 0.01, "shape"), (np.zeros((4, 4, 3)), -0.01, "std")],
)
def test_gaussian_srgb_rejects_bad_arguments(image, std, message):
    with pytest.raises(ValueError, match=message):
        noise.add_gaussian_srgb(image, std, seed=SEED, sample_index=0)


def test_draw_noise_levels_spans_half_to_one_and_a_half_beta():
    beta1, beta2 = RSBLUR_LEVELS
    assert noise.draw_noise_levels(0.0, 1.0, beta1, beta2) == (0.5 * beta1, 1.5 * beta2)
    assert noise.draw_noise_levels(0.5, 0.5, beta1, beta2) == (beta1, beta2)
    k, sigma_r = noise.draw_noise_levels(0.25, 0.75, beta1, beta2)
    assert k == beta1 * (1.0 - 0.5 + 2.0 * 0.5 * 0.25) and sigma_r == beta2 * 1.25
    assert noise.draw_noise_levels(0.9, 0.1, beta1, beta2, spread=0.0) == (beta1, beta2)
    # Affine in u: uniform u gives a uniform level over the whole range.
    u = rng.image_uniforms(SEED, 0, Stream.PARAMS, 2000)
    levels = np.array([noise.draw_noise_levels(a, a, beta1, beta2)[0] for a in u])
    assert levels.min() >= 0.5 * beta1 and levels.max() <= 1.5 * beta1
    assert abs(levels.mean() - beta1) <= 5.0 * beta1 / math.sqrt(12 * u.size)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((-0.1, 0.5, 1e-4, 1e-3), "u_shot"),
        ((0.5, 1.5, 1e-4, 1e-3), "u_read"),
        ((0.5, 0.5, 0.0, 1e-3), "shot-noise gain"),
        ((0.5, 0.5, 1e-4, -1e-3), "read_noise_std"),
        ((0.5, 0.5, 1e-4, 1e-3, 1.5), "spread"),
        ((0.0, 0.5, 1e-4, 1e-3, 1.0), "K must be > 0"),
    ],
)
def test_draw_noise_levels_rejects_bad_arguments(args, message):
    with pytest.raises(ValueError, match=message):
        noise.draw_noise_levels(*args)
