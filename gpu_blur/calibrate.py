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
rendered = i / (n - 1)), which ``gpu_blur.calibrate.read_response`` reads back. To synthesize
with the fitted response, set ``output.crf = "camera"`` in the scene: output and sharp
reference are re-toned as ``polynomial(srgb_to_linear(x))`` (``load_camera`` reads the
polynomial into ``Camera.response``), so the pairs take this camera's tone curve.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
from importlib import resources
from pathlib import Path

import numpy as np

from gpu_blur.constants import D50_TO_D65, rsblur_data
from gpu_blur.reference.color import camera_to_linear_matrix, linear_to_xyz
from gpu_blur.reference.transfer import polynomial_crf

#: Built-in chart reference (gpu_blur/data).
COLORCHECKER24 = "colorchecker24.json"
#: T (9 unknowns) and alpha (1) from 3 equations per patch need at least 4 patches.
MIN_PATCHES = 4
#: Largest condition number (ratio of the largest to the smallest singular value) of an N x 3
#: matrix of patch colours that a 3 x 3 least-squares fit accepts. The ColorChecker's own XYZ
#: measure 13.3 (D50) and 13.9 (D65); above 1e3 the patches' colours nearly lie in a plane
#: (a grey or one-channel image, a swapped file) and T would amplify measurement noise
#: by as much.
MAX_CHART_CONDITION = 1e3
#: Default order K of the response polynomial (Rim et al. fit K = 7, supplementary Sec. 7).
DEFAULT_CRF_ORDER = 7
#: Highest order accepted: the ascending-power coefficients of higher orders cancel so much
#: that float64 evaluation loses digits.
MAX_CRF_ORDER = 12
#: Largest condition number of the response fit's Bernstein design matrix. Samples spread
#: over [0, 1] measure about 800 at K = 7; samples confined to [0, 0.5] measure 4e5, where
#: the upper half of the curve would be extrapolated.
MAX_CRF_CONDITION = 1e5
#: Rendered values within this distance of 0 or 1 may be clipped and are left out of the
#: response fit (half an 8-bit code).
CRF_CLIP_MARGIN = 0.5 / 255
#: The fitted response's slope may dip this far below 0 (rendered per linear unit): over at
#: most the whole unit interval that lowers it by less than 1e-9, far below a 16-bit step.
MONOTONE_SLOPE_TOL = 1e-9
#: Points of [0, 1] where the constrained response fit asks for a slope >= 0 to begin with;
#: the worst point in between is then added until the slope holds everywhere.
MONOTONE_GRID = 1025
#: Rounds of adding the worst point before giving up.
MONOTONE_ROUNDS = 20
#: Nodes of the inverse response table (rendered = 0, 1/1024, ..., 1).
INVERSE_TABLE_NODES = 1025
_IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")


def help_text() -> str:
    """The input and output formats of this module's docstring, for ``gpu-blur calibrate``."""
    text = __doc__[__doc__.index("Input files"):].replace("``", "")
    return text.replace("::\n", ":\n")


# ---- the chart's reference colours ----

@dataclasses.dataclass(frozen=True)
class ChartReference:
    """A chart's reference colours in the package's XYZ (D65, Y = 1 for a perfect white).

    Attributes:
        name: the chart's name.
        source: where the numbers come from.
        patch_names: N names, in chart order.
        xyz: (N, 3) float64 reference XYZ under D65.
        neutral: (N,) bool, the neutral (grey) patches that white balance uses.
    """

    name: str
    source: str
    patch_names: tuple[str, ...]
    xyz: np.ndarray
    neutral: np.ndarray


def lab_to_xyz(lab, white_xyz) -> np.ndarray:
    """CIE 1976 L*a*b* -> XYZ relative to a white (CIE 15:2004, Sec. 8.2.1, inverse form).

    Args:
        lab: (..., 3) L* in [0, 100], a*, b*.
        white_xyz: (3,) the white's XYZ (Y = 1 gives Y in [0, 1]).

    Returns:
        (..., 3) float64 XYZ.
    """
    lab = np.asarray(lab, dtype=np.float64)
    fy = (lab[..., 0] + 16.0) / 116.0
    f = np.stack([fy + lab[..., 1] / 500.0, fy, fy - lab[..., 2] / 200.0], axis=-1)
    delta = 6.0 / 29.0
    linear_part = 3.0 * delta**2 * (f - 4.0 / 29.0)
    return np.where(f > delta, f**3, linear_part) * np.asarray(white_xyz, dtype=np.float64)


def load_chart_reference(path: str | Path | None = None) -> ChartReference:
    """Load a chart reference: the built-in ColorChecker 24, or a file of the same format.

    The format is that of ``gpu_blur/data/colorchecker24.json``: ``name``, ``source``,
    ``illuminant`` (``"D50"``, adapted to D65 by Bradford, or ``"D65"``), and ``patches``, a
    list in chart order of ``{"name": ..., "lab": [L, a, b]}`` (with a top-level
    ``lab_white_xyz``) or ``{"name": ..., "xyz": [X, Y, Z]}`` (Y = 1 for a perfect white),
    each with ``"neutral": true`` for the grey patches.

    Raises:
        ValueError: naming the file and the bad key.
    """
    if path is None:
        where = f"gpu_blur/data/{COLORCHECKER24}"
        text = resources.files("gpu_blur").joinpath("data", COLORCHECKER24).read_text()
    else:
        where = str(path)
        try:
            text = Path(path).read_text()
        except OSError as e:
            raise ValueError(f"chart reference {where}: cannot read it ({e.strerror})") from None
    try:
        spec = json.loads(text)
    except ValueError as e:
        raise ValueError(f"chart reference {where}: not valid JSON: {e}") from None

    def fail(key, problem):
        raise ValueError(f"chart reference {where}: {key}: {problem}; see "
                         f"gpu_blur/data/{COLORCHECKER24} for the format")

    patches = spec.get("patches") if isinstance(spec, dict) else None
    if not isinstance(patches, list) or not patches:
        fail("patches", "expected a list of {name, lab or xyz, neutral}")
    illuminant = spec.get("illuminant")
    if illuminant not in ("D50", "D65"):
        fail("illuminant", f"{illuminant!r} is not 'D50' or 'D65'")
    values = []
    for i, p in enumerate(patches):
        kind = [k for k in ("lab", "xyz") if isinstance(p, dict) and k in p]
        if len(kind) != 1:
            fail(f"patches[{i}]", "needs exactly one of 'lab' or 'xyz'")
        v = _numbers(p[kind[0]], 3)
        if v is None:
            fail(f"patches[{i}].{kind[0]}", f"{p[kind[0]]!r} is not 3 finite numbers")
        if kind[0] == "lab":
            white = _numbers(spec.get("lab_white_xyz"), 3)
            if white is None:
                fail("lab_white_xyz", "L*a*b* patches need the white's XYZ (3 numbers)")
            v = lab_to_xyz(v, white)
        values.append(v)
    xyz = np.array(values)
    if illuminant == "D50":
        xyz = xyz @ D50_TO_D65.T
    neutral = np.array([bool(p.get("neutral", False)) for p in patches])
    names = tuple(str(p.get("name", f"patch {i + 1}")) for i, p in enumerate(patches))
    for a in (xyz, neutral):
        a.setflags(write=False)
    return ChartReference(str(spec.get("name", where)), str(spec.get("source", where)), names,
                          xyz, neutral)


def _numbers(value, count: int) -> np.ndarray | None:
    """``value`` as ``count`` finite float64 numbers, or None."""
    if not (isinstance(value, list) and len(value) == count
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        return None
    out = np.array(value, dtype=np.float64)
    return out if np.all(np.isfinite(out)) else None


# ---- reading patch values ----

def _read_table(path: Path, columns: tuple[str, ...], json_key: str) -> tuple[np.ndarray, list]:
    """Rows of the named columns from a CSV (header) or JSON file, with their line numbers.

    Returns:
        ``(values, where)``: (N, len(columns)) float64 and N strings like ``"line 4"``.
    """
    try:
        text = path.read_text()
    except OSError as e:
        raise ValueError(f"{path}: cannot read it ({e.strerror})") from None
    want = ", ".join(columns)
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as e:
            raise ValueError(f"{path}: not valid JSON: {e}") from None
        rows = data.get(json_key) if isinstance(data, dict) else data
        if not isinstance(rows, list):
            raise ValueError(f'{path}: expected {{"{json_key}": [[{want}], ...]}} or '
                             f"[[{want}], ...]")
        where = [f"entry {i}" for i in range(len(rows))]
        values = []
        for i, row in enumerate(rows):
            if not (isinstance(row, list) and len(row) == len(columns)):
                raise ValueError(f"{path}: {where[i]} is {row!r}; expected [{want}]")
            values.append(_finite_row(path, where[i], columns, row))
        return np.array(values, dtype=np.float64).reshape(-1, len(columns)), where
    if path.suffix.lower() != ".csv":
        raise ValueError(f"{path}: expected a .csv or .json file (or an image: "
                         f"{', '.join(_IMAGE_SUFFIXES)})")
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path}: no header line; expected one naming the columns {want}")
    header_line, header = lines[0]
    names = [c.strip().lower() for c in next(csv.reader([header]))]
    missing = [c for c in columns if c not in names]
    if missing:
        raise ValueError(f"{path} line {header_line}: the header has columns {names}; "
                         f"expected a header naming {want} (missing {', '.join(missing)})")
    index = [names.index(c) for c in columns]
    values, where = [], []
    for number, line in lines[1:]:
        fields = next(csv.reader([line]))
        if len(fields) != len(names):
            raise ValueError(f"{path} line {number}: {len(fields)} fields, the header has "
                             f"{len(names)} ({', '.join(names)})")
        where.append(f"line {number}")
        values.append(_finite_row(path, where[-1], columns, [fields[i] for i in index]))
    return np.array(values, dtype=np.float64).reshape(-1, len(columns)), where


def _finite_row(path, where, columns, row) -> list[float]:
    out = []
    for name, v in zip(columns, row, strict=True):
        try:
            x = float(v) if not isinstance(v, bool) else math.nan
        except (TypeError, ValueError):
            x = math.nan
        if not math.isfinite(x):
            raise ValueError(f"{path} {where}: {name} = {v!r} is not a finite number")
        out.append(x)
    return out


def read_patch_values(path: str | Path) -> np.ndarray:
    """Patch RGB values from a CSV or JSON file (formats in the module docstring).

    Returns:
        (N, 3) float64, one row per patch in file order.

    Raises:
        ValueError: naming the file and line (CSV) or entry (JSON) for a missing column,
            a wrong field count, or a value that is not a finite number.
    """
    values, _ = _read_table(Path(path), ("r", "g", "b"), "rgb")
    return values


def read_patch_boxes(path: str | Path) -> np.ndarray:
    """Patch boxes ``x y w h`` (pixels) from a CSV or JSON file (module docstring).

    Returns:
        (N, 4) int64.

    Raises:
        ValueError: naming the file and line or entry for bad columns, values that are not
            whole numbers, negative positions or empty boxes.
    """
    path = Path(path)
    values, where = _read_table(path, ("x", "y", "w", "h"), "boxes")
    for v, w in zip(values, where, strict=True):
        if np.any(v != np.round(v)) or np.any(v[:2] < 0) or np.any(v[2:] < 1):
            raise ValueError(f"{path} {w}: box {v.tolist()} must be whole pixels with x, y "
                             ">= 0 and w, h >= 1")
    return values.astype(np.int64)


def sample_patches(image_path: str | Path, boxes) -> np.ndarray:
    """Mean RGB of each box of an image, in [0, 1] (codes / 255 or / 65535).

    Args:
        image_path: PNG, TIFF or JPEG; 8 or 16 bits per channel, or float TIFF in [0, 1].
        boxes: (N, 4) ``x, y, w, h`` in pixels.

    Returns:
        (N, 3) float64.

    Raises:
        ValueError: naming the image and the box that does not fit inside it.
    """
    from gpu_blur.imageio import read_image, to_unit

    image = to_unit(read_image(image_path), str(image_path))
    height, width = image.shape[:2]
    out = []
    for i, (x, y, w, h) in enumerate(np.asarray(boxes, dtype=np.int64)):
        if x < 0 or y < 0 or w < 1 or h < 1 or x + w > width or y + h > height:
            raise ValueError(f"{image_path}: box {i + 1} (x={x}, y={y}, w={w}, h={h}) does not "
                             f"lie inside the {width} x {height} image; check --boxes")
        out.append(image[y:y + h, x:x + w].reshape(-1, 3).mean(axis=0))
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def read_patches(path: str | Path, boxes: str | Path | None = None) -> np.ndarray:
    """Patch values from a CSV/JSON file, or sampled from an image at the boxes of a file.

    Returns:
        (N, 3) float64.

    Raises:
        ValueError: for an image without a boxes file, and as the readers above.
    """
    path = Path(path)
    if path.suffix.lower() in _IMAGE_SUFFIXES:
        if boxes is None:
            raise ValueError(f"{path} is an image: give the patch boxes too (--boxes FILE "
                             "with x,y,w,h per patch)")
        return sample_patches(path, read_patch_boxes(boxes))
    return read_patch_values(path)


# ---- fits ----

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


def _condition(matrix) -> float:
    """Ratio of the largest to the smallest singular value (inf when rank-deficient)."""
    s = np.linalg.svd(np.asarray(matrix, dtype=np.float64), compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else math.inf


def _fit_3x3(source, target, what: str) -> tuple[np.ndarray, float]:
    """The 3 x 3 M minimising ``sum_i |target_i - M source_i|^2``, and cond(source).

    Raises:
        ValueError: naming ``what`` and the condition number when ``source`` is too close
            to rank-deficient (:data:`MAX_CHART_CONDITION`).
    """
    cond = _condition(source)
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


# ---- camera response ----

def _bernstein(x, order: int) -> np.ndarray:
    """(len(x), order + 1) Bernstein basis ``C(K, k) x^k (1 - x)^(K - k)`` on [0, 1]."""
    x = np.asarray(x, dtype=np.float64)[:, None]
    k = np.arange(order + 1)
    binomial = np.array([math.comb(order, i) for i in k], dtype=np.float64)
    return binomial * x**k * (1.0 - x) ** (order - k)


def _slope_rows(x, order: int) -> np.ndarray:
    """Rows D with ``D @ b = p'(x)`` for a Bernstein polynomial with coefficients b.

    ``p'(x) = K sum_k (b_{k+1} - b_k) B_{k, K-1}(x)`` (the Bernstein derivative rule).
    """
    lower = _bernstein(x, order - 1) * order
    rows = np.zeros((lower.shape[0], order + 1))
    rows[:, 1:] += lower
    rows[:, :-1] -= lower
    return rows


def _bernstein_to_power(b) -> np.ndarray:
    """Ascending power coefficients of ``sum_k b_k C(K, k) x^k (1 - x)^(K - k)``."""
    order = len(b) - 1
    c = np.zeros(order + 1)
    for k, bk in enumerate(b):
        for j in range(k, order + 1):
            c[j] += bk * math.comb(order, k) * math.comb(order - k, j - k) * (-1) ** (j - k)
    return c


def _min_slope(b) -> tuple[float, float]:
    """The smallest slope of a Bernstein polynomial on [0, 1], and where it is.

    The minimum of p' lies at 0, 1 or a root of p'' (found from p's power coefficients);
    a grid of :data:`MONOTONE_GRID` points backs up roots that come out slightly complex.
    """
    order = len(b) - 1
    c = _bernstein_to_power(b)
    second = c[2:] * np.arange(2, order + 1) * np.arange(1, order)
    points = list(np.linspace(0.0, 1.0, MONOTONE_GRID))
    if second.size and np.any(second != 0):
        roots = np.polynomial.polynomial.polyroots(np.trim_zeros(second, "b"))
        points += [r.real for r in np.atleast_1d(roots)
                   if abs(r.imag) < 1e-6 and 0.0 < r.real < 1.0]
    x = np.array(points)
    slopes = _slope_rows(x, order) @ b
    i = int(np.argmin(slopes))
    return float(slopes[i]), float(x[i])


def nonnegative_least_squares(a, b, max_rounds: int | None = None) -> np.ndarray:
    """Non-negative least squares: x >= 0 minimising ``|a x - b|``.

    Lawson and Hanson, *Solving Least Squares Problems*, 1974, ch. 23, Algorithm NNLS.

    Args:
        a: (m, n) float64.
        b: (m,) float64.
        max_rounds: bound on inner iterations (default 3 n).

    Returns:
        (n,) float64, non-negative.

    Raises:
        RuntimeError: when the iterations do not settle.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    n = a.shape[1]
    tol = 10.0 * np.finfo(np.float64).eps * np.linalg.norm(a, 1) * max(a.shape)
    x = np.zeros(n)
    active = np.zeros(n, dtype=bool)  # Lawson and Hanson's set P: variables free to move
    gradient = a.T @ b
    rounds, limit = 0, max_rounds or 3 * n
    while not active.all() and np.max(np.where(active, -np.inf, gradient)) > tol:
        active[int(np.argmax(np.where(active, -np.inf, gradient)))] = True
        while True:
            rounds += 1
            if rounds > limit:
                raise RuntimeError(f"non-negative least squares did not settle in {limit} "
                                   "iterations")
            trial = np.zeros(n)
            trial[active] = np.linalg.lstsq(a[:, active], b, rcond=None)[0]
            if trial[active].min() > 0:
                break
            # step from x towards trial until the first variable reaches 0; drop it
            blocking = active & (trial <= 0)
            gap = x[blocking] - trial[blocking]  # >= 0: x >= 0 >= trial
            step = np.min(np.divide(x[blocking], gap, out=np.zeros_like(gap), where=gap > 0))
            x = x + step * (trial - x)
            active &= x > tol
            x[~active] = 0.0
        x = trial
        gradient = a.T @ (b - a @ x)
    return x


def _least_squares_with_inequalities(e, f, g, h) -> np.ndarray:
    """Least squares under inequalities: x minimising ``|e x - f|`` subject to ``g x >= h``.

    Lawson and Hanson 1974, ch. 23: problem LSI reduced to least distance programming, which
    is solved by NNLS. ``e`` must have full column rank (checked by the caller's condition number).
    """
    q, r = np.linalg.qr(e)
    r_inv = np.linalg.inv(r)
    f1 = q.T @ f
    # with z = r x - f1: minimise |z| subject to (g r^-1) z >= h - g r^-1 f1
    gz = g @ r_inv
    hz = h - gz @ f1
    n = gz.shape[1]
    stacked = np.vstack([gz.T, hz[None, :]])
    unit = np.zeros(n + 1)
    unit[-1] = 1.0
    u = nonnegative_least_squares(stacked, unit, max_rounds=30 * stacked.shape[1])
    residual = stacked @ u - unit
    if abs(residual[-1]) < 1e-12:
        raise RuntimeError("the monotone response constraints are infeasible")
    z = -residual[:n] / residual[n]
    return r_inv @ (z + f1)


@dataclasses.dataclass(frozen=True)
class ResponseFit:
    """A fitted camera response (Eq. 6).

    Attributes:
        coefficients: (K + 1,) c_0 ... c_K in ascending powers, for
            :func:`gpu_blur.reference.transfer.polynomial_crf`.
        pairs: (linear, rendered) pairs used.
        left_out: pairs left out (clipped rendered values, linear values outside [0, 1]).
        residual_rms: root mean square of rendered - fit over the pairs used.
        residual_max: largest absolute residual.
        condition_number: condition number of the Bernstein design matrix.
        constrained: True when the unconstrained fit was not monotone and the slope
            constraint shaped the result.
        min_slope: the fit's smallest slope on [0, 1] (>= -MONOTONE_SLOPE_TOL).
    """

    coefficients: np.ndarray
    pairs: int
    left_out: int
    residual_rms: float
    residual_max: float
    condition_number: float
    constrained: bool
    min_slope: float


def fit_response(linear, rendered, order: int = DEFAULT_CRF_ORDER,
                 what: str = "response pairs") -> ResponseFit:
    """Fit a polynomial camera response that increases on [0, 1] (Eq. 6).

    The polynomial is fitted in the Bernstein basis (well conditioned on [0, 1]). When the
    plain least-squares fit dips anywhere in [0, 1], it is refitted by least squares under
    ``p'(x) >= 0`` at :data:`MONOTONE_GRID` points, adding the point where the slope is
    lowest until it is nowhere below ``-MONOTONE_SLOPE_TOL``.

    Args:
        linear: linear values, any shape.
        rendered: rendered values in [0, 1], same shape; each element pairs with ``linear``'s.
        order: polynomial order K (1 to :data:`MAX_CRF_ORDER`).
        what: name of the data for error messages.

    Raises:
        ValueError: naming ``what`` for mismatched shapes, non-finite values, too few pairs
            after leaving out clipped ones, or samples that cover too little of [0, 1]
            (with the condition number).
    """
    if not (isinstance(order, int) and 1 <= order <= MAX_CRF_ORDER):
        raise ValueError(f"response order {order!r}: must be an integer from 1 to "
                         f"{MAX_CRF_ORDER} (default {DEFAULT_CRF_ORDER})")
    x = np.asarray(linear, dtype=np.float64)
    y = np.asarray(rendered, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"{what}: {x.size} linear values but {y.size} rendered values; give "
                         "the same patches in both")
    x, y = x.ravel(), y.ravel()
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError(f"{what}: NaN or infinite values; every value must be finite")
    keep = (y > CRF_CLIP_MARGIN) & (y < 1.0 - CRF_CLIP_MARGIN) & (x >= 0.0) & (x <= 1.0)
    x, y = x[keep], y[keep]
    if x.size <= order:
        raise ValueError(f"{what}: {x.size} usable pairs (of {keep.size}; clipped rendered "
                         f"values and linear values outside [0, 1] are left out); an order "
                         f"{order} response needs more than {order}, spread over [0, 1]")
    design = _bernstein(x, order)
    cond = _condition(design)
    if cond > MAX_CRF_CONDITION:
        raise ValueError(
            f"{what}: the linear values (from {x.min():.3g} to {x.max():.3g}) cover too little "
            f"of [0, 1] for an order {order} response: condition number {cond:.3g} > "
            f"{MAX_CRF_CONDITION:g}; add exposures that reach the bright and dark ends, or "
            "lower the order (--crf-order)")
    b = np.linalg.lstsq(design, y, rcond=None)[0]
    slope, at = _min_slope(b)
    constrained = slope < -MONOTONE_SLOPE_TOL
    points = np.linspace(0.0, 1.0, MONOTONE_GRID)
    for _ in range(MONOTONE_ROUNDS if constrained else 0):
        points = np.append(points, at)
        b = _least_squares_with_inequalities(design, y, _slope_rows(points, order),
                                             np.zeros(points.size))
        slope, at = _min_slope(b)
        if slope >= -MONOTONE_SLOPE_TOL:
            break
    else:
        if constrained:
            raise RuntimeError(f"{what}: the response fit still has slope {slope:.3g} at "
                               f"linear {at:.6g} after {MONOTONE_ROUNDS} rounds; lower the "
                               "order (--crf-order)")
    residual = y - design @ b
    return ResponseFit(_bernstein_to_power(b), int(x.size), int(keep.size - x.size),
                       float(np.sqrt(np.mean(residual**2))), float(np.abs(residual).max()),
                       cond, constrained, slope)


def response_inverse_table(coefficients, nodes: int = INVERSE_TABLE_NODES) -> np.ndarray:
    """The inverse of ``polynomial_crf(x, coefficients)`` at rendered = 0, 1/(n-1), ..., 1.

    Each node holds the smallest linear x in [0, 1] whose rendered value reaches the node's
    (bisection to float64 resolution), so the table never decreases: 0 below the curve's
    value at 0, 1 above its value at 1.

    Returns:
        (nodes,) float64 linear values.
    """
    targets = np.linspace(0.0, 1.0, nodes)
    low, high = np.zeros(nodes), np.ones(nodes)
    for _ in range(60):  # 2^-60 < float64 resolution on [0, 1]
        middle = 0.5 * (low + high)
        below = polynomial_crf(middle, coefficients) < targets
        low = np.where(below, middle, low)
        high = np.where(below, high, middle)
    return np.where(polynomial_crf(0.0, coefficients) >= targets, 0.0, high)


def inverse_response(rendered, table) -> np.ndarray:
    """Linear values from rendered ones by a table of :func:`response_inverse_table`."""
    table = np.asarray(table, dtype=np.float64)
    return np.interp(np.asarray(rendered, dtype=np.float64),
                     np.linspace(0.0, 1.0, table.size), table)


def read_response(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``[response]`` table of a camera file that ``gpu-blur calibrate`` wrote.

    The polynomial is read and checked as :func:`gpu_blur.cameras.load_camera` reads it
    (:func:`gpu_blur.cameras.response_polynomial`).

    Returns:
        ``(coefficients, inverse_table)``: c_0 ... c_K ascending, and the linear values at
        rendered = i / (n - 1).

    Raises:
        ValueError: naming the file when it has no valid ``[response]``.
    """
    from gpu_blur.cameras import read_camera_spec, response_polynomial

    path = Path(path)
    spec = read_camera_spec(path)
    if not isinstance(spec.get("response"), dict):
        raise ValueError(f"camera file {path}: no [response] table; run gpu-blur calibrate "
                         "with --crf-linear and --crf-rendered")
    c = response_polynomial(spec, path)
    value = spec["response"].get("inverse_linear")
    table = None
    if isinstance(value, list) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        table = np.array(value, dtype=np.float64)
    if (table is None or table.size < 2 or not np.all(np.isfinite(table))
            or np.any(np.diff(table) < 0)):
        raise ValueError(f"camera file {path}: response.inverse_linear = {value!r} is invalid; "
                         "expected >= 2 non-decreasing finite numbers: rerun gpu-blur "
                         "calibrate with --crf-linear and --crf-rendered")
    return np.array(c), table


# ---- the whole calibration and the camera file ----

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


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value) if isinstance(value, int) else repr(float(value))
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def camera_file_text(camera: dict, suffix: str = ".toml") -> str:
    """A camera dict (top-level scalars, then tables of values) as TOML or JSON text."""
    if suffix.lower() == ".json":
        return json.dumps(camera, indent=2) + "\n"
    lines = [f"{k} = {_toml_value(v)}" for k, v in camera.items() if not isinstance(v, dict)]
    for table, values in camera.items():
        if isinstance(values, dict):
            lines += ["", f"[{table}]"]
            lines += [f"{k} = {_toml_value(v)}" for k, v in values.items()]
    return "\n".join(lines) + "\n"


def write_camera_file(path: str | Path, camera: dict) -> None:
    """Write a camera file atomically and check that ``load_camera`` reads it.

    The text goes to a temporary file next to ``path``, is loaded back with
    :func:`gpu_blur.cameras.load_camera`, and is renamed onto ``path``, so ``path`` is never
    half-written or invalid.

    Raises:
        ValueError: for a name not ending in .toml or .json, or a camera the loader refuses.
        OSError: naming the file when it cannot be written.
    """
    from gpu_blur.cameras import load_camera

    path = Path(path)
    if path.suffix.lower() not in (".toml", ".json"):
        raise ValueError(f"{path}: a camera file's name must end in .toml or .json")
    tmp = path.with_name(f".{path.name}.part{path.suffix}")
    try:
        tmp.write_text(camera_file_text(camera, path.suffix))
        try:
            load_camera(tmp)
        except ValueError as e:
            raise ValueError(str(e).replace(str(tmp), str(path))) from None
        os.replace(tmp, path)
    except OSError as e:
        raise OSError(f"{path}: cannot write the camera file ({e.strerror})") from None
    finally:
        if tmp.exists():
            tmp.unlink()
