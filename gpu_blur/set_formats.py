"""A set's samples in an LMDB (BasicSR's paired convention) or in WebDataset tar shards.

``gpu-blur generate --format`` picks how the pairs are stored; every format holds the bytes
the PNG set's files hold (:meth:`gpu_blur.dataset.DatasetWriter.save` encodes once, for any
format) beside the same ``manifest.jsonl`` and ``run.json``, and keeps its guarantees: one
writer per folder (the lock), nothing half-written where a finished sample is looked for,
the manifest in sample order, and ``--resume`` keeping finished samples and remaking the
others into what an uninterrupted run writes.

**lmdb** follows BasicSR (``XPixelGroup/BasicSR``, ``basicsr/utils/lmdb_util.py``,
``make_lmdb_from_imgs``; ``basicsr/data/data_util.py``, ``paired_paths_from_lmdb``):
``blur.lmdb/`` and ``sharp.lmdb/`` are LMDB environments (``data.mdb``, ``lock.mdb``) holding
each image PNG-encoded under the ASCII key of its name without extension, with a
``meta_info.txt`` of lines ``<key>.png (h,w,c) <compression level>``; BasicSR's paired data
set (``basicsr/data/paired_image_dataset.py``, ``io_backend: {type: lmdb}``) takes
``dataroot_lq: blur.lmdb`` and ``dataroot_gt: sharp.lmdb``, requires both folders to end in
``.lmdb`` and both meta_info key lists to be equal, and pairs the same key in both (it
splits each meta_info line at its first dot, so keys hold none). ``mask.lmdb`` (with a
meta_info.txt), ``params.lmdb`` (the ``.npz`` arrays) and ``raw.lmdb`` (the DNGs) hold the
other outputs under the same key. Each sample goes in with one transaction per environment,
committed before its manifest line is written: a sample is in (its line written) or out. A
resume deletes the keys of samples no kept line lists before making them again, and
``meta_info.txt`` is rewritten, whole, when a run opens and when it closes the set, listing
the finished samples in index order (a killed run's is brought up to date by ``--resume``).
The LMDB files themselves are not byte-for-byte those of another run (LMDB places pages by
its transaction history); their keys and values are.

**webdataset** writes tar shards ``shard-000000.tar``, ``shard-000001.tar``, ... of
``--shard-size`` consecutive samples (shard ``k`` holds samples ``k * size`` to ``(k + 1) *
size - 1``, those that did not fail), each sample as the members ``<key>.blur.png``,
``<key>.sharp.png``, ``<key>.params.npz`` (arrays, where the sample has them),
``<key>.mask.png``, ``<key>.raw.dng`` (with ``--save``) and ``<key>.json`` (its manifest
line without file names and sizes). WebDataset groups a tar's consecutive members into a
sample by the member name up to the first dot of its last path component (``webdataset``'s
``tariterators.base_plus_ext``), so keys hold no dot. A shard is written under a temporary
name and renamed once its last sample is in: a finished shard is whole, and an unfinished
one never looks finished. A resume redoes the samples of unfinished shards, and rewrites a
finished shard whose failed samples it makes again (its other samples copied over, byte for
byte). The members' metadata is fixed (mtime 0, mode 0444, uid and gid 0, no user or group
name, POSIX pax format), so a seed gives the same shard bytes in any run, resumed or not.

The key of sample ``index`` named ``name`` is the PNG set's file stem ``NNNNNN_<name>``
(:func:`gpu_blur.dataset._stem`) with every character but ASCII letters, digits, ``_`` and
``-`` as ``_``: unique by its index, ASCII as BasicSR encodes keys, and without dots.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import tarfile
from pathlib import Path

from gpu_blur.dataset import _PROBE, _TEMPORARY, PATHS, SUBFOLDERS, DatasetWriter, _stem
from gpu_blur.file_writing import temporary_path, write_new, write_text

__all__ = ["DEFAULT_FORMAT", "DEFAULT_SHARD_SIZE", "FORMATS", "LMDB_FOLDERS", "META_INFO",
           "LmdbWriter", "PngWriter", "SetWriter", "ShardWriter", "check_format", "format_record",
           "png_level", "png_shape", "sample_key", "shard_name", "writer"]

#: ``--format``: how a set stores its samples.
FORMATS = {
    "png": "blur/, sharp/ (and params/, mask/, raw/) of files, one per output",
    "lmdb": "blur.lmdb, sharp.lmdb (BasicSR's paired LMDB; mask, params, raw beside them)",
    "webdataset": "tar shards shard-NNNNNN.tar of --shard-size samples (WebDataset)",
}
DEFAULT_FORMAT = "png"
#: ``--shard-size``' default: samples a WebDataset shard holds. 1280 x 720 8-bit pairs take
#: about 3 to 5 MB a sample, so 100 of them make shards of a few hundred MB, the size
#: WebDataset's readers stream well.
DEFAULT_SHARD_SIZE = 100
#: Characters a key keeps; any other becomes ``_``.
_KEY_UNSAFE = re.compile(r"[^A-Za-z0-9_-]")
#: A key this module writes (:func:`sample_key`).
_KEY = re.compile(r"\d{6,}_[A-Za-z0-9_-]*")


def sample_key(index: int, name: str) -> str:
    """The LMDB key and WebDataset key of sample ``index`` named ``name`` (module docstring)."""
    return _KEY_UNSAFE.sub("_", _stem(index, name))


def check_format(format: str, shard_size: int | None, bits: int) -> None:
    """Refuse a format the set cannot be written in, before anything is made.

    Args:
        format: ``--format``.
        shard_size: ``--shard-size`` (None: not given).
        bits: the scene's ``output.bits``.

    Raises:
        ValueError: an unknown format, a shard size below 1 or without ``webdataset``,
            ``lmdb`` with float TIFF output or without the ``lmdb`` package; one line each.
    """
    if format not in FORMATS:
        raise ValueError(f"--format {format}: unknown; choose one of {', '.join(FORMATS)}")
    if shard_size is not None:
        if format != "webdataset":
            raise ValueError(f"--shard-size {shard_size}: only --format webdataset writes "
                             f"shards (this run: --format {format}); drop --shard-size or "
                             "pass --format webdataset")
        if shard_size < 1:
            raise ValueError(f"--shard-size {shard_size}: samples per shard, must be >= 1")
    if format == "lmdb":
        if bits == 0:
            raise ValueError("--format lmdb: the scene's output.bits = 0 writes float32 TIFF, "
                             "but BasicSR's LMDB holds PNG images (meta_info.txt names "
                             "<key>.png); set output.bits = 8 or 16, or use --format png or "
                             "webdataset")
        _lmdb("--format lmdb")


def format_record(format: str, shard_size: int | None) -> dict:
    """What run.json records of the format: nothing for PNG (as sets made before it)."""
    if format == "png":
        return {}
    if format == "webdataset":
        return {"format": format, "shard_size": shard_size or DEFAULT_SHARD_SIZE}
    return {"format": format}


def writer(format: str, shard_size: int | None = None):
    """The writer class of ``format``, as a callable taking DatasetWriter's arguments."""
    if format == "lmdb":
        return LmdbWriter
    if format == "webdataset":
        size = shard_size or DEFAULT_SHARD_SIZE
        return lambda *args, **kwargs: ShardWriter(*args, shard_size=size, **kwargs)
    return PngWriter


def _foreign(out: Path, others: list[str], what: str) -> ValueError:
    more = f" and {len(others) - 5} more" if len(others) > 5 else ""
    return ValueError(f"--output {out}: {', '.join(others[:5])}{more}: not {what} gpu-blur "
                      "wrote; a set's folders and containers hold only its own samples "
                      "(gpu-blur replaces and removes those), so move these out, or choose "
                      "another --output")


def _temporary_of(entry: Path, earlier, finals) -> bool:
    """Whether ``entry`` is a temporary file a run of ``earlier`` wrote for one of ``finals``."""
    match = _TEMPORARY.fullmatch(entry.name)
    return bool(match and int(match[2]) in earlier and not entry.is_symlink()
                and entry.is_file() and finals(match[1]))


def _new_file(path: Path):
    """``path`` opened as a new regular file for writing (the flags of ``write_new``)."""
    path.unlink(missing_ok=True)
    flags = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
    return os.fdopen(os.open(path, flags, 0o666), "wb")


def _record(line: dict) -> bytes:
    """A sample's ``<key>.json``: its manifest line without file names and sizes."""
    kept = {k: v for k, v in line.items() if k not in PATHS and k not in ("bytes", "key")}
    return (json.dumps(kept) + "\n").encode()


# -- LMDB ----------------------------------------------------------------------------------------
#: The environment of each output, by manifest key.
LMDB_FOLDERS = {"blurred": "blur.lmdb", "sharp": "sharp.lmdb", "arrays": "params.lmdb",
                "mask": "mask.lmdb", "raw": "raw.lmdb"}
#: Outputs whose environment has a meta_info.txt (images).
_IMAGES = ("blurred", "sharp", "mask")
META_INFO = "meta_info.txt"
_LMDB_FILES = ("data.mdb", "lock.mdb", META_INFO)
#: An environment's first map size; it doubles whenever a sample does not fit.
_MAP_SIZE = 1 << 28
#: PNG colour type -> channels (PNG specification, 11.2.1).
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}


def png_shape(png) -> tuple[int, int, int]:
    """(height, width, channels) of a PNG's bytes, from its IHDR chunk (PNG spec, 11.2.2)."""
    data = bytes(png[:26])
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return height, width, _CHANNELS.get(data[25], 3)


def png_level(mode: str, bits: int) -> int:
    """The zlib level of a ``bits``-bit PNG written in ``mode`` (``png_codecs.PNG_MODES``).

    meta_info.txt's last column, as BasicSR writes the ``compress_level`` it encoded with
    (its readers do not read it): 0 for ``stored`` (no compression), 6 for 16-bit ``small``,
    else 1.
    """
    return 0 if mode == "stored" else 6 if mode == "small" and bits == 16 else 1


# -- WebDataset ----------------------------------------------------------------------------------
#: A shard's file name.
_SHARD = re.compile(r"shard-(\d{6,})\.tar")
#: A member's extension, by manifest key (images: bits 0 writes TIFF).
_MEMBERS = {"blurred": "blur", "sharp": "sharp", "arrays": "params.npz", "mask": "mask.png",
            "raw": "raw.dng"}


def shard_name(number: int) -> str:
    """The file name of shard ``number``."""
    return f"shard-{number:06d}.tar"


def _member_info(name: str, size: int) -> tarfile.TarInfo:
    """A member's header: fixed metadata, so equal samples give equal shard bytes."""
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode, info.type = size, 0, 0o444, tarfile.REGTYPE
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    return info


class _OpenShard:
    """The shard being written: its number, temporary file and tar stream."""

    def __init__(self, out: Path, number: int):
        self.number, self.final = number, out / shard_name(number)
        self.temporary = temporary_path(self.final)
        self.file = _new_file(self.temporary)
        self.tar = tarfile.open(fileobj=self.file, mode="w", format=tarfile.PAX_FORMAT)

    def add(self, name: str, data: bytes) -> None:
        self.tar.addfile(_member_info(name, len(data)), io.BytesIO(data))

    def finish(self) -> None:
        """Close the tar and rename it into place."""
        self.tar.close()
        self.file.close()
        os.replace(self.temporary, self.final)

    def abandon(self) -> None:
        """Drop the shard: its temporary file goes, without the tar's end blocks."""
        self.file.close()
        self.temporary.unlink(missing_ok=True)


# -- the writers ---------------------------------------------------------------------------------


class SetWriter(DatasetWriter):
    """A set in any format, seeing the samples every format stores.

    So an ``overwrite`` replaces an older set whatever its format, and resuming over another
    format's samples is refused (run.json's ``format`` differs, or no line lists them).

    Entries (:class:`~gpu_blur.dataset.DatasetWriter`'s names of stored samples) are
    ``<folder>.lmdb/<key>`` for an LMDB's keys and ``shard-NNNNNN.tar/<member>`` for a
    shard's members, besides the PNG set's ``blur/<file>``.
    """

    FORMAT = "png"

    def __init__(self, *args, **kwargs):
        self._sizes: dict[str, int] = {}  # LMDB entry -> the size of its value
        self._envs: dict[str, object] = {}  # LMDB folder -> its open environment
        self._members: dict[str, list[tuple[str, int, int]]] = {}  # shard -> name, at, size
        self._member_sizes: dict[str, int] = {}  # shard entry -> size (whole members only)
        self._overwriting = True
        super().__init__(*args, **kwargs)

    def _open(self, run, overwrite, resume, specs, total) -> None:
        self._overwriting = not resume
        super()._open(run, overwrite, resume, specs, total)
        if self.FORMAT != "png":  # the empty folders of a PNG set this one replaced
            for sub in SUBFOLDERS:
                with contextlib.suppress(OSError):
                    (self.out / sub).rmdir()

    def _stored(self) -> list[str]:
        return [*super()._stored(), *self._lmdb_entries(), *self._shard_entries()]

    def _lmdb_entries(self) -> list[str]:
        """The keys of the set's LMDB environments, as entries (sizes in ``_sizes``)."""
        entries, others, keys = [], [], []
        for folder in LMDB_FOLDERS.values():
            path = self.out / folder
            if path.is_symlink() or (path.exists() and not path.is_dir()):
                others.append(str(path))
                continue
            for entry in sorted(path.iterdir()) if path.is_dir() else ():
                if entry.name not in _LMDB_FILES and not _temporary_of(
                        entry, self._earlier, lambda final: final in (_PROBE, META_INFO)):
                    others.append(str(entry))
            if not (path / "data.mdb").is_file():
                continue
            lmdb = _lmdb(f"--output {self.out}: {path} is an LMDB")
            try:
                env = lmdb.open(str(path), readonly=True, lock=False, readahead=False)
            except lmdb.Error as e:
                raise ValueError(f"--output {self.out}: {path} is not an LMDB gpu-blur can "
                                 f"read ({e}); move it out, or choose another --output") from None
            with env, env.begin(buffers=True) as txn:
                for key, value in txn.cursor():
                    text = bytes(key).decode("ascii", "replace")
                    if _KEY.fullmatch(text):
                        entries.append(f"{folder}/{text}")
                        self._sizes[f"{folder}/{text}"] = len(value)
                    else:
                        keys.append(f"{folder} key {text!r}")
        if others:
            raise _foreign(self.out, others, "a file")
        if keys:
            raise _foreign(self.out, keys, "a key")
        return entries

    def _shard_entries(self) -> list[str]:
        """The members of the set's shards, as entries (``.json`` ones left out).

        Only whole members count: a shard cut short (by a crash after its rename) lists
        those before the cut. A shard without any is an entry of its own while a run
        replaces the set (so it goes), and none while it resumes it (kept until rewritten).
        """
        entries = []
        for path in sorted(self.out.iterdir()):
            if not _SHARD.fullmatch(path.name):
                continue
            if path.is_symlink() or not path.is_file():
                raise _foreign(self.out, [str(path)], "a shard")
            members, end = [], path.stat().st_size
            try:
                with tarfile.open(path, "r:", format=tarfile.PAX_FORMAT) as tar:
                    for info in tar:
                        if info.isreg() and info.offset_data + info.size <= end:
                            members.append((info.name, info.offset_data, info.size))
            except (tarfile.TarError, OSError):
                pass  # not a tar, or cut within its first header: no member
            self._members[path.name] = members
            self._member_sizes.update((f"{path.name}/{name}", size) for name, _, size in members)
            own = [f"{path.name}/{name}" for name, _, _ in members if not name.endswith(".json")]
            entries += own or ([path.name] if self._overwriting else [])
        return entries

    def _whole(self, entry: str, size) -> bool:
        container = entry.split("/", 1)[0]
        if container in LMDB_FOLDERS.values():
            have = self._sizes.get(entry)
        elif _SHARD.fullmatch(container):
            have = self._member_sizes.get(entry)
        else:
            return super()._whole(entry, size)
        return have is not None and (have == size if type(size) is int else have > 0)

    def _remove(self, entries: list[str], listed: set[str]) -> None:
        containers = [e.split("/", 1)[0] for e in entries]
        kept = {e.split("/", 1)[0] for e in listed}
        super()._remove([e for e, c in zip(entries, containers, strict=True)
                         if c not in LMDB_FOLDERS.values() and not _SHARD.fullmatch(c)], listed)
        for folder in LMDB_FOLDERS.values():
            keys = [e.split("/", 1)[1] for e, c in zip(entries, containers, strict=True)
                    if c == folder]
            if not keys:
                continue
            if folder not in kept:  # nothing of it is kept: the whole environment goes
                self._close_envs()
                for name in _LMDB_FILES:
                    (self.out / folder / name).unlink(missing_ok=True)
                with contextlib.suppress(OSError):
                    (self.out / folder).rmdir()
                continue
            with self._env(folder).begin(write=True) as txn:
                for key in keys:
                    txn.delete(key.encode("ascii"))
        for shard in sorted({c for c in containers if _SHARD.fullmatch(c)} - kept):
            (self.out / shard).unlink()  # no finished sample in it
        # a shard holding finished samples too is rewritten when its others are made again

    def _remove_temporaries(self) -> None:
        super()._remove_temporaries()
        for folder in LMDB_FOLDERS.values():
            path = self.out / folder
            for entry in path.iterdir() if path.is_dir() and not path.is_symlink() else ():
                if _temporary_of(entry, self._earlier, lambda f: f in (_PROBE, META_INFO)):
                    entry.unlink()
        for entry in self.out.iterdir():
            if _temporary_of(entry, self._earlier, _SHARD.fullmatch):
                entry.unlink()

    def _env(self, folder: str):
        """``folder``'s LMDB environment, opened for writing (created if need be)."""
        if folder not in self._envs:
            lmdb = _lmdb(f"--output {self.out}: {self.out / folder}")
            path = self.out / folder
            path.mkdir(exist_ok=True)
            data = path / "data.mdb"
            size = max(_MAP_SIZE, 2 * data.stat().st_size if data.is_file() else 0)
            self._envs[folder] = lmdb.open(str(path), map_size=size, metasync=False,
                                           readahead=False)
        return self._envs[folder]

    def _close_envs(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs = {}

    def close(self) -> None:
        """Close the set (DatasetWriter.close) and any LMDB environment open."""
        try:
            super().close()
        finally:
            self._close_envs()


class PngWriter(SetWriter):
    """A set of files: ``blur/``, ``sharp/`` and the rest (:class:`DatasetWriter`'s)."""


def _lmdb(what: str):
    """The lmdb module, or a ValueError saying ``what`` needs it."""
    try:
        import lmdb
    except ImportError:
        raise ValueError(f"{what} needs the lmdb package, which is not installed: pip install "
                         "'gpu_blur[lmdb]'") from None
    return lmdb


class LmdbWriter(SetWriter):
    """A set whose samples are in LMDB environments, BasicSR's paired convention (module doc).

    Takes :class:`~gpu_blur.dataset.DatasetWriter`'s arguments and keeps its guarantees; see
    the module docstring for what a sample's keys are and when meta_info.txt is written.
    """

    FORMAT = "lmdb"
    FILES_ANY_PROCESS = False  # stored through this writer's environments

    def __init__(self, *args, **kwargs):
        self._pending: dict[int, dict[str, tuple[str, bytes]]] = {}
        self._keys: dict[int, dict[str, str]] = {}  # index -> output -> key, finished samples
        super().__init__(*args, **kwargs)

    def _names(self, index: int, name: str) -> dict[str, str]:
        key = sample_key(index, name)
        return {k: f"{folder}/{key}" for k, folder in LMDB_FOLDERS.items()}

    def _make_folders(self) -> None:
        try:
            for folder in (self.out / "blur.lmdb", self.out / "sharp.lmdb"):
                folder.mkdir(exist_ok=True)
            for folder in (self.out, self.out / "blur.lmdb", self.out / "sharp.lmdb"):
                write_new(temporary_path(folder / _PROBE), b"").unlink()
        except OSError as e:
            raise self._unwritable(e) from None

    def _open(self, run, overwrite, resume, specs, total) -> None:
        super()._open(run, overwrite, resume, specs, total)
        self._keys = {index: {k: line[k].split("/", 1)[1] for k in _IMAGES if k in line}
                      for index, line in self.done.items()}
        self._write_meta_info()

    def _store(self, line: dict, data: dict[str, bytes]) -> None:
        key = sample_key(line["index"], line["name"])
        line["key"] = key
        self._pending[line["index"]] = {k: (key, data[k]) for k in PATHS if k in data}

    def _write_line(self, index: int, text: str) -> None:
        """Put the sample's values, a transaction each, then write its line."""
        import lmdb

        for kind, (key, value) in self._pending.pop(index, {}).items():
            folder = LMDB_FOLDERS[kind]
            env = self._env(folder)
            while True:
                try:
                    with env.begin(write=True) as txn:
                        txn.put(key.encode("ascii"), value)
                    break
                except lmdb.MapFullError:
                    env.set_mapsize(2 * env.info()["map_size"])
                except lmdb.Error as e:
                    raise OSError(f"{self.out / folder}: cannot put key {key} ({e})") from None
            if kind in _IMAGES:
                self._keys.setdefault(index, {})[kind] = key
        super()._write_line(index, text)

    def _write_meta_info(self) -> None:
        """Each image environment's meta_info.txt: its finished samples, in index order."""
        for kind in _IMAGES:
            folder = LMDB_FOLDERS[kind]
            keys = [self._keys[i][kind] for i in sorted(self._keys) if kind in self._keys[i]]
            if not keys and not (self.out / folder / "data.mdb").is_file():
                continue
            lines = []
            with self._env(folder).begin(buffers=True) as txn:
                level = png_level(self.png, 16 if kind == "mask" else self.bits)
                for key in keys:
                    h, w, c = png_shape(txn.get(key.encode("ascii")))
                    lines.append(f"{key}.png ({h},{w},{c}) {level}\n")
            write_text(self.out / folder / META_INFO, "".join(lines))

    def close(self) -> None:
        """Write meta_info.txt, then close the set and the environments."""
        try:
            if self._lock is not None:  # not closed yet
                self._pending.clear()  # samples whose lines were dropped (a stopped run)
                self._write_meta_info()
        finally:
            super().close()


class ShardWriter(SetWriter):
    """A set whose samples are in WebDataset tar shards (module docstring).

    Takes :class:`~gpu_blur.dataset.DatasetWriter`'s arguments and ``shard_size``, the
    samples a shard holds; keeps its guarantees. ``specs`` tells when a shard is complete; a
    writer without them finishes the shard in writing at :meth:`close`.
    """

    FORMAT = "webdataset"
    FILES_ANY_PROCESS = False  # stored through this writer's shard in writing

    def __init__(self, *args, shard_size: int = DEFAULT_SHARD_SIZE, **kwargs):
        self.shard_size = shard_size
        self._pending: dict[int, list[tuple[str, bytes]]] = {}
        self._shard: _OpenShard | None = None
        self._copied: set[int] = set()  # finished samples copied into the shard in writing
        self._ends: dict[int, int] = {}
        super().__init__(*args, **kwargs)

    def _names(self, index: int, name: str) -> dict[str, str]:
        key, shard = sample_key(index, name), shard_name(index // self.shard_size)
        image = ".tiff" if self.bits == 0 else ".png"
        return {k: f"{shard}/{key}.{ext}{image if ext in ('blur', 'sharp') else ''}"
                for k, ext in _MEMBERS.items()}

    def _entries_of(self, spec) -> set[str]:
        return {*super()._entries_of(spec), shard_name(spec.index // self.shard_size)}

    def _make_folders(self) -> None:
        try:
            write_new(temporary_path(self.out / _PROBE), b"").unlink()
        except OSError as e:
            raise self._unwritable(e) from None

    def _open(self, run, overwrite, resume, specs, total) -> None:
        super()._open(run, overwrite, resume, specs, total)
        # where each shard's samples end in specs: it is complete once the writing is past
        for position, spec in enumerate(specs or ()):
            self._ends[spec.index // self.shard_size] = position + 1

    def _store(self, line: dict, data: dict[str, bytes]) -> None:
        key = sample_key(line["index"], line["name"])
        line["key"] = key
        members = [(line[k].split("/", 1)[1], data[k]) for k in PATHS if k in data]
        self._pending[line["index"]] = [*members, (f"{key}.json", _record(line))]

    def _copy_finished(self, before: int | None) -> None:
        """Copy the finished samples of the shard in writing (those below ``before``)."""
        shard = self._shard
        low = shard.number * self.shard_size
        indices = sorted(i for i in self.done if low <= i < low + self.shard_size
                         and i not in self._copied and (before is None or i < before))
        if not indices:
            return
        keys = {sample_key(i, self.done[i]["name"]) for i in indices}
        with open(shard.final, "rb") as old:
            for name, at, size in self._members.get(shard.final.name, ()):
                if name.split(".", 1)[0] in keys:
                    old.seek(at)
                    shard.add(name, old.read(size))
        self._copied.update(indices)

    def _finish_shard(self) -> None:
        self._copy_finished(None)
        shard, self._shard = self._shard, None
        shard.finish()
        self._copied = set()

    def _write_line(self, index: int, text: str) -> None:
        """Add the sample's members to its shard (finishing the one before), then its line."""
        number = index // self.shard_size
        try:
            if self._shard is not None and self._shard.number != number:
                self._finish_shard()
            if self._shard is None:
                self._shard = _OpenShard(self.out, number)
            self._copy_finished(index)
            for name, data in self._pending.pop(index, ()):
                self._shard.add(name, data)
        except tarfile.TarError as e:
            raise OSError(f"{self.out / shard_name(number)}: cannot write it ({e})") from None
        super()._write_line(index, text)

    def _complete(self) -> bool:
        """Whether every sample of the shard in writing has come (made or failed)."""
        if self._specs is None:
            return True
        return self._next >= self._ends.get(self._shard.number, 0)

    def close(self) -> None:
        """Finish the shard in writing if it is complete, else drop it; then close the set."""
        try:
            if self._shard is not None:
                if self._complete():
                    self._finish_shard()
                else:
                    shard, self._shard = self._shard, None
                    shard.abandon()
        finally:
            self._pending.clear()
            super().close()
