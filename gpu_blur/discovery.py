"""Finding inputs on disk: frame sequences, photos and already-blurred images, as samples.

What ``gpu-blur generate`` and :mod:`gpu_blur.datasets` read: the published layouts (GoPro,
RSBlur, RealBlur, datalists), in natural order, each sample numbered (:class:`SampleSpec`);
a set written inside its input is never read back. Writing a set: :mod:`gpu_blur.dataset`.
"""

from __future__ import annotations

import dataclasses
import itertools
import re
from collections.abc import Callable, Iterator, Sequence
from importlib import resources
from pathlib import Path

from gpu_blur import input_folders
from gpu_blur.blurred_inputs import (
    BLURRED_EXPECTED,
    BlurredSample,
    blurred_layout,
    find_blurred,
)
from gpu_blur.scene import FROM_NAME

__all__ = ["BUILT_IN_INPUT", "FoundSequence", "GOPRO_NAME", "LAYOUT_NAMES", "MAX_SAMPLES",
           "SampleSpec", "Samples", "Window", "check_layout", "default_photo", "find_samples",
           "find_sequences", "frames_from_name", "input_label", "sequence_folder",
           "sequence_layout", "sequence_samples", "shown"]

#: The most samples one run makes. Each waits in memory until made (a SampleSpec with its
#: input paths, about 0.3 KB) and adds a manifest line (about 1 KB): 10 million samples hold
#: some 3 GB of list and write 10 GB of manifest, and take days on a fast GPU.
MAX_SAMPLES = 10_000_000
#: A GoPro sequence folder's name, ``GOPRxxxx_yy_zz``: in GOPRO_Large_all (every frame of the
#: 240 fps video), ``yy`` consecutive frames make one blur (SeungjunNah/DeepDeblur_release#59).
GOPRO_NAME = re.compile(r"GOPR(\d{4})_(\d{2})_(\d{2})")

#: The layouts of frame sequences, as :func:`sequence_layout` names a sequence's:
#: GOPRO_Large's ``<seq>/sharp/`` beside ``<seq>/blur/`` (the sharp frames of blurs averaged
#: already, one per blurred image, with gaps between them: DeepDeblur_release#22), other
#: ``<seq>/sharp/`` folders, GOPRO_Large_all's ``GOPRxxxx_yy_zz/*.png`` (every frame) and
#: RSBlur's ``<session>/<id>/*.png``.
GOPRO_LARGE, SHARP_FOLDER, GOPRO_LARGE_ALL, RSBLUR = (
    "GOPRO_Large", "<seq>/sharp/", "GOPRO_Large_all", "RSBlur")
#: Each layout as ``generate`` describes it.
LAYOUT_NAMES = {GOPRO_LARGE: "GOPRO_Large (<seq>/sharp/ beside <seq>/blur/)",
                SHARP_FOLDER: "frame sequences (<seq>/sharp/*.png)",
                GOPRO_LARGE_ALL: "GOPRO_Large_all (GOPRxxxx_yy_zz/*.png)",
                RSBLUR: "RSBlur frames (<session>/<id>/*.png)"}


@dataclasses.dataclass(frozen=True)
class Window:
    """Where a window of blur mode average lies: its sequence and its place in it.

    Attributes:
        sequence: the sequence's name (:func:`find_sequences`).
        sequence_index: the sequence's number among the input's sequences, from 0, in
            their natural order; under ``blur.draws = "per-sequence"`` it keys the draws
            every window of the sequence shares (with the seed).
        number: the window's number in its sequence, from 0.
        first_frame: the number of its first frame in the sequence, from 0.
    """

    sequence: str
    sequence_index: int
    number: int
    first_frame: int

    def manifest(self) -> dict:
        """The keys a manifest line gives the window: sequence, its index, window, first frame."""
        return {"sequence": self.sequence, "sequence_index": self.sequence_index,
                "window": self.number, "first_frame": self.first_frame}


@dataclasses.dataclass(frozen=True)
class SampleSpec:
    """One sample to make: its index (which, with the seed, fixes its draws) and its inputs.

    ``problem`` says why the sample cannot be made (a sequence shorter than ``blur.frames``,
    a blurred image without its mask); such a sample keeps its index, so fixing its input
    later moves no other sample's draws. ``roles`` names each input for blur mode none
    (``blurred``, ``mask``, ``sharp``); empty for frames and photos. ``window``: in blur mode
    average, the sequence the sample's frames come from and where (None for photos and
    blurred images).
    """

    index: int
    name: str
    inputs: tuple[Path, ...]
    problem: str | None = None
    roles: tuple[str, ...] = ()
    window: Window | None = None


#: How the manifest and run.json name the built-in photo: its installed path differs from one
#: machine or environment to the next, so a set records the name.
BUILT_IN_INPUT = "built-in: coffee.png"


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


def _sequence_name(folder: Path, root: Path) -> str:
    """A sequence's name: its folder relative to ``root``, or ``root``'s name when it is root."""
    return root.name if folder == root else folder.relative_to(root).as_posix()


def _is_rsblur_sample(folder: Path) -> bool:
    """Whether ``folder`` is an RSBlur-style ``<session>/<id>/`` folder: both names digits."""
    return folder.name.isdigit() and folder.parent.name.isdigit()


def _is_gopro_all_sequence(folder: Path) -> bool:
    """Whether ``folder`` is named as a GoPro sequence (:data:`GOPRO_NAME`)."""
    return GOPRO_NAME.fullmatch(folder.name) is not None


def find_sequences(root: Path, exclude: Path | None = None) -> list[tuple[str, list[Path]]]:
    """Frame sequences under ``root``, GoPro-style and RSBlur-style, in natural order.

    * GoPro-style: every ``.../<seq>/sharp/`` folder; its images are the sequence
      (``GOPRO_Large/train/GOPR0372_07_00/sharp/000047.png``); named ``<seq>``.
    * GOPRO_Large_all: every folder named ``GOPRxxxx_yy_zz`` that holds images itself
      (``GOPRO_Large_all/train/GOPR0372_07_00/000047.png``, every frame); named by its folder.
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
    return _sequences(root, list(input_folders.walk(root, input_folders.identity(exclude))))


def _sequences(root: Path, walked: list[tuple[Path, bool]]) -> list[tuple[str, list[Path]]]:
    """:func:`find_sequences` of ``root`` from its :func:`input_folders.walk` (``walked``)."""
    folders = [root] + [p for p, is_dir in walked if is_dir]
    sharp = {f: input_folders.images(f) for f in folders[1:] if f.name == "sharp"}
    named = {f.parent for f, frames in sharp.items() if frames}
    seqs = []
    for folder in folders:
        if sharp.get(folder):
            seqs.append((_sequence_name(folder.parent, root), sharp[folder]))
        elif folder not in named and (_is_rsblur_sample(folder)
                                      or _is_gopro_all_sequence(folder)):
            frames = input_folders.images(folder)
            if frames:
                seqs.append((_sequence_name(folder, root), frames))
    return seqs


def sequence_layout(frames: list[Path]) -> str:
    """The layout a sequence of :func:`find_sequences` comes in (see :data:`LAYOUT_NAMES`).

    ``<seq>/sharp/`` beside a ``<seq>/blur/`` folder is GOPRO_Large's.
    """
    folder = frames[0].parent
    if folder.name == "sharp":
        return GOPRO_LARGE if (folder.parent / "blur").is_dir() else SHARP_FOLDER
    return GOPRO_LARGE_ALL if _is_gopro_all_sequence(folder) else RSBLUR


def sequence_folder(frames: list[Path]) -> Path:
    """The folder a sequence is named by: ``<seq>`` of ``<seq>/sharp/``, else the frames'."""
    folder = frames[0].parent
    return folder.parent if folder.name == "sharp" else folder


def frames_from_name(frames: list[Path], where: str = "the scene") -> int:
    """``yy`` of a sequence folder named ``GOPRxxxx_yy_zz``: its frames per blur (``from-name``).

    ``where``: where ``blur.frames`` is set, for the message (``scene file s.toml``).

    Raises:
        ValueError: naming the folder when its name is not of that form, or ``yy`` is 0.
    """
    folder = sequence_folder(frames)
    match = GOPRO_NAME.fullmatch(folder.name)
    if match is None or int(match[2]) == 0:
        why = "is not named in that form" if match is None else "has yy = 00"
        raise ValueError(
            f"{where}: blur.frames = '{FROM_NAME}' takes each sequence's frames per blur from "
            f"its folder's name GOPRxxxx_yy_zz (yy, as GOPRO_Large_all names them: "
            f"DeepDeblur_release#59), but sequence folder {shown(str(folder))} {why}; "
            "rename the folder, or set blur.frames to a number of frames")
    return int(match[2])


def _windows(count: int, size: int, per_sequence: int | None, stride: int = 0
             ) -> Iterator[int]:
    """First frames of a sequence's windows, in order (see :func:`find_samples`).

    ``stride``: frames between consecutive windows' first frames without ``per_sequence``
    (0: ``size``, windows side by side).
    """
    if per_sequence is None:
        return iter(range(0, count - size + 1, stride or size))
    if per_sequence == 1:
        return iter([0])
    last = count - size
    return (round(j * last / (per_sequence - 1)) for j in range(per_sequence))


def sequence_samples(sequences, size: int | Sequence[int], per_sequence: int | None,
                     stride: int = 0) -> Iterator[SampleSpec]:
    """The windows of ``size`` frames of :func:`find_sequences`' sequences, numbered in order.

    ``size``: frames per window, one number for all or one per sequence (``from-name``).
    ``stride``: frames between consecutive windows' first frames (0: ``size``).
    See :func:`find_samples`; a sequence too short gives one sample with ``problem``. Each
    sample's :class:`Window` says its sequence (numbered in the order given) and place.
    """
    index = 0
    named = isinstance(size, (list, tuple))
    sizes = size if named else [size] * len(sequences)
    for number, ((name, frames), wanted) in enumerate(zip(sequences, sizes, strict=True)):
        if len(frames) < wanted:
            asked = (f"the {wanted} its name asks for (blur.frames = '{FROM_NAME}'); add frames"
                     if named else
                     f"blur.frames = {wanted}; add frames, lower blur.frames in the scene")
            yield SampleSpec(index, f"{name}/{frames[0].stem}", tuple(frames),
                             f"sequence {name} has {len(frames)} frame(s) in {frames[0].parent}, "
                             f"fewer than {asked}, or remove the sequence",
                             window=Window(name, number, 0, 0))
            index += 1
            continue
        previous = None  # starts never decrease, so a repeat follows its first
        for j, start in enumerate(_windows(len(frames), wanted, per_sequence, stride)):
            window = tuple(frames[start:start + wanted])
            repeat = f"_{j}" if start == previous else ""
            previous = start
            yield SampleSpec(index, f"{name}/{window[0].stem}{repeat}", window,
                             window=Window(name, number, j, start))
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

    Its name (and any problem, and its window's sequence) is then :func:`shown`, so its
    manifest line holds UTF-8 text.
    """
    for spec in specs:
        odd = [text for text in (*map(str, spec.inputs), spec.name) if not _text(text)]
        if odd:
            window = spec.window and dataclasses.replace(spec.window,
                                                         sequence=shown(spec.window.sequence))
            spec = dataclasses.replace(spec, name=shown(spec.name), window=window, problem=(
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
class FoundSequence:
    """A frame sequence under the input, as :func:`find_samples` reports it.

    Attributes:
        name: its name (:func:`find_sequences`).
        layout: its layout (:func:`sequence_layout`).
        frames: how many frames it holds.
        folder: the folder it is named by (:func:`sequence_folder`).
    """

    name: str
    layout: str
    frames: int
    folder: Path


@dataclasses.dataclass(frozen=True)
class Samples:
    """The samples an input gives: how many (``total``), each made only when taken.

    What the input holds, for ``generate``'s summary and :func:`check_layout`: ``layout`` in
    words, ``images`` (the frames of the sequences taken, the photos, or the blurred images)
    and ``sequences``, every frame sequence under the input: also in a photo mode, which
    takes their frames as photos.
    """

    total: int
    make: Callable[[], Iterator[SampleSpec]]
    layout: str = ""
    images: int = 0
    sequences: tuple[FoundSequence, ...] = ()

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


def _found(root: Path, seqs: list[tuple[str, list[Path]]]) -> tuple[FoundSequence, ...]:
    """:func:`find_sequences`' sequences under ``root`` as :class:`FoundSequence` records."""
    return tuple(FoundSequence(name, sequence_layout(frames), len(frames),
                               sequence_folder(frames)) for name, frames in seqs)


def _layouts(found: tuple[FoundSequence, ...]) -> str:
    """The layouts of ``found`` in words (:data:`LAYOUT_NAMES`), in the order first seen."""
    return " and ".join(LAYOUT_NAMES[k] for k in dict.fromkeys(f.layout for f in found))


def find_samples(root: Path | None, mode: str, frames_per_sample: int | str,
                 samples_per_photo: int = 1, samples_per_sequence: int | None = None,
                 exclude: Path | None = None, masks: bool = True,
                 where: str = "the scene", stride: int = 0) -> Samples:
    """The samples a folder yields for a blur mode, counted at once and made when taken.

    Args:
        root: input folder, or None for the built-in photo.
        mode: ``average`` takes windows of ``frames_per_sample`` consecutive frames from every
            sequence :func:`find_sequences` finds: GoPro-style ``<seq>/sharp/*.png``,
            GOPRO_Large_all's ``GOPRxxxx_yy_zz/*.png`` and RSBlur-style
            ``<session>/<id>/*.png`` (digit names, the sharp frames of one real
            blurred image directly in the folder; ``avg*/``, ``gt/``, ``real_blur/`` and other
            subfolders ignored), frames and sequences in natural order (``2.png`` before
            ``10.png``). ``kernel`` and ``trajectory`` take every image under ``root``
            (recursively, in the same natural order) as a photo. ``none`` takes the
            already-blurred images :func:`find_blurred` finds (GoPro_INTER_ABME, RSBlur and
            GoPro_U layouts); a sample's inputs are its (blurred, mask, sharp) files, those
            found, named by ``roles``.
        frames_per_sample: frames per window (mode ``average``), or :data:`FROM_NAME`: each
            sequence's ``yy`` (:func:`frames_from_name`).
        samples_per_photo: samples made from each photo, or each blurred image in mode
            ``none`` (each with its own draws).
        samples_per_sequence: mode ``average``: None (default) takes every consecutive,
            non-overlapping window (``n // frames`` per sequence of ``n`` frames); ``K`` takes
            exactly ``K`` windows per sequence, their first frames spread evenly from the first
            window to the last (``round(j (n - frames) / (K - 1))``, ``j = 0 .. K - 1``; ``K = 1``
            the first window): strided when ``K <= n // frames``, overlapping beyond, and the
            same window again (with its own draws) when ``K > n - frames + 1``. Windows are
            named by their first frame, plus ``_<j>`` for a repeat.
        stride: mode ``average`` without ``samples_per_sequence``: frames between
            consecutive windows' first frames (``blur.stride``), ``(n - frames) // stride +
            1`` windows per sequence; 0 (default): ``frames``, the windows side by side.
        exclude: a folder under ``root`` whose images are never taken (the output folder:
            a set written inside its input is not read back as input).
        masks: mode ``none``: each blurred image needs its mask (without one its sample has
            ``problem`` set); False reads no masks (for ``saturation.mode = off``).
        where: where the blur mode is set, for messages (``scene file s.toml``).

    A sequence with fewer than ``frames_per_sample`` frames gives one sample with its
    ``problem`` set (reported as failed), unless no sequence is long enough. Samples are
    numbered in order; taking the first N makes only those N.

    Raises:
        ValueError: naming the folder when it is missing, not a folder, or yields no sample;
            with :data:`FROM_NAME`, naming a sequence folder not named ``GOPRxxxx_yy_zz``;
            ``samples_per_sequence`` with a ``stride``.
    """
    if root is None:
        if mode == "average":
            raise ValueError("the built-in input is a single photo; blur.mode = average needs "
                             "--input with <seq>/sharp/*.png sequences")
        if mode == "none":
            raise ValueError(f"the built-in input is a sharp photo; blur.mode = none needs "
                             f"--input with {BLURRED_EXPECTED}")
        photos = [("coffee", default_photo())]
        layout, sequences = "the built-in photo (coffee.png)", ()
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
            if samples_per_sequence is not None and stride:
                raise ValueError(
                    f"--samples-per-sequence {samples_per_sequence} and blur.stride = {stride} "
                    f"({where}) both place the windows: --samples-per-sequence spreads that "
                    "many evenly over each sequence, blur.stride steps them that many frames "
                    "apart from the first; give one")
            seqs = find_sequences(root, exclude)
            named = frames_per_sample == FROM_NAME
            sizes = ([frames_from_name(frames, where) for _, frames in seqs] if named
                     else [frames_per_sample] * len(seqs))
            if all(len(frames) < n for (_, frames), n in zip(seqs, sizes, strict=True)):
                short = "".join(f"; {name} has {len(frames)}" for name, frames in seqs[:5])
                if named:
                    raise ValueError(
                        f"--input {root}: no sequence holds the yy frames its name "
                        f"GOPRxxxx_yy_zz asks for (blur.frames = '{FROM_NAME}', {where})"
                        f"{short}; give "
                        "GOPRO_Large_all sequences (every frame, GOPRxxxx_yy_zz/*.png), or set "
                        "blur.frames to a number")
                raise ValueError(
                    f"--input {root}: no <seq>/sharp/ folder with at least {frames_per_sample} "
                    f"images (blur.frames){short} (nor a GOPRO_Large_all GOPRxxxx_yy_zz/ or "
                    "RSBlur-style <session>/<id>/ folder of frames); lower blur.frames, or for "
                    "single photos use blur.mode = trajectory or kernel")
            total = sum(1 if len(frames) < n else samples_per_sequence
                        or (len(frames) - n) // (stride or n) + 1
                        for (_, frames), n in zip(seqs, sizes, strict=True))
            size = sizes if named else frames_per_sample
            found = _found(root, seqs)
            return Samples(total, lambda: _in_utf8(sequence_samples(seqs, size,
                                                                    samples_per_sequence,
                                                                    stride)),
                           _layouts(found), sum(len(frames) for _, frames in seqs), found)
        if mode == "none":
            found = find_blurred(root, masks, exclude)
            if not found:
                raise ValueError(f"--input {root}: blur.mode = none found no {BLURRED_EXPECTED}")
            return Samples(len(found) * samples_per_photo,
                           lambda: _in_utf8(_blurred_samples(found, samples_per_photo)),
                           "already-blurred images (" + ", ".join(
                               dict.fromkeys(blurred_layout(b) for b in found)) + ")",
                           len(found))
        walked = list(input_folders.walk(root, input_folders.identity(exclude)))
        photos = [(p.relative_to(root).with_suffix("").as_posix(), p)
                  for p, is_dir in walked
                  if not is_dir and p.suffix.lower() in input_folders.IMAGE_SUFFIXES]
        if not photos:
            suffixes = ", ".join(input_folders.IMAGE_SUFFIXES)
            raise ValueError(f"--input {root}: no images ({suffixes}) found in it or its "
                             "subfolders")
        sequences = _found(root, _sequences(root, walked))
        layout = f"photos, {_layouts(sequences)} among them" if sequences else "photos"
    return Samples(len(photos) * samples_per_photo,
                   lambda: _in_utf8(_photo_samples(photos, samples_per_photo)), layout,
                   len(photos), sequences)


def check_layout(found: Samples, root: Path | None, mode: str, where: str, *,
                 average_gopro_large_sharp: bool = False,
                 frames_as_photos: bool = False) -> None:
    """Refuse an input whose layout the blur mode would misread, before any sample.

    * Mode ``average`` over GOPRO_Large (``<seq>/sharp/`` beside ``<seq>/blur/``): those sharp
      frames are the ground truth of blurs averaged already, one per blurred image with gaps
      between them (DeepDeblur_release#22), so their average ghosts; allowed with
      ``average_gopro_large_sharp``.
    * A photo mode (``trajectory``, ``kernel``) over frame sequences (two frames or more):
      each frame would become a photo of its own; allowed with ``frames_as_photos``.

    Args:
        found: :func:`find_samples`' answer for ``root``.
        root: the input folder (None: the built-in photo).
        mode: ``blur.mode``.
        where: where the mode is set, for the message (``scene file s.toml``).
        average_gopro_large_sharp: average GOPRO_Large's sharp frames all the same.
        frames_as_photos: take sequences' frames as photos all the same.

    Raises:
        ValueError: one line naming the input, what it holds, why, and the two ways out.
    """
    if mode == "average" and not average_gopro_large_sharp:
        large = [f for f in found.sequences if f.layout == GOPRO_LARGE]
        if large:
            seq = shown(large[0].name)
            raise ValueError(
                f"--input {root}: {seq}/sharp/ sits beside {seq}/blur/ as in GOPRO_Large "
                f"({len(large)} such sequence(s)), whose sharp frames are the ground truth of "
                "blurs averaged already, one per blurred image with gaps between them "
                "(DeepDeblur_release#22), so averaging them makes ghosted blur; average "
                "GOPRO_Large_all's frames instead (every frame, GOPRxxxx_yy_zz/*.png) with "
                f"blur.frames = \"{FROM_NAME}\" ({where}), or pass --average-gopro-large-sharp "
                "to average these anyway")
    if mode in ("trajectory", "kernel") and not frames_as_photos:
        sequences = [f for f in found.sequences if f.frames >= 2]
        if sequences:
            large = any(f.layout == GOPRO_LARGE for f in sequences)
            raise ValueError(
                f"--input {root}: holds {len(sequences)} frame sequence(s) "
                f"({_layouts(tuple(sequences))}; {sum(f.frames for f in sequences)} frames, "
                f"the first {shown(sequences[0].name)}) but blur.mode = '{mode}' ({where}) "
                "blurs single photos, so each frame would become a sample of its own; set "
                "blur.mode = 'average' in the scene to average consecutive frames (as the "
                "built-in scene rsblur does"
                + ("; for GoPro, over GOPRO_Large_all with blur.frames = "
                   f"\"{FROM_NAME}\"" if large else "")
                + "), or pass --frames-as-photos to blur each frame as a photo")


def _text(value) -> bool:
    """Whether ``value`` is a string that UTF-8 can hold (no lone surrogates)."""
    if not isinstance(value, str):
        return False
    try:
        value.encode()
    except UnicodeEncodeError:
        return False
    return True
