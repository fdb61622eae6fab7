"""The kernels' constants come from the numpy reference (gpu_blur.kernel_constants).

The expected values are read from the reference modules themselves, so a constant retyped on
either side (a kernel, Warp, kernel_constants, the header on disk) fails here.
"""

import math
import re
from fractions import Fraction

import numpy as np
import pytest
from conftest import BACKEND_SPECS, make_backend

from gpu_blur import kernel_constants
from gpu_blur.reference import average, demosaic, poisson_counts, rng, transfer

OPENCL = [s for s in BACKEND_SPECS if s.startswith("opencl")]

#: The sRGB curve constants as the reference uses them (1 / gamma as its quotient).
SRGB = [transfer.SRGB_ENCODE_KNEE, transfer.SRGB_SLOPE, transfer.SRGB_GAMMA,
        1.0 / transfer.SRGB_GAMMA, transfer.SRGB_SCALE, transfer.SRGB_OFFSET]
PTRS = ["B0", "B1", "A0", "A1", "IA0", "IA1", "IA2", "VR0", "VR1", "K_SHIFT", "US_SQUEEZE",
        "US_TAIL"]
MALVAR = [demosaic.MALVAR2004_G_AT_RB, demosaic.MALVAR2004_RB_AT_G_ROW,
          demosaic.MALVAR2004_RB_AT_G_COLUMN, demosaic.MALVAR2004_RB_AT_BR]
BILINEAR = [demosaic.BILINEAR_G, demosaic.BILINEAR_RB]
#: The taps as the kernels hold them: Malvar's times 8, bilinear's times 4.
TAPS = [8.0 * t for t in MALVAR] + [4.0 * t for t in BILINEAR]


#: One literal of a rendered constant: wrapped in GB_REAL/GB_WIDE, a float32 hex, or bare.
LITERAL = r"(?:GB_REAL|GB_WIDE)\(([^)]*)\)|(0x[0-9a-f.]+p[-+]\d+)f|(-?[\d.e+-]+)u?"


def nearest_float32(decimal: str) -> np.float32:
    """The float32 nearest a decimal literal, rounded once (as an OpenCL ``...f`` literal)."""
    exact = Fraction(decimal)
    guess = np.float32(float(exact))
    around = [np.nextafter(guess, np.float32(-np.inf)), guess,
              np.nextafter(guess, np.float32(np.inf))]
    return min(around, key=lambda f: abs(Fraction(float(f)) - exact))


def test_header_on_disk_is_the_rendering_of_the_python_values():
    from gpu_blur.backends.opencl import kernel_dir

    on_disk = (kernel_dir() / kernel_constants.HEADER).read_text()
    assert on_disk == kernel_constants.opencl_header(), (
        f"{kernel_constants.HEADER} is out of date with gpu_blur.kernel_constants: run "
        "python -m gpu_blur.kernel_constants")


def test_every_literal_reads_back_as_its_python_value_in_both_precisions():
    for macro, name, how in kernel_constants.OPENCL:
        value = kernel_constants.value_of(name)
        values = value if isinstance(value, tuple) else (value,)
        text = kernel_constants.c_literal(value, how)
        literals = re.findall(LITERAL, text)
        assert len(literals) == len(values), (macro, text)
        for (wrapped, hex_float, bare), v in zip(literals, values, strict=True):
            if hex_float:
                assert float.fromhex(hex_float) == v, macro
            elif how in (kernel_constants.UINT, kernel_constants.INT):
                assert int(bare) == v, macro
            else:
                decimal = wrapped or bare
                assert float(decimal) == v, macro
                # a float build reads the decimal once into float; Warp rounds the double:
                # both must give the same float
                assert nearest_float32(decimal) == np.float32(v), macro


def opencl_source() -> str:
    reals = ["GB_SRGB_ENCODE_KNEE", "GB_SRGB_SLOPE", "GB_SRGB_GAMMA", "GB_SRGB_INV_GAMMA",
             "GB_SRGB_SCALE", "GB_SRGB_OFFSET", "GB_SATURATION_LEVEL", "GB_UNIFORM_SCALE",
             "GB_SRGB_DECODE_KNEE", "(real)GB_TWO_PI_FLOAT", "GB_MALVAR2004_TAP_WEIGHT",
             "GB_BILINEAR_TAP_WEIGHT"]
    words = [f"GB_STREAM_{s.name}" for s in rng.Stream] + [
        "GB_STREAM_SHIFT", "GB_ROUND_LIMIT", "GB_UNIFORM_SHIFT", "GB_POISSON_INVERSION_MAX_K",
        "GB_LOG_FACTORIAL_TABLE_SIZE"]
    wide = ["GB_HALF_LOG_TWO_PI", "GB_POISSON_PTRS_MIN_RATE", "(gb_wide)GB_TWO_PI_DOUBLE",
            *(f"GB_PTRS_{name}" for name in PTRS)]
    taps = ["GB_MALVAR2004_G_AT_RB", "GB_MALVAR2004_RB_AT_G_ROW", "GB_MALVAR2004_RB_AT_G_COLUMN",
            "GB_MALVAR2004_RB_AT_BR", "GB_BILINEAR_G", "GB_BILINEAR_RB"]
    lines = [f"reals[{i}] = {x};" for i, x in enumerate(reals)]
    lines += [f"words[{i}] = (uint)({x});" for i, x in enumerate(words)]
    lines += [f"wide[{i}] = {x};" for i, x in enumerate(wide)]
    lines += [f"for (int k = 0; k < 16; ++k) wide[{len(wide)} + k] = gb_log_factorial_table[k];"]
    offset = len(reals)
    for t, n in zip(taps, (25, 25, 25, 25, 9, 9), strict=True):
        lines.append(f"for (int k = 0; k < {n}; ++k) reals[{offset} + k] = {t}[k];")
        offset += n
    return ('#include "gb_pixel.h"\n#include "gb_random.h"\n#include "gb_demosaic.h"\n'
            "__kernel void constants(__global real *reals, __global uint *words,\n"
            "                        __global gb_wide *wide)\n{\n    "
            + "\n    ".join(lines) + "\n}\n")


def opencl_constants(backend):
    """What a program built by ``backend`` sees: (reals, words, wide) as numpy arrays."""
    import pyopencl as cl

    wide_type = np.float64 if backend.info.fp64 else np.float32
    outs = [np.zeros(12 + 118, backend.real), np.zeros(12, np.uint32),
            np.zeros(3 + len(PTRS) + 16, wide_type)]
    bufs = [cl.Buffer(backend.ctx, cl.mem_flags.WRITE_ONLY, o.nbytes) for o in outs]
    backend.program_from_source(opencl_source()).constants(backend.queue, (1,), None, *bufs)
    for o, b in zip(outs, bufs, strict=True):
        cl.enqueue_copy(backend.queue, o, b)
    return outs


@pytest.mark.skipif(not OPENCL, reason="needs an OpenCL device")
@pytest.mark.parametrize("spec", OPENCL)
def test_opencl_kernels_see_the_reference_values(spec):
    backend = make_backend(spec).backend
    reals, words, wide = opencl_constants(backend)
    real = backend.real
    expected = [*SRGB, average.SATURATION_LEVEL, rng._UNIFORM_SCALE]
    assert reals[:8].tolist() == [real(v) for v in expected]
    knee = real(reals[8])
    if real is np.float64:
        assert knee == transfer.SRGB_DECODE_KNEE
    else:  # the float at or just above the knee: `a < knee` decides as in float64
        assert float(knee) >= transfer.SRGB_DECODE_KNEE
        assert float(np.nextafter(knee, real(0))) < transfer.SRGB_DECODE_KNEE
    assert reals[9] == np.float32(2.0 * math.pi)
    malvar_weight, bilinear_weight = reals[10:12]
    taps = np.split(reals[12:], np.cumsum([t.size for t in TAPS])[:-1])
    # the kernel's weight of an entry is the reference's tap, exactly
    for held, weight, tap in zip(taps, [malvar_weight] * 4 + [bilinear_weight] * 2,
                                 MALVAR + BILINEAR, strict=True):
        assert (held.astype(np.float64) * float(weight)).tolist() == tap.ravel().tolist()
    assert words[:7].tolist() == [int(s) for s in rng.Stream]
    shift, limit, uniform_shift, max_k, table_size = words[7:].tolist()
    assert (1 << shift, limit) == (rng._ROUND_LIMIT, rng._ROUND_LIMIT)
    assert (uniform_shift, max_k) == (rng._UNIFORM_SHIFT, poisson_counts.POISSON_INVERSION_MAX_K)
    assert table_size == poisson_counts.LOG_FACTORIAL_TABLE.size
    w = wide.dtype.type
    ptrs = [getattr(poisson_counts, f"PTRS_{name}") for name in PTRS]
    assert wide.tolist() == [w(v) for v in (poisson_counts._HALF_LOG_TWO_PI,
                                            poisson_counts.POISSON_PTRS_MIN_RATE, 2.0 * math.pi,
                                            *ptrs, *poisson_counts.LOG_FACTORIAL_TABLE)]


@pytest.mark.skipif(not OPENCL, reason="needs an OpenCL device")
def test_an_edited_python_value_reaches_the_opencl_build(monkeypatch):
    backend = make_backend(OPENCL[0]).backend
    monkeypatch.setattr(kernel_constants, "SRGB_SLOPE", 13.0)
    monkeypatch.setitem(kernel_constants.STREAMS, "SHOT_NOISE", 9)
    reals, words, _ = opencl_constants(backend)
    # the build's text, not the header on disk (which still says 12.92 and 4)
    assert reals[1] == 13.0
    assert words[3] == 9


def test_warp_kernels_read_the_reference_values():
    """The values Warp's kernels capture (wp.constant and module-level floats), from Python.

    Read where the kernels read them, without a compile: Warp emits each as its own literal.
    """
    pytest.importorskip("warp")
    from gpu_blur.warp_kernels import pixel, random

    knee = np.float32(pixel.SRGB_DECODE_KNEE_FLOAT32)
    assert float(knee) == pixel.SRGB_DECODE_KNEE_FLOAT32
    assert float(knee) >= transfer.SRGB_DECODE_KNEE
    assert float(np.nextafter(knee, np.float32(0))) < transfer.SRGB_DECODE_KNEE
    curve = [pixel.SRGB_DECODE_KNEE, pixel.SRGB_ENCODE_KNEE, pixel.SRGB_SLOPE, pixel.SRGB_GAMMA,
             pixel.SRGB_INV_GAMMA, pixel.SRGB_SCALE, pixel.SRGB_OFFSET]
    assert curve == [transfer.SRGB_DECODE_KNEE, *SRGB]
    held = [pixel.MALVAR2004_G_AT_RB, pixel.MALVAR2004_RB_AT_G_ROW,
            pixel.MALVAR2004_RB_AT_G_COLUMN, pixel.MALVAR2004_RB_AT_BR, pixel.BILINEAR_G,
            pixel.BILINEAR_RB]
    weights = [pixel.MALVAR2004_TAP_WEIGHT] * 4 + [pixel.BILINEAR_TAP_WEIGHT] * 2
    for matrix, weight, tap in zip(held, weights, MALVAR + BILINEAR, strict=True):
        assert (np.array(matrix, np.float64) * weight).ravel().tolist() == tap.ravel().tolist()
    streams = [random.PARAMS, random.TRAJECTORY, random.KERNEL, random.SHOT_NOISE,
               random.READ_NOISE, random.SRGB_NOISE, random.SPOT_CHECK]
    assert [int(s) for s in streams] == [int(s) for s in rng.Stream]
    assert int(random.ROUND_LIMIT) == rng._ROUND_LIMIT
    assert 1 << int(random._STREAM_SHIFT) == rng._ROUND_LIMIT
    assert int(random._UNIFORM_SHIFT) == rng._UNIFORM_SHIFT
    assert float(random._UNIFORM_SCALE) == rng._UNIFORM_SCALE
    assert float(random._TWO_PI) == 2.0 * math.pi
    assert float(random._TWO_PI_F32) == float(np.float32(2.0 * math.pi))
    assert list(random.LOG_FACTORIAL_TABLE) == poisson_counts.LOG_FACTORIAL_TABLE.tolist()
    assert float(random._F_TABLE) == poisson_counts.LOG_FACTORIAL_TABLE.size
    assert float(random._HALF_LOG_TWO_PI) == poisson_counts._HALF_LOG_TWO_PI
    assert float(random.POISSON_PTRS_MIN_RATE) == poisson_counts.POISSON_PTRS_MIN_RATE
    assert int(random.POISSON_INVERSION_MAX_K) == poisson_counts.POISSON_INVERSION_MAX_K
    ptrs = {"B0": random._PTRS_B0, "B1": random._PTRS_B1, "A0": random._PTRS_A0,
            "A1": random._PTRS_A1, "IA0": random._PTRS_IA0, "IA1": random._PTRS_IA1,
            "IA2": random._PTRS_IA2, "VR0": random._PTRS_VR0, "VR1": random._PTRS_VR1,
            "K_SHIFT": random._PTRS_SHIFT, "US_SQUEEZE": random._PTRS_US_SQUEEZE,
            "US_TAIL": random._PTRS_US_TAIL}
    assert {k: float(v) for k, v in ptrs.items()} == {
        k: getattr(poisson_counts, f"PTRS_{k}") for k in PTRS}
    philox = [random._PHILOX_M0, random._PHILOX_M1, random._PHILOX_W0, random._PHILOX_W1]
    assert [int(v) for v in philox] == [int(rng.PHILOX_M4X32_0), int(rng.PHILOX_M4X32_1),
                                        int(rng.PHILOX_W32_0), int(rng.PHILOX_W32_1)]
