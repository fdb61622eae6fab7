"""The draws against gpu_blur.reference.rng, in both kernel languages.

OpenCL (kernels/opencl/include/gb_random.h), three builds: ``float32`` (real = float, the
samplers in double because the device has cl_khr_fp64), ``float64`` (real = double) and
``float32-nofp64`` (float throughout, what a device without cl_khr_fp64 runs). Warp
(gpu_blur/warp_kernels/random.py): the samplers in float64, built with ``fuse_fp=False``. The
probes are in tests/device_functions/random.cl and random_warp.py. Measured numbers go to the
test report (``record_property``) and, with ``-s``, to stdout.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import KNOWN_ANSWERS, report
from device_functions import target_fixture, target_specs

from gpu_blur.reference import poisson_counts, rng
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, tolerance, z_mean, z_var

SEED = 0x5EED_CAFE_F00D_1234
TARGETS = target_specs("random")


program = target_fixture(TARGETS)


# --------------------------------------------------------------------------------------------
# Philox, words and uniforms: bitwise
# --------------------------------------------------------------------------------------------

#: Random123 kat_vectors, philox4x32 10 rounds: (counter, key, expected).
KNOWN_ANSWERS_10 = [(c, k, e) for rounds, c, k, e in KNOWN_ANSWERS if rounds == 10]


def test_philox_matches_random123_known_answers_and_reference(program):
    n = 4096
    gen = np.random.default_rng(3)
    counters = gen.integers(0, 2**32, size=(n, 4), dtype=np.uint32)
    keys = gen.integers(0, 2**32, size=(n, 2), dtype=np.uint32)
    for i, (counter, key, _) in enumerate(KNOWN_ANSWERS_10):
        counters[i], keys[i] = counter, key
    (out,) = program.run("t_philox", n, [counters, keys], [((n, 4), np.uint32)])
    for i, (_, _, expected) in enumerate(KNOWN_ANSWERS_10):
        assert [hex(v) for v in out[i]] == [hex(v) for v in expected]
    np.testing.assert_array_equal(out, rng.philox4x32(counters, keys))


PIXEL_DRAWS = [
    (0, 0, Stream.SHOT_NOISE, 0),
    (SEED, 17, Stream.READ_NOISE, 1),
    (2**32, 1, Stream.SRGB_NOISE, 3),
    (0x1_0000_0001, 123_456, Stream.SHOT_NOISE, 77),
    (2**64 - 1, 2**32 - 1, Stream.SRGB_NOISE, 2**24 - 1),
]


@pytest.mark.parametrize(("seed", "sample_index", "stream", "round_"), PIXEL_DRAWS)
def test_pixel_bits_and_uniforms_are_bitwise_equal(program, seed, sample_index, stream, round_):
    n = 100_000
    gen = np.random.default_rng(seed % 1000 + round_)
    xs = gen.integers(0, 2**32, n, dtype=np.uint32)
    ys = gen.integers(0, 2**32, n, dtype=np.uint32)
    xs[:4], ys[:4] = [0, 2**32 - 1, 0, 2**32 - 1], [0, 0, 2**32 - 1, 2**32 - 1]
    xs[4:1004] = np.arange(1000)  # a row of neighbours
    bits, u = program.run(
        "t_pixel_uniforms",
        n,
        [*program.key(seed), np.uint32(sample_index), np.uint32(stream), np.uint32(round_), xs,
         ys],
        [((n, 4), np.uint32), ((n, 4), program.real)],
    )  # fmt: skip
    np.testing.assert_array_equal(bits, rng.pixel_bits(seed, sample_index, stream, ys, xs, round_))
    expected = rng.pixel_uniforms(seed, sample_index, stream, ys, xs, round_)
    np.testing.assert_array_equal(u.astype(np.float64), expected)


def test_uniform_is_exact_for_every_23_bit_value_and_both_ends(program):
    top = np.arange(2**23, dtype=np.uint32) << np.uint32(9)
    low = np.random.default_rng(4).integers(0, 2**9, top.size, dtype=np.uint32)
    words = np.concatenate([top | low, np.array([0, 0x1FF, 0xFFFFFE00, 0xFFFFFFFF], np.uint32)])
    (u,) = program.run("t_uniform", words.size, [words], [(words.shape, program.real)])
    np.testing.assert_array_equal(u.astype(np.float64), rng.uniform_from_bits(words))
    if program.real != np.float32:  # exact in float32
        np.testing.assert_array_equal(u.astype(np.float32).astype(program.real), u)
    assert u[-4] == 2.0**-24 and u[-1] == 1.0 - 2.0**-24


def test_warp_stream_constants_mirror_rng_stream():
    wr = pytest.importorskip("gpu_blur.warp_kernels.random")
    for stream in Stream:
        constant = getattr(wr, stream.name)
        assert int(getattr(constant, "value", constant)) == int(stream)


# --------------------------------------------------------------------------------------------
# Normals and log(k!)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("seed", "sample_index", "stream"),
    [(SEED, 11, Stream.READ_NOISE), (2**40 + 7, 3, Stream.SRGB_NOISE),
     (2**40 + 7, 2**32 - 1, Stream.SRGB_NOISE)],
)  # fmt: skip
def test_pixel_normals_match_reference(program, record_property, seed, sample_index, stream):
    rows, cols, count = 200, 500, 6  # normals 4 and 5 come from round 1
    y0, x0 = 1_000, 70_000
    ys, xs = (a.reshape(-1).astype(np.uint32) for a in np.mgrid[y0 : y0 + rows, x0 : x0 + cols])
    (z,) = program.run(
        "t_pixel_normals",
        xs.size,
        [*program.key(seed), np.uint32(sample_index), np.uint32(stream), np.uint32(count), xs,
         ys],
        [((xs.size, count), program.real)],
    )  # fmt: skip
    expected = rng.pixel_normals(seed, sample_index, stream, ys, xs, count)
    report(record_property, f"normal_max_abs_error[{program}]", np.abs(z - expected).max())
    assert_close(z, expected, "normal", program.lang, program.build)


def test_box_muller_at_extreme_and_random_uniforms(program, record_property):
    ends = np.array([0, 0x1FF, 0x80000000, 0xFFFFFE00, 0xFFFFFFFF], np.uint32)
    pairs = np.stack(np.meshgrid(ends, ends, indexing="ij"), axis=-1).reshape(-1, 2)
    gen = np.random.default_rng(6)
    words = np.concatenate([pairs, gen.integers(0, 2**32, (50_000, 2), dtype=np.uint32)])
    (z,) = program.run("t_box_muller", words.shape[0], [words], [(words.shape, program.real)])
    u = rng.uniform_from_bits(words)
    expected = np.stack(rng.box_muller(u[:, 0], u[:, 1]), axis=-1)
    report(record_property, f"box_muller_max_abs_error[{program}]", np.abs(z - expected).max())
    assert_close(z, expected, "normal", program.lang, program.build)


def test_log_factorial_matches_reference(program, record_property):
    k = np.concatenate([np.arange(0, 3000), np.round(np.logspace(np.log10(3000), 12, 500))])
    k = k.astype(program.wide)
    (out,) = program.run("t_log_factorial", k.size, [k], [(k.shape, program.wide)])
    expected = poisson_counts.log_factorial(k.astype(np.float64))
    np.testing.assert_array_equal(out[:16], expected[:16].astype(program.wide))
    rel = np.abs(out - expected)[16:] / expected[16:]
    report(record_property, f"log_factorial_max_rel_error[{program}]", rel.max())
    assert_close(out, expected, "log_factorial", program.lang, program.build)


# --------------------------------------------------------------------------------------------
# Poisson
# --------------------------------------------------------------------------------------------

POISSON_ROWS, POISSON_COLS = 200, 500  # 1e5 pixels per rate
POISSON_ORIGIN = (3, 1_000)
#: The last rate below 10 in the build's type (the last inversion rate).
BELOW_10 = "below 10"
#: Rates as asked; both sides get them rounded to the build's type.
POISSON_RATES = [0.0, 1e-12, 0.5, 3.0, 9.99, BELOW_10, 10.0, 10.01, 15.0, 100.0, 1e4, 1e7]
SWEEP_RATES = np.logspace(-3, 7, 41)
SWEEP_ROWS = 20_000


def poisson_rate(rate, real) -> float:
    """``rate`` rounded to ``real``, or the last one below 10 in ``real``."""
    if rate == BELOW_10:
        return float(np.nextafter(real.type(10.0), real.type(0.0)))
    return float(real.type(rate))


def poisson_grid(rows, cols, origin=(0, 0)):
    ys, xs = np.mgrid[origin[0] : origin[0] + rows, origin[1] : origin[1] + cols]
    return ys.astype(np.uint32), xs.astype(np.uint32)


@functools.cache
def reference_poisson(rate: float, sample_index: int) -> np.ndarray:
    """poisson_counts.poisson on the fixed grid at one rate (cached across targets)."""
    ys, xs = poisson_grid(POISSON_ROWS, POISSON_COLS, POISSON_ORIGIN)
    return poisson_counts.poisson(np.full(ys.shape, rate), SEED, sample_index, ys, xs)


@functools.cache
def reference_sweep(real: np.dtype) -> np.ndarray:
    ys, xs = poisson_grid(SWEEP_ROWS, SWEEP_RATES.size)
    rates = np.broadcast_to(SWEEP_RATES.astype(real).astype(np.float64), ys.shape)
    return poisson_counts.poisson(rates, SEED, 23, ys, xs)


def device_poisson(program, rates, ys, xs, sample_index, seed=SEED):
    rates = np.asarray(rates, dtype=np.float64)
    (out,) = program.run(
        "t_poisson",
        rates.size,
        [*program.key(seed), np.uint32(sample_index), rates.astype(program.real),
         np.broadcast_to(xs, rates.shape), np.broadcast_to(ys, rates.shape)],
        [(rates.shape, program.real)],
    )  # fmt: skip
    return out.astype(np.float64)


def skip_float_ptrs(program, rate):
    if program.build == "float32-nofp64" and rate >= poisson_counts.POISSON_PTRS_MIN_RATE:
        pytest.skip("float PTRS is not expected to repeat the reference (statistics test it)")


@pytest.mark.parametrize("rate", POISSON_RATES, ids=lambda r: r if isinstance(r, str) else
                         f"{r:.9g}")  # fmt: skip
def test_poisson_counts_equal_reference(program, record_property, rate):
    rate = poisson_rate(rate, program.real)
    skip_float_ptrs(program, rate)
    ys, xs = poisson_grid(POISSON_ROWS, POISSON_COLS, POISSON_ORIGIN)
    counts = device_poisson(program, np.full(ys.shape, rate), ys, xs, sample_index=41)
    expected = reference_poisson(rate, 41)
    differing = np.count_nonzero(counts != expected) / counts.size
    report(record_property, f"poisson_differing_fraction[{program}, {rate:.17g}]", differing)
    assert_close(differing, 0.0, "poisson_agreement", program.lang, program.build)


def test_poisson_counts_equal_reference_over_log_spaced_rates(program, record_property):
    ys, xs = poisson_grid(SWEEP_ROWS, SWEEP_RATES.size)
    rates = np.broadcast_to(SWEEP_RATES.astype(program.real), ys.shape)
    counts = device_poisson(program, rates, ys, xs, sample_index=23)
    expected = reference_sweep(program.real)
    columns = slice(None)
    if program.build == "float32-nofp64":
        columns = SWEEP_RATES.astype(program.real) < poisson_counts.POISSON_PTRS_MIN_RATE
    differ = counts[:, columns] != expected[:, columns]
    report(record_property, f"poisson_sweep_differing_fraction[{program}]", differ.mean())
    report(record_property, f"poisson_sweep_worst_rate_fraction[{program}]",
           differ.mean(axis=0).max())  # fmt: skip
    assert_close(differ.mean(), 0.0, "poisson_agreement", program.lang, program.build)


def test_poisson_edge_rates(program):
    rates = np.array([-1.0, -0.0, -1e30, np.nan, np.inf, -np.inf, 0.0])
    ys, xs = np.zeros(rates.size, np.uint32), np.arange(rates.size, dtype=np.uint32)
    counts = device_poisson(program, rates, ys, xs, sample_index=0)
    assert np.array_equal(counts[[0, 1, 2, 5, 6]], np.zeros(5))
    assert not np.signbit(counts[[0, 1, 2, 5, 6]]).any()
    assert np.isnan(counts[3]) and counts[4] == np.inf


@pytest.mark.parametrize("rate", [0.5, 3.0, 9.99, 10.0, 30.0, 1e4, 1e7])
def test_poisson_mean_and_variance_match_rate(program, rate):
    ys, xs = poisson_grid(400, 500)
    counts = device_poisson(program, np.full(ys.shape, rate), ys, xs, sample_index=97)
    assert np.all(counts == np.round(counts)) and counts.min() >= 0
    # Poisson: variance = rate, fourth central moment = rate * (1 + 3 rate); 5-sigma bounds.
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, rate * (1.0 + 3.0 * rate))) < 5.0


@pytest.mark.parametrize("spec", TARGETS, ids=str)
def test_tolerance_rows_exist_for_every_build(spec):
    for stage in ("normal", "log_factorial", "poisson_agreement"):
        tolerance(stage, spec.lang, spec.build)
