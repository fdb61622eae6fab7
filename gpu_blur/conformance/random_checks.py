"""Checks of the random draws: Philox words and uniforms, Poisson counts of the samplers.

Registered into :data:`gpu_blur.conformance.checks.CHECKS` (and, one device against another,
:data:`~gpu_blur.conformance.checks.AGAINST`) on import, in the order ``gpu-blur validate``
runs them.
"""

from __future__ import annotations

import numpy as np

from gpu_blur.backends import to_host
from gpu_blur.conformance import SAMPLE, SEED, on_device, prepare
from gpu_blur.conformance.checks import (
    AGAINST,
    REFERENCE,
    Check,
    Outcome,
    Target,
    check,
    exact,
    within,
)
from gpu_blur.reference import rng

__all__ = ["HIGH_RATES", "LOW_RATES", "UNIFORM_DRAW", "UNIFORM_PROBE_CL", "device_uniforms",
           "poisson_block", "poisson_counts", "reference_uniforms"]

#: OpenCL C that writes the noise stages' Philox words and uniforms of each pixel (the kernels'
#: own gb_pixel_bits and gb_uniform). The Warp twin is gpu_blur/conformance/warp_probe.py.
UNIFORM_PROBE_CL = """
#include "gb_random.h"
__kernel void gb_probe_uniforms(uint key0, uint key1, uint sample_index, uint stream,
                                uint width, __global uint *words, __global real *out)
{
    uint i = get_global_id(0);
    uint4 bits = gb_pixel_bits((uint2)(key0, key1), sample_index, stream, i % width,
                               i / width, 0u);
    vstore4(bits, i, words);
    out[4 * i] = gb_uniform(bits.x);
    out[4 * i + 1] = gb_uniform(bits.y);
    out[4 * i + 2] = gb_uniform(bits.z);
    out[4 * i + 3] = gb_uniform(bits.w);
}
"""

#: (seed, sample index, stream, width, height) of the uniforms compared: seeds beyond 32 bits,
#: the largest sample index.
UNIFORM_DRAW = (2**40 + 17, 2**32 - 5, rng.Stream.SHOT_NOISE, 97, 61)


def device_uniforms(backend) -> tuple[np.ndarray, np.ndarray]:
    """(words, uniforms) of :data:`UNIFORM_DRAW` on a kernel backend, pixel-major, 4 each."""
    seed, sample_index, stream, width, height = UNIFORM_DRAW
    key = rng.key_from_seed(seed)
    n = width * height
    args = (int(key[0]), int(key[1]), sample_index, int(stream))
    if backend.name == "opencl":
        import pyopencl as cl

        program = backend.program_from_source(UNIFORM_PROBE_CL, name="uniform probe")
        words = cl.Buffer(backend.ctx, cl.mem_flags.WRITE_ONLY, 4 * n * 4)
        values = cl.Buffer(backend.ctx, cl.mem_flags.WRITE_ONLY,
                           4 * n * np.dtype(backend.np_real).itemsize)
        program.gb_probe_uniforms(backend.queue, (n,), None, *map(np.uint32, args),
                                  np.uint32(width), words, values)
        got_words, got = np.empty(4 * n, np.uint32), np.empty(4 * n, backend.np_real)
        cl.enqueue_copy(backend.queue, got_words, words)
        cl.enqueue_copy(backend.queue, got, values)
        return got_words, got.astype(np.float64)
    import warp as wp

    from gpu_blur.conformance.warp_probe import pixel_uniforms

    device = backend.wp_device
    words = wp.zeros(4 * n, dtype=wp.uint32, device=device)
    values = wp.zeros(4 * n, dtype=wp.float64, device=device)
    wp.launch(pixel_uniforms, dim=n, device=device,
              inputs=[*(wp.uint32(a) for a in args), width, words, values])
    return words.numpy(), values.numpy()


def reference_uniforms() -> tuple[np.ndarray, np.ndarray]:
    """(words, uniforms) of :data:`UNIFORM_DRAW` from :mod:`gpu_blur.reference.rng`."""
    seed, sample_index, stream, width, height = UNIFORM_DRAW
    y, x = np.divmod(np.arange(width * height), width)
    words = rng.pixel_bits(seed, sample_index, stream, y, x)
    return words.reshape(-1), rng.uniform_from_bits(words).reshape(-1)


@check("random: Philox words and uniforms", quick=True, kernels_only=True)
def _uniforms(t: Target) -> list[Outcome]:
    words, uniforms = device_uniforms(t.backend)
    ref_words, ref_uniforms = reference_uniforms()
    why = "Philox4x32-10 words and their uniforms are exact"
    return [exact("philox words", words, ref_words, why),
            exact("uniforms", uniforms, ref_uniforms, why)]


def poisson_block(precision: str, rates, k: float, block: int = 24) -> np.ndarray:
    """A linear image of ``block`` x ``block`` pixels per rate, rate x ``k`` as devices hold it.

    A power-of-two ``k`` keeps ``value / k`` exact in either precision.
    """
    values = on_device(precision, np.asarray(rates, dtype=np.float64) * k)
    return np.repeat(np.repeat(values, block)[None, :, None], block, axis=0).repeat(3, 2)


def poisson_counts(t: Target, backend, rates, k: float = 0.125) -> np.ndarray:
    """The Poisson counts ``backend``'s to_raw pass draws at ``rates``, as float64.

    Identity camera, white balance gains 1, no read noise, no saturation: the RAW value is
    the count times ``k``.
    """
    linear = poisson_block(t.precision, rates, k)
    settings = {"blur": {"mode": "none"}, "saturation": {"mode": "off"}}
    p, cam, params = prepare(t.precision, settings, linear.shape[:2], camera="srgb",
                             overrides={"shot_noise_k": k, "read_noise_std": 0.0,
                                        "pattern": "RGGB"})
    raw, _ = backend.to_raw(p, params, cam, linear, np.zeros_like(linear), seed=SEED,
                            sample_index=SAMPLE)
    return to_host(raw) / k


#: Rates of the inversion sampler (< 10), where a count depends on the uniform alone.
LOW_RATES = [0.0, 1e-12, 0.3, 1.0, 2.5, 5.0, 9.99]
#: Rates through the switch to PTRS and beyond, up to 1e7.
HIGH_RATES = [10.01, 100.0, 1e4, 1e7]


def _float_samplers(t: Target) -> bool:
    """Whether the device samples in float (an OpenCL device without cl_khr_fp64)."""
    return t.family == "opencl" and not t.backend.info.fp64


@check("random: Poisson counts, rates 0 to 9.99 (inversion)", quick=True)
def _poisson_low(t: Target) -> list[Outcome]:
    got = poisson_counts(t, t.backend, LOW_RATES)
    ref = poisson_counts(t, REFERENCE, LOW_RATES)
    if _float_samplers(t):  # float cumulative sums: a count may move (its own row)
        return [within("poisson_agreement", t, np.mean(got != ref), 0.0,
                       dtype="float32-nofp64")]
    return [exact("poisson counts", got, ref,
                  "same uniforms, same inversion: the same counts (K = 1/8 keeps rates exact)")]


@check("random: Poisson counts, rates 10 to 1e7 (PTRS)")
def _poisson_high(t: Target) -> list[Outcome]:
    if _float_samplers(t):
        return [Outcome("", "poisson_agreement", None, "", None, "", None,
                        "float PTRS moves counts at large rates: the test suite checks their "
                        "statistics (tests/backends/test_hard_cases.py)")]
    got = poisson_counts(t, t.backend, HIGH_RATES)
    ref = poisson_counts(t, REFERENCE, HIGH_RATES)
    if not t.kernels:
        return [exact("poisson counts", got, ref, "the reference itself")]
    # Warp samples in float64 whatever the caller's type: its float64 row
    dtype = "float64" if t.family == "warp" else None
    return [within("poisson_agreement", t, np.mean(got != ref), 0.0, dtype=dtype)]


# -- one device against another (validate --against) --------------------------------------------

def _against_uniforms(a: Target, b: Target) -> list[Outcome]:
    why = "both kernel languages draw the reference's Philox words and uniforms"
    (wa, ua), (wb, ub) = device_uniforms(a.backend), device_uniforms(b.backend)
    return [exact("philox words", wa, wb, why), exact("uniforms", ua, ub, why)]


def _against_poisson(a: Target, b: Target) -> list[Outcome]:
    return [exact("poisson counts",
                  poisson_counts(a, a.backend, LOW_RATES), poisson_counts(b, b.backend, LOW_RATES),
                  "same uniforms, same inversion: the same counts")]


AGAINST.extend([Check("random: Philox words and uniforms", _against_uniforms),
                Check("random: Poisson counts, rates 0 to 9.99", _against_poisson)])
