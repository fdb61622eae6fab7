"""Functions of scipy imported where they are used, with the way out when scipy is missing.

Importing ``scipy.fft`` or ``scipy.optimize`` takes tenths of a second each, which every
``import gpu_blur`` and ``gpu-blur --help`` paid while modules imported them at their top
(tests/architecture/test_startup_imports.py keeps it so).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

__all__ = ["scipy_function"]


def scipy_function(module: str, name: str, who: str) -> Callable:
    """``name`` from scipy's ``module`` (e.g. ``"scipy.fft"``, ``"next_fast_len"``), imported now.

    Raises:
        ModuleNotFoundError: scipy cannot be imported: naming ``who`` (what needs it) and the
            fix. One of scipy's own dependencies missing goes up as it is.
    """
    try:
        return getattr(importlib.import_module(module), name)
    except ModuleNotFoundError as e:
        if (e.name or "").partition(".")[0] != "scipy":
            raise
        raise ModuleNotFoundError(
            f"{who} needs scipy, a dependency of gpu_blur, which could not be imported ({e}): "
            "pip install scipy, or reinstall gpu_blur", name=e.name) from None
