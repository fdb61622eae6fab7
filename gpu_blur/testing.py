"""The comparison helpers every test uses: a tolerance row's check, statistical scores.

The rows are :mod:`gpu_blur.tolerances` (production code reads them there); the names tests
take from it (``TOLERANCES``, ``tolerance``, ``mismatch``) are here too.
"""

from __future__ import annotations

import math

import numpy as np

from gpu_blur.tolerances import TOLERANCES, mismatch, tolerance

__all__ = ["TOLERANCES", "assert_close", "mismatch", "tolerance", "z_mean", "z_var"]


def assert_close(
    actual, expected, stage: str, backend: str = "numpy", dtype: str = "float64"
) -> None:
    """Assert ``|actual - expected| <= atol + rtol * |expected|`` under the table's row."""
    problem = mismatch(actual, expected, stage, backend, dtype)
    if problem:
        raise AssertionError(problem)


def z_mean(sample: np.ndarray, mean: float, var: float) -> float:
    """Standard score of a sample mean against a known mean and variance."""
    if var == 0.0:
        return 0.0 if np.all(sample == mean) else math.inf
    return (sample.mean() - mean) / math.sqrt(var / sample.size)


def z_var(sample: np.ndarray, var: float, mu4: float) -> float:
    """Standard score of a sample variance; its standard error is sqrt((mu4 - var^2) / n)."""
    spread = mu4 - var * var
    if spread <= 0.0:
        return 0.0 if sample.var() == var else math.inf
    return (sample.var(ddof=1) - var) / math.sqrt(spread / sample.size)
