"""``gpu-blur cameras``: the built-in cameras."""

from __future__ import annotations


def add_parser(sub) -> None:
    """The subcommand (no options)."""
    sub.add_parser("cameras", help="list the built-in cameras")


def run(args) -> int:
    """Print one line per camera."""
    _cameras()
    return 0


def _cameras() -> None:
    """``gpu-blur cameras``: each built-in camera with the numbers one chooses by."""
    from gpu_blur.cameras import get_camera, preset_names

    print(f"{'camera':<14} {'K':>10} {'read std':>10}  {'WB red':<12} {'WB blue':<12} source")
    for name in preset_names():
        c = get_camera(name)
        wb = c.white_balance
        if wb.pairs:
            red, blue = (f"{len(wb.pairs)} pairs", f"{min(p[1] for p in wb.pairs):.2f}-"
                         f"{max(p[1] for p in wb.pairs):.2f}")
            red += f" {min(p[0] for p in wb.pairs):.2f}-{max(p[0] for p in wb.pairs):.2f}"
        else:
            red, blue = ("-".join(f"{g:.2f}" for g in dict.fromkeys(r))
                         for r in (wb.red_range, wb.blue_range))
        print(f"{name:<14} {c.shot_noise_k:>10.4g} {c.read_noise_std:>10.4g}  {red:<12} "
              f"{blue:<12} {c.source}")

