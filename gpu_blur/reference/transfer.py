"""Transfer functions: sRGB EOTF/OETF, pure gamma, and polynomial / lookup-table camera responses.

All functions take and return float64 arrays of any shape (values are per channel).

sRGB constants are those of IEC 61966-2-1 as the RSBlur code uses them (MATLAB ``rgb2lin`` /
``lin2rgb`` clones in ``Uformer-RSBlur/ISP/utils.py``): odd extension for negative inputs, no
clipping inside. The A7R3 camera response (a degree-7 polynomial and its 2,551-entry table) is
camera data and lives in :mod:`gpu_blur.constants`; a calibrated camera's fitted response is in
its camera file (:mod:`gpu_blur.cameras`); these functions take them as arguments.

Powers are :func:`gpu_blur.reference.fixedmath.power` (IEEE operations only, within 1 ulp),
not numpy's ``**``, whose SIMD paths give other last bits on other CPUs.
"""

from __future__ import annotations

import functools

import numpy as np

from gpu_blur.reference import fixedmath

__all__ = ["RETONE_CURVES", "SRGB_DECODE_KNEE", "SRGB_ENCODE_KNEE", "SRGB_GAMMA", "SRGB_OFFSET",
           "SRGB_SCALE", "SRGB_SLOPE", "a7r3_lookup_table", "gamma_to_linear", "image_to_linear",
           "inverse_lookup_crf", "linear_to_gamma", "linear_to_srgb", "lookup_crf",
           "lookup_table_grid", "polynomial_crf", "resample_lookup_table", "retone",
           "retone_polynomial", "srgb_to_linear"]

#: sRGB EOTF knee on the encoded value (IEC 61966-2-1).
SRGB_DECODE_KNEE = 0.04045
#: sRGB OETF knee on the linear value (IEC 61966-2-1).
SRGB_ENCODE_KNEE = 0.0031308
SRGB_SLOPE = 12.92
SRGB_GAMMA = 2.4
SRGB_SCALE = 1.055
SRGB_OFFSET = 0.055


def srgb_to_linear(encoded) -> np.ndarray:
    """SRGB EOTF: y = sign(x) * (|x| / 12.92 if |x| < 0.04045 else ((|x| + 0.055) / 1.055)^2.4).

    Args:
        encoded: sRGB values, nominally in [0, 1]; any shape.

    Returns:
        Linear values, float64, same shape. Negative inputs map oddly, nothing is clipped.
    """
    x = np.asarray(encoded, dtype=np.float64)
    a = np.abs(x)
    curve = np.where(a < SRGB_DECODE_KNEE, SRGB_DECODE_KNEE, a)  # keep pow on its own branch
    y = np.where(
        a < SRGB_DECODE_KNEE,
        a / SRGB_SLOPE,
        fixedmath.power((curve + SRGB_OFFSET) / SRGB_SCALE, SRGB_GAMMA),
    )
    return np.copysign(y, x)


@functools.cache
def _linear_codes(bits: int) -> np.ndarray:
    """srgb_to_linear of every ``bits``-bit code's value ``k / (2^bits - 1)`` (read-only)."""
    table = srgb_to_linear(np.arange(2**bits) / float(2**bits - 1))
    table.flags.writeable = False
    return table


def image_to_linear(image) -> np.ndarray:
    """The sRGB EOTF of an image: ``srgb_to_linear`` of its values in [0, 1].

    8- and 16-bit codes go through a table of every code's linear value (the same numbers, a
    lookup instead of a power a value: 9 frames of 960 x 600 in 30 instead of 270 ms on a
    2-core EPYC); floats are decoded directly.

    Args:
        image: uint8 or uint16 codes (``k / 255``, ``k / 65535``), or float sRGB values.

    Returns:
        Linear values, float64, the image's shape.
    """
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return _linear_codes(8)[image]
    if image.dtype == np.uint16:
        return _linear_codes(16)[image]
    return srgb_to_linear(image)


def linear_to_srgb(linear) -> np.ndarray:
    """SRGB OETF: y = sign(x) * (12.92 |x| if |x| < 0.0031308 else 1.055 |x|^(1/2.4) - 0.055).

    The branch is selected before the power, so 0 and denormals never reach a log or pow.
    The standard's knees do not meet exactly: just below 0.0031308 the linear segment gives
    0.04044994, at it the curve gives 0.04044991, a step down of 3.1e-8 (the only place the
    function is not monotone; kept to match the definition and the RSBlur code).

    Args:
        linear: linear values; any shape.

    Returns:
        sRGB-encoded values, float64, same shape; not clipped.
    """
    x = np.asarray(linear, dtype=np.float64)
    a = np.abs(x)
    curve = np.where(a < SRGB_ENCODE_KNEE, SRGB_ENCODE_KNEE, a)
    y = np.where(
        a < SRGB_ENCODE_KNEE,
        SRGB_SLOPE * a,
        SRGB_SCALE * fixedmath.power(curve, 1.0 / SRGB_GAMMA) - SRGB_OFFSET,
    )
    return np.copysign(y, x)


def gamma_to_linear(encoded, gamma: float = 2.2) -> np.ndarray:
    """Pure power-law decode ``sign(x) |x|^gamma`` (no linear toe)."""
    x = np.asarray(encoded, dtype=np.float64)
    return np.copysign(fixedmath.power(np.abs(x), gamma), x)


def linear_to_gamma(linear, gamma: float = 2.2) -> np.ndarray:
    """Pure power-law encode ``sign(x) |x|^(1/gamma)`` (no linear toe)."""
    x = np.asarray(linear, dtype=np.float64)
    return np.copysign(fixedmath.power(np.abs(x), 1.0 / gamma), x)


def polynomial_crf(linear, coefficients) -> np.ndarray:
    """Polynomial camera response ``clip(sum_k c_k x^k, 0, 1)``, evaluated by Horner's rule.

    Supplementary Sec. 7, Eq. 6 (Rim et al. fit K = 7 for the Sony A7R3). The A7R3 polynomial is
    negative below about 0.0011 and exceeds 1 at 1, hence the clip; it is very slightly
    non-monotone near 0.862.

    Args:
        linear: linear intensities; any shape.
        coefficients: c_0 ... c_K in ascending powers.

    Returns:
        Rendered values in [0, 1], float64, same shape.
    """
    x = np.asarray(linear, dtype=np.float64)
    c = np.asarray(coefficients, dtype=np.float64)
    y = np.full_like(x, c[-1])
    for ck in c[-2::-1]:
        y = y * x + ck
    return np.clip(y, 0.0, 1.0)


def lookup_table_grid(rendered_x255) -> tuple[np.ndarray, np.ndarray]:
    """The (linear, rendered) nodes of a response table sampled at linear = 0, 1/N, ..., 1.

    Args:
        rendered_x255: (N + 1,) rendered values times 255 at evenly spaced linear values
            (the A7R3 table has N + 1 = 2,551 nodes, linear x 255 = 0.0, 0.1, ..., 255.0).

    Returns:
        ``(linear_nodes, rendered_nodes)``, both in [0, 1].
    """
    rendered = np.asarray(rendered_x255, dtype=np.float64) / 255.0
    if rendered.ndim != 1 or rendered.size < 2 or np.any(np.diff(rendered) <= 0):
        raise ValueError("a response lookup table must be 1-D, >= 2 nodes, strictly increasing")
    return np.linspace(0.0, 1.0, rendered.size), rendered


def lookup_crf(linear, rendered_x255) -> np.ndarray:
    """Camera response by piecewise-linear interpolation of a table, clipped to [0, 1]."""
    nodes, rendered = lookup_table_grid(rendered_x255)
    x = np.asarray(linear, dtype=np.float64)
    return np.clip(np.interp(x, nodes, rendered), 0.0, 1.0)


def resample_lookup_table(rendered_x255, size: int) -> np.ndarray:
    """A response table resampled to ``size`` evenly spaced linear nodes by linear interpolation.

    Node ``i`` lies at linear ``i / (size - 1)`` (``np.linspace(0, 1, size)``) and takes the
    value of the table's own piecewise-linear curve there (``np.interp`` on the table's nodes,
    as :func:`lookup_crf` before its clip). Sampling a strictly increasing piecewise-linear
    curve at strictly increasing points keeps the new table strictly increasing, so it has an
    inverse too, and both end nodes keep the table's end values.

    Args:
        rendered_x255: (N + 1,) rendered values times 255 at linear 0, 1/N, ..., 1.
        size: nodes of the new table, an integer >= 2.

    Returns:
        float64 array ``(size,)``, rendered values times 255.
    """
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 2:
        raise ValueError(f"a response table needs an integer size >= 2 (nodes); got {size!r}")
    nodes, rendered = lookup_table_grid(rendered_x255)
    return np.interp(np.linspace(0.0, 1.0, int(size)), nodes, rendered) * 255.0


@functools.cache
def a7r3_lookup_table(size: int = 0) -> np.ndarray:
    """The A7R3 response table that ``output.crf = "a7r3-lut"`` re-tones with, x 255.

    ``size`` 0 is the authors' table itself (2,551 nodes, RSBlur ``lookup_table.mat``);
    another size (``output.crf_table_size``, an accuracy knob) is that table resampled by
    :func:`resample_lookup_table`. It is resampled from the authors' table, not from the
    degree-7 polynomial, so that every size approximates the one curve "a7r3-lut" names and
    the error against size 0 is the table's resolution alone: the polynomial differs from the
    table by up to 0.0071 and dips near linear 0.862, so its samples would not be monotone.

    Args:
        size: 0, or the number of nodes (>= 2).

    Returns:
        Read-only float64 array of rendered values times 255 at linear ``i / (n - 1)``.
    """
    from gpu_blur.constants import A7R3_CRF_TABLE_X255

    if isinstance(size, (int, np.integer)) and not isinstance(size, bool) and size == 0:
        return A7R3_CRF_TABLE_X255
    table = resample_lookup_table(A7R3_CRF_TABLE_X255, size)
    table.setflags(write=False)
    return table


def inverse_lookup_crf(encoded, rendered_x255) -> np.ndarray:
    """Inverse camera response from the same table: monotone because the table is."""
    nodes, rendered = lookup_table_grid(rendered_x255)
    x = np.asarray(encoded, dtype=np.float64)
    return np.clip(np.interp(x, rendered, nodes), 0.0, 1.0)


#: The curve each re-toning ``output.crf`` evaluates: an Eq. 6 polynomial or a lookup table.
RETONE_CURVES = {"a7r3": "polynomial", "camera": "polynomial", "a7r3-lut": "lookup"}


def retone_polynomial(crf: str, coefficients=None) -> np.ndarray:
    """The polynomial a polynomial ``crf`` re-tones with, c_0 ... c_K in ascending powers.

    Args:
        crf: ``"a7r3"`` (the A7R3 fit, :data:`gpu_blur.constants.A7R3_CRF_POLYNOMIAL`) or
            ``"camera"`` (a calibrated camera's fitted response).
        coefficients: ``"camera"`` only, and required there: the camera's fitted response
            (:attr:`gpu_blur.cameras.Camera.response`).

    Returns:
        float64 coefficients, (K + 1,).
    """
    from gpu_blur.constants import A7R3_CRF_POLYNOMIAL

    if crf == "camera":
        if coefficients is None:
            raise ValueError("crf 'camera' needs the camera's fitted response: pass its "
                             "coefficients (c_0 ... c_K, ascending powers)")
        c = np.asarray(coefficients, dtype=np.float64)
        if c.ndim != 1 or c.size < 2 or not np.all(np.isfinite(c)):
            raise ValueError(f"crf 'camera': coefficients must be >= 2 finite numbers in a 1-D "
                             f"array, got {coefficients!r}")
        return c
    if coefficients is not None:
        raise ValueError(f"coefficients are for crf 'camera'; crf {crf!r} has its own curve "
                         "(pass coefficients=None)")
    if crf == "a7r3":
        return A7R3_CRF_POLYNOMIAL
    raise ValueError(f"crf {crf!r} is not a polynomial; polynomial crfs: "
                     f"{', '.join(k for k, v in RETONE_CURVES.items() if v == 'polynomial')}")


def retone(encoded, crf: str, table_size: int = 0, coefficients=None) -> np.ndarray:
    """Re-tone an sRGB image with a camera response: ``crf(srgb_to_linear(x))``.

    The RSBlur PyTorch pipeline does this to both the synthetic input and its ground truth with
    the A7R3 response, so that they look like RealBlur-J's camera JPEGs (pipeline note, Sec. 3
    step 18); ``"camera"`` does the same with a calibrated camera's fitted response.

    Args:
        encoded: sRGB image in [0, 1]; any shape.
        crf: ``"a7r3"`` (the A7R3 polynomial), ``"a7r3-lut"`` (its lookup table) or
            ``"camera"`` (the polynomial ``coefficients``); see :data:`RETONE_CURVES`.
        table_size: ``"a7r3-lut"`` only: 0 for the authors' 2,551-node table, else the nodes
            of :func:`a7r3_lookup_table` (``output.crf_table_size``).
        coefficients: ``"camera"`` only, and required there: c_0 ... c_K in ascending powers
            (:attr:`gpu_blur.cameras.Camera.response`).

    Returns:
        Re-toned values in [0, 1], float64, same shape.
    """
    curve = RETONE_CURVES.get(crf)
    if curve is None:
        raise ValueError(f"crf must be one of {', '.join(map(repr, RETONE_CURVES))}, "
                         f"got {crf!r}")
    if curve == "polynomial":
        if table_size != 0:
            raise ValueError(f"table_size = {table_size!r} needs crf 'a7r3-lut'; the {crf!r} "
                             "polynomial has no table (use table_size 0)")
        return polynomial_crf(srgb_to_linear(encoded), retone_polynomial(crf, coefficients))
    if coefficients is not None:
        raise ValueError(f"coefficients are for crf 'camera'; crf {crf!r} is a lookup table "
                         "(pass coefficients=None)")
    return lookup_crf(srgb_to_linear(encoded), a7r3_lookup_table(table_size))
