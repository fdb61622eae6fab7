"""The camera response (RSBlur supplementary Eq. 6): a polynomial that increases on [0, 1].

Fitted by least squares in the Bernstein basis; when the plain fit dips, refitted under
slope constraints as a least-squares problem with inequalities (Lawson and Hanson, *Solving
Least Squares Problems*, 1974, ch. 23), solved by :func:`scipy.optimize.nnls`. Also the
inverse as a lookup table, and reading a camera file's ``[response]`` back.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from gpu_blur.analysis.calibrate.chart_fit import condition_number
from gpu_blur.reference.lazy_scipy import scipy_function
from gpu_blur.reference.transfer import polynomial_crf

__all__ = ["CRF_CLIP_MARGIN", "DEFAULT_CRF_ORDER", "INVERSE_TABLE_NODES", "MAX_CRF_CONDITION",
           "MAX_CRF_ORDER", "MONOTONE_GRID", "MONOTONE_ROUNDS", "MONOTONE_SLOPE_TOL", "ResponseFit",
           "fit_response", "inverse_response", "read_response", "response_inverse_table"]

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


def _least_squares_with_inequalities(e, f, g, h) -> np.ndarray:
    """Least squares under inequalities: x minimising ``|e x - f|`` subject to ``g x >= h``.

    Lawson and Hanson 1974, ch. 23: problem LSI reduced to least distance programming, which
    is solved by non-negative least squares (:func:`scipy.optimize.nnls`). ``e`` must have full
    column rank (checked by the caller's condition number).
    """
    nnls = scipy_function("scipy.optimize", "nnls", "the camera response fit")
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
    u = nnls(stacked, unit, maxiter=30 * stacked.shape[1])[0]
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
    cond = condition_number(design)
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
