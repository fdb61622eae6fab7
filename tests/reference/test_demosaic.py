from __future__ import annotations

import functools
import importlib
import warnings

import numpy as np
import pytest
import scipy.ndimage
from hypothesis import given, settings
from hypothesis import strategies as st

from gpu_blur.constants import rsblur_data
from gpu_blur.reference.bayer import BayerPattern, channel_masks, mosaic
from gpu_blur.reference.demosaic import (
    BORDERS,
    HALO,
    MALVAR2004_G_AT_RB,
    MALVAR2004_RB_AT_BR,
    MALVAR2004_RB_AT_G_COLUMN,
    MALVAR2004_RB_AT_G_ROW,
    demosaic_bilinear,
    demosaic_malvar2004,
    halo,
)
from gpu_blur.testing import assert_close

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from colour_demosaicing import (
        demosaicing_CFA_Bayer_bilinear,
        demosaicing_CFA_Bayer_Malvar2004,
    )

    COLOUR_MODULES = {
        "malvar2004": importlib.import_module("colour_demosaicing.bayer.demosaicing.malvar2004"),
        "bilinear": importlib.import_module("colour_demosaicing.bayer.demosaicing.bilinear"),
    }

PATTERNS = list(BayerPattern)
METHODS = {"malvar2004": demosaic_malvar2004, "bilinear": demosaic_bilinear}
COLOUR = {
    "malvar2004": demosaicing_CFA_Bayer_Malvar2004,
    "bilinear": demosaicing_CFA_Bayer_bilinear,
}
# colour-demosaicing pads with scipy's "reflect" (edge sample repeated): compare away from it.
INTERIOR = (slice(2, -2), slice(2, -2))

# Whole photo; a crop at an odd row and column offset; the transpose (rows become columns);
# a second photograph (tests/data/rocket.jpg).
PHOTOS = {
    "coffee": lambda coffee, rocket: coffee,
    "coffee_crop_at_odd_offset": lambda coffee, rocket: coffee[1:-1, 3:-1],
    "coffee_transposed": lambda coffee, rocket: coffee.transpose(1, 0, 2),
    "rocket": lambda coffee, rocket: rocket,
}


def colour_demosaic(method, raw, pattern, monkeypatch=None, scipy_mode=None):
    """colour-demosaicing's result, optionally with its scipy convolve border mode replaced."""
    if scipy_mode is not None:
        monkeypatch.setattr(
            COLOUR_MODULES[method],
            "convolve",
            functools.partial(scipy.ndimage.convolve, mode=scipy_mode),
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.asarray(COLOUR[method](raw, pattern.value), dtype=np.float64)


@pytest.mark.parametrize("photo", list(PHOTOS))
@pytest.mark.parametrize("pattern", PATTERNS)
def test_malvar2004_matches_colour_demosaicing_on_photos_interior(
    photo, pattern, coffee_rgb, rocket_rgb
):
    raw = mosaic(PHOTOS[photo](coffee_rgb, rocket_rgb), pattern)
    ours = demosaic_malvar2004(raw, pattern)
    theirs = colour_demosaic("malvar2004", raw, pattern)
    assert_close(ours[INTERIOR], theirs[INTERIOR], "demosaic_malvar2004", "independent")


@pytest.mark.parametrize("photo", list(PHOTOS))
@pytest.mark.parametrize("pattern", PATTERNS)
def test_bilinear_matches_colour_demosaicing_on_photos_interior(
    photo, pattern, coffee_rgb, rocket_rgb
):
    raw = mosaic(PHOTOS[photo](coffee_rgb, rocket_rgb), pattern)
    ours = demosaic_bilinear(raw, pattern)
    theirs = colour_demosaic("bilinear", raw, pattern)
    assert_close(ours[INTERIOR], theirs[INTERIOR], "demosaic_bilinear", "independent")


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize(
    ("border", "scipy_mode"),
    [("reflect", "mirror"), ("zero", "constant")],
)
@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (6, 2), (4, 4), (24, 30)])
def test_whole_image_matches_colour_demosaicing_with_the_same_border(
    method, pattern, border, scipy_mode, shape, coffee_rgb, monkeypatch
):
    # scipy's "mirror" mirrors without repeating the edge sample, as often as needed: the
    # documented reflect rule, tiny images included. "constant" is the authors' zero padding.
    raw = mosaic(coffee_rgb[101 : 101 + shape[0], 203 : 203 + shape[1]], pattern)
    ours = METHODS[method](raw, pattern, border=border)
    theirs = colour_demosaic(method, raw, pattern, monkeypatch, scipy_mode)
    assert_close(ours, theirs, f"demosaic_{method}", "independent")


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("pattern", PATTERNS)
def test_raw_values_are_kept_at_their_own_sites(method, pattern, coffee_rgb):
    raw = mosaic(coffee_rgb, pattern)
    out = METHODS[method](raw, pattern)
    masks = channel_masks(pattern, *raw.shape)
    for channel in range(3):
        np.testing.assert_array_equal(
            out[..., channel][masks[..., channel]], raw[masks[..., channel]]
        )


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (6, 2), (4, 4), (10, 14)])
@pytest.mark.parametrize("origin", [(0, 0), (1, 0), (0, 1), (1, 1)])
def test_flat_field_comes_back_flat_everywhere_with_reflect(method, pattern, shape, origin):
    value = 0.3721
    raw = mosaic(np.full(shape + (3,), value), pattern, origin=origin)
    out = METHODS[method](raw, pattern, border="reflect", origin=origin)
    assert out.shape == shape + (3,)
    assert_close(out, np.full(shape + (3,), value), "demosaic_flat_field", "numpy")


@settings(max_examples=150, deadline=None)
@given(
    value=st.floats(
        min_value=-1e200, max_value=1e200, allow_nan=False, allow_subnormal=False
    ).filter(lambda v: v == 0.0 or abs(v) > 1e-200),
    half_height=st.integers(1, 9),
    half_width=st.integers(1, 9),
    pattern=st.sampled_from(PATTERNS),
    method=st.sampled_from(list(METHODS)),
    origin=st.tuples(st.integers(0, 3), st.integers(0, 3)),
)
def test_flat_field_property(value, half_height, half_width, pattern, method, origin):
    shape = (2 * half_height, 2 * half_width)
    out = METHODS[method](np.full(shape, value), pattern, origin=origin)
    assert_close(out, np.full(shape + (3,), value), "demosaic_flat_field", "numpy")


@pytest.mark.parametrize("pattern", PATTERNS)
def test_zero_border_makes_a_fringe_in_the_first_two_rows_that_reflect_does_not(pattern):
    shape = (12, 16)
    flat = np.ones(shape)
    ones = np.ones(shape + (3,))
    masks = channel_masks(pattern, *shape)
    reflect = demosaic_malvar2004(flat, pattern, border="reflect")
    zero = demosaic_malvar2004(flat, pattern, border="zero")
    assert_close(reflect, ones, "demosaic_flat_field", "numpy")
    # Away from the 2 px halo both agree: the border rule touches nothing else.
    assert_close(zero[INTERIOR], reflect[INTERIOR], "demosaic_flat_field", "numpy")
    # The edge row comes out darker on average, the next one brighter (negative taps) ...
    assert zero[0, 2:-2].mean() < 1.0 < zero[1, 2:-2].mean()
    # ... exactly as the missing taps say: G at an R/B site of row 0 loses the -1 at distance
    # 2 and the +2 at distance 1 above it, (8 - 2 + 1) / 8; on row 1 it loses only the -1.
    for row, expected in ((0, 7.0 / 8.0), (1, 9.0 / 8.0)):
        g_interpolated = ~masks[row, 2:-2, 1]
        np.testing.assert_array_equal(zero[row, 2:-2, 1][g_interpolated], expected)
    # Bilinear reads 1 px and has no negative taps: a dark edge row only.
    zero_bilinear = demosaic_bilinear(flat, pattern, border="zero")
    np.testing.assert_array_equal(zero_bilinear[0, 1:-1, 1][~masks[0, 1:-1, 1]], 3.0 / 4.0)
    assert zero_bilinear[0].max() == 1.0 and zero_bilinear[0].mean() < 1.0
    assert_close(zero_bilinear[1:-1, 1:-1], ones[1:-1, 1:-1], "demosaic_flat_field", "numpy")
    assert_close(demosaic_bilinear(flat, pattern), ones, "demosaic_flat_field", "numpy")


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("origin", [(1, 0), (0, 3), (5, 7)])
def test_tile_with_halo_and_origin_reproduces_the_full_image(method, pattern, origin, coffee_rgb):
    full_raw = mosaic(coffee_rgb[:64, :80], pattern)
    full = METHODS[method](full_raw, pattern)
    r, c = origin
    h = halo(method)
    tile = METHODS[method](full_raw[r : r + 20, c : c + 30], pattern, origin=origin)
    np.testing.assert_array_equal(tile[h:-h, h:-h], full[r + h : r + 20 - h, c + h : c + 30 - h])


def test_malvar2004_output_is_not_clipped(coffee_rgb):
    out = demosaic_malvar2004(mosaic(coffee_rgb, "RGGB"), "RGGB")
    assert out.min() < 0.0 and out.max() > 1.0


@pytest.mark.parametrize(
    "kernel",
    [MALVAR2004_G_AT_RB, MALVAR2004_RB_AT_G_ROW, MALVAR2004_RB_AT_G_COLUMN, MALVAR2004_RB_AT_BR],
)
def test_malvar2004_filters_sum_to_one_and_are_point_symmetric(kernel):
    assert kernel.shape == (5, 5)
    assert kernel.sum() == 1.0
    np.testing.assert_array_equal(kernel, kernel[::-1, ::-1])


def test_malvar2004_filters_match_the_authors_kernels():
    kernels = rsblur_data()["malvar2004_kernels"]
    ours = {
        "g_at_rb": MALVAR2004_G_AT_RB,
        "rb_at_g_row": MALVAR2004_RB_AT_G_ROW,
        "rb_at_g_column": MALVAR2004_RB_AT_G_COLUMN,
        "rb_at_br": MALVAR2004_RB_AT_BR,
    }
    for key, kernel in ours.items():
        np.testing.assert_array_equal(kernel, np.array(kernels[key]))
    np.testing.assert_array_equal(MALVAR2004_RB_AT_G_COLUMN, MALVAR2004_RB_AT_G_ROW.T)


def test_halo_names_the_context_each_method_reads():
    assert HALO == {"malvar2004": 2, "bilinear": 1}
    assert halo("malvar2004") == 2 and halo("bilinear") == 1
    with pytest.raises(ValueError, match="malvar2004, bilinear"):
        halo("menon2007")


@pytest.mark.parametrize("method", list(METHODS))
def test_bad_inputs_raise_errors_that_quote_them(method):
    func = METHODS[method]
    with pytest.raises(ValueError, match="'mirror'.*reflect, zero"):
        func(np.ones((4, 4)), "RGGB", border="mirror")
    assert BORDERS == ("reflect", "zero")
    with pytest.raises(ValueError, match=r"\(5, 4\).*crop to \(4, 4\)"):
        func(np.ones((5, 4)), "RGGB")
    with pytest.raises(ValueError, match=r"\(4, 4, 3\)"):
        func(np.ones((4, 4, 3)), "RGGB")
    with pytest.raises(ValueError, match="RGGB, BGGR, GRBG, GBRG"):
        func(np.ones((4, 4)), "RGBG")
