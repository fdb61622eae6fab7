"""The accuracy knobs in the OpenCL headers, device function by device function (issue 7).

* ``gb_poisson_normal_above`` (gb_random.h): the normal approximation of the Poisson counts above
  a threshold rate, against ``rng.poisson(..., normal_above=...)``, in the three builds of
  tests/test_opencl_random.py (float32 with double samplers, float64, float32 without fp64);
* resampled A7R3 tables through ``gb_lookup_crf`` (gb_pixel.h);
* ``GB_FAST_MATH`` (gb_math.h): native_ functions in the sRGB curves and the normals of float
  builds, against the reference within the tolerance table's "float32-fast" rows, and no change
  at all in double builds.

Measured numbers go to the test report (``record_property``) and, with ``-s``, to stdout.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import opencl_key_arg as key_arg
from conftest import report

from gpu_blur.reference import rng, transfer
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, z_mean, z_var

cl = pytest.importorskip("pyopencl")

INCLUDE = Path(__file__).resolve().parents[1] / "kernels" / "opencl" / "include"
SEED = 0xFEED_0007

TEST_KERNELS = r"""
#include "gb_random.h"
#include "gb_pixel.h"

__kernel void t_poisson(const uint2 key, const uint sample_index, __global const real *rate,
                        __global const uint *xs, __global const uint *ys, __global real *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_poisson(rate[i], key, sample_index, xs[i], ys[i]);
}

__kernel void t_poisson_normal_above(const uint2 key, const uint sample_index,
                                     const real normal_above, __global const real *rate,
                                     __global const uint *xs, __global const uint *ys,
                                     __global real *out)
{
    const size_t i = get_global_id(0);
    out[i] = gb_poisson_normal_above(rate[i], normal_above, key, sample_index, xs[i], ys[i]);
}

__kernel void t_pixel_normals(const uint2 key, const uint sample_index, const uint stream,
                              const uint count, __global const uint *xs,
                              __global const uint *ys, __global real *z)
{
    const size_t i = get_global_id(0);
    for (uint j = 0; j < count; ++j)
        z[i * count + j] = gb_pixel_normal(key, sample_index, stream, xs[i], ys[i], j);
}

__kernel void t_srgb(__global const real *x, __global real *linear, __global real *encoded)
{
    const size_t i = get_global_id(0);
    linear[i] = gb_srgb_to_linear(x[i]);
    encoded[i] = gb_linear_to_srgb(x[i]);
}

__kernel void t_lookup_crf(__global const real *x, __global const real *rendered, int n,
                           __global real *y)
{
    const size_t i = get_global_id(0);
    y[i] = gb_lookup_crf(x[i], rendered, n);
}
"""

#: build -> (real dtype, needs cl_khr_fp64, -D options); the names are the tolerance table's
#: dtype column.
BUILDS = {
    "float32": (np.float32, True, ["-DGB_HAS_FP64"]),
    "float64": (np.float64, True, ["-DGB_HAS_FP64", "-DGB_FP64"]),
    "float32-nofp64": (np.float32, False, []),
    "float32-fast": (np.float32, True, ["-DGB_HAS_FP64", "-DGB_FAST_MATH"]),
    "float64-fast": (np.float64, True, ["-DGB_HAS_FP64", "-DGB_FP64", "-DGB_FAST_MATH"]),
}
EXACT_BUILDS = ["float32", "float64", "float32-nofp64"]


class Program:
    """TEST_KERNELS built one way, with a helper that runs a kernel on numpy arrays."""

    def __init__(self, context, queue, build: str):
        self.context, self.queue, self.build = context, queue, build
        self.real, _, defines = BUILDS[build]
        options = ["-I", str(INCLUDE), "-I", str(Path(cl.__file__).parent / "cl"), *defines]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            program = cl.Program(context, TEST_KERNELS).build(options=options, cache_dir=False)
        self.kernels = {name: cl.Kernel(program, name) for name in program.kernel_names.split(";")}

    def run(self, name, n, args, outputs):
        """Launch kernel ``name`` over ``n`` items; ``outputs`` are (shape, dtype) pairs."""
        flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        converted = [cl.Buffer(self.context, flags, hostbuf=np.ascontiguousarray(a))
                     if isinstance(a, np.ndarray) and a.ndim else a for a in args]
        results = [np.empty(shape, dtype) for shape, dtype in outputs]
        buffers = [cl.Buffer(self.context, cl.mem_flags.WRITE_ONLY, max(r.nbytes, 1))
                   for r in results]
        self.kernels[name](self.queue, (n,), None, *converted, *buffers)
        for out, buf in zip(results, buffers, strict=True):
            cl.enqueue_copy(self.queue, out, buf)
        self.queue.finish()
        return results


_PROGRAMS: dict = {}


def program_for(build: str, opencl_queue) -> Program:
    """One build per session; skipped where the device lacks the fp64 it needs."""
    _, context, queue = opencl_queue
    if BUILDS[build][1] and "cl_khr_fp64" not in queue.device.extensions:
        pytest.skip(f"{queue.device.name} has no cl_khr_fp64")
    if build not in _PROGRAMS:
        _PROGRAMS[build] = Program(context, queue, build)
    return _PROGRAMS[build]


def device_counts(program, kernel, rates, ys, xs, sample_index, *threshold):
    (out,) = program.run(
        kernel, rates.size,
        [key_arg(SEED), np.uint32(sample_index), *threshold,
         rates.astype(program.real).reshape(-1), xs.reshape(-1), ys.reshape(-1)],
        [(rates.size, program.real)])
    return out.astype(np.float64).reshape(rates.shape)


# --------------------------------------------------------------------------------------------
# Poisson: the normal approximation
# --------------------------------------------------------------------------------------------

THRESHOLD = 1000.0
#: Rates on both sides of the threshold, up to 1e7 (float counts are exact below 2**24); all
#: exact in float32.
KNOB_RATES = np.concatenate([
    np.float32([0.0, 3.0, 10.0, 999.0, THRESHOLD, np.nextafter(np.float32(THRESHOLD), 2e3),
                1024.0, 1e7]),
    np.logspace(0, 7, 50).astype(np.float32),
])
ROWS = 4_000


def knob_grid():
    ys, xs = np.mgrid[0:ROWS, 100:100 + KNOB_RATES.size]
    rates = np.broadcast_to(KNOB_RATES, ys.shape)
    return rates, ys.astype(np.uint32), xs.astype(np.uint32)


@pytest.mark.parametrize("build", ["float32", "float64"])
def test_normal_path_counts_equal_the_reference(build, opencl_queue, record_property):
    program = program_for(build, opencl_queue)
    rates, ys, xs = knob_grid()
    counts = device_counts(program, "t_poisson_normal_above", rates, ys, xs, 13,
                           program.real(THRESHOLD))
    expected = rng.poisson(rates.astype(np.float64), SEED, 13, ys, xs, normal_above=THRESHOLD)
    differing = np.count_nonzero(counts != expected) / counts.size
    report(record_property, f"poisson_normal_differing_fraction[{build}]", differing)
    assert_close(differing, 0.0, "poisson_normal_agreement", "opencl", build)


@pytest.mark.parametrize("build", EXACT_BUILDS)
def test_counts_at_or_below_the_threshold_are_gb_poisson_bit_for_bit(build, opencl_queue):
    program = program_for(build, opencl_queue)
    rates, ys, xs = knob_grid()
    below = np.broadcast_to(KNOB_RATES <= THRESHOLD, rates.shape)
    mixed = device_counts(program, "t_poisson_normal_above", rates, ys, xs, 14,
                          program.real(THRESHOLD))
    exact = device_counts(program, "t_poisson", rates, ys, xs, 14)
    np.testing.assert_array_equal(mixed[below], exact[below])
    assert np.count_nonzero(mixed[~below] != exact[~below]) > 0.5 * np.count_nonzero(~below)


@pytest.mark.parametrize("build", EXACT_BUILDS)
@pytest.mark.parametrize("rate", [1001.0, 1e4, 1e6])
def test_normal_path_mean_and_variance_match_the_rate(build, rate, opencl_queue):
    program = program_for(build, opencl_queue)
    ys, xs = (a.astype(np.uint32) for a in np.mgrid[0:400, 0:500])
    counts = device_counts(program, "t_poisson_normal_above", np.full(ys.shape, rate), ys, xs,
                           15, program.real(THRESHOLD))
    assert np.all(counts == np.floor(counts)) and counts.min() >= 0
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, 3.0 * rate * rate)) < 5.0


def test_normal_path_passes_nan_and_inf_and_clamps_negative_rates(opencl_queue):
    program = program_for("float32", opencl_queue)
    rates = np.array([np.nan, np.inf, -5.0, -np.inf, 0.0])
    ys, xs = np.zeros(rates.size, np.uint32), np.arange(rates.size, dtype=np.uint32)
    counts = device_counts(program, "t_poisson_normal_above", rates, ys, xs, 0, np.float32(0.0))
    assert np.isnan(counts[0]) and counts[1] == np.inf
    assert counts[2:].tolist() == [0.0, 0.0, 0.0] and not np.signbit(counts[2:]).any()


# --------------------------------------------------------------------------------------------
# Resampled response tables
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("build", ["float32", "float64"])
@pytest.mark.parametrize("size", [256, 1024, 4096])
def test_lookup_of_resampled_tables_matches_the_reference(build, size, opencl_queue):
    program = program_for(build, opencl_queue)
    table = transfer.a7r3_lookup_table(size)
    nodes = np.linspace(0.0, 1.0, size)
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001), nodes, (nodes[:-1] + nodes[1:]) / 2])
    x = x.astype(program.real)
    rendered = (table / 255.0).astype(program.real)
    (got,) = program.run("t_lookup_crf", x.size, [x, rendered, np.int32(size)],
                         [(x.size, program.real)])
    expected = transfer.lookup_crf(x.astype(np.float64), table)
    assert_close(got, expected, "crf_lookup_resampled", "opencl", build)


# --------------------------------------------------------------------------------------------
# Fast maths
# --------------------------------------------------------------------------------------------


def srgb_inputs() -> np.ndarray:
    """[-0.1, 1.1] densely, both knees, 0, 1 and a denormal, both signs."""
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001),
                        [0.0, 1.0, transfer.SRGB_DECODE_KNEE, transfer.SRGB_ENCODE_KNEE, 1e-40]])
    return np.concatenate([x, -x])


def run_srgb(program):
    x = srgb_inputs().astype(program.real)
    linear, encoded = program.run("t_srgb", x.size, [x],
                                  [(x.size, program.real), (x.size, program.real)])
    return x.astype(np.float64), linear.astype(np.float64), encoded.astype(np.float64)


def run_normals(program, count=6):
    ys, xs = (a.reshape(-1).astype(np.uint32) for a in np.mgrid[500:700, 9000:9500])
    (z,) = program.run("t_pixel_normals", xs.size,
                       [key_arg(SEED), np.uint32(21), np.uint32(Stream.READ_NOISE),
                        np.uint32(count), xs, ys], [((xs.size, count), program.real)])
    expected = rng.pixel_normals(SEED, 21, Stream.READ_NOISE, ys, xs, count)
    return z.astype(np.float64), expected


def test_fast_srgb_curves_stay_within_their_fast_rows(opencl_queue, record_property):
    program = program_for("float32-fast", opencl_queue)
    x, linear, encoded = run_srgb(program)
    for name, got, expected in (("srgb_to_linear", linear, transfer.srgb_to_linear(x)),
                                ("linear_to_srgb", encoded, transfer.linear_to_srgb(x))):
        scale = np.maximum(np.abs(expected), np.finfo(np.float32).tiny)
        report(record_property, f"{name}_fast_max_rel_error",
               float(np.max(np.abs(got - expected) / scale)))
        assert_close(got, expected, name, "opencl", "float32-fast")
        assert np.array_equal(np.signbit(got), np.signbit(expected))


def test_fast_normals_stay_within_their_fast_row(opencl_queue, record_property):
    z, expected = run_normals(program_for("float32-fast", opencl_queue))
    report(record_property, "normal_fast_max_abs_error", float(np.abs(z - expected).max()))
    assert_close(z, expected, "normal", "opencl", "float32-fast")


def test_fast_maths_changes_float_builds_and_leaves_double_builds_bit_for_bit(opencl_queue):
    fast, precise = program_for("float32-fast", opencl_queue), program_for("float32",
                                                                           opencl_queue)
    assert not np.array_equal(run_normals(fast)[0], run_normals(precise)[0])
    fast64, precise64 = (program_for("float64-fast", opencl_queue),
                         program_for("float64", opencl_queue))
    np.testing.assert_array_equal(run_srgb(fast64)[1:], run_srgb(precise64)[1:])
    np.testing.assert_array_equal(run_normals(fast64)[0], run_normals(precise64)[0])


def test_fast_maths_leaves_poisson_counts_exact(opencl_queue):
    fast, precise = program_for("float32-fast", opencl_queue), program_for("float32",
                                                                           opencl_queue)
    rates, ys, xs = knob_grid()
    np.testing.assert_array_equal(device_counts(fast, "t_poisson", rates, ys, xs, 16),
                                  device_counts(precise, "t_poisson", rates, ys, xs, 16))
    threshold = np.float32(THRESHOLD)
    np.testing.assert_array_equal(
        device_counts(fast, "t_poisson_normal_above", rates, ys, xs, 16, threshold),
        device_counts(precise, "t_poisson_normal_above", rates, ys, xs, 16, threshold))
