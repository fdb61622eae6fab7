"""The accuracy knobs in the Warp device functions (issue 7), on Warp's "cpu" device and, where
CUDA is available, "cuda:0": the Warp counterpart of tests/test_opencl_knobs.py.

* ``random.poisson_normal_above``: the normal approximation of the Poisson counts above a
  threshold rate, against ``rng.poisson(..., normal_above=...)`` (float64, as every Warp
  sampler; this module is built with ``fuse_fp=False``, as random.py asks);
* resampled A7R3 tables through ``pixel.lookup_crf``;
* fast maths: kernels in modules built with Warp's ``fast_math`` option (CUDA's approximate
  float intrinsics; Warp's CPU compiler ignores the option) calling the sRGB curves and
  ``random.pixel_normal_fast``, against the reference within the "float32-fast" rows.

Measured numbers go to the test report (``record_property``) and, with ``-s``, to stdout.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import report
from conftest import warp_key_args as key_args
from conftest import warp_launch as launch

from gpu_blur.reference import rng, transfer
from gpu_blur.reference.rng import Stream
from gpu_blur.testing import assert_close, z_mean, z_var

wp = pytest.importorskip("warp")
wp.config.quiet = True

from gpu_blur.warp_kernels import pixel as px  # noqa: E402  (needs warp, checked above)
from gpu_blur.warp_kernels import random as wr  # noqa: E402

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

SEED = 0xFEED_0007
DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])
DTYPES = {"float32": (wp.float32, np.float32), "float64": (wp.float64, np.float64)}
FAST = {"fast_math": True, "enable_backward": False}


# --------------------------------------------------------------------------------------------
# Test kernels
# --------------------------------------------------------------------------------------------


@wp.kernel
def t_poisson(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
              rates: wp.array(dtype=wp.float64), xs: wp.array(dtype=wp.uint32),
              ys: wp.array(dtype=wp.uint32), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wr.poisson(rates[i], key0, key1, sample_index, xs[i], ys[i])


@wp.kernel
def t_poisson_normal_above(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                           normal_above: wp.float64, rates: wp.array(dtype=wp.float64),
                           xs: wp.array(dtype=wp.uint32), ys: wp.array(dtype=wp.uint32),
                           out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wr.poisson_normal_above(rates[i], normal_above, key0, key1, sample_index, xs[i],
                                     ys[i])


@wp.kernel
def t_lookup_crf32(x: wp.array(dtype=wp.float32), rendered: wp.array(dtype=wp.float32),
                   out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    out[i] = px.lookup_crf(x[i], rendered, rendered.shape[0])


@wp.kernel
def t_lookup_crf64(x: wp.array(dtype=wp.float64), rendered: wp.array(dtype=wp.float64),
                   out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = px.lookup_crf(x[i], rendered, rendered.shape[0])


def srgb_kernel(options: dict):
    """sRGB curves of float32 values in a module built with ``options``."""

    @wp.kernel(module="unique", module_options=options)
    def t_srgb(x: wp.array(dtype=wp.float32), linear: wp.array(dtype=wp.float32),
               encoded: wp.array(dtype=wp.float32)):
        i = wp.tid()
        linear[i] = px.srgb_to_linear(x[i])
        encoded[i] = px.linear_to_srgb(x[i])

    return t_srgb


@wp.kernel(module="unique", module_options=FAST)
def t_pixel_normals_fast(key0: wp.uint32, key1: wp.uint32, sample_index: wp.uint32,
                         stream: wp.uint32, xs: wp.array(dtype=wp.uint32),
                         ys: wp.array(dtype=wp.uint32), z: wp.array2d(dtype=wp.float32)):
    i = wp.tid()
    for j in range(z.shape[1]):
        z[i, j] = wr.pixel_normal_fast(key0, key1, sample_index, stream, xs[i], ys[i],
                                       wp.uint32(j))


T_SRGB_FAST = srgb_kernel(FAST)
T_SRGB = srgb_kernel({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=DEVICES)
def device(request):
    return request.param


def device_counts(device, kernel, rates, ys, xs, sample_index, *threshold):
    rates = np.asarray(rates, dtype=np.float64)
    (out,) = launch(kernel, device, rates.size,
                    [*key_args(SEED), wp.uint32(sample_index), *threshold],
                    [(rates.reshape(-1), wp.float64), (xs.reshape(-1), wp.uint32),
                     (ys.reshape(-1), wp.uint32)],
                    [(rates.size, wp.float64)])
    return out.reshape(rates.shape)


# --------------------------------------------------------------------------------------------
# Poisson: the normal approximation
# --------------------------------------------------------------------------------------------

THRESHOLD = 1000.0
KNOB_RATES = np.concatenate([[0.0, 3.0, 10.0, 999.0, THRESHOLD, np.nextafter(THRESHOLD, 2e3),
                              1024.0, 1e7], np.logspace(0, 7, 50)])
ROWS = 4_000


def knob_grid():
    ys, xs = np.mgrid[0:ROWS, 100:100 + KNOB_RATES.size]
    return np.broadcast_to(KNOB_RATES, ys.shape), ys.astype(np.uint32), xs.astype(np.uint32)


def test_normal_path_counts_equal_the_reference(device, record_property):
    rates, ys, xs = knob_grid()
    counts = device_counts(device, t_poisson_normal_above, rates, ys, xs, 13,
                           wp.float64(THRESHOLD))
    expected = rng.poisson(rates, SEED, 13, ys, xs, normal_above=THRESHOLD)
    differing = np.count_nonzero(counts != expected) / counts.size
    report(record_property, f"poisson_normal_differing_fraction[{device}]", differing)
    assert_close(differing, 0.0, "poisson_normal_agreement", "warp", "float64")


def test_counts_at_or_below_the_threshold_are_poissons_bit_for_bit(device):
    rates, ys, xs = knob_grid()
    below = np.broadcast_to(KNOB_RATES <= THRESHOLD, rates.shape)
    mixed = device_counts(device, t_poisson_normal_above, rates, ys, xs, 14,
                          wp.float64(THRESHOLD))
    exact = device_counts(device, t_poisson, rates, ys, xs, 14)
    np.testing.assert_array_equal(mixed[below], exact[below])
    assert np.count_nonzero(mixed[~below] != exact[~below]) > 0.5 * np.count_nonzero(~below)


@pytest.mark.parametrize("rate", [1001.0, 1e4, 1e6])
def test_normal_path_mean_and_variance_match_the_rate(device, rate):
    ys, xs = (a.astype(np.uint32) for a in np.mgrid[0:400, 0:500])
    counts = device_counts(device, t_poisson_normal_above, np.full(ys.shape, rate), ys, xs, 15,
                           wp.float64(THRESHOLD))
    assert np.all(counts == np.floor(counts)) and counts.min() >= 0
    assert abs(z_mean(counts, rate, rate)) < 5.0
    assert abs(z_var(counts, rate, 3.0 * rate * rate)) < 5.0


def test_normal_path_passes_nan_and_inf_and_clamps_negative_rates(device):
    rates = np.array([np.nan, np.inf, -5.0, -np.inf, 0.0])
    ys, xs = np.zeros(rates.size, np.uint32), np.arange(rates.size, dtype=np.uint32)
    counts = device_counts(device, t_poisson_normal_above, rates, ys, xs, 0, wp.float64(0.0))
    assert np.isnan(counts[0]) and counts[1] == np.inf
    assert counts[2:].tolist() == [0.0, 0.0, 0.0] and not np.signbit(counts[2:]).any()


# --------------------------------------------------------------------------------------------
# Resampled response tables
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", list(DTYPES))
@pytest.mark.parametrize("size", [256, 1024, 4096])
def test_lookup_of_resampled_tables_matches_the_reference(device, dtype, size):
    wtype, ntype = DTYPES[dtype]
    table = transfer.a7r3_lookup_table(size)
    nodes = np.linspace(0.0, 1.0, size)
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001), nodes, (nodes[:-1] + nodes[1:]) / 2])
    x = x.astype(ntype)
    kernel = t_lookup_crf32 if dtype == "float32" else t_lookup_crf64
    (got,) = launch(kernel, device, x.size, [], [(x, wtype), ((table / 255.0).astype(ntype),
                                                              wtype)], [(x.size, wtype)])
    expected = transfer.lookup_crf(x.astype(np.float64), table)
    assert_close(got, expected, "crf_lookup_resampled", "warp", dtype)


# --------------------------------------------------------------------------------------------
# Fast maths
# --------------------------------------------------------------------------------------------


def srgb_inputs() -> np.ndarray:
    """[-0.1, 1.1] densely, both knees, 0, 1 and a denormal, both signs, in float32."""
    x = np.concatenate([np.linspace(-0.1, 1.1, 20001),
                        [0.0, 1.0, transfer.SRGB_DECODE_KNEE, transfer.SRGB_ENCODE_KNEE, 1e-40]])
    return np.concatenate([x, -x]).astype(np.float32)


def test_fast_srgb_curves_stay_within_their_fast_rows(device, record_property):
    x = srgb_inputs()
    linear, encoded = launch(T_SRGB_FAST, device, x.size, [], [(x, wp.float32)],
                             [(x.size, wp.float32), (x.size, wp.float32)])
    x = x.astype(np.float64)
    for name, got, expected in (("srgb_to_linear", linear, transfer.srgb_to_linear(x)),
                                ("linear_to_srgb", encoded, transfer.linear_to_srgb(x))):
        got = got.astype(np.float64)
        normal = np.abs(expected) >= np.finfo(np.float32).tiny  # CUDA's fast maths flushes
        report(record_property, f"{name}_fast_max_rel_error[{device}]",  # denormals to zero
               float(np.max(np.abs(got - expected)[normal] / np.abs(expected[normal]))))
        assert_close(got, expected, name, "warp", "float32-fast")
        assert np.array_equal(np.signbit(got), np.signbit(expected))


def test_fast_normals_stay_within_their_fast_row(device, record_property):
    ys, xs = (a.reshape(-1).astype(np.uint32) for a in np.mgrid[500:700, 9000:9500])
    (z,) = launch(t_pixel_normals_fast, device, xs.size,
                  [*key_args(SEED), wp.uint32(21), wp.uint32(Stream.READ_NOISE)],
                  [(xs, wp.uint32), (ys, wp.uint32)], [((xs.size, 6), wp.float32)])
    expected = rng.pixel_normals(SEED, 21, Stream.READ_NOISE, ys, xs, 6)
    report(record_property, f"normal_fast_max_abs_error[{device}]",
           float(np.abs(z - expected).max()))
    assert_close(z, expected, "normal", "warp", "float32-fast")


def test_fast_math_option_reaches_the_module_and_the_cpu_build_ignores_it(device):
    assert T_SRGB_FAST.module.options["fast_math"] and not T_SRGB.module.options["fast_math"]
    x = srgb_inputs()
    fast = launch(T_SRGB_FAST, device, x.size, [], [(x, wp.float32)],
                  [(x.size, wp.float32), (x.size, wp.float32)])
    precise = launch(T_SRGB, device, x.size, [], [(x, wp.float32)],
                     [(x.size, wp.float32), (x.size, wp.float32)])
    if device == "cpu":  # Warp passes fast_math to NVRTC only
        np.testing.assert_array_equal(fast, precise)
    else:
        assert not np.array_equal(fast, precise)
