"""Writing a generated set: image pairs, array parameters, a JSONL manifest and run.json.

Its inputs are found by :mod:`gpu_blur.discovery`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import os
import re
import stat
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gpu_blur.backends.flows import REGIONS_KEY
from gpu_blur.discovery import SampleSpec, _text, input_label
from gpu_blur.file_writing import (
    EncodedImages,
    encode_image,
    temporary_path,
    write_new,
    write_text,
    write_whole,
)
from gpu_blur.input_folders import MANIFEST, RUN
from gpu_blur.locking import earlier_pids, forget_earlier, release_lock, take_lock
from gpu_blur.outputs import dng_bytes
from gpu_blur.params import ARRAY_PARAMS
from gpu_blur.png_codecs import DEFAULT_PNG_MODE
from gpu_blur.run_record import check_run, jsonable

__all__ = ["ARRAY_CONVENTIONS", "DatasetWriter", "EXTRAS", "FolderWrites", "LOCK", "NAME_BYTES",
           "PATHS", "SAVED_ARRAYS", "SUBFOLDERS", "SampleFiles", "arrays_bytes", "sample_record",
           "save_arrays"]

#: The lock file a run holds (:mod:`gpu_blur.locking`) while it writes its output folder; a run
#: that closes its set removes it (:meth:`DatasetWriter.close`).
LOCK = ".gpu_blur.lock"
#: The set's folders; they hold only files named as DatasetWriter.write names them.
SUBFOLDERS = ("blur", "sharp", "params", "mask", "raw")
#: A sample's files, as manifest keys (paths relative to the set's folder).
PATHS = ("blurred", "sharp", "arrays", "mask", "raw")
#: What ``gpu-blur generate --save`` may add to each pair: the saturation mask (16-bit PNG in
#: ``mask/``) and the noisy Bayer mosaic before demosaicing (16-bit DNG in ``raw/``).
EXTRAS = ("mask", "raw")
_SAMPLE_FILE = re.compile(r"\d{6,}_.*\.(png|tiff|npz|dng)", re.DOTALL)
_PROBE = "gpu_blur_write_test"
#: A temporary file's name (:func:`gpu_blur.file_writing.temporary_path`):
#: ``.<final name>.<pid>.part<final suffix>``.
_TEMPORARY = re.compile(r"\.(.+)\.(\d+)\.part(\.[^.]*)?", re.DOTALL)
#: The most bytes (UTF-8) of a sample's name its file names keep (``NNNNNN_<name>``): with
#: the index, the temporary name's dots, pid and suffixes, a name stays under the 255 bytes a
#: file name may have; a longer name keeps its first bytes and a hash of the whole.
NAME_BYTES = 180
#: What each array of ``params/*.npz`` holds, stored beside it as ``<name>_convention`` (a text
#: entry: ``str(np.load(path)["homographies_convention"])``).
ARRAY_CONVENTIONS = {
    "homographies": (
        "steps x 3 x 3 float64, the camera path: H[s] for the time sample "
        "t_s = (s + 1/2) / steps - 1/2 of the exposure (time order, t in [-1/2, 1/2], the sharp "
        "image at t = 0). H[s] maps a pixel of the sharp input image to where its scene point is "
        "at t_s: (u, v, w) = H[s] @ (x, y, 1), seen at (u / w, v / w); x is the column and y the "
        "row, in pixels, with pixel centres at integers and (0, 0) the centre of the top-left "
        "pixel, on the input's grid before output.crop (the saved images' pixel (x, y) is the "
        "input's (x + crop, y + crop)); H[2, 2] is not normalised. The blurred image is the mean "
        "over s of the input warped by H[s]: output pixel p takes the input at H[s]^-1 p "
        "(bilinear; where that leaves the input, only the samples' weight on the input counts "
        "and the mean is over that weight: gpu_blur.reference.shake.shake_blur)."),
    "kernel": (
        "kh x kw float64 motion kernel, rows y and columns x, odd sides, normalised to sum 1 "
        "where it is used: a true convolution centred on the middle entry, "
        "blurred[y, x] = sum over i, j of k[i, j] sharp[y + kh // 2 - i, x + kw // 2 - j], in "
        "linear RGB, reflect-101 borders, on the input's grid before output.crop "
        "(gpu_blur.reference.motion_kernel.convolve_kernel)."),
    REGIONS_KEY: (
        "gaps x rows x columns uint8, blur.interpolation = 'auto' with regions: gap g's frame-"
        "rate factor (1, 2, 4 or 8) in the square of side blur.interpolation_region pixels at "
        "that row and column of a grid from the input's top-left pixel, before output.crop; "
        "interpolation_factors holds each gap's largest (gpu_blur.reference.interpolate, "
        "module step 7)."),
}
#: Parameters saved in the sample's arrays file rather than in its manifest line.
SAVED_ARRAYS = (*ARRAY_PARAMS, REGIONS_KEY)


def _inputs(spec: SampleSpec) -> dict:
    """A manifest line's ``inputs`` (:func:`input_label`), and in mode none ``input_roles``.

    The roles are ``blurred``, ``mask`` and ``sharp``, in the order of the inputs. A window
    of frames (blur mode average) says its sequence and place (:meth:`Window.manifest`).
    """
    line = {"inputs": [input_label(p) for p in spec.inputs]}
    if spec.roles:
        line["input_roles"] = list(spec.roles)
    if spec.window is not None:
        line.update(spec.window.manifest())
    return line


def _json_object(text: bytes) -> dict | None:
    """A manifest line as the object it holds, or None when it is not one (not UTF-8 JSON)."""
    try:
        line = json.loads(text.decode())
    except ValueError:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        return None
    return line if isinstance(line, dict) else None


def _whole(path: Path, size) -> bool:
    """Whether ``path`` is a regular file (not a link) of ``size`` bytes (None: not empty)."""
    try:
        info = path.lstat()
    except OSError:
        return False
    return stat.S_ISREG(info.st_mode) and (
        info.st_size == size if type(size) is int else info.st_size > 0)


def save_arrays(path: Path, arrays: dict) -> None:
    """``np.savez`` with fixed zip timestamps, so equal arrays give equal bytes.

    The file appears complete or not at all (written to a temporary name, then renamed).
    """
    write_whole(path, arrays_bytes(arrays))


def arrays_bytes(arrays: dict) -> bytes:
    """The bytes of the ``.npz`` file :func:`save_arrays` writes."""
    encoded = io.BytesIO()
    with zipfile.ZipFile(encoded, "w", zipfile.ZIP_STORED) as z:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with z.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asarray(value), allow_pickle=False)
    return encoded.getvalue()


def _stem(index: int, name: str) -> str:
    """``NNNNNN_<name>``, the stem of sample ``index``'s files (:func:`_paths`)."""
    flat = name.replace("/", "_")
    if len(flat.encode()) > NAME_BYTES:
        digest = hashlib.sha256(flat.encode()).hexdigest()[:16]
        flat = flat.encode()[:NAME_BYTES - 17].decode(errors="ignore") + "~" + digest
    return f"{index:06d}_{flat}"


def _paths(index: int, name: str, bits: int) -> dict[str, str]:
    """The files of sample ``index`` named ``name``, relative to the set's folder.

    ``NNNNNN_<name>`` with ``/`` as ``_``; a name of more than :data:`NAME_BYTES` bytes
    keeps its first bytes and the first 16 hex digits of its sha256. ``bits``: the
    :class:`DatasetWriter`'s (0: TIFF images).
    """
    stem = _stem(index, name)
    ext = ".png" if bits else ".tiff"
    return {"blurred": f"blur/{stem}{ext}", "sharp": f"sharp/{stem}{ext}",
            "arrays": f"params/{stem}.npz", "mask": f"mask/{stem}.png",
            "raw": f"raw/{stem}.dng"}


def _ours(entry: Path, out: Path, earlier) -> bool:
    """Whether ``entry`` is a temporary file an earlier run on the folder ``out`` made.

    Its name must be :func:`gpu_blur.file_writing.temporary_path`'s for a file that run writes
    there (a sample file in the set's folders; the manifest, run.json or the write probe
    beside them), with the process id of a run the lock file records
    (``earlier``, :func:`gpu_blur.locking.earlier_pids`): a file of the same look that
    someone else made is never taken for one.
    """
    match = _TEMPORARY.fullmatch(entry.name)
    if not match or int(match[2]) not in earlier or entry.is_symlink() \
            or not entry.is_file():
        return False
    final, suffix = match[1], match[3] or ""
    if Path(final).suffix != suffix:
        return False
    if entry.parent == out:
        return final in (MANIFEST, RUN, _PROBE)
    return bool(_SAMPLE_FILE.fullmatch(final)) or final == _PROBE


def _sample_files(out: Path, earlier) -> list[Path]:
    """The sample files in the set's folders (:data:`SUBFOLDERS` of ``out``).

    Those named as :meth:`DatasetWriter.write` names them; ``earlier``: as for :func:`_ours`.

    Raises:
        ValueError: naming anything else there but temporary files, since those folders
            are the set's: a new set, ``overwrite`` and ``resume`` remove sample files
            no manifest line lists.
    """
    ours, others = [], []
    for sub in SUBFOLDERS:
        folder = out / sub
        if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
            others.append(folder)
            continue
        for entry in sorted(folder.iterdir()) if folder.is_dir() else ():
            if entry.is_symlink() or not entry.is_file():
                others.append(entry)
            elif _SAMPLE_FILE.fullmatch(entry.name):
                ours.append(entry)
            elif not _ours(entry, out, earlier):
                others.append(entry)
    if others:
        more = f" and {len(others) - 5} more" if len(others) > 5 else ""
        raise ValueError(
            f"--output {out}: {', '.join(map(str, others[:5]))}{more}: not a file "
            f"gpu-blur wrote; {', '.join(SUBFOLDERS)} hold only a set's own files "
            "(gpu-blur replaces and removes those), so move these out, or choose another "
            "--output")
    return ours


def sample_record(record: dict, result) -> dict:
    """The run's fields of a made sample's manifest line.

    ``record``, with the device model that made the sample (``result.device``, where the
    backend names one).
    """
    return {**record, "device": result.device or record["device"]}


@dataclasses.dataclass(frozen=True)
class SampleFiles:
    """A made sample's files and manifest line, as any process encodes them (picklable).

    ``out``, ``bits``, ``png``, ``extras``: the set's (:class:`DatasetWriter`'s); ``pid``: the
    process whose id the temporary files bear, the writer's (the one its lock file records).
    """

    out: Path
    bits: int
    png: str
    extras: tuple[str, ...]
    pid: int
    #: the sharp references' files, each image encoded once in a process
    sharp_files: EncodedImages = dataclasses.field(default_factory=EncodedImages,
                                                   compare=False, repr=False)

    def encode(self, spec: SampleSpec, result, record: dict,
               paths: dict[str, str]) -> tuple[dict, dict[str, bytes]]:
        """A sample's manifest line and its files' bytes, keyed as the line names them.

        ``paths``: where its files go (:func:`_paths`, or a container's names). The line
        holds, besides ``record``, how many tiles the sample ran in and how many of them were
        spot-checked (``spot_check`` "passed", or "none" when no tile was checked: a failed
        check fails the sample), the stages that ran and why each other one did not
        (``skipped``); its arrays' file holds each array's convention. With :attr:`extras`,
        the sample's saturation mask (``mask``: a 16-bit PNG, codes ``round(m * 65535)``) and
        RAW mosaic (``raw``: a 16-bit DNG, and ``raw_info``, its
        :func:`gpu_blur.outputs.raw_metadata`) are written too, cropped like the pair.
        """
        streams = result.png or {}  # deflated on the device (gpu_blur.png_device)
        data = {"blurred": encode_image(result.blurred, self.bits,
                                        str(self.out / paths["blurred"]), self.png,
                                        streams.get("blurred")),
                "sharp": (encode_image(result.sharp, self.bits, str(self.out / paths["sharp"]),
                                       self.png, streams["sharp"]) if "sharp" in streams
                          else self.sharp_files.encode(result.sharp, self.bits,
                                                       str(self.out / paths["sharp"]),
                                                       self.png))}
        arrays = {k: result.params[k] for k in SAVED_ARRAYS if k in result.params}
        line = {
            "index": spec.index,
            "name": spec.name,
            **_inputs(spec),
            "blurred": paths["blurred"],
            "sharp": paths["sharp"],
            **record,
            "tiles": result.tiles,
            "spot_checked_tiles": result.spot_checks,
            "spot_check": "passed" if result.spot_checks else "none",
            "status": "ok",
            "params": {k: jsonable(v) for k, v in result.params.items() if k not in arrays},
            "stages": [s.name for s in result.plan.stages if s.kept],
            "skipped": {s.name: s.reason for s in result.plan.stages if not s.kept},
        }
        if arrays:
            data["arrays"] = arrays_bytes(arrays | {
                f"{k}_convention": ARRAY_CONVENTIONS[k] for k in arrays})
            line["arrays"] = paths["arrays"]
        if "mask" in self.extras:  # as gpu_blur.outputs.write_mask writes it
            data["mask"] = encode_image(result.mask, 16, str(self.out / paths["mask"]),
                                         self.png)
            line["mask"] = paths["mask"]
        if "raw" in self.extras:
            data["raw"] = dng_bytes(result.raw, result.raw_info)
            line["raw"] = paths["raw"]
            line["raw_info"] = result.raw_info
        # what a resume checks the files against (a file cut by a crash is made again)
        line["bytes"] = {k: len(data[k]) for k in PATHS if k in line}
        return line, data

    def store(self, line: dict, data: dict[str, bytes],
              check: Callable[[Path], None] | None = None) -> None:
        """Put a sample's encoded files where ``line`` names them (threads may call at once).

        ``check``: as :func:`~gpu_blur.file_writing.write_whole`'s, before each rename.
        """
        for key, blob in data.items():
            path = self.out / line[key]
            path.parent.mkdir(exist_ok=True)
            write_whole(path, blob, check, self.pid)

    def temporaries(self, spec: SampleSpec) -> list[Path]:
        """Every temporary file a write of ``spec``'s files may leave (those it names)."""
        return [temporary_path(self.out / path, self.pid)
                for path in _paths(spec.index, spec.name, self.bits).values()]


@dataclasses.dataclass(frozen=True)
class FolderWrites:
    """How another process writes the samples it makes into a set of files (picklable).

    ``--devices`` workers do (:func:`gpu_blur.distributed.run_devices`), so a sample's
    images never cross to the driver, which writes only the manifest lines they send.
    ``record``: the run's part of each line (:func:`sample_record`).
    """

    files: SampleFiles
    record: dict

    def write(self, spec: SampleSpec, result,
              check: Callable[[Path], None] | None = None) -> dict:
        """Write a made sample's files as :meth:`DatasetWriter.save` does; its line back."""
        line, data = self.files.encode(spec, result, sample_record(self.record, result),
                                       _paths(spec.index, spec.name, self.files.bits))
        self.files.store(line, data, check)
        return line


class DatasetWriter:
    """Writes ``blur/`` and ``sharp/`` PNGs, array parameters, ``manifest.jsonl`` and ``run.json``.

    What it guarantees:

    * One writer per folder: it holds an advisory lock (:func:`gpu_blur.locking.take_lock` on
      :data:`LOCK`, which names its pid, host and start) from opening to :meth:`close`; another
      writer on the folder is refused at once, naming the holder. The lock dies with its
      process; :meth:`close` and a refusal remove the file (a killed run leaves it, blocking
      nothing, as the record of its temporary files).
    * Nothing half-written under a final name: each file is written under a temporary name
      unique to the process (:func:`gpu_blur.file_writing.temporary_path`; a ``--devices``
      worker's bear its driver's id, and no two processes write one sample) and renamed, and a
      sample's line is appended and flushed only after its files, so the manifest lists
      only finished samples whatever moment a run is killed.
    * The manifest in sample order: lines are written in the order of ``specs`` however the
      samples finish (see :meth:`_append`), so any executor writes a serial run's bytes; a
      resume that makes earlier samples again puts them in place at :meth:`close`.
    * The set's folders are the set's: ``blur/``, ``sharp/``, ``params/`` (and ``mask/``,
      ``raw/``) hold only
      sample files named as :meth:`write` names them (``NNNNNN_<name>.png``); anything else
      there is refused, named, before any change, and is never removed. Opening a folder
      removes the sample files no kept manifest line lists (on resume, only those of samples
      it makes again: :meth:`_check_unlisted`) and the temporary files a killed run left
      (only those named with the pid of a run its lock file records, :func:`_ours`).

    Three ways to open a folder: a new set (refused if the folder holds a manifest, run.json
    or sample files), ``overwrite`` (remove the old set's sample files, then its manifest and
    run.json, then start again), or ``resume``: finish the set a previous run started.
    Sample files with neither a manifest nor run.json beside them are no set gpu-blur made: refused
    in every way, never removed. Resuming checks that ``run`` matches the folder's ``run.json`` in
    every key of :data:`~gpu_blur.run_record.RESUME_KEYS` (options, device, library versions, camera
    and kernel file contents) and that each finished sample's index still names the same inputs,
    keeps the finished samples (``done``; their files are not touched), and drops the other lines:
    failed samples (to be tried again), a line torn by a kill, and any line it cannot verify (an
    index that is not an int in ``[0, total)``, files not named as this writer names them, missing,
    or not of the sizes the line records). A missing, unreadable or damaged manifest (NUL bytes, a
    line that is not JSON but a last one cut before its newline), and sample files no kept line
    lists that this run would not make again (an emptied manifest, an input that changed), are
    refused while sample files are there, changing nothing: resuming would remove finished samples.

    Args:
        out: the set's folder (created if needed).
        bits: 8 or 16 (PNG), 0 (float TIFF).
        run: what ``run.json`` records (``gpu-blur generate``'s settings).
        specs: the samples this run makes, in index order: the order of the manifest.
        total: how many samples the input gives (before ``--limit``); default ``len(specs)``.
        extras: what else to write per sample, of :data:`EXTRAS` (results made
            ``with_raw`` for ``raw``).
        png: how PNG files are compressed (the scene's ``output.png``,
            :data:`gpu_blur.png_codecs.PNG_MODES`).

    Raises:
        ValueError: an existing set without ``overwrite``/``resume``, a folder another run
            holds or that holds files not of a set, or a resume whose settings, files or
            inputs differ, naming what differs and the way out.
        OSError: naming the folder when it cannot be created or written.
    """

    #: Whether each sample is files of its own in the set's folders, named by :func:`_paths`,
    #: which any process may write (:meth:`folder_writes`); a container format's writer (its
    #: own names and store) says no.
    FILES_ANY_PROCESS = True

    def __init__(self, out: Path, bits: int, run: dict | None = None, *,
                 overwrite: bool = False, resume: bool = False,
                 specs: list[SampleSpec] | None = None, total: int | None = None,
                 extras: tuple[str, ...] = (), png: str = DEFAULT_PNG_MODE):
        unknown = sorted(set(extras) - set(EXTRAS))
        if unknown:
            raise ValueError(f"--save {unknown[0]!r}: unknown; allowed: {', '.join(EXTRAS)} "
                             "(comma-separated)")
        if overwrite and resume:
            raise ValueError("--overwrite and --resume exclude each other: --resume finishes "
                             "an interrupted set, --overwrite starts it again")
        #: the set's folder, bits, PNG mode and extra outputs, and the pid its temporary
        #: files bear (this process's, the one its lock records)
        self.files = SampleFiles(out, bits, png, tuple(extras), os.getpid())
        self.manifest_path = out / MANIFEST
        self.done: dict[int, dict] = {}
        self.retry = 0  # failed samples whose lines were dropped, to be tried again
        self.torn = 0  # manifest lines cut by a kill, or that could not be verified
        self._lock = self._take_lock()
        self._earlier = earlier_pids(self._lock)  # runs whose temporary files may be left
        try:
            self._open(run, overwrite, resume, specs,
                       len(specs) if total is None and specs is not None else total)
        except BaseException as e:  # a refusal (ValueError) changed nothing: no file left
            release_lock(self._lock, self.out / LOCK, remove=isinstance(e, ValueError))
            raise

    @property
    def out(self) -> Path:
        """The set's folder."""
        return self.files.out

    @property
    def bits(self) -> int:
        """The outputs' bits (8, 16; 0: float TIFF)."""
        return self.files.bits

    @property
    def png(self) -> str:
        """``output.png``: how PNG files are written (:data:`gpu_blur.png_codecs.PNG_MODES`)."""
        return self.files.png

    @property
    def extras(self) -> tuple[str, ...]:
        """``--save``'s extra outputs (:data:`EXTRAS`)."""
        return self.files.extras

    def _open(self, run, overwrite, resume, specs, total) -> None:
        out = self.out
        files = self._stored()
        found = [str(p) for p in (self.manifest_path, out / RUN) if p.exists()]
        if files:
            held = list(dict.fromkeys(entry.split("/", 1)[0] for entry in files))
            found.append(f"{len(files)} sample file(s) in {', '.join(held)}")
        if files and not (self.manifest_path.exists() or (out / RUN).exists()):
            raise ValueError(f"--output {out}: {found[-1]} named like a set's, but no "
                             f"{MANIFEST} or {RUN}: not a set gpu-blur made, so nothing there "
                             "is replaced or removed; move those files out, or choose another "
                             "--output")
        if found and not (overwrite or resume):
            raise ValueError(f"--output {out} holds a set already ({'; '.join(found)}); choose "
                             "another --output, pass --resume to finish that set (retrying "
                             "failed samples), or --overwrite to replace it")
        kept = None
        if resume and found:
            check_run(out, run or {})
            kept = self._read_manifest(total, files)
            self._check_inputs(specs or [])
        listed = {line[k] for line in self.done.values() for k in PATHS if k in line}
        if kept is not None:
            self._check_unlisted([p for p in files if p not in listed], specs or [])
        # nothing is changed above this line
        self._make_folders()
        if kept is not None:
            write_text(self.manifest_path, "".join(kept))
        # of the set replaced, or of a sample this run makes again
        self._remove([entry for entry in files if entry not in listed], listed)
        if kept is None:  # a new set: its files are gone, now the state that listed them
            self.manifest_path.unlink(missing_ok=True)
            (out / RUN).unlink(missing_ok=True)
        self._remove_temporaries()
        forget_earlier(self._lock)
        if kept is None and run is not None:
            write_text(out / RUN, json.dumps(run, indent=1) + "\n")
        self.manifest = open(self.manifest_path, "a")
        self._specs, self._next = specs, 0  # lines go out in this order (see _append)
        self._waiting: dict[int, str] = {}
        self._waiting_made: set[int] = set()  # those of made samples (status "ok")
        self._last = max(self.done, default=-1)  # the highest index listed so far
        self._sorted = True  # whether the manifest's lines are in index order

    def _check_unlisted(self, unlisted: list[str], specs: list[SampleSpec]) -> None:
        """Refuse to resume over sample files no kept line lists that this run does not remake.

        Such a file is one of a sample a stopped run was writing, which this run makes again
        (and so removes first), or a finished sample whose line is gone (an emptied manifest)
        or that another input or ``--limit`` gave: that is not removed.
        """
        again = {entry for spec in specs if spec.index not in self.done
                 and not spec.problem and _text(spec.name)
                 for entry in self._entries_of(spec)}
        strays = [entry for entry in unlisted if entry not in again]
        if not strays:
            return
        empty = "is empty (0 bytes, as a power loss may leave it) and " if (
            self.manifest_path.is_file() and self.manifest_path.stat().st_size == 0) else ""
        more = f" and {len(strays) - 3} more" if len(strays) > 3 else ""
        raise ValueError(
            f"--resume: {self.manifest_path} {empty}lists none of {len(strays)} sample file(s) "
            f"in {self.out} that this run would not make again ({', '.join(strays[:3])}{more}): "
            "finished samples, if the input folder, --limit or the manifest changed since, and "
            "resuming would remove them; nothing was changed: resume with the input and "
            "--limit that made them, restore the manifest, start the set again with "
            "--overwrite (which removes them), or use another --output")

    def _unwritable(self, e: OSError) -> OSError:
        reason = e.strerror or str(e)
        return OSError(f"--output {self.out}: cannot create or write the folder ({reason}"
                       f"{': ' + str(e.filename) if e.filename else ''}); choose another "
                       "--output, or make it a writable folder")

    def _take_lock(self) -> int:
        """Create the folder and lock it for this process (:func:`gpu_blur.locking.take_lock`).

        Returns the lock file's descriptor; the lock ends with :meth:`close` or the process.
        """
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            return take_lock(self.out / LOCK, f"--output {self.out}", "wait for that run to "
                             "end, or choose another --output", keep_earlier=True)
        except OSError as e:  # LockHeld is a ValueError: it passes through
            raise self._unwritable(e) from None

    # -- where the samples are: files in the set's folders here, containers in subclasses
    # (gpu_blur.set_formats); an entry is a sample file's name as a manifest line gives it

    def _names(self, index: int, name: str) -> dict[str, str]:
        """The entries of sample ``index`` named ``name``, by :data:`PATHS` key."""
        return _paths(index, name, self.bits)

    def _entries_of(self, spec: SampleSpec) -> set[str]:
        """What making ``spec`` again replaces (:meth:`_check_unlisted`)."""
        return set(self._names(spec.index, spec.name).values())

    def _stored(self) -> list[str]:
        """The sample entries the set holds (:func:`_sample_files`, relative to the folder)."""
        return [p.relative_to(self.out).as_posix() for p in _sample_files(self.out, self._earlier)]

    def _whole(self, entry: str, size) -> bool:
        """Whether ``entry`` holds ``size`` bytes (None: not empty) (:func:`_whole`)."""
        return _whole(self.out / entry, size)

    def _remove(self, entries: list[str], listed: set[str]) -> None:
        """Remove ``entries`` (``listed``: the entries the set keeps)."""
        for entry in entries:
            (self.out / entry).unlink()

    def _remove_temporaries(self) -> None:
        """Remove the temporary files a killed run left (:func:`_ours`)."""
        for folder in (self.out, *(self.out / sub for sub in SUBFOLDERS)):
            for entry in folder.iterdir() if folder.is_dir() else ():
                if _ours(entry, self.out, self._earlier):
                    entry.unlink()  # left by a killed run (the lock keeps live runs out)

    def _store(self, line: dict, data: dict[str, bytes]) -> None:
        """Put a sample's encoded files where ``line`` names them (threads may call at once)."""
        self.files.store(line, data)

    def _make_folders(self) -> None:
        try:
            for sub in ("blur", "sharp"):
                (self.out / sub).mkdir(exist_ok=True)
            for folder in (self.out, self.out / "blur", self.out / "sharp"):
                write_new(temporary_path(folder / _PROBE), b"").unlink()
        except OSError as e:
            raise self._unwritable(e) from None

    def _read_manifest(self, total: int | None, files: list[str]) -> list[str]:
        """The manifest lines to keep (finished samples whose files are whole), filling ``done``.

        A line is trusted only as far as it is checked: its index an int in ``[0, total)``,
        its name and inputs strings, and its files exactly the names :meth:`write` gives that
        index and name, present as regular files (not links) of the sizes the line records
        (not empty, for lines written before sizes were). Other lines are dropped (their
        samples made again), so no path in a manifest is ever read or removed. The lines kept
        are in index order.

        Raises:
            ValueError: with sample files there (``files``), a manifest that is missing,
                unreadable or damaged (NUL bytes, a line that is not a JSON object other than
                a last line a kill cut short, before its newline): resuming would remove
                finished samples.
        """
        path = self.manifest_path
        fix = ("restore it, or start the set again with --overwrite (which removes its "
               "samples), or use another --output")
        if not path.is_file():
            if files:
                raise ValueError(f"--resume: {path} is missing, so which of the "
                                 f"sample files in {self.out} are finished is unknown; {fix}")
            return []
        try:
            texts = path.read_bytes().splitlines(keepends=True)
        except OSError as e:
            raise ValueError(f"--resume: cannot read {path} ({e.strerror or e}); "
                             f"{fix}") from None
        kept = {}  # by index
        for number, text in enumerate(texts, 1):
            line = _json_object(text)
            cut = number == len(texts) and not text.endswith(b"\n")  # a kill cuts only this
            if files and (b"\0" in text or (line is None and not cut)):
                what = "holds NUL bytes" if b"\0" in text else "is not JSON"
                cut_to = (f"cut it to its first {number - 1} line(s) (head -n {number - 1}) "
                          "and resume (the samples of later lines are made again), or "
                          if number > 1 else "")
                raise ValueError(
                    f"--resume: {path}, line {number}, {what}: the manifest is damaged (a kill "
                    "cuts only its last line, a power loss may leave NULs), and resuming "
                    f"would remove finished samples; nothing was changed: {cut_to}{fix}")
            if not (line is not None and type(line.get("index")) is int and line["index"] >= 0
                    and _text(line.get("name")) and isinstance(line.get("inputs"), list)
                    and all(isinstance(p, str) for p in line["inputs"])):
                self.torn += 1
                continue
            index = line["index"]
            if index >= (total if total is not None else math.inf):
                self.torn += 1
                continue
            if line.get("status") != "ok":
                self.retry += 1
                continue
            if index in self.done or not self._finished(line):
                continue  # a repeat, files named otherwise, gone or cut: made again
            self.done[index] = line
            kept[index] = text.decode() if text.endswith(b"\n") else text.decode() + "\n"
        return [kept[i] for i in sorted(kept)]

    def _finished(self, line: dict) -> bool:
        """Whether an "ok" line's files are those :meth:`write` names, of the sizes it records."""
        paths = self._names(line["index"], line["name"])
        keys = [k for k in PATHS if k in line]
        sizes = line.get("bytes") if isinstance(line.get("bytes"), dict) else {}
        return keys[:2] == ["blurred", "sharp"] and all(
            line[k] == paths[k] and self._whole(paths[k], sizes.get(k)) for k in keys)

    def _check_inputs(self, specs: list[SampleSpec]) -> None:
        for spec in specs:
            line = self.done.get(spec.index)
            if line is None:
                continue
            inputs = [input_label(p) for p in spec.inputs]
            if line.get("name") != spec.name or line.get("inputs") != inputs:
                raise ValueError(
                    f"--resume: sample {spec.index} of {self.manifest_path} is "
                    f"{line.get('name')!r} (first input {(line.get('inputs') or ['?'])[0]}) but "
                    f"the input now gives {spec.name!r} (first input {inputs[0]}) at that "
                    "index: the input folder changed since the set was started; restore it, "
                    "or start a new set with --overwrite or another --output")

    def _append(self, line: dict) -> None:
        """Write a sample's line, in the order of ``specs`` when given (finished ones skipped).

        Executors (``--devices``, ``--ray``) hand samples back as they finish; a line waits
        here until every earlier sample has its own, so the manifest is a serial run's, byte
        for byte. What waits is small and bounded: lines (about 1 KB; the images and arrays
        are on disk already) of samples finished while an earlier one is still being made,
        and the executors hand out samples in order, a bounded number per worker ahead
        (``distributed.worker_depth``, in runs of at most ``RUN_SAMPLES``; Ray's window).
        Lines still waiting at :meth:`close` (a run stopped early) are dropped: a resume
        makes those samples again, in order.
        """
        text = json.dumps(line) + "\n"
        if self._specs is None:
            self._write_line(line["index"], text)
        else:
            self._waiting[line["index"]] = text
            if line["status"] == "ok":
                self._waiting_made.add(line["index"])
            while self._next < len(self._specs):
                index = self._specs[self._next].index
                if index not in self.done:
                    if index not in self._waiting:
                        break
                    self._write_line(index, self._waiting.pop(index))
                    self._waiting_made.discard(index)
                self._next += 1
        self.manifest.flush()

    @property
    def held_back(self) -> int:
        """Made samples whose lines still wait for an earlier sample's (dropped at close)."""
        return len(self._waiting_made)

    def _write_line(self, index: int, text: str) -> None:
        """Append a line, noting whether the manifest is still in index order."""
        self.manifest.write(text)
        self._sorted = self._sorted and index > self._last
        self._last = max(self._last, index)

    def write(self, spec: SampleSpec, result, record: dict) -> dict:
        """Write one sample, then its manifest line (``status`` "ok"); returns the line."""
        return self.add(self.save(spec, result, record))

    def save(self, spec: SampleSpec, result, record: dict) -> dict:
        """Write one sample's files; returns its manifest line, for :meth:`add` to write.

        The files and line are :meth:`SampleFiles.encode`'s; threads may save different
        samples at once (each file has its own temporary name); only :meth:`add` and
        :meth:`fail` touch the manifest, from one thread. The files are encoded first, then
        stored (:meth:`_store`: files here, a container in :mod:`gpu_blur.set_formats`), so
        every format holds the same bytes.
        """
        line, data = self.files.encode(spec, result, record,
                                       self._names(spec.index, spec.name))
        self._store(line, data)
        return line

    def folder_writes(self, record: dict) -> FolderWrites | None:
        """What lets other processes write made samples into this set, or None.

        A set of files (PNG format): each sample's files are written under their own names,
        so a ``--devices`` worker can write the samples it makes (``record`` is the run's
        part of each line, :func:`sample_record`). A container format stores through this
        writer alone: None.
        """
        return FolderWrites(self.files, record) if self.FILES_ANY_PROCESS else None

    def add(self, line: dict) -> dict:
        """Write the manifest line of a sample :meth:`save` wrote; returns it."""
        self._append(line)
        return line

    def fail(self, spec: SampleSpec, reason: str, record: dict) -> dict:
        """Record a sample that could not be made (``status`` "failed", ``error``)."""
        line = {"index": spec.index, "name": spec.name, **_inputs(spec),
                **record, "status": "failed", "error": reason}
        self._append(line)
        return line

    def _sort_manifest(self) -> None:
        """Rewrite the manifest with its lines in index order (it appears whole or not at all).

        Only lines this writer kept or wrote are there, one per index.
        """
        lines = self.manifest_path.read_text().splitlines(keepends=True)
        lines.sort(key=lambda text: json.loads(text)["index"])
        write_text(self.manifest_path, "".join(lines))
        self._sorted = True

    def close(self) -> None:
        """Close the manifest and release the output folder's lock, removing :data:`LOCK`.

        The lock file stays when the manifest's last lines cannot be written (the next run
        removes this one's temporary files by its record) or it records a killed run
        (:func:`gpu_blur.locking.release_lock`).

        Raises:
            OSError: naming the manifest when its last lines cannot be written (a full disk).
        """
        closed = False
        try:
            self.manifest.close()
            if not self._sorted:  # a resume made an earlier sample again
                self._sort_manifest()
            closed = True
        except OSError as e:
            raise OSError(f"{self.manifest_path}: cannot write its last lines ({e.strerror or e}); "
                          "the samples it lists are kept: free space or fix the folder, then "
                          "run the same command with --resume") from None
        finally:
            if self._lock is not None:
                release_lock(self._lock, self.out / LOCK, remove=closed)
                self._lock = None
