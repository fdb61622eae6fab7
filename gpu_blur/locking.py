"""One writer at a time: an advisory lock file that names the process holding it."""

from __future__ import annotations

import errno
import fcntl
import os
import socket
import stat
import time
from pathlib import Path


class LockHeld(ValueError):
    """Another process holds the lock; the message names it (pid, host, start)."""


def take_lock(path: Path, what: str, fix: str) -> int:
    """Lock ``path`` (created if needed) for this process; returns the open descriptor.

    ``flock`` locks belong to the open file, so the lock ends when the descriptor is closed or
    the process ends (a killed run's lock file blocks nothing); the file itself stays and
    names the last holder: ``pid <n> on <host>, started <time>``.

    Args:
        path: the lock file.
        what: what the lock guards, for the message (``--output out``).
        fix: the way out, for the message.

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
        holder = os.read(fd, 4096).decode(errors="replace").strip()
        os.close(fd)
        if e.errno not in (errno.EAGAIN, errno.EACCES):
            raise
        raise LockHeld(f"{what}: another gpu-blur run is writing it (its lock file {path} "
                       f"says: {holder or 'nothing yet'}); {fix}") from None
    os.ftruncate(fd, 0)
    started = time.strftime("%Y-%m-%d %H:%M:%S %z")
    os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}, started {started}\n".encode())
    return fd
