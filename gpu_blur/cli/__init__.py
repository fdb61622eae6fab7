"""The ``gpu-blur`` command: one module per subcommand, each with ``add_parser`` and ``run``.

``generate`` (:mod:`.generate`) runs :func:`gpu_blur.generate_set`; ``plan``, ``devices``,
``scene``, ``cameras``, ``bench``, ``compare``, ``align``, ``calibrate`` and ``validate``
each have a module of that name; :mod:`.common` holds what several share.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

from gpu_blur import __version__

__all__ = ["COMMANDS", "EPILOG", "main"]

EPILOG = """examples:
  gpu-blur generate --output out/                      # built-in photo, camera shake
  gpu-blur generate --input RSBlur --output out/ --scene rsblur   # 9 sharp frames averaged
  gpu-blur plan realblur_j.toml                        # which stages a scene runs, and why
  gpu-blur calibrate --chart patches.csv --output my_camera.toml   # a camera from a chart
  gpu-blur scene                                       # every scene key with its default
  gpu-blur compare real.png synth.png --interp interp.png --json scores.json
  gpu-blur align real.png avg.png seq/*.png --output aligned/   # ECC, then warp the frames

exit status of generate: 0 all samples made; 1 some samples failed (each is in the manifest
with "status": "failed" and why; fix them and rerun with --resume); 2 nothing could start
(bad option, scene, input folder or output folder)
"""

#: The subcommands, in the order ``gpu-blur --help`` lists them: each a module of this package.
COMMANDS = ("generate", "plan", "devices", "scene", "cameras", "bench", "compare", "align",
            "calibrate", "validate")


def _command(name: str):
    return importlib.import_module(f"gpu_blur.cli.{name}")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="gpu-blur", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Realistic motion-blur synthesis (RSBlur, Rim et al. ECCV 2022).")
    p.add_argument("--version", action="version", version=f"gpu_blur {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        _command(name).add_parser(sub)
    return p


def _open_standard_streams() -> None:
    """Make closed standard streams (``gpu-blur ... >&- 2>&-``) ``/dev/null``.

    A closed descriptor 0, 1 or 2 would be taken by the next file opened (a sample, the
    manifest), which messages and worker processes would then write into; and Python sets
    ``sys.stdout`` or ``sys.stderr`` to None, on which the progress bar fails.
    """
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:  # closed: the lowest free descriptor, this one, becomes /dev/null
            os.open(os.devnull, os.O_RDWR)
    if sys.stdout is None:
        sys.stdout = open(os.devnull, "w")  # for the process's life
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")



def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpu-blur``; returns the exit status."""
    _open_standard_streams()
    args = _parser().parse_args(argv)
    try:
        return _command(args.command).run(args)
    except BrokenPipeError:  # the reader left (gpu-blur cameras | head -1): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except (ValueError, OSError, RuntimeError) as e:
        print(f"gpu-blur: error: {e}", file=sys.stderr)
        return 2
    except MemoryError as e:  # inputs too large for this machine, outside any one sample
        print(f"gpu-blur: error: out of memory ({str(e) or 'no detail'}): use smaller inputs "
              "or free memory", file=sys.stderr)
        return 2
