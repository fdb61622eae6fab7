"""Accuracy knobs in the reference and the scene: the Poisson normal approximation, resampled
A7R3 response tables, and the fast-maths switch (issue 7).

The kernels' side of the same knobs is in tests/backends/test_device_knobs.py,
the passes' in tests/backends/test_knobs_backends.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_noise import poisson_gaussian_moments

from gpu_blur.constants import A7R3_CRF_TABLE_X255
from gpu_blur.planning import plan
from gpu_blur.reference import noise, poisson_counts, rng, transfer
from gpu_blur.reference.rng import Stream
from gpu_blur.scene import SceneError, scene_from_dict
from gpu_blur.testing import assert_close, z_mean, z_var

SEED = 0x0DD_BA11
N = 200_000
_Y = np.zeros(N, dtype=np.int64)
_X = np.arange(N, dtype=np.int64)


# --------------------------------------------------------------------------------------------
# Poisson: the normal approximation above a threshold
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rate", [1000.5, 3e3, 1e4, 1e6, 1e9])
def test_normal_approximation_has_the_poisson_mean_and_variance_on_flat_patches(rate):
    counts = poisson_counts.poisson(np.full(N, rate), SEED, 3, _Y, _X, normal_above=1000.0)
    assert np.all(counts == np.floor(counts)) and counts.min() >= 0
    # N(rate, rate) rounded: mean rate, variance rate + 1/12 (Sheppard), far below the
    # standard error of the variance here; fourth moment of the normal, 3 rate^2.
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, 3.0 * rate * rate)) < 5.0


def test_normal_approximation_is_not_the_exact_sampler_above_the_threshold():
    rate = np.full(N, 5e4)
    exact = poisson_counts.poisson(rate, SEED, 5, _Y, _X)
    approx = poisson_counts.poisson(rate, SEED, 5, _Y, _X, normal_above=1e3)
    assert np.count_nonzero(approx != exact) > 0.9 * N


def test_counts_at_or_below_the_threshold_are_the_exact_samplers_bit_for_bit():
    gen = np.random.default_rng(1)
    threshold = 250.0
    rates = np.concatenate([[0.0, -3.0, 1e-9, 9.99, 10.0, threshold, np.nextafter(threshold, 0)],
                            10 ** gen.uniform(-2, 2.4, 20_000), 10 ** gen.uniform(2.4, 7, 20_000)])
    ys, xs = gen.integers(0, 2**20, rates.size), gen.integers(0, 2**20, rates.size)
    exact = poisson_counts.poisson(rates, SEED, 9, ys, xs)
    mixed = poisson_counts.poisson(rates, SEED, 9, ys, xs, normal_above=threshold)
    below = rates <= threshold
    assert below.sum() > 20_000 and (~below).sum() > 15_000
    np.testing.assert_array_equal(mixed[below], exact[below])
    above = poisson_counts.poisson_normal_approximation(rates[~below], SEED, 9, ys[~below],
                                                        xs[~below])
    np.testing.assert_array_equal(mixed[~below], above)


def normal_count_scalar(rate: float, seed: int, sample: int, y: int, x: int) -> float:
    """The approximation as its docstring states it, one pixel, in plain Python (math's libm)."""
    u = rng.pixel_uniforms(seed, sample, Stream.SHOT_NOISE, y, x, 0)
    z = math.sqrt(-2.0 * math.log(float(u[0]))) * math.cos(2.0 * math.pi * float(u[1]))
    return float(max(0, math.floor(rate + math.sqrt(rate) * z + 0.5)))


def test_normal_approximation_matches_a_scalar_transcription_of_its_formula():
    gen = np.random.default_rng(2)
    rates = np.concatenate([[0.0, 1e-6, 0.3, 2.0], 10 ** gen.uniform(-1, 8, 3000)])
    ys, xs = gen.integers(0, 5000, rates.size), gen.integers(0, 5000, rates.size)
    counts = poisson_counts.poisson_normal_approximation(rates, SEED, 4, ys, xs)
    expected = [normal_count_scalar(float(r), SEED, 4, int(y), int(x))
                for r, y, x in zip(rates, ys, xs, strict=True)]
    np.testing.assert_array_equal(counts, expected)


def test_normal_approximation_clamps_at_zero_for_small_rates():
    rates = np.full(N, 0.5)  # rate - sqrt(rate) * 5.8 < 0: the clamp decides often
    counts = poisson_counts.poisson(rates, SEED, 6, _Y, _X, normal_above=0.0)
    assert counts.min() == 0.0 and not np.signbit(counts).any()
    assert np.array_equal(poisson_counts.poisson(np.array([0.0, -1.0]), SEED, 6, 0, np.arange(2),
                                      normal_above=0.0), [0.0, 0.0])


def test_normal_approximation_uses_global_coordinates_so_a_tile_draws_what_the_image_draws():
    rate = 10 ** np.random.default_rng(3).uniform(2, 6, (40, 30))
    rows, cols = np.arange(40)[:, None], np.arange(30)[None, :]
    whole = poisson_counts.poisson(rate, SEED, 2, rows, cols, normal_above=500.0)
    tile = poisson_counts.poisson(rate[7:33, 4:19], SEED, 2, rows[7:33], cols[:, 4:19],
                                  normal_above=500.0)
    np.testing.assert_array_equal(tile, whole[7:33, 4:19])


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, "many"])
def test_bad_threshold_is_refused_naming_it(bad):
    with pytest.raises(ValueError, match="normal_above must be a finite Poisson rate >= 0"):
        poisson_counts.poisson(np.ones(3), SEED, 0, 0, np.arange(3), normal_above=bad)


@pytest.mark.parametrize("x", [0.2, 0.6])
def test_poisson_gaussian_noise_with_the_approximation_keeps_its_mean_and_variance(x):
    k, sigma_r = 8.8915e-5, 2.9430e-5  # RealBlur: rates 2,249 and 6,748, above 1,000
    out = noise.add_poisson_gaussian(np.full((400, 500), x), k, sigma_r, seed=SEED,
                                     sample_index=8, poisson_normal_above=1000.0)
    var, mu4 = poisson_gaussian_moments(x, k, sigma_r)
    assert abs(z_mean(out, x, var)) < 5.0
    assert abs(z_var(out, var, mu4)) < 5.0
    exact = noise.add_poisson_gaussian(np.full((400, 500), x), k, sigma_r, seed=SEED,
                                       sample_index=8)
    assert np.count_nonzero(out != exact) > 0.9 * out.size


# --------------------------------------------------------------------------------------------
# A7R3 response tables of other sizes
# --------------------------------------------------------------------------------------------

TABLE_SIZES = [256, 1024, 4096]


@pytest.mark.parametrize("size", [2, 16, *TABLE_SIZES, 65536])
def test_resampled_tables_are_strictly_increasing_with_the_authors_end_values(size):
    table = transfer.a7r3_lookup_table(size)
    assert table.shape == (size,) and not table.flags.writeable
    assert np.all(np.diff(table) > 0)
    assert table[0] == A7R3_CRF_TABLE_X255[0] and table[-1] == A7R3_CRF_TABLE_X255[-1]
    # a table that is strictly increasing has an inverse, and it undoes the curve
    x = np.linspace(0.0, 1.0, 1001)
    back = transfer.inverse_lookup_crf(transfer.lookup_crf(x, table), table)
    assert np.abs(back - x).max() < 1e-12


def test_size_zero_is_the_authors_table_and_their_own_size_resamples_to_it():
    assert transfer.a7r3_lookup_table(0) is A7R3_CRF_TABLE_X255
    same = transfer.a7r3_lookup_table(A7R3_CRF_TABLE_X255.size)
    np.testing.assert_allclose(same, A7R3_CRF_TABLE_X255, rtol=0, atol=1e-12)


def test_resampled_nodes_lie_on_the_authors_curve():
    table = transfer.a7r3_lookup_table(1000)
    nodes = np.arange(1000) / 999.0
    np.testing.assert_allclose(table / 255.0, transfer.lookup_crf(nodes, A7R3_CRF_TABLE_X255),
                               rtol=0, atol=1e-15)


@pytest.mark.parametrize("size", TABLE_SIZES)
def test_resampled_table_follows_the_authors_curve_within_its_resolution_row(size):
    x = np.linspace(0.0, 1.0, 1_000_001)
    got = transfer.retone(transfer.linear_to_srgb(x), "a7r3-lut", size)
    full = transfer.retone(transfer.linear_to_srgb(x), "a7r3-lut")
    assert_close(got, full, f"crf_table_{size}")


def test_coarser_tables_stray_further_from_the_authors_curve():
    x = np.linspace(0.0, 1.0, 200_001)
    full = transfer.lookup_crf(x, A7R3_CRF_TABLE_X255)
    errors = [np.abs(transfer.lookup_crf(x, transfer.a7r3_lookup_table(n)) - full).max()
              for n in (64, *TABLE_SIZES)]
    assert errors == sorted(errors, reverse=True) and errors[-1] > 0.0


@pytest.mark.parametrize("size", [1, -4, 2.5, True])
def test_bad_table_sizes_are_refused(size):
    with pytest.raises(ValueError, match="integer size >= 2"):
        transfer.a7r3_lookup_table(size)


def test_table_size_with_the_polynomial_is_refused():
    with pytest.raises(ValueError, match="needs crf 'a7r3-lut'"):
        transfer.retone(np.zeros(3), "a7r3", 256)


# --------------------------------------------------------------------------------------------
# Scene keys and the plan
# --------------------------------------------------------------------------------------------


def test_knobs_reach_the_plan_as_stage_options():
    scene = scene_from_dict({"noise": {"poisson": "normal", "normal_above": 300},
                             "output": {"crf": "a7r3-lut", "crf_table_size": 1024,
                                        "fast_math": True}})
    p = plan(scene)
    assert p["poisson_gaussian_noise"].options == {"sampler": "normal", "normal_above": 300.0}
    assert p["poisson_gaussian_noise"].variant == "normal above 300"
    assert p.poisson_normal_above == 300.0
    assert p["retone"].options == {"crf": "a7r3-lut", "table_size": 1024}
    assert p.fast_math and "fast float transcendentals" in str(p)
    default = plan(scene_from_dict({}))
    assert default["poisson_gaussian_noise"].options["sampler"] == "exact"
    assert default.poisson_normal_above is None
    assert not default.fast_math and "fast" not in str(default)


@pytest.mark.parametrize("data, message", [
    ({"noise": {"poisson": "gauss"}}, "noise.poisson = 'gauss' is invalid; allowed: 'exact'"),
    ({"noise": {"normal_above": -1.0}}, "noise.normal_above = -1.0 is invalid"),
    ({"noise": {"normal_above": math.inf}}, "noise.normal_above = inf is invalid"),
    ({"noise": {"normal_above": math.nan}}, "noise.normal_above = nan is invalid"),
    ({"output": {"crf": "a7r3-lut", "crf_table_size": 1}}, "crf_table_size = 1 is invalid"),
    ({"output": {"crf_table_size": 256}}, "needs output.crf = 'a7r3-lut' (it is 'srgb')"),
    ({"output": {"fast_math": 1}}, "output.fast_math = 1 is invalid; allowed: bool"),
    ({"output": {"fast_math": True, "precision": "float64"}}, "needs output.precision"),
])
def test_bad_knob_values_are_named_with_what_is_allowed(data, message):
    with pytest.raises(SceneError) as e:
        scene_from_dict(data, "knobs.toml")
    assert str(e.value).startswith("knobs.toml: ") and message in str(e.value)
