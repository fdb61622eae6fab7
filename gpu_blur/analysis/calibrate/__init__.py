"""Colour-chart calibration: white balance, colour correction, photometric alignment, CRF.

Fits a camera file for the pipeline (:func:`gpu_blur.cameras.load_camera`) from a photo of a
24-patch colour chart, as the RSBlur supplementary material describes (Rim et al., ECCV 2022,
sections 4, 5 and 7):

* white-balance gains from the neutral patches, ``g_c = P_n(G) / P_n(c)`` (Eq. 1), where
  ``P_n(c)`` is the mean of channel c over the neutral patches;
* a brightness scalar alpha, then a 3 x 3 XYZ-space colour correction T, each by least squares
  (Eq. 2): ``XYZ_ref = alpha T XYZ_meas`` with ``XYZ_meas = M_Lin2XYZ (g * camera RGB)``. Alpha
  comes first (T = identity), T second with alpha fixed. alpha is the chart photo's exposure
  and is not part of the camera; the pipeline applies ``Cam2Lin = M_XYZ2Lin T M_Lin2XYZ``
  (Eq. 3), which is the camera file's ``color.ccm_xyz = T``;
* photometric alignment between two cameras, ``XYZ_C1 = T_p XYZ_C2`` (Eq. 4), by least squares
  on both cameras' colour-corrected patches;
* a camera response of order K, ``I_srgb = sum_k c_k I_lin^k`` (Eq. 6), by least squares on
  pairs of linear and rendered values, constrained to increase on [0, 1], and its inverse as a
  lookup table.

The chart's reference colours are in ``gpu_blur/data/colorchecker24.json``: X-Rite's CIE
L*a*b* (D50) for the ColorChecker Classic made after November 2014, converted here to XYZ D50
(CIE 1976 formulas) and adapted to D65 with the Bradford matrix ``constants.D50_TO_D65``, so
T works in the package's XYZ D65 / linear sRGB.

Input files
-----------
Patch values (``--chart``, ``--align-to``, ``--crf-linear``, ``--crf-rendered``): one RGB
triple per patch, in chart order (ColorChecker 24: row by row from dark skin, top left, to
black, bottom right), linear in light. For the chart fit these are camera RGB before white
balance: RAW values with the black level subtracted, averaged over each patch (e.g. from
``dcraw -4 -T -o 0 -r 1 1 1 1 photo.raw``: linear, raw colour, unit gains). Any scale works
(alpha absorbs it). Either

* CSV: a header line naming the columns ``r,g,b`` (any case, any order; other columns such
  as ``patch`` are labels and ignored), then one line per patch; lines starting with ``#``
  and blank lines are skipped::

      patch,r,g,b
      dark skin,0.0431,0.0367,0.0189
      ...

* JSON: ``{"rgb": [[r, g, b], ...]}`` or just ``[[r, g, b], ...]``;
* or an image (``.png``, ``.tif``, ``.tiff``, ``.jpg``; 8 or 16 bits, or float TIFF): each
  patch is the mean of its box from ``--boxes``, codes divided by 255 or 65535. The values
  are used as they are, so give a linear image (a RAW developed without white balance,
  colour conversion or tone curve) for ``--chart``, and the camera's own JPEG for
  ``--crf-rendered``.

Patch boxes (``--boxes``): ``x y w h`` in pixels per patch, in chart order (x the column of
the left edge, y the row of the top edge, w and h >= 1); keep them inside the patches, away
from their borders. CSV with the header ``x,y,w,h``, or JSON ``{"boxes": [[x, y, w, h],
...]}`` or ``[[x, y, w, h], ...]``.

Response pairs (``--crf-linear`` with ``--crf-rendered``, repeatable for several exposures):
row i of the linear file (linear sRGB after the camera's white balance and colour correction,
e.g. from the RAW) goes with row i of the rendered file (the camera's JPEG of the same shot);
every channel is one pair. Rendered values within half an 8-bit code of 0 or 1 are left out
(clipped values say nothing about the curve), as are linear values outside [0, 1].

Output
------
A camera file (TOML, or JSON when the name ends in ``.json``) that a scene names with
``camera.name = "my_camera.toml"``: ``[color] ccm_xyz`` (T), ``[white_balance]`` (the fixed
gains), ``[noise]`` (given, else RSBlur's levels), ``[calibration]`` (alpha, residuals,
condition numbers, inputs; ``load_camera`` does not read it) and, with a response fit,
``[response]`` (``polynomial``: c_0 ... c_K ascending; ``inverse_linear``: the linear value at
rendered = i / (n - 1)), which ``gpu_blur.analysis.calibrate.read_response`` reads back.
To synthesize with the fitted response, set ``output.crf = "camera"`` in the scene: output
and sharp reference are re-toned as ``polynomial(srgb_to_linear(x))`` (``load_camera`` reads
the polynomial into ``Camera.response``), so the pairs take this camera's tone curve.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gpu_blur.analysis.calibrate.camera_file import camera_file_text, write_camera_file
from gpu_blur.analysis.calibrate.chart import (
    COLORCHECKER24,
    ChartReference,
    lab_to_xyz,
    load_chart_reference,
)
from gpu_blur.analysis.calibrate.chart_fit import (
    MAX_CHART_CONDITION,
    MIN_PATCHES,
    ChartFit,
    fit_brightness,
    fit_chart,
    fit_color_correction,
    fit_photometric_alignment,
    white_balance_gains,
)
from gpu_blur.analysis.calibrate.patches import (
    read_patch_boxes,
    read_patch_values,
    read_patches,
    sample_patches,
)
from gpu_blur.analysis.calibrate.response import (
    DEFAULT_CRF_ORDER,
    INVERSE_TABLE_NODES,
    MAX_CRF_ORDER,
    MONOTONE_SLOPE_TOL,
    ResponseFit,
    fit_response,
    inverse_response,
    read_response,
    response_inverse_table,
)
from gpu_blur.constants import rsblur_data
from gpu_blur.reference.color import camera_to_linear_matrix

__all__ = [
    "COLORCHECKER24", "DEFAULT_CRF_ORDER", "INVERSE_TABLE_NODES", "MAX_CHART_CONDITION",
    "MAX_CRF_ORDER", "MIN_PATCHES", "MONOTONE_SLOPE_TOL", "Calibration", "ChartFit",
    "ChartReference", "ResponseFit", "calibrate", "camera_file_text", "fit_brightness",
    "fit_chart", "fit_color_correction", "fit_photometric_alignment", "fit_response",
    "help_text", "inverse_response", "lab_to_xyz", "load_chart_reference", "read_patch_boxes",
    "read_patch_values", "read_patches", "read_response", "response_inverse_table",
    "sample_patches", "white_balance_gains", "write_camera_file",
]


def help_text() -> str:
    """The input and output formats of this module's docstring, for ``gpu-blur calibrate``."""
    text = __doc__[__doc__.index("Input files"):].replace("``", "")
    return text.replace("::\n", ":\n")


@dataclasses.dataclass(frozen=True)
class Calibration:
    """The result of :func:`calibrate`.

    Attributes:
        chart: the chart fit of the camera being calibrated.
        alignment: (3, 3) T_p onto the ``align_to`` camera (Eq. 4), or None.
        alignment_rms: XYZ root mean square residual of Eq. 4 (0 without alignment).
        response: the response fit, or None.
        camera: the camera file's contents (see :func:`write_camera_file`).
    """

    chart: ChartFit
    alignment: np.ndarray | None
    alignment_rms: float
    response: ResponseFit | None
    camera: dict

    def report(self) -> str:
        """Fitted values, residuals and condition numbers, for people."""
        fit = self.chart

        def matrix(m):
            return "\n".join("    [" + ", ".join(f"{v: .6f}" for v in row) + "]" for row in m)

        lines = [
            f"white balance gains (Eq. 1): R {fit.gains[0]:.6f}  G 1  B {fit.gains[2]:.6f}",
            f"brightness alpha (Eq. 2): {fit.alpha:.6g}",
            "colour correction T (Eq. 2, XYZ D65, out = T @ in):", matrix(fit.ccm_xyz),
            f"chart residual, XYZ: rms {fit.residual_rms:.3g}, max "
            f"{np.abs(fit.residual_xyz).max():.3g}",
            f"condition numbers: patches {fit.condition_patches:.3g} (limit "
            f"{MAX_CHART_CONDITION:g}), T {fit.condition_ccm:.3g}",
        ]
        if self.alignment is not None:
            lines += ["photometric alignment T_p (Eq. 4; written T = T_p @ T):",
                      matrix(self.alignment),
                      f"alignment residual, XYZ: rms {self.alignment_rms:.3g}"]
        if self.response is not None:
            r = self.response
            lines += [
                f"response (Eq. 6, order {r.coefficients.size - 1}): c = "
                + ", ".join(f"{v:.6g}" for v in r.coefficients),
                f"response residual: rms {r.residual_rms:.3g}, max {r.residual_max:.3g} over "
                f"{r.pairs} pairs ({r.left_out} clipped left out); condition number "
                f"{r.condition_number:.3g}; "
                + ("monotone constraint active" if r.constrained else "monotone as fitted")
                + f" (min slope {r.min_slope:.3g})",
            ]
        return "\n".join(lines)


def calibrate(chart, *, boxes=None, reference=None, name: str | None = None,
              crf_linear=(), crf_rendered=(), crf_order: int = DEFAULT_CRF_ORDER,
              align_to=None, shot_noise_k: float | None = None,
              read_noise_std: float | None = None) -> Calibration:
    """Calibrate a camera from chart files (what ``gpu-blur calibrate`` runs).

    Args:
        chart: patch values file or image (module docstring) of this camera's RAW chart.
        boxes: patch boxes file, for image inputs.
        reference: chart reference JSON (default: the built-in ColorChecker 24).
        name: the camera's name (default: none written, so the camera file's stem).
        crf_linear: linear patch files or images, one per exposure, for a response fit.
        crf_rendered: the matching rendered ones (camera JPEGs), same count and order.
        crf_order: response polynomial order K.
        align_to: another camera's RAW chart file of the same chart: T is replaced by
            ``T_p @ T`` so this camera's colours match that one's (Eq. 4).
        shot_noise_k: Poisson gain K for ``[noise]`` (default: RSBlur's estimate).
        read_noise_std: read-noise std for ``[noise]`` (default: RSBlur's estimate).

    Raises:
        ValueError: naming the file and the problem, as the readers and fits above.
    """
    ref = load_chart_reference(reference)
    fit = fit_chart(read_patches(chart, boxes), ref, str(chart))
    ccm, alignment, alignment_rms = fit.ccm_xyz, None, 0.0
    if align_to is not None:
        other = fit_chart(read_patches(align_to, boxes), ref, str(align_to))
        corrected_c1 = other.measured_xyz @ other.ccm_xyz.T
        corrected_c2 = fit.measured_xyz @ fit.ccm_xyz.T
        alignment = fit_photometric_alignment(corrected_c1, corrected_c2,
                                              f"{align_to} and {chart}")
        alignment_rms = float(np.sqrt(np.mean((corrected_c1 - corrected_c2 @ alignment.T)**2)))
        ccm = alignment @ fit.ccm_xyz
        try:
            camera_to_linear_matrix(ccm=ccm)
        except ValueError as e:
            raise ValueError(f"{chart} aligned to {align_to}: {e}") from None
    response = None
    if len(crf_linear) != len(crf_rendered):
        raise ValueError(f"--crf-linear given {len(crf_linear)} times but --crf-rendered "
                         f"{len(crf_rendered)} times; give one rendered file per linear one")
    if crf_linear:
        linear, rendered = [], []
        for lin_path, out_path in zip(crf_linear, crf_rendered, strict=True):
            lin = read_patches(lin_path, boxes)
            out = read_patches(out_path, boxes)
            if lin.shape != out.shape:
                raise ValueError(f"{lin_path} has {lin.shape[0]} patches but {out_path} has "
                                 f"{out.shape[0]}; give the same patches in both")
            linear.append(lin)
            rendered.append(out)
        names = ", ".join(f"{a} / {b}" for a, b in zip(crf_linear, crf_rendered, strict=True))
        response = fit_response(np.concatenate(linear), np.concatenate(rendered), crf_order,
                                f"response pairs {names}")
    noise = rsblur_data()["rsblur"]
    shot = noise["shot_noise_k"] if shot_noise_k is None else shot_noise_k
    read = noise["read_noise_std"] if read_noise_std is None else read_noise_std
    noise_source = ("given" if shot_noise_k is not None and read_noise_std is not None
                    else f"not measured: RSBlur's levels where not given ({noise['noise_source']})")
    camera = {
        **({"name": name} if name else {}),
        "source": (f"gpu-blur calibrate: chart {chart} against {ref.name} ({ref.source}); "
                   f"WB gains Eq. 1, T Eq. 2 (Rim et al. ECCV 2022 supplementary)"
                   + (f", aligned to {align_to} (Eq. 4)" if align_to is not None else "")
                   + f"; noise {noise_source}"),
        "color": {"ccm_xyz": ccm.tolist(), "adapt_d50": False},
        "white_balance": {"red": float(fit.gains[0]), "blue": float(fit.gains[2])},
        "noise": {"shot_noise_k": float(shot), "read_noise_std": float(read)},
        "calibration": {
            "chart": str(chart), "reference": ref.name, "alpha": fit.alpha,
            "residual_rms_xyz": fit.residual_rms,
            "residual_max_xyz": float(np.abs(fit.residual_xyz).max()),
            "condition_patches": fit.condition_patches, "condition_ccm": fit.condition_ccm,
        },
    }
    if alignment is not None:
        camera["calibration"].update({"align_to": str(align_to),
                                      "alignment": alignment.tolist(),
                                      "alignment_rms_xyz": alignment_rms,
                                      "ccm_before_alignment": fit.ccm_xyz.tolist()})
    if response is not None:
        camera["response"] = {
            "source": f"Eq. 6 least squares, increasing on [0, 1], from {names}",
            "polynomial": response.coefficients.tolist(),
            "inverse_linear": response_inverse_table(response.coefficients).tolist(),
            "residual_rms": response.residual_rms,
            "condition_number": response.condition_number,
        }
    return Calibration(fit, alignment, alignment_rms, response, camera)
