"""Tolerances, in one table, and the comparison helper every test uses.

A tolerance is a claim about a stage on a backend at a precision: ``(stage, backend, dtype) ->
(rtol, atol)``. Tests never write numbers of their own; they name the row they rely on.
"""

from __future__ import annotations

import numpy as np

#: (stage, backend, dtype) -> (rtol, atol). "independent" rows compare the reference with an
#: outside implementation of the same maths (colour-demosaicing, OpenCV, a literal transcription).
TOLERANCES: dict[tuple[str, str, str], tuple[float, float]] = {
    # -- helper rows: demosaic / bayer --
    # Against colour-demosaicing 0.2.7 (scipy convolve) on photographs: measured bit-identical
    # (max abs difference 0.0); 1e-12 leaves room for another summation order only.
    ("demosaic_malvar2004", "independent", "float64"): (0.0, 1e-12),
    ("demosaic_bilinear", "independent", "float64"): (0.0, 1e-12),
    # A flat field must come back flat: rounding only (Malvar measured <= 4.2e-16 relative).
    ("demosaic_flat_field", "numpy", "float64"): (2e-15, 0.0),
    # x / g * g: two roundings, <= 2.2e-16 relative measured.
    ("white_balance_round_trip", "numpy", "float64"): (1e-15, 0.0),
    # -- helper rows: rng / noise --
    # -- helper rows: blur --
}


def tolerance(stage: str, backend: str = "numpy", dtype: str = "float64") -> tuple[float, float]:
    """Return ``(rtol, atol)`` for a stage; a missing row is an error, never a silent default."""
    try:
        return TOLERANCES[(stage, backend, dtype)]
    except KeyError:
        raise KeyError(
            f"no tolerance row for stage={stage!r}, backend={backend!r}, dtype={dtype!r}; "
            "add one to gpu_blur.testing.TOLERANCES"
        ) from None


def assert_close(
    actual, expected, stage: str, backend: str = "numpy", dtype: str = "float64"
) -> None:
    """Assert ``|actual - expected| <= atol + rtol * |expected|`` under the table's row."""
    rtol, atol = tolerance(stage, backend, dtype)
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    if actual.shape != expected.shape:
        raise AssertionError(f"{stage}: shape {actual.shape} != expected {expected.shape}")
    err = np.abs(actual - expected)
    bound = atol + rtol * np.abs(expected)
    bad = ~(err <= bound)
    if bad.any():
        idx = np.unravel_index(np.argmax(np.where(bad, err - bound, -np.inf)), err.shape)
        raise AssertionError(
            f"{stage} on {backend}/{dtype}: {int(bad.sum())} of {err.size} values out of "
            f"tolerance (rtol={rtol:g}, atol={atol:g}); worst at {idx}: "
            f"{actual[idx]!r} vs {expected[idx]!r} (max abs error {np.nanmax(err):.3g})"
        )
