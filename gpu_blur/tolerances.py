"""Tolerances, in one table: what spot checks, ``gpu-blur validate`` and the tests accept.

A tolerance is a claim about a stage on a backend at a precision: ``(stage, backend, dtype) ->
(rtol, atol)``. Nothing writes numbers of its own; each caller names the row it relies on.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["F64_APPLY_MATRIX", "F64_CRF_POLYNOMIAL", "F64_LERP", "F64_LOG_FACTORIAL", "F64_MALVAR",
           "F64_SRGB_OPENCL", "F64_SRGB_WARP", "TOLERANCES", "mismatch", "tolerance"]

#: Unit roundoff of float64 (IEEE 754 binary64, round to nearest).
_U64 = 2.0**-53


def _sum_bound(terms: int, magnitude: float) -> float:
    """Rounding bound of a float64 sum of ``terms`` products, any order, fused or not.

    ``gamma_n * sum |w_i x_i|`` with ``gamma_n = n u / (1 - n u)`` (Higham, "Accuracy and
    Stability of Numerical Algorithms", 2nd ed., eq. 3.5): what every correct IEEE double
    compiler meets, whatever it contracts. Doubled: the device and the reference both round.
    """
    return 2.0 * terms * _U64 / (1.0 - terms * _U64) * magnitude


#: Float64 rows of weighted sums, from their bound instead of one device's measurement (a
#: compiler may contract ``a * b + c`` or sum in another order; issue 35 saw Intel's runtime
#: without AVX-512 at 6.7e-16 where AVX-512 gave 4.4e-16). apply_matrix: 3 products, the A7R3
#: camera_to_linear row sums of |m| up to 2.47, |x| <= 1.2 (tests/backends/test_device_pixel.py).
F64_APPLY_MATRIX = _sum_bound(3, 2.47 * 1.2)  # 2.0e-15
#: Malvar-He-Cutler: at most 13 taps whose |weights| add up to at most 2.5 (R or B at a green
#: or at the other colour, 20/8), linear RAW <= 1.
F64_MALVAR = _sum_bound(13, 2.5)  # 7.2e-15

#: A7R3 polynomial by Horner, degree 7: 14 roundings over sum |c_i| = 1178 (x in [0, 1];
#: Higham eq. 5.3). Measured 4.1e-14; the bound is what a compiler that fuses elsewhere meets.
F64_CRF_POLYNOMIAL = _sum_bound(14, 1178.1)  # 3.7e-12
#: Table lookup ``a + t (b - a)`` on values <= 1: three roundings.
F64_LERP = _sum_bound(3, 1.0)  # 6.7e-16
#: sRGB curves, relative: the device's pow (OpenCL C allows 16 ulps in double, CUDA documents
#: 2 for Warp's; glibc's is within 1) and the curve's roundings around it (about 4 ulps, the
#: exponent 2.4 scaling the input's), each side. One ulp of [1, 2) is 2**-52.
F64_SRGB_OPENCL = 20 * 2.0**-52  # 4.4e-15
F64_SRGB_WARP = 6 * 2.0**-52  # 1.3e-15
#: log(k!) by Stirling from k = 16, relative: the device's log (OpenCL: 3 ulps; CUDA 1) times
#: the sum's condition (at most 1.6, at k = 16), and the series' roundings.
F64_LOG_FACTORIAL = 8 * 2.0**-52  # 1.8e-15

#: (stage, backend, dtype) -> (rtol, atol). "independent" rows compare the reference with an
#: outside implementation of the same maths (colour-demosaicing, OpenCV, a literal transcription).
TOLERANCES: dict[tuple[str, str, str], tuple[float, float]] = {
    # -- transfer functions --
    # Against a scalar transcription of the defining formula with math.pow.
    ("srgb_transfer", "independent", "float64"): (1e-15, 1e-17),
    # EOTF(OETF(x)): the IEC knees disagree (12.92 * 0.0031308 != 0.04045), which costs up to
    # 2.3e-9 absolute just above the linear knee; elsewhere the round trip is ~1e-16.
    ("srgb_round_trip", "numpy", "float64"): (1e-13, 2.5e-9),
    # Horner against numpy's polyval: rounding in a degree-7 sum with coefficients up to 368.
    ("crf_polynomial", "independent", "float64"): (0.0, 1e-12),
    # A7R3 tables resampled to N nodes (output.crf_table_size, tests/reference/test_knobs.py)
    # against the authors' 2,551-node table, re-toning 1e6 + 1 values: the resolution alone,
    # largest in the steep dark end (measured 5.79e-3, 1.46e-3 and 3.51e-4; one 8-bit code is
    # 3.9e-3).
    ("crf_table_256", "numpy", "float64"): (0.0, 6e-3),
    ("crf_table_1024", "numpy", "float64"): (0.0, 1.5e-3),
    ("crf_table_4096", "numpy", "float64"): (0.0, 3.6e-4),
    # -- colour --
    # Composed 3 x 3 matrices against the stage-by-stage chain and the authors' derived values.
    ("color_matrix", "independent", "float64"): (1e-12, 1e-13),
    # lin -> cam -> lin with float64 inverses (condition numbers <= 5.2).
    ("color_round_trip", "numpy", "float64"): (0.0, 1e-13),
    # -- whole pipeline --
    # The RealBlur-J chain with noise off against a literal transcription of the note's steps
    # (row-vector matrices, packed 4-plane mosaic, stored-order gains, correlate with zero pad).
    ("pipeline_realblur_j", "independent", "float64"): (0.0, 1e-9),
    # bench/torch_chain.py (the authors' chain as float32 torch ops;
    # tests/synthesis/test_torch_chain.py) against the reference, noise off (issue 15: 1e-4):
    # float32 Horner of the A7R3 polynomial (section 8: <= 3e-5) and pow; measured 2.7e-5 on
    # photo crops, CPU. With noise, each channel's std on a flat grey: both draw their own
    # noise; spread over seeds 0.3 to 0.6 % each, means within 0.05 %.
    ("pipeline_realblur_j", "torch", "float32"): (0.0, 5e-5),
    ("noise_std_realblur_j", "torch", "float32"): (0.03, 0.0),
    # WB and colour steps cancel with noise off, on a flat field (issue 2: <= 1e-9).
    ("pipeline_wb_color_cancel", "numpy", "float64"): (0.0, 1e-9),
    # -- OpenCL pixel stages --
    # kernels/opencl/include/gb_pixel.h and gb_demosaic.h against the reference
    # (tests/backends/test_device_pixel.py). Inputs are rounded to the build's type and the
    # reference is fed the same values; float32 builds also round the constants the host passes.
    # Measured on Intel's CPU OpenCL runtime (FP contraction on: the compiler may fuse a * b + c).
    # sRGB: float32 pow and the rounded 0.055 / 1.055: measured 3.6e-7 / 1.7e-7 relative on
    # Intel's CPU runtime and up to 2.4e-7 on an NVIDIA H200 (OpenCL allows pow 16 ulps);
    # denormal results round to float32's denormal grid (< 1e-45).
    ("srgb_to_linear", "opencl", "float32"): (6e-7, 1e-45),
    ("linear_to_srgb", "opencl", "float32"): (6e-7, 1e-45),
    # float64: the device's pow (measured 2.2e-16 and 5.7e-16 relative).
    ("srgb_to_linear", "opencl", "float64"): (F64_SRGB_OPENCL, 0.0),
    ("linear_to_srgb", "opencl", "float64"): (F64_SRGB_OPENCL, 0.0),
    # A7R3 polynomial: degree 7, coefficients up to 368 that cancel to a value <= 1, so Horner's
    # error is absolute. float32: 8.1e-6 from rounding the coefficients plus 1.4e-5 from float
    # arithmetic (measured 2.2e-5 in all, ~1.4 codes of 16-bit output); float64 measured 4.1e-14.
    ("crf_polynomial", "opencl", "float32"): (0.0, 2.5e-5),
    ("crf_polynomial", "opencl", "float64"): (0.0, F64_CRF_POLYNOMIAL),
    # A7R3 lookup table (2,551 nodes): measured 7.4e-8 (float32) and 1.1e-16 (float64, one ulp
    # where a * b + c is fused) absolute.
    ("crf_lookup", "opencl", "float32"): (0.0, 8e-8),
    ("crf_lookup", "opencl", "float64"): (0.0, F64_LERP),
    # The same function on the tables resampled to 256, 1,024 and 4,096 nodes
    # (output.crf_table_size, tests/backends/test_device_knobs.py): measured 8.5e-8 (float32,
    # 256 nodes; 7.2e-8 on the authors' table in the same test) and 1.1e-16 (float64).
    ("crf_lookup_resampled", "opencl", "float32"): (0.0, 1e-7),
    ("crf_lookup_resampled", "opencl", "float64"): (0.0, F64_LERP),
    # A7R3 3 x 3 matrices (float64 ones for the reference) on linear pixels in [-0.1, 1.2]:
    # measured 1.9e-7 (float32, matrix rounding included) and 4.4e-16 (float64) absolute.
    ("apply_matrix", "opencl", "float32"): (0.0, 2.5e-7),
    ("apply_matrix", "opencl", "float64"): (0.0, F64_APPLY_MATRIX),
    # Demosaicing linear RAW <= 1: Malvar's 13-tap sums measured 2.2e-7 (float32) and 4.4e-16
    # (float64, fused a * b + c) absolute; bilinear measured 7.5e-8 (float32) and 0 in float64,
    # where its weights (1/4, 1/2) make every product exact and the sums run in the reference's
    # order, so any IEEE double device gives the reference bit for bit.
    ("demosaic_malvar2004", "opencl", "float32"): (0.0, 2.5e-7),
    ("demosaic_malvar2004", "opencl", "float64"): (0.0, F64_MALVAR),
    ("demosaic_bilinear", "opencl", "float32"): (0.0, 8e-8),
    ("demosaic_bilinear", "opencl", "float64"): (0.0, 0.0),
    # -- Warp pixel stages --
    # gpu_blur/warp_kernels/pixel.py against the reference (tests/backends/test_device_pixel.py),
    # Warp's default fuse_fp=True. Inputs are rounded to the instance's type and the reference is
    # fed the same values; float32 instances also round the constants the host passes. Measured on
    # Warp's "cpu" device (clang, no contraction across Warp's statements) and on CUDA (NVIDIA H200,
    # which fuses a * b + c): each row covers the larger, both given as CPU / CUDA.
    # sRGB float32: float pow and the rounded 0.055 / 1.055, relative 3.6e-7 / 3.6e-7 (decode)
    # and 2.0e-7 / 1.7e-7 (encode); denormal results round to float32's grid (< 1e-45).
    ("srgb_to_linear", "warp", "float32"): (4e-7, 1e-45),
    ("linear_to_srgb", "warp", "float32"): (2.5e-7, 1e-45),
    # sRGB float64: libm / CUDA pow, relative 2.2e-16 / 2.2e-16 and 5.4e-16 / 5.8e-16.
    ("srgb_to_linear", "warp", "float64"): (F64_SRGB_WARP, 0.0),
    ("linear_to_srgb", "warp", "float64"): (F64_SRGB_WARP, 0.0),
    # A7R3 polynomial (degree 7, coefficients up to 368 that cancel): absolute 2.4e-5 / 2.2e-5
    # in float32 (8.1e-6 of it from rounding the coefficients), 0 / 4.1e-14 in float64.
    ("crf_polynomial", "warp", "float32"): (0.0, 2.5e-5),
    ("crf_polynomial", "warp", "float64"): (0.0, F64_CRF_POLYNOMIAL),
    # A7R3 lookup table (2,551 nodes): absolute 7.4e-8 / 7.4e-8 (float32), 0 / 1.1e-16 (float64).
    ("crf_lookup", "warp", "float32"): (0.0, 8e-8),
    ("crf_lookup", "warp", "float64"): (0.0, F64_LERP),
    # Tables resampled to 256, 1,024 and 4,096 nodes (tests/backends/test_device_knobs.py):
    # measured 8.5e-8 (float32) and 0 (float64) on the CPU.
    ("crf_lookup_resampled", "warp", "float32"): (0.0, 1e-7),
    ("crf_lookup_resampled", "warp", "float64"): (0.0, F64_LERP),
    # A7R3 3 x 3 matrices (float64 ones for the reference) on linear pixels in [-0.1, 1.2]:
    # absolute 2.5e-7 / 1.9e-7 (float32, matrix rounding included), 4.4e-16 / 4.4e-16 (float64).
    ("apply_matrix", "warp", "float32"): (0.0, 3e-7),
    ("apply_matrix", "warp", "float64"): (0.0, F64_APPLY_MATRIX),
    # Demosaicing linear RAW <= 1: Malvar absolute 2.2e-7 / 2.2e-7 (float32) and 0 / 4.4e-16
    # (float64); bilinear 7.5e-8 / 7.5e-8 (float32) and 0 / 0 in float64, where its weights make
    # every product exact and the sums run in the reference's order.
    ("demosaic_malvar2004", "warp", "float32"): (0.0, 2.5e-7),
    ("demosaic_malvar2004", "warp", "float64"): (0.0, F64_MALVAR),
    ("demosaic_bilinear", "warp", "float32"): (0.0, 8e-8),
    ("demosaic_bilinear", "warp", "float64"): (0.0, 0.0),
    # -- Bayer and demosaicing --
    # Against colour-demosaicing 0.2.7 (scipy convolve) on photographs: measured bit-identical
    # (max abs difference 0.0); 1e-12 leaves room for another summation order only.
    ("demosaic_malvar2004", "independent", "float64"): (0.0, 1e-12),
    ("demosaic_bilinear", "independent", "float64"): (0.0, 1e-12),
    # A flat field must come back flat: rounding only (Malvar measured <= 4.2e-16 relative).
    ("demosaic_flat_field", "numpy", "float64"): (2e-15, 0.0),
    # x / g * g: two roundings, <= 2.2e-16 relative measured.
    ("white_balance_round_trip", "numpy", "float64"): (1e-15, 0.0),
    # -- random numbers and noise --
    # log(k!) against 50-digit decimal values, k = 16 .. 1e12 (the table below 16 is tested for
    # equality): the Stirling branch measured <= 4.9e-16 relative (at k = 16).
    ("log_factorial", "numpy", "float64"): (6e-16, 0.0),
    # Box-Muller through numpy's log/cos/sin against Python's math (libm): measured over 2e5
    # pairs <= 2.2e-16 absolute and <= 3.5e-16 relative.
    ("box_muller", "independent", "float64"): (5e-16, 5e-16),
    # -- OpenCL random --
    # kernels/opencl/include/gb_random.h against rng (tests/backends/test_device_random.py); the
    # dtype names the build: float32 (samplers in double on an fp64 device), float64, and
    # float32-nofp64 (float throughout, for devices without cl_khr_fp64). Measured on Intel's
    # CPU OpenCL runtime. Words and uniforms are compared bit for bit (no row).
    # Normals: float32 computes Box-Muller in double and rounds once, <= half a float32 ulp of
    # |z| < 5.8 = 2.4e-7 (measured 2.4e-7 over 2e5 pixels x 6 normals and 5e4 pairs).
    ("normal", "opencl", "float32"): (0.0, 1e-6),
    # float64: the reference's operations through the device's libm (measured 1.8e-15).
    ("normal", "opencl", "float64"): (0.0, 1e-12),
    # float32 without fp64: float log/sqrt, cospi/sinpi, a few float ulps (measured 7.8e-7).
    ("normal", "opencl", "float32-nofp64"): (0.0, 3e-6),
    # log(k!), k = 0 .. 1e12: the table exactly, Stirling through the device's log (measured
    # 0.0 in double; 1.8e-7 relative in float).
    ("log_factorial", "opencl", "float32"): (1e-15, 0.0),
    ("log_factorial", "opencl", "float64"): (F64_LOG_FACTORIAL, 0.0),
    ("log_factorial", "opencl", "float32-nofp64"): (1e-6, 0.0),
    # Poisson counts: the FRACTION OF PIXELS whose count differs from poisson_counts.poisson, as
    # atol against 0 (issue: identical on >= 99.999 %). Measured 0 of 1.2e6 + 8.2e5 pixels.
    ("poisson_agreement", "opencl", "float32"): (0.0, 1e-5),
    ("poisson_agreement", "opencl", "float64"): (0.0, 1e-5),
    # float32 without fp64, inversion rates (< 10) only (measured 1e-5 at rate 3); float PTRS
    # differs on 0.35 % of pixels at 1e4 and 15 % at 1e7, so it is checked statistically.
    ("poisson_agreement", "opencl", "float32-nofp64"): (0.0, 1e-4),
    # The normal approximation above a threshold (noise.poisson = "normal",
    # tests/backends/test_device_knobs.py): the FRACTION OF COUNTS differing from
    # poisson_counts.poisson(..., normal_above=1000) at rates 0 to 1e7; a count moves only where
    # rate + sqrt(rate) z falls within the device libm's ulps of a half integer. Measured 0 of 2.3e5
    # (Intel's CPU runtime, PoCL, an NVIDIA H200). Without fp64 the sum rounds in float (0.5 % of
    # counts move at 1e5, half at 1e7): statistics only.
    ("poisson_normal_agreement", "opencl", "float32"): (0.0, 1e-5),
    ("poisson_normal_agreement", "opencl", "float64"): (0.0, 1e-5),
    # -- Warp random --
    # gpu_blur/warp_kernels/random.py against rng (tests/backends/test_device_random.py), on Warp's
    # "cpu" device (x86-64) and on CUDA (an NVIDIA H200); the samplers are float64 whatever the
    # caller's type, and the test module is built with fuse_fp=False. Words and uniforms are
    # compared bit for bit (no row).
    # Normals: the reference's operations through Warp's libm (measured 4.4e-16 on the CPU,
    # 8.9e-16 on the H200, over 2e5 pixels x 6 normals and 5e4 pairs).
    ("normal", "warp", "float64"): (0.0, 1e-12),
    # log(k!), k = 0 .. 1e12: the table exactly, Stirling through Warp's log (measured 0.0 on
    # both; 1.5e-16 relative on the H200 with fuse_fp=True).
    ("log_factorial", "warp", "float64"): (F64_LOG_FACTORIAL, 0.0),
    # Poisson counts: the FRACTION OF PIXELS whose count differs from poisson_counts.poisson, as
    # atol against 0 (issue: identical on >= 99.999 %). Measured 0 of 1.2e6 + 8.2e5 pixels on
    # both devices, with fuse_fp=False and (H200) fuse_fp=True.
    ("poisson_agreement", "warp", "float64"): (0.0, 1e-5),
    # The normal approximation above a threshold, as the OpenCL row
    # (tests/backends/test_device_knobs.py): measured 0 of 2.3e5 counts on the CPU and on an H200.
    ("poisson_normal_agreement", "warp", "float64"): (0.0, 1e-5),
    # -- fast maths (output.fast_math) --
    # float32 builds with GB_FAST_MATH (OpenCL native_powr in the sRGB curves, native_log /
    # sqrt / cos / sin in the normals; kernels/opencl/include/gb_math.h) and Warp modules built
    # with its fast_math option (CUDA's approximate float intrinsics, which also flush
    # denormals to zero; Warp's CPU compiler ignores the option) with float32 normals
    # (random.pixel_normal_fast), against the reference (tests/backends/test_device_knobs.py).
    # Measured on Intel's CPU OpenCL runtime, Warp's CPU device and
    # an NVIDIA H200 (OpenCL and Warp CUDA give the same numbers there).
    # OpenCL leaves native_ accuracy to the runtime, so its rows are the largest measured:
    # Intel's runtime told to build for AVX2 (CL_CONFIG_CPU_TARGET_ARCH=core-avx2, as on a CPU
    # without AVX-512) takes far coarser approximations than with AVX-512.
    # sRGB, relative: OpenCL 4.0e-6 / 8.4e-6 (decode / encode, Intel, AVX-512), 1.5e-4 / 2.1e-4
    # (Intel, AVX2), 7.7e-7 / 6.8e-7 (H200); Warp 3.6e-7 / 2.0e-7 (CPU) and 7.7e-7 / 6.8e-7
    # (CUDA), whose denormal results become 0 (below 1.2e-38).
    ("srgb_to_linear", "opencl", "float32-fast"): (2e-4, 1e-45),
    ("linear_to_srgb", "opencl", "float32-fast"): (3e-4, 1e-45),
    ("srgb_to_linear", "warp", "float32-fast"): (1e-6, 1.2e-38),
    ("linear_to_srgb", "warp", "float32-fast"): (1e-6, 1.2e-38),
    # Normals, absolute: 8.0e-7 (Intel, AVX-512), 4.5e-5 (Intel, AVX2), 7.8e-7 (Warp CPU),
    # 1.6e-5 (H200, both backends) over 6e5 normals. A fast log's absolute error near 1 reaches
    # r = sqrt(-2 log u1) divided by 2 r, so it grows where u1 nears 1 and r is smallest: the
    # H200's worst is at z = -0.0026.
    ("normal", "opencl", "float32-fast"): (0.0, 6e-5),
    ("normal", "warp", "float32-fast"): (0.0, 2e-5),
    # The whole pipeline with output.fast_math (tests/backends/test_knobs_backends.py: trajectory
    # blur, saturation, RAW round trip, noise none or sRGB Gaussian, float output) against the
    # float64 reference: OpenCL 4.9e-6 / 1.2e-5 (Intel with AVX-512, noise none / Gaussian),
    # 1.19e-4 / 1.19e-4 (Intel, AVX2), 6.6e-7 (PoCL), 5.5e-7 (H200); Warp 7.5e-7 (CPU), 8.2e-7
    # (CUDA).
    ("pipeline_fast_math", "opencl", "float32"): (0.0, 2e-4),
    ("pipeline_fast_math", "warp", "float32"): (0.0, 2e-6),
    # -- backends against the reference (tests/backends/test_backends.py) --
    # numpy is the reference: it must agree with itself exactly, tiled or not.
    **{(stage, "numpy", "float64"): (0.0, 0.0) for stage in (
        "accumulate", "to_raw", "saturate", "finish", "finish_crf_polynomial", "pipeline",
        "quantize_code_changes")},
    ("to_raw_noisy_outliers", "numpy", "float64"): (0.0, 0.0),
    ("pipeline_noisy", "numpy", "float64"): (0.0, 0.0),
    ("pipeline_noisy_outliers", "numpy", "float64"): (0.0, 0.0),
    # Kernel backends against the reference: one claim for OpenCL and Warp, measured on
    # Intel's CPU OpenCL runtime, Warp's CPU device and an NVIDIA H200 (the larger value).
    **{(stage, backend, dtype): tol for backend in ("opencl", "warp")
       for (stage, dtype), tol in {
        # float32: float rounding of pow/exp in the sRGB curves and of 3 x 3 sums.
        ("accumulate", "float32"): (0.0, 1e-6),  # measured 4.6e-7
        ("saturate", "float32"): (0.0, 1e-7),  # 3.0e-8
        ("to_raw", "float32"): (0.0, 5e-7),  # 1.4e-7 (noise draws identical)
        ("finish", "float32"): (0.0, 1e-6),  # 4.4e-7
        # float32 Horner of the A7R3 polynomial cancels (coefficients up to 368): pipeline
        # note section 8 bounds it at 3e-5.
        ("finish_crf_polynomial", "float32"): (0.0, 3e-5),  # 2.65e-5 (Warp), 1.85e-5 (OpenCL)
        # A value within float32 rounding of a code boundary may round to the next code: at
        # most one code, on this fraction of values (3.3e-5 at 8 bits, 1.1e-3 at 16 bits).
        ("quantize_code_changes", "float32"): (0.0, 2e-3),
        # whole pipeline, real photographs, noise off (issue target 2e-4): measured 1.6e-6.
        ("pipeline", "float32"): (0.0, 1e-5),
        # With noise, the float32 linear image differs from float64 by ~5e-7 relative, so a
        # Poisson rate near 1e4 moves by ~5e-3 and its count flips on a few bright pixels; the
        # flip (K = 9e-5 in RAW) spreads over the demosaic stencil. Issue target 1e-5; measured
        # 4.6e-5 to 2.3e-4 of values over 3 samples (max 0.016). float64 builds meet 1e-5.
        # The same float64 inputs, rounded to float32 on upload: a rate near 1e4 moves by
        # ~1e-3 and flips a count on 4.3e-5 of values on real photos (3.1 M values measured;
        # 0 on the test's crop); float64 builds flip none.
        ("to_raw_noisy_outliers", "float32"): (0.0, 1e-4),
        ("pipeline_noisy", "float32"): (0.0, 2e-4),  # the bound per value
        ("pipeline_noisy_outliers", "float32"): (0.0, 3e-4),
        # float64: the reference's operations in another order.
        ("accumulate", "float64"): (0.0, 1e-14),  # 9.7e-16 (direct sum vs FFT)
        ("saturate", "float64"): (0.0, 1e-15),  # 0
        ("to_raw", "float64"): (0.0, 1e-14),  # 2.2e-16
        ("finish", "float64"): (0.0, 1e-14),  # 6.7e-16
        ("finish_crf_polynomial", "float64"): (0.0, F64_CRF_POLYNOMIAL),  # 4.4e-14
        ("quantize_code_changes", "float64"): (0.0, 0.0),
        ("pipeline", "float64"): (0.0, 1e-12),  # 0 (after the float32 result cast)
        ("to_raw_noisy_outliers", "float64"): (0.0, 1e-5),
        ("pipeline_noisy", "float64"): (0.0, 1e-12),
        ("pipeline_noisy_outliers", "float64"): (0.0, 1e-5),
    }.items()},
    # Spot checks of runs with output.fast_math (float32 only; gpu_blur.scheduler reads these
    # rows as dtype "float32-fast"): the float32 rows, wider where the fast sRGB curves act.
    # Measured per pass on Intel's CPU OpenCL runtime over 15 samples (average with A7R3
    # re-toning, 8 and 16 bits, sRGB Gaussian noise, trajectory, kernel blur): accumulate
    # 3.3e-6 (the 8-bit table is made with the fast EOTF), finish 1.5e-5, finish with the A7R3
    # polynomial 2.8e-5, to_raw 1.0e-7, saturate 4.3e-8. Warp's CPU compiler ignores fast
    # maths; CUDA's fast sRGB functions are within 7.7e-7 relative (rows above), Intel's 8.4e-6
    # with AVX-512. OpenCL's accumulate and finish rows cover Intel's runtime built for AVX2,
    # whose sRGB curves err up to 2.1e-4 relative (rows above): 8.4e-5 measured in accumulate.
    **{(stage, backend, "float32-fast"): tol for backend in ("opencl", "warp")
       for stage, tol in {
        "accumulate": (0.0, 2e-4 if backend == "opencl" else 1e-5),
        "saturate": (0.0, 1e-7),
        "to_raw": (0.0, 5e-7),
        "finish": (0.0, 3e-4 if backend == "opencl" else 3e-5),
        "finish_crf_polynomial": (0.0, 3.5e-4 if backend == "opencl" else 5e-5),
        "quantize_code_changes": (0.0, 2e-3),
        "to_raw_noisy_outliers": (0.0, 1e-4),
    }.items()},
    # OpenCL against Warp: each within the "pipeline" row of the reference, so within twice it.
    ("cross_backend", "kernels", "float32"): (0.0, 2e-5),
    ("cross_backend", "kernels", "float64"): (0.0, 2e-12),
    # Scenes that re-tone with the A7R3 polynomial (gpu-blur validate --against, realblur_j):
    # each within the "finish_crf_polynomial" row, so within twice it (measured 2.7e-5, PoCL
    # against Warp's CPU device, float32; 0 in float64).
    ("cross_backend_crf_polynomial", "kernels", "float32"): (0.0, 6e-5),
    ("cross_backend_crf_polynomial", "kernels", "float64"): (0.0, F64_CRF_POLYNOMIAL),
    # -- hard cases --
    # tests/backends/test_hard_cases.py: crafted inputs through the passes on every backend,
    # measured on Intel's CPU OpenCL runtime and Warp's CPU device (the larger value); numpy is the
    # reference. The sRGB curves through the passes (accumulate with blur mode none is the
    # EOTF, finish without RAW the OETF) use the pixel rows above on the kernels.
    ("srgb_to_linear", "numpy", "float64"): (0.0, 0.0),
    ("linear_to_srgb", "numpy", "float64"): (0.0, 0.0),
    # sRGB -> linear -> sRGB: just below the decode knee 0.04045 the linear value lies just above
    # the encode knee, which the curve encodes up to 3.0e-8 low (the OETF's IEC step; measured
    # 2.96e-8 in both precisions); elsewhere rounding. (linear -> sRGB -> linear is the
    # "srgb_round_trip" row, 2.3e-9 at the knee.)
    ("srgb_decode_encode", "numpy", "float64"): (1e-13, 3.2e-8),
    # A flat colour through to_raw and finish (identity camera, any WB gains, both demosaics,
    # crf none) against the colour: WB's two roundings and the demosaic sums, whose weights add
    # up to 2.5 in magnitude and mix the channels, so the error is absolute (measured 2.2e-16).
    ("flat_field_passes", "numpy", "float64"): (0.0, 1e-15),
    # A float32 sRGB input against the same 8-bit image in float64 (whole pipeline, noise off):
    # the input's rounding (<= 3e-8) through the demosaic and colour matrices (measured 6.0e-8).
    ("input_float32", "numpy", "float64"): (0.0, 2.5e-7),
    ("accumulate_long_sum", "numpy", "float64"): (0.0, 0.0),
    **{(stage, backend, dtype): tol for backend in ("opencl", "warp")
       for (stage, dtype), tol in {
        # linear -> sRGB -> linear on the device: the OETF's error times the EOTF's slope 2.4,
        # plus the EOTF's own (float32 measured 7.4e-7 relative); the knees' 2.3e-9 absolute.
        ("srgb_round_trip", "float32"): (1.5e-6, 2.5e-9),
        ("srgb_round_trip", "float64"): (1e-13, 2.5e-9),
        # sRGB -> linear -> sRGB (see the numpy row): float32 measured 6.0e-8 absolute.
        ("srgb_decode_encode", "float32"): (1e-6, 3.2e-8),
        ("srgb_decode_encode", "float64"): (1e-13, 3.2e-8),
        # Means of streamed sums, up to 1,000 frames (blur mode average) or poses
        # (trajectory). The kernels sum with compensation (accumulate.cl, gb_add_compensated),
        # so float32 keeps the one-frame error at any count: measured 2.3e-7 at 1, 2, 65 and
        # 1,000 frames and 1,000 poses (a plain float32 sum: 1.5e-5 at 1,000 equal frames,
        # 5.5e-6 at 1,000 poses). float64: the reference's own plain sum errs up to (n - 1)
        # 2^-53 = 1.1e-13 relative at 1,000 terms, plus a rounding of each term (measured
        # 2.4e-14).
        ("accumulate_long_sum", "float32"): (0.0, 1e-6),
        ("accumulate_long_sum", "float64"): (1.2e-13, 1e-15),
        # See the numpy row: measured 1.2e-7 (float32) and 2.2e-16 (float64); float32 allows
        # OpenCL's 2.5-ulp division in the white balance (see below).
        ("flat_field_passes", "float32"): (0.0, 6e-7),
        ("flat_field_passes", "float64"): (0.0, 1e-15),
        # to_raw with an identity camera and no noise against the mosaic: x / g * g, two
        # roundings, 2^-23 = 1.19e-7 relative in float32 where division is correctly rounded
        # (measured 1.05e-7; float64 2.0e-16); OpenCL lets float division err 2.5 ulps, 3
        # ulps in all (3.6e-7).
        ("white_balance_round_trip", "float32"): (4e-7, 0.0),
        ("white_balance_round_trip", "float64"): (1e-15, 0.0),
        # See the numpy row: float32 builds round a float64 input to float32 themselves
        # (measured 0); float64 measured 6.0e-8.
        ("input_float32", "float32"): (0.0, 2.5e-7),
        ("input_float32", "float64"): (0.0, 2.5e-7),
    }.items()},
    # -- quality metrics and alignment (tests/analysis/test_metrics.py, test_align.py) --
    # gpu_blur.analysis.metrics against scikit-image 0.26 (peak_signal_noise_ratio;
    # structural_similarity with gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    # channel_axis=-1) on two photographs with noise, blur, JPEG, shift and darkening, RGB and
    # one channel: the same maths summed in another order. PSNR in dB, measured <= 3.6e-15;
    # SSIM measured <= 1.6e-15.
    ("psnr", "independent", "float64"): (0.0, 1e-13),
    ("ssim", "independent", "float64"): (0.0, 1e-14),
    # noise_level(255 x) against 255 noise_level(x): the same eigenvalues scaled, rounding only
    # (measured 2.9e-15 relative).
    ("noise_level_units", "numpy", "float64"): (1e-13, 0.0),
    # ECC homography (OpenCV findTransformECC, float32) against the homography a photograph
    # was warped by (float64 bilinear), as the largest displacement of the image's corners, in
    # pixels (tests/analysis/test_align.py: 280 x 480 and 306 x 520 crops, rotations of 1.5 and 2
    # degrees, shifts of 4 to 28 px, slight perspective, 1 and 3 pyramid levels, with and
    # without 8-bit noise): measured 0.021 to 0.116 (rocket's 1.5 degree rotation, its sky
    # constrains the perspective terms weakly); 0.14 in a wider sweep (2 degrees, shifts of 8
    # to 32 px). OpenCV resamples at 1/32 px inside ECC.
    ("ecc_corners_px", "opencv", "float32"): (0.0, 0.2),
    # -- blur --
    # FrameAccumulator's plain float64 running sum of 1,000 frames in [0, 1) against np.mean
    # and an exact math.fsum mean: the running sum's bound (n - 1) * 2**-53 = 1.1e-13 relative.
    ("blur_average", "independent", "float64"): (1.2e-13, 0.0),
    # FFT convolution against cv2.filter2D / a direct sum / exact shifts, images of values
    # <= 1.5, kernels 3x3 .. 65x65: FFT rounding is absolute, a few 1e-16 times max |image|
    # (measured <= 1.4e-15).
    ("blur_convolve", "independent", "float64"): (0.0, 4e-15),
    # Bilinear warp against cv2.warpPerspective: OpenCV rounds positions to 1/32 px, an error up
    # to (|dI/dx| + |dI/dy|) / 64 = 1.8e-3 on the test's sinusoids (gradients <= 0.068, 0.047).
    ("blur_warp_opencv", "independent", "float64"): (0.0, 2e-3),
    # Bilinear warp against scipy.ndimage.map_coordinates(order=1, mode="mirror"): same maths,
    # float64 positions; the order of operations moves positions by ~1e-14 px (measured
    # <= 6e-15 on values in [0, 1]).
    ("blur_warp_bilinear", "independent", "float64"): (0.0, 2e-14),
    # A float32 output of the float64 reference (a float TIFF of `gpu-blur generate`) against
    # the same maths computed independently in float64: the cast's rounding, at most half an
    # ulp of values <= 1 (2^-25 = 2.98e-8), and ~1e-14 of float64 order (measured 2.98e-8).
    ("float32_output", "independent", "float64"): (0.0, 3e-8),
    # A motion kernel's sum after normalisation, and a blurred point's mass.
    ("kernel_sum", "numpy", "float64"): (0.0, 1e-14),
    # A motion kernel's centroid against its centre pixel, in pixels (asked: 0.5; bilinear
    # splatting keeps the first moment, so only rounding remains: measured <= 3.6e-15).
    ("kernel_centroid", "numpy", "float64"): (0.0, 1e-12),
    # Centre's path extent against extent_px: the iteration stops at 1e-13 relative
    # (SHAKE_EXTENT_RTOL); the test re-measures it with its own rounding.
    ("shake_extent", "numpy", "float64"): (2e-13, 0.0),
    # K^-1 H K against a rotation (orthonormality, determinant).
    ("shake_rotation", "numpy", "float64"): (0.0, 1e-14),
    # The mean of n <= 9 identical frames or warps by a running sum: (n - 1) * 2**-53 relative.
    ("blur_mean_of_copies", "numpy", "float64"): (1e-15, 0.0),
    # -- calibration (tests/analysis/test_calibrate.py) --
    # CIE L*a*b* -> XYZ against colour-science's Lab_to_XYZ on the ColorChecker: measured 0.
    ("lab_to_xyz", "independent", "float64"): (1e-15, 1e-17),
    # The chart's XYZ adapted by constants.D50_TO_D65 (RSBlur's MATLAB matrix) against
    # colour-science's Bradford from the chart's ICC D50 white to CIE D65 (0.3127, 0.3290):
    # the white points differ in the fourth decimal; measured 4.4e-4.
    ("chart_reference_d65", "independent", "float64"): (0.0, 5e-4),
    # Gains, alpha, T, Cam2Lin, residuals and T_p recovered from exact synthetic charts
    # (values up to 2.1, condition numbers up to ~30): measured 7.5e-15 over 50 cameras.
    ("chart_fit_exact", "numpy", "float64"): (0.0, 2e-14),
    # Box means of flat patches in 8/16-bit images against their codes / (2^bits - 1)
    # (measured 1.1e-16), and T fitted from them (measured 2.7e-15).
    ("patch_sampling", "numpy", "float64"): (0.0, 1e-14),
    # Power coefficients (up to ~60, alternating) of a monotone order-7 response fitted from
    # 300 exact samples: measured 1.4e-12.
    ("crf_fit_exact", "numpy", "float64"): (0.0, 5e-12),
    # The monotone order-7 fit of samples of the A7R3 polynomial against it on [0, 1]: the
    # polynomial dips near 0.862 and the fit may not; measured 9.45e-4 (at linear 0.918).
    ("crf_fit_a7r3", "numpy", "float64"): (0.0, 1e-3),
    # An order-7 fit of the sRGB OETF: a polynomial cannot follow its toe; measured 0.0583
    # (at linear 0, where the fit starts at 0.058), RMS 0.0038.
    ("crf_fit_srgb", "numpy", "float64"): (0.0, 0.06),
    # The response at its inverse table's nodes against the nodes: bisection to float64
    # resolution, then Horner's rounding with cancelling coefficients (measured 2.6e-14).
    ("crf_inverse_nodes", "numpy", "float64"): (0.0, 1e-13),
    # -- frame interpolation (tests/reference/test_interpolate.py) --
    # An integer-shift sequence of a photo with exact flows against its bilinear reconstruction
    # at the intermediates' sub-pixel shifts, written out independently: the same bilinear
    # maths in another order, values <= 1 (measured 1.1e-16 per frame, 2.8e-17 averaged).
    ("interpolate_translation", "numpy", "float64"): (0.0, 5e-16),
    # One intermediate frame added by gb_blur_interpolate_add / blur_interpolate_add against
    # the reference's linearized frame, sums + compensation; real frames and DIS flows, both
    # trust states present, positions and the occlusion test in float64 on both. float32: the
    # sRGB EOTF's float pow and float bilinear weights (measured 3.9e-7 on Intel's CPU OpenCL
    # runtime and Warp's CPU device); float64: the device's pow (measured 1.1e-16 on both).
    **{("interpolate", backend, dtype): tol for backend in ("opencl", "warp")
       for dtype, tol in {"float32": (0.0, 1e-6), "float64": (0.0, 1e-15)}.items()},
}


def tolerance(stage: str, backend: str = "numpy", dtype: str = "float64") -> tuple[float, float]:
    """Return ``(rtol, atol)`` for a stage; a missing row is an error, never a silent default."""
    try:
        return TOLERANCES[(stage, backend, dtype)]
    except KeyError:
        raise KeyError(
            f"no tolerance row for stage={stage!r}, backend={backend!r}, dtype={dtype!r}; "
            "add one to gpu_blur.tolerances.TOLERANCES"
        ) from None


def mismatch(actual, expected, stage: str, backend: str = "numpy", dtype: str = "float64", *,
             allowed_fraction: float = 0.0, accept=None) -> str | None:
    """Why ``actual`` is not within the row's tolerance of ``expected``, or None when it is.

    Args:
        actual: the values to check.
        expected: the values they should match (same shape).
        stage: the tolerance row's stage; each value must satisfy ``|actual - expected| <=
            atol + rtol * |expected|``.
        backend: the row's backend column (``numpy``, ``opencl``, ``warp``).
        dtype: the row's dtype column.
        allowed_fraction: values that may lie outside (an outlier row's fraction): at most
            ``floor(allowed_fraction * size)`` of them.
        accept: optional boolean array of values to accept whatever their error (a caller's
            own rule, e.g. a code change at a quantization boundary).
    """
    rtol, atol = tolerance(stage, backend, dtype)
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    if actual.shape != expected.shape:
        return f"{stage}: shape {actual.shape} != expected {expected.shape}"
    err = np.abs(actual - expected)
    bound = atol + rtol * np.abs(expected)
    bad = ~(err <= bound)
    if accept is not None:
        bad &= ~accept
    count = int(bad.sum())
    if count <= math.floor(allowed_fraction * err.size):
        return None
    idx = np.unravel_index(np.argmax(np.where(bad, err - bound, -np.inf)), err.shape)
    allowed = (f" (at most {math.floor(allowed_fraction * err.size)} may)"
               if allowed_fraction else "")
    return (f"{stage} on {backend}/{dtype}: {count} of {err.size} values out of "
            f"tolerance{allowed} (rtol={rtol:g}, atol={atol:g}); worst at {idx}: "
            f"{actual[idx]!r} vs {expected[idx]!r} (max abs error {np.nanmax(err):.3g})")
