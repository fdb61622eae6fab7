from __future__ import annotations

import warnings

import numpy as np
import pytest

from gpu_blur.reference.bayer import (
    BayerPattern,
    channel_index,
    channel_masks,
    inverse_white_balance,
    mosaic,
    site_gains,
    white_balance,
)
from gpu_blur.testing import assert_close

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from colour_demosaicing import masks_CFA_Bayer, mosaicing_CFA_Bayer

PATTERNS = list(BayerPattern)
R, G, B = 0, 1, 2
EXPECTED_CHANNELS = {
    BayerPattern.RGGB: (R, G, G, B),
    BayerPattern.BGGR: (B, G, G, R),
    BayerPattern.GRBG: (G, R, B, G),
    BayerPattern.GBRG: (G, B, R, G),
}


@pytest.mark.parametrize("pattern", PATTERNS)
def test_channels_name_the_colour_at_each_cell_offset(pattern):
    assert pattern.channels == EXPECTED_CHANNELS[pattern]
    for k, (i, j) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        assert pattern.channel_at(i + 4, j + 6) == EXPECTED_CHANNELS[pattern][k]


@pytest.mark.parametrize("text", ["rggb", "RGGB", "Gbrg", " bggr "])
def test_parse_accepts_any_case(text):
    assert BayerPattern.parse(text) is BayerPattern(text.strip().upper())
    assert BayerPattern.parse(BayerPattern.GRBG) is BayerPattern.GRBG


@pytest.mark.parametrize("bad", ["RGBG", "", "XYZW", 3, None])
def test_parse_rejects_unknown_names_and_lists_the_four(bad):
    with pytest.raises(ValueError, match="RGGB, BGGR, GRBG, GBRG") as info:
        BayerPattern.parse(bad)
    assert repr(bad) in str(info.value)


def test_shifted_gives_the_pattern_seen_from_an_odd_origin():
    assert BayerPattern.RGGB.shifted(0, 1) is BayerPattern.GRBG
    assert BayerPattern.RGGB.shifted(1, 0) is BayerPattern.GBRG
    assert BayerPattern.RGGB.shifted(1, 1) is BayerPattern.BGGR
    for pattern in PATTERNS:
        assert pattern.shifted(2, -4) is pattern
        assert pattern.shifted(1, 1).shifted(1, 1) is pattern


@pytest.mark.parametrize("pattern", PATTERNS)
def test_channel_index_repeats_the_cell(pattern):
    index = channel_index(pattern, 6, 8)
    assert index.shape == (6, 8)
    cell = np.array(EXPECTED_CHANNELS[pattern]).reshape(2, 2)
    np.testing.assert_array_equal(index, np.tile(cell, (3, 4)))


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("origin", [(0, 1), (1, 0), (3, 5), (2, 2)])
def test_channel_index_with_origin_is_the_crop_of_the_full_image(pattern, origin):
    r, c = origin
    full = channel_index(pattern, 10 + r, 12 + c)
    np.testing.assert_array_equal(channel_index(pattern, 10, 12, origin=origin), full[r:, c:])


@pytest.mark.parametrize("pattern", PATTERNS)
def test_channel_masks_are_one_hot_and_agree_with_colour_demosaicing(pattern):
    masks = channel_masks(pattern, 6, 10)
    assert masks.shape == (6, 10, 3) and masks.dtype == bool
    np.testing.assert_array_equal(masks.sum(axis=2), 1)
    expected = np.stack(masks_CFA_Bayer((6, 10), pattern.value), axis=-1)
    np.testing.assert_array_equal(masks, expected)


@pytest.mark.parametrize("pattern", PATTERNS)
def test_mosaic_picks_the_pattern_channel_at_each_offset(pattern):
    rng = np.random.default_rng(1)
    rgb = rng.uniform(size=(4, 6, 3))
    raw = mosaic(rgb, pattern)
    assert raw.shape == (4, 6) and raw.dtype == np.float64
    for y in range(4):
        for x in range(6):
            channel = EXPECTED_CHANNELS[pattern][2 * (y % 2) + x % 2]
            assert raw[y, x] == rgb[y, x, channel]


@pytest.mark.parametrize("pattern", PATTERNS)
def test_mosaic_agrees_with_colour_demosaicing_on_a_photo(pattern, coffee_rgb):
    np.testing.assert_array_equal(
        mosaic(coffee_rgb, pattern), mosaicing_CFA_Bayer(coffee_rgb, pattern.value)
    )


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("origin", [(1, 0), (0, 1), (1, 3)])
def test_mosaic_of_a_tile_with_its_origin_is_the_crop_of_the_full_mosaic(
    pattern, origin, coffee_rgb
):
    r, c = origin
    full = mosaic(coffee_rgb, pattern)
    tile = mosaic(coffee_rgb[r : r + 8, c : c + 10], pattern, origin=origin)
    np.testing.assert_array_equal(tile, full[r : r + 8, c : c + 10])


@pytest.mark.parametrize("shape", [(3, 4), (4, 5), (1, 2), (0, 4)])
def test_mosaic_rejects_odd_or_empty_sizes_quoting_the_shape(shape):
    rgb = np.zeros(shape + (3,))
    with pytest.raises(ValueError, match="even") as info:
        mosaic(rgb, "RGGB")
    assert str(rgb.shape) in str(info.value)
    assert f"crop to ({shape[0] // 2 * 2}, {shape[1] // 2 * 2})" in str(info.value)


@pytest.mark.parametrize("shape", [(4, 4), (4, 4, 4), (4, 4, 3, 1)])
def test_mosaic_rejects_non_rgb_arrays(shape):
    with pytest.raises(ValueError, match=r"H x W x 3") as info:
        mosaic(np.zeros(shape), "RGGB")
    assert str(shape) in str(info.value)


@pytest.mark.parametrize(
    ("pattern", "expected"),
    [
        ("RGGB", [[2.0, 1.0], [1.0, 3.0]]),
        ("BGGR", [[3.0, 1.0], [1.0, 2.0]]),
        ("GRBG", [[1.0, 2.0], [3.0, 1.0]]),
        ("GBRG", [[1.0, 3.0], [2.0, 1.0]]),
    ],
)
def test_site_gains_are_laid_out_in_pattern_order(pattern, expected):
    gains = site_gains(pattern, red_gain=2.0, blue_gain=3.0)
    assert gains.dtype == np.float64
    np.testing.assert_array_equal(gains, expected)


@pytest.mark.parametrize("pattern", PATTERNS)
def test_white_balance_multiplies_each_site_by_its_gain(pattern):
    raw = np.arange(1.0, 25.0).reshape(4, 6)
    balanced = white_balance(raw, pattern, 1.5, 2.5)
    gain_of_channel = np.array([1.5, 1.0, 2.5])
    np.testing.assert_array_equal(balanced, raw * gain_of_channel[channel_index(pattern, 4, 6)])
    np.testing.assert_array_equal(
        inverse_white_balance(raw, pattern, 1.5, 2.5),
        raw / gain_of_channel[channel_index(pattern, 4, 6)],
    )


@pytest.mark.parametrize("pattern", PATTERNS)
def test_white_balance_origin_keeps_the_phase_of_the_full_image(pattern):
    rng = np.random.default_rng(2)
    raw = rng.uniform(size=(12, 14))
    full = white_balance(raw, pattern, 2.1, 1.7)
    tile = white_balance(raw[3:9, 1:11], pattern, 2.1, 1.7, origin=(3, 1))
    np.testing.assert_array_equal(tile, full[3:9, 1:11])


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize(("red_gain", "blue_gain"), [(2.1, 1.7), (1.9, 2.4), (0.37, 11.3)])
def test_inverse_white_balance_then_white_balance_cancels(pattern, red_gain, blue_gain):
    rng = np.random.default_rng(3)
    raw = rng.uniform(1e-6, 1.0, size=(32, 48))
    there_and_back = white_balance(
        inverse_white_balance(raw, pattern, red_gain, blue_gain), pattern, red_gain, blue_gain
    )
    assert_close(there_and_back, raw, "white_balance_round_trip", "numpy", "float64")
    back_and_there = inverse_white_balance(
        white_balance(raw, pattern, red_gain, blue_gain), pattern, red_gain, blue_gain
    )
    assert_close(back_and_there, raw, "white_balance_round_trip", "numpy", "float64")


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "x", None])
@pytest.mark.parametrize("which", ["red_gain", "blue_gain"])
@pytest.mark.parametrize("func", [white_balance, inverse_white_balance])
def test_gains_must_be_finite_and_positive(bad, which, func):
    gains = {"red_gain": 2.0, "blue_gain": 1.5}
    gains[which] = bad
    with pytest.raises(ValueError, match=f"{which} must be a finite number > 0"):
        func(np.ones((4, 4)), "RGGB", **gains)
    with pytest.raises(ValueError, match=which):
        site_gains("RGGB", **gains)


@pytest.mark.parametrize("shape", [(3, 4), (4, 7), (4, 4, 1), (4,)])
@pytest.mark.parametrize("func", [white_balance, inverse_white_balance])
def test_white_balance_rejects_odd_or_non_2d_raw_quoting_the_shape(shape, func):
    with pytest.raises(ValueError) as info:
        func(np.ones(shape), "RGGB", 2.0, 1.5)
    assert str(shape) in str(info.value)
