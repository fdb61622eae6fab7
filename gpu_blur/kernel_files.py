"""Blur kernel files (``.npy`` or a grayscale image) and the checks of a kernel's weights."""

from __future__ import annotations

import math
import os
from pathlib import Path
from tokenize import TokenError

import numpy as np

from gpu_blur import limits
from gpu_blur.image_reading import decode_file

__all__ = ["check_kernel", "kernel_weights", "read_kernel"]


def read_kernel(path: str | Path) -> np.ndarray:
    """A blur kernel from ``.npy`` (2-D floats) or a grayscale image (PNG, ...), as float64.

    The kernel is checked (odd sides up to :data:`gpu_blur.limits.KERNEL_SIDE`, finite,
    non-negative, positive sum) but not normalized here; the blur stage normalizes it to sum
    1. Its size is checked from the header before it is loaded (:func:`_read_npy`,
    :func:`gpu_blur.image_reading.decode_file`).

    Raises:
        ValueError: naming the file (as ``blur.kernel = ...``) and what is wrong with it.
    """
    path = Path(path)
    where = f"blur.kernel = {str(path)!r}"
    if not path.exists():  # anything else there is refused by its kind (files.open_regular)
        raise ValueError(f"{where}: no such file (a relative path is taken from the scene "
                         "file's folder)")
    if path.suffix.lower() == ".npy":
        kernel = _read_npy(path, where)
    else:
        kernel = decode_file(path, where, "", lambda width, height: _kernel_too_wide(height, width))
    kernel = kernel_weights(kernel, where)
    check_kernel(kernel, where)
    return kernel


def kernel_weights(kernel, where: str) -> np.ndarray:
    """A kernel's weights as float64; integers and floats only (a complex part is not dropped).

    Raises:
        ValueError: starting with ``where``, naming the dtype and the way out.
    """
    try:
        kernel = np.asarray(kernel)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: not an array of numbers; give a 2-D array of "
                         "floats") from None
    kind = kernel.dtype.kind
    if kind == "c":
        raise ValueError(f"{where}: holds {kernel.dtype} values; kernel weights are real (the "
                         "imaginary part would be lost): pass np.real(k) or np.abs(k)")
    if kind not in "iuf":
        raise ValueError(f"{where}: holds {kernel.dtype} values, not numbers; kernel weights "
                         "are integers or floats: pass k.astype(np.float64)")
    return kernel.astype(np.float64)


def _read_npy(path: Path, where: str) -> np.ndarray:
    """A kernel's ``.npy`` file, after its header's shape and dtype are checked.

    The header (format 1.0 or 2.0, what ``np.save`` writes for numbers) is read first, and a
    shape :func:`check_kernel` refuses, or one whose data does not fit in the file, is
    refused before any array is made: ``np.load`` makes the array the header asks for.
    """
    from numpy.lib import format as npy

    from gpu_blur.files import open_regular

    way_out = "save the kernel with np.save"
    with open_regular(path, where) as f:
        try:
            version = npy.read_magic(f)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"format version {version[0]}.{version[1]}, not 1.0 or 2.0")
            read_header = npy.read_array_header_1_0 if version == (1, 0) \
                else npy.read_array_header_2_0
            shape, _, dtype = read_header(f)
            start = f.tell()
        except (SyntaxError, TokenError, RecursionError):  # numpy parses the header as Python
            raise ValueError(f"{where}: not a numpy array file (its header is no valid Python "
                             f"literal); {way_out}") from None
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"{where}: not a numpy array file ({e}); {way_out}") from None
        if dtype.hasobject:
            raise ValueError(f"{where}: holds Python objects ({dtype}), which are not loaded; "
                             f"{way_out} from a float array")
        _check_kernel_shape(shape, where)
        need, have = math.prod(shape) * dtype.itemsize, os.fstat(f.fileno()).st_size - start
        if need > have:
            raise ValueError(f"{where}: its header gives a {shape[0]} x {shape[1]} array of "
                             f"{dtype} ({need:,} bytes) but {have:,} bytes follow it: the file "
                             f"is truncated or its header damaged; {way_out} again")
        try:
            f.seek(0)
            return np.load(f, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"{where}: not a numpy array file ({e}); {way_out}") from None


def _kernel_too_wide(rows: int, cols: int) -> str | None:
    """Why a kernel of ``rows`` x ``cols`` is too large or empty (limits.KERNEL_SIDE), or None."""
    if min(rows, cols) < 1:
        return (f"is {rows} x {cols}; a kernel needs at least one row and column of weights: "
                "check what wrote it")
    problem = limits.KERNEL_SIDE.problem(max(rows, cols))
    if problem is None:
        return None
    return (f"is {rows} x {cols}; allowed sides: {problem}: crop it to the rows and columns "
            "that hold its weight, or scale it down with the images it blurs")


def _check_kernel_shape(shape: tuple[int, ...], where: str) -> None:
    """Refuse a kernel shape: not 2-D, a side above limits.KERNEL_SIDE, or an even side."""
    if len(shape) != 2:
        raise ValueError(f"{where}: a kernel is 2-D (one channel), got shape {shape}")
    problem = _kernel_too_wide(*shape)
    if problem:
        raise ValueError(f"{where}: {problem}")
    if shape[0] % 2 == 0 or shape[1] % 2 == 0:
        raise ValueError(f"{where}: is {shape[0]} x {shape[1]}; a kernel needs odd "
                         "sides (its centre is the origin): pad it with a row or column of "
                         "zeros where the blur should not move")


def check_kernel(kernel: np.ndarray, where: str) -> None:
    """Refuse what :func:`gpu_blur.reference.motion_kernel.normalize_kernel` cannot normalize.

    Raises:
        ValueError: starting with ``where``, saying what is wrong and the way out.
    """
    _check_kernel_shape(kernel.shape, where)
    bad = int(np.count_nonzero(~np.isfinite(kernel)))
    if bad:
        raise ValueError(f"{where}: holds {bad} NaN or infinite weight(s); kernel weights must "
                         "be finite")
    negative = int(np.count_nonzero(kernel < 0))
    if negative:
        raise ValueError(f"{where}: holds {negative} negative weight(s), the lowest "
                         f"{float(kernel.min()):.6g}; a blur kernel is non-negative: clip them "
                         "to 0 (np.clip(k, 0, None)) or fix what made it")
    if not kernel.sum() > 0:
        raise ValueError(f"{where}: its weights sum to {float(kernel.sum()):.6g}; a blur kernel "
                         "needs some positive weight (it is scaled to sum 1)")
