"""Reading patch values: CSV or JSON files, or the mean of boxes of a chart image.

The formats are in :mod:`gpu_blur.analysis.calibrate` (``gpu-blur calibrate --help``).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from gpu_blur.files import parse_settings, read_text

__all__ = ["IMAGE_SUFFIXES", "read_patch_boxes", "read_patch_values", "read_patches",
           "sample_patches"]

#: The suffixes read as images (patch means over ``--boxes``).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")


def _read_table(path: Path, columns: tuple[str, ...], json_key: str) -> tuple[np.ndarray, list]:
    """Rows of the named columns from a CSV (header) or JSON file, with their line numbers.

    Returns:
        ``(values, where)``: (N, len(columns)) float64 and N strings like ``"line 4"``.
    """
    text = read_text(path, str(path))
    want = ", ".join(columns)
    if path.suffix.lower() == ".json":
        data = parse_settings(text, "JSON", str(path))
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
                         f"{', '.join(IMAGE_SUFFIXES)})")
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
    from gpu_blur.image_arrays import to_unit
    from gpu_blur.image_reading import read_image

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
    if path.suffix.lower() in IMAGE_SUFFIXES:
        if boxes is None:
            raise ValueError(f"{path} is an image: give the patch boxes too (--boxes FILE "
                             "with x,y,w,h per patch)")
        return sample_patches(path, read_patch_boxes(boxes))
    return read_patch_values(path)
