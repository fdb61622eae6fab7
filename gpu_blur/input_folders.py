"""Walking an input folder: its images in natural order, sets gpu-blur wrote left out.

The helpers :mod:`gpu_blur.discovery` (sequences and photos) and :mod:`gpu_blur.blurred_inputs`
(already-blurred images) find their files with.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

__all__ = ["IMAGE_SUFFIXES", "MANIFEST", "RUN", "holds_a_set", "identity", "images", "natural",
           "walk"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


#: The files that mark a folder as a set gpu-blur wrote (:class:`gpu_blur.dataset.DatasetWriter`).
MANIFEST = "manifest.jsonl"


RUN = "run.json"


def natural(name: str) -> tuple:
    """Sort key comparing runs of digits as numbers: ``2.png`` before ``10.png``.

    Names that tie as numbers (``01.png``, ``1.png``) fall back to the plain text.
    """
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def identity(path: Path | None) -> tuple[int, int] | None:
    """(device, inode) of an existing folder, else None."""
    try:
        st = os.stat(path) if path is not None else None
    except OSError:
        return None
    return (st.st_dev, st.st_ino) if st is not None else None


def walk(folder: Path, skip: tuple[int, int] | None) -> Iterator[tuple[Path, bool]]:
    """(path, is a folder) of every entry under ``folder``, depth first, in natural order.

    The folder whose :func:`identity` is ``skip`` is left out with all it holds, and so is
    every folder holding a set ``gpu-blur generate`` wrote (its :data:`MANIFEST` and
    :data:`RUN`): a set made inside the input is never read back as input. Linked folders are
    listed but not entered, and unreadable ones skipped, as ``Path.rglob`` does; a link that
    leads nowhere or into a loop of links is no folder.
    """
    try:
        with os.scandir(folder) as it:
            entries = sorted(it, key=lambda e: natural(e.name))
    except OSError:  # unreadable, or gone since it was listed
        return
    for entry in entries:
        try:
            is_dir = entry.is_dir()
        except OSError:  # a loop of links (ELOOP): no folder, and an image fails when read
            is_dir = False
        if is_dir and ((skip is not None and identity(Path(entry.path)) == skip)
                       or holds_a_set(Path(entry.path))):
            continue
        yield Path(entry.path), is_dir
        if is_dir and not entry.is_symlink():
            yield from walk(Path(entry.path), skip)


def holds_a_set(folder: Path) -> bool:
    """Whether ``folder`` holds a set ``gpu-blur generate`` wrote (a manifest and run.json)."""
    return (folder / MANIFEST).is_file() and (folder / RUN).is_file()


def images(folder: Path) -> list[Path]:
    """The images directly in ``folder``, in natural order (none when it cannot be read)."""
    try:
        paths = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    except OSError:
        return []
    return sorted(paths, key=lambda p: natural(p.name))
