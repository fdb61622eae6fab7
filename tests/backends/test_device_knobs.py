"""The accuracy knobs in the device functions (issue 7), in both kernel languages.

* the normal approximation of the Poisson counts above a threshold rate (OpenCL
  ``gb_poisson_normal_above``, Warp ``random.poisson_normal_above``) against
  ``poisson_counts.poisson(..., normal_above=...)``, over the targets of
  tests/backends/test_device_random.py;
* resampled A7R3 tables through the CRF lookup (gb_pixel.h, pixel.py), over the targets of
  tests/backends/test_device_pixel.py;
* fast maths: the sRGB curves and the normals of the ``float32-fast`` builds (OpenCL
  ``GB_FAST_MATH``: native_ functions in float builds; Warp: modules built with ``fast_math``,
  CUDA's approximate float intrinsics, which Warp's CPU compiler ignores) against the reference
  within the tolerance table's "float32-fast" rows.

Measured numbers go to the test report (``record_property``) and, with ``-s``, to stdout.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import report
from device_functions import target_fixture, target_specs

from gpu_blur.reference import poisson_counts, rng, transfer
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, z_mean, z_var

SEED = 0xFEED_0007


program = target_fixture(target_specs("random"))
built = target_fixture(target_specs("pixel"))
fast = target_fixture(target_specs("random", ["float32-fast"]))


def device_counts(program, kernel, rates, ys, xs, sample_index, *threshold):
    (out,) = program.run(
        kernel, rates.size,
        [*program.key(SEED), np.uint32(sample_index), *(program.real.type(t) for t in threshold),
         rates.astype(program.real), xs, ys],
        [(rates.shape, program.real)])  # fmt: skip
    return out.astype(np.float64)


# --------------------------------------------------------------------------------------------
# Poisson: the normal approximation
# --------------------------------------------------------------------------------------------

THRESHOLD = 1000.0
ROWS = 4_000


def knob_rates(real) -> np.ndarray:
    """Rates on both sides of the threshold, up to 1e7 (float counts are exact below 2**24), in
    the build's type."""
    t = real.type(THRESHOLD)
    return np.concatenate([np.array([0.0, 3.0, 10.0, 999.0, t, np.nextafter(t, real.type(2e3)),
                                     1024.0, 1e7], dtype=real),
                           np.logspace(0, 7, 50).astype(real)])  # fmt: skip


def knob_grid(real):
    rates = knob_rates(real)
    ys, xs = np.mgrid[0:ROWS, 100:100 + rates.size]
    return np.broadcast_to(rates, ys.shape), ys.astype(np.uint32), xs.astype(np.uint32)


@pytest.mark.parametrize("program", target_specs("random", ["float32", "float64"]), ids=str,
                         indirect=True)  # fmt: skip
def test_normal_path_counts_equal_the_reference(program, record_property):
    rates, ys, xs = knob_grid(program.real)
    counts = device_counts(program, "t_poisson_normal_above", rates, ys, xs, 13, THRESHOLD)
    expected = poisson_counts.poisson(rates.astype(np.float64), SEED, 13, ys, xs,
                                      normal_above=THRESHOLD)
    differing = np.count_nonzero(counts != expected) / counts.size
    report(record_property, f"poisson_normal_differing_fraction[{program}]", differing)
    assert_close(differing, 0.0, "poisson_normal_agreement", program.lang, program.build)


def test_counts_at_or_below_the_threshold_are_poissons_bit_for_bit(program):
    rates, ys, xs = knob_grid(program.real)
    below = rates <= THRESHOLD
    mixed = device_counts(program, "t_poisson_normal_above", rates, ys, xs, 14, THRESHOLD)
    exact = device_counts(program, "t_poisson", rates, ys, xs, 14)
    np.testing.assert_array_equal(mixed[below], exact[below])
    assert np.count_nonzero(mixed[~below] != exact[~below]) > 0.5 * np.count_nonzero(~below)


@pytest.mark.parametrize("rate", [1001.0, 1e4, 1e6])
def test_normal_path_mean_and_variance_match_the_rate(program, rate):
    ys, xs = (a.astype(np.uint32) for a in np.mgrid[0:400, 0:500])
    counts = device_counts(program, "t_poisson_normal_above", np.full(ys.shape, rate), ys, xs,
                           15, THRESHOLD)  # fmt: skip
    assert np.all(counts == np.floor(counts)) and counts.min() >= 0
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, 3.0 * rate * rate)) < 5.0


def test_normal_path_passes_nan_and_inf_and_clamps_negative_rates(program):
    rates = np.array([np.nan, np.inf, -5.0, -np.inf, 0.0])
    ys, xs = np.zeros(rates.size, np.uint32), np.arange(rates.size, dtype=np.uint32)
    counts = device_counts(program, "t_poisson_normal_above", rates, ys, xs, 0, 0.0)
    assert np.isnan(counts[0]) and counts[1] == np.inf
    assert counts[2:].tolist() == [0.0, 0.0, 0.0] and not np.signbit(counts[2:]).any()


# --------------------------------------------------------------------------------------------
# Resampled response tables
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [256, 1024, 4096])
def test_lookup_of_resampled_tables_matches_the_reference(built, size):
    table = transfer.a7r3_lookup_table(size)
    nodes = np.linspace(0.0, 1.0, size)
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001), nodes, (nodes[:-1] + nodes[1:]) / 2])
    x = x.astype(built.real)
    rendered = (table / 255.0).astype(built.real)
    (got,) = built.run("t_lookup_crf", x.size, [x, rendered, np.int32(size)],
                       [(x.size, built.real)])
    expected = transfer.lookup_crf(x.astype(np.float64), table)
    assert_close(got, expected, "crf_lookup_resampled", built.lang, built.build)


# --------------------------------------------------------------------------------------------
# Fast maths
# --------------------------------------------------------------------------------------------


def srgb_inputs() -> np.ndarray:
    """[-0.1, 1.1] densely, both knees, 0, 1 and a denormal, both signs, in float32."""
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001),
                        [0.0, 1.0, transfer.SRGB_DECODE_KNEE, transfer.SRGB_ENCODE_KNEE, 1e-40]])
    return np.concatenate([x, -x]).astype(np.float32)


def run_srgb(program) -> list[np.ndarray]:
    """(linear, encoded) of :func:`srgb_inputs` in the build's type."""
    x = srgb_inputs().astype(program.real)
    return program.run("t_srgb", x.size, [x], [(x.size, program.real), (x.size, program.real)])


def run_normals(program, count=6):
    ys, xs = (a.reshape(-1).astype(np.uint32) for a in np.mgrid[500:700, 9000:9500])
    (z,) = program.run("t_pixel_normals", xs.size,
                       [*program.key(SEED), np.uint32(21), np.uint32(Stream.READ_NOISE),
                        np.uint32(count), xs, ys], [((xs.size, count), program.real)])
    expected = rng.pixel_normals(SEED, 21, Stream.READ_NOISE, ys, xs, count)
    return z.astype(np.float64), expected


@pytest.mark.bits
def test_fast_srgb_curves_stay_within_their_fast_rows(fast, record_property):
    x = srgb_inputs().astype(np.float64)
    linear, encoded = run_srgb(fast)
    for name, got, expected in (("srgb_to_linear", linear, transfer.srgb_to_linear(x)),
                                ("linear_to_srgb", encoded, transfer.linear_to_srgb(x))):
        got = got.astype(np.float64)
        normal = np.abs(expected) >= np.finfo(np.float32).tiny  # CUDA's fast maths flushes
        report(record_property, f"{name}_fast_max_rel_error[{fast}]",  # denormals to zero
               float(np.max(np.abs(got - expected)[normal] / np.abs(expected[normal]))))
        assert_close(got, expected, name, fast.lang, fast.build)
        assert np.array_equal(np.signbit(got), np.signbit(expected))


@pytest.mark.bits
def test_fast_normals_stay_within_their_fast_row(fast, record_property):
    z, expected = run_normals(fast)
    report(record_property, f"normal_fast_max_abs_error[{fast}]",
           float(np.abs(z - expected).max()))
    assert_close(z, expected, "normal", fast.lang, fast.build)


OPENCL_FAST = target_specs("random", ["float32-fast"], langs=("opencl",))


@pytest.mark.parametrize("fast", OPENCL_FAST, ids=str, indirect=True)
def test_opencl_fast_maths_changes_float_builds_and_leaves_double_builds_bit_for_bit(fast):
    assert not np.array_equal(run_normals(fast)[0], run_normals(fast.at("float32"))[0])
    fast64, precise64 = fast.at("float64-fast"), fast.at("float64")
    np.testing.assert_array_equal(run_srgb(fast64), run_srgb(precise64))
    np.testing.assert_array_equal(run_normals(fast64)[0], run_normals(precise64)[0])


@pytest.mark.parametrize("fast", OPENCL_FAST, ids=str, indirect=True)
@pytest.mark.bits
def test_opencl_fast_maths_leaves_poisson_counts_exact(fast):
    precise = fast.at("float32")
    rates, ys, xs = knob_grid(fast.real)
    np.testing.assert_array_equal(device_counts(fast, "t_poisson", rates, ys, xs, 16),
                                  device_counts(precise, "t_poisson", rates, ys, xs, 16))
    np.testing.assert_array_equal(
        device_counts(fast, "t_poisson_normal_above", rates, ys, xs, 16, THRESHOLD),
        device_counts(precise, "t_poisson_normal_above", rates, ys, xs, 16, THRESHOLD))


@pytest.mark.parametrize("fast", target_specs("random", ["float32-fast"], langs=("warp",)),
                         ids=str, indirect=True)  # fmt: skip
def test_warp_fast_math_option_reaches_the_module_and_the_cpu_build_ignores_it(fast):
    from device_functions.random_warp import T_SRGB, T_SRGB_FAST

    assert T_SRGB_FAST.module.options["fast_math"] and not T_SRGB.module.options["fast_math"]
    x = srgb_inputs()
    fast_values = run_srgb(fast)
    precise = fast.launch(T_SRGB, x.size, [x], [(x.size, np.float32), (x.size, np.float32)])
    if fast.device == "cpu":  # Warp passes fast_math to NVRTC only
        np.testing.assert_array_equal(fast_values, precise)
    else:
        assert not np.array_equal(fast_values, precise)
