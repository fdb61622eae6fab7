"""The numbers the kernels share with the numpy reference, taken from it in one place.

Every constant a kernel needs from the reference (sRGB curve, demosaicing taps, random stream
numbers, Poisson sampler settings, ...) is read here from its Python source and reaches both
kernel languages from this module:

- Warp: ``gpu_blur/warp_kernels/*`` import the module-level values below.
- OpenCL: :func:`opencl_header` renders them as ``#define`` lines;
  ``gpu_blur.backends.opencl`` puts that text in front of every program it builds.
  ``kernels/opencl/include/gb_constants.h`` is the same text on disk, for builds that only
  pass ``-I kernels/opencl/include`` (the device-function tests); ``python -m
  gpu_blur.kernel_constants`` rewrites it and tests/backends/test_kernel_constants.py fails when
  it is out of date.

Literals are exact: a float is written as its shortest round-trip decimal (``repr``), wrapped
in ``GB_REAL``/``GB_WIDE`` where the kernel's type decides between float and double, so a
float build rounds the decimal once to float, as it did when the kernels spelled it out.
A float32 value (``FLOAT``) is written as the hex literal of that float.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gpu_blur.reference import average, demosaic, poisson_counts, rng, transfer

__all__ = ["BILINEAR_G_X4", "BILINEAR_RB_X4", "BILINEAR_TAP_WEIGHT", "EXACT_COUNT_SHIFT",
           "EXACT_FRAMES_MAX", "EXACT_UNIT", "HALF_LOG_TWO_PI", "HEADER", "INSPECT_LOADS",
           "KERNEL_WORDS", "KERNEL_WORDS_COUNT", "LOG_FACTORIAL_TABLE", "LOG_FACTORIAL_TABLE_SIZE",
           "MALVAR2004_G_AT_RB_X8", "MALVAR2004_RB_AT_BR_X8", "MALVAR2004_RB_AT_G_COLUMN_X8",
           "MALVAR2004_RB_AT_G_ROW_X8", "MALVAR2004_TAP_WEIGHT", "OPENCL", "PHILOX_M4X32_0",
           "PHILOX_M4X32_1", "PHILOX_W32_0", "PHILOX_W32_1", "POISSON_INVERSION_MAX_K",
           "POISSON_PTRS_MIN_RATE", "PTRS", "ROUND_LIMIT", "SAMPLE_REALS", "SAMPLE_WORDS",
           "SATURATION_LEVEL", "SRGB_DECODE_KNEE", "SRGB_DECODE_KNEE_FLOAT32", "SRGB_ENCODE_KNEE",
           "SRGB_GAMMA", "SRGB_INV_GAMMA", "SRGB_OFFSET", "SRGB_SCALE", "SRGB_SLOPE", "STREAMS",
           "STREAM_SHIFT", "TWO_PI", "TWO_PI_FLOAT32", "UNIFORM_SCALE", "UNIFORM_SHIFT",
           "c_literal", "opencl_header", "value_of", "write_header"]

# -- sRGB curve (reference.transfer) --------------------------------------------------------
SRGB_DECODE_KNEE = transfer.SRGB_DECODE_KNEE
SRGB_ENCODE_KNEE = transfer.SRGB_ENCODE_KNEE
SRGB_SLOPE = transfer.SRGB_SLOPE
SRGB_GAMMA = transfer.SRGB_GAMMA
#: 1 / gamma as the reference forms it (``1.0 / SRGB_GAMMA``).
SRGB_INV_GAMMA = 1.0 / transfer.SRGB_GAMMA
SRGB_SCALE = transfer.SRGB_SCALE
SRGB_OFFSET = transfer.SRGB_OFFSET


def _float32_at_or_above(x: float) -> float:
    """The smallest float32 >= x: a float32 knee with which ``a < knee`` decides as in float64."""
    f = np.float32(x)
    if float(f) < x:
        f = np.nextafter(f, np.float32(np.inf))
    return float(f)


#: The decode knee of float32 kernels: the float nearest 0.04045 lies below it, the next one
#: up makes ``a < knee`` pick the float64 reference's branch for every float a. (The float
#: nearest the encode knee lies above it with no float in between: no such care there.)
SRGB_DECODE_KNEE_FLOAT32 = _float32_at_or_above(SRGB_DECODE_KNEE)

# -- saturation (reference.average) ------------------------------------------------------------
#: A linear value at or above this is saturated (the indicator of the accumulate pass).
SATURATION_LEVEL = average.SATURATION_LEVEL

# -- exact sums of 8-bit frames (the average's one-launch sum, gb_blur_average_exact) ---------
#: Float32 linear values of 8-bit codes are whole multiples of 2^-35: the smallest nonzero one
#: (code 1, 3.0e-4) is at least 2^-12, whose float32 spacing is 2^-35. A code's value is a
#: count of these units (at most 2^35) and a frame sum an exact integer sum of counts.
EXACT_UNIT = 2.0**-35
#: A code's table entry counts it saturated at this bit, above its units: a sum of at most
#: EXACT_FRAMES_MAX entries keeps its units below 2^42 and its saturated count above bit 47.
EXACT_COUNT_SHIFT = 48
#: Most frames the exact sum takes: up to 128 frames of such values, the compensated float32
#: sum of gb_blur_average_add is the correctly rounded sum (kernels/opencl/include/gb_sum.h),
#: which the exact sum rounds once to; so the two give the same bits.
EXACT_FRAMES_MAX = 128

# -- input checks (gb_inspect, gpu_blur.backends.kernel.KernelBackend.inspect) -------------
#: Values each work item of an inspect launch loads before counting them: the pass is bound by
#: the loads in flight, not by bandwidth (docs/performance.md#input-checks).
INSPECT_LOADS = 4

# -- demosaicing taps (reference.demosaic), as the kernels hold them ------------------------
# Kernels hold each filter times a power of two (exact) and weigh an entry by its inverse,
# ``entry * TAP_WEIGHT``, which is the reference's weight exactly.
MALVAR2004_TAP_SCALE, BILINEAR_TAP_SCALE = 8.0, 4.0
MALVAR2004_TAP_WEIGHT = 1.0 / MALVAR2004_TAP_SCALE
BILINEAR_TAP_WEIGHT = 1.0 / BILINEAR_TAP_SCALE


def _scaled(taps: np.ndarray, scale: float) -> tuple[float, ...]:
    return tuple((scale * taps).ravel().tolist())


#: Malvar 2004 filters times 8 (multiples of 1/2, exact in float), rows dy = -2 .. 2.
MALVAR2004_G_AT_RB_X8 = _scaled(demosaic.MALVAR2004_G_AT_RB, MALVAR2004_TAP_SCALE)
MALVAR2004_RB_AT_G_ROW_X8 = _scaled(demosaic.MALVAR2004_RB_AT_G_ROW, MALVAR2004_TAP_SCALE)
MALVAR2004_RB_AT_G_COLUMN_X8 = _scaled(demosaic.MALVAR2004_RB_AT_G_COLUMN, MALVAR2004_TAP_SCALE)
MALVAR2004_RB_AT_BR_X8 = _scaled(demosaic.MALVAR2004_RB_AT_BR, MALVAR2004_TAP_SCALE)
#: Bilinear filters times 4 (integers), rows dy = -1 .. 1.
BILINEAR_G_X4 = _scaled(demosaic.BILINEAR_G, BILINEAR_TAP_SCALE)
BILINEAR_RB_X4 = _scaled(demosaic.BILINEAR_RB, BILINEAR_TAP_SCALE)

# -- counter-based random draws (reference.rng, reference.poisson_counts) -------------------
#: Stream numbers (rng.Stream), by name.
STREAMS = {s.name: int(s) for s in rng.Stream}
#: Philox4x32 round multipliers and Weyl key increments (Warp; OpenCL uses Random123's header).
PHILOX_M4X32_0 = int(rng.PHILOX_M4X32_0)
PHILOX_M4X32_1 = int(rng.PHILOX_M4X32_1)
PHILOX_W32_0 = int(rng.PHILOX_W32_0)
PHILOX_W32_1 = int(rng.PHILOX_W32_1)
#: Rounds per pixel and stream: counter word 3 holds the round below the stream byte.
ROUND_LIMIT = rng._ROUND_LIMIT
STREAM_SHIFT = ROUND_LIMIT.bit_length() - 1
#: A uniform is ((bits >> UNIFORM_SHIFT) + 0.5) * UNIFORM_SCALE.
UNIFORM_SHIFT = int(rng._UNIFORM_SHIFT)
UNIFORM_SCALE = rng._UNIFORM_SCALE
#: 2 pi in float64 (Box-Muller's angle), and rounded to float32 (the fast float normals).
TWO_PI = rng._TWO_PI
TWO_PI_FLOAT32 = float(np.float32(TWO_PI))
#: log(k!) for k below the table's size, then Stirling's series with 0.5 log(2 pi).
LOG_FACTORIAL_TABLE = tuple(poisson_counts.LOG_FACTORIAL_TABLE.tolist())
LOG_FACTORIAL_TABLE_SIZE = len(LOG_FACTORIAL_TABLE)
HALF_LOG_TWO_PI = poisson_counts._HALF_LOG_TWO_PI
POISSON_PTRS_MIN_RATE = poisson_counts.POISSON_PTRS_MIN_RATE
POISSON_INVERSION_MAX_K = poisson_counts.POISSON_INVERSION_MAX_K
#: PTRS (Hörmann 1993): setup, candidate shift, squeeze and tail bounds (poisson_counts.PTRS_*).
PTRS = {name: getattr(poisson_counts, f"PTRS_{name}") for name in (
    "B0", "B1", "A0", "A1", "IA0", "IA1", "IA2", "VR0", "VR1", "K_SHIFT", "US_SQUEEZE",
    "US_TAIL")}

# -- per-sample tables of a batched launch (gpu_blur.backends.kernel) -----------------------
#: A sample's row of uint32 words in the to_raw and finish launches: its Bayer pattern
#: (gb_cfa_channel's packed channels), its sample index, its slot in the batch's buffers.
SAMPLE_WORDS = ("cfa", "sample_index", "slot")
#: A sample's row of drawn reals (gpu_blur.params) in the to_raw and finish launches, in this
#: order (to_raw reads the first five, finish the last), with the value a plan that does not
#: draw one passes (the kernels do not read it then).
SAMPLE_REALS = (("alpha", 0.0), ("red_gain", 1.0), ("blue_gain", 1.0), ("shot_noise_k", 1.0),
                ("read_noise_std", 0.0), ("gaussian_std", 0.0))
SAMPLE_WORDS_COUNT, SAMPLE_REALS_COUNT = len(SAMPLE_WORDS), len(SAMPLE_REALS)
#: A sample's row of uint32 words in the batched kernel blur (gb_blur_kernel): where its kernel
#: starts in the launch's taps, the kernel's height and width, the sample's slot.
KERNEL_WORDS = ("offset", "height", "width", "slot")
KERNEL_WORDS_COUNT = len(KERNEL_WORDS)

# -- rendering for OpenCL -------------------------------------------------------------------
#: How a value is written in OpenCL C: in the compute type ``real`` (GB_REAL), in the
#: samplers' wide type (GB_WIDE), as a double, as the exact float32 (hex), unsigned, int.
REAL, WIDE, DOUBLE, FLOAT, UINT, INT = "real", "wide", "double", "float", "uint", "int"

#: (macro, name in this module, how it is written), in the order the header lists them.
#: A tuple value becomes a brace initializer of its elements.
OPENCL: tuple[tuple[str, str, str], ...] = (
    ("GB_SRGB_DECODE_KNEE_DOUBLE", "SRGB_DECODE_KNEE", DOUBLE),
    ("GB_SRGB_DECODE_KNEE_FLOAT", "SRGB_DECODE_KNEE_FLOAT32", FLOAT),
    ("GB_SRGB_ENCODE_KNEE", "SRGB_ENCODE_KNEE", REAL),
    ("GB_SRGB_SLOPE", "SRGB_SLOPE", REAL),
    ("GB_SRGB_GAMMA", "SRGB_GAMMA", REAL),
    ("GB_SRGB_INV_GAMMA", "SRGB_INV_GAMMA", REAL),
    ("GB_SRGB_SCALE", "SRGB_SCALE", REAL),
    ("GB_SRGB_OFFSET", "SRGB_OFFSET", REAL),
    ("GB_SATURATION_LEVEL", "SATURATION_LEVEL", REAL),
    ("GB_EXACT_UNIT", "EXACT_UNIT", FLOAT),
    ("GB_EXACT_COUNT_SHIFT", "EXACT_COUNT_SHIFT", UINT),
    ("GB_INSPECT_LOADS", "INSPECT_LOADS", INT),
    ("GB_MALVAR2004_TAP_WEIGHT", "MALVAR2004_TAP_WEIGHT", REAL),
    ("GB_MALVAR2004_G_AT_RB_X8", "MALVAR2004_G_AT_RB_X8", REAL),
    ("GB_MALVAR2004_RB_AT_G_ROW_X8", "MALVAR2004_RB_AT_G_ROW_X8", REAL),
    ("GB_MALVAR2004_RB_AT_G_COLUMN_X8", "MALVAR2004_RB_AT_G_COLUMN_X8", REAL),
    ("GB_MALVAR2004_RB_AT_BR_X8", "MALVAR2004_RB_AT_BR_X8", REAL),
    ("GB_BILINEAR_TAP_WEIGHT", "BILINEAR_TAP_WEIGHT", REAL),
    ("GB_BILINEAR_G_X4", "BILINEAR_G_X4", REAL),
    ("GB_BILINEAR_RB_X4", "BILINEAR_RB_X4", REAL),
    *((f"GB_STREAM_{name}", f"STREAMS.{name}", UINT) for name in STREAMS),
    ("GB_STREAM_SHIFT", "STREAM_SHIFT", UINT),
    ("GB_ROUND_LIMIT", "ROUND_LIMIT", UINT),
    ("GB_UNIFORM_SHIFT", "UNIFORM_SHIFT", UINT),
    ("GB_UNIFORM_SCALE", "UNIFORM_SCALE", REAL),
    ("GB_TWO_PI_DOUBLE", "TWO_PI", DOUBLE),
    ("GB_TWO_PI_FLOAT", "TWO_PI_FLOAT32", FLOAT),
    ("GB_LOG_FACTORIAL_TABLE", "LOG_FACTORIAL_TABLE", WIDE),
    ("GB_LOG_FACTORIAL_TABLE_SIZE", "LOG_FACTORIAL_TABLE_SIZE", INT),
    ("GB_HALF_LOG_TWO_PI", "HALF_LOG_TWO_PI", WIDE),
    ("GB_POISSON_PTRS_MIN_RATE", "POISSON_PTRS_MIN_RATE", WIDE),
    ("GB_POISSON_INVERSION_MAX_K", "POISSON_INVERSION_MAX_K", INT),
    *((f"GB_PTRS_{name}", f"PTRS.{name}", WIDE) for name in PTRS),
    ("GB_SAMPLE_WORDS", "SAMPLE_WORDS_COUNT", INT),
    ("GB_SAMPLE_REALS", "SAMPLE_REALS_COUNT", INT),
    ("GB_KERNEL_WORDS", "KERNEL_WORDS_COUNT", INT),
)

#: The header on disk (see the module docstring), relative to the kernels' folder.
HEADER = Path("include") / "gb_constants.h"


def value_of(name: str):
    """The current value of a name of :data:`OPENCL` (``STREAMS.X``: an entry of a dict)."""
    table, _, key = name.partition(".")
    return globals()[table][key] if key else globals()[name]


def c_literal(value, how: str) -> str:
    """``value`` as an OpenCL C expression of kind ``how`` (see :data:`OPENCL`), exactly."""
    if isinstance(value, Sequence):
        return "{" + ", ".join(c_literal(v, how) for v in value) + "}"
    if how in (UINT, INT):
        if value != int(value) or value < 0 or value >= 2**31:
            raise ValueError(f"kernel constant {value!r} is no int in [0, 2^31)")
        return f"{int(value)}u" if how == UINT else str(int(value))
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"kernel constant {value!r} is not finite")
    if how == FLOAT:
        if float(np.float32(value)) != value:
            raise ValueError(f"kernel constant {value!r} is no float32")
        return f"{value.hex()}f"
    text = repr(value)  # shortest decimal that reads back as this double; has '.' or 'e'
    return {REAL: f"GB_REAL({text})", WIDE: f"GB_WIDE({text})", DOUBLE: text}[how]


def opencl_header() -> str:
    """The ``#define`` lines of every kernel constant, from the current Python values."""
    lines = [
        "/* gb_constants.h: the kernels' constants from the numpy reference. GENERATED by",
        " * gpu_blur.kernel_constants from the Python values; do not edit (python -m",
        " * gpu_blur.kernel_constants rewrites it). GB_REAL and GB_WIDE are gb_common.h's and",
        " * gb_random.h's literal wrappers of the compute and the samplers' types. */",
        "#ifndef GB_CONSTANTS_H",
        "#define GB_CONSTANTS_H",
    ]
    for macro, name, how in OPENCL:
        text = textwrap.wrap(f"#define {macro} {c_literal(value_of(name), how)}", width=94,
                             subsequent_indent="    ", break_long_words=False)
        lines.append(" \\\n".join(text))  # a long initializer continues on the next lines
    lines.append("#endif")
    return "\n".join(lines) + "\n"


def write_header(kernels: Path) -> Path:
    """Write :func:`opencl_header` to ``kernels/``:data:`HEADER`; returns its path."""
    path = kernels / HEADER
    path.write_text(opencl_header())
    return path


if __name__ == "__main__":
    from gpu_blur.backends.opencl import kernel_dir

    print(f"wrote {write_header(kernel_dir())}")
