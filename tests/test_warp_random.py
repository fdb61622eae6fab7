"""Warp draws (gpu_blur/warp_kernels/random.py) against gpu_blur.reference.rng.

The test kernels below call the ``@wp.func`` functions on Warp's "cpu" device and, where CUDA is
available, on "cuda:0". This module is built with ``fuse_fp=False`` (no a * b + c contraction),
as random.py asks of modules that must repeat the reference's Poisson counts. Measured numbers
go to the test report (``record_property``) and, with ``-s``, to stdout.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import report
from conftest import warp_key_args as key_args
from conftest import warp_launch as launch

from gpu_blur.reference import rng
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, tolerance, z_mean, z_var

wp = pytest.importorskip("warp")
wp.config.quiet = True

from gpu_blur.warp_kernels import random as wr  # noqa: E402  (needs warp, checked above)

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

SEED = 0x5EED_CAFE_F00D_1234
DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


# --------------------------------------------------------------------------------------------
# Test kernels
# --------------------------------------------------------------------------------------------


@wp.kernel
def t_philox(
    counters: wp.array(dtype=wp.vec4ui),
    keys: wp.array(dtype=wp.vec2ui),
    out: wp.array(dtype=wp.vec4ui),
):
    i = wp.tid()
    key = keys[i]
    out[i] = wr.philox4x32(counters[i], key[0], key[1])


@wp.kernel
def t_pixel_uniforms(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    stream: wp.uint32,
    round: wp.uint32,
    xs: wp.array(dtype=wp.uint32),
    ys: wp.array(dtype=wp.uint32),
    bits: wp.array(dtype=wp.vec4ui),
    u: wp.array2d(dtype=wp.float64),
):
    i = wp.tid()
    b = wr.pixel_bits(key0, key1, sample_index, stream, xs[i], ys[i], round)
    bits[i] = b
    for j in range(4):
        u[i, j] = wr.uniform(b[j])


@wp.kernel
def t_uniform(words: wp.array(dtype=wp.uint32), u: wp.array(dtype=wp.float64)):
    i = wp.tid()
    u[i] = wr.uniform(words[i])


@wp.kernel
def t_box_muller(words: wp.array(dtype=wp.vec2ui), z: wp.array(dtype=wp.vec2d)):
    i = wp.tid()
    w = words[i]
    z[i] = wr.box_muller(wr.uniform(w[0]), wr.uniform(w[1]))


@wp.kernel
def t_pixel_normals(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    stream: wp.uint32,
    xs: wp.array(dtype=wp.uint32),
    ys: wp.array(dtype=wp.uint32),
    z: wp.array2d(dtype=wp.float64),
):
    i = wp.tid()
    for j in range(z.shape[1]):
        z[i, j] = wr.pixel_normal(key0, key1, sample_index, stream, xs[i], ys[i], wp.uint32(j))


@wp.kernel
def t_log_factorial(k: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wr.log_factorial(k[i])


@wp.kernel
def t_poisson(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    rates: wp.array(dtype=wp.float64),
    xs: wp.array(dtype=wp.uint32),
    ys: wp.array(dtype=wp.uint32),
    out: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    out[i] = wr.poisson(rates[i], key0, key1, sample_index, xs[i], ys[i])


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=DEVICES)
def device(request):
    return request.param


# --------------------------------------------------------------------------------------------
# Philox, words and uniforms: bitwise
# --------------------------------------------------------------------------------------------

#: Random123 kat_vectors, philox4x32 10 rounds (tests/test_rng.py's KNOWN_ANSWERS).
KNOWN_ANSWERS_10 = [
    ((0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    (
        (0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF),
        (0xFFFFFFFF, 0xFFFFFFFF),
        (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD),
    ),
    (
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xA4093822, 0x299F31D0),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1),
    ),
]


def test_philox_matches_random123_known_answers_and_reference(device):
    n = 4096
    gen = np.random.default_rng(3)
    counters = gen.integers(0, 2**32, size=(n, 4), dtype=np.uint32)
    keys = gen.integers(0, 2**32, size=(n, 2), dtype=np.uint32)
    for i, (counter, key, _) in enumerate(KNOWN_ANSWERS_10):
        counters[i], keys[i] = counter, key
    (out,) = launch(
        t_philox, device, n, [], [(counters, wp.vec4ui), (keys, wp.vec2ui)], [(n, wp.vec4ui)]
    )
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
def test_pixel_bits_and_uniforms_are_bitwise_equal(device, seed, sample_index, stream, round_):
    n = 100_000
    gen = np.random.default_rng(seed % 1000 + round_)
    xs = gen.integers(0, 2**32, n, dtype=np.uint32)
    ys = gen.integers(0, 2**32, n, dtype=np.uint32)
    xs[:4], ys[:4] = [0, 2**32 - 1, 0, 2**32 - 1], [0, 0, 2**32 - 1, 2**32 - 1]
    xs[4:1004] = np.arange(1000)  # a row of neighbours
    bits, u = launch(
        t_pixel_uniforms,
        device,
        n,
        [*key_args(seed), wp.uint32(sample_index), wp.uint32(stream), wp.uint32(round_)],
        [(xs, wp.uint32), (ys, wp.uint32)],
        [(n, wp.vec4ui), ((n, 4), wp.float64)],
    )
    np.testing.assert_array_equal(bits, rng.pixel_bits(seed, sample_index, stream, ys, xs, round_))
    np.testing.assert_array_equal(u, rng.pixel_uniforms(seed, sample_index, stream, ys, xs, round_))


def test_uniform_is_exact_for_every_23_bit_value_and_both_ends(device):
    top = np.arange(2**23, dtype=np.uint32) << np.uint32(9)
    low = np.random.default_rng(4).integers(0, 2**9, top.size, dtype=np.uint32)
    words = np.concatenate([top | low, np.array([0, 0x1FF, 0xFFFFFE00, 0xFFFFFFFF], np.uint32)])
    (u,) = launch(
        t_uniform, device, words.size, [], [(words, wp.uint32)], [(words.size, wp.float64)]
    )
    np.testing.assert_array_equal(u, rng.uniform_from_bits(words))
    np.testing.assert_array_equal(u.astype(np.float32).astype(np.float64), u)  # exact in float32
    assert u[-4] == 2.0**-24 and u[-1] == 1.0 - 2.0**-24


def test_stream_constants_mirror_rng_stream():
    for stream in Stream:
        constant = getattr(wr, stream.name)
        assert int(getattr(constant, "value", constant)) == int(stream)


# --------------------------------------------------------------------------------------------
# Normals and log(k!)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("seed", "sample_index", "stream"),
    [(SEED, 11, Stream.READ_NOISE), (2**40 + 7, 2**32 - 1, Stream.SRGB_NOISE)],
)
def test_pixel_normals_match_reference(device, record_property, seed, sample_index, stream):
    rows, cols, count = 200, 500, 6  # normals 4 and 5 come from round 1
    y0, x0 = 1_000, 70_000
    ys, xs = (a.reshape(-1).astype(np.uint32) for a in np.mgrid[y0 : y0 + rows, x0 : x0 + cols])
    (z,) = launch(
        t_pixel_normals,
        device,
        xs.size,
        [*key_args(seed), wp.uint32(sample_index), wp.uint32(stream)],
        [(xs, wp.uint32), (ys, wp.uint32)],
        [((xs.size, count), wp.float64)],
    )
    expected = rng.pixel_normals(seed, sample_index, stream, ys, xs, count)
    report(record_property, f"normal_max_abs_error[{device}]", np.abs(z - expected).max())
    assert_close(z, expected, "normal", "warp", "float64")


def test_box_muller_at_extreme_and_random_uniforms(device, record_property):
    ends = np.array([0, 0x1FF, 0x80000000, 0xFFFFFE00, 0xFFFFFFFF], np.uint32)
    pairs = np.stack(np.meshgrid(ends, ends, indexing="ij"), axis=-1).reshape(-1, 2)
    gen = np.random.default_rng(6)
    words = np.concatenate([pairs, gen.integers(0, 2**32, (50_000, 2), dtype=np.uint32)])
    n = words.shape[0]
    (z,) = launch(t_box_muller, device, n, [], [(words, wp.vec2ui)], [(n, wp.vec2d)])
    u = rng.uniform_from_bits(words)
    expected = np.stack(rng.box_muller(u[:, 0], u[:, 1]), axis=-1)
    report(record_property, f"box_muller_max_abs_error[{device}]", np.abs(z - expected).max())
    assert_close(z, expected, "normal", "warp", "float64")


def test_log_factorial_matches_reference(device, record_property):
    k = np.concatenate([np.arange(0, 3000), np.round(np.logspace(np.log10(3000), 12, 500))])
    k = k.astype(np.float64)
    (out,) = launch(t_log_factorial, device, k.size, [], [(k, wp.float64)], [(k.size, wp.float64)])
    expected = rng.log_factorial(k)
    np.testing.assert_array_equal(out[:16], expected[:16])
    rel = np.abs(out - expected)[16:] / expected[16:]
    report(record_property, f"log_factorial_max_rel_error[{device}]", rel.max())
    assert_close(out, expected, "log_factorial", "warp", "float64")


# --------------------------------------------------------------------------------------------
# Poisson
# --------------------------------------------------------------------------------------------

POISSON_ROWS, POISSON_COLS = 200, 500  # 1e5 pixels per rate
POISSON_ORIGIN = (3, 1_000)
POISSON_RATES = [
    0.0,
    1e-12,
    0.5,
    3.0,
    9.99,
    float(np.nextafter(10.0, 0.0)),  # the last inversion rate
    10.0,
    10.01,
    15.0,
    100.0,
    1e4,
    1e7,
]
SWEEP_RATES = np.logspace(-3, 7, 41)
SWEEP_ROWS = 20_000


def poisson_grid(rows, cols, origin=(0, 0)):
    ys, xs = np.mgrid[origin[0] : origin[0] + rows, origin[1] : origin[1] + cols]
    return ys.astype(np.uint32), xs.astype(np.uint32)


@functools.cache
def reference_poisson(rate: float, sample_index: int) -> np.ndarray:
    """rng.poisson on the fixed grid at one rate (cached across devices)."""
    ys, xs = poisson_grid(POISSON_ROWS, POISSON_COLS, POISSON_ORIGIN)
    return rng.poisson(np.full(ys.shape, rate), SEED, sample_index, ys, xs)


@functools.cache
def reference_sweep() -> np.ndarray:
    ys, xs = poisson_grid(SWEEP_ROWS, SWEEP_RATES.size)
    return rng.poisson(np.broadcast_to(SWEEP_RATES, ys.shape), SEED, 23, ys, xs)


def device_poisson(device, rates, ys, xs, sample_index, seed=SEED):
    rates = np.asarray(rates, dtype=np.float64)
    (out,) = launch(
        t_poisson,
        device,
        rates.size,
        [*key_args(seed), wp.uint32(sample_index)],
        [
            (rates.reshape(-1), wp.float64),
            (np.broadcast_to(xs, rates.shape).reshape(-1), wp.uint32),
            (np.broadcast_to(ys, rates.shape).reshape(-1), wp.uint32),
        ],
        [(rates.size, wp.float64)],
    )
    return out.reshape(rates.shape)


@pytest.mark.parametrize("rate", POISSON_RATES, ids=lambda r: f"{r:.17g}")
def test_poisson_counts_equal_reference(device, record_property, rate):
    ys, xs = poisson_grid(POISSON_ROWS, POISSON_COLS, POISSON_ORIGIN)
    counts = device_poisson(device, np.full(ys.shape, rate), ys, xs, sample_index=41)
    expected = reference_poisson(rate, 41)
    differing = np.count_nonzero(counts != expected) / counts.size
    report(record_property, f"poisson_differing_fraction[{device}, {rate:.17g}]", differing)
    assert_close(differing, 0.0, "poisson_agreement", "warp", "float64")


def test_poisson_counts_equal_reference_over_log_spaced_rates(device, record_property):
    ys, xs = poisson_grid(SWEEP_ROWS, SWEEP_RATES.size)
    rates = np.broadcast_to(SWEEP_RATES, ys.shape)
    counts = device_poisson(device, rates, ys, xs, sample_index=23)
    differ = counts != reference_sweep()
    report(record_property, f"poisson_sweep_differing_fraction[{device}]", differ.mean())
    report(record_property, f"poisson_sweep_worst_rate_fraction[{device}]", differ.mean(0).max())
    assert_close(differ.mean(), 0.0, "poisson_agreement", "warp", "float64")


def test_poisson_edge_rates(device):
    rates = np.array([-1.0, -0.0, -1e30, np.nan, np.inf, -np.inf, 0.0])
    ys, xs = np.zeros(rates.size, np.uint32), np.arange(rates.size, dtype=np.uint32)
    counts = device_poisson(device, rates, ys, xs, sample_index=0)
    assert np.array_equal(counts[[0, 1, 2, 5, 6]], np.zeros(5))
    assert not np.signbit(counts[[0, 1, 2, 5, 6]]).any()
    assert np.isnan(counts[3]) and counts[4] == np.inf


@pytest.mark.parametrize("rate", [0.5, 3.0, 9.99, 10.0, 30.0, 1e4, 1e7])
def test_poisson_mean_and_variance_match_rate(device, rate):
    ys, xs = poisson_grid(400, 500)
    counts = device_poisson(device, np.full(ys.shape, rate), ys, xs, sample_index=97)
    assert np.all(counts == np.round(counts)) and counts.min() >= 0
    # Poisson: variance = rate, fourth central moment = rate * (1 + 3 rate); 5-sigma bounds.
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, rate * (1.0 + 3.0 * rate))) < 5.0


def test_tolerance_rows_exist():
    for stage in ("normal", "log_factorial", "poisson_agreement"):
        tolerance(stage, "warp", "float64")
