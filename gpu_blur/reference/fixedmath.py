"""Elementary functions whose float64 results are fixed by IEEE arithmetic alone.

numpy's ``exp``, ``log``, ``sin``, ``cos``, ``power``, ``hypot``, ... take another SIMD path on
another CPU (SVML on AVX-512, libm or numpy's own kernels elsewhere) and can differ in the
last bits; BLAS (``@``, ``dot``, ``einsum``, ``linalg``) picks its kernels (and FMA) by CPU too.
Everything here is built from operations IEEE 754 rounds exactly once and identically on every
machine: ``+ - * /``, ``sqrt``, ``rint``, ``floor``, comparisons, selections and integer
operations on the bits (exponents are read and powers of two made through ``view``, not
``frexp``/``ldexp``), each a separate numpy ufunc call in a fixed order (so no compiler can
fuse a product into a sum). A sample's draws and pixels then have the same bits on any CPU.
The functions work chunk by chunk with in-place steps, which change no rounding (IEEE sums
and products commute exactly; no operation is regrouped), and fix up special values on the
elements that have them; tests/reference/test_fixedmath.py holds the plain formulas (one new
array per operation, every selection over the whole array) and checks the bits against them.

Methods (formulas and coefficients from the literature; the code is ours):

* error-free transformations: Knuth's TwoSum, Dekker's Fast2Sum and Dekker's product with
  Veltkamp's split (T. J. Dekker, "A floating-point technique for extending the available
  precision", Numer. Math. 18, 1971; J.-M. Muller et al., *Handbook of Floating-Point
  Arithmetic*, 2nd ed., 2018, ch. 4);
* ``exp``: ``x = k ln2 + r`` with a two-part (Cody and Waite, *Software Manual for the
  Elementary Functions*, 1980) ln2 whose high part has 42 bits, ``|r| <= ln2 / 2``, the Taylor
  series of ``exp(r) - 1 - r`` to degree 14 (Horner), ``1 + r`` added error-free, scaled by
  ``2**k`` built from its bits; double-double input for :func:`power`;
* ``log``: ``x = 2**e m`` with ``m`` in ``[sqrt(1/2), sqrt(2))``, ``f = (m - 1) / (m + 1)`` in
  double-double, ``log m = 2 atanh f = 2 f + 2 f^3 / 3 + ...`` (Abramowitz and Stegun 4.1.27)
  to ``f^25``, plus ``e ln2``, summed as a double-double;
* ``sin``/``cos``: Cody-Waite reduction by pi/2 in three parts (33 + 33 + 53 bits), the
  remainder kept as a double-double, Taylor polynomials on ``|r| <= pi/4`` (to ``r^19`` and
  ``r^18``), quadrant by ``q mod 4``;
* ``power(x, y) = exp(y log x)`` with ``log x`` and the product in double-double.

Accuracy (tests/reference/test_fixedmath.py, against 50-digit :mod:`decimal` values and Python's
``math``): ``exp``, ``log``, ``sin``, ``cos`` within 1 ulp of the correctly rounded value on
their tested ranges, ``power`` within 1 ulp for ``|y log x| <= 700`` and ``|y| <= 16`` (its
error grows with ``|y|`` by about ``|y| 2**-62`` relative). Results in the subnormal range
are rounded once more (a relative error up to half their coarser ulp).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "TRIG_ARGUMENT_MAX",
    "cos",
    "det3",
    "exp",
    "hypot",
    "inverse3",
    "log",
    "matmul3",
    "matvec3",
    "power",
    "sin",
    "sincos",
]

# -- constants (each checked against 50-digit decimal values in tests/reference/test_fixedmath.py)
#: ln 2 in two parts: a 42-bit high part (``k * LN2_HI`` is exact for ``|k| < 2**11``) and
#: the float64 nearest the rest.
LN2_HI = float.fromhex("0x1.62e42fefa3800p-1")
LN2_LO = float.fromhex("0x1.ef35793c76730p-45")
#: 1 / ln 2, nearest float64 (only picks ``k``; its rounding never reaches a result).
INV_LN2 = float.fromhex("0x1.71547652b82fep+0")
#: pi / 2 in three parts: 33 + 33 bits (``q * part`` exact for ``|q| < 2**20``) and the rest.
PIO2_1 = float.fromhex("0x1.921fb54400000p+0")
PIO2_2 = float.fromhex("0x1.0b4611a600000p-34")
PIO2_3 = float.fromhex("0x1.3198a2e037073p-69")
#: 2 / pi, nearest float64 (only picks the quadrant).
TWO_OVER_PI = float.fromhex("0x1.45f306dc9c883p-1")
#: sqrt(2), nearest float64: the upper bound of the reduced mantissa in :func:`log`.
SQRT2 = float.fromhex("0x1.6a09e667f3bcdp+0")
#: Largest ``|x|`` :func:`sin` and :func:`cos` accept: the three-part reduction stays exact
#: for quadrant numbers below ``2**20``.
TRIG_ARGUMENT_MAX = 2.0**20
#: exp(x) is +inf above this (the largest x with a finite result, rounded up) ...
EXP_OVERFLOW = 709.782712893384
#: ... and 0 below this (exp(x) < 2**-1075, half the smallest subnormal).
EXP_UNDERFLOW = -745.1332191019412

#: Veltkamp's splitter 2**27 + 1: splits a float64 into two 26-bit halves.
_SPLITTER = 134217729.0
_TWO54 = 2.0**54
_MANTISSA = np.int64(0x000FFFFFFFFFFFFF)
_EXP_ONE = np.int64(0x3FF0000000000000)

#: Taylor coefficients 1/n! for n = 2 .. 14 (exp), each the float64 nearest.
_EXP_COEFFS = (
    0.5,
    1.0 / 6.0,
    1.0 / 24.0,
    1.0 / 120.0,
    1.0 / 720.0,
    1.0 / 5040.0,
    1.0 / 40320.0,
    1.0 / 362880.0,
    1.0 / 3628800.0,
    1.0 / 39916800.0,
    1.0 / 479001600.0,
    1.0 / 6227020800.0,
    1.0 / 87178291200.0,
)
#: 2 / (2n + 1) for n = 1 .. 12: the atanh series of :func:`log` after its first term.
_LOG_COEFFS = tuple(2.0 / (2 * n + 1) for n in range(1, 13))
#: (-1)^n / (2n + 1)! for n = 1 .. 9 (sin) and (-1)^n / (2n)! for n = 2 .. 9 (cos).
_SIN_COEFFS = (
    -1.0 / 6.0,
    1.0 / 120.0,
    -1.0 / 5040.0,
    1.0 / 362880.0,
    -1.0 / 39916800.0,
    1.0 / 6227020800.0,
    -1.0 / 1307674368000.0,
    1.0 / 355687428096000.0,
    -1.0 / 121645100408832000.0,
)
_COS_COEFFS = (
    1.0 / 24.0,
    -1.0 / 720.0,
    1.0 / 40320.0,
    -1.0 / 3628800.0,
    1.0 / 479001600.0,
    -1.0 / 87178291200.0,
    1.0 / 20922789888000.0,
    -1.0 / 6402373705728000.0,
)


def _horner(x: np.ndarray, coeffs: tuple[float, ...]) -> np.ndarray:
    """``c0 + x (c1 + x (c2 + ...))`` from the innermost term out (two coefficients or more).

    One array updated in place; its first product is ``x * c`` for ``c * x`` (IEEE products,
    like sums, commute exactly).
    """
    acc = x * coeffs[-1]
    acc += coeffs[-2]
    for c in coeffs[-3::-1]:
        acc *= x
        acc += c
    return acc


# -- error-free transformations ------------------------------------------------------------
# Each returns new arrays and leaves its arguments alone. The in-place steps are the
# docstrings' formulas, operation for operation in the same order; ``t += s`` stands for
# ``s + t`` (exact commutation), never for a regrouping.


def _two_sum(a, b):
    """``(s, e)`` with ``s = fl(a + b)`` and ``s + e = a + b`` exactly (Knuth).

    ``bb = s - a``, ``e = (a - (s - bb)) + (b - bb)``.
    """
    s = a + b
    bb = s - a
    e = s - bb
    np.subtract(a, e, out=e)
    np.subtract(b, bb, out=bb)
    e += bb
    return s, e


def _fast_two_sum(a, b):
    """``(s, e)`` with ``s + e = a + b`` exactly, for ``|a| >= |b|`` (Dekker).

    ``e = b - (s - a)``.
    """
    s = a + b
    e = s - a
    np.subtract(b, e, out=e)
    return s, e


def _split(a):
    """Veltkamp's split: ``a = hi + lo`` with 26-bit halves (``|a| < 2**996``).

    ``c = SPLITTER a``, ``hi = c - (c - a)``, ``lo = a - hi``.
    """
    hi = a * _SPLITTER
    lo = hi - a
    np.subtract(hi, lo, out=hi)
    np.subtract(a, hi, out=lo)
    return hi, lo


def _two_prod(a, b):
    """``(p, e)`` with ``p = fl(a b)`` and ``p + e = a b`` exactly (Dekker; no FMA).

    ``e = ((ah bh - p) + ah bl + al bh) + al bl``; a square (``b is a``) is split once.
    """
    p = a * b
    ah, al = _split(a)
    bh, bl = (ah, al) if b is a else _split(b)
    e = ah * bh
    e -= p
    t = ah * bl
    e += t
    np.multiply(al, bh, out=t)
    e += t
    np.multiply(al, bl, out=t)
    e += t
    return p, e


def _pow2(k: np.ndarray) -> np.ndarray:
    """``2.0**k`` for int64 ``k`` in ``[-1022, 1023]``, made from its bits."""
    bits = k + 1023
    bits <<= 52
    return bits.view(np.float64)


def _scale(m: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``m * 2**k`` rounded once, for ``m`` in ``[0.5, 2)`` and int64 ``k`` in ``[-1080, 1030]``.

    ``(m 2**k1) 2**(k - k1)`` with ``k1 = clip(k, -1000, 1000)``: two power-of-two products;
    only the last one can round. Where every ``k`` is inside the clip the second factor is 1,
    and that exact product is left out.
    """
    if not k.size or (k.min() >= -1000 and k.max() <= 1000):
        return m * _pow2(k)
    k1 = np.clip(k, -1000, 1000)
    return (m * _pow2(k1)) * _pow2(k - k1)


#: Elements a function works on at a time: its temporaries stay in a core's cache (1 M values:
#: 390 -> ~100 ms for exp).
CHUNK = 1 << 13


def _chunked(fn, *arrays):
    """``fn`` over broadcast float64 arrays, ``CHUNK`` elements at a time.

    For elementwise functions only (each result element depends on its own inputs alone) that
    leave their arguments unchanged; returns a tuple of outputs of the broadcast shape, each
    filled chunk by chunk. A single value broadcast over the others goes in as a chunk-long
    constant.
    """
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    n = math.prod(shape)
    if n <= CHUNK:
        flat = [np.ascontiguousarray(np.broadcast_to(a, shape)).reshape(-1) for a in arrays]
        return tuple(o.reshape(shape) for o in fn(*flat))
    flat = [(np.full(CHUNK, a.reshape(-1)[0]), True) if a.size == 1
            else (np.ascontiguousarray(np.broadcast_to(a, shape)).reshape(-1), False)
            for a in arrays]
    outs = None
    for i in range(0, n, CHUNK):
        size = min(CHUNK, n - i)
        parts = fn(*(a[:size] if const else a[i:i + size] for a, const in flat))
        if outs is None:
            outs = [np.empty(n, dtype=part.dtype) for part in parts]
        for o, part in zip(outs, parts, strict=True):
            o[i:i + size] = part
    return tuple(o.reshape(shape) for o in outs)


def _as_float(x) -> tuple[np.ndarray, bool]:
    arr = np.asarray(x, dtype=np.float64)
    return arr, arr.ndim == 0


def _result(out: np.ndarray, scalar: bool):
    return out[()] if scalar else out


# -- exp ---------------------------------------------------------------------------------


def _exp_dd(zh: np.ndarray, zl) -> np.ndarray:
    """``exp(zh + zl)`` for ``zh`` in ``[EXP_UNDERFLOW, EXP_OVERFLOW]``, ``|zl| < ulp(zh)``.

    ``k = rint(zh / ln2)``; ``r = (zh - k LN2_HI) + (zl - k LN2_LO)`` (the first difference is
    exact: Sterbenz), kept as ``rh + rl``; ``exp(r) = 1 + rh + (s + rl (1 + rh))`` with
    ``s = rh^2 (1/2 + rh/6 + ... + rh^12 / 14!)``, ``1 + rh`` error-free; times ``2**k``.
    ``zl`` may be the scalar 0.0 (``exp`` of a plain float64).
    """
    k = zh * INV_LN2
    np.rint(k, out=k)
    a = k * LN2_HI
    np.subtract(zh, a, out=a)
    b = k * LN2_LO
    np.subtract(zl, b, out=b)
    rh, rl = _two_sum(a, b)
    s = rh * rh
    s *= _horner(rh, _EXP_COEFFS)
    h, lo = _fast_two_sum(1.0, rh)
    m = rh + 1.0  # h + (lo + (s + rl (1 + rh)))
    m *= rl
    m += s
    m += lo
    m += h
    return _scale(m, k.astype(np.int64))


def exp(x):
    """``e**x``, float64, elementwise; ``exp(0) = 1`` exactly.

    Args:
        x: float array (or scalar), any shape.

    Returns:
        float64 of ``x``'s shape (a float64 scalar for a scalar): +inf above
        :data:`EXP_OVERFLOW` and for +inf, 0 below :data:`EXP_UNDERFLOW` and for -inf, NaN for
        NaN. Within 1 ulp.
    """
    x, scalar = _as_float(x)
    return _result(_chunked(_exp, x)[0], scalar)


def _exp(x):
    ok = (x >= EXP_UNDERFLOW) & (x <= EXP_OVERFLOW)
    if ok.all():
        return (_exp_dd(x, 0.0),)
    out = _exp_dd(np.where(ok, x, 0.0), 0.0)
    bad = ~ok
    xb = x[bad]
    out[bad] = np.where(xb > 0.0, np.inf, np.where(xb < 0.0, 0.0, np.nan))
    return (out,)


# -- log ---------------------------------------------------------------------------------


def _log_dd(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``log x`` as a double-double ``(hi, lo)`` for finite ``x > 0``.

    Error about 2**-100 absolute plus 2**-62 of ``log m`` (``|log m| <= 0.35``).
    """
    sub = x < 2.0**-1022
    if sub.any():
        bits = (x * np.where(sub, _TWO54, 1.0)).view(np.int64)  # subnormals become normal
        e = (bits >> 52) - 1023 - np.where(sub, 54, 0)  # (sign bit 0: x > 0)
    else:
        bits = x.view(np.int64)
        e = (bits >> 52) - 1023
    m = ((bits & _MANTISSA) | _EXP_ONE).view(np.float64)  # in [1, 2)
    big = m >= SQRT2
    m = np.where(big, m * 0.5, m)  # now in [sqrt(1/2), sqrt(2))
    e += big
    e = e.astype(np.float64)
    # f = (m - 1) / (m + 1) as fh + fl; m - 1 is exact (Sterbenz)
    num = m - 1.0
    dh, dl = _two_sum(m, 1.0)
    fh = num / dh
    ph, pl = _two_prod(fh, dh)
    fl = num - ph  # (((num - ph) - pl) - fh dl) / dh
    fl -= pl
    np.multiply(fh, dl, out=dl)
    fl -= dl
    fl /= dh
    # log m = 2 atanh f = 2 f + t, t = f w (2/3 + w (2/5 + ...)) + (2 w) fl, w = f^2
    w = fh * fh
    t = fh * w
    t *= _horner(w, _LOG_COEFFS)
    w *= 2.0
    w *= fl
    t += w
    np.multiply(fh, 2.0, out=fh)
    sh, sl = _two_sum(fh, t)
    fl *= 2.0
    sl += fl  # sl + 2 fl
    # + e ln2 (e LN2_HI exact): hl + (sl + e LN2_LO)
    hh, hl = _two_sum(e * LN2_HI, sh)
    e *= LN2_LO
    e += sl
    hl += e
    return _fast_two_sum(hh, hl)


def log(x):
    """Natural logarithm, float64, elementwise; ``log(1) = 0`` exactly.

    Args:
        x: float array (or scalar), any shape.

    Returns:
        float64 of ``x``'s shape: -inf at 0, NaN below 0 and for NaN, +inf at +inf; within
        1 ulp elsewhere (subnormals included).
    """
    x, scalar = _as_float(x)
    return _result(_chunked(_log, x)[0], scalar)


def _log(x):
    ok = (x > 0.0) & (x < np.inf)
    every = ok.all()
    hi, lo = _log_dd(x if every else np.where(ok, x, 1.0))
    hi += lo
    if not every:
        bad = ~ok
        xb = x[bad]
        hi[bad] = np.where(xb == 0.0, -np.inf, np.where(xb == np.inf, np.inf, np.nan))
    return (hi,)


# -- power -------------------------------------------------------------------------------


def power(x, y):
    """``x**y`` for ``x >= 0`` as ``exp(y log x)``, float64, elementwise (broadcast).

    ``log x`` and the product are carried in double-double.

    Args:
        x: float array (or scalar), the base; values below 0 give NaN.
        y: float array (or scalar), the exponent, finite.

    Returns:
        float64 of the broadcast shape: ``x**0 = 1`` and ``1**y = 1`` exactly; ``0**y`` is 0
        for ``y > 0`` and +inf for ``y < 0``; ``inf**y`` is +inf for ``y > 0`` and 0 for
        ``y < 0``; overflow gives +inf, underflow 0; NaN in, NaN out. Within 1 ulp for
        ``|y| <= 16`` (see the module docstring).
    """
    x, sx = _as_float(x)
    y, sy = _as_float(y)
    return _result(_chunked(_power, x, y)[0], sx and sy)


def _power(x, y):
    ok = (x > 0.0) & (x < np.inf) & np.isfinite(y)
    every = ok.all()
    lh, ll = _log_dd(x if every else np.where(ok, x, 1.0))
    yy = y if every else np.where(ok, y, 0.0)
    ph, pl = _two_prod(yy, lh)
    ll *= yy
    pl += ll  # pl + yy ll
    zh, zl = _fast_two_sum(ph, pl)
    # decided on ph = fl(y hi): zh may be NaN where the split of a huge y overflowed
    inside = ok & (ph >= EXP_UNDERFLOW) & (ph <= EXP_OVERFLOW)
    if inside.all():
        out = _exp_dd(zh, zl)
    else:
        out = _exp_dd(np.where(inside, zh, 0.0), np.where(inside, zl, 0.0))
    # the rest: outside exp's range, exponent 0, bases 0 and inf, NaN (none of them is inside)
    rest = np.flatnonzero(~inside | (y == 0.0))
    if rest.size:
        xr, yr, okr = x[rest], y[rest], ok[rest]
        o = np.where(inside[rest], out[rest], np.where(ph[rest] > 0.0, np.inf, 0.0))
        edge = np.where(yr > 0.0, np.where(xr == 0.0, 0.0, np.inf),
                        np.where(xr == 0.0, np.inf, 0.0))
        o = np.where(okr, o, np.where((xr == 0.0) | (xr == np.inf), edge, np.nan))
        o = np.where(yr == 0.0, 1.0, o)
        out[rest] = np.where(np.isnan(xr) | np.isnan(yr) | (xr < 0.0), np.nan, o)
    return (out,)


# -- sin and cos -------------------------------------------------------------------------


def _reduce(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x = q pi/2 + (rh + rl)`` with ``|rh + rl| <= pi/4`` (about); ``q mod 4`` as int64.

    ``a = x - q PIO2_1`` (exact: ``q PIO2_1`` is exact and close to ``x``), ``(rh, rl) =
    TwoSum(a, -(q PIO2_2))`` (``q PIO2_2`` exact), ``rl - q PIO2_3``, renormalized.
    """
    q = x * TWO_OVER_PI
    np.rint(q, out=q)
    a = q * PIO2_1
    np.subtract(x, a, out=a)
    b = q * PIO2_2
    np.negative(b, out=b)
    rh, rl = _two_sum(a, b)
    np.multiply(q, PIO2_3, out=b)
    rl -= b
    rh, rl = _fast_two_sum(rh, rl)
    return rh, rl, q.astype(np.int64) & 3


def _sin_poly(rh, rl):
    """sin(rh + rl), ``|rh| <= pi/4``: ``rh + ((rh w) P(w) + rl (1 - w/2))``, ``w = rh^2``."""
    w = rh * rh
    s = rh * w
    s *= _horner(w, _SIN_COEFFS)
    w *= 0.5
    np.subtract(1.0, w, out=w)
    w *= rl
    s += w
    s += rh
    return s


def _cos_poly(rh, rl):
    """cos(rh + rl), ``|rh| <= pi/4``: ``1 - w/2 + w^2 Q(w)``.

    ``w = rh^2 + 2 rh rl`` is a double-double and ``1 - w/2`` error-free:
    ``c + ((corr - wl/2) + wh^2 Q(wh))`` with ``c = 1 - wh/2``, ``corr = (1 - c) - wh/2``.
    """
    wh, wl = _two_prod(rh, rh)
    t = 2.0 * rh  # wl + (2 rh) rl
    t *= rl
    wl += t
    half = 0.5 * wh
    c = 1.0 - half
    corr = 1.0 - c  # exact (Sterbenz, Fast2Sum)
    corr -= half
    wl *= 0.5
    corr -= wl
    np.multiply(wh, wh, out=t)
    t *= _horner(wh, _COS_COEFFS)
    corr += t
    corr += c
    return corr


def _check_trig(x: np.ndarray) -> None:
    if (np.abs(x) > TRIG_ARGUMENT_MAX).any():
        worst = float(np.abs(np.where(np.isfinite(x), x, 0.0)).max())
        if worst > TRIG_ARGUMENT_MAX:
            raise ValueError(f"sin/cos need |x| <= {TRIG_ARGUMENT_MAX:g} (radians) for their "
                             f"argument reduction; got {worst!r}")


def sincos(x) -> tuple:
    """``(sin x, cos x)``, float64, elementwise, sharing one argument reduction.

    Args:
        x: float array (or scalar) of radians, ``|x| <= TRIG_ARGUMENT_MAX``; inf and NaN
            give NaN.

    Returns:
        Two float64 arrays of ``x``'s shape, each within 1 ulp; ``sin(+-0) = +-0`` and
        ``cos(0) = 1``.

    Raises:
        ValueError: for a finite ``|x| > TRIG_ARGUMENT_MAX``.
    """
    x, scalar = _as_float(x)
    _check_trig(x)
    sin_x, cos_x = _chunked(_sincos, x)
    return _result(sin_x, scalar), _result(cos_x, scalar)


def _sincos(x):
    finite = np.isfinite(x)
    every = finite.all()
    rh, rl, q = _reduce(x if every else np.where(finite, x, 0.0))
    s, c = _sin_poly(rh, rl), _cos_poly(rh, rl)
    swap = (q & 1).astype(bool)
    sin_x = np.where(swap, c, s)
    cos_x = np.where(swap, s, c)
    # negations as sign-bit flips (what -x is): sin in quadrants 2 and 3, cos in 1 and 2
    flip = q >> 1
    flip <<= 63
    np.bitwise_xor(sin_x.view(np.int64), flip, out=sin_x.view(np.int64))
    q += 1
    q &= 2
    q <<= 62
    np.bitwise_xor(cos_x.view(np.int64), q, out=cos_x.view(np.int64))
    zero = x == 0.0
    if zero.any():
        np.copyto(sin_x, x, where=zero)  # sin(+-0) = +-0
    if not every:
        bad = ~finite
        sin_x[bad] = np.nan
        cos_x[bad] = np.nan
    return sin_x, cos_x


def sin(x):
    """Sine of radians, float64, elementwise (see :func:`sincos`)."""
    return sincos(x)[0]


def cos(x):
    """Cosine of radians, float64, elementwise (see :func:`sincos`)."""
    return sincos(x)[1]


def hypot(x, y):
    """``sqrt(x*x + y*y)``, elementwise, in that order.

    No scaling: for ``|x|, |y|`` between ``2**-511`` and ``2**511``; within 1.5 ulp.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    return np.sqrt(x * x + y * y)


# -- 3 x 3 matrices in a fixed order (no BLAS) -------------------------------------------


def matmul3(a, b) -> np.ndarray:
    """``a @ b`` for ``(..., 3, 3)`` stacks (broadcast), in a fixed order.

    Each entry is ``(a[i,0] b[0,j] + a[i,1] b[1,j]) + a[i,2] b[2,j]``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    shape = np.broadcast_shapes(a.shape, b.shape)
    out = np.empty(shape)
    for i in range(3):
        for j in range(3):
            out[..., i, j] = ((a[..., i, 0] * b[..., 0, j] + a[..., i, 1] * b[..., 1, j])
                              + a[..., i, 2] * b[..., 2, j])
    return out


def matvec3(m, v) -> np.ndarray:
    """``m @ v`` per vector: ``m`` ``(..., 3, 3)``, ``v`` ``(..., 3)`` (broadcast).

    Each component is ``(m[i,0] v0 + m[i,1] v1) + m[i,2] v2``; e.g. a colour matrix on an
    image's pixels (``m`` 3 x 3, ``v`` H x W x 3).
    """
    m = np.asarray(m, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    rows = [(m[..., i, 0] * v0 + m[..., i, 1] * v1) + m[..., i, 2] * v2 for i in range(3)]
    return np.stack(rows, axis=-1)


def det3(m) -> np.ndarray:
    """Determinant of ``(..., 3, 3)`` by the first row's cofactors, in a fixed order."""
    m = np.asarray(m, dtype=np.float64)
    c0 = m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1]
    c1 = m[..., 1, 2] * m[..., 2, 0] - m[..., 1, 0] * m[..., 2, 2]
    c2 = m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0]
    return (m[..., 0, 0] * c0 + m[..., 0, 1] * c1) + m[..., 0, 2] * c2


def inverse3(m) -> np.ndarray:
    """Inverse of ``(..., 3, 3)`` matrices: the adjugate over the determinant, fixed order.

    The determinant is the first row's expansion, each cofactor ``a d - b c``. For the
    well-conditioned colour matrices and homographies it serves (condition numbers well under
    1e6) as accurate as LU; a singular matrix gives inf or NaN entries (callers check the
    determinant). A single matrix is worked in Python floats (IEEE float64, the same
    operations in the same order, without numpy's per-call cost).
    """
    m = np.asarray(m, dtype=np.float64)
    if m.shape == (3, 3):
        out = _inverse3_one(m.tolist())
        if out is not None:
            return np.array(out)
    adj = np.empty(m.shape)
    for i in range(3):
        for j in range(3):
            r0, r1 = [r for r in range(3) if r != j]
            c0, c1 = [c for c in range(3) if c != i]
            minor = m[..., r0, c0] * m[..., r1, c1] - m[..., r0, c1] * m[..., r1, c0]
            adj[..., i, j] = -minor if (i + j) % 2 else minor
    det = (m[..., 0, 0] * adj[..., 0, 0] + m[..., 0, 1] * adj[..., 1, 0]) \
        + m[..., 0, 2] * adj[..., 2, 0]
    return adj / det[..., None, None]


def _inverse3_one(m: list) -> list | None:
    """:func:`inverse3` of one matrix given as nested lists of floats.

    None unless the determinant is nonzero and every entry finite: numpy then makes the inf
    and NaN entries, with its warnings, as for a stack.
    """
    adj = [[0.0] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(3):
            r0, r1 = [r for r in range(3) if r != j]
            c0, c1 = [c for c in range(3) if c != i]
            minor = m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
            adj[i][j] = -minor if (i + j) % 2 else minor
    det = (m[0][0] * adj[0][0] + m[0][1] * adj[1][0]) + m[0][2] * adj[2][0]
    if det == 0.0 or not math.isfinite(det):
        return None
    out = [[a / det for a in row] for row in adj]
    if not all(math.isfinite(v) for row in out for v in row):
        return None
    return out
