"""``gpu-blur cameras``: the built-in cameras."""

from __future__ import annotations

import textwrap

__all__ = ["WIDTH", "add_parser", "camera_rows", "run"]

#: The listing's width: rows and the wrapped sources fit a 100-column terminal.
WIDTH = 100


def add_parser(sub) -> None:
    """The subcommand (no options)."""
    sub.add_parser("cameras", help="list the built-in cameras")


def run(args) -> int:
    """Print one row per camera, then each distinct source once."""
    _cameras()
    return 0


def _gains(low: float, high: float) -> str:
    return f"{low:.2f}" if low == high else f"{low:.2f}-{high:.2f}"


def camera_rows() -> tuple[list[tuple[str, ...]], list[str]]:
    """The table's rows (name, K, read std, WB red, WB blue, how WB is drawn, source note).

    And the sources in the order the notes number them: cameras of one origin (the 19 RSBlur
    sessions) share one note, so each text is printed once.
    """
    from gpu_blur.cameras import get_camera, preset_names

    rows, sources = [], []
    for name in preset_names():
        c = get_camera(name)
        wb = c.white_balance
        if wb.pairs:
            reds, blues = [p[0] for p in wb.pairs], [p[1] for p in wb.pairs]
            red, blue = _gains(min(reds), max(reds)), _gains(min(blues), max(blues))
            drawn = f"{len(wb.pairs)} listed pairs"
        else:
            red, blue = _gains(*wb.red_range), _gains(*wb.blue_range)
            fixed = wb.red_range[0] == wb.red_range[1] and wb.blue_range[0] == wb.blue_range[1]
            drawn = "fixed" if fixed else "uniform"
        if c.source not in sources:
            sources.append(c.source)
        rows.append((name, f"{c.shot_noise_k:.4g}", f"{c.read_noise_std:.4g}", red, blue, drawn,
                     f"[{sources.index(c.source) + 1}]"))
    return rows, sources


def _cameras() -> None:
    """``gpu-blur cameras``: each built-in camera with the numbers one chooses by."""
    rows, sources = camera_rows()
    head = ("camera", "shot noise K", "read noise std", "WB red", "WB blue", "WB drawn",
            "source")
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    right = {1, 2}  # numbers align right

    def line(cells) -> str:
        return "  ".join(c.rjust(w) if i in right else c.ljust(w)
                         for i, (c, w) in enumerate(zip(cells, widths, strict=True))).rstrip()

    print(line(head))
    for row in rows:
        print(line(row))
    print("\nsources (noise levels: RSBlur's beta1 = K and beta2 = read noise std, in [0, 1] RAW "
          "units):")
    for i, text in enumerate(sources, 1):
        label = f"[{i}] "
        print(textwrap.fill(text, WIDTH, initial_indent=label, subsequent_indent=" " * len(label),
                            break_long_words=False, break_on_hyphens=False))
