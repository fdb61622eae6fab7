"""``gpu-blur plan``: the stages a scene runs, kept or skipped, with why (and their cost)."""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["add_parser", "cost_size", "run"]


def add_parser(sub) -> None:
    """The subcommand and its options."""
    pl = sub.add_parser("plan", help="print the stages a scene runs, kept or skipped, with why")
    pl.add_argument("scene", type=Path, nargs="?", help="scene TOML, or a built-in scene's "
                    "name (realblur_j, rsblur, minimal; default: the default scene)")
    pl.add_argument("--cost", action="store_true", help="also time what each kept stage costs "
                    "and what each skipped one would cost, on the built-in photo (a few "
                    "seconds)")
    pl.add_argument("--backend", default="numpy", help="with --cost: the backend timed "
                    "(numpy, opencl:P:D, warp:cpu, warp:cuda:0; default numpy: present "
                    "everywhere, no kernel builds)")
    pl.add_argument("--size", default="480x320", help="with --cost: the input's WxH in "
                    "pixels, even sides (default 480x320)")


def run(args) -> int:
    """Print the plan, and with --cost what each stage costs."""
    from gpu_blur.cameras import scene_camera
    from gpu_blur.planning import plan
    from gpu_blur.scene import load_scene

    scene = load_scene(args.scene)
    scene_camera(scene)  # an unknown camera or a bad camera file, as generate says
    print(plan(scene))
    if args.cost:
        from gpu_blur.analysis.stage_cost import format_costs, stage_costs

        costs = stage_costs(scene, args.backend, cost_size(args.size))
        print(format_costs(costs, plan(scene)))
    return 0


def cost_size(text: str) -> tuple[int, int]:
    """``plan --size WxH`` as (height, width), within the pixel budget of an input image.

    Raises:
        ValueError: naming the option and its value, for text that is not WxH or a size above
            :func:`gpu_blur.limits.max_pixels` (the timed images are made in memory).
    """
    from gpu_blur import limits

    match = re.fullmatch(r"(\d{1,9})x(\d{1,9})", text.lower(), re.ASCII)
    if not match:
        raise ValueError(f"--size {text!r} is invalid; allowed: WxH in pixels, e.g. 480x320")
    width, height = int(match[1]), int(match[2])
    most = limits.max_pixels()
    if width * height > most:
        raise ValueError(f"--size {text!r} is invalid; allowed: at most {most:,} pixels (the "
                         f"pixel budget of an input image; {width * height:,} would be made in "
                         f"memory): give a smaller size, or raise the budget with the "
                         f"environment variable {limits.MAX_PIXELS_VARIABLE}")
    return height, width

