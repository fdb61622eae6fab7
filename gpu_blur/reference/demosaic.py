"""Demosaicing of Bayer mosaics: Malvar-He-Cutler 2004 and bilinear (numpy float64 reference).

Both methods keep the RAW value at the sites of its own channel and interpolate the two
missing channels from a small neighbourhood. They are linear, so each is a handful of fixed
stencils, written here as literal arrays and applied with shifted slices in float64.

Border rule (how the stencils see past the image edge):
    * ``border="reflect"`` (default) pads by mirroring about the edge sample *without*
      repeating it, as ``numpy.pad(mode="reflect")`` does: ``... x2 x1 | x0 x1 x2 ...``.
      A mirror about a sample maps position ``i`` to ``-i`` (or ``2(n-1) - i`` at the far
      edge), which has the same parity, so the padding keeps the Bayer phase: every tap that
      reaches past the edge reads a sample of the colour it expects. A flat field therefore
      comes back flat up to the last pixel, with no dark fringe.
    * ``border="zero"`` pads with zeros, as the RSBlur authors' PyTorch code does
      (``torch.nn.functional.conv2d(padding=2)``; TF uses SAME padding). The missing taps
      make a coloured fringe within 2 px of the edge. For Malvar it is not simply dark, since
      the stencils have negative taps: on a flat field of 1, G at R/B sites reads 7/8 on the
      edge row and 9/8 on the next, and single channels range from 5.5/8 to 11/8. Bilinear's
      1 px fringe is dark only. The authors crop 4 px per side afterwards. Kept only to
      reproduce their chain.

    colour-demosaicing, used as the independent check in the tests, pads with scipy's
    ``"reflect"`` mode, which *does* repeat the edge sample (``x1 x0 | x0 x1``) and so breaks
    the Bayer phase at the border; the two agree only away from the border.

Tiny images: the Bayer steps need even sizes of at least 2 x 2. When an axis is shorter than
the padding needs (``n - 1 < pad``, e.g. a 2 x 2 or 2 x N mosaic), the mirror is applied
again at the other edge, as often as needed: the padded axis is the even periodic extension of
the samples with period ``2 (n - 1)`` (for ``n = 2``: ``x0 x1 x0 x1 ...``). This is also what
``numpy.pad(mode="reflect")`` does. It keeps the phase, so the output is finite and a flat
field stays flat even for 2 x 2.

Output is **not clipped**: Malvar's stencils have negative taps and overshoot at edges (values
below 0 or above the input range); clipping is the pipeline's decision (the RSBlur PyTorch code
does not clip, its TF code clips to [0, 1]).

All stencils here are symmetric under a 180-degree rotation, so correlation equals
convolution and the orientation convention does not matter.
"""

from __future__ import annotations

import numpy as np

from .bayer import BayerPattern, _as_raw, _origin_parity, channel_index

__all__ = [
    "BILINEAR_G",
    "BILINEAR_RB",
    "BORDERS",
    "HALO",
    "MALVAR2004_G_AT_RB",
    "MALVAR2004_RB_AT_BR",
    "MALVAR2004_RB_AT_G_COLUMN",
    "MALVAR2004_RB_AT_G_ROW",
    "demosaic_bilinear",
    "demosaic_malvar2004",
    "halo",
]

#: Pixels of context each method reads on every side (the tile scheduler's halo).
HALO: dict[str, int] = {"malvar2004": 2, "bilinear": 1}

#: Accepted values of ``border``.
BORDERS: tuple[str, ...] = ("reflect", "zero")

R, G, B = 0, 1, 2

# Malvar, He, Cutler, "High-quality linear interpolation for demosaicing of Bayer-patterned
# color images", ICASSP 2004, Fig. 2. All four are divided by 8 and sum to 1.

#: G at R sites and at B sites (paper: "G at R locations", "G at B locations").
MALVAR2004_G_AT_RB = (
    np.array(
        [
            [0.0, 0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, 2.0, 0.0, 0.0],
            [-1.0, 2.0, 4.0, 2.0, -1.0],
            [0.0, 0.0, 2.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, 0.0, 0.0],
        ],
        dtype=np.float64,
    )
    / 8.0
)

#: R at a G site in an R row / B column; B at a G site in a B row / R column
#: (paper: "R at green in R row, B column"): the same colour sits left and right.
MALVAR2004_RB_AT_G_ROW = (
    np.array(
        [
            [0.0, 0.0, 0.5, 0.0, 0.0],
            [0.0, -1.0, 0.0, -1.0, 0.0],
            [-1.0, 4.0, 5.0, 4.0, -1.0],
            [0.0, -1.0, 0.0, -1.0, 0.0],
            [0.0, 0.0, 0.5, 0.0, 0.0],
        ],
        dtype=np.float64,
    )
    / 8.0
)

#: R at a G site in a B row / R column; B at a G site in an R row / B column
#: (paper: "R at green in B row, R column"): the transpose, the same colour above and below.
MALVAR2004_RB_AT_G_COLUMN = (
    np.array(
        [
            [0.0, 0.0, -1.0, 0.0, 0.0],
            [0.0, -1.0, 4.0, -1.0, 0.0],
            [0.5, 0.0, 5.0, 0.0, 0.5],
            [0.0, -1.0, 4.0, -1.0, 0.0],
            [0.0, 0.0, -1.0, 0.0, 0.0],
        ],
        dtype=np.float64,
    )
    / 8.0
)

#: R at B sites and B at R sites (paper: "R at blue in B row, B column").
MALVAR2004_RB_AT_BR = (
    np.array(
        [
            [0.0, 0.0, -1.5, 0.0, 0.0],
            [0.0, 2.0, 0.0, 2.0, 0.0],
            [-1.5, 0.0, 6.0, 0.0, -1.5],
            [0.0, 2.0, 0.0, 2.0, 0.0],
            [0.0, 0.0, -1.5, 0.0, 0.0],
        ],
        dtype=np.float64,
    )
    / 8.0
)

#: Bilinear G, applied to the G plane with zeros at R/B sites: mean of the 4 axial neighbours.
BILINEAR_G = (
    np.array(
        [
            [0.0, 1.0, 0.0],
            [1.0, 4.0, 1.0],
            [0.0, 1.0, 0.0],
        ],
        dtype=np.float64,
    )
    / 4.0
)

#: Bilinear R (or B), applied to the R (or B) plane with zeros elsewhere: mean of the 2
#: neighbours at G sites, of the 4 diagonal neighbours at B (or R) sites.
BILINEAR_RB = (
    np.array(
        [
            [1.0, 2.0, 1.0],
            [2.0, 4.0, 2.0],
            [1.0, 2.0, 1.0],
        ],
        dtype=np.float64,
    )
    / 4.0
)


def halo(method: str) -> int:
    """Pixels of context ``method`` ("malvar2004" or "bilinear") reads on each side."""
    try:
        return HALO[method]
    except KeyError:
        raise ValueError(
            f"unknown demosaic method {method!r}; expected one of {', '.join(HALO)}"
        ) from None


def _reflect_indices(n: int, pad: int) -> np.ndarray:
    """Source index of each position ``-pad .. n + pad - 1`` under the reflect border rule.

    Mirrors about sample 0 and sample ``n - 1`` without repeating them, as often as needed:
    the even periodic extension with period ``2 (n - 1)``. Parity of the index is kept.
    """
    positions = np.arange(-pad, n + pad)
    if n == 1:
        return np.zeros_like(positions)
    period = 2 * (n - 1)
    folded = np.mod(positions, period)
    return np.where(folded > n - 1, period - folded, folded)


def _pad(raw: np.ndarray, pad: int, border: str) -> np.ndarray:
    """Pad an ``H x W`` plane by ``pad`` on every side under ``border``."""
    if border == "reflect":
        rows = _reflect_indices(raw.shape[0], pad)
        cols = _reflect_indices(raw.shape[1], pad)
        return raw[rows[:, None], cols[None, :]]
    _check_border(border)
    return np.pad(raw, pad, mode="constant", constant_values=0.0)


def _correlate(
    padded: np.ndarray,
    kernel: np.ndarray,
    pad: int,
    shape: tuple[int, int],
    start: tuple[int, int] = (0, 0),
    step: int = 1,
) -> np.ndarray:
    """Correlate a padded plane with ``kernel`` at the sites ``start::step`` of the image.

    Args:
        padded: ``(H + 2 pad) x (W + 2 pad)`` plane.
        kernel: Odd square stencil, half-width ``<= pad``.
        pad: Padding of ``padded`` on each side.
        shape: ``(H, W)`` of the unpadded image.
        start: ``(row, col)`` of the first output site.
        step: Stride between output sites (2 for one site of each Bayer cell).

    Returns:
        Array of the sites ``[start[0]::step, start[1]::step]``. Zero taps are skipped.
    """
    height, width = shape
    r0, c0 = start
    half = kernel.shape[0] // 2
    out_rows = len(range(r0, height, step))
    out_cols = len(range(c0, width, step))
    out = np.zeros((out_rows, out_cols), dtype=np.float64)
    for di in range(kernel.shape[0]):
        for dj in range(kernel.shape[1]):
            weight = kernel[di, dj]
            if weight == 0.0:
                continue
            rs = pad + r0 + di - half
            cs = pad + c0 + dj - half
            out += (
                weight * padded[rs : rs + step * out_rows : step, cs : cs + step * out_cols : step]
            )
    return out


def _check_border(border: str) -> None:
    if border not in BORDERS:
        raise ValueError(f"unknown border {border!r}; expected one of {', '.join(BORDERS)}")


def demosaic_malvar2004(
    raw: np.ndarray,
    pattern: BayerPattern | str,
    border: str = "reflect",
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Malvar-He-Cutler gradient-corrected linear demosaicing.

    Malvar, He, Cutler, "High-quality linear interpolation for demosaicing of Bayer-patterned
    color images", ICASSP 2004 (filters of Fig. 2; RSBlur notes section 5.6).

    Each site keeps its own RAW value for its channel; G at R and B sites comes from
    :data:`MALVAR2004_G_AT_RB`; at G sites the R and B values come from
    :data:`MALVAR2004_RB_AT_G_ROW` for the colour that shares the site's row and from
    :data:`MALVAR2004_RB_AT_G_COLUMN` for the colour that shares its column; R at B sites and
    B at R sites come from :data:`MALVAR2004_RB_AT_BR`. Only the two values a site needs are
    computed. The output is not clipped.

    Args:
        raw: ``H x W`` mosaic, ``H`` and ``W`` even (>= 2).
        pattern: Bayer order of the full image.
        border: "reflect" (phase-keeping mirror, default) or "zero" (the RSBlur authors'
            padding); see the module docstring.
        origin: ``(row, col)`` of ``raw[0, 0]`` in the full image.

    Returns:
        ``H x W x 3`` float64 RGB image.

    Raises:
        ValueError: Bad shape, odd size, unknown pattern or border.
    """
    raw = _as_raw(raw)
    _check_border(border)
    local = BayerPattern.parse(pattern).shifted(*_origin_parity(origin))
    pad = HALO["malvar2004"]
    padded = _pad(raw, pad, border)
    shape = (raw.shape[0], raw.shape[1])
    rgb = np.empty(shape + (3,), dtype=np.float64)
    for i in (0, 1):
        row_channels = (local.channels[2 * i], local.channels[2 * i + 1])
        for j in (0, 1):
            channel = local.channels[2 * i + j]
            rgb[i::2, j::2, channel] = raw[i::2, j::2]

            def at_site(kernel: np.ndarray, i: int = i, j: int = j) -> np.ndarray:
                return _correlate(padded, kernel, pad, shape, (i, j), 2)

            if channel == G:
                for other in (R, B):
                    in_row = other in row_channels
                    kernel = MALVAR2004_RB_AT_G_ROW if in_row else MALVAR2004_RB_AT_G_COLUMN
                    rgb[i::2, j::2, other] = at_site(kernel)
            else:
                rgb[i::2, j::2, G] = at_site(MALVAR2004_G_AT_RB)
                rgb[i::2, j::2, B if channel == R else R] = at_site(MALVAR2004_RB_AT_BR)
    return rgb


def demosaic_bilinear(
    raw: np.ndarray,
    pattern: BayerPattern | str,
    border: str = "reflect",
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Classic bilinear demosaicing.

    Each channel's plane, with zeros at the other channels' sites, is correlated with
    :data:`BILINEAR_G` (G: mean of the 4 axial neighbours) or :data:`BILINEAR_RB` (R, B:
    mean of the 2 neighbours at G sites, of the 4 diagonal neighbours at B/R sites); the RAW
    value is then restored at the channel's own sites. Under ``border="zero"`` the padded
    plane is zero, so the 1 px border is darkened.

    Args:
        raw: ``H x W`` mosaic, ``H`` and ``W`` even (>= 2).
        pattern: Bayer order of the full image.
        border: "reflect" (phase-keeping mirror, default) or "zero"; see the module docstring.
        origin: ``(row, col)`` of ``raw[0, 0]`` in the full image.

    Returns:
        ``H x W x 3`` float64 RGB image.

    Raises:
        ValueError: Bad shape, odd size, unknown pattern or border.
    """
    raw = _as_raw(raw)
    _check_border(border)
    local = BayerPattern.parse(pattern).shifted(*_origin_parity(origin))
    pad = HALO["bilinear"]
    shape = (raw.shape[0], raw.shape[1])
    index = channel_index(local, shape[0], shape[1])
    rgb = np.empty(shape + (3,), dtype=np.float64)
    for channel, kernel in ((R, BILINEAR_RB), (G, BILINEAR_G), (B, BILINEAR_RB)):
        own = index == channel
        plane = np.where(own, raw, 0.0)
        rgb[:, :, channel] = np.where(
            own, raw, _correlate(_pad(plane, pad, border), kernel, pad, shape)
        )
    return rgb
