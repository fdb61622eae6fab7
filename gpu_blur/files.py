"""Reading the files gpu_blur is given: regular files only, and every error names the file.

Scene files, camera files, chart references, patch tables and images are read here
(:func:`read_bytes`, :func:`read_text`, :func:`read_settings`), so that each problem is one
line that starts with the file (as the caller words it, e.g. ``scene file a.toml``) and says
what is wrong and the fix: a missing or unreadable file, one that is no regular file (a FIFO
would block forever, a device never end), text that is not UTF-8, and TOML or JSON that does
not parse, nests too deeply, or holds an integer of more than 4,300 digits.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path
from typing import BinaryIO

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["open_regular", "parse_settings", "read_bytes", "read_settings", "read_text"]

#: What a file that is not a regular one is, by its ``stat`` type, for messages.
_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def open_regular(path: str | Path, what: str) -> BinaryIO:
    """``path`` opened for reading, binary, once it is known to be a regular file.

    The file is opened without blocking and its type checked on the open descriptor, so a
    FIFO, a device or a folder is refused before anything is read from it (a FIFO without a
    writer would block forever), also when it replaced a file after an earlier check.

    Args:
        path: the file.
        what: how messages name it, e.g. ``scene file a.toml``.

    Raises:
        ValueError: ``what``, then why it cannot be read and the fix.
    """
    nonblock = getattr(os, "O_NONBLOCK", 0)  # POSIX; Windows has no FIFOs to open
    try:
        fd = os.open(path, os.O_RDONLY | nonblock | getattr(os, "O_CLOEXEC", 0)
                     | getattr(os, "O_BINARY", 0))
    except OSError as e:
        raise ValueError(f"{what}: cannot read it ({e.strerror}); check the path and its "
                         "permissions") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        kind = next((name for test, name in _KINDS if test(mode)), "no regular file")
        raise ValueError(f"{what}: is {kind}, not a regular file; give the path of a file")
    if nonblock:
        os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def read_bytes(path: str | Path, what: str) -> bytes:
    """The contents of the regular file ``path`` (:func:`open_regular`).

    Raises:
        ValueError: ``what``, then why it cannot be read and the fix.
    """
    with open_regular(path, what) as f:
        try:
            return f.read()
        except OSError as e:
            raise ValueError(f"{what}: cannot read it ({e.strerror}); check the file") from None


def read_text(path: str | Path, what: str) -> str:
    """The contents of the regular file ``path`` as UTF-8 text (:func:`read_bytes`).

    Raises:
        ValueError: ``what``, then why it cannot be read (also: not UTF-8) and the fix.
    """
    data = read_bytes(path, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise ValueError(f"{what}: not UTF-8 text (byte 0x{data[e.start]:02X} on line {line} "
                         "cannot be decoded); save the file as UTF-8") from None


def parse_settings(text: str, kind: str, what: str):
    """Parse ``text`` as ``kind`` (``"TOML"`` or ``"JSON"``).

    Raises:
        ValueError: ``what: not valid TOML: ...`` for any way the text does not parse,
            including nesting deeper than Python's recursion limit.
    """
    try:
        return json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except RecursionError:
        nested = "arrays or objects" if kind == "JSON" else "arrays or tables"
        raise ValueError(f"{what}: not valid {kind}: {nested} are nested too deeply (more "
                         f"than about {sys.getrecursionlimit()} levels); a settings file nests "
                         "a few levels: fix what wrote it") from None
    except ValueError as e:  # decode errors, and integers beyond 4,300 digits
        raise ValueError(f"{what}: not valid {kind}: {e}") from None


def read_settings(path: str | Path, what: str):
    """A TOML file's tables, or a JSON file's value for a name ending in ``.json``.

    Raises:
        ValueError: ``what``, then why the file cannot be read or parsed (:func:`read_text`,
            :func:`parse_settings`).
    """
    kind = "JSON" if Path(path).suffix.lower() == ".json" else "TOML"
    return parse_settings(read_text(path, what), kind, what)
