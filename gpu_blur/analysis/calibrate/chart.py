"""A colour chart's reference colours: the built-in ColorChecker 24 or a file of its format."""

from __future__ import annotations

import dataclasses
from importlib import resources
from pathlib import Path

import numpy as np

from gpu_blur.constants import D50_TO_D65
from gpu_blur.files import parse_settings, read_text

__all__ = ["COLORCHECKER24", "ChartReference", "lab_to_xyz", "load_chart_reference"]

#: Built-in chart reference (gpu_blur/data).
COLORCHECKER24 = "colorchecker24.json"


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
        text = read_text(path, f"chart reference {where}")
    spec = parse_settings(text, "JSON", f"chart reference {where}")

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
