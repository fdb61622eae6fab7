"""Finding inputs on disk, and writing a generated set: image pairs and a JSONL manifest."""

from __future__ import annotations

import dataclasses
import json
from importlib import resources
from pathlib import Path

import numpy as np

from gpu_blur.imageio import write_image
from gpu_blur.params import ARRAY_PARAMS

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")


@dataclasses.dataclass(frozen=True)
class SampleSpec:
    """One sample to make: its index (which, with the seed, fixes its draws) and its inputs."""

    index: int
    name: str
    inputs: tuple[Path, ...]


def default_photo() -> Path:
    """The built-in input: 'coffee' by Rachel Michetti, CC0, as shipped by scikit-image.

    A 600 x 400 photograph whose spoon and cup rim have specular highlights that clip.
    """
    return Path(str(resources.files("gpu_blur").joinpath("data/coffee.png")))


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def find_sequences(root: Path) -> list[tuple[str, list[Path]]]:
    """GoPro-style sequences: every ``.../<seq>/sharp/`` folder under ``root``, sorted.

    Returns:
        (sequence name relative to root, its frames sorted by file name) pairs.
    """
    seqs = []
    for sharp in sorted(root.rglob("sharp")):
        if sharp.is_dir():
            frames = _images(sharp)
            if frames:
                seqs.append((sharp.parent.relative_to(root).as_posix() or root.name, frames))
    return seqs


def discover(root: Path | None, mode: str, frames_per_sample: int,
             samples_per_photo: int = 1) -> list[SampleSpec]:
    """The samples a folder yields for a blur mode.

    Args:
        root: input folder, or None for the built-in photo.
        mode: ``average`` takes consecutive, non-overlapping windows of ``frames_per_sample``
            frames from every ``<seq>/sharp/`` folder; ``kernel`` and ``trajectory`` take every
            image under ``root`` (recursively) as a photo.
        frames_per_sample: frames per window (mode ``average``).
        samples_per_photo: samples made from each photo (each with its own draws).

    Raises:
        ValueError: naming the folder when it is missing or yields no sample.
    """
    if mode == "none":
        raise ValueError("gpu-blur generate makes blur from sharp input; blur.mode = none "
                         "(already blurred input) is available from Python: "
                         "gpu_blur.synthesize({'blurred': ..., 'mask': ...}, scene)")
    if root is None:
        if mode == "average":
            raise ValueError("the built-in input is a single photo; blur.mode = average needs "
                             "--input with <seq>/sharp/*.png sequences")
        photos = [("coffee", default_photo())]
    else:
        if not root.is_dir():
            raise ValueError(f"--input {root}: no such folder")
        if mode == "average":
            specs = []
            for name, frames in find_sequences(root):
                for start in range(0, len(frames) - frames_per_sample + 1, frames_per_sample):
                    window = tuple(frames[start:start + frames_per_sample])
                    specs.append(SampleSpec(len(specs), f"{name}/{window[0].stem}", window))
            if not specs:
                raise ValueError(
                    f"--input {root}: no <seq>/sharp/ folder with at least {frames_per_sample} "
                    "images (blur.frames); for single photos use blur.mode = trajectory or kernel")
            return specs
        photos = [(p.relative_to(root).with_suffix("").as_posix(), p)
                  for p in sorted(root.rglob("*")) if p.suffix.lower() in IMAGE_SUFFIXES]
        if not photos:
            raise ValueError(f"--input {root}: no images ({', '.join(IMAGE_SUFFIXES)}) found")
    specs = []
    for name, path in photos:
        for k in range(samples_per_photo):
            suffix = f"_{k}" if samples_per_photo > 1 else ""
            specs.append(SampleSpec(len(specs), f"{name}{suffix}", (path,)))
    return specs


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    return value


class DatasetWriter:
    """Writes ``blur/`` and ``sharp/`` PNGs, array parameters and ``manifest.jsonl``.

    Each sample's files are written completely (temporary name, then rename) before its
    manifest line is appended and flushed, so the manifest only lists finished samples.
    """

    def __init__(self, out: Path, bits: int, overwrite: bool = False):
        self.out, self.bits = out, bits
        self.manifest_path = out / "manifest.jsonl"
        if self.manifest_path.exists() and self.manifest_path.stat().st_size and not overwrite:
            raise ValueError(f"{self.manifest_path} already exists; choose another --output or "
                             "pass --overwrite to replace the set")
        for sub in ("blur", "sharp"):
            (out / sub).mkdir(parents=True, exist_ok=True)
        self.manifest = open(self.manifest_path, "w")

    def write(self, spec: SampleSpec, result, record: dict) -> dict:
        """Write one sample and its manifest line; returns the line as a dict."""
        ext = ".png" if self.bits else ".tiff"
        stem = spec.name.replace("/", "_")
        blurred = Path("blur") / f"{spec.index:06d}_{stem}{ext}"
        sharp = Path("sharp") / f"{spec.index:06d}_{stem}{ext}"
        write_image(self.out / blurred, result.blurred, self.bits)
        write_image(self.out / sharp, result.sharp, self.bits)
        arrays = {k: result.params[k] for k in ARRAY_PARAMS if k in result.params}
        line = {
            "index": spec.index,
            "name": spec.name,
            "inputs": [str(p) for p in spec.inputs],
            "blurred": blurred.as_posix(),
            "sharp": sharp.as_posix(),
            **record,
            "params": {k: _jsonable(v) for k, v in result.params.items() if k not in arrays},
            "stages": [s.name for s in result.plan.stages if s.kept],
        }
        if arrays:
            (self.out / "params").mkdir(exist_ok=True)
            rel = Path("params") / f"{spec.index:06d}_{stem}.npz"
            tmp = self.out / "params" / f".{spec.index:06d}.part.npz"
            np.savez(tmp, **arrays)
            tmp.replace(self.out / rel)
            line["arrays"] = rel.as_posix()
        self.manifest.write(json.dumps(line) + "\n")
        self.manifest.flush()
        return line

    def close(self) -> None:
        """Close the manifest."""
        self.manifest.close()
