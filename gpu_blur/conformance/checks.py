"""What ``gpu-blur validate`` runs: each check of a device against the float64 reference.

A check runs one conformance case (:mod:`gpu_blur.conformance`) on a device at a precision and
gives one :class:`Outcome` per comparison: the measured error against the tolerance table's
row (:data:`gpu_blur.tolerances.TOLERANCES`, the rows the test suite uses) or bit for bit where
the claim is exact.

This module is the machinery and the registry (:data:`CHECKS`, :data:`AGAINST`); the checks
themselves are in the topic modules beside it (``transfer_checks``, ``accumulate_checks``,
``raw_checks``, ``random_checks``, ``pipeline_checks``), which register on import.
:mod:`gpu_blur.conformance` imports them, in the order the table lists the checks, so
:data:`CHECKS` is whole once this package is imported.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import math
from collections.abc import Callable

import numpy as np

from gpu_blur import tolerances
from gpu_blur.backends import to_host
from gpu_blur.backends.numpy import NumpyBackend

__all__ = ["AGAINST", "CHECKS", "Check", "Outcome", "REFERENCE", "Target", "check", "exact",
           "family", "finite_or_none", "holds", "passed", "row_sources", "run_check", "selected",
           "within"]

REFERENCE = NumpyBackend()


# -- results -----------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Outcome:
    """One comparison of a check.

    Attributes:
        check: the check's name (``accumulate: blur mode kernel, photo``); :func:`run_check`
            fills it in.
        stage: what is compared: the tolerance row's stage, or a name for an exact claim.
        measured: the largest absolute error, or for outlier rows the fraction of values out
            of tolerance; None when the check did not run.
        tolerance: the claim in words (``rtol 0, atol 1e-06``, ``bit for bit``).
        row: the tolerance row ``"stage/backend/dtype"``, or None for an exact claim.
        source: where the row is (``gpu_blur/tolerances.py:231``) or why the claim is exact.
        passed: True, False, or None when skipped (``detail`` says why).
        detail: the first mismatch, or why the check was skipped.
    """

    check: str
    stage: str
    measured: float | None
    tolerance: str
    row: str | None
    source: str
    passed: bool | None
    detail: str = ""


@dataclasses.dataclass(frozen=True)
class Target:
    """A device under test at one precision: its backend and the table's backend column."""

    backend: object
    family: str  # numpy, opencl or warp: the tolerance table's backend column
    precision: str

    @property
    def kernels(self) -> bool:
        """Whether it is a kernel device (not the numpy reference)."""
        return self.family != "numpy"


@functools.cache
def row_sources() -> dict[tuple[str, str, str], tuple[int, str]]:
    """Each tolerance row's (line in gpu_blur/tolerances.py, comment stating its claim).

    Rows written one by one carry their own line; rows made by a comprehension carry the line
    of their stage in it. The claim is the row's end-of-line comment, else the comment block
    above it.
    """
    text = inspect.getsource(tolerances)
    lines = text.splitlines()
    tree = ast.parse(text)
    table = next(n.value for n in tree.body if isinstance(n, ast.AnnAssign)
                 and getattr(n.target, "id", "") == "TOLERANCES")
    found: dict = {}
    for key, value in zip(table.keys, table.values, strict=True):
        if key is not None:  # ("stage", "backend", "dtype"): (rtol, atol)
            found[ast.literal_eval(key)] = key.lineno
            continue
        namespace = vars(tolerances)
        for row in eval(compile(ast.Expression(value), "tolerances", "eval"), namespace):
            found[row] = _line_in(value, row)
    return {row: (line, _claim(lines, line)) for row, line in found.items()}


def _line_in(node: ast.AST, row: tuple[str, str, str]) -> int:
    """The line of ``row``'s stage inside a comprehension of the table (its own, else 1st)."""
    stage, _, dtype = row
    best = node.lineno
    for item in ast.walk(node):
        if isinstance(item, ast.Tuple) and all(isinstance(e, ast.Constant) for e in item.elts):
            values = [e.value for e in item.elts]
            if values[:1] == [stage] and (len(values) < 2 or values[-1] == dtype):
                return item.lineno
        if isinstance(item, ast.Constant) and item.value == stage:
            best = item.lineno
    return best


def _claim(lines: list[str], line: int) -> str:
    """The comment on ``line`` (1-based), else the block of comment lines above it."""
    own = lines[line - 1].partition("#")[2].strip()
    if own:
        return own
    above = []
    for text in reversed(lines[:line - 1]):
        if not text.strip().startswith("#"):
            break
        above.insert(0, text.strip().lstrip("#").strip())
    return " ".join(above)


def _row(stage: str, target: Target, dtype: str | None = None) -> tuple[str, str, str]:
    return (stage, target.family, dtype or target.precision)


def _tolerance_text(key) -> str:
    rtol, atol = tolerances.tolerance(*key)
    return f"rtol {rtol:g}, atol {atol:g}"


def _source(key) -> str:
    line, _ = row_sources().get(key, (0, ""))
    return f"gpu_blur/tolerances.py:{line}"


def within(stage: str, target: Target, actual, expected, *, outliers: str = "",
           accept=None, dtype: str | None = None) -> Outcome:
    """``actual`` against ``expected`` under the row ``(stage, target's backend, precision)``.

    Args:
        stage: the row's stage.
        target: the device; its backend and precision give the row's other columns.
        actual: the device's values.
        expected: the reference's values (same shape).
        outliers: a row whose atol is the fraction of values allowed outside the tolerance
            (``to_raw_noisy_outliers``); the measured number is then that fraction.
        accept: boolean array of values accepted whatever their error (a one-code change at a
            quantization boundary, counted under its own row by the caller).
        dtype: the row's dtype column when not the target's precision (``float32-fast``).
    """
    key = _row(stage, target, dtype)
    actual = np.asarray(to_host(actual), dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    rtol, atol = tolerances.tolerance(*key)
    tolerance = _tolerance_text(key)
    source = _source(key)
    if actual.shape != expected.shape:
        return Outcome("", stage, None, tolerance, "/".join(key), source, False,
                       f"shape {actual.shape} != reference {expected.shape}")
    finite = np.isfinite(actual)
    err = np.where(finite, np.abs(actual - expected), np.inf)
    bad = ~(err <= atol + rtol * np.abs(expected))
    if accept is not None:
        bad &= ~accept
    allowed = tolerances.tolerance(*_row(outliers, target, dtype))[1] if outliers else 0.0
    problem = tolerances.mismatch(actual, expected, *key, allowed_fraction=allowed, accept=accept)
    if not finite.all():
        problem = f"{int((~finite).sum())} values are not finite"
    if outliers:
        okey = _row(outliers, target, dtype)
        measured = float(bad.mean()) if bad.size else 0.0
        tolerance += f"; {allowed:g} of values may miss"
        source += f", {_source(okey).rpartition(':')[2]}"
    else:  # the largest error, leaving out values the caller accepts
        measured = float(np.max(err if accept is None else np.where(accept, 0.0, err),
                                initial=0.0))
    return Outcome("", stage, measured, tolerance, "/".join(key), source, problem is None,
                   problem or "")


def exact(stage: str, actual, expected, why: str) -> Outcome:
    """``actual`` equal to ``expected`` value for value (bit for bit): ``why`` the claim is."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    if actual.shape != expected.shape:
        return Outcome("", stage, None, "bit for bit", None, why, False,
                       f"shape {actual.shape} != {expected.shape}")
    differ = actual != expected
    if actual.dtype.kind == "f":
        differ &= ~(np.isnan(actual) & np.isnan(expected))
    measured = (float(np.max(np.abs(actual.astype(np.float64) - expected), initial=0.0))
                if actual.dtype.kind == "f" else float(differ.sum()))
    detail = ""
    if differ.any():
        i = np.unravel_index(np.argmax(differ), differ.shape)
        detail = (f"{int(differ.sum())} of {differ.size} values differ; first at {i}: "
                  f"{actual[i]!r} vs {expected[i]!r}")
    return Outcome("", stage, measured, "bit for bit", None, why, not differ.any(), detail)


def holds(ok: bool, claim: str, detail: str = "") -> Outcome:
    """An invariant of the case, ``claim`` in words (``monotone``), as the outcome's stage."""
    return Outcome("", claim, None, "holds", None, "invariant", bool(ok),
                   "" if ok else detail or f"does not hold: {claim}")


# -- checks ------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Check:
    """A conformance check: ``run(target)`` gives its outcomes.

    Attributes:
        name: what is checked, as the table shows it.
        run: the check on one device and precision.
        quick: part of ``validate --quick``.
        kernels_only: meaningless on the reference itself (numpy is skipped).
    """

    name: str
    run: Callable[[Target], list[Outcome]]
    quick: bool = False
    kernels_only: bool = False


CHECKS: list[Check] = []


def check(name: str, *, quick: bool = False, kernels_only: bool = False):
    """Register the decorated function as a :class:`Check`."""
    def register(run):
        CHECKS.append(Check(name, run, quick, kernels_only))
        return run
    return register


#: Checks of one kernel device against another: ``run(a, b)`` with both at one precision.
AGAINST: list[Check] = []


# -- running ---------------------------------------------------------------------------------------

def family(name: str) -> str:
    """The tolerance table's backend column for a backend name (``opencl:1:0`` -> opencl)."""
    return name.split(":", 1)[0]


def run_check(item: Check, target: Target, other: Target | None = None) -> list[Outcome]:
    """One check on one target (against ``other`` for :data:`AGAINST`), names filled in.

    An exception becomes a failed outcome that names it.
    """
    if item.kernels_only and not target.kernels:
        return [Outcome(item.name, "-", None, "", None, "", None, "numpy is the reference")]
    try:
        outcomes = item.run(target) if other is None else item.run(target, other)
    except Exception as e:  # a device error is a result, not the end of the run
        return [Outcome(item.name, "-", None, "", None, "", False,
                        f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")]
    return [dataclasses.replace(o, check=item.name) for o in outcomes]


def selected(quick: bool) -> list[Check]:
    """The checks of a run: every one, or those marked quick."""
    return [c for c in CHECKS if c.quick or not quick]


def passed(outcomes: list[Outcome]) -> bool:
    """Whether no outcome failed (skipped ones do not fail a run)."""
    return all(o.passed is not False for o in outcomes)


def finite_or_none(x: float | None) -> float | None:
    """``x`` for JSON: infinities and NaN become None."""
    return None if x is None or not math.isfinite(x) else x
