"""Finding already-blurred images: the RSBlur authors' layouts, RealBlur pairs, datalists.

What blur mode none reads (:func:`gpu_blur.discovery.find_samples`) and what
:mod:`gpu_blur.datasets`' ``BlurredImages`` and ``RealBlurPairs`` serve: each blurred image with
its saturation mask and sharp reference.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from gpu_blur import files, input_folders

__all__ = ["BLURRED_EXPECTED", "BLURRED_LAYOUTS", "BlurredLayout", "BlurredSample",
           "blurred_layout", "find_blurred", "find_realblur_pairs", "read_datalist"]

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
    images = input_folders.images(folder)
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
    for folder, is_dir in input_folders.walk(root, input_folders.identity(exclude)):
        layout = by_folder.get(folder.name) if is_dir else None
        if layout is None:
            continue
        base = folder.parent
        prefix = "" if base == root else base.relative_to(root).as_posix() + "/"
        for blurred in input_folders.images(folder):
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


def find_realblur_pairs(root: Path) -> list[BlurredSample]:
    """RealBlur's evaluation pairs under ``root``, in natural order.

    ``<scene>/blur/blur_<n>.png`` with ``<scene>/gt/gt_<n>.png`` (RealBlur_J and RealBlur_R,
    Rim et al. ECCV 2020), named ``<scene>/blur_<n>``; a blurred image without its ground
    truth has ``problem`` set, naming the file expected.
    """
    pairs = []
    for folder, is_dir in input_folders.walk(root, None):
        if not (is_dir and folder.name == "blur"):
            continue
        prefix = "" if folder.parent == root else folder.parent.relative_to(root).as_posix() + "/"
        for blurred in input_folders.images(folder):
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


def blurred_layout(sample: BlurredSample) -> str:
    """The data set a blurred image's folder is named after (:data:`BLURRED_LAYOUTS`)."""
    folder = sample.blurred.parent.name
    return next(lay.dataset for lay in BLURRED_LAYOUTS if lay.blurred == folder)
