"""OpenCL draws (kernels/opencl/include/gb_random.h) against gpu_blur.reference.rng.

Three builds of the same test kernels: ``float32`` (real = float, the samplers in double because
the device has cl_khr_fp64), ``float64`` (real = double) and ``float32-nofp64`` (float
throughout, what a device without cl_khr_fp64 runs). Measured numbers go to the test report
(``record_property``) and, with ``-s``, to stdout.
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import opencl_key_arg as key_arg
from conftest import report

from gpu_blur.reference import rng
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, tolerance, z_mean, z_var

cl = pytest.importorskip("pyopencl")

REPO = Path(__file__).resolve().parents[1]
INCLUDE = REPO / "kernels" / "opencl" / "include"
SEED = 0x5EED_CAFE_F00D_1234

TEST_KERNELS = r"""
#include "gb_random.h"

__kernel void t_philox(__global const uint *counters, __global const uint *keys,
                       __global uint *out)
{
    const size_t i = get_global_id(0);
    vstore4(gb_philox(vload4(i, counters), vload2(i, keys)), i, out);
}

__kernel void t_pixel_uniforms(const uint2 key, const uint sample_index, const uint stream,
                               const uint round, __global const uint *xs,
                               __global const uint *ys, __global uint *bits, __global real *u)
{
    const size_t i = get_global_id(0);
    const uint4 b = gb_pixel_bits(key, sample_index, stream, xs[i], ys[i], round);
    vstore4(b, i, bits);
    u[4 * i] = gb_uniform(b.x);
    u[4 * i + 1] = gb_uniform(b.y);
    u[4 * i + 2] = gb_uniform(b.z);
    u[4 * i + 3] = gb_uniform(b.w);
}

__kernel void t_uniform(__global const uint *words, __global real *u)
{
    const size_t i = get_global_id(0);
    u[i] = gb_uniform(words[i]);
}

__kernel void t_box_muller(__global const uint *words, __global real *z)
{
    const size_t i = get_global_id(0);
    real z_cos, z_sin;
    gb_box_muller(gb_uniform(words[2 * i]), gb_uniform(words[2 * i + 1]), &z_cos, &z_sin);
    z[2 * i] = z_cos;
    z[2 * i + 1] = z_sin;
}

__kernel void t_pixel_normals(const uint2 key, const uint sample_index, const uint stream,
                              const uint count, __global const uint *xs,
                              __global const uint *ys, __global real *z)
{
    const size_t i = get_global_id(0);
    for (uint j = 0; j < count; ++j)
        z[i * count + j] = gb_pixel_normal(key, sample_index, stream, xs[i], ys[i], j);
}

__kernel void t_log_factorial(__global const gb_wide *k, __global gb_wide *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_log_factorial(k[i]);
}

__kernel void t_poisson(const uint2 key, const uint sample_index, __global const real *rate,
                        __global const uint *xs, __global const uint *ys, __global real *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_poisson(rate[i], key, sample_index, xs[i], ys[i]);
}
"""

#: build -> (real dtype, wide dtype, needs cl_khr_fp64, -D options)
BUILDS = {
    "float32": (np.float32, np.float64, True, ["-DGB_HAS_FP64"]),
    "float64": (np.float64, np.float64, True, ["-DGB_HAS_FP64", "-DGB_FP64"]),
    "float32-nofp64": (np.float32, np.float32, False, []),
}


# --------------------------------------------------------------------------------------------
# Device and programs
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def opencl_context(opencl_queue):
    _, context, queue = opencl_queue
    return context, queue


class Program:
    """The test kernels built one way, with helpers that run them on numpy arrays."""

    def __init__(self, context, queue, build: str):
        self.context = context  # pyopencl's queue alone does not keep its context alive
        self.queue = queue
        self.build = build
        self.real, self.wide, _, defines = BUILDS[build]
        options = ["-I", str(INCLUDE), "-I", str(Path(cl.__file__).parent / "cl"), *defines]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            program = cl.Program(self.context, TEST_KERNELS).build(options=options, cache_dir=False)
        self.kernels = {name: cl.Kernel(program, name) for name in program.kernel_names.split(";")}

    def _in(self, array):
        flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        return cl.Buffer(self.context, flags, hostbuf=np.ascontiguousarray(array))

    def _out(self, shape, dtype):
        out = np.empty(shape, dtype)
        return out, cl.Buffer(self.context, cl.mem_flags.WRITE_ONLY, max(out.nbytes, 1))

    def run(self, name, n, args, outputs):
        """Launch kernel ``name`` over ``n`` items; ``outputs`` are (shape, dtype) pairs."""
        results = [self._out(shape, dtype) for shape, dtype in outputs]
        converted = [self._in(a) if isinstance(a, np.ndarray) and a.ndim else a for a in args]
        self.kernels[name](self.queue, (n,), None, *converted, *(b for _, b in results))
        for out, buf in results:
            cl.enqueue_copy(self.queue, out, buf)
        self.queue.finish()
        return [out for out, _ in results]


@pytest.fixture(scope="module", params=list(BUILDS))
def program(request, opencl_context):
    build = request.param
    context, queue = opencl_context
    device = queue.device
    if BUILDS[build][2] and "cl_khr_fp64" not in device.extensions:
        pytest.skip(f"{device.name} has no cl_khr_fp64; the float32-nofp64 build covers it")
    return Program(context, queue, build)


# --------------------------------------------------------------------------------------------
# Philox, words and uniforms: bitwise
# --------------------------------------------------------------------------------------------


def test_philox_matches_reference_and_random123_known_answer(program):
    gen = np.random.default_rng(3)
    counters = gen.integers(0, 2**32, size=(4096, 4), dtype=np.uint32)
    keys = gen.integers(0, 2**32, size=(4096, 2), dtype=np.uint32)
    counters[:2] = [(0, 0, 0, 0), (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344)]
    keys[:2] = [(0, 0), (0xA4093822, 0x299F31D0)]
    (out,) = program.run("t_philox", 4096, [counters, keys], [((4096, 4), np.uint32)])
    np.testing.assert_array_equal(out, rng.philox4x32(counters, keys))
    # Random123 kat_vectors, philox4x32 10 rounds.
    assert [hex(v) for v in out[0]] == ["0x6627e8d5", "0xe169c58d", "0xbc57ac4c", "0x9b00dbd8"]
    assert [hex(v) for v in out[1]] == ["0xd16cfe09", "0x94fdcceb", "0x5001e420", "0x24126ea1"]


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
        [key_arg(seed), np.uint32(sample_index), np.uint32(stream), np.uint32(round_), xs, ys],
        [((n, 4), np.uint32), ((n, 4), program.real)],
    )
    np.testing.assert_array_equal(bits, rng.pixel_bits(seed, sample_index, stream, ys, xs, round_))
    expected = rng.pixel_uniforms(seed, sample_index, stream, ys, xs, round_)
    np.testing.assert_array_equal(u.astype(np.float64), expected)


def test_uniform_is_exact_for_every_23_bit_value_and_both_ends(program):
    top = np.arange(2**23, dtype=np.uint32) << np.uint32(9)
    low = np.random.default_rng(4).integers(0, 2**9, top.size, dtype=np.uint32)
    words = np.concatenate([top | low, np.array([0, 0x1FF, 0xFFFFFE00, 0xFFFFFFFF], np.uint32)])
    (u,) = program.run("t_uniform", words.size, [words], [(words.shape, program.real)])
    expected = rng.uniform_from_bits(words)
    np.testing.assert_array_equal(u.astype(np.float64), expected)
    assert u[-4] == 2.0**-24 and u[-1] == 1.0 - 2.0**-24


# --------------------------------------------------------------------------------------------
# Normals and log(k!)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("seed", "sample_index", "stream"),
    [(SEED, 11, Stream.READ_NOISE), (2**40 + 7, 3, Stream.SRGB_NOISE)],
)
def test_pixel_normals_match_reference(program, record_property, seed, sample_index, stream):
    rows, cols, count = 200, 500, 6  # normals 4 and 5 come from round 1
    y0, x0 = 1_000, 70_000
    ys, xs = (a.reshape(-1).astype(np.uint32) for a in np.mgrid[y0 : y0 + rows, x0 : x0 + cols])
    (z,) = program.run(
        "t_pixel_normals",
        xs.size,
        [key_arg(seed), np.uint32(sample_index), np.uint32(stream), np.uint32(count), xs, ys],
        [((xs.size, count), program.real)],
    )
    expected = rng.pixel_normals(seed, sample_index, stream, ys, xs, count)
    report(record_property, f"normal_max_abs_error[{program.build}]", np.abs(z - expected).max())
    assert_close(z, expected, "normal", "opencl", program.build)


def test_box_muller_at_extreme_and_random_uniforms(program, record_property):
    ends = np.array([0, 0x1FF, 0x80000000, 0xFFFFFE00, 0xFFFFFFFF], np.uint32)
    pairs = np.stack(np.meshgrid(ends, ends, indexing="ij"), axis=-1).reshape(-1, 2)
    gen = np.random.default_rng(6)
    words = np.concatenate([pairs, gen.integers(0, 2**32, (50_000, 2), dtype=np.uint32)])
    (z,) = program.run("t_box_muller", words.shape[0], [words], [(words.shape, program.real)])
    u = rng.uniform_from_bits(words)
    expected = np.stack(rng.box_muller(u[:, 0], u[:, 1]), axis=-1)
    error = np.abs(z - expected).max()
    report(record_property, f"box_muller_max_abs_error[{program.build}]", error)
    assert_close(z, expected, "normal", "opencl", program.build)


def test_log_factorial_matches_reference(program, record_property):
    k = np.concatenate([np.arange(0, 3000), np.round(np.logspace(np.log10(3000), 12, 500))]).astype(
        program.wide
    )
    (out,) = program.run("t_log_factorial", k.size, [k], [(k.shape, program.wide)])
    expected = rng.log_factorial(k.astype(np.float64))
    np.testing.assert_array_equal(out[:16], expected[:16].astype(program.wide))
    rel = np.abs(out - expected)[16:] / expected[16:]
    report(record_property, f"log_factorial_max_rel_error[{program.build}]", rel.max())
    assert_close(out, expected, "log_factorial", "opencl", program.build)


# --------------------------------------------------------------------------------------------
# Poisson
# --------------------------------------------------------------------------------------------

POISSON_ROWS, POISSON_COLS = 200, 500  # 1e5 pixels per rate
POISSON_ORIGIN = (3, 1_000)
#: Rates as asked; both sides get them rounded to float32 (exact in every build's real).
POISSON_RATES = [
    0.0,
    1e-12,
    0.5,
    3.0,
    9.99,
    float(np.nextafter(np.float32(10.0), np.float32(0.0))),
    10.0,
    10.01,
    15.0,
    100.0,
    1e4,
    1e7,
]
SWEEP_RATES = np.logspace(-3, 7, 41).astype(np.float32)
SWEEP_ROWS = 20_000


def poisson_grid(rows, cols, origin=(0, 0)):
    ys, xs = np.mgrid[origin[0] : origin[0] + rows, origin[1] : origin[1] + cols]
    return ys.astype(np.uint32), xs.astype(np.uint32)


@functools.cache
def reference_poisson(rate_bits: int, sample_index: int) -> np.ndarray:
    """rng.poisson on the fixed grid at one float32 rate (cached across the builds)."""
    rate = float(np.uint32(rate_bits).view(np.float32))
    ys, xs = poisson_grid(POISSON_ROWS, POISSON_COLS, POISSON_ORIGIN)
    return rng.poisson(np.full(ys.shape, rate), SEED, sample_index, ys, xs)


@functools.cache
def reference_sweep() -> np.ndarray:
    ys, xs = poisson_grid(SWEEP_ROWS, SWEEP_RATES.size)
    rates = np.broadcast_to(SWEEP_RATES.astype(np.float64), ys.shape)
    return rng.poisson(rates, SEED, 23, ys, xs)


def device_poisson(program, rates, ys, xs, sample_index, seed=SEED):
    (out,) = program.run(
        "t_poisson",
        rates.size,
        [
            key_arg(seed),
            np.uint32(sample_index),
            rates.astype(program.real).reshape(-1),
            xs.reshape(-1),
            ys.reshape(-1),
        ],
        [(rates.size, program.real)],
    )
    return out.astype(np.float64).reshape(rates.shape)


def skip_float_ptrs(program, rate):
    if program.build == "float32-nofp64" and rate >= rng.POISSON_PTRS_MIN_RATE:
        pytest.skip("float PTRS is not expected to repeat the reference (statistics test it)")


@pytest.mark.parametrize("rate", POISSON_RATES, ids=lambda r: f"{r:.9g}")
def test_poisson_counts_equal_reference(program, record_property, rate):
    rate32 = np.float32(rate)
    skip_float_ptrs(program, rate32)
    ys, xs = poisson_grid(POISSON_ROWS, POISSON_COLS, POISSON_ORIGIN)
    counts = device_poisson(program, np.full(ys.shape, rate32), ys, xs, sample_index=41)
    expected = reference_poisson(int(rate32.view(np.uint32)), 41)
    differing = np.count_nonzero(counts != expected) / counts.size
    report(record_property, f"poisson_differing_fraction[{program.build}, {rate:.9g}]", differing)
    assert_close(differing, 0.0, "poisson_agreement", "opencl", program.build)


def test_poisson_counts_equal_reference_over_log_spaced_rates(program, record_property):
    ys, xs = poisson_grid(SWEEP_ROWS, SWEEP_RATES.size)
    rates = np.broadcast_to(SWEEP_RATES, ys.shape)
    counts = device_poisson(program, rates, ys, xs, sample_index=23)
    expected = reference_sweep()
    columns = slice(None)
    if program.build == "float32-nofp64":
        columns = SWEEP_RATES < rng.POISSON_PTRS_MIN_RATE
    differ = counts[:, columns] != expected[:, columns]
    per_rate = differ.mean(axis=0)
    report(record_property, f"poisson_sweep_differing_fraction[{program.build}]", differ.mean())
    report(record_property, f"poisson_sweep_worst_rate_fraction[{program.build}]", per_rate.max())
    assert_close(differ.mean(), 0.0, "poisson_agreement", "opencl", program.build)


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


def test_tolerance_rows_exist_for_every_build():
    for build in BUILDS:
        for stage in ("normal", "log_factorial", "poisson_agreement"):
            tolerance(stage, "opencl", build)
