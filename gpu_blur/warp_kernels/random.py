"""Counter-based random draws as Warp device functions: the Warp side of the reference's draws.

They repeat gpu_blur/reference/rng.py and gpu_blur/reference/poisson_counts.py.

Provides Philox4x32-10 (:func:`philox4x32`), the per-pixel words (:func:`pixel_bits`),
uniforms (:func:`uniform`), Box-Muller normals (:func:`box_muller`, :func:`pixel_normal`, and
the float32 :func:`pixel_normal_fast` of scene ``output.fast_math``), ``log(k!)``
(:func:`log_factorial`), the Poisson sampler (:func:`poisson`) and its normal approximation
above a threshold rate (:func:`poisson_normal_above`, scene ``noise.poisson = "normal"``), all
``@wp.func``, for kernels of the Warp backend to call. kernels/opencl/include/gb_random.h is
the OpenCL port of the same functions.

The contract is the module docstrings of rng.py and poisson_counts.py, repeated here operation
for operation:

key
    ``(key0, key1) = (seed & 0xFFFFFFFF, seed >> 32)`` (``rng.key_from_seed``), two
    ``wp.uint32`` arguments.
counter
    ``(x, y, sample_index, (stream << 24) | round)``; ``x`` and ``y`` are the pixel's GLOBAL
    column and row, ``round`` in ``[0, 2**24)`` numbers blocks of four words of one pixel.
uniform
    ``((bits >> 9) + 0.5) * 2**-23``: exact in float64, and exact again when cast to float32.
normals
    four per round: (cos, sin) of Box-Muller on words (0, 1), then on words (2, 3).
Poisson
    stream SHOT_NOISE; inversion on word 0 of round 0 below rate 10, PTRS at 10 and above,
    attempt ``2r`` on words (0, 1) and attempt ``2r + 1`` on words (2, 3) of round ``r``; the
    normal approximation on the cos normal of words (0, 1) of round 0.

Warp types. Words, keys, sample indices, streams, coordinates and rounds are ``wp.uint32``; a
block of four words is ``wp.vec4ui`` (Warp's built-in ``vector(length=4, dtype=uint32)``);
the two normals of :func:`box_muller` are a ``wp.vec2d``; every real is ``wp.float64``.

Precision rule. Everything after the words is float64 (Warp has it on the CPU and on CUDA),
whatever the calling kernel's compute type: the Poisson sampler must repeat the reference's
roundings to give the same count (float32 PTRS flips ``floor()`` on ~0.1 % of pixels at rate
1e4, see gb_random.h), and float32 Box-Muller misses 1e-6 for the normals. Callers round the
result once to their own type. Constants are ``wp.constant`` values of 64-bit type, so no
literal passes through float32 on its way into the generated code.

Floating-point contraction: the reference rounds every product and sum. Contraction is a
property of the module that compiles the calling kernel, not of this one, so a module that must
give the reference's Poisson counts pixel for pixel should be built with ``fuse_fp=False``
(``wp.set_module_options({"fuse_fp": False})``). With Warp's default ``fuse_fp=True`` the
compiler may fuse ``a * b + c``, which can move a ``floor()`` or a CDF comparison across its
boundary on a rare pixel; the tests' 2e6 pixels still gave identical counts that way on an
H200 (the measured agreement is in gpu_blur/tolerances.py, section "Warp random").
"""

from __future__ import annotations

import math

import warp as wp

from gpu_blur import kernel_constants as constants

__all__ = [
    "KERNEL",
    "LOG_FACTORIAL_TABLE",
    "PARAMS",
    "POISSON_INVERSION_MAX_K",
    "POISSON_PTRS_MIN_RATE",
    "READ_NOISE",
    "ROUND_LIMIT",
    "SHOT_NOISE",
    "SPOT_CHECK",
    "SRGB_NOISE",
    "TRAJECTORY",
    "box_muller",
    "log_factorial",
    "philox4x32",
    "box_muller_fast",
    "pixel_bits",
    "pixel_normal",
    "pixel_normal_fast",
    "poisson",
    "poisson_normal_above",
    "poisson_normal_count",
    "uniform",
]

# The numbers below come from gpu_blur.reference.rng and .poisson_counts through
# gpu_blur.kernel_constants, which gives gb_random.h the same values.

# -- stream numbers (rng.Stream), as wp.uint32 constants -----------------------------------------
PARAMS = wp.constant(wp.uint32(constants.STREAMS["PARAMS"]))
TRAJECTORY = wp.constant(wp.uint32(constants.STREAMS["TRAJECTORY"]))
KERNEL = wp.constant(wp.uint32(constants.STREAMS["KERNEL"]))
SHOT_NOISE = wp.constant(wp.uint32(constants.STREAMS["SHOT_NOISE"]))
READ_NOISE = wp.constant(wp.uint32(constants.STREAMS["READ_NOISE"]))
SRGB_NOISE = wp.constant(wp.uint32(constants.STREAMS["SRGB_NOISE"]))
SPOT_CHECK = wp.constant(wp.uint32(constants.STREAMS["SPOT_CHECK"]))  # host only (scheduler)

# -- Philox4x32 (Random123's PHILOX_M4x32_0/1 and PHILOX_W32_0/1) -------------------------------
_PHILOX_M0 = wp.constant(wp.uint64(constants.PHILOX_M4X32_0))
_PHILOX_M1 = wp.constant(wp.uint64(constants.PHILOX_M4X32_1))
_PHILOX_W0 = wp.constant(wp.uint32(constants.PHILOX_W32_0))
_PHILOX_W1 = wp.constant(wp.uint32(constants.PHILOX_W32_1))
_SHIFT_HI = wp.constant(wp.uint64(32))
_STREAM_SHIFT = wp.constant(wp.uint32(constants.STREAM_SHIFT))
#: Rounds per pixel: bits of counter word 3 below the stream byte.
ROUND_LIMIT = wp.constant(wp.uint32(constants.ROUND_LIMIT))

# -- uniforms and Box-Muller ---------------------------------------------------------------------
_UNIFORM_SHIFT = wp.constant(wp.uint32(constants.UNIFORM_SHIFT))
_UNIFORM_SCALE = wp.constant(wp.float64(constants.UNIFORM_SCALE))
#: 2 * pi rounded to float64, as the reference's ``2.0 * math.pi``.
_TWO_PI = wp.constant(wp.float64(constants.TWO_PI))
#: 2 * pi rounded to float32 (6.2831855), for the fast normals.
_TWO_PI_F32 = wp.constant(wp.float32(constants.TWO_PI_FLOAT32))

# -- log(k!) and Poisson -------------------------------------------------------------------------
_vec16d = wp.types.vector(length=constants.LOG_FACTORIAL_TABLE_SIZE, dtype=wp.float64)
#: log(k!) for k = 0..15: poisson_counts.LOG_FACTORIAL_TABLE, the same float64 values.
LOG_FACTORIAL_TABLE = wp.constant(_vec16d(*constants.LOG_FACTORIAL_TABLE))
_HALF_LOG_TWO_PI = wp.constant(wp.float64(constants.HALF_LOG_TWO_PI))
#: poisson_counts.POISSON_PTRS_MIN_RATE: PTRS at and above this rate, inversion below.
POISSON_PTRS_MIN_RATE = wp.constant(wp.float64(constants.POISSON_PTRS_MIN_RATE))
#: poisson_counts.POISSON_INVERSION_MAX_K: hard stop of the inversion search.
POISSON_INVERSION_MAX_K = wp.constant(int(constants.POISSON_INVERSION_MAX_K))

_F0 = wp.constant(wp.float64(0.0))
_NAN = wp.constant(wp.float64(math.nan))
_F_HALF = wp.constant(wp.float64(0.5))
_F1 = wp.constant(wp.float64(1.0))
_F2 = wp.constant(wp.float64(2.0))
_F_TABLE = wp.constant(wp.float64(float(constants.LOG_FACTORIAL_TABLE_SIZE)))
_F_MINUS2 = wp.constant(wp.float64(-2.0))
# Stirling series coefficients, each formed as the reference forms it (1.0 / n in float64).
_F12 = wp.constant(wp.float64(12.0))
_F360 = wp.constant(wp.float64(360.0))
_F1260 = wp.constant(wp.float64(1260.0))
_F1680 = wp.constant(wp.float64(1680.0))
# PTRS setup and test constants (Hoermann 1993): poisson_counts.PTRS_*.
_PTRS_B0 = wp.constant(wp.float64(constants.PTRS["B0"]))
_PTRS_B1 = wp.constant(wp.float64(constants.PTRS["B1"]))
_PTRS_A0 = wp.constant(wp.float64(constants.PTRS["A0"]))
_PTRS_A1 = wp.constant(wp.float64(constants.PTRS["A1"]))
_PTRS_IA0 = wp.constant(wp.float64(constants.PTRS["IA0"]))
_PTRS_IA1 = wp.constant(wp.float64(constants.PTRS["IA1"]))
_PTRS_IA2 = wp.constant(wp.float64(constants.PTRS["IA2"]))
_PTRS_VR0 = wp.constant(wp.float64(constants.PTRS["VR0"]))
_PTRS_VR1 = wp.constant(wp.float64(constants.PTRS["VR1"]))
_PTRS_SHIFT = wp.constant(wp.float64(constants.PTRS["K_SHIFT"]))
_PTRS_US_SQUEEZE = wp.constant(wp.float64(constants.PTRS["US_SQUEEZE"]))
_PTRS_US_TAIL = wp.constant(wp.float64(constants.PTRS["US_TAIL"]))


# ------------------------------------------------------------------------------------------------
# Philox4x32-10
# ------------------------------------------------------------------------------------------------


@wp.func
def _philox_round(c: wp.vec4ui, k0: wp.uint32, k1: wp.uint32) -> wp.vec4ui:
    """One Philox4x32 round: 32 x 32 -> 64-bit products of words 0 and 2, formed in uint64."""
    prod0 = _PHILOX_M0 * wp.uint64(c[0])
    prod1 = _PHILOX_M1 * wp.uint64(c[2])
    hi0 = wp.uint32(prod0 >> _SHIFT_HI)
    lo0 = wp.uint32(prod0)  # the conversion keeps the low 32 bits
    hi1 = wp.uint32(prod1 >> _SHIFT_HI)
    lo1 = wp.uint32(prod1)
    return wp.vec4ui(hi1 ^ c[1] ^ k0, lo1, hi0 ^ c[3] ^ k1, lo0)


@wp.func
def philox4x32(counter: wp.vec4ui, key0: wp.uint32, key1: wp.uint32) -> wp.vec4ui:
    """Philox4x32-10 block function (rng.philox4x32 with rounds=10).

    Ten rounds; before every round but the first the key is bumped by the Weyl constants,
    ``k0 += 0x9E3779B9``, ``k1 += 0xBB67AE85`` (uint32 arithmetic wraps mod 2**32).
    """
    c = _philox_round(counter, key0, key1)
    k0 = key0
    k1 = key1
    for _ in range(9):  # a constant trip count: Warp unrolls it
        k0 = k0 + _PHILOX_W0
        k1 = k1 + _PHILOX_W1
        c = _philox_round(c, k0, k1)
    return c


@wp.func
def pixel_bits(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    stream: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
    round: wp.uint32,
) -> wp.vec4ui:
    """The four words of pixel ``(x, y)`` (global column, row) at ``round`` (< 2**24).

    ``counter = (x, y, sample_index, (stream << 24) | round)`` (rng.pixel_bits; note the
    argument order here is x before y, as in gb_random.h).
    """
    return philox4x32(wp.vec4ui(x, y, sample_index, (stream << _STREAM_SHIFT) | round), key0, key1)


# ------------------------------------------------------------------------------------------------
# Uniforms and normals
# ------------------------------------------------------------------------------------------------


@wp.func
def uniform(bits: wp.uint32) -> wp.float64:
    """A word as a uniform in (0, 1): ``((bits >> 9) + 0.5) * 2**-23``, exact.

    The result is an odd multiple of 2**-24 with at most 24 significant bits, so a cast to
    float32 is exact too.
    """
    return (wp.float64(bits >> _UNIFORM_SHIFT) + _F_HALF) * _UNIFORM_SCALE


@wp.func
def box_muller(u1: wp.float64, u2: wp.float64) -> wp.vec2d:
    """Box-Muller in float64 (rng.box_muller): ``r = sqrt(-2 log u1)``, ``t = (2 pi) u2``.

    Returns ``wp.vec2d(r cos t, r sin t)``.
    """
    radius = wp.sqrt(_F_MINUS2 * wp.log(u1))
    angle = _TWO_PI * u2
    return wp.vec2d(radius * wp.cos(angle), radius * wp.sin(angle))


@wp.func
def normal_words(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    stream: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
    index: wp.uint32,
) -> wp.vec2ui:
    """The two words Box-Muller turns into normal ``index`` of pixel ``(x, y)`` (and its pair).

    Round ``index // 4``; normals 0, 1 of a round come from words (0, 1), normals 2, 3 from
    words (2, 3); the normal is the cos (even ``index``) or sin (odd) of the pair.
    """
    bits = pixel_bits(key0, key1, sample_index, stream, x, y, index >> wp.uint32(2))
    if (index & wp.uint32(3)) >= wp.uint32(2):
        return wp.vec2ui(bits[2], bits[3])
    return wp.vec2ui(bits[0], bits[1])


@wp.func
def pixel_normal(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    stream: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
    index: wp.uint32,
) -> wp.float64:
    """Normal number ``index`` of pixel ``(x, y)``, as ``rng.pixel_normals(...)[..., index]``.

    Round ``index // 4``; within it normals 0, 1 are Box-Muller (cos, sin) of words (0, 1) and
    normals 2, 3 of words (2, 3).
    """
    w = normal_words(key0, key1, sample_index, stream, x, y, index)
    z = box_muller(uniform(w[0]), uniform(w[1]))
    return z[wp.int32(index & wp.uint32(1))]


@wp.func
def box_muller_fast(u1: wp.float32, u2: wp.float32) -> wp.vec2f:
    """Box-Muller in float32 (scene ``output.fast_math``), as gb_box_muller under GB_FAST_MATH.

    ``r = sqrt(-2 log u1)``; the angle is moved into [-pi, pi), where fast sin and cos are most
    accurate: ``t' = (2 pi)_f (u2 - 0.5)`` (``u2 - 0.5`` is exact), and ``cos t = -cos t'``,
    ``sin t = -sin t'``. A module built with Warp's ``fast_math`` option runs these on CUDA's
    approximate intrinsics; on the CPU they are libm's float functions. Returns
    ``wp.vec2f(r cos t, r sin t)``.
    """
    radius = wp.sqrt(wp.float32(-2.0) * wp.log(u1))
    angle = _TWO_PI_F32 * (u2 - wp.float32(0.5))
    return wp.vec2f(-radius * wp.cos(angle), -radius * wp.sin(angle))


@wp.func
def pixel_normal_fast(
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    stream: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
    index: wp.uint32,
) -> wp.float32:
    """:func:`pixel_normal` through :func:`box_muller_fast`: the same words, in float32.

    The uniforms are exact in float32 (:func:`uniform`), so only the fast Box-Muller differs.
    """
    w = normal_words(key0, key1, sample_index, stream, x, y, index)
    z = box_muller_fast(wp.float32(uniform(w[0])), wp.float32(uniform(w[1])))
    return z[wp.int32(index & wp.uint32(1))]


# ------------------------------------------------------------------------------------------------
# log(k!) and Poisson
# ------------------------------------------------------------------------------------------------


@wp.func
def log_factorial(k: wp.float64) -> wp.float64:
    """``log(k!)`` for integer-valued ``k >= 0`` (poisson_counts.log_factorial).

    The table below 16; else Stirling::

        r = 1/k;  s = r (1/12 - r^2 (1/360 - r^2 (1/1260 - r^2 / 1680)))
        log k! = (k + 0.5) log k - k + 0.5 log(2 pi) + s
    """
    if k < _F_TABLE:
        return LOG_FACTORIAL_TABLE[wp.int32(k)]
    r = _F1 / k
    r2 = r * r
    series = r * (_F1 / _F12 - r2 * (_F1 / _F360 - r2 * (_F1 / _F1260 - r2 / _F1680)))
    return (k + _F_HALF) * wp.log(k) - k + _HALF_LOG_TWO_PI + series


@wp.func
def _ptrs_attempt(
    word_u: wp.uint32,
    word_v: wp.uint32,
    mu: wp.float64,
    log_mu: wp.float64,
    a: wp.float64,
    b: wp.float64,
    inv_alpha: wp.float64,
    v_r: wp.float64,
) -> wp.vec2d:
    """One PTRS attempt (rng._ptrs_attempt): ``vec2d(k, 1.0)`` if accepted, else ``(k, 0.0)``."""
    big_u = uniform(word_u) - _F_HALF
    v = uniform(word_v)
    us = _F_HALF - wp.abs(big_u)
    # k stays floating: a rejected candidate can lie far outside the int range.
    k = wp.floor((_F2 * a / us + b) * big_u + mu + _PTRS_SHIFT)
    if us >= _PTRS_US_SQUEEZE and v <= v_r:
        return wp.vec2d(k, _F1)
    if k < _F0 or (us < _PTRS_US_TAIL and v > us):
        return wp.vec2d(k, _F0)
    lhs = wp.log(v * inv_alpha / (a / (us * us) + b))
    rhs = -mu + k * log_mu - log_factorial(k)
    if lhs <= rhs:
        return wp.vec2d(k, _F1)
    return wp.vec2d(k, _F0)


@wp.func
def poisson(
    rate: wp.float64,
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
) -> wp.float64:
    """One Poisson count at pixel ``(x, y)`` of stream SHOT_NOISE (poisson_counts.poisson), float64.

    The rate is clamped at 0 (negative rates and -0.0 give +0.0). The reference refuses
    non-finite rates; here NaN gives NaN and +inf gives +inf (as gb_poisson), so the PTRS loop
    never runs on them. Inversion below rate 10 on word 0 of round 0 (at most 64 steps); PTRS
    at 10 and above, attempts 2r and 2r + 1 on words (0, 1) and (2, 3) of round r.
    """
    if wp.isnan(rate):
        return rate
    mu = _F0
    if rate > _F0:
        mu = rate
    if wp.isinf(mu):
        return mu

    if mu < POISSON_PTRS_MIN_RATE:
        # Inversion by sequential search.
        bits = pixel_bits(key0, key1, sample_index, SHOT_NOISE, x, y, wp.uint32(0))
        u = uniform(bits[0])
        k = _F0
        p = wp.exp(-mu)
        cdf = p
        step = wp.int32(0)  # typed: a bare literal cannot be reassigned in a Warp loop
        while u > cdf and step < POISSON_INVERSION_MAX_K:
            step = step + 1
            k = wp.float64(step)
            p = p * (mu / k)
            cdf = cdf + p
        return k

    # PTRS (Hoermann 1993).
    log_mu = wp.log(mu)
    b = _PTRS_B0 + _PTRS_B1 * wp.sqrt(mu)
    a = _PTRS_A0 + _PTRS_A1 * b
    inv_alpha = _PTRS_IA0 + _PTRS_IA1 / (b - _PTRS_IA2)
    v_r = _PTRS_VR0 - _PTRS_VR1 / (b - _F2)
    block = wp.uint32(0)
    while block < ROUND_LIMIT:
        bits = pixel_bits(key0, key1, sample_index, SHOT_NOISE, x, y, block)
        first = _ptrs_attempt(bits[0], bits[1], mu, log_mu, a, b, inv_alpha, v_r)
        if first[1] != _F0:
            return first[0]
        second = _ptrs_attempt(bits[2], bits[3], mu, log_mu, a, b, inv_alpha, v_r)
        if second[1] != _F0:
            return second[0]
        block = block + wp.uint32(1)
    return _NAN  # unreachable: each attempt accepts with probability > 0.9


@wp.func
def poisson_normal_count(
    rate: wp.float64,
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
) -> wp.float64:
    """A count by the normal approximation (poisson_counts.poisson_normal_approximation), float64.

    For a finite rate >= 0: ``z`` the cos normal of :func:`box_muller` on words 0 and 1 of round
    0 of stream SHOT_NOISE, then ``max(0, floor(rate + sqrt(rate) z + 0.5))`` (rounded half
    up, clamped at 0), as gb_poisson_normal_count. Bit for bit with the reference needs a module
    built with ``fuse_fp=False``, as :func:`poisson` (see the module docstring).
    """
    bits = pixel_bits(key0, key1, sample_index, SHOT_NOISE, x, y, wp.uint32(0))
    z = box_muller(uniform(bits[0]), uniform(bits[1]))
    count = wp.floor(rate + wp.sqrt(rate) * z[0] + _F_HALF)
    if count > _F0:
        return count
    return _F0


@wp.func
def poisson_normal_above(
    rate: wp.float64,
    normal_above: wp.float64,
    key0: wp.uint32,
    key1: wp.uint32,
    sample_index: wp.uint32,
    x: wp.uint32,
    y: wp.uint32,
) -> wp.float64:
    """poisson_counts.poisson with ``normal_above``: the normal approximation above the threshold.

    Rates strictly above ``normal_above`` (>= 0, the host checks it) take
    :func:`poisson_normal_count`, all others :func:`poisson`, so counts at or below it are
    :func:`poisson`'s bit for bit; NaN and +inf go to :func:`poisson` (as gb_poisson_normal_above).
    """
    if rate > normal_above and not wp.isinf(rate):
        return poisson_normal_count(rate, key0, key1, sample_index, x, y)
    return poisson(rate, key0, key1, sample_index, x, y)
