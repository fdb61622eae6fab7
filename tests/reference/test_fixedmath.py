"""gpu_blur.reference.fixedmath: accuracy, special values, and bits that no CPU changes.

Accuracy is measured in ulps of the exact value, computed with 50-digit :mod:`decimal`
arithmetic. The recorded digests fix the functions' bits on fixed grids, so any change of
evaluation order shows. The ``bits`` tests run the draws of every blur mode and numpy-backend
samples in subprocesses with and without numpy's AVX-512 and AVX2 paths and compare digests.

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
