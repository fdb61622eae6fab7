"""Made samples from ``--devices`` workers to the driver through shared memory, not the pipe.

A device worker (:mod:`gpu_blur.distributed`) used to pickle each made sample through its
pipe: a 1920 x 1200 sample is 14 MB of 8-bit codes, and the driver's one receiving thread took
31 samples/s (0.43 GB/s) however many workers sent them. Now the worker writes the sample's
arrays into a block of shared memory, and its pipe carries a small message: the rest of the
:class:`~gpu_blur.synthesis.Synthesis` (params, plan, timings: a few KB) and a :class:`Layout`
(the block's name, each array's byte offset, shape and dtype). The driver copies the arrays
out of the block (:meth:`Blocks.receive`: one memcpy per array, in the thread that receives,
numpy releasing the GIL), so it holds the same Synthesis, bytes identical, and gives the block
back to the worker at once.

The arrays (:data:`FIELDS`, what :func:`gpu_blur.generate.for_driver` leaves): blurred and
sharp, H x W x 3 in the set's codes (uint8 or uint16; float32 with ``output.bits = 0``); the
mask, H x W x 3 float32 in [0, 1], when the set saves it; the RAW mosaic, H x W float32, with
``--save raw``. A failed sample has none and goes through the pipe, as a small message.

Ownership: the driver (:class:`Blocks`) makes every block, when a worker asks for one, and
unlinks all of them when the run ends, however it ends (finished, Ctrl-C, an error, its
generator closed, a worker killed; else when the Blocks object is collected or Python exits);
a worker (:class:`Outbox`) only attaches and writes, so a worker killed mid-run leaves nothing
behind. A worker holds at most :data:`BLOCKS_PER_WORKER` blocks, each the size of a sample it
made, and waits for one to come back before it writes the next sample: with the pipe's
back-pressure gone, that is what bounds the memory of results in flight. A driver killed by
SIGKILL cannot unlink: its workers, which exit within a second, unlink the blocks they hold
(:meth:`Outbox.abandon`) and multiprocessing's resource tracker any other one.

Resource tracker (POSIX): making a block registers its name with the tracker, and attaching
does too (always before Python 3.13, by default since). Spawned workers share the driver's
tracker, which keeps a set of names: a worker's attach re-registers the driver's own name, and
the one unlink (which unregisters it) leaves the tracker nothing to clean or warn about.
Nothing here unregisters a name twice (the tracker would print a KeyError).

Portability: :mod:`multiprocessing.shared_memory`, no /dev/shm path. On Windows a block
lives while a handle to it is open: the driver holds one until it unlinks. Where
``os.posix_fallocate`` exists (Linux) a block's pages are allocated as it is made, so a /dev/shm
too small for it (a Docker container's is 64 MB unless ``--shm-size`` says more) is refused
there, not met as SIGBUS in the worker writing to it. Refused, the driver makes the block as an
anonymous file instead where the system has ``memfd_create`` (Linux, :class:`MemfdBlock`: no
name, its descriptor passed to the worker through the pipe, gone with the last descriptor, so
nothing to unlink, and its pages count against memory, not /dev/shm); where that fails too, a
worker sends its samples through the pipe, as before (slower: the summary counts them).

Messages, besides those of :mod:`gpu_blur.distributed`:

* worker to driver: ``(ASK, (bytes, retired))``: a block of at least ``bytes``, the worker
  giving back ``retired`` (one too small; None for none);
* driver to worker: ``(GRANT, (name, bytes))``, or ``(GRANT, (None, why))`` when no block can be
  made; a :class:`MemfdBlock`'s grant is followed at once by its file descriptor
  (:func:`multiprocessing.reduction.send_handle`); ``(FREE, name)``: the driver has copied
  the sample out of block ``name``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import mmap
import os
import sys
import weakref
from collections.abc import Callable
from multiprocessing import reduction
from multiprocessing.shared_memory import SharedMemory

import numpy as np

from gpu_blur import notices

__all__ = ["ALIGN", "ASK", "BLOCKS_PER_WORKER", "FIELDS", "FREE", "GRAIN", "GRANT", "MEMFD",
           "Blocks", "Layout", "MemfdBlock", "Outbox", "send"]

ASK, GRANT, FREE = "block?", "block", "free"
#: Blocks a worker may hold: one the driver copies a sample out of while the worker writes the
#: next one into the other.
BLOCKS_PER_WORKER = 2
#: The :class:`~gpu_blur.synthesis.Synthesis` fields that go through a block (mask and raw
#: are ``_mask`` and ``_raw`` there).
FIELDS = ("blurred", "sharp", "_mask", "_raw")
#: Bytes each array's offset in a block is a multiple of.
ALIGN = 64
#: Bytes a block's size is a multiple of.
GRAIN = 1 << 16
#: Whether a block /dev/shm has no room for may be an anonymous file (:class:`MemfdBlock`):
#: Linux, whose pipes between processes are sockets that can pass a file descriptor.
MEMFD = sys.platform == "linux" and hasattr(os, "memfd_create")


class MemfdBlock:
    """A block of shared memory in an anonymous file (``memfd_create``), where /dev/shm is full.

    It has a name only for the messages (``memfd-<pid>-<n>``): the driver sends the worker its
    file descriptor through the pipe, and the memory is freed once every descriptor and mapping
    of it is closed, by whichever process ends last. Its pages are taken when it is made
    (``posix_fallocate``), so a host without the memory says so then. The attributes the
    module uses of a :class:`SharedMemory`: ``name``, ``buf``, :meth:`close`, :meth:`unlink`.
    """

    _made = itertools.count()

    def __init__(self, fd: int, size: int, name: str):
        """Map ``fd``, which the block owns from now on (closed here if it cannot be mapped)."""
        self.name, self.size, self._fd = name, size, fd
        self.buf: memoryview | None = None
        try:
            self._mmap = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            raise
        self.buf = memoryview(self._mmap)

    @classmethod
    def create(cls, size: int) -> MemfdBlock:
        """A new block of ``size`` bytes, its pages taken. OSError where there is no room."""
        fd = os.memfd_create("gpu-blur-results", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, size)
            os.posix_fallocate(fd, 0, size)
        except BaseException:
            os.close(fd)
            raise
        return cls(fd, size, f"memfd-{os.getpid()}-{next(cls._made)}")

    @staticmethod
    def named(name: str) -> bool:
        """Whether a granted block's ``name`` is a MemfdBlock's (its descriptor follows)."""
        return name.startswith("memfd-")

    def fileno(self) -> int:
        """Its file descriptor."""
        return self._fd

    def close(self) -> None:
        """Unmap it and close its descriptor; BufferError while arrays over it live."""
        if self.buf is None:
            return
        self.buf.release()  # BufferError if any array still uses it: nothing closed
        self.buf = None
        self._mmap.close()
        os.close(self._fd)

    def unlink(self) -> None:
        """Nothing: an anonymous file goes with its last descriptor."""

    def __del__(self):  # as SharedMemory's: a block dropped on an error path is closed too
        with contextlib.suppress(BufferError, OSError, AttributeError):
            self.close()


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where a sample's arrays lie in a block.

    Attributes:
        block: the block's name.
        arrays: per array, ``(field, byte offset, shape, dtype)``: a :data:`FIELDS` name, the
            offset (a multiple of :data:`ALIGN`), the shape and the dtype's string (``|u1``,
            ``<u2``, ``<f4``); C order.
    """

    block: str
    arrays: tuple[tuple[str, int, tuple[int, ...], str], ...]


def _arrays(result) -> dict[str, np.ndarray]:
    """A result's arrays by field, the mask and the mosaic on the host, absent ones left out."""
    found = {"blurred": result.blurred, "sharp": result.sharp, "_mask": result.mask,
             "_raw": result.raw}
    return {field: np.asarray(a) for field, a in found.items() if a is not None}


def _offsets(arrays: dict[str, np.ndarray]) -> tuple[dict[str, int], int]:
    """Each array's byte offset in a block, and the bytes all of them need (at least 1)."""
    offsets, end = {}, 0
    for field, array in arrays.items():
        offsets[field] = end
        end += -(-array.nbytes // ALIGN) * ALIGN
    return offsets, max(end, 1)


def send(conn, message) -> None:
    """Send ``message``; EOFError when the other end is closed (its process gone)."""
    try:
        conn.send(message)
    except OSError:
        raise EOFError("the other end of the pipe is closed") from None


class Outbox:
    """A device worker's side: its made samples written into blocks the driver makes.

    Args:
        conn: the worker's end of its pipe.
        other: called with each message from the driver that is not about blocks (a sample
            to make) and comes while :meth:`pack` waits for a block.
    """

    def __init__(self, conn, other: Callable[[object], None]):
        self._conn, self._other = conn, other
        self._blocks: dict[str, SharedMemory] = {}
        self._sizes: dict[str, int] = {}  # bytes the driver made each block with
        self._free: list[str] = []  # blocks the driver has copied out of
        self._granted: tuple | None = None
        #: Why no block is to be had (then every sample goes through the pipe), or None.
        self.refused: str | None = None

    def take(self, message) -> bool:
        """Take the driver's message if it is about blocks (True); False for any other."""
        if not (isinstance(message, tuple) and len(message) == 2
                and message[0] in (GRANT, FREE)):
            return False
        kind, value = message
        if kind == FREE:
            self._free.append(value)
        else:
            self._granted = value
        return True

    def pack(self, result):
        """``result`` for the driver: ``(shell, layout)``, or ``(result, None)`` for the pipe.

        ``result``'s arrays are written into a block, at ``layout``; ``shell`` is the rest
        (those fields None). With no result, or no block to be had, it goes whole through the
        pipe. While both blocks are in use, this waits for one to come back.

        Raises:
            EOFError: the driver is gone.
        """
        if result is None or self.refused is not None:
            return result, None
        arrays = _arrays(result)
        offsets, need = _offsets(arrays)
        name = self._block(need)
        if name is None:
            return result, None
        buffer = self._blocks[name].buf
        for field, array in arrays.items():
            np.copyto(np.ndarray(array.shape, array.dtype, buffer, offsets[field]), array,
                      casting="no")
        layout = Layout(name, tuple((field, offsets[field], array.shape, array.dtype.str)
                                    for field, array in arrays.items()))
        return dataclasses.replace(result, **dict.fromkeys(FIELDS)), layout

    def _block(self, need: int) -> str | None:
        """A free block of at least ``need`` bytes, asked for if none fits; None: refused."""
        while True:
            fits = [name for name in self._free if self._sizes[name] >= need]
            if fits:
                name = min(fits, key=self._sizes.__getitem__)
                self._free.remove(name)
                return name
            if len(self._blocks) < BLOCKS_PER_WORKER:
                return self._ask(need, None)
            if self._free:  # too small: give the smallest back for a bigger one
                retired = min(self._free, key=self._sizes.__getitem__)
                self._free.remove(retired)
                self._close(retired)
                return self._ask(need, retired)
            self._wait(lambda: self._free)

    def _ask(self, need: int, retired: str | None) -> str | None:
        self._granted = None
        send(self._conn, (ASK, (-(-need // GRAIN) * GRAIN, retired)))
        self._wait(lambda: self._granted is not None)
        name, detail = self._granted
        if name is None:
            self.refused = detail
            return None
        try:
            if MemfdBlock.named(name):  # its descriptor comes right after the grant
                block = MemfdBlock(reduction.recv_handle(self._conn), detail, name)
            else:
                block = SharedMemory(name)
        except OSError as e:  # the driver unlinks it at the end
            self.refused = f"cannot open shared memory block {name}: {e}"
            return None
        self._blocks[name], self._sizes[name] = block, detail
        return name

    def _wait(self, ready: Callable[[], object]) -> None:
        while not ready():
            message = self._conn.recv()  # EOFError: the driver is gone
            if not self.take(message):
                self._other(message)

    def _close(self, name: str) -> None:
        self._sizes.pop(name, None)
        block = self._blocks.pop(name, None)
        if block is not None:
            with contextlib.suppress(BufferError):
                block.close()

    def close(self) -> None:
        """Unmap every block (the driver unlinks them)."""
        for name in list(self._blocks):
            self._close(name)

    def abandon(self) -> None:
        """Unlink the blocks this worker holds: its driver is gone (killed) and cannot."""
        with contextlib.suppress(Exception):  # another thread may be changing them
            for block in list(self._blocks.values()):
                with contextlib.suppress(OSError):
                    block.unlink()


class Blocks:
    """The driver's side: makes the blocks its workers ask for, copies samples out of them.

    Every block it made is unlinked at :meth:`close`, or when the object is collected or
    Python exits, whichever comes first.
    """

    def __init__(self):
        self._made: dict[str, SharedMemory | MemfdBlock] = {}
        self._finalizer = weakref.finalize(self, _unlink_all, self._made)
        #: Why a block could not be made (the workers then use the pipe), or None.
        self.refused: str | None = None
        #: Why /dev/shm refused a block (later ones are anonymous files), or None.
        self.shm_refused: str | None = None

    def __len__(self) -> int:
        """Blocks made and not yet unlinked."""
        return len(self._made)

    def answer(self, conn, need: int, retired: str | None) -> None:
        """Answer a worker's ASK on its ``conn``: a new block of ``need`` bytes, or why none.

        ``retired`` (the worker's block too small) is unlinked first. A worker gone is no
        error here (its next message says so).
        """
        if retired is not None:
            _unlink(self._made.pop(retired, None))
        handle = None  # an anonymous block's descriptor, sent after the grant
        try:
            block = self._make(need)
        except (OSError, ValueError) as e:
            reply = (None, f"{type(e).__name__}: {e}")
            if self.refused is None and notices.verbosity() >= notices.NORMAL:
                notices.say(f"--devices: no shared memory for results ({reply[1]}); they go "
                            "through the workers' pipes, slower")
            self.refused = reply[1]
        else:
            reply = (block.name, need)
            if isinstance(block, MemfdBlock):
                handle = block.fileno()
        with contextlib.suppress(EOFError):
            send(conn, (GRANT, reply))
            if handle is not None:
                try:
                    reduction.send_handle(conn, handle, None)
                except OSError:  # the worker is gone: its next message says so
                    pass

    def _make(self, size: int) -> SharedMemory | MemfdBlock:
        if self.shm_refused is None:
            try:
                return self._make_shm(size)
            except (OSError, ValueError) as e:
                if not MEMFD:
                    raise
                self.shm_refused = f"{type(e).__name__}: {e}"
                if notices.verbosity() >= notices.NORMAL:
                    notices.say(f"--devices: /dev/shm has no room for results "
                                f"({self.shm_refused}); anonymous shared memory instead")
        block = MemfdBlock.create(size)
        self._made[block.name] = block
        return block

    def _make_shm(self, size: int) -> SharedMemory:
        block = SharedMemory(create=True, size=size)
        self._made[block.name] = block
        fd = getattr(block, "_fd", -1)  # POSIX: the shm_open descriptor
        if fd >= 0 and hasattr(os, "posix_fallocate"):
            try:  # take the pages now: a full /dev/shm says so here, not by SIGBUS later
                os.posix_fallocate(fd, 0, size)
            except OSError:
                _unlink(self._made.pop(block.name))
                raise
        return block

    def receive(self, conn, shell, layout: Layout):
        """The sample a worker wrote at ``layout``: ``shell`` with its arrays.

        They are copied out of the block (C order, writable), which then goes back to the
        worker on ``conn`` (FREE).
        """
        buffer = self._made[layout.block].buf
        arrays = {field: np.ndarray(shape, dtype, buffer, offset).copy()
                  for field, offset, shape, dtype in layout.arrays}
        with contextlib.suppress(EOFError):  # a worker gone: its next message says so
            send(conn, (FREE, layout.block))
        return dataclasses.replace(shell, **arrays)

    def close(self) -> None:
        """Unlink and unmap every block made (again: nothing)."""
        self._finalizer()


def _unlink(block: SharedMemory | None) -> None:
    """Unlink a block (unregistering it from the resource tracker) and unmap it."""
    if block is None:
        return
    with contextlib.suppress(OSError):  # FileNotFoundError: a worker unlinked it (abandon)
        block.unlink()
    with contextlib.suppress(BufferError):
        block.close()


def _unlink_all(made: dict[str, SharedMemory]) -> None:
    while made:
        _unlink(made.popitem()[1])
