"""Finding inputs on disk, and writing a generated set: image pairs and a JSONL manifest."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import itertools
import json
import math
import os
import re
import stat
import zipfile
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path

import numpy as np

from gpu_blur import files
from gpu_blur.backends.flows import REGIONS_KEY
from gpu_blur.file_writing import temporary_path, write_image, write_new, write_text, write_whole
from gpu_blur.locking import earlier_pids, forget_earlier, take_lock
from gpu_blur.outputs import write_dng, write_mask
from gpu_blur.params import ARRAY_PARAMS
from gpu_blur.reference.interpolate import INTERPOLATION_AUTO

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
MANIFEST = "manifest.jsonl"
RUN = "run.json"
#: The most samples one run makes. Each waits in memory until made (a SampleSpec with its
#: input paths, about 0.3 KB) and adds a manifest line (about 1 KB): 10 million samples hold
#: some 3 GB of list and write 10 GB of manifest, and take days on a fast GPU.
MAX_SAMPLES = 10_000_000
#: The lock file a run holds (``fcntl.flock``) while it writes its output folder.
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
#: run.json keys a resumed run must share with the set it finishes, with what sets each:
#: everything that decides a sample's inputs, draws or pixels (not --tile or --limit). "files"
#: holds the sha256 of each file the scene names (camera.name, blur.kernel), "device" the
#: backend's device (OpenCL platform numbers change when a runtime is installed),
#: "libraries" the versions of the libraries that compute the pixels (library_versions),
#: "save" the extra outputs of --save (absent without it).
RESUME_KEYS = {"seed": "--seed", "scene": "--scene", "backend": "--backend",
               "device": "device behind --backend", "input": "--input",
               "samples_per_photo": "--samples-per-photo",
               "samples_per_sequence": "--samples-per-sequence",
               "files": "camera or kernel file contents", "libraries": "library version",
               "save": "--save"}


@dataclasses.dataclass(frozen=True)
class SampleSpec:
    """One sample to make: its index (which, with the seed, fixes its draws) and its inputs.

    ``problem`` says why the sample cannot be made (a sequence shorter than ``blur.frames``,
    a blurred image without its mask); such a sample keeps its index, so fixing its input
    later moves no other sample's draws. ``roles`` names each input for blur mode none
    (``blurred``, ``mask``, ``sharp``); empty for frames and photos.
    """

    index: int
    name: str
    inputs: tuple[Path, ...]
    problem: str | None = None
    roles: tuple[str, ...] = ()


#: How the manifest and run.json name the built-in photo: its installed path differs from one
#: machine or environment to the next, so a set records the name.
BUILT_IN_INPUT = "built-in: coffee.png"
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


def default_photo() -> Path:
    """The built-in input: 'coffee' by Rachel Michetti, CC0, as shipped by scikit-image.

    A 600 x 400 photograph whose spoon and cup rim have specular highlights that clip.
    """
    return Path(str(resources.files("gpu_blur").joinpath("data/coffee.png")))


def input_label(path: Path) -> str:
    """How the manifest records an input: its path (:func:`shown`), the built-in photo by name."""
    return BUILT_IN_INPUT if path == default_photo() else shown(str(path))


def shown(text: str) -> str:
    r"""``text`` as UTF-8 text holds it: each byte of a path that is not UTF-8 as ``\xNN``.

    Python gives such a byte of a file name as a lone surrogate (``surrogateescape``), which
    UTF-8, and so the manifest's JSON, cannot hold; other text is returned as it is.
    """
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a lone surrogate no file name gives
        return text.encode("utf-8", "backslashreplace").decode()


def _natural(name: str) -> tuple:
    """Sort key comparing runs of digits as numbers: ``2.png`` before ``10.png``.

    Names that tie as numbers (``01.png``, ``1.png``) fall back to the plain text.
    """
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def _identity(path: Path | None) -> tuple[int, int] | None:
    """(device, inode) of an existing folder, else None."""
    try:
        st = os.stat(path) if path is not None else None
    except OSError:
        return None
    return (st.st_dev, st.st_ino) if st is not None else None


def _walk(folder: Path, skip: tuple[int, int] | None) -> Iterator[tuple[Path, bool]]:
    """(path, is a folder) of every entry under ``folder``, depth first, in natural order.

    The folder whose :func:`_identity` is ``skip`` is left out with all it holds, and so is
    every folder holding a set ``gpu-blur generate`` wrote (its :data:`MANIFEST` and
    :data:`RUN`): a set made inside the input is never read back as input. Linked folders are
    listed but not entered, and unreadable ones skipped, as ``Path.rglob`` does; a link that
    leads nowhere or into a loop of links is no folder.
    """
    try:
        with os.scandir(folder) as it:
            entries = sorted(it, key=lambda e: _natural(e.name))
    except OSError:  # unreadable, or gone since it was listed
        return
    for entry in entries:
        try:
            is_dir = entry.is_dir()
        except OSError:  # a loop of links (ELOOP): no folder, and an image fails when read
            is_dir = False
        if is_dir and ((skip is not None and _identity(Path(entry.path)) == skip)
                       or _holds_a_set(Path(entry.path))):
            continue
        yield Path(entry.path), is_dir
        if is_dir and not entry.is_symlink():
            yield from _walk(Path(entry.path), skip)


def _holds_a_set(folder: Path) -> bool:
    """Whether ``folder`` holds a set ``gpu-blur generate`` wrote (a manifest and run.json)."""
    return (folder / MANIFEST).is_file() and (folder / RUN).is_file()


def _images(folder: Path) -> list[Path]:
    """The images directly in ``folder``, in natural order (none when it cannot be read)."""
    try:
        paths = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    except OSError:
        return []
    return sorted(paths, key=lambda p: _natural(p.name))


def _sequence_name(folder: Path, root: Path) -> str:
    """A sequence's name: its folder relative to ``root``, or ``root``'s name when it is root."""
    return root.name if folder == root else folder.relative_to(root).as_posix()


def _is_rsblur_sample(folder: Path) -> bool:
    """Whether ``folder`` is an RSBlur-style ``<session>/<id>/`` folder: both names digits."""
    return folder.name.isdigit() and folder.parent.name.isdigit()


def find_sequences(root: Path, exclude: Path | None = None) -> list[tuple[str, list[Path]]]:
    """Frame sequences under ``root``, GoPro-style and RSBlur-style, in natural order.

    * GoPro-style: every ``.../<seq>/sharp/`` folder; its images are the sequence
      (``GOPRO_Large/train/GOPR0372_07_00/sharp/000047.png``); named ``<seq>``.
    * RSBlur-style: every ``.../<session>/<id>/`` folder whose two names are digits (RSBlur's
      ``0001/000001``) and that holds images itself: those images are the sequence, the
      sharp frames of one real blurred image (RSBlur_sharps gives 9 per image). Its
      subfolders (``avg65_img/``, ``avg65_mask_100/``, ``gt/``, ``real_blur/``) are not
      frames and are never read; named ``<session>/<id>``. ``root`` itself counts when it
      is such a folder.

    Natural order compares runs of digits as numbers: frames ``0.png, 1.png, ..., 9.png,
    10.png`` in that order, and sequences likewise by their folders' names.

    Args:
        root: the input folder.
        exclude: a folder under ``root`` left out with all it holds (the output folder).

    Returns:
        (sequence name relative to root, its frames) pairs.
    """
    folders = [root] + [p for p, is_dir in _walk(root, _identity(exclude)) if is_dir]
    sharp = {f: _images(f) for f in folders[1:] if f.name == "sharp"}
    named = {f.parent for f, frames in sharp.items() if frames}
    seqs = []
    for folder in folders:
        if sharp.get(folder):
            seqs.append((_sequence_name(folder.parent, root), sharp[folder]))
        elif folder not in named and _is_rsblur_sample(folder):
            frames = _images(folder)
            if frames:
                seqs.append((_sequence_name(folder, root), frames))
    return seqs


@dataclasses.dataclass(frozen=True)
class BlurredLayout:
    """Where a published layout of already-blurred images keeps each sample's files.

    Every ``.../<blurred>/`` folder holds blurred images; each image's saturation mask has the
    same file name in the folder beside it named as :attr:`mask` says, and its sharp reference
    is in the ``<sharp>/`` folder beside both (RSBlur authors' README and datalists; layouts in
    ``RSBLUR_PIPELINE.md`` Sec. 2).
    """

    dataset: str
    blurred: str
    sharp: str
    #: (end of a blurred file's stem, end of its sharp file's stem): the sharp file's name;
    #: None: the sharp folder holds the one sharp image of its sample.
    sharp_stem: tuple[str, str] | None = None

    @property
    def mask(self) -> str:
        """The mask folder: the authors' loaders replace ``_img`` by ``_mask_100``."""
        return self.blurred.removesuffix("_img") + "_mask_100"


#: The already-blurred layouts blur mode none reads: GoPro_INTER_ABME's
#: ``<seq>/<id>/avg_inter_img/avg_blur.png`` (sharp ``<id>/gt/gt_sharp.png``), RSBlur's
#: ``<session>/<id>/avg65_img/avg_blur.png`` (sharp in ``gt/`` too) and GoPro_U's
#: ``centroid_blurred_img/<name>_blurred.png`` (sharp ``target_img/<name>_gt.png``).
BLURRED_LAYOUTS = (
    BlurredLayout("GoPro_INTER_ABME", "avg_inter_img", "gt"),
    BlurredLayout("RSBlur", "avg65_img", "gt"),
    BlurredLayout("GoPro_U", "centroid_blurred_img", "target_img", ("_blurred", "_gt")),
)
#: What blur mode none looks for, for messages.
BLURRED_EXPECTED = ("already-blurred images in " + ", ".join(
    f"{lay.blurred}/ (masks in {lay.mask}/, {lay.dataset})" for lay in BLURRED_LAYOUTS))


@dataclasses.dataclass(frozen=True)
class BlurredSample:
    """One already-blurred image with its saturation mask and sharp reference (when found).

    ``problem`` says why it cannot be used (no mask; a sharp folder without its image).
    """

    name: str
    blurred: Path
    mask: Path | None
    sharp: Path | None
    problem: str | None = None


def _sharp_of(blurred: Path, layout: BlurredLayout) -> tuple[Path | None, str | None]:
    """(sharp reference, problem) of a blurred image: (None, None) without a sharp folder."""
    folder = blurred.parent.parent / layout.sharp
    if not folder.is_dir():
        return None, None
    if layout.sharp_stem is not None:
        end, sharp_end = layout.sharp_stem
        stem = blurred.stem.removesuffix(end) + sharp_end if blurred.stem.endswith(end) \
            else blurred.stem
        path = folder / (stem + blurred.suffix)
        if path.is_file():
            return path, None
        return None, (f"{blurred}: its sharp reference {path} is missing ({layout.dataset} "
                      f"names it <name>{sharp_end}{blurred.suffix} in {layout.sharp}/); add "
                      f"it, or move {folder} away to use the blurred image as the reference")
    images = _images(folder)
    if len(images) == 1:
        return images[0], None
    return None, (f"{blurred}: {folder} holds {len(images)} images where {layout.dataset} "
                  f"keeps the one sharp reference of this sample (gt_sharp.png); leave one "
                  f"there, or move {folder} away to use the blurred image as the reference")


def find_blurred(root: Path, masks: bool = True,
                 exclude: Path | None = None) -> list[BlurredSample]:
    """Already-blurred images under ``root`` in the layouts of :data:`BLURRED_LAYOUTS`.

    Every image directly in a ``<blurred>/`` folder is a sample, in natural order, named by
    its path relative to ``root`` without the ``<blurred>/`` folder and the suffix
    (``GOPR0372_07_00/000001/avg_blur``). Its mask is the file of the same name in the mask
    folder beside it (``avg65_mask_100/avg_blur.png``), read as the authors do (8-bit value /
    255). A sharp folder beside them (``gt/``, ``target_img/``) must hold the sample's sharp
    reference; without that folder the sample has none (blur mode none then uses the blurred
    image as the reference).

    Args:
        root: the input folder.
        masks: look for masks; a blurred image without its mask is a sample with its
            ``problem`` set. False: masks are not read (no saturation synthesis).
        exclude: a folder under ``root`` left out with all it holds (the output folder).
    """
    by_folder = {lay.blurred: lay for lay in BLURRED_LAYOUTS}
    samples = []
    for folder, is_dir in _walk(root, _identity(exclude)):
        layout = by_folder.get(folder.name) if is_dir else None
        if layout is None:
            continue
        base = folder.parent
        prefix = "" if base == root else base.relative_to(root).as_posix() + "/"
        for blurred in _images(folder):
            name = prefix + blurred.stem
            mask = base / layout.mask / blurred.name if masks else None
            sharp, problem = _sharp_of(blurred, layout)
            if mask is not None and not mask.is_file():
                problem = (f"{blurred}: no saturation mask {mask} ({layout.dataset} keeps it "
                           f"under the same name in {layout.mask}/); add it, or run "
                           "without masks: saturation.mode = off for gpu-blur generate, "
                           "masks=False for gpu_blur.datasets")
                mask = None
            samples.append(BlurredSample(name, blurred, mask, sharp, problem))
    return samples


def _windows(count: int, size: int, per_sequence: int | None) -> Iterator[int]:
    """First frames of a sequence's windows, in order (see :func:`find_samples`)."""
    if per_sequence is None:
        return iter(range(0, count - size + 1, size))
    if per_sequence == 1:
        return iter([0])
    last = count - size
    return (round(j * last / (per_sequence - 1)) for j in range(per_sequence))


def find_realblur_pairs(root: Path) -> list[BlurredSample]:
    """RealBlur's evaluation pairs under ``root``, in natural order.

    ``<scene>/blur/blur_<n>.png`` with ``<scene>/gt/gt_<n>.png`` (RealBlur_J and RealBlur_R,
    Rim et al. ECCV 2020), named ``<scene>/blur_<n>``; a blurred image without its ground
    truth has ``problem`` set, naming the file expected.
    """
    pairs = []
    for folder, is_dir in _walk(root, None):
        if not (is_dir and folder.name == "blur"):
            continue
        prefix = "" if folder.parent == root else folder.parent.relative_to(root).as_posix() + "/"
        for blurred in _images(folder):
            if not blurred.stem.startswith("blur_"):
                continue
            sharp = folder.parent / "gt" / ("gt_" + blurred.stem[5:] + blurred.suffix)
            problem = None if sharp.is_file() else (
                f"{blurred}: its ground truth {sharp} is missing (RealBlur pairs "
                "<scene>/blur/blur_<n> with <scene>/gt/gt_<n>)")
            pairs.append(BlurredSample(prefix + blurred.stem, blurred, None,
                                       sharp if problem is None else None, problem))
    return pairs


def read_datalist(path: Path, root: Path) -> list[BlurredSample]:
    """The pairs of a datalist as the RSBlur authors ship them (``datalist/*.txt``).

    One ``<sharp> <blurred>`` line each, paths relative to ``root``; named by the blurred path
    without its suffix. A pair whose file is missing has ``problem`` set. Each path must lie
    inside ``root`` once resolved: a list must not read files elsewhere (an absolute path, a
    ``..`` out of ``root``, or a link under ``root`` that points out of it).

    Raises:
        ValueError: naming the file and line when a line is not two paths, or a path lies
            outside ``root``.
    """
    inside = root.resolve()
    pairs = []
    for number, line in enumerate(files.read_text(path, f"datalist {path}").splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 2:
            raise ValueError(f"{path}, line {number}: {len(fields)} field(s) in {line!r}; a "
                             "datalist line is '<sharp path> <blurred path>', relative to the "
                             "data folder")
        for field in fields:
            try:
                resolved = (root / field).resolve()
                leads = None if resolved.is_relative_to(inside) else f"to {resolved}"
            except (OSError, RuntimeError):
                leads = "through a loop of links"
            if leads:
                raise ValueError(
                    f"{path}, line {number}: {field} leads outside the data folder {inside} "
                    f"({leads}); datalist paths are relative to the data folder and stay in "
                    "it: fix the line, or pass the folder that holds the files as the data "
                    "folder")
        sharp, blurred = root / fields[0], root / fields[1]
        missing = [str(p) for p in (blurred, sharp) if not p.is_file()]
        problem = (f"{path}, line {number}: {' and '.join(missing)} not found (paths are "
                   f"relative to {root})") if missing else None
        pairs.append(BlurredSample(Path(fields[1]).with_suffix("").as_posix(), blurred, None,
                                   sharp, problem))
    return pairs


def sequence_samples(sequences, size: int, per_sequence: int | None) -> Iterator[SampleSpec]:
    """The windows of ``size`` frames of :func:`find_sequences`' sequences, numbered in order.

    See :func:`find_samples`; a sequence too short gives one sample with ``problem``.
    """
    index = 0
    for name, frames in sequences:
        if len(frames) < size:
            yield SampleSpec(index, f"{name}/{frames[0].stem}", tuple(frames),
                             f"sequence {name} has {len(frames)} frame(s) in {frames[0].parent}, "
                             f"fewer than blur.frames = {size}; add frames, lower blur.frames "
                             "in the scene, or remove the sequence")
            index += 1
            continue
        previous = None  # starts never decrease, so a repeat follows its first
        for j, start in enumerate(_windows(len(frames), size, per_sequence)):
            window = tuple(frames[start:start + size])
            repeat = f"_{j}" if start == previous else ""
            previous = start
            yield SampleSpec(index, f"{name}/{window[0].stem}{repeat}", window)
            index += 1


def _blurred_samples(found: list[BlurredSample], per_photo: int) -> Iterator[SampleSpec]:
    for i, sample in enumerate(found):
        files = {"blurred": sample.blurred, "mask": sample.mask, "sharp": sample.sharp}
        roles = tuple(k for k, path in files.items() if path is not None)
        for k in range(per_photo):
            suffix = f"_{k}" if per_photo > 1 else ""
            yield SampleSpec(i * per_photo + k, f"{sample.name}{suffix}",
                             tuple(files[r] for r in roles), sample.problem, roles)


def _in_utf8(specs: Iterator[SampleSpec]) -> Iterator[SampleSpec]:
    """``specs``, each whose name or an input's path is not UTF-8 failed with its reason.

    Its name (and any problem) is then :func:`shown`, so its manifest line holds UTF-8 text.
    """
    for spec in specs:
        odd = [text for text in (*map(str, spec.inputs), spec.name) if not _text(text)]
        if odd:
            spec = dataclasses.replace(spec, name=shown(spec.name), problem=(
                f"{shown(odd[0])}: the path is not UTF-8 (\\xNN here is a byte that is not), "
                "and a set records its samples' names and inputs as UTF-8 text; rename it to "
                "UTF-8 (convmv -r -f <its encoding> -t utf-8 <folder>), then run the same "
                "command with --resume"))
        elif not _text(spec.problem or ""):
            spec = dataclasses.replace(spec, problem=shown(spec.problem))
        yield spec


def _photo_samples(photos, per_photo: int) -> Iterator[SampleSpec]:
    for i, (name, path) in enumerate(photos):
        for k in range(per_photo):
            suffix = f"_{k}" if per_photo > 1 else ""
            yield SampleSpec(i * per_photo + k, f"{name}{suffix}", (path,))


@dataclasses.dataclass(frozen=True)
class Samples:
    """The samples an input gives: how many (``total``), each made only when taken."""

    total: int
    make: Callable[[], Iterator[SampleSpec]]

    def take(self, limit: int | None = None) -> list[SampleSpec]:
        """The first ``limit`` samples (all without one), in index order.

        Raises:
            ValueError: when that is more than :data:`MAX_SAMPLES`, saying why.
        """
        count = self.total if limit is None else min(limit, self.total)
        if count > MAX_SAMPLES:
            raise ValueError(
                f"the input gives {self.total:,} samples, more than the {MAX_SAMPLES:,} one run "
                "makes: each waits in memory until it is made and adds a manifest line (about "
                "1 KB); lower --samples-per-photo or --samples-per-sequence, or pass --limit "
                f"(at most {MAX_SAMPLES:,})")
        return list(itertools.islice(self.make(), count))


def find_samples(root: Path | None, mode: str, frames_per_sample: int,
                 samples_per_photo: int = 1, samples_per_sequence: int | None = None,
                 exclude: Path | None = None, masks: bool = True) -> Samples:
    """The samples a folder yields for a blur mode, counted at once and made when taken.

    Args:
        root: input folder, or None for the built-in photo.
        mode: ``average`` takes windows of ``frames_per_sample`` consecutive frames from every
            sequence :func:`find_sequences` finds: GoPro-style ``<seq>/sharp/*.png`` and
            RSBlur-style ``<session>/<id>/*.png`` (digit names, the sharp frames of one real
            blurred image directly in the folder; ``avg*/``, ``gt/``, ``real_blur/`` and other
            subfolders ignored), frames and sequences in natural order (``2.png`` before
            ``10.png``). ``kernel`` and ``trajectory`` take every image under ``root``
            (recursively, in the same natural order) as a photo. ``none`` takes the
            already-blurred images :func:`find_blurred` finds (GoPro_INTER_ABME, RSBlur and
            GoPro_U layouts); a sample's inputs are its (blurred, mask, sharp) files, those
            found, named by ``roles``.
        frames_per_sample: frames per window (mode ``average``).
        samples_per_photo: samples made from each photo, or each blurred image in mode
            ``none`` (each with its own draws).
        samples_per_sequence: mode ``average``: None (default) takes every consecutive,
            non-overlapping window (``n // frames`` per sequence of ``n`` frames); ``K`` takes
            exactly ``K`` windows per sequence, their first frames spread evenly from the first
            window to the last (``round(j (n - frames) / (K - 1))``, ``j = 0 .. K - 1``; ``K = 1``
            the first window): strided when ``K <= n // frames``, overlapping beyond, and the
            same window again (with its own draws) when ``K > n - frames + 1``. Windows are
            named by their first frame, plus ``_<j>`` for a repeat.
        exclude: a folder under ``root`` whose images are never taken (the output folder:
            a set written inside its input is not read back as input).
        masks: mode ``none``: each blurred image needs its mask (without one its sample has
            ``problem`` set); False reads no masks (for ``saturation.mode = off``).

    A sequence with fewer than ``frames_per_sample`` frames gives one sample with its
    ``problem`` set (reported as failed), unless no sequence is long enough. Samples are
    numbered in order; taking the first N makes only those N.

    Raises:
        ValueError: naming the folder when it is missing, not a folder, or yields no sample.
    """
    if root is None:
        if mode == "average":
            raise ValueError("the built-in input is a single photo; blur.mode = average needs "
                             "--input with <seq>/sharp/*.png sequences")
        if mode == "none":
            raise ValueError(f"the built-in input is a sharp photo; blur.mode = none needs "
                             f"--input with {BLURRED_EXPECTED}")
        photos = [("coffee", default_photo())]
    else:
        if not root.exists():
            raise ValueError(f"--input {root}: no such folder")
        if not root.is_dir():
            raise ValueError(f"--input {root}: is a file, not a folder; pass the folder that "
                             "holds the images")
        if not any(root.iterdir()):
            raise ValueError(f"--input {root}: the folder is empty")
        if mode == "average":
            if samples_per_sequence is not None and samples_per_sequence < 1:
                raise ValueError(f"--samples-per-sequence {samples_per_sequence}: must be >= 1")
            size = frames_per_sample
            seqs = find_sequences(root, exclude)
            if all(len(frames) < size for _, frames in seqs):
                short = "".join(f"; {name} has {len(frames)}" for name, frames in seqs[:5])
                raise ValueError(
                    f"--input {root}: no <seq>/sharp/ folder with at least {size} "
                    f"images (blur.frames){short} (nor an RSBlur-style <session>/<id>/ folder "
                    "of frames); lower blur.frames, or for single photos use blur.mode = "
                    "trajectory or kernel")
            total = sum(1 if len(frames) < size else samples_per_sequence or len(frames) // size
                        for _, frames in seqs)
            return Samples(total, lambda: _in_utf8(sequence_samples(seqs, size,
                                                                    samples_per_sequence)))
        if mode == "none":
            found = find_blurred(root, masks, exclude)
            if not found:
                raise ValueError(f"--input {root}: blur.mode = none found no {BLURRED_EXPECTED}")
            return Samples(len(found) * samples_per_photo,
                           lambda: _in_utf8(_blurred_samples(found, samples_per_photo)))
        photos = [(p.relative_to(root).with_suffix("").as_posix(), p)
                  for p, is_dir in _walk(root, _identity(exclude))
                  if not is_dir and p.suffix.lower() in IMAGE_SUFFIXES]
        if not photos:
            raise ValueError(f"--input {root}: no images ({', '.join(IMAGE_SUFFIXES)}) found "
                             "in it or its subfolders")
    return Samples(len(photos) * samples_per_photo,
                   lambda: _in_utf8(_photo_samples(photos, samples_per_photo)))


def _inputs(spec: SampleSpec) -> dict:
    """A manifest line's ``inputs`` (:func:`input_label`), and in mode none ``input_roles``.

    The roles are ``blurred``, ``mask`` and ``sharp``, in the order of the inputs.
    """
    line = {"inputs": [input_label(p) for p in spec.inputs]}
    if spec.roles:
        line["input_roles"] = list(spec.roles)
    return line


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    return value


def _plain(value):
    """``value`` as it reads back from JSON (tuples become lists, numpy scalars numbers)."""
    return json.loads(json.dumps(value, default=_jsonable))


def _json_object(text: bytes) -> dict | None:
    """A manifest line as the object it holds, or None when it is not one (not UTF-8 JSON)."""
    try:
        line = json.loads(text.decode())
    except ValueError:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        return None
    return line if isinstance(line, dict) else None


def _text(value) -> bool:
    """Whether ``value`` is a string that UTF-8 can hold (no lone surrogates)."""
    if not isinstance(value, str):
        return False
    try:
        value.encode()
    except UnicodeEncodeError:
        return False
    return True


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
    encoded = io.BytesIO()
    with zipfile.ZipFile(encoded, "w", zipfile.ZIP_STORED) as z:
        for name, value in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with z.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asarray(value), allow_pickle=False)
    write_whole(path, encoded.getvalue())


def library_versions(backend: str) -> dict[str, str]:
    """The versions of the libraries a sample's pixels depend on with ``backend``.

    gpu_blur, numpy and OpenCV (image decoding and encoding, resampling) always; pyopencl or
    Warp with their backends.
    """
    import cv2

    from gpu_blur import __version__

    versions = {"gpu_blur": __version__, "numpy": np.__version__, "opencv": cv2.__version__}
    family = backend.split(":", 1)[0]
    if family == "opencl":
        import pyopencl

        versions["pyopencl"] = pyopencl.VERSION_TEXT
    elif family == "warp":
        import warp

        versions["warp"] = warp.config.version
    return versions


def _set_keys(scene):
    """A recorded scene without its None-valued keys, as resume compares it.

    A key added to the scene format since a set was made is absent from its run.json, and
    None means the same (a stage off, or the camera's level). ``blur.interpolation_region``
    counts only under ``blur.interpolation = "auto"``, where a set made before it had one
    factor per gap: 0.
    """
    if not isinstance(scene, dict):
        return scene
    scene = {section: ({k: v for k, v in keys.items() if v is not None}
                       if isinstance(keys, dict) else keys) for section, keys in scene.items()}
    blur = scene.get("blur")
    if isinstance(blur, dict):
        scene["blur"] = ({"interpolation_region": 0, **blur}
                         if blur.get("interpolation") == INTERPOLATION_AUTO
                         else {k: v for k, v in blur.items() if k != "interpolation_region"})
    return scene


def _difference(name: str, old, new) -> str:
    """Where two JSON values first differ, as ``name.key = old (this run: new)``."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            if old.get(key) != new.get(key):
                return _difference(f"{name}.{key}", old.get(key), new.get(key))
    shown = [repr(v) if len(repr(v)) <= 80 else repr(v)[:77] + "..." for v in (old, new)]
    return f"{name} = {shown[0]} (this run: {shown[1]})"


class DatasetWriter:
    """Writes ``blur/`` and ``sharp/`` PNGs, array parameters, ``manifest.jsonl`` and ``run.json``.

    What it guarantees:

    * One writer per folder: it holds an advisory lock (``fcntl.flock`` on :data:`LOCK`, which
      names its pid, host and start) from opening to :meth:`close`; another writer on the
      folder is refused at once, naming the holder. The lock dies with its process.
    * Nothing half-written under a final name: each file is written under a temporary name
      unique to the process (:func:`gpu_blur.file_writing.temporary_path`) and renamed, and a
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
      (only those named with the pid of a run its lock file records, :meth:`_ours`).

    Three ways to open a folder: a new set (refused if the folder holds a manifest, run.json
    or sample files), ``overwrite`` (remove the old set's sample files, then its manifest and
    run.json, then start again), or ``resume``: finish the set a previous run started.
    Sample files with neither a manifest nor run.json beside them are no set gpu-blur made:
    refused in every way, never removed. Resuming checks that ``run`` matches the folder's
    ``run.json`` in every key of :data:`RESUME_KEYS` (options, device, library versions,
    camera and kernel file contents) and that each finished sample's index still names the
    same inputs, keeps the finished samples (``done``; their files are not touched), and drops
    the other lines: failed samples (to be tried again), a line torn by a kill, and any line
    it cannot verify (an index that is not an int in ``[0, total)``, files not named as this
    writer names them, missing, or not of the sizes the line records). A missing, unreadable
    or damaged manifest (NUL bytes, a line that is not JSON but a last one cut before its
    newline), and sample files no kept line lists that this run would not make again (an
    emptied manifest, an input that changed), are refused while sample files are there,
    changing nothing: resuming would remove finished samples.

    Args:
        out: the set's folder (created if needed).
        bits: 8 or 16 (PNG), 0 (float TIFF).
        run: what ``run.json`` records (``gpu-blur generate``'s settings).
        specs: the samples this run makes, in index order: the order of the manifest.
        total: how many samples the input gives (before ``--limit``); default ``len(specs)``.
        extras: what else to write per sample, of :data:`EXTRAS` (results made
            ``with_raw`` for ``raw``).

    Raises:
        ValueError: an existing set without ``overwrite``/``resume``, a folder another run
            holds or that holds files not of a set, or a resume whose settings, files or
            inputs differ, naming what differs and the way out.
        OSError: naming the folder when it cannot be created or written.
    """

    def __init__(self, out: Path, bits: int, run: dict | None = None, *,
                 overwrite: bool = False, resume: bool = False,
                 specs: list[SampleSpec] | None = None, total: int | None = None,
                 extras: tuple[str, ...] = ()):
        unknown = sorted(set(extras) - set(EXTRAS))
        if unknown:
            raise ValueError(f"--save {unknown[0]!r}: unknown; allowed: {', '.join(EXTRAS)} "
                             "(comma-separated)")
        self.extras = tuple(extras)
        if overwrite and resume:
            raise ValueError("--overwrite and --resume exclude each other: --resume finishes "
                             "an interrupted set, --overwrite starts it again")
        self.out, self.bits = out, bits
        self.manifest_path = out / MANIFEST
        self.done: dict[int, dict] = {}
        self.retry = 0  # failed samples whose lines were dropped, to be tried again
        self.torn = 0  # manifest lines cut by a kill, or that could not be verified
        self._lock = self._take_lock()
        self._earlier = earlier_pids(self._lock)  # runs whose temporary files may be left
        try:
            self._open(run, overwrite, resume, specs,
                       len(specs) if total is None and specs is not None else total)
        except BaseException:
            os.close(self._lock)
            raise

    def _open(self, run, overwrite, resume, specs, total) -> None:
        out = self.out
        files = self._sample_files()
        found = [str(p) for p in (self.manifest_path, out / RUN) if p.exists()]
        if files:
            held = [sub for sub in SUBFOLDERS if any(p.parent.name == sub for p in files)]
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
            self._check_run(run or {})
            kept = self._read_manifest(total, files)
            self._check_inputs(specs or [])
        listed = {out / line[k] for line in self.done.values() for k in PATHS if k in line}
        if kept is not None:
            self._check_unlisted([p for p in files if p not in listed], specs or [])
        # nothing is changed above this line
        self._make_folders()
        if kept is not None:
            write_text(self.manifest_path, "".join(kept))
        for path in files:
            if path not in listed:
                path.unlink()  # of the set replaced, or of a sample this run makes again
        if kept is None:  # a new set: its files are gone, now the state that listed them
            self.manifest_path.unlink(missing_ok=True)
            (out / RUN).unlink(missing_ok=True)
        for folder in (out, *(out / sub for sub in SUBFOLDERS)):
            for entry in folder.iterdir() if folder.is_dir() else ():
                if self._ours(entry):
                    entry.unlink()  # left by a killed run (the lock keeps live runs out)
        forget_earlier(self._lock)
        if kept is None and run is not None:
            write_text(out / RUN, json.dumps(run, indent=1) + "\n")
        self.manifest = open(self.manifest_path, "a")
        self._specs, self._next = specs, 0  # lines go out in this order (see _append)
        self._waiting: dict[int, str] = {}
        self._last = max(self.done, default=-1)  # the highest index listed so far
        self._sorted = True  # whether the manifest's lines are in index order

    def _check_unlisted(self, unlisted: list[Path], specs: list[SampleSpec]) -> None:
        """Refuse to resume over sample files no kept line lists that this run does not remake.

        Such a file is one of a sample a stopped run was writing, which this run makes again
        (and so removes first), or a finished sample whose line is gone (an emptied manifest)
        or that another input or ``--limit`` gave: that is not removed.
        """
        again = {self.out / path for spec in specs if spec.index not in self.done
                 and not spec.problem and _text(spec.name)
                 for path in self._paths(spec.index, spec.name).values()}
        strays = [str(p.relative_to(self.out)) for p in unlisted if p not in again]
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

    def _sample_files(self) -> list[Path]:
        """The sample files in the set's folders (:data:`SUBFOLDERS`, named as :meth:`write` does).

        Raises:
            ValueError: naming anything else there but temporary files, since those folders
                are the set's: a new set, ``overwrite`` and ``resume`` remove sample files
                no manifest line lists.
        """
        ours, others = [], []
        for sub in SUBFOLDERS:
            folder = self.out / sub
            if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
                others.append(folder)
                continue
            for entry in sorted(folder.iterdir()) if folder.is_dir() else ():
                if entry.is_symlink() or not entry.is_file():
                    others.append(entry)
                elif _SAMPLE_FILE.fullmatch(entry.name):
                    ours.append(entry)
                elif not self._ours(entry):
                    others.append(entry)
        if others:
            more = f" and {len(others) - 5} more" if len(others) > 5 else ""
            raise ValueError(
                f"--output {self.out}: {', '.join(map(str, others[:5]))}{more}: not a file "
                f"gpu-blur wrote; {', '.join(SUBFOLDERS)} hold only a set's own files "
                "(gpu-blur replaces and removes those), so move these out, or choose another "
                "--output")
        return ours

    def _ours(self, entry: Path) -> bool:
        """Whether ``entry`` is a temporary file an earlier run on this folder made.

        Its name must be :func:`gpu_blur.file_writing.temporary_path`'s for a file that run writes
        there (a sample file in the set's folders; the manifest, run.json or the write probe
        beside them), with the process id of a run the lock file records
        (:func:`gpu_blur.locking.earlier_pids`): a file of the same look that someone else
        made is never taken for one.
        """
        match = _TEMPORARY.fullmatch(entry.name)
        if not match or int(match[2]) not in self._earlier or entry.is_symlink() \
                or not entry.is_file():
            return False
        final, suffix = match[1], match[3] or ""
        if Path(final).suffix != suffix:
            return False
        if entry.parent == self.out:
            return final in (MANIFEST, RUN, _PROBE)
        return bool(_SAMPLE_FILE.fullmatch(final)) or final == _PROBE

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

    def _make_folders(self) -> None:
        try:
            for sub in ("blur", "sharp"):
                (self.out / sub).mkdir(exist_ok=True)
            for folder in (self.out, self.out / "blur", self.out / "sharp"):
                write_new(temporary_path(folder / _PROBE), b"").unlink()
        except OSError as e:
            raise self._unwritable(e) from None

    def _check_run(self, run: dict) -> None:
        path = self.out / RUN
        try:
            if not os.path.lexists(path):
                raise FileNotFoundError(path)
            old = json.loads(files.read_text(path, str(path)))  # a regular file: no FIFO wait
        except FileNotFoundError:
            raise ValueError(f"--resume: {path} is missing, so the settings the set in "
                             f"{self.out} was made with are unknown; start it again with "
                             "--overwrite, or use another --output") from None
        except (OSError, ValueError) as e:
            raise ValueError(f"--resume: cannot read {path} ({e}); start the set again with "
                             "--overwrite, or use another --output") from None
        if not isinstance(old, dict):
            raise ValueError(f"--resume: {path} holds a JSON {type(old).__name__}, not the "
                             "object gpu-blur writes; start the set again with --overwrite, or "
                             "use another --output")
        for key, option in RESUME_KEYS.items():
            was, now = _plain(old.get(key)), _plain(run.get(key))
            if key == "scene":  # a key added since (output.jpeg_quality) is absent there
                was, now = _set_keys(was), _set_keys(now)
            if was != now:
                raise ValueError(
                    f"--resume: the set in {self.out} was made with another {option}: "
                    f"{_difference(key, was, now)}; resume with what {path} records (options, "
                    "device, library versions, camera and kernel files), or start a new set "
                    "with --overwrite or another --output")

    def _read_manifest(self, total: int | None, files: list[Path]) -> list[str]:
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
        paths = self._paths(line["index"], line["name"])
        keys = [k for k in PATHS if k in line]
        sizes = line.get("bytes") if isinstance(line.get("bytes"), dict) else {}
        return keys[:2] == ["blurred", "sharp"] and all(
            line[k] == paths[k] and _whole(self.out / paths[k], sizes.get(k)) for k in keys)

    def _paths(self, index: int, name: str) -> dict[str, str]:
        """The files of sample ``index`` named ``name``, relative to the set's folder.

        ``NNNNNN_<name>`` with ``/`` as ``_``; a name of more than :data:`NAME_BYTES` bytes
        keeps its first bytes and the first 16 hex digits of its sha256.
        """
        flat = name.replace("/", "_")
        if len(flat.encode()) > NAME_BYTES:
            digest = hashlib.sha256(flat.encode()).hexdigest()[:16]
            flat = flat.encode()[:NAME_BYTES - 17].decode(errors="ignore") + "~" + digest
        stem = f"{index:06d}_{flat}"
        ext = ".png" if self.bits else ".tiff"
        return {"blurred": f"blur/{stem}{ext}", "sharp": f"sharp/{stem}{ext}",
                "arrays": f"params/{stem}.npz", "mask": f"mask/{stem}.png",
                "raw": f"raw/{stem}.dng"}

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
        and the executors hand out samples in order, only a few per worker ahead
        (``DEVICE_DEPTH``, Ray's window). Lines still waiting at :meth:`close` (a run
        stopped early) are dropped: a resume makes those samples again, in order.
        """
        text = json.dumps(line) + "\n"
        if self._specs is None:
            self._write_line(line["index"], text)
        else:
            self._waiting[line["index"]] = text
            while self._next < len(self._specs):
                index = self._specs[self._next].index
                if index not in self.done:
                    if index not in self._waiting:
                        break
                    self._write_line(index, self._waiting.pop(index))
                self._next += 1
        self.manifest.flush()

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

        The line holds, besides ``record``, how many tiles the sample ran in and how many of
        them were spot-checked (``spot_check`` "passed", or "none" when no tile was checked:
        a failed check fails the sample), the stages that ran and why each other one did not
        (``skipped``); its arrays' file holds each array's convention.
        With :attr:`extras`, the sample's saturation mask (``mask``: a 16-bit PNG, codes
        ``round(m * 65535)``) and RAW mosaic (``raw``: a 16-bit DNG, and ``raw_info``, its
        :func:`gpu_blur.outputs.raw_metadata`) are written too, cropped like the pair.
        Threads may save different samples at once (each file has its own temporary name);
        only :meth:`add` and :meth:`fail` touch the manifest, from one thread.
        """
        paths = self._paths(spec.index, spec.name)
        write_image(self.out / paths["blurred"], result.blurred, self.bits)
        write_image(self.out / paths["sharp"], result.sharp, self.bits)
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
            "params": {k: _jsonable(v) for k, v in result.params.items() if k not in arrays},
            "stages": [s.name for s in result.plan.stages if s.kept],
            "skipped": {s.name: s.reason for s in result.plan.stages if not s.kept},
        }
        if arrays:
            (self.out / "params").mkdir(exist_ok=True)
            save_arrays(self.out / paths["arrays"], arrays | {
                f"{k}_convention": ARRAY_CONVENTIONS[k] for k in arrays})
            line["arrays"] = paths["arrays"]
        if "mask" in self.extras:
            (self.out / "mask").mkdir(exist_ok=True)
            write_mask(self.out / paths["mask"], result.mask)
            line["mask"] = paths["mask"]
        if "raw" in self.extras:
            (self.out / "raw").mkdir(exist_ok=True)
            write_dng(self.out / paths["raw"], result.raw, result.raw_info)
            line["raw"] = paths["raw"]
            line["raw_info"] = result.raw_info
        # what a resume checks the files against (a file cut by a crash is made again)
        line["bytes"] = {k: (self.out / line[k]).stat().st_size for k in PATHS if k in line}
        return line

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
        """Close the manifest and release the output folder's lock.

        Raises:
            OSError: naming the manifest when its last lines cannot be written (a full disk).
        """
        try:
            self.manifest.close()
            if not self._sorted:  # a resume made an earlier sample again
                self._sort_manifest()
        except OSError as e:
            raise OSError(f"{self.manifest_path}: cannot write its last lines ({e.strerror or e}); "
                          "the samples it lists are kept: free space or fix the folder, then "
                          "run the same command with --resume") from None
        finally:
            if self._lock is not None:
                os.close(self._lock)
                self._lock = None
