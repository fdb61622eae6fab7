"""Philox4x32-10, the counter layouts, uniforms, normals, log(k!) and the Poisson sampler."""

from __future__ import annotations

import math
from decimal import Decimal, localcontext
from pathlib import Path

import numpy as np
import pytest
from conftest import KNOWN_ANSWERS
from scipy import stats

from gpu_blur.reference import poisson_counts, rng
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, z_mean, z_var

SEED = 0x5EED_CAFE_F00D_1234


# --------------------------------------------------------------------------------------------
# Philox4x32
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("rounds", "counter", "key", "expected"), KNOWN_ANSWERS)
def test_philox_matches_random123_known_answer_vectors(rounds, counter, key, expected):
    out = rng.philox4x32(np.array(counter, np.uint32), np.array(key, np.uint32), rounds=rounds)
    assert out.dtype == np.uint32
    assert [hex(v) for v in out] == [hex(v) for v in expected]


def test_philox_default_is_ten_rounds():
    counter = np.array(KNOWN_ANSWERS[2][1], np.uint32)
    key = np.array(KNOWN_ANSWERS[2][2], np.uint32)
    np.testing.assert_array_equal(rng.philox4x32(counter, key), rng.philox4x32(counter, key, 10))


def test_philox_broadcasts_keys_over_leading_axes():
    gen = np.random.default_rng(1)
    counters = gen.integers(0, 2**32, size=(3, 5, 4), dtype=np.uint32)
    keys = gen.integers(0, 2**32, size=(5, 2), dtype=np.uint32)
    out = rng.philox4x32(counters, keys)
    assert out.shape == (3, 5, 4)
    for i in range(3):
        for j in range(5):
            np.testing.assert_array_equal(out[i, j], rng.philox4x32(counters[i, j], keys[j]))


@pytest.mark.parametrize(
    ("counter", "key", "rounds", "message"),
    [
        (np.zeros(3, np.uint32), np.zeros(2, np.uint32), 10, "shape"),
        (np.zeros(4, np.uint32), np.zeros(3, np.uint32), 10, "shape"),
        (np.array([0, 0, 0, 2**32]), np.zeros(2, np.uint32), 10, r"\[0, 2\*\*32\)"),
        (np.array([0, -1, 0, 0]), np.zeros(2, np.uint32), 10, r"\[0, 2\*\*32\)"),
        (np.zeros(4), np.zeros(2, np.uint32), 10, "integers"),
        (np.zeros(4, np.uint32), np.zeros(2, np.uint32), 17, "rounds"),
    ],
)
def test_philox_rejects_bad_input(counter, key, rounds, message):
    with pytest.raises(ValueError, match=message):
        rng.philox4x32(counter, key, rounds=rounds)


OPENCL_PHILOX_SOURCE = r"""
#include <pyopencl-random123/philox.cl>

__kernel void gb_test_philox4x32(__global const uint *ctr, __global const uint *key,
                                 const uint rounds, __global uint *out)
{
    const size_t i = get_global_id(0);
    philox4x32_ctr_t c = {{ctr[4 * i], ctr[4 * i + 1], ctr[4 * i + 2], ctr[4 * i + 3]}};
    philox4x32_key_t k = {{key[2 * i], key[2 * i + 1]}};
    philox4x32_ctr_t r = philox4x32_R(rounds, c, k);
    for (int j = 0; j < 4; ++j) out[4 * i + j] = r.v[j];
}
"""


@pytest.fixture(scope="module")
def opencl_philox(opencl_queue):
    """pyopencl, a context, a queue and the test kernel on the OpenCL backend's device."""
    cl, context, queue = opencl_queue
    include = Path(cl.__file__).parent / "cl"
    program = cl.Program(context, OPENCL_PHILOX_SOURCE).build(options=["-I", str(include)])
    return cl, context, queue, cl.Kernel(program, "gb_test_philox4x32")


def run_opencl_philox(opencl_philox, counters: np.ndarray, keys: np.ndarray, rounds: int):
    cl, context, queue, kernel = opencl_philox
    mf = cl.mem_flags
    ctr_buf = cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=counters)
    key_buf = cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=keys)
    out = np.empty_like(counters)
    out_buf = cl.Buffer(context, mf.WRITE_ONLY, out.nbytes)
    kernel(queue, (counters.shape[0],), None, ctr_buf, key_buf, np.uint32(rounds), out_buf)
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    return out


@pytest.mark.parametrize("rounds", [10, 7])
def test_philox_matches_pyopencl_random123_on_opencl(opencl_philox, rounds):
    gen = np.random.default_rng(2024 + rounds)
    counters = gen.integers(0, 2**32, size=(10_000, 4), dtype=np.uint32)
    keys = gen.integers(0, 2**32, size=(10_000, 2), dtype=np.uint32)
    # The known-answer inputs and the layouts' corner values ride along.
    kat = [(c, k) for r, c, k, _ in KNOWN_ANSWERS if r == rounds]
    counters[: len(kat)] = [c for c, _ in kat]
    keys[: len(kat)] = [k for _, k in kat]
    counters[len(kat)] = (0, 0, 0, (int(Stream.SRGB_NOISE) << 24) | (2**24 - 1))
    expected = run_opencl_philox(opencl_philox, counters, keys, rounds)
    np.testing.assert_array_equal(rng.philox4x32(counters, keys, rounds=rounds), expected)
    answers = [answer for r, _, _, answer in KNOWN_ANSWERS if r == rounds]
    for i, answer in enumerate(answers):
        assert tuple(int(v) for v in expected[i]) == answer, f"OpenCL disagrees with KAT {i}"


# --------------------------------------------------------------------------------------------
# Keys, counters, layouts
# --------------------------------------------------------------------------------------------


def test_key_from_seed_splits_low_and_high_words():
    np.testing.assert_array_equal(rng.key_from_seed(0x0123456789ABCDEF), [0x89ABCDEF, 0x01234567])
    np.testing.assert_array_equal(rng.key_from_seed(2**64 - 1), [0xFFFFFFFF, 0xFFFFFFFF])
    np.testing.assert_array_equal(rng.key_from_seed(np.uint64(7)), [7, 0])
    assert rng.key_from_seed(0).dtype == np.uint32


@pytest.mark.parametrize("seed", [-1, 2**64, 1.0, "3", True, None])
def test_key_from_seed_rejects_non_int_or_out_of_range(seed):
    with pytest.raises(ValueError, match="seed"):
        rng.key_from_seed(seed)


def test_stream_values_are_the_documented_contract():
    assert {s.name: int(s) for s in Stream} == {
        "PARAMS": 1,
        "TRAJECTORY": 2,
        "KERNEL": 3,
        "SHOT_NOISE": 4,
        "READ_NOISE": 5,
        "SRGB_NOISE": 6,
        "SPOT_CHECK": 7,
    }


def test_pixel_bits_use_counter_x_y_sample_stream_round():
    y = np.array([[0], [7], [2**32 - 1]])
    x = np.array([[0, 5, 123456]])
    bits = rng.pixel_bits(SEED, 99, Stream.READ_NOISE, y, x, round=3)
    assert bits.shape == (3, 3, 4)
    for i in range(3):
        for j in range(3):
            counter = np.array(
                [x[0, j], y[i, 0], 99, (int(Stream.READ_NOISE) << 24) | 3], dtype=np.uint32
            )
            np.testing.assert_array_equal(
                bits[i, j], rng.philox4x32(counter, rng.key_from_seed(SEED))
            )


def test_image_uniforms_use_counter_block_zero_sample_stream():
    count = 11
    u = rng.image_uniforms(SEED, 42, Stream.PARAMS, count)
    assert u.shape == (count,)
    key = rng.key_from_seed(SEED)
    for i in range(count):
        counter = np.array([i // 4, 0, 42, int(Stream.PARAMS) << 24], dtype=np.uint32)
        assert u[i] == rng.uniform_from_bits(rng.philox4x32(counter, key)[i % 4])
    # Asking for more never changes the earlier ones; zero is allowed.
    np.testing.assert_array_equal(rng.image_uniforms(SEED, 42, Stream.PARAMS, 3), u[:3])
    assert rng.image_uniforms(SEED, 42, Stream.PARAMS, 0).shape == (0,)


def test_tile_draws_equal_whole_image_draws_at_the_same_pixels():
    height, width = 37, 53
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    whole = rng.pixel_uniforms(SEED, 5, Stream.SHOT_NOISE, rows, cols, round=2)
    r0, r1, c0, c1 = 10, 26, 17, 41
    tile = rng.pixel_uniforms(
        SEED, 5, Stream.SHOT_NOISE, np.arange(r0, r1)[:, None], np.arange(c0, c1)[None, :], 2
    )
    np.testing.assert_array_equal(tile, whole[r0:r1, c0:c1])
    normals_whole = rng.pixel_normals(SEED, 5, Stream.SRGB_NOISE, rows, cols, count=6)
    normals_tile = rng.pixel_normals(
        SEED, 5, Stream.SRGB_NOISE, np.arange(r0, r1)[:, None], np.arange(c0, c1)[None, :], 6
    )
    np.testing.assert_array_equal(normals_tile, normals_whole[r0:r1, c0:c1])


@pytest.mark.parametrize(
    "change",
    [
        {"seed": SEED + 1},
        {"seed": SEED + 2**32},  # the key's high word matters
        {"sample_index": 1},
        {"stream": Stream.READ_NOISE},
        {"round": 1},
    ],
)
def test_draws_differ_with_seed_sample_index_stream_or_round(change):
    base = {"seed": SEED, "sample_index": 0, "stream": Stream.SHOT_NOISE, "round": 0}
    y = np.arange(64)[:, None]
    x = np.arange(64)[None, :]
    a = rng.pixel_bits(base["seed"], base["sample_index"], base["stream"], y, x, base["round"])
    other = {**base, **change}
    b = rng.pixel_bits(other["seed"], other["sample_index"], other["stream"], y, x, other["round"])
    # Independent 32-bit words coincide with probability 2**-32 each.
    assert np.count_nonzero(a == b) <= 2


def test_neighbouring_pixels_and_rows_get_different_draws():
    bits = rng.pixel_bits(SEED, 0, Stream.SHOT_NOISE, np.arange(128)[:, None], np.arange(128))
    words = bits.reshape(-1)
    assert np.unique(words).size >= words.size - 4


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sample_index": -1}, "sample_index"),
        ({"sample_index": 2**32}, "sample_index"),
        ({"round": 2**24}, "round"),
        ({"round": -1}, "round"),
        ({"stream": 9}, "stream"),
        ({"y": np.array([-1])}, "y must lie"),
        ({"x": np.array([2**32])}, "x must lie"),
        ({"x": np.array([1.5])}, "integer"),
    ],
)
def test_pixel_bits_reject_out_of_range_arguments(kwargs, message):
    args = {"seed": 1, "sample_index": 0, "stream": Stream.SHOT_NOISE, "y": 0, "x": 0, "round": 0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        rng.pixel_bits(**args)


def test_image_uniforms_reject_out_of_range_sample_index():
    with pytest.raises(ValueError, match="sample_index"):
        rng.image_uniforms(1, 2**32, Stream.PARAMS, 4)


# --------------------------------------------------------------------------------------------
# Uniforms
# --------------------------------------------------------------------------------------------


def test_uniforms_are_never_0_or_1_even_at_extreme_words():
    bits = np.array([0, 1, 0x1FF, 0x200, 0x7FFFFFFF, 0x80000000, 0xFFFFFE00, 0xFFFFFFFF])
    u = rng.uniform_from_bits(bits.astype(np.uint32))
    assert u[0] == 2.0**-24 and u[-1] == 1.0 - 2.0**-24
    for values in (u, u.astype(np.float32)):
        assert np.all(values > 0) and np.all(values < 1)


def test_uniforms_are_exact_in_float32_for_every_23_bit_value():
    top = np.arange(2**23, dtype=np.uint32)
    bits = (top << np.uint32(9)) | np.uint32(0x155)  # the dropped low bits play no part
    u = rng.uniform_from_bits(bits)
    np.testing.assert_array_equal(u.astype(np.float32).astype(np.float64), u)
    # A float32 kernel evaluating the same expression gets the same numbers, bit for bit.
    u32 = ((bits >> np.uint32(9)).astype(np.float32) + np.float32(0.5)) * np.float32(2.0**-23)
    np.testing.assert_array_equal(u32.astype(np.float64), u)
    assert np.all(np.diff(u) == 2.0**-23)  # evenly spaced, all distinct


def test_uniforms_from_pixel_draws_are_uniform():
    u = rng.pixel_uniforms(SEED, 3, Stream.SHOT_NOISE, np.arange(250)[:, None], np.arange(200))
    flat = u.reshape(-1)
    assert abs(z_mean(flat, 0.5, 1.0 / 12.0)) < 5.0
    assert stats.kstest(flat, "uniform").pvalue > 1e-6
    # The four words of one counter are uncorrelated.
    corr = np.corrcoef(u.reshape(-1, 4), rowvar=False)
    assert np.max(np.abs(corr - np.eye(4))) < 5.0 / math.sqrt(u.shape[0] * u.shape[1])


# --------------------------------------------------------------------------------------------
# Normals
# --------------------------------------------------------------------------------------------


def test_box_muller_matches_closed_form():
    u1 = np.array([math.exp(-0.5), 2.0**-24, 0.3, 1.0 - 2.0**-24])
    u2 = np.array([0.25, 0.5, 0.7, 2.0**-24])
    z_cos, z_sin = rng.box_muller(u1, u2)
    radius = [math.sqrt(-2.0 * math.log(a)) for a in u1]
    expected_cos = [r * math.cos(2.0 * math.pi * b) for r, b in zip(radius, u2, strict=True)]
    expected_sin = [r * math.sin(2.0 * math.pi * b) for r, b in zip(radius, u2, strict=True)]
    assert_close(z_cos, expected_cos, "box_muller", backend="independent")
    assert_close(z_sin, expected_sin, "box_muller", backend="independent")
    assert abs(z_sin[0] - 1.0) < 1e-15  # radius 1 at a quarter turn


def test_pixel_normals_take_four_per_round_from_box_muller_pairs():
    y = np.arange(6)[:, None]
    x = np.arange(5)[None, :]
    z = rng.pixel_normals(SEED, 8, Stream.SRGB_NOISE, y, x, count=7)
    assert z.shape == (6, 5, 7)
    for r in range(2):
        u = rng.pixel_uniforms(SEED, 8, Stream.SRGB_NOISE, y, x, round=r)
        first = rng.box_muller(u[..., 0], u[..., 1])
        second = rng.box_muller(u[..., 2], u[..., 3])
        expected = np.stack([*first, *second], axis=-1)[..., : 7 - 4 * r]
        np.testing.assert_array_equal(z[..., 4 * r : 4 * r + 4], expected)
    np.testing.assert_array_equal(
        rng.pixel_normals(SEED, 8, Stream.SRGB_NOISE, y, x, count=3), z[..., :3]
    )


def test_pixel_normals_are_independent_standard_normals():
    z = rng.pixel_normals(SEED, 11, Stream.READ_NOISE, np.arange(150)[:, None], np.arange(200), 8)
    samples = z.reshape(-1, 8)
    n = samples.shape[0]
    for j in range(8):
        column = samples[:, j]
        assert abs(z_mean(column, 0.0, 1.0)) < 5.0, f"normal {j}: mean"
        assert abs(z_var(column, 1.0, 3.0)) < 5.0, f"normal {j}: variance"
        assert stats.kstest(column, "norm").pvalue > 1e-6, f"normal {j}: shape"
    corr = np.corrcoef(samples, rowvar=False)
    assert np.max(np.abs(corr - np.eye(8))) < 5.0 / math.sqrt(n)


# --------------------------------------------------------------------------------------------
# log(k!)
# --------------------------------------------------------------------------------------------

# Stirling-series coefficients B_2j / (2j (2j - 1)) for the 50-digit reference values.
_STIRLING_TERMS = [
    (1, 12),
    (-1, 360),
    (1, 1260),
    (-1, 1680),
    (1, 1188),
    (-691, 360360),
    (1, 156),
    (-3617, 122400),
]


def exact_log_factorial(k: int) -> Decimal:
    """log(k!) to about 45 digits: exact factorial below 3000, a long Stirling series above."""
    with localcontext() as ctx:
        ctx.prec = 50
        if k < 3000:
            return Decimal(math.factorial(k)).ln() if k > 1 else Decimal(0)
        n = Decimal(k)
        pi = Decimal("3.14159265358979323846264338327950288419716939937510")
        value = (n + Decimal("0.5")) * n.ln() - n + (2 * pi).ln() / 2
        for j, (num, den) in enumerate(_STIRLING_TERMS):
            value += Decimal(num) / (Decimal(den) * n ** (2 * j + 1))
        return value


def test_log_factorial_table_is_correctly_rounded():
    for k in range(poisson_counts.LOG_FACTORIAL_TABLE.size):
        got = poisson_counts.log_factorial(np.array([k]))[0]
        assert got == float(exact_log_factorial(k)), f"k = {k}"


def test_log_factorial_relative_error_is_at_float64_rounding():
    ks = np.unique(
        np.concatenate(
            [
                np.arange(16, 400),
                np.round(np.logspace(np.log10(400), 12, 200)),
            ]
        )
    ).astype(np.int64)
    got = poisson_counts.log_factorial(ks.astype(np.float64))
    expected = [float(exact_log_factorial(int(k))) for k in ks]
    assert_close(got, expected, "log_factorial")
    log_factorial = poisson_counts.log_factorial
    assert log_factorial(np.array([15.0, 16.0]))[1] > log_factorial(np.array([15.0]))[0]


def test_log_factorial_rejects_negative_k():
    with pytest.raises(ValueError, match="k >= 0"):
        poisson_counts.log_factorial(np.array([3.0, -1.0]))


# --------------------------------------------------------------------------------------------
# Poisson
# --------------------------------------------------------------------------------------------

POISSON_N = 200_000
_Y = np.zeros(POISSON_N, dtype=np.int64)
_X = np.arange(POISSON_N, dtype=np.int64)


@pytest.mark.parametrize("rate", [0.0, 1e-12, 0.5, 1.0, 9.99, 10.0, 10.01, 30.0, 1e4, 1e7])
def test_poisson_mean_and_variance_match_rate(rate):
    counts = poisson_counts.poisson(np.full(POISSON_N, rate), SEED, 17, _Y, _X)
    assert np.all(counts == np.round(counts)) and counts.min() >= 0
    # Poisson: variance = rate, fourth central moment = rate * (1 + 3 rate).
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, rate * (1.0 + 3.0 * rate))) < 5.0


def test_poisson_mean_and_variance_over_log_spaced_rates():
    rates = np.logspace(-3, 7, 41)
    rows = 20_000
    counts = poisson_counts.poisson(
        np.broadcast_to(rates, (rows, rates.size)),
        SEED,
        23,
        np.arange(rows)[:, None],
        np.arange(rates.size)[None, :],
    )
    for j, rate in enumerate(rates):
        column = counts[:, j]
        assert abs(z_mean(column, rate, rate)) < 5.0, f"rate {rate:g}: mean"
        assert abs(z_var(column, rate, rate * (1.0 + 3.0 * rate))) < 5.0, f"rate {rate:g}: var"


@pytest.mark.parametrize("rate", [3.0, 10.0, 15.0])
def test_poisson_distribution_matches_exact_pmf_chi_square(rate):
    counts = poisson_counts.poisson(np.full(POISSON_N, rate), SEED, 29, _Y, _X).astype(np.int64)
    # Bins holding at least 20 expected counts; both tails lumped into the end bins.
    lo = int(stats.poisson.ppf(20.0 / POISSON_N, rate))
    hi = int(stats.poisson.isf(20.0 / POISSON_N, rate))
    edges = np.arange(lo, hi + 1)
    observed = np.array(
        [np.count_nonzero(counts <= lo)]
        + [np.count_nonzero(counts == k) for k in edges[1:-1]]
        + [np.count_nonzero(counts >= hi)]
    )
    prob = np.concatenate(
        [[stats.poisson.cdf(lo, rate)], stats.poisson.pmf(edges[1:-1], rate)]
        + [[stats.poisson.sf(hi - 1, rate)]]
    )
    assert observed.sum() == POISSON_N and abs(prob.sum() - 1.0) < 1e-12
    result = stats.chisquare(observed, prob * POISSON_N)
    assert result.pvalue > 1e-6, f"chi2 = {result.statistic:.1f} on {observed.size - 1} dof"


def test_poisson_rate_zero_and_negative_rates_give_exact_zero():
    rate = np.array([0.0, -0.0, -1.0, -1e300, 0.0])
    counts = poisson_counts.poisson(rate, SEED, 0, 0, np.arange(5))
    assert np.array_equal(counts, np.zeros(5)) and not np.signbit(counts).any()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_poisson_rejects_nan_and_inf_rates_naming_how_many(bad):
    rate = np.array([[1.0, bad], [bad, 2.0]])
    with pytest.raises(ValueError, match=r"2 of 4 rates .*index \(0, 1\)"):
        poisson_counts.poisson(rate, SEED, 0, np.arange(2)[:, None], np.arange(2))


def test_poisson_inversion_cap_is_never_reached_below_the_switch():
    rate = np.nextafter(poisson_counts.POISSON_PTRS_MIN_RATE, 0.0)
    u_max = float(rng.uniform_from_bits(np.uint32(0xFFFFFFFF)))
    k, p = 0, math.exp(-rate)
    cdf = p
    while u_max > cdf:
        k += 1
        p *= rate / k
        cdf += p
    assert k < poisson_counts.POISSON_INVERSION_MAX_K, f"search needs k = {k}"
    assert k <= 31


def reference_poisson_scalar(rate: float, seed: int, sample: int, y: int, x: int) -> float:
    """The sampler exactly as the docstring states it, one pixel at a time, in plain Python."""
    rate = max(rate, 0.0)

    def words(r):
        return [float(w) for w in rng.pixel_uniforms(seed, sample, Stream.SHOT_NOISE, y, x, r)]

    if rate < 10.0:
        u = words(0)[0]
        k, p = 0, math.exp(-rate)
        cdf = p
        while u > cdf and k < 64:
            k += 1
            p = p * (rate / k)
            cdf = cdf + p
        return float(k)
    mu = rate
    b = 0.931 + 2.53 * math.sqrt(mu)
    a = -0.059 + 0.02483 * b
    inv_alpha = 1.1239 + 1.1328 / (b - 3.4)
    v_r = 0.9277 - 3.6224 / (b - 2.0)
    r = 0
    while True:
        w = words(r)
        for big_u, v in ((w[0] - 0.5, w[1]), (w[2] - 0.5, w[3])):
            us = 0.5 - abs(big_u)
            k = math.floor((2.0 * a / us + b) * big_u + mu + 0.43)
            if us >= 0.07 and v <= v_r:
                return float(k)
            if k < 0 or (us < 0.013 and v > us):
                continue
            log_fact = float(poisson_counts.log_factorial(np.array([float(k)]))[0])
            if math.log(v * inv_alpha / (a / (us * us) + b)) <= -mu + k * math.log(mu) - log_fact:
                return float(k)
        r += 1


def test_poisson_vectorized_matches_scalar_transcription_of_the_algorithm():
    gen = np.random.default_rng(5)
    rates = np.concatenate(
        [[0.0, 1e-9, 9.999, 10.0, 10.5], gen.uniform(0, 12, 300), 10 ** gen.uniform(1, 7, 1500)]
    )
    ys = gen.integers(0, 5000, rates.size)
    xs = gen.integers(0, 5000, rates.size)
    counts = poisson_counts.poisson(rates, SEED, 31, ys, xs)
    expected = [
        reference_poisson_scalar(float(r), SEED, 31, int(y), int(x))
        for r, y, x in zip(rates, ys, xs, strict=True)
    ]
    np.testing.assert_array_equal(counts, expected)


def test_poisson_tile_equals_whole_image_and_seed_changes_draws():
    gen = np.random.default_rng(9)
    rate = 10 ** gen.uniform(-1, 5, (40, 30))
    rows = np.arange(40)[:, None]
    cols = np.arange(30)[None, :]
    whole = poisson_counts.poisson(rate, SEED, 2, rows, cols)
    tile = poisson_counts.poisson(rate[12:31, 5:22], SEED, 2, rows[12:31], cols[:, 5:22])
    np.testing.assert_array_equal(tile, whole[12:31, 5:22])
    other = poisson_counts.poisson(rate, SEED + 1, 2, rows, cols)
    assert np.count_nonzero(other != whole) > 0.8 * whole.size


def test_image_uniforms_of_a_few_blocks_equal_the_vectorized_philox():
    """The Python-int path for a sample's few draws gives philox4x32's words exactly."""
    for seed in (0, 1, 2**64 - 1, 12345678901234):
        for index in (0, 7, 2**32 - 1):
            for stream in (rng.Stream.PARAMS, rng.Stream.KERNEL, rng.Stream.TRAJECTORY):
                for count in (0, 1, 5, 9, 32, 33):
                    blocks = -(-count // 4)
                    counter = np.zeros((blocks, 4), np.uint64)
                    counter[:, 0] = np.arange(blocks)
                    counter[:, 2] = index
                    counter[:, 3] = int(stream) << 24
                    want = rng.uniform_from_bits(
                        rng.philox4x32(counter, rng.key_from_seed(seed)).reshape(-1)[:count])
                    got = rng.image_uniforms(seed, index, stream, count)
                    assert got.dtype == np.float64 and np.array_equal(got, want)


def test_a_batch_of_image_uniforms_equals_each_sample_drawn_alone():
    """Row b of image_uniforms_batch is image_uniforms of sample_indices[b], on both of its
    paths (a few blocks on Python ints, more through numpy), in any order of indices."""
    indices = [5, 0, 2**32 - 1, 5, 123456]
    for seed in (0, 2**64 - 1):
        for stream in (rng.Stream.PARAMS, rng.Stream.KERNEL, rng.Stream.TRAJECTORY):
            for count in (0, 3, 9, 257):
                got = rng.image_uniforms_batch(seed, indices, stream, count)
                assert got.shape == (len(indices), count) and got.dtype == np.float64
                for row, index in zip(got, indices, strict=True):
                    assert np.array_equal(row, rng.image_uniforms(seed, index, stream, count))
    with pytest.raises(ValueError, match="sample_index"):
        rng.image_uniforms_batch(0, [1, 2**32], rng.Stream.PARAMS, 4)


@pytest.mark.parametrize("mode", ["average", "kernel", "trajectory"])
def test_parameters_drawn_from_batch_uniforms_equal_those_drawn_alone(mode):
    from gpu_blur.cameras import get_camera
    from gpu_blur.params import batch_uniforms, draw_params
    from gpu_blur.planning import plan
    from gpu_blur.scene import scene_from_dict

    scene = scene_from_dict({"blur": {"mode": mode}, "noise": {"model": "poisson-gaussian"},
                             "output": {"jpeg_quality": [60, 90]}})
    p, camera = plan(scene, size=(40, 60)), get_camera("a7r3")
    indices = [3, 0, 9]
    for index, uniforms in zip(indices, batch_uniforms(scene, seed=7, sample_indices=indices),
                               strict=True):
        alone = draw_params(scene, p, camera, seed=7, sample_index=index, image_shape=(40, 60))
        batched = draw_params(scene, p, camera, seed=7, sample_index=index,
                              image_shape=(40, 60), uniforms=uniforms)
        assert alone.keys() == batched.keys()
        for name, value in alone.items():
            assert np.array_equal(batched[name], value), name


def test_philox_over_several_chunks_equals_the_one_counter_computation():
    """Counters and per-counter keys across chunk boundaries give each counter's own words."""
    generator = np.random.default_rng(11)
    count = 2 * rng.PHILOX_CHUNK + 5
    counter = generator.integers(0, 2**32, (count, 4), dtype=np.uint64)
    keys = generator.integers(0, 2**32, (count, 2), dtype=np.uint64)
    one_key = rng.philox4x32(counter, keys[0])
    per_counter = rng.philox4x32(counter.reshape(count, 1, 4), keys.reshape(count, 1, 2))
    assert per_counter.shape == (count, 1, 4)
    edges = [0, 1, rng.PHILOX_CHUNK - 1, rng.PHILOX_CHUNK, 2 * rng.PHILOX_CHUNK, count - 1]
    for i in edges:
        c = [int(v) for v in counter[i]]
        assert tuple(one_key[i]) == rng._philox4x32_ints(*c, *(int(k) for k in keys[0]))
        assert tuple(per_counter[i, 0]) == rng._philox4x32_ints(*c, *(int(k) for k in keys[i]))


@pytest.mark.parametrize("normal_above", [None, 100.0])
def test_poisson_in_chunks_of_pixels_equals_the_whole_image_bit_for_bit(monkeypatch,
                                                                        normal_above):
    generator = np.random.default_rng(12)
    rate = generator.uniform(0.0, 500.0, (37, 53))
    rate[:5] = generator.uniform(0.0, 9.9, (5, 53))  # inversion
    rate[5, :7] = 0.0
    y, x = np.arange(37)[:, None] + 1000, np.arange(53)[None, :]
    monkeypatch.setattr(poisson_counts, "POISSON_CHUNK", 10**9)
    whole = poisson_counts.poisson(rate, 3, 9, y, x, normal_above=normal_above)
    monkeypatch.setattr(poisson_counts, "POISSON_CHUNK", 97)  # chunks that end mid-row
    chunked = poisson_counts.poisson(rate, 3, 9, y, x, normal_above=normal_above)
    assert np.array_equal(chunked, whole)
