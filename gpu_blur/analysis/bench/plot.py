"""The benchmark's plot: error against time, log scales, the Pareto front marked and labelled.

Colour is the backend and device, the marker shape the knob. The front's points carry their
backend, knob and setting, the labels pushed apart so that none covers another, each with a
leader line to its point. The legend sits below the panels with every name in full, and the
image grows to hold every label: nothing is cut off. matplotlib draws it when installed
(``pip install matplotlib``), else OpenCV draws the same layout.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["MARKERS", "PAD", "PANELS", "Placed", "Point", "figure", "pareto_front", "place_labels",
           "spread", "write_plot"]


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and error (lower is better).

    Args:
        points: (time, error) pairs.

    Returns:
        The front's indices, fastest first; of equal points, the first.
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1], i))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def spread(wanted: Sequence[float], gap: float, low: float, high: float) -> list[float]:
    """Positions close to ``wanted`` (ascending), at least ``gap`` apart, within [low, high].

    Labels of close points go up from the lowest as far as they must; if the last then passes
    ``high`` they come down from there (below ``low`` only when they cannot all fit).
    """
    out: list[float] = []
    for w in wanted:
        out.append(max(w, low) if not out else max(w, out[-1] + gap))
    if out and out[-1] > high:
        out[-1] = high
        for i in range(len(out) - 2, -1, -1):
            out[i] = min(out[i], out[i + 1] - gap)
    return out


#: The plot's panels: (row key, axis label).
PANELS = (("max_abs_error", "max abs error, no noise (vs float64 reference)"),
          ("residual_kl", "residual KL divergence, nats (noise)"))
#: Decades of room around the points on each axis (markers stay inside the panel).
PAD = 0.15
#: Knob markers in order of the knobs' first row (matplotlib names; OpenCV draws the same).
MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*")


@dataclasses.dataclass(frozen=True)
class Point:
    """One measured setting in a panel: time, error (0 drawn at the floor) and who made it."""

    ms: float
    error: float
    series: str
    knob: str
    label: str


def _floor(values: list[float]) -> float:
    """Where a log axis shows 0: a decade below the smallest positive value."""
    positive = [v for v in values if v > 0]
    return 10.0 ** (math.floor(math.log10(min(positive))) - 1) if positive else 1e-9


def _series_name(row: dict) -> str:
    return f"{row['backend']}: {row['device']}"


def _points(rows: list[dict], key: str) -> tuple[list[Point], float]:
    """A panel's points (one per run: a run shared by several knobs once) and its floor."""
    usable = [r for r in rows if r["available"] and r[key] is not None]
    floor = _floor([r[key] for r in usable])
    points: list[Point] = []
    for r in usable:
        p = Point(r["ms_per_megapixel"], max(r[key], floor), _series_name(r), r["knob"],
                  f"{r['backend']} {r['knob']}: {r['setting']}")
        if not any((q.series, q.ms, q.error) == (p.series, p.ms, p.error) for q in points):
            points.append(p)
    return points, floor


def _decades(values: list[float], pad: float) -> tuple[float, float]:
    """The log10 range of an axis holding ``values``, ``pad`` decades wider on each side."""
    logs = [math.log10(v) for v in values]
    lo, hi = min(logs), max(logs)
    if hi - lo < 1.0:
        lo, hi = (lo + hi) / 2 - 0.5, (lo + hi) / 2 + 0.5
    return lo - pad, hi + pad


@dataclasses.dataclass(frozen=True)
class Placed:
    """A front label's place in a panel, in panel units from its bottom-left corner, y up.

    Units are points for matplotlib, pixels for OpenCV.
    """

    point: Point
    x: float
    y: float
    label_y: float
    left: bool  # the label ends at the point (it would pass the panel's right edge)


def place_labels(front: list[Point], xs: tuple[float, float], ys: tuple[float, float],
                 width: float, height: float, text_width, line: float) -> list[Placed]:
    """Where the front's labels go in a ``width`` x ``height`` panel of log ranges xs, ys.

    Each label sits level with its point, on the right unless it would pass the right edge;
    labels are then pushed apart vertically, at least ``line`` apart, so none overlaps
    another (:func:`spread`). ``text_width(text)`` is a label's width in panel units.
    """
    pos = [((math.log10(p.ms) - xs[0]) / (xs[1] - xs[0]) * width,
            (math.log10(p.error) - ys[0]) / (ys[1] - ys[0]) * height) for p in front]
    order = sorted(range(len(front)), key=lambda i: pos[i][1])
    heights = spread([pos[i][1] for i in order], line, line / 2, height - line / 2)
    placed = []
    for i, label_y in zip(order, heights, strict=True):
        x, y = pos[i]
        left = x + line + text_width(front[i].label) > width
        placed.append(Placed(front[i], x, y, label_y, left))
    return placed


def write_plot(rows: list[dict], path: Path, title: str) -> str:
    """Error against time, log scales, one colour per backend and device, front labelled.

    Uses matplotlib when installed, else draws with OpenCV. Returns which one drew it.
    """
    try:
        import matplotlib
    except ImportError:
        _plot_cv2(rows, path, title)
        return "cv2"
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = figure(rows, title)
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.15)
    plt.close(fig)
    return "matplotlib"


#: matplotlib layout, inches: panel size, margins, gap between the panels.
_PANEL_W, _PANEL_H, _LEFT, _GAP, _TOP, _BELOW = 5.8, 4.4, 0.9, 1.3, 0.5, 0.75
_LABEL_PT = 7.0


def figure(rows: list[dict], title: str):
    """The matplotlib figure of :func:`write_plot` (saved with a tight box: nothing cut)."""
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    series = list(dict.fromkeys(_series_name(r) for r in rows if r["available"]))
    knobs = list(dict.fromkeys(r["knob"] for r in rows if r["available"]))
    colour = {s: f"C{i % 10}" for i, s in enumerate(series)}
    marker = {k: MARKERS[i % len(MARKERS)] for i, k in enumerate(knobs)}
    width = _LEFT + len(PANELS) * _PANEL_W + (len(PANELS) - 1) * _GAP + 0.3
    height = _TOP + _PANEL_H + _BELOW
    fig = plt.figure(figsize=(width, height))
    fig.suptitle(title, fontsize=10, y=1 - 0.2 / height, va="top", wrap=True)
    line = 1.3 * _LABEL_PT
    for n, (key, axis_label) in enumerate(PANELS):
        left = _LEFT + n * (_PANEL_W + _GAP)
        ax = fig.add_axes((left / width, _BELOW / height, _PANEL_W / width, _PANEL_H / height))
        points, floor = _points(rows, key)
        ax.set(xscale="log", yscale="log", xlabel="ms per megapixel",
               ylabel=f"{axis_label}; {floor:.0e} = 0")
        ax.grid(True, which="major", alpha=0.3)
        if not points:
            continue
        xs, ys = _decades([p.ms for p in points], PAD), _decades([p.error for p in points], PAD)
        ax.set_xlim(10 ** xs[0], 10 ** xs[1])
        ax.set_ylim(10 ** ys[0], 10 ** ys[1])
        ax.axhline(floor, color="0.7", lw=0.8, ls=":")
        for s in series:
            for k in knobs:
                mine = [p for p in points if p.series == s and p.knob == k]
                ax.scatter([p.ms for p in mine], [p.error for p in mine], s=24,
                           color=colour[s], marker=marker[k], alpha=0.85, lw=0)
        front = [points[i] for i in pareto_front([(p.ms, p.error) for p in points])]
        ax.step([p.ms for p in front], [p.error for p in front], where="post", color="k", lw=1)
        ax.scatter([p.ms for p in front], [p.error for p in front], s=90,
                   facecolors="none", edgecolors="k")
        placed = place_labels(front, xs, ys, _PANEL_W * 72, _PANEL_H * 72,
                              lambda text: 0.55 * _LABEL_PT * len(text), line)
        for p in placed:
            offset = (-line if p.left else line, p.label_y - p.y)
            ax.annotate(p.point.label, (p.point.ms, p.point.error), xytext=offset,
                        textcoords="offset points", ha="right" if p.left else "left",
                        va="center", fontsize=_LABEL_PT,
                        bbox={"boxstyle": "square,pad=0.1", "fc": "white", "ec": "none",
                              "alpha": 0.75},
                        arrowprops={"arrowstyle": "-", "color": "0.45", "lw": 0.6,
                                    "shrinkA": 0, "shrinkB": 5})
    handles = [Line2D([], [], ls="", marker="o", color=colour[s], label=s) for s in series]
    handles.append(Line2D([], [], color="k", lw=1, marker="o", mfc="none", ms=9,
                          label="Pareto front (labelled: backend knob: setting)"))
    fig.legend(handles=handles, loc="upper left", fontsize=8, title="backend: device",
               title_fontsize=8, bbox_to_anchor=(_LEFT / width, -0.1 / height))
    knob_handles = [Line2D([], [], ls="", marker=marker[k], color="0.3", label=k)
                    for k in knobs]
    fig.legend(handles=knob_handles, loc="upper right", fontsize=8, title="knob",
               title_fontsize=8, ncol=min(4, max(1, len(knobs))),
               bbox_to_anchor=(1 - 0.3 / width, -0.1 / height))
    return fig


#: OpenCV drawing: BGR colours of the series (matplotlib's first ten), in order.
_COLOURS = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
            (75, 86, 140), (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23))
_FONT_SCALE, _LABEL_SCALE = 0.45, 0.38


def _cv2_marker(canvas, at: tuple[int, int], shape: str, colour) -> None:
    """Draw one of :data:`MARKERS` (5 px radius) with OpenCV."""
    import cv2

    x, y = at
    polygons = {"s": [(-4, -4), (4, -4), (4, 4), (-4, 4)], "^": [(0, -5), (5, 4), (-5, 4)],
                "v": [(0, 5), (5, -4), (-5, -4)], "D": [(0, -5), (5, 0), (0, 5), (-5, 0)]}
    if shape in polygons:
        pts = np.array([(x + dx, y + dy) for dx, dy in polygons[shape]], np.int32)
        cv2.fillPoly(canvas, [pts], colour, cv2.LINE_AA)
    elif shape in ("P", "X", "*"):
        kind = {"P": cv2.MARKER_CROSS, "X": cv2.MARKER_TILTED_CROSS, "*": cv2.MARKER_STAR}
        cv2.drawMarker(canvas, at, colour, kind[shape], 11, 2, cv2.LINE_AA)
    else:
        cv2.circle(canvas, at, 4, colour, -1, cv2.LINE_AA)


def _plot_cv2(rows: list[dict], path: Path, title: str) -> None:
    """The plot of :func:`write_plot` drawn with OpenCV (no matplotlib)."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX

    def size(text: str, scale: float = _FONT_SCALE) -> tuple[int, int]:
        (w, h), base = cv2.getTextSize(text, font, scale, 1)
        return w, h + base

    series = list(dict.fromkeys(_series_name(r) for r in rows if r["available"]))
    knobs = list(dict.fromkeys(r["knob"] for r in rows if r["available"]))
    colour = {s: _COLOURS[i % len(_COLOURS)] for i, s in enumerate(series)}
    marker = {k: MARKERS[i % len(MARKERS)] for i, k in enumerate(knobs)}
    panel_w, panel_h, left, gap, right = 620, 460, 80, 110, 30
    width = left + len(PANELS) * panel_w + (len(PANELS) - 1) * gap + right
    title_lines = _wrap(title, width - 20, size)
    top = 24 + 18 * len(title_lines) + 24
    legend_rows = max(len(series) + 1, math.ceil(len(knobs) / 2)) + 1
    height = top + panel_h + 60 + 18 * legend_rows + 12
    canvas = np.full((height, width, 3), 255, np.uint8)

    def text(s: str, org: tuple[int, int], scale: float = _FONT_SCALE, colour=(0, 0, 0)):
        cv2.putText(canvas, s, org, font, scale, colour, 1, cv2.LINE_AA)

    for i, line in enumerate(title_lines):
        text(line, (10, 24 + 18 * i))
    line_px = size("Ag", _LABEL_SCALE)[1] + 3
    for n, (key, axis_label) in enumerate(PANELS):
        x0 = left + n * (panel_w + gap)
        x1, y0, y1 = x0 + panel_w, top + panel_h, top
        points, floor = _points(rows, key)
        text(f"{axis_label}; {floor:.0e} = 0", (x0, y1 - 10))
        text("ms per megapixel", (x0 + panel_w // 2 - size("ms per megapixel")[0] // 2,
                                  y0 + 40))
        cv2.rectangle(canvas, (x0, y1), (x1, y0), (0, 0, 0), 1)
        if not points:
            continue
        xs, ys = _decades([p.ms for p in points], PAD), _decades([p.error for p in points], PAD)

        def at(ms, error, xs=xs, ys=ys, x0=x0, y0=y0):
            fx = (math.log10(ms) - xs[0]) / (xs[1] - xs[0])
            fy = (math.log10(error) - ys[0]) / (ys[1] - ys[0])
            return round(x0 + fx * panel_w), round(y0 - fy * panel_h)

        for d in range(math.ceil(xs[0]), math.floor(xs[1]) + 1):
            x = at(10.0 ** d, 10.0 ** ys[0])[0]
            cv2.line(canvas, (x, y0), (x, y1), (225, 225, 225), 1)
            text(f"1e{d}", (x - size(f"1e{d}")[0] // 2, y0 + 18))
        for d in range(math.ceil(ys[0]), math.floor(ys[1]) + 1):
            y = at(10.0 ** xs[0], 10.0 ** d)[1]
            cv2.line(canvas, (x0, y), (x1, y), (225, 225, 225), 1)
            text(f"1e{d}", (x0 - 8 - size(f"1e{d}")[0], y + 5))
        cv2.line(canvas, (x0, at(1.0, floor)[1]), (x1, at(1.0, floor)[1]), (180, 180, 180), 1)
        cv2.rectangle(canvas, (x0, y1), (x1, y0), (0, 0, 0), 1)
        for p in points:
            _cv2_marker(canvas, at(p.ms, p.error), marker[p.knob], colour[p.series])
        front = [points[i] for i in pareto_front([(p.ms, p.error) for p in points])]
        corners = [at(p.ms, p.error) for p in front]
        for a, b in zip(corners, corners[1:], strict=False):
            cv2.line(canvas, a, (b[0], a[1]), (0, 0, 0), 1, cv2.LINE_AA)
            cv2.line(canvas, (b[0], a[1]), b, (0, 0, 0), 1, cv2.LINE_AA)
        for c in corners:
            cv2.circle(canvas, c, 8, (0, 0, 0), 1, cv2.LINE_AA)
        for p in place_labels(front, xs, ys, panel_w, panel_h,
                              lambda s: size(s, _LABEL_SCALE)[0], line_px):
            w, h = size(p.point.label, _LABEL_SCALE)
            lx = x0 + round(p.x) + (-line_px - w if p.left else line_px)
            ly = y0 - round(p.label_y)
            cv2.line(canvas, (x0 + round(p.x), y0 - round(p.y)),
                     (lx + (w if p.left else 0), ly), (150, 150, 150), 1, cv2.LINE_AA)
            box = canvas[max(ly - h // 2 - 1, 0):ly + h // 2 + 1, max(lx - 1, 0):lx + w + 1]
            box[:] = 191 + box // 4  # the label on a light backing, the points still show
            text(p.point.label, (lx, ly + h // 2 - 2), _LABEL_SCALE)
    # the legend, below the panels: devices (colours) on the left, knobs (markers) right
    ly = top + panel_h + 70
    text("backend: device", (left, ly))
    for i, s in enumerate(series):
        _cv2_marker(canvas, (left + 8, ly + 18 * (i + 1) - 4), "o", colour[s])
        text(s, (left + 20, ly + 18 * (i + 1)))
    y_front = ly + 18 * (len(series) + 1)
    cv2.circle(canvas, (left + 8, y_front - 4), 7, (0, 0, 0), 1, cv2.LINE_AA)
    text("Pareto front (labelled: backend knob: setting)", (left + 20, y_front))
    kx = left + panel_w + gap
    text("knob", (kx, ly))
    for i, k in enumerate(knobs):
        x, y = kx + 200 * (i % 2), ly + 18 * (i // 2 + 1)
        _cv2_marker(canvas, (x + 8, y - 4), marker[k], (80, 80, 80))
        text(k, (x + 20, y))
    if not cv2.imwrite(str(path), canvas):
        raise OSError(f"cannot write {path}")


def _wrap(text: str, width: int, size) -> list[str]:
    """``text`` in lines of at most ``width`` pixels (``size(line)[0]``), broken at spaces."""
    lines: list[str] = []
    for word in text.split(" "):
        if lines and size(f"{lines[-1]} {word}")[0] <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines
