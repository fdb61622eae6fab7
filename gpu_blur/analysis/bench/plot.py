"""The benchmark's plot: error against time, log scales, the Pareto front marked."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np


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


#: The plot's panels: (row key, axis label).
PANELS = (("max_abs_error", "max abs error, no noise (vs float64 reference)"),
          ("residual_kl", "residual KL divergence, nats (noise)"))


def _floor(values: list[float]) -> float:
    """Where a log axis shows 0: a decade below the smallest positive value."""
    positive = [v for v in values if v > 0]
    return 10.0 ** (math.floor(math.log10(min(positive))) - 1) if positive else 1e-9


def _series(rows: list[dict], key: str):
    """(series label -> [(ms/MP, error, label)]), the floor that stands for 0."""
    usable = [r for r in rows if r["available"] and r[key] is not None]
    floor = _floor([r[key] for r in usable])
    series: dict[str, list] = {}
    for r in usable:
        name = f"{r['backend']}: {r['device']}"
        point = (r["ms_per_megapixel"], max(r[key], floor),
                 f"{r['backend']} {r['knob']}: {r['setting']}")
        points = series.setdefault(name, [])
        if not any(p[:2] == point[:2] for p in points):  # one run shared by several knobs
            points.append(point)
    return series, floor


def write_plot(rows: list[dict], path: Path, title: str) -> str:
    """Error against time, log scales, one series per backend and device, front marked.

    Uses matplotlib when installed, else draws with OpenCV. Returns which one drew it.
    """
    try:
        import matplotlib
    except ImportError:
        _plot_cv2(rows, path, title)
        return "cv2"
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(14, 6))
    for ax, (key, label) in zip(axes, PANELS, strict=True):
        series, floor = _series(rows, key)
        everything = [p for points in series.values() for p in points]
        for name, points in series.items():
            ax.scatter([p[0] for p in points], [p[1] for p in points], label=name, s=22)
        front = [everything[i] for i in pareto_front([p[:2] for p in everything])]
        if front:
            ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="k",
                    lw=1, label="Pareto front")
            ax.scatter([p[0] for p in front], [p[1] for p in front], s=90,
                       facecolors="none", edgecolors="k")
            for x, y, text in front:
                ax.annotate(text, (x, y), textcoords="offset points", xytext=(4, 4),
                            fontsize=7)
        ax.axhline(floor, color="0.7", lw=0.8, ls=":")
        ax.set(xscale="log", yscale="log", xlabel="ms per megapixel",
               ylabel=f"{label}; {floor:.0e} = 0")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return "matplotlib"


#: cv2 drawing: BGR colours of the series, in order.
_COLOURS = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
            (75, 86, 140), (194, 119, 227), (127, 127, 127))


def _plot_cv2(rows: list[dict], path: Path, title: str) -> None:
    """The plot of :func:`write_plot` drawn with OpenCV (no matplotlib)."""
    import cv2

    panel_w, h, margin = 700, 620, 80
    canvas = np.full((h, panel_w * len(PANELS), 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, title[:150], (10, 20), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for n, (key, label) in enumerate(PANELS):
        series, floor = _series(rows, key)
        everything = [p for points in series.values() for p in points]
        if not everything:
            continue
        x0, x1 = margin + n * panel_w, (n + 1) * panel_w - 20
        y0, y1 = h - margin, 50
        lx = [math.log10(p[0]) for p in everything]
        ly = [math.log10(p[1]) for p in everything]
        xs = (math.floor(min(lx)), math.ceil(max(lx)) + (min(lx) == max(lx)))
        ys = (math.floor(min(ly)), math.ceil(max(ly)) + (min(ly) == max(ly)))

        def at(p, xs=xs, ys=ys, x0=x0, x1=x1, y0=y0, y1=y1):
            fx = (math.log10(p[0]) - xs[0]) / (xs[1] - xs[0])
            fy = (math.log10(p[1]) - ys[0]) / (ys[1] - ys[0])
            return int(x0 + fx * (x1 - x0)), int(y0 + fy * (y1 - y0))

        for d in range(xs[0], xs[1] + 1):
            x, _ = at((10.0 ** d, 10.0 ** ys[0]))
            cv2.line(canvas, (x, y0), (x, y1), (225, 225, 225), 1)
            cv2.putText(canvas, f"1e{d}", (x - 12, y0 + 18), font, 0.4, (0, 0, 0), 1)
        for d in range(ys[0], ys[1] + 1):
            _, y = at((10.0 ** xs[0], 10.0 ** d))
            cv2.line(canvas, (x0, y), (x1, y), (225, 225, 225), 1)
            cv2.putText(canvas, f"1e{d}", (x0 - 45, y + 4), font, 0.4, (0, 0, 0), 1)
        cv2.rectangle(canvas, (x0, y1), (x1, y0), (0, 0, 0), 1)
        cv2.putText(canvas, "ms per megapixel", (x0 + 200, y0 + 40), font, 0.45, (0, 0, 0), 1)
        cv2.putText(canvas, f"{label}; {floor:.0e} = 0"[:80], (x0, y1 - 10), font, 0.4,
                    (0, 0, 0), 1)
        for (name, points), colour in zip(series.items(), _COLOURS * 4, strict=False):
            for p in points:
                cv2.circle(canvas, at(p), 4, colour, -1, cv2.LINE_AA)
            if n == 0:
                k = list(series).index(name)
                cv2.circle(canvas, (x0 + 10, y1 + 15 + 16 * k), 4, colour, -1)
                cv2.putText(canvas, name[:70], (x0 + 20, y1 + 19 + 16 * k), font, 0.38,
                            (0, 0, 0), 1)
        front = [at(everything[i]) for i in pareto_front([p[:2] for p in everything])]
        for a, b in zip(front, front[1:], strict=False):
            cv2.line(canvas, a, (b[0], a[1]), (0, 0, 0), 1, cv2.LINE_AA)
            cv2.line(canvas, (b[0], a[1]), b, (0, 0, 0), 1, cv2.LINE_AA)
        for p in front:
            cv2.circle(canvas, p, 8, (0, 0, 0), 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), canvas):
        raise OSError(f"cannot write {path}")
