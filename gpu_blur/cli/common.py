"""What several subcommands share: --quiet/--verbose, reading images, refusing to overwrite."""

from __future__ import annotations

import argparse
import contextlib
import os
from pathlib import Path

__all__ = ["read_unit", "refuse_writing_over_inputs", "same_size", "verbosity",
           "verbosity_arguments"]


def verbosity_arguments(p: argparse.ArgumentParser) -> None:
    """--quiet / --verbose: how much the command says on stderr besides errors."""
    said = p.add_mutually_exclusive_group()
    said.add_argument("--quiet", action="store_true", help="no progress bar and no notices "
                      "(the device line, errors and the summary remain)")
    said.add_argument("--verbose", action="store_true", help="also each kernel build's time "
                      "(by default one line per device says when kernels compile on first "
                      "use)")


def verbosity(args) -> int:
    """The notice level (:mod:`gpu_blur.notices`) that --quiet / --verbose ask for."""
    from gpu_blur import notices

    return (notices.QUIET if args.quiet else notices.VERBOSE if args.verbose
            else notices.NORMAL)


def refuse_writing_over_inputs(option: str, outputs, inputs, fix: str) -> None:
    """Refuse a command whose output file is one of its inputs, before any work.

    Args:
        option: the option that places the outputs (``--json``, ``--output DIR``).
        outputs: the paths the command may write.
        inputs: ``(role, path)`` of the files it reads (``("REAL", Path("real.png"))``).
        fix: what to do instead.

    The same file is found by device and inode (:func:`os.path.samefile`), so a symbolic or
    hard link to an input counts; an output that does not exist yet is no input.

    Raises:
        ValueError: naming the option, the output, the input and ``fix``.
    """
    files = {}
    for role, path in inputs:
        with contextlib.suppress(OSError):  # a missing input is refused when it is read
            st = os.stat(path)
            files.setdefault((st.st_dev, st.st_ino), (role, path))
    for out in outputs:
        try:
            st = os.stat(out)
        except OSError:
            continue
        if (st.st_dev, st.st_ino) in files:
            role, path = files[st.st_dev, st.st_ino]
            raise ValueError(f"{option}: it would write {out}, which is {role} {path} (the same "
                             f"file): the command would destroy its own input; {fix}")



def read_unit(path: Path, role: str):
    """An image file as float64 sRGB values in [0, 1], H x W x 3; errors name the role."""
    from gpu_blur.image_arrays import to_unit
    from gpu_blur.image_reading import read_image

    try:
        return to_unit(read_image(path), str(path))
    except ValueError as e:
        raise ValueError(f"{role} {e}") from None


def same_size(a, a_name: str, b, b_name: str, fix: str) -> None:
    """Refuse two images of different sizes, naming both sizes and the way out."""
    if a.shape[:2] != b.shape[:2]:
        raise ValueError(f"{a_name} is {a.shape[0]} x {a.shape[1]} (H x W) but {b_name} is "
                         f"{b.shape[0]} x {b.shape[1]}; {fix}")

