"""One writer at a time: an advisory lock file that names the process holding it.

It imports and works on every platform: ``fcntl.flock`` where :mod:`fcntl` exists (Linux,
macOS, the BSDs), ``msvcrt.locking`` on Windows. Both locks end when their process does, so a
killed run's lock file blocks nothing. The lock file is removed when a holder releases it with
:func:`release_lock` and no earlier holder's line is left in it (see there for why that is
safe against a process waiting on the same file).

:mod:`filelock` would do the locking too, but not the rest: the holder's line written into
the lock file (on Windows its lock covers the bytes a second process must read to name the
holder), the refusal of a lock file that is a link, and the earlier holders' record.
"""

from __future__ import annotations

import errno
import os
import re
import socket
import stat
import time
from pathlib import Path

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None
try:
    import msvcrt
except ImportError:  # everywhere but Windows
    msvcrt = None

__all__ = ["LockHeld", "earlier_pids", "forget_earlier", "release_lock", "take_lock"]


class LockHeld(ValueError):
    """Another process holds the lock; the message names it (pid, host, start)."""


#: A holder's line in a lock file, as :func:`take_lock` writes it.
_HOLDER = re.compile(r"pid (\d+) on .*")
#: Where ``msvcrt.locking`` locks its one byte: far past the holder lines, which Windows'
#: mandatory byte-range locks would otherwise keep a second process from reading.
_WINDOWS_BYTE = 1 << 30
#: How many times :func:`take_lock` opens the file again when the one it locked was removed
#: or replaced meanwhile (each time by a holder that finished in between).
_ATTEMPTS = 100
#: The errors a lock attempt gives when another process holds the lock.
_BUSY = {errno.EAGAIN, errno.EACCES, getattr(errno, "EDEADLOCK", errno.EDEADLK)}


def _lock(fd: int) -> None:
    """Lock ``fd`` for this process without waiting (OSError, one of :data:`_BUSY`: held)."""
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    elif msvcrt is not None:
        os.lseek(fd, _WINDOWS_BYTE, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
    else:
        raise OSError(errno.ENOTSUP, "no file locking on this platform (neither fcntl nor "
                      "msvcrt), so gpu-blur cannot keep a second run out of the folder")


def _unlock(fd: int) -> None:
    """Release the lock on ``fd`` (closing it releases it too; Windows asks for this first)."""
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_UN)
    elif msvcrt is not None:
        os.lseek(fd, _WINDOWS_BYTE, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the file open as ``fd`` (not removed or replaced)."""
    try:
        named = os.stat(path, follow_symlinks=False)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (named.st_dev, named.st_ino) == (mine.st_dev, mine.st_ino)


def _open(path: Path) -> int:
    """Open (or create) the lock file ``path``; returns its descriptor.

    Raises:
        OSError: it is a link, not a regular file, or has other names.
    """
    flags = (os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as e:
        if e.errno != errno.ELOOP:
            raise
        raise OSError(errno.ELOOP, "the lock file is a symbolic link, which gpu-blur does "
                      "not write through; remove it", str(path)) from None
    info = os.fstat(fd)
    # no other name: st_nlink 0 is a file its last holder removed since (take_lock retries)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink > 1 or os.path.islink(path):
        os.close(fd)
        kind = "a hard link" if stat.S_ISREG(info.st_mode) and info.st_nlink > 1 else (
            "a symbolic link" if os.path.islink(path) else "not a regular file")
        raise OSError(errno.EPERM, f"the lock file is {kind}, which gpu-blur does not write "
                      "into; remove it", str(path))
    return fd


def take_lock(path: Path, what: str, fix: str, keep_earlier: bool = False) -> int:
    """Lock ``path`` (created if needed) for this process; returns the open descriptor.

    The lock belongs to the open file and ends when the descriptor is closed
    (:func:`release_lock`) or the process ends (a killed run's lock file blocks nothing). The
    file names the holder on its first line: ``pid <n> on <host>, started <time>``.

    Args:
        path: the lock file.
        what: what the lock guards, for the message (``--output out``).
        fix: the way out, for the message.
        keep_earlier: keep the earlier holders' lines below this one, a record of the
            processes whose temporary files may be left (:func:`earlier_pids`), until
            :func:`forget_earlier`.

    The file is opened without following a link, and must be a regular file with no other
    name (no hard link): the holder's line is written into it, so it must not be a way onto
    another file. A file locked after its last holder removed it (it was opened just before)
    is let go and ``path`` opened again, so two processes never hold two files of one name.

    Raises:
        LockHeld: another process holds it, naming that process, then ``fix``.
        OSError: the lock file cannot be created or locked, or is a link, not a regular
            file, or has other names.
    """
    for _ in range(_ATTEMPTS):
        fd = _open(path)
        try:
            _lock(fd)
        except OSError as e:
            os.lseek(fd, 0, os.SEEK_SET)
            holder = os.read(fd, 4096).decode(errors="replace").strip().split("\n")[0]
            os.close(fd)
            if e.errno not in _BUSY:
                raise
            raise LockHeld(f"{what}: another gpu-blur run is writing it (its lock file {path} "
                           f"says: {holder or 'nothing yet'}); {fix}") from None
        if _same_file(fd, path):
            break
        _unlock(fd)  # removed by the holder that just finished: lock the file there now
        os.close(fd)
    else:
        raise OSError(errno.EAGAIN, "the lock file was removed and made again each time it "
                      "was locked; try again", str(path))
    earlier = _read(fd) if keep_earlier else ""
    os.ftruncate(fd, 0)
    started = time.strftime("%Y-%m-%d %H:%M:%S %z")
    line = f"pid {os.getpid()} on {socket.gethostname()}, started {started}\n"
    _write(fd, (line + earlier).encode())
    return fd


def release_lock(fd: int, path: Path, remove: bool = True) -> None:
    """Release the lock :func:`take_lock` gave as ``fd`` on ``path``; ``remove``: the file too.

    The file stays when it still records earlier holders (:func:`earlier_pids`: their
    temporary files may be left, and the next holder removes them by that record), when
    another process has it open on Windows, or when it cannot be removed (that is no error).
    A holder that ends without this (killed, or only ``os.close(fd)``) leaves the file, which
    blocks nothing.

    Why removing it is safe: where ``fcntl`` locks, the file is removed while still locked,
    then closed. A process that opened it before may lock it only after that, and then sees
    that ``path`` no longer names the file it locked, so it opens ``path`` again
    (:func:`take_lock`): whoever locks the new file first holds it, as before. On Windows a
    file cannot be removed while another process has it open, so it is unlocked and closed
    first, then removed only if no one opened it meanwhile.
    """
    try:
        remove = remove and not earlier_pids(fd) and _same_file(fd, path)
        if remove and fcntl is not None:
            _remove(path)
    finally:
        try:
            if fcntl is None:
                _unlock(fd)
        finally:
            os.close(fd)  # with fcntl, the lock ends here: after the removal
    if remove and fcntl is None:
        _remove(path)


def _remove(path: Path) -> None:
    """Remove the lock file if it can be (Windows: not while another process has it open)."""
    try:
        os.unlink(path)
    except OSError:
        pass


def _read(fd: int) -> str:
    """The lock file ``fd`` as text (its first 64 KiB), each line ending with a newline."""
    os.lseek(fd, 0, os.SEEK_SET)
    text = os.read(fd, 1 << 16).decode(errors="replace")
    return "".join(line + "\n" for line in text.splitlines())


def _write(fd: int, data: bytes) -> None:
    """Write ``data`` at the start of the lock file ``fd``."""
    os.lseek(fd, 0, os.SEEK_SET)
    while data:
        data = data[os.write(fd, data):]


def earlier_pids(fd: int) -> set[int]:
    """The process ids of the earlier holders :func:`take_lock` kept below this one's line."""
    lines = _read(fd).splitlines()[1:]
    return {int(m[1]) for m in map(_HOLDER.fullmatch, lines) if m}


def forget_earlier(fd: int) -> None:
    """Keep only this holder's line (the earlier holders' temporary files are gone)."""
    os.lseek(fd, 0, os.SEEK_SET)
    data = os.read(fd, 1 << 16)
    os.ftruncate(fd, data.find(b"\n") + 1 if b"\n" in data else len(data))
