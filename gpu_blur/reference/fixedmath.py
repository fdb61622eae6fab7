"""Elementary functions whose float64 results are fixed by IEEE arithmetic alone.

numpy's ``exp``, ``log``, ``sin``, ``cos``, ``power``, ``hypot``, ... take another SIMD path on
another CPU (SVML on AVX-512, libm or numpy's own kernels elsewhere) and can differ in the
last bits; BLAS (``@``, ``dot``, ``einsum``, ``linalg``) picks its kernels (and FMA) by CPU too.
Everything here is built from operations IEEE 754 rounds exactly once and identically on every
machine: ``+ - * /``, ``sqrt``, ``rint``, ``floor``, comparisons, selections and integer
operations on the bits (exponents are read and powers of two made through ``view``, not
``frexp``/``ldexp``), each a separate numpy ufunc call in a fixed order (so no compiler can
fuse a product into a sum). A sample's draws and pixels then have the same bits on any CPU.

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
    """``c0 + x (c1 + x (c2 + ...))`` from the innermost term out."""
    acc = np.full_like(x, coeffs[-1])
    for c in coeffs[-2::-1]:
        acc = acc * x + c
    return acc


# -- error-free transformations ------------------------------------------------------------


def _two_sum(a, b):
    """``(s, e)`` with ``s = fl(a + b)`` and ``s + e = a + b`` exactly (Knuth)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _fast_two_sum(a, b):
    """``(s, e)`` with ``s + e = a + b`` exactly, for ``|a| >= |b|`` (Dekker)."""
    s = a + b
    return s, b - (s - a)


def _split(a):
    """Veltkamp's split: ``a = hi + lo`` with 26-bit halves (``|a| < 2**996``)."""
    c = _SPLITTER * a
    hi = c - (c - a)
    return hi, a - hi


def _two_prod(a, b):
    """``(p, e)`` with ``p = fl(a b)`` and ``p + e = a b`` exactly (Dekker; no FMA)."""
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _pow2(k: np.ndarray) -> np.ndarray:
    """``2.0**k`` for integer ``k`` in ``[-1022, 1023]``, made from its bits."""
    return ((k.astype(np.int64) + 1023) << 52).view(np.float64)


def _scale(m: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``m * 2**k`` rounded once, for ``m`` in ``[0.5, 2)`` and integer ``k`` in ``[-1080, 1030]``.

    Two power-of-two products; only the last one can round.
    """
    k1 = np.clip(k, -1000, 1000)
    return (m * _pow2(k1)) * _pow2(k - k1)


#: Elements a function works on at a time: its temporaries stay in a core's cache (1 M values:
#: 390 -> ~100 ms for exp).
CHUNK = 1 << 13


def _chunked(fn, *arrays):
    """``fn`` over broadcast float64 arrays, ``CHUNK`` elements at a time.

    For elementwise functions only (each result element depends on its own inputs alone);
    returns a tuple of outputs of the broadcast shape.
    """
    arrays = np.broadcast_arrays(*arrays)
    shape = arrays[0].shape
    flat = [np.ascontiguousarray(a).reshape(-1) for a in arrays]
    n = flat[0].size
    if n <= CHUNK:
        return tuple(o.reshape(shape) for o in fn(*flat))
    parts = [fn(*(a[i:i + CHUNK] for a in flat)) for i in range(0, n, CHUNK)]
    return tuple(np.concatenate(p).reshape(shape) for p in zip(*parts, strict=True))


def _as_float(x) -> tuple[np.ndarray, bool]:
    arr = np.asarray(x, dtype=np.float64)
    return arr, arr.ndim == 0


def _result(out: np.ndarray, scalar: bool):
    return out[()] if scalar else out


# -- exp ---------------------------------------------------------------------------------


def _exp_dd(zh: np.ndarray, zl: np.ndarray) -> np.ndarray:
    """``exp(zh + zl)`` for ``zh`` in ``[EXP_UNDERFLOW, EXP_OVERFLOW]``, ``|zl| < ulp(zh)``.

    ``k = rint(zh / ln2)``; ``r = (zh - k LN2_HI) + (zl - k LN2_LO)`` (the first difference is
    exact: Sterbenz), kept as ``rh + rl``; ``exp(r) = 1 + rh + (s + rl (1 + rh))`` with
    ``s = rh^2 (1/2 + rh/6 + ... + rh^12 / 14!)``, ``1 + rh`` error-free; times ``2**k``.
    """
    k = np.rint(zh * INV_LN2)
    a = zh - k * LN2_HI
    b = zl - k * LN2_LO
    rh, rl = _two_sum(a, b)
    s = (rh * rh) * _horner(rh, _EXP_COEFFS)
    h, lo = _fast_two_sum(1.0, rh)
    m = h + (lo + (s + rl * (1.0 + rh)))
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
    z = np.where(ok, x, 0.0)
    out = _exp_dd(z, np.zeros_like(z))
    return (np.where(ok, out, np.where(x > 0.0, np.inf, np.where(x < 0.0, 0.0, np.nan))),)


# -- log ---------------------------------------------------------------------------------


def _log_dd(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``log x`` as a double-double ``(hi, lo)`` for finite ``x > 0``.

    Error about 2**-100 absolute plus 2**-62 of ``log m`` (``|log m| <= 0.35``).
    """
    sub = x < 2.0**-1022
    xs = x * np.where(sub, _TWO54, 1.0)  # subnormals become normal, exactly
    bits = xs.view(np.int64)
    e = ((bits >> 52) & 0x7FF) - 1023 - np.where(sub, 54, 0)
    m = ((bits & _MANTISSA) | _EXP_ONE).view(np.float64)  # in [1, 2)
    big = m >= SQRT2
    m = np.where(big, m * 0.5, m)  # now in [sqrt(1/2), sqrt(2))
    e = (e + big).astype(np.float64)
    # f = (m - 1) / (m + 1) as fh + fl; m - 1 is exact (Sterbenz)
    num = m - 1.0
    dh, dl = _two_sum(m, 1.0)
    fh = num / dh
    ph, pl = _two_prod(fh, dh)
    fl = (((num - ph) - pl) - fh * dl) / dh
    # log m = 2 atanh f = 2 f + t, t = f w (2/3 + w (2/5 + ...)), w = f^2
    w = fh * fh
    t = (fh * w) * _horner(w, _LOG_COEFFS) + (2.0 * w) * fl
    sh, sl = _two_sum(2.0 * fh, t)
    sl = sl + 2.0 * fl
    # + e ln2 (e LN2_HI exact)
    hh, hl = _two_sum(e * LN2_HI, sh)
    lo = hl + (sl + e * LN2_LO)
    return _fast_two_sum(hh, lo)


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
    hi, lo = _log_dd(np.where(ok, x, 1.0))
    out = hi + lo
    return (np.where(ok, out, np.where(x == 0.0, -np.inf,
                                       np.where(x == np.inf, np.inf, np.nan))),)


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
    lh, ll = _log_dd(np.where(ok, x, 1.0))
    yy = np.where(ok, y, 0.0)
    ph, pl = _two_prod(yy, lh)
    pl = pl + yy * ll
    zh, zl = _fast_two_sum(ph, pl)
    # decided on ph = fl(y hi): zh may be NaN where the split of a huge y overflowed
    inside = ok & (ph >= EXP_UNDERFLOW) & (ph <= EXP_OVERFLOW)
    out = _exp_dd(np.where(inside, zh, 0.0), np.where(inside, zl, 0.0))
    out = np.where(inside, out, np.where(ph > 0.0, np.inf, 0.0))
    # bases 0 and inf, exponent 0, NaN
    edge = np.where(y > 0.0, np.where(x == 0.0, 0.0, np.inf), np.where(x == 0.0, np.inf, 0.0))
    out = np.where(ok, out, np.where((x == 0.0) | (x == np.inf), edge, np.nan))
    out = np.where(y == 0.0, 1.0, out)
    return (np.where(np.isnan(x) | np.isnan(y) | (x < 0.0), np.nan, out),)


# -- sin and cos -------------------------------------------------------------------------


def _reduce(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x = q pi/2 + (rh + rl)`` with ``|rh + rl| <= pi/4`` (about); ``q mod 4`` as int64."""
    q = np.rint(x * TWO_OVER_PI)
    a = x - q * PIO2_1  # exact: q PIO2_1 is exact and close to x
    rh, rl = _two_sum(a, -(q * PIO2_2))  # q PIO2_2 exact
    rl = rl - q * PIO2_3
    rh, rl = _fast_two_sum(rh, rl)
    return rh, rl, q.astype(np.int64) & 3


def _sin_poly(rh, rl):
    """sin(rh + rl), ``|rh| <= pi/4``: ``rh + (rh w P(w) + rl)``, ``w = rh^2``."""
    w = rh * rh
    return rh + ((rh * w) * _horner(w, _SIN_COEFFS) + rl * (1.0 - 0.5 * w))


def _cos_poly(rh, rl):
    """cos(rh + rl), ``|rh| <= pi/4``: ``1 - w/2 + w^2 Q(w)``.

    ``w = rh^2 + 2 rh rl`` is a double-double and ``1 - w/2`` error-free.
    """
    wh, wl = _two_prod(rh, rh)
    wl = wl + 2.0 * rh * rl
    half = 0.5 * wh
    c = 1.0 - half
    corr = (1.0 - c) - half  # exact (Sterbenz, Fast2Sum)
    return c + ((corr - 0.5 * wl) + (wh * wh) * _horner(wh, _COS_COEFFS))


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
    rh, rl, q = _reduce(np.where(finite, x, 0.0))
    s, c = _sin_poly(rh, rl), _cos_poly(rh, rl)
    swap = (q & 1) == 1
    sin_x = np.where(swap, c, s)
    cos_x = np.where(swap, s, c)
    sin_x = np.where((q == 2) | (q == 3), -sin_x, sin_x)
    cos_x = np.where((q == 1) | (q == 2), -cos_x, cos_x)
    sin_x = np.where(x == 0.0, x, sin_x)
    sin_x = np.where(finite, sin_x, np.nan)
    return sin_x, np.where(finite, cos_x, np.nan)


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
    determinant).
    """
    m = np.asarray(m, dtype=np.float64)
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
