"""gpu_blur.reference.fixedmath: accuracy, special values, and bits that no CPU changes.

Accuracy is measured in ulps of the exact value, computed with 50-digit :mod:`decimal`
arithmetic. The recorded digests fix the functions' bits on fixed grids, so any change of
evaluation order shows; fixedmath must also give the bits of its plain formulas (as it had
them before it worked in place) on random and edge inputs, special values included. The
``bits`` tests run the draws of every blur mode and numpy-backend samples in subprocesses with
and without numpy's AVX-512 and AVX2 paths and compare digests.

Run as a script (``python tests/reference/test_fixedmath.py``) this module prints those digests
as JSON.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys
from decimal import Decimal, localcontext
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

#: The tests folder (golden.py) and the repository root: this module also runs as a script,
#: without conftest, so it counts its own parents (it sits in tests/reference/).
TESTS = Path(__file__).resolve().parents[1]
ROOT = TESTS.parent
if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))

from gpu_blur.reference import fixedmath as fm  # noqa: E402

#: numpy's SIMD paths switched off for the comparison (X86_V3 is AVX2 with FMA; the baseline
#: X86_V2 stays).
NO_AVX = "AVX512_SPR AVX512_ICL X86_V4 X86_V3"
#: Most ulps from the correctly rounded value any function may err on the tested grids
#: (measured 0.57 exp, 0.51 log, 0.65 sin, 0.64 cos, 0.59 power).
ULP_BOUND = 1.0
_PI = Decimal("3.14159265358979323846264338327950288419716939937510582097494459")


def _ulps(got: float, exact: Decimal) -> float:
    """(got - exact) in ulps of the float64 nearest ``exact`` (subnormal ulp below 2**-1022)."""
    e = float(exact)
    ulp = math.ulp(e) if abs(e) >= 2.0**-1022 else 2.0**-1074
    return float((Decimal(got) - exact) / Decimal(ulp))


def _dsin_cos(x: float) -> tuple[Decimal, Decimal]:
    """sin and cos of a float64 by their Taylor series in 60-digit decimal arithmetic."""
    with localcontext() as ctx:
        ctx.prec = 60
        d = Decimal(x)
        r = d - (d / (2 * _PI)).to_integral_value() * 2 * _PI
        s, c, term, k = Decimal(0), Decimal(0), Decimal(1), 0
        while k < 200:
            if k % 4 == 0:
                c += term
            elif k % 4 == 1:
                s += term
            elif k % 4 == 2:
                c -= term
            else:
                s -= term
            k += 1
            term = term * r / k
            if k > 4 and abs(term) < Decimal(10) ** -70 * max(abs(r), Decimal(10) ** -300):
                break
    return s, c


def _worst(got, xs, exact) -> float:
    with localcontext() as ctx:
        ctx.prec = 50
        return max(abs(_ulps(float(g), exact(x))) for g, x in zip(got, xs, strict=True))


_RNG = np.random.default_rng(2024)


def test_constants_are_the_parts_they_claim():
    with localcontext() as ctx:
        ctx.prec = 50
        ln2 = Decimal(2).ln()
        assert abs(Decimal(fm.LN2_HI) + Decimal(fm.LN2_LO) - ln2) < Decimal(2) ** -98
        assert Fraction(fm.LN2_HI).denominator <= 2**42  # 42 bits: k * LN2_HI exact, |k| < 2**11
        pio2 = _PI / 2
        parts = Decimal(fm.PIO2_1) + Decimal(fm.PIO2_2) + Decimal(fm.PIO2_3)
        assert abs(parts - pio2) < Decimal(2) ** -120
        for part in (fm.PIO2_1, fm.PIO2_2):  # 33 significant bits: q * part exact, |q| < 2**20
            m, _ = math.frexp(part)
            assert (Fraction(m) * 2**33).denominator == 1
        assert fm.TWO_OVER_PI == float(1 / pio2) and fm.INV_LN2 == float(1 / ln2)
        assert fm.SQRT2 == float(Decimal(2).sqrt())


def test_exp_is_within_an_ulp():
    xs = np.concatenate([_RNG.uniform(-745.0, 709.7, 1500), _RNG.uniform(-1.0, 1.0, 800),
                         _RNG.uniform(-1e-8, 1e-8, 200), [-745.0, -708.5, 709.78, 1e-300]])
    assert _worst(fm.exp(xs), xs, lambda x: Decimal(x).exp()) <= ULP_BOUND


def test_log_is_within_an_ulp():
    xs = np.concatenate([np.exp(_RNG.uniform(-744.0, 709.0, 1500)), _RNG.uniform(0.5, 2.0, 800),
                         [5e-324, 1e-310, 2.0**-1022, 1 + 2.0**-52, 1 - 2.0**-53, 1.7e308]])
    assert _worst(fm.log(xs), xs, lambda x: Decimal(x).ln()) <= ULP_BOUND


def test_sin_and_cos_are_within_an_ulp():
    # Box-Muller's angles 2 pi u (u odd multiples of 2**-24, near the zeros of sin and cos
    # included), the camera path's phases, and wider arguments
    u = (np.arange(1, 2**24, 2 * 4099) * 2.0**-24)
    xs = np.concatenate([2.0 * math.pi * u, _RNG.uniform(-8.0, 8.0, 600),
                         _RNG.uniform(-1e5, 1e5, 200), [1e-300, 0.5 * math.pi, math.pi]])
    s, c = fm.sincos(xs)
    assert _worst(s, xs, lambda x: _dsin_cos(x)[0]) <= ULP_BOUND
    assert _worst(c, xs, lambda x: _dsin_cos(x)[1]) <= ULP_BOUND
    np.testing.assert_array_equal(s, fm.sin(xs))
    np.testing.assert_array_equal(c, fm.cos(xs))


@pytest.mark.parametrize("y", [2.4, 1 / 2.4, 2.2, 1 / 2.2, -3.7, 15.9])
def test_power_is_within_an_ulp(y):
    xs = np.concatenate([_RNG.uniform(0.04, 1.1, 500), np.exp(_RNG.uniform(-40.0, 40.0, 200))])
    assert _worst(fm.power(xs, y), xs,
                  lambda x: (Decimal(x).ln() * Decimal(y)).exp()) <= ULP_BOUND


def test_power_is_within_an_ulp_over_wide_ranges():
    xs = np.exp(_RNG.uniform(-300.0, 300.0, 600))
    ys = _RNG.uniform(-2.0, 2.0, 600)
    got = fm.power(xs, ys)
    with localcontext() as ctx:
        ctx.prec = 50
        worst = max(abs(_ulps(float(g), (Decimal(x).ln() * Decimal(y)).exp()))
                    for g, x, y in zip(got, xs, ys, strict=True))
    assert worst <= ULP_BOUND


def test_special_values():
    inf, nan = math.inf, math.nan
    np.testing.assert_array_equal(fm.exp([0.0, -0.0, inf, -inf, 710.0, -746.0]),
                                  [1.0, 1.0, inf, 0.0, inf, 0.0])
    assert np.isnan(fm.exp(nan))
    assert fm.exp(-745.0) == 5e-324
    np.testing.assert_array_equal(fm.log([1.0, 0.0, -0.0, inf]), [0.0, -inf, -inf, inf])
    assert np.isnan(fm.log([-1.0, nan, -inf])).all()
    s, c = fm.sincos(np.array([0.0, -0.0]))
    assert list(s) == [0.0, -0.0] and math.copysign(1, s[1]) == -1 and list(c) == [1.0, 1.0]
    assert np.isnan(fm.sincos(np.array([inf, -inf, nan]))).all()
    with pytest.raises(ValueError, match="sin/cos need"):
        fm.sin(2.0**21)
    p = fm.power([2.0, 1.0, 0.0, 0.0, 0.0, inf, inf, 4.0, 7.0, 10.0, 10.0],
                 [0.5, 123.4, 2.0, -2.0, 0.0, 2.0, -2.0, 0.5, 0.0, 400.0, -400.0])
    np.testing.assert_array_equal(p, [math.sqrt(2.0), 1.0, 0.0, inf, 1.0, inf, 0.0, 2.0, 1.0,
                                      inf, 0.0])
    assert np.isnan(fm.power([-1.0, nan, 2.0], [2.0, 1.0, nan])).all()
    assert fm.power(2.0, 1e300) == inf and fm.power(0.5, 1e300) == 0.0
    assert isinstance(fm.exp(1.0), np.float64) and fm.log(np.ones((2, 3))).shape == (2, 3)


def test_matrix_helpers_agree_with_numpy_to_rounding():
    a = _RNG.uniform(-2.0, 2.0, (50, 3, 3)) + 3.0 * np.eye(3)
    b = _RNG.uniform(-2.0, 2.0, (50, 3, 3))
    np.testing.assert_allclose(fm.matmul3(a, b), a @ b, rtol=0, atol=1e-14)
    v = _RNG.uniform(-1.0, 1.0, (7, 5, 3))
    np.testing.assert_allclose(fm.matvec3(a[0], v), v @ a[0].T, rtol=0, atol=1e-14)
    np.testing.assert_allclose(fm.det3(a), np.linalg.det(a), rtol=1e-13)
    np.testing.assert_allclose(fm.inverse3(a), np.linalg.inv(a), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(fm.inverse3(np.eye(3)), np.eye(3))


# -- the same bits as the plain formulas ---------------------------------------------------
# fixedmath works in place, chunk by chunk, and fixes up special values on the few elements
# that have them. The functions below are its formulas written out plainly, one new array per
# operation and every selection over the whole array, as fixedmath had them before: the
# optimized code must give their bits on any input, special values included.


def _plain_horner(x, coeffs):
    acc = np.full_like(x, coeffs[-1])
    for c in coeffs[-2::-1]:
        acc = acc * x + c
    return acc


def _plain_two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _plain_fast_two_sum(a, b):
    s = a + b
    return s, b - (s - a)


def _plain_split(a):
    c = fm._SPLITTER * a
    hi = c - (c - a)
    return hi, a - hi


def _plain_two_prod(a, b):
    p = a * b
    ah, al = _plain_split(a)
    bh, bl = _plain_split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _plain_pow2(k):
    return ((k.astype(np.int64) + 1023) << 52).view(np.float64)


def _plain_exp_dd(zh, zl):
    k = np.rint(zh * fm.INV_LN2)
    rh, rl = _plain_two_sum(zh - k * fm.LN2_HI, zl - k * fm.LN2_LO)
    s = (rh * rh) * _plain_horner(rh, fm._EXP_COEFFS)
    h, lo = _plain_fast_two_sum(1.0, rh)
    m = h + (lo + (s + rl * (1.0 + rh)))
    k = k.astype(np.int64)
    k1 = np.clip(k, -1000, 1000)
    return (m * _plain_pow2(k1)) * _plain_pow2(k - k1)


def _plain_exp(x):
    ok = (x >= fm.EXP_UNDERFLOW) & (x <= fm.EXP_OVERFLOW)
    z = np.where(ok, x, 0.0)
    out = _plain_exp_dd(z, np.zeros_like(z))
    return np.where(ok, out, np.where(x > 0.0, np.inf, np.where(x < 0.0, 0.0, np.nan)))


def _plain_log_dd(x):
    sub = x < 2.0**-1022
    bits = (x * np.where(sub, fm._TWO54, 1.0)).view(np.int64)
    e = ((bits >> 52) & 0x7FF) - 1023 - np.where(sub, 54, 0)
    m = ((bits & fm._MANTISSA) | fm._EXP_ONE).view(np.float64)
    big = m >= fm.SQRT2
    m = np.where(big, m * 0.5, m)
    e = (e + big).astype(np.float64)
    num = m - 1.0
    dh, dl = _plain_two_sum(m, 1.0)
    fh = num / dh
    ph, pl = _plain_two_prod(fh, dh)
    fl = (((num - ph) - pl) - fh * dl) / dh
    w = fh * fh
    t = (fh * w) * _plain_horner(w, fm._LOG_COEFFS) + (2.0 * w) * fl
    sh, sl = _plain_two_sum(2.0 * fh, t)
    sl = sl + 2.0 * fl
    hh, hl = _plain_two_sum(e * fm.LN2_HI, sh)
    return _plain_fast_two_sum(hh, hl + (sl + e * fm.LN2_LO))


def _plain_log(x):
    ok = (x > 0.0) & (x < np.inf)
    hi, lo = _plain_log_dd(np.where(ok, x, 1.0))
    return np.where(ok, hi + lo, np.where(x == 0.0, -np.inf,
                                          np.where(x == np.inf, np.inf, np.nan)))


def _plain_power(x, y):
    x, y = np.broadcast_arrays(x, y)
    ok = (x > 0.0) & (x < np.inf) & np.isfinite(y)
    lh, ll = _plain_log_dd(np.where(ok, x, 1.0))
    yy = np.where(ok, y, 0.0)
    ph, pl = _plain_two_prod(yy, lh)
    zh, zl = _plain_fast_two_sum(ph, pl + yy * ll)
    inside = ok & (ph >= fm.EXP_UNDERFLOW) & (ph <= fm.EXP_OVERFLOW)
    out = _plain_exp_dd(np.where(inside, zh, 0.0), np.where(inside, zl, 0.0))
    out = np.where(inside, out, np.where(ph > 0.0, np.inf, 0.0))
    edge = np.where(y > 0.0, np.where(x == 0.0, 0.0, np.inf), np.where(x == 0.0, np.inf, 0.0))
    out = np.where(ok, out, np.where((x == 0.0) | (x == np.inf), edge, np.nan))
    out = np.where(y == 0.0, 1.0, out)
    return np.where(np.isnan(x) | np.isnan(y) | (x < 0.0), np.nan, out)


def _plain_sincos(x):
    finite = np.isfinite(x)
    z = np.where(finite, x, 0.0)
    q = np.rint(z * fm.TWO_OVER_PI)
    rh, rl = _plain_two_sum(z - q * fm.PIO2_1, -(q * fm.PIO2_2))
    rh, rl = _plain_fast_two_sum(rh, rl - q * fm.PIO2_3)
    q = q.astype(np.int64) & 3
    w = rh * rh
    s = rh + ((rh * w) * _plain_horner(w, fm._SIN_COEFFS) + rl * (1.0 - 0.5 * w))
    wh, wl = _plain_two_prod(rh, rh)
    wl = wl + 2.0 * rh * rl
    half = 0.5 * wh
    c = 1.0 - half
    corr = (1.0 - c) - half
    c = c + ((corr - 0.5 * wl) + (wh * wh) * _plain_horner(wh, fm._COS_COEFFS))
    swap = (q & 1) == 1
    sin_x, cos_x = np.where(swap, c, s), np.where(swap, s, c)
    sin_x = np.where((q == 2) | (q == 3), -sin_x, sin_x)
    cos_x = np.where((q == 1) | (q == 2), -cos_x, cos_x)
    sin_x = np.where(x == 0.0, x, sin_x)
    return np.where(finite, sin_x, np.nan), np.where(finite, cos_x, np.nan)


def _assert_same_bits(got, want):
    got, want = np.asarray(got), np.asarray(want)
    assert got.dtype == want.dtype == np.float64 and got.shape == want.shape
    differ = got.view(np.int64) != want.view(np.int64)
    assert not differ.any(), (f"{int(differ.sum())} of {differ.size} differ, e.g. "
                              f"{got[differ][:3]!r} for {want[differ][:3]!r}")


def _near(values, ulps: int = 3) -> np.ndarray:
    """``values`` and their float64 neighbours up to ``ulps`` away on each side."""
    out = [np.asarray(values, dtype=np.float64)]
    up, down = out[0], out[0]
    for _ in range(ulps):
        up, down = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
        out += [up, down]
    return np.concatenate(out)


def _random_doubles(rng, n: int) -> np.ndarray:
    """Every finite float64 equally likely by its bits (any exponent, subnormals, both signs)."""
    bits = rng.integers(0, 0x7FF0000000000000, n, dtype=np.int64)
    return bits.view(np.float64) * np.where(rng.random(n) < 0.5, -1.0, 1.0)


_SPECIALS = [0.0, -0.0, 5e-324, -5e-324, 2.0**-1022, 1.0, -1.0, 1.7976931348623157e308,
             np.inf, -np.inf, np.nan]


def _exp_inputs() -> np.ndarray:
    rng = np.random.default_rng(31)
    k = np.arange(-1080, 1030)
    return np.concatenate([
        rng.uniform(-746.0, 710.0, 60000), rng.uniform(-1.0, 1.0, 20000),
        rng.uniform(-1e-8, 1e-8, 5000), _random_doubles(rng, 5000),
        _near([fm.EXP_OVERFLOW, fm.EXP_UNDERFLOW, -708.4, -709.1, 709.0, 0.0], 8),
        _near((k + 0.5) * math.log(2.0)), _near(k * math.log(2.0)), _SPECIALS])


def _positive_inputs() -> np.ndarray:
    rng = np.random.default_rng(32)
    twos = 2.0 ** np.arange(-1074, 1024, dtype=np.float64)
    return np.concatenate([
        np.abs(_random_doubles(rng, 60000)), rng.uniform(0.0, 2.0, 20000),
        rng.integers(1, 2**52, 5000).view(np.float64),  # subnormals
        _near(twos), _near(fm.SQRT2 * twos[:-1]), _near(twos * 1.5), _near([1.0], 64),
        rng.uniform(0.04, 1.1, 20000), _SPECIALS, -rng.uniform(0.0, 1.0, 100)])


@pytest.mark.bits
def test_exp_log_keep_the_bits_of_the_plain_formulas():
    x = _exp_inputs()
    _assert_same_bits(fm.exp(x), _plain_exp(x))
    p = _positive_inputs()
    _assert_same_bits(fm.log(p), _plain_log(p))
    # each size and layout: one chunk, chunks with a partial last one, strided, 0-d, empty
    for a in (x[:fm.CHUNK], x[:3 * fm.CHUNK + 5], x[::3], x[:5000].reshape(50, 100).T):
        _assert_same_bits(fm.exp(a), _plain_exp(a))
        _assert_same_bits(fm.log(np.abs(a)), _plain_log(np.abs(a)))
    for v in (0.5, 800.0, np.nan, -0.0):
        assert fm.exp(v).tobytes() == _plain_exp(np.float64(v)).tobytes()
        assert fm.log(v).tobytes() == _plain_log(np.float64(v)).tobytes()
    assert fm.exp(np.zeros((0, 3))).shape == (0, 3) and fm.log(np.zeros(0)).shape == (0,)


@pytest.mark.bits
@pytest.mark.parametrize("y", [2.4, 1 / 2.4, 2.2, 1 / 2.2, -3.7, 15.9, 0.0, -0.0, 1.0, -1.0,
                               0.5, 1e300, -1e300, 1e306, 5e-324, np.inf, -np.inf, np.nan])
def test_power_keeps_the_bits_of_the_plain_formulas(y):
    x = _positive_inputs()
    with np.errstate(all="ignore"):  # a huge y overflows Veltkamp's split, in both alike
        _assert_same_bits(fm.power(x, y), _plain_power(x, np.float64(y)))
        _assert_same_bits(fm.power(x[:7777], y), _plain_power(x[:7777], np.float64(y)))


@pytest.mark.bits
def test_power_keeps_the_bits_of_the_plain_formulas_over_both_arguments():
    rng = np.random.default_rng(33)
    x = _positive_inputs()
    n = x.size
    ys = (rng.uniform(-2.0, 2.0, n), rng.uniform(-20.0, 20.0, n), _random_doubles(rng, n),
          rng.choice(np.array(_SPECIALS + [2.4, 0.5, -3.0]), n))
    with np.errstate(all="ignore"):  # huge exponents overflow the split, in both alike
        for y in ys:
            _assert_same_bits(fm.power(x, y), _plain_power(x, y))
        # broadcasting: a column of bases against a row of exponents, a scalar base
        xb, yb = x[:3000:7, None], np.array(_SPECIALS + [2.4, -0.7, 1e-300, 33.0])
        _assert_same_bits(fm.power(xb, yb), _plain_power(xb, yb))
        yw = rng.uniform(-50.0, 50.0, 3 * fm.CHUNK + 1)
        for base in (0.3, 0.0, np.inf, 7.0):
            _assert_same_bits(fm.power(base, yw), _plain_power(np.float64(base), yw))
    assert fm.power(2.0, 0.5).tobytes() == _plain_power(np.float64(2.0), 0.5).tobytes()


@pytest.mark.bits
def test_sincos_keeps_the_bits_of_the_plain_formulas():
    rng = np.random.default_rng(34)
    k = np.arange(-4000, 4000)
    x = np.concatenate([
        rng.uniform(-fm.TRIG_ARGUMENT_MAX, fm.TRIG_ARGUMENT_MAX, 40000),
        rng.uniform(-8.0, 8.0, 40000), rng.uniform(-1e-6, 1e-6, 5000),
        2.0 * math.pi * (np.arange(1, 2**24, 2 * 1021) * 2.0**-24),
        _near(k * (math.pi / 4)), _near(k * (math.pi / 2)),
        [fm.TRIG_ARGUMENT_MAX, -fm.TRIG_ARGUMENT_MAX],
        _near([5e-324, 1e-300, 2.0**-1022]), _SPECIALS[:7], [np.inf, -np.inf, np.nan]])
    s, c = fm.sincos(x)
    ps, pc = _plain_sincos(x)
    _assert_same_bits(s, ps)
    _assert_same_bits(c, pc)
    for a in (x[:100], x[1::2], x[:6000].reshape(3, 2000)):
        s, c = fm.sincos(a)
        ps, pc = _plain_sincos(a)
        _assert_same_bits(s, ps)
        _assert_same_bits(c, pc)


@pytest.mark.bits
def test_inverse3_of_one_matrix_keeps_the_bits_of_the_stacked_formulas():
    # one matrix is worked in Python floats; the stack's numpy formulas (unchanged, their bits
    # held by the recorded digests below) are the oracle
    rng = np.random.default_rng(35)
    mats = [rng.uniform(-1.0, 1.0, (3, 3)) + 3.0 * np.eye(3) for _ in range(300)]
    mats += [rng.uniform(-1.0, 1.0, (3, 3)) * 10.0 ** rng.integers(-150, 150) for _ in range(300)]
    mats += [rng.integers(-2, 3, (3, 3)).astype(np.float64) for _ in range(300)]  # singular too
    mats += [np.eye(3), np.zeros((3, 3)), np.full((3, 3), 1e200), np.full((3, 3), 1e-200),
             np.diag([1e300, 1e300, 1e-300]), np.diag([np.inf, 1.0, 1.0]),
             np.diag([np.nan, 1.0, 1.0]), np.diag([5e-324, 1.0, 1.0])]
    with np.errstate(all="ignore"):
        stacked = fm.inverse3(np.stack(mats))
        for m, want in zip(mats, stacked, strict=True):
            _assert_same_bits(fm.inverse3(m), want)
    # a single matrix given as nested lists, and a singular one: numpy's warning as before
    given = [[2.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 4.0]]
    _assert_same_bits(fm.inverse3(given), fm.inverse3(np.array([given]))[0])
    with pytest.warns(RuntimeWarning):
        fm.inverse3(np.zeros((3, 3)))


# -- bits --------------------------------------------------------------------------------


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:32]


def function_digests() -> dict[str, str]:
    """Digests of each function's outputs on fixed grids."""
    x = np.linspace(-745.5, 710.0, 20001)
    pos = fm.exp(np.linspace(-744.0, 709.0, 20001))  # not np.exp2: its bits vary by CPU
    angles = np.linspace(-200.0, 200.0, 20001)
    base = np.linspace(0.0, 1.5, 20001)
    eye = np.eye(3)
    return {
        "exp": _digest(fm.exp(x)),
        "log": _digest(fm.log(pos)),
        "sincos": _digest(*fm.sincos(angles)),
        "power": _digest(fm.power(base, 2.4), fm.power(base, 1 / 2.4), fm.power(pos, -0.3)),
        "matrices": _digest(fm.inverse3(fm.matmul3(angles[:999].reshape(-1, 3, 3) + 300 * eye,
                                                   angles[1000:1999].reshape(-1, 3, 3) + eye))),
    }


#: function_digests() as recorded (the same with numpy's AVX-512 and AVX2 paths off).
RECORDED = {
    "exp": "494f683c215e1923b0b747eba053279d",
    "log": "2a2c6c5563b372277775c4574436e965",
    "sincos": "81afd925c31e91a98174f1cabd8a0d4f",
    "power": "10c1c8cf1f06acea915d78fb799d754c",
    "matrices": "76a1d15282dc74ae3da5ba3d2175f06a",
}


@pytest.mark.bits
def test_functions_keep_their_recorded_bits():
    assert function_digests() == RECORDED


#: Scenes whose draws and numpy-backend samples the bits test compares: every blur mode
#: (the interpolated ones use OpenCV's flows, which this comparison does not vary).
PROBE_SCENES = {
    "kernel": ({"blur": {"mode": "kernel"}, "saturation": {"mode": "on"}}, "photo"),
    "trajectory": ({"blur": {"mode": "trajectory"}, "noise": {"model": "gaussian"},
                    "isp": {"round_trip": "always"}, "output": {"crf": "a7r3"}}, "photo"),
    "average": ({"blur": {"mode": "average", "frames": 9}}, "frames"),
    "interpolated": ({"blur": {"mode": "average", "frames": 5, "interpolation": 2}}, "frames"),
    "auto": ({"blur": {"mode": "average", "frames": 5, "interpolation": "auto"}}, "frames"),
    "none": ({"blur": {"mode": "none"}, "output": {"crf": "a7r3-lut", "bits": 16}}, "blurred"),
}


def sample_digests() -> dict[str, str]:
    """Digests (tests/golden.py's: outputs and drawn parameters) of numpy-backend samples of
    :data:`PROBE_SCENES`, and of the draws alone for more sample indices."""
    sys.path.insert(0, str(TESTS))
    from golden import _inputs, digest

    from gpu_blur import synthesize
    from gpu_blur.cameras import scene_camera
    from gpu_blur.params import draw_params
    from gpu_blur.planning import plan
    from gpu_blur.scene import scene_from_dict

    out = {}
    for name, (changes, kind) in PROBE_SCENES.items():
        scene = scene_from_dict(changes)
        inputs = _inputs(kind)
        if kind == "frames":
            inputs = inputs[:scene.blur.frames]
        out[name] = digest(synthesize(inputs, scene, seed=7, sample_index=3))[:32]
        the_plan = plan(scene, size=(96, 128))
        draws = [draw_params(scene, the_plan, scene_camera(scene), seed=11, sample_index=i,
                             image_shape=(96, 128)) for i in range(4)]
        out[f"{name} draws"] = hashlib.sha256(
            repr([sorted((k, np.asarray(v).tobytes().hex()) for k, v in d.items())
                  for d in draws]).encode()).hexdigest()[:32]
    return out


def _run_probe(env_changes: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "NPY_DISABLE_CPU_FEATURES"}
    env.update(env_changes)
    done = subprocess.run([sys.executable, str(Path(__file__).resolve())], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.bits
def test_draws_and_samples_are_the_same_without_avx512_and_avx2():
    from numpy._core._multiarray_umath import __cpu_features__

    if not __cpu_features__.get("AVX512F"):
        pytest.skip("this CPU has no AVX-512 paths to switch off")
    plain = _run_probe({})
    reduced = _run_probe({"NPY_DISABLE_CPU_FEATURES": NO_AVX})
    assert reduced == plain
    assert plain["functions"] == RECORDED


if __name__ == "__main__":
    print(json.dumps({"functions": function_digests(), **sample_digests()}, sort_keys=True))
