"""Bayer colour filter arrays: pattern, mosaic and white balance (numpy float64 reference).

A Bayer mosaic samples one colour per pixel in a repeating 2 x 2 cell. The pattern's four
letters name the colours at offsets ``(0, 0), (0, 1), (1, 0), (1, 1)`` of that cell, so
``RGGB`` has red at the top-left, green beside and below it, and blue at the bottom-right.

Source: RSBlur (Rim et al., ECCV 2022), pipeline notes sections 5.3 and 5.4: one of the four
patterns is drawn per image; the RAW mosaic is divided by the white-balance gains of its red
and blue sites before noise and multiplied back after it (green has gain 1).

Conventions:
    * RGB images are ``H x W x 3`` (channel order R, G, B), a RAW mosaic is ``H x W``.
    * Channel indices are R = 0, G = 1, B = 2.
    * Everything is computed in float64.
    * ``origin=(row, col)`` is the position of ``raw[0, 0]`` in the full image. A tile cut at
      an odd row or column sees the cell with a different phase; passing its origin keeps the
      pattern of the full image. Only ``origin % 2`` matters.
    * The Bayer steps (:func:`mosaic`, :func:`white_balance`, :func:`inverse_white_balance`)
      need even ``H`` and ``W`` of at least 2, so every 2 x 2 cell is complete.
"""

from __future__ import annotations

import enum
import math

import numpy as np

__all__ = [
    "BayerPattern",
    "channel_index",
    "channel_masks",
    "inverse_white_balance",
    "mosaic",
    "site_gains",
    "white_balance",
]

_CHANNEL_OF_LETTER = {"R": 0, "G": 1, "B": 2}


class BayerPattern(str, enum.Enum):
    """The four Bayer orders.

    The letters name the colours at offsets ``(0, 0), (0, 1), (1, 0), (1, 1)`` of each 2 x 2
    cell, i.e. row-major through the cell.
    """

    RGGB = "RGGB"
    BGGR = "BGGR"
    GRBG = "GRBG"
    GBRG = "GBRG"

    @property
    def channels(self) -> tuple[int, int, int, int]:
        """Channel index (R = 0, G = 1, B = 2) at offsets (0,0), (0,1), (1,0), (1,1)."""
        c = tuple(_CHANNEL_OF_LETTER[letter] for letter in self.value)
        return (c[0], c[1], c[2], c[3])

    def channel_at(self, row: int, col: int) -> int:
        """Channel index at full-image position ``(row, col)`` (only its parity matters)."""
        return self.channels[2 * (row % 2) + (col % 2)]

    def shifted(self, row: int, col: int) -> BayerPattern:
        """Return the pattern seen by a tile whose ``[0, 0]`` lies at ``(row, col)`` of this one.

        Example: ``BayerPattern.RGGB.shifted(0, 1)`` is ``GRBG``.
        """
        letters = "".join(
            self.value[2 * ((i + row) % 2) + ((j + col) % 2)] for i in (0, 1) for j in (0, 1)
        )
        return BayerPattern(letters)

    @classmethod
    def parse(cls, value: BayerPattern | str) -> BayerPattern:
        """Return the pattern named by ``value`` (any case); a pattern is returned as is.

        Raises:
            ValueError: ``value`` names none of RGGB, BGGR, GRBG, GBRG.
        """
        if isinstance(value, cls):
            return value
        if isinstance(value, str):
            try:
                return cls(value.strip().upper())
            except ValueError:
                pass
        allowed = ", ".join(p.value for p in cls)
        raise ValueError(f"unknown Bayer pattern {value!r}; expected one of {allowed} (any case)")


def _origin_parity(origin: tuple[int, int]) -> tuple[int, int]:
    """Validate ``origin`` and return ``(row % 2, col % 2)``."""
    try:
        row, col = (int(v) for v in origin)
    except (TypeError, ValueError):
        raise ValueError(f"origin must be a pair of integers (row, col); got {origin!r}") from None
    return row % 2, col % 2


def _local_pattern(pattern: BayerPattern | str, origin: tuple[int, int]) -> BayerPattern:
    """Return the pattern as seen from ``origin``: its ``[0, 0]`` is the array's ``[0, 0]``."""
    return BayerPattern.parse(pattern).shifted(*_origin_parity(origin))


def _check_bayer_size(height: int, width: int, what: str) -> None:
    """Raise unless ``height`` and ``width`` are even and at least 2."""
    if height < 2 or width < 2 or height % 2 or width % 2:
        raise ValueError(
            f"{what} has size {height} x {width}: Bayer steps need even sizes of at least 2; "
            f"crop to ({height // 2 * 2}, {width // 2 * 2})"
        )


def _as_raw(raw: np.ndarray, what: str = "raw") -> np.ndarray:
    """Return ``raw`` as a float64 ``H x W`` array with even sizes, or raise."""
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2:
        raise ValueError(f"{what} must be a H x W mosaic (one sample per pixel); got {raw.shape}")
    _check_bayer_size(raw.shape[0], raw.shape[1], f"{what} of shape {raw.shape}")
    return raw


def _check_gain(name: str, gain: float) -> float:
    """Return ``gain`` as a float; raise unless it is finite and > 0."""
    try:
        value = float(gain)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a finite number > 0; got {gain!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a finite number > 0; got {gain!r}")
    return value


def channel_index(
    pattern: BayerPattern | str, height: int, width: int, origin: tuple[int, int] = (0, 0)
) -> np.ndarray:
    """Channel sampled at each pixel of a mosaic.

    Args:
        pattern: Bayer order of the full image.
        height: Rows ``H`` (any size >= 0; the cells at the edges may be partial).
        width: Columns ``W``.
        origin: ``(row, col)`` of pixel ``[0, 0]`` in the full image.

    Returns:
        ``H x W`` int array of channel indices, R = 0, G = 1, B = 2.
    """
    local = _local_pattern(pattern, origin)
    if height < 0 or width < 0:
        raise ValueError(f"height and width must be >= 0; got {height} x {width}")
    cell = np.array(local.channels, dtype=np.intp).reshape(2, 2)
    rows = np.arange(height) % 2
    cols = np.arange(width) % 2
    return cell[rows[:, None], cols[None, :]]


def channel_masks(
    pattern: BayerPattern | str, height: int, width: int, origin: tuple[int, int] = (0, 0)
) -> np.ndarray:
    """Boolean masks of the sites of each channel.

    Args:
        pattern: Bayer order of the full image.
        height: Rows ``H``.
        width: Columns ``W``.
        origin: ``(row, col)`` of pixel ``[0, 0]`` in the full image.

    Returns:
        ``H x W x 3`` bool array; ``[..., c]`` is True where channel ``c`` is sampled. Exactly
        one of the three is True at each pixel.
    """
    index = channel_index(pattern, height, width, origin)
    return index[:, :, None] == np.arange(3)[None, None, :]


def mosaic(
    rgb: np.ndarray, pattern: BayerPattern | str, origin: tuple[int, int] = (0, 0)
) -> np.ndarray:
    """Sample an RGB image through a Bayer colour filter array.

    Args:
        rgb: ``H x W x 3`` image (R, G, B), ``H`` and ``W`` even.
        pattern: Bayer order of the full image.
        origin: ``(row, col)`` of ``rgb[0, 0]`` in the full image.

    Returns:
        ``H x W`` float64 mosaic: at each pixel, the channel the pattern puts there.

    Raises:
        ValueError: ``rgb`` is not ``H x W x 3`` or has an odd size.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be a H x W x 3 image (R, G, B); got shape {rgb.shape}")
    height, width = rgb.shape[:2]
    _check_bayer_size(height, width, f"rgb of shape {rgb.shape}")
    index = channel_index(pattern, height, width, origin)
    return np.take_along_axis(rgb, index[:, :, None], axis=2)[:, :, 0]


def site_gains(pattern: BayerPattern | str, red_gain: float, blue_gain: float) -> np.ndarray:
    """White-balance gain of each site of the 2 x 2 cell, in pattern order.

    RGGB -> ``[[r, 1], [1, b]]``, BGGR -> ``[[b, 1], [1, r]]``, GRBG -> ``[[1, r], [b, 1]]``,
    GBRG -> ``[[1, b], [r, 1]]`` (RSBlur notes section 5.3 lists the same as packed planes).

    Args:
        pattern: Bayer order.
        red_gain: Gain of the red sites, finite and > 0.
        blue_gain: Gain of the blue sites, finite and > 0.

    Returns:
        ``2 x 2`` float64 array.

    Raises:
        ValueError: A gain is not finite or not > 0.
    """
    pattern = BayerPattern.parse(pattern)
    per_channel = (
        _check_gain("red_gain", red_gain),
        1.0,
        _check_gain("blue_gain", blue_gain),
    )
    return np.array([per_channel[c] for c in pattern.channels], dtype=np.float64).reshape(2, 2)


def _gain_map(
    raw: np.ndarray,
    pattern: BayerPattern | str,
    red_gain: float,
    blue_gain: float,
    origin: tuple[int, int],
) -> np.ndarray:
    """Gains tiled over ``raw`` (``H x W``), phase set by ``origin``."""
    cell = site_gains(_local_pattern(pattern, origin), red_gain, blue_gain)
    return np.tile(cell, (raw.shape[0] // 2, raw.shape[1] // 2))


def white_balance(
    raw: np.ndarray,
    pattern: BayerPattern | str,
    red_gain: float,
    blue_gain: float,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Multiply each site of a mosaic by its white-balance gain (green sites by 1).

    Args:
        raw: ``H x W`` mosaic, ``H`` and ``W`` even.
        pattern: Bayer order of the full image.
        red_gain: Gain of the red sites, finite and > 0.
        blue_gain: Gain of the blue sites, finite and > 0.
        origin: ``(row, col)`` of ``raw[0, 0]`` in the full image.

    Returns:
        ``H x W`` float64 mosaic (a new array).

    Raises:
        ValueError: Bad shape, odd size, or a gain not finite and > 0.
    """
    raw = _as_raw(raw)
    return raw * _gain_map(raw, pattern, red_gain, blue_gain, origin)


def inverse_white_balance(
    raw: np.ndarray,
    pattern: BayerPattern | str,
    red_gain: float,
    blue_gain: float,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Divide each site of a mosaic by its white-balance gain; undoes :func:`white_balance`.

    Args:
        raw: ``H x W`` mosaic, ``H`` and ``W`` even.
        pattern: Bayer order of the full image.
        red_gain: Gain of the red sites, finite and > 0.
        blue_gain: Gain of the blue sites, finite and > 0.
        origin: ``(row, col)`` of ``raw[0, 0]`` in the full image.

    Returns:
        ``H x W`` float64 mosaic (a new array).

    Raises:
        ValueError: Bad shape, odd size, or a gain not finite and > 0.
    """
    raw = _as_raw(raw)
    return raw / _gain_map(raw, pattern, red_gain, blue_gain, origin)
