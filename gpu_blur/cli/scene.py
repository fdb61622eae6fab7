"""``gpu-blur scene``: the default scene as TOML, every key with its meaning and range."""

from __future__ import annotations

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """The subcommand (no options)."""
    sub.add_parser("scene", help="print the default scene as TOML: every key with its default, "
                   "meaning and range (gpu-blur scene > my.toml, then --scene my.toml)")


def run(args) -> int:
    """Print the default scene."""
    from gpu_blur.scene import describe_fields

    print(describe_fields())
    return 0
