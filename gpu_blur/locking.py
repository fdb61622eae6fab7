"""One writer at a time: an advisory lock file that names the process holding it."""

from __future__ import annotations

import errno
import fcntl
import os
import re
import socket
import stat
import time
from pathlib import Path


class LockHeld(ValueError):
    """Another process holds the lock; the message names it (pid, host, start)."""


#: A holder's line in a lock file, as :func:`take_lock` writes it.
_HOLDER = re.compile(r"pid (\d+) on .*")


def take_lock(path: Path, what: str, fix: str, keep_earlier: bool = False) -> int:
    """Lock ``path`` (created if needed) for this process; returns the open descriptor.

    ``flock`` locks belong to the open file, so the lock ends when the descriptor is closed or
    the process ends (a killed run's lock file blocks nothing); the file itself stays and
    names the last holder first: ``pid <n> on <host>, started <time>``.

    Args:
        path: the lock file.
        what: what the lock guards, for the message (``--output out``).
        fix: the way out, for the message.
        keep_earlier: keep the earlier holders' lines below this one, a record of the
            processes whose temporary files may be left (:func:`earlier_pids`), until
            :func:`forget_earlier`.

    The file is opened without following a link, and must be a regular file with no other
    name (no hard link): the holder's line is written into it, so it must not be a way onto
    another file.

    Raises:
        LockHeld: another process holds it, naming that process, then ``fix``.
        OSError: the lock file cannot be created or locked, or is a link, not a regular
            file, or has other names.
    """
    flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as e:
        if e.errno != errno.ELOOP:
            raise
        raise OSError(errno.ELOOP, "the lock file is a symbolic link, which gpu-blur does "
                      "not write through; remove it", str(path)) from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
        os.close(fd)
        kind = "a hard link" if stat.S_ISREG(info.st_mode) else "not a regular file"
        raise OSError(errno.EPERM, f"the lock file is {kind}, which gpu-blur does not write "
                      "into; remove it", str(path))
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        holder = os.read(fd, 4096).decode(errors="replace").strip().split("\n")[0]
        os.close(fd)
        if e.errno not in (errno.EAGAIN, errno.EACCES):
            raise
        raise LockHeld(f"{what}: another gpu-blur run is writing it (its lock file {path} "
                       f"says: {holder or 'nothing yet'}); {fix}") from None
    earlier = _read(fd) if keep_earlier else ""
    os.ftruncate(fd, 0)
    started = time.strftime("%Y-%m-%d %H:%M:%S %z")
    line = f"pid {os.getpid()} on {socket.gethostname()}, started {started}\n"
    os.pwrite(fd, (line + earlier).encode(), 0)
    return fd


def _read(fd: int) -> str:
    """The lock file ``fd`` as text (its first 64 KiB), each line ending with a newline."""
    text = os.pread(fd, 1 << 16, 0).decode(errors="replace")
    return "".join(line + "\n" for line in text.splitlines())


def earlier_pids(fd: int) -> set[int]:
    """The process ids of the earlier holders :func:`take_lock` kept below this one's line."""
    lines = _read(fd).splitlines()[1:]
    return {int(m[1]) for m in map(_HOLDER.fullmatch, lines) if m}


def forget_earlier(fd: int) -> None:
    """Keep only this holder's line (the earlier holders' temporary files are gone)."""
    data = os.pread(fd, 1 << 16, 0)
    os.ftruncate(fd, data.find(b"\n") + 1 if b"\n" in data else len(data))
