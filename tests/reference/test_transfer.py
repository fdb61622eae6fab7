import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gpu_blur.constants import A7R3_CRF_POLYNOMIAL, A7R3_CRF_TABLE_X255
from gpu_blur.reference import transfer
from gpu_blur.testing import assert_close

KNEES = [0.0, 5e-324, 1e-300, 1e-12, 0.0031308, np.nextafter(0.0031308, 0), 0.04045,
         np.nextafter(0.04045, 0), np.nextafter(0.04045, 1), 0.5, 1.0]


def eotf_formula(x):
    a = abs(x)
    y = a / 12.92 if a < 0.04045 else math.pow((a + 0.055) / 1.055, 2.4)
    return math.copysign(y, x)


def oetf_formula(x):
    a = abs(x)
    y = 12.92 * a if a < 0.0031308 else 1.055 * math.pow(a, 1 / 2.4) - 0.055
    return math.copysign(y, x)


def test_srgb_functions_match_their_defining_formula():
    x = np.concatenate([KNEES, -np.array(KNEES), np.linspace(-1.5, 1.5, 3001)])
    assert_close(transfer.srgb_to_linear(x), [eotf_formula(v) for v in x],
                 "srgb_transfer", "independent")
    assert_close(transfer.linear_to_srgb(x), [oetf_formula(v) for v in x],
                 "srgb_transfer", "independent")


def test_srgb_functions_are_finite_and_monotone_at_knees_and_zero():
    x = np.sort(np.concatenate([KNEES, np.linspace(0, 1, 10001)]))
    with np.errstate(divide="raise", over="raise", invalid="raise"):  # no log(0), inf, NaN
        lin, enc = transfer.srgb_to_linear(x), transfer.linear_to_srgb(x)
    assert np.all(np.isfinite(lin)) and np.all(np.isfinite(enc))
    assert np.all(np.diff(lin) >= 0)
    # IEC 61966-2-1's knees disagree: the OETF steps down by 3.1e-8 at 0.0031308 (the linear
    # segment ends at 0.04044994, the curve starts at 0.04044991), and nowhere else.
    drops = np.flatnonzero(np.diff(enc) < 0)
    assert x[drops].tolist() == [np.nextafter(0.0031308, 0)]
    assert -np.diff(enc)[drops[0]] < 3.2e-8
    assert transfer.linear_to_srgb(0.0) == 0.0 and transfer.srgb_to_linear(1.0) == 1.0


@given(st.floats(-2.0, 2.0, allow_nan=False))
def test_srgb_round_trip_returns_the_input(x):
    assert_close(transfer.srgb_to_linear(transfer.linear_to_srgb(x)), x, "srgb_round_trip")
    assert_close(transfer.linear_to_srgb(transfer.srgb_to_linear(x)), x, "srgb_decode_encode")


def test_srgb_decode_encode_loses_up_to_3e_8_just_below_the_decode_knee():
    x = np.nextafter(0.04045, 0)
    err = abs(transfer.linear_to_srgb(transfer.srgb_to_linear(x)) - x)
    assert 2.5e-8 < err <= 3.2e-8  # the IEC knees' mismatch, pinned


def test_pure_gamma_round_trip():
    x = np.linspace(-1, 1, 101)
    assert_close(transfer.gamma_to_linear(transfer.linear_to_gamma(x, 2.2), 2.2), x,
                 "srgb_round_trip")


def test_a7r3_polynomial_is_horner_of_the_coefficients_and_clips():
    x = np.linspace(0.0, 1.0, 2001)
    expected = np.clip(np.polynomial.polynomial.polyval(x, A7R3_CRF_POLYNOMIAL), 0, 1)
    assert_close(transfer.polynomial_crf(x, A7R3_CRF_POLYNOMIAL), expected, "crf_polynomial",
                 "independent")
    # P(0) < 0 and P(1) > 1 in the raw polynomial: both ends clip; outside [0, 1] too.
    y = transfer.polynomial_crf(np.array([-1.0, 0.0, 1.0, 2.0]), A7R3_CRF_POLYNOMIAL)
    assert y.tolist() == [0.0, 0.0, 1.0, 1.0]


def test_a7r3_lookup_table_has_2551_nodes_and_stays_within_0_0072_of_the_polynomial():
    assert A7R3_CRF_TABLE_X255.shape == (2551,)
    x = np.linspace(0, 1, 20001)
    diff = transfer.lookup_crf(x, A7R3_CRF_TABLE_X255) - transfer.polynomial_crf(
        x, A7R3_CRF_POLYNOMIAL)
    assert np.max(np.abs(diff)) < 0.0072  # the authors' table vs polynomial: 0.00711


def test_a7r3_lookup_inverse_is_monotone_and_inverts_the_table():
    y = np.linspace(0, 1, 100001)
    inv = transfer.inverse_lookup_crf(y, A7R3_CRF_TABLE_X255)
    assert np.all(np.diff(inv) >= 0)
    x = np.linspace(0, 1, 2551)  # on the nodes both directions are exact interpolations
    round_trip = transfer.inverse_lookup_crf(transfer.lookup_crf(x, A7R3_CRF_TABLE_X255),
                                             A7R3_CRF_TABLE_X255)
    assert_close(round_trip, x, "crf_polynomial", "independent")


def test_retone_rejects_unknown_curves():
    with pytest.raises(ValueError, match="a7r3"):
        transfer.retone(np.zeros(3), "srgb")


@pytest.mark.parametrize("dtype, top", [(np.uint8, 255), (np.uint16, 65535)])
def test_codes_decode_through_the_table_to_the_bits_of_the_direct_eotf(dtype, top):
    codes = np.arange(top + 1, dtype=dtype)
    for offset in range(17):  # every code at several positions of a vectorized loop
        image = np.concatenate([np.zeros(offset, dtype), codes, codes[::-1]]).reshape(-1, 1)
        direct = transfer.srgb_to_linear(image / float(top))
        table = transfer.image_to_linear(image)
        assert table.shape == image.shape and table.dtype == np.float64
        assert np.array_equal(table.view(np.uint64), direct.view(np.uint64))


def test_float_images_decode_directly():
    image = np.linspace(-0.1, 1.1, 60, dtype=np.float32).reshape(4, 5, 3)
    assert np.array_equal(transfer.image_to_linear(image), transfer.srgb_to_linear(image))
