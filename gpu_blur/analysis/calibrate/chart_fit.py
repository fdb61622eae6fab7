"""Chart fits (RSBlur supplementary Eq. 1-4): white balance, brightness, colour correction.

Also the photometric alignment of two cameras' corrected colours. Each fit is a linear least
squares; a fit refuses patch colours that are too close to rank-deficient.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from gpu_blur.analysis.calibrate.chart import ChartReference, load_chart_reference
from gpu_blur.reference.color import camera_to_linear_matrix, linear_to_xyz

__all__ = ["ChartFit", "MAX_CHART_CONDITION", "MIN_PATCHES", "condition_number", "fit_brightness",
           "fit_chart", "fit_color_correction", "fit_photometric_alignment", "white_balance_gains"]

#: T (9 unknowns) and alpha (1) from 3 equations per patch need at least 4 patches.
MIN_PATCHES = 4
#: Largest condition number (ratio of the largest to the smallest singular value) of an N x 3
#: matrix of patch colours that a 3 x 3 least-squares fit accepts. The ColorChecker's own XYZ
#: measure 13.3 (D50) and 13.9 (D65); above 1e3 the patches' colours nearly lie in a plane
#: (a grey or one-channel image, a swapped file) and T would amplify measurement noise
#: by as much.
MAX_CHART_CONDITION = 1e3


def _patch_array(values, what: str, rows: int | None = None) -> np.ndarray:
    """An (N, 3) finite float64 array, or a ValueError naming ``what``."""
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what}: expected N x 3 patch values, got shape {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        i, c = np.argwhere(bad)[0]
        raise ValueError(f"{what}: patch {i + 1} channel {'RGB'[c]} is {a[i, c]}; every value "
                         "must be finite")
    if rows is not None and a.shape[0] != rows:
        raise ValueError(f"{what}: {a.shape[0]} patches, expected {rows} (one per chart patch, "
                         "in chart order)")
    return a


def condition_number(matrix) -> float:
    """Ratio of the largest to the smallest singular value (inf when rank-deficient)."""
    return float(np.linalg.cond(np.asarray(matrix, dtype=np.float64)))


def _fit_3x3(source, target, what: str) -> tuple[np.ndarray, float]:
    """The 3 x 3 M minimising ``sum_i |target_i - M source_i|^2``, and cond(source).

    Raises:
        ValueError: naming ``what`` and the condition number when ``source`` is too close
            to rank-deficient (:data:`MAX_CHART_CONDITION`).
    """
    cond = condition_number(source)
    if cond > MAX_CHART_CONDITION:
        raise ValueError(
            f"{what}: the patch colours are (nearly) rank-deficient: condition number "
            f"{cond:.3g} > {MAX_CHART_CONDITION:g}; the patches must span three independent "
            "colours (check the file is the chart's colour patches, in chart order, "
            "not a grey or single-channel image)")
    solution, *_ = np.linalg.lstsq(source, target, rcond=None)
    return solution.T, cond


def white_balance_gains(camera_rgb, neutral, what: str = "chart patches") -> np.ndarray:
    """White-balance gains from the neutral patches, ``g_c = P_n(G) / P_n(c)`` (Eq. 1).

    Args:
        camera_rgb: (N, 3) camera RGB per patch, before white balance.
        neutral: (N,) bool, the neutral patches.
        what: name of the data for error messages (e.g. the file).

    Returns:
        (3,) float64 gains (R, G = 1, B).

    Raises:
        ValueError: when no patch is neutral or a channel's neutral mean is not positive.
    """
    rgb = _patch_array(camera_rgb, what)
    neutral = np.asarray(neutral, dtype=bool)
    if neutral.shape != (rgb.shape[0],):
        raise ValueError(f"{what}: {neutral.shape[0] if neutral.ndim else 0} neutral flags for "
                         f"{rgb.shape[0]} patches")
    if not neutral.any():
        raise ValueError(f"{what}: no patch is marked neutral; white balance (Eq. 1) needs the "
                         'grey patches: mark them "neutral": true in the chart reference')
    means = rgb[neutral].mean(axis=0)
    if np.any(means <= 0):
        raise ValueError(f"{what}: the neutral patches' mean is {means.tolist()} (R, G, B); "
                         "every channel must be > 0: subtract the black level only, and check "
                         "the patches are in chart order")
    return means[1] / means


def fit_brightness(reference_xyz, measured_xyz, what: str = "chart patches") -> float:
    """Alpha minimising ``sum_i |ref_i - alpha meas_i|^2`` (Eq. 2, first step).

    Raises:
        ValueError: when alpha is not positive (measured values of the wrong sign or all 0).
    """
    ref = _patch_array(reference_xyz, f"{what} (reference)")
    meas = _patch_array(measured_xyz, what, ref.shape[0])
    power = float(np.sum(meas * meas))
    alpha = float(np.sum(ref * meas)) / power if power > 0 else math.nan
    if not alpha > 0:
        raise ValueError(f"{what}: brightness alpha = {alpha:.6g}; it must be > 0 (are the "
                         "measured values all zero or negative?)")
    return alpha


def fit_color_correction(reference_xyz, measured_xyz, alpha: float,
                         what: str = "chart patches") -> np.ndarray:
    """T minimising ``sum_i |ref_i - alpha T meas_i|^2`` with alpha fixed (Eq. 2).

    Args:
        reference_xyz: (N, 3) the chart's XYZ (D65).
        measured_xyz: (N, 3) the camera's XYZ after white balance, ``M_Lin2XYZ (g * rgb)``.
        alpha: the brightness from :func:`fit_brightness`.
        what: name of the data for error messages.

    Returns:
        (3, 3) float64 T, column convention.

    Raises:
        ValueError: with the condition number when the measured colours are rank-deficient.
    """
    ref = _patch_array(reference_xyz, f"{what} (reference)")
    meas = _patch_array(measured_xyz, what, ref.shape[0])
    return _fit_3x3(alpha * meas, ref, what)[0]


def fit_photometric_alignment(xyz_c1, xyz_c2, what: str = "alignment patches") -> np.ndarray:
    """T_p minimising ``sum_i |C1_i - T_p C2_i|^2`` (Eq. 4).

    Args:
        xyz_c1: (N, 3) the patches' XYZ from camera C1 after its colour correction.
        xyz_c2: (N, 3) the same patches from camera C2.
        what: name of the data for error messages.

    Returns:
        (3, 3) float64 T_p mapping C2's colours onto C1's.

    Raises:
        ValueError: with the condition number when C2's colours are rank-deficient.
    """
    c1 = _patch_array(xyz_c1, f"{what} (C1)")
    c2 = _patch_array(xyz_c2, f"{what} (C2)", c1.shape[0])
    return _fit_3x3(c2, c1, what)[0]


@dataclasses.dataclass(frozen=True)
class ChartFit:
    """What a chart fit found.

    Attributes:
        gains: (3,) white-balance gains R, G = 1, B (Eq. 1).
        alpha: brightness of the chart photo (Eq. 2).
        ccm_xyz: (3, 3) colour correction T (Eq. 2), XYZ D65, column convention.
        camera_to_linear: (3, 3) the pipeline's Cam2Lin, ``M_XYZ2Lin T M_Lin2XYZ`` (Eq. 3).
        measured_xyz: (N, 3) the patches' XYZ after white balance, before T.
        residual_xyz: (N, 3) ``ref - alpha T meas`` per patch.
        condition_patches: condition number of ``measured_xyz``.
        condition_ccm: condition number of T.
    """

    gains: np.ndarray
    alpha: float
    ccm_xyz: np.ndarray
    camera_to_linear: np.ndarray
    measured_xyz: np.ndarray
    residual_xyz: np.ndarray
    condition_patches: float
    condition_ccm: float

    @property
    def residual_rms(self) -> float:
        """Root mean square of the XYZ residuals over patches and components."""
        return float(np.sqrt(np.mean(self.residual_xyz**2)))


def fit_chart(camera_rgb, reference: ChartReference | None = None,
              what: str = "chart patches") -> ChartFit:
    """White balance, brightness and colour correction from a chart's camera RGB (Eq. 1-3).

    Args:
        camera_rgb: (N, 3) camera RGB per patch before white balance, in the reference's
            patch order.
        reference: the chart (default: the built-in ColorChecker 24).
        what: name of the data for error messages (e.g. the file).

    Raises:
        ValueError: naming ``what`` for a patch count that does not match the chart, fewer
            than :data:`MIN_PATCHES` patches, a chart whose patches are all neutral or none,
            NaN or infinite values, and rank-deficient or ill-conditioned colours (with the
            condition number).
    """
    reference = reference or load_chart_reference()
    count = len(reference.patch_names)
    if count < MIN_PATCHES:
        raise ValueError(f"chart {reference.name!r} has {count} patches; a colour correction "
                         f"needs at least {MIN_PATCHES}")
    if np.all(reference.neutral):
        raise ValueError(f"chart {reference.name!r}: all {count} patches are neutral; the "
                         "colour correction T needs coloured patches too")
    rgb = _patch_array(camera_rgb, what)
    if rgb.shape[0] != count:
        few = "too few" if rgb.shape[0] < count else "too many"
        raise ValueError(f"{what}: {rgb.shape[0]} patches, {few}: the chart {reference.name!r} "
                         f"has {count}; give one row per patch, in chart order")
    gains = white_balance_gains(rgb, reference.neutral, what)
    measured = linear_to_xyz(rgb * gains)
    alpha = fit_brightness(reference.xyz, measured, what)
    ccm, cond = _fit_3x3(alpha * measured, reference.xyz, what)
    try:
        cam_to_lin = camera_to_linear_matrix(ccm=ccm)
    except ValueError as e:
        raise ValueError(f"{what}: {e}") from None
    residual = reference.xyz - alpha * measured @ ccm.T
    return ChartFit(gains, alpha, ccm, cam_to_lin, measured, residual, cond,
                    float(np.linalg.cond(ccm)))
