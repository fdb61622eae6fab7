"""Map-style data sets of the published deblurring layouts, for training loops (no torch here).

Each class has ``__len__`` and ``__getitem__``, so it serves as a ``torch.utils.data.Dataset``
in DataLoader workers (CPU) without importing torch. Discovery is :mod:`gpu_blur.discovery`'s,
as ``gpu-blur generate`` finds its inputs.

An item is a tuple: the item's index (an ``int``, 0 <= index < len) first, then numpy arrays
of the stored codes, channels-last, RGB and contiguous: ``uint8`` for 8-bit files, ``uint16``
for 16-bit ones (float TIFFs: ``float32`` in [0, 1]).

- :class:`Photos`: ``(index, image)``, image H x W x 3.
- :class:`SharpSequences`: ``(index, frames)``, frames F x H x W x 3 (F = ``frames``).
- :class:`BlurredImages`: ``(index, blurred, mask, sharp)``, each H x W x 3 (the mask as
  stored: 8-bit codes, value x 255); with ``masks=False`` ``(index, blurred, sharp)``.
- :class:`RealBlurPairs`: ``(index, blurred, sharp)``, each H x W x 3.

H x W is ``crop`` x ``crop`` when a crop is given, else the file's size. A DataLoader stacks
items into an int64 tensor of B indices and B x H x W x 3 (B x F x H x W x 3) tensors of the
same dtype, which :class:`gpu_blur.torch.RealisticBlur` takes as they are (it reads the layout
from the shape), on the CPU or moved to a GPU, drawing the blur, noise and ISP of each sample
from (seed, epoch, index).

Seeded random crops and flips are fixed by (seed, epoch, index) too (:func:`epoch_seed`), so
a run repeats and each epoch sees other crops. Crop offsets are even: a crop then starts on
the 2 x 2 Bayer grid of the whole image, so the synthetic mosaic (a fixed ``isp.pattern``)
sits on the photosites it would cover in a whole-image run, and the real camera's own CFA
traces in RSBlur and RealBlur images keep their phase relative to it. Crop sizes are even
for the same reason (the RAW round trip cuts an odd last row or column). A flip mirrors the
image, and with it that phase, as the authors' own flip augmentation does.

Call :meth:`set_epoch` before each epoch's loader is iterated: workers get the data set as it
is when iteration starts (with ``persistent_workers=True`` they keep the epoch they started
with).
"""

from __future__ import annotations

import operator
from pathlib import Path

import numpy as np

from gpu_blur.blurred_inputs import (
    BLURRED_EXPECTED,
    BlurredSample,
    find_blurred,
    find_realblur_pairs,
    read_datalist,
)
from gpu_blur.discovery import (
    SampleSpec,
    Window,
    find_samples,
    find_sequences,
    sequence_samples,
)
from gpu_blur.image_reading import read_image

__all__ = ["BlurredImages", "Photos", "RealBlurPairs", "SharpSequences", "epoch_seed"]

_MASK64 = (1 << 64) - 1
#: Mixed into the crop generator's seed, so crops are drawn apart from the pipeline's draws.
_CROP_STREAM = 0x63726F70  # "crop"
#: How many problems a refused data set lists (the count says how many there are).
_SHOWN = 3


def epoch_seed(seed: int, epoch: int) -> int:
    """The dataset seed of one epoch: SplitMix64 of ``seed`` mixed with ``epoch``.

    SplitMix64's constants and steps (Steele, Lea and Flood, OOPSLA 2014), applied to the
    seed plus the epoch times the golden-ratio increment: epochs 0, 1, 2, ... of one seed get
    unrelated 64-bit seeds.
    """
    if not (0 <= seed < 2**64) or epoch < 0:
        raise ValueError(f"seed must be in [0, 2**64) and epoch >= 0; got seed {seed}, epoch "
                         f"{epoch}")
    z = (seed + (epoch + 1) * 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _checked_root(root, what: str) -> Path:
    root = Path(root)
    if not root.is_dir():
        state = "is a file, not a folder" if root.exists() else "no such folder"
        raise ValueError(f"{what} {root}: {state}; pass the folder that holds the data set")
    return root


def _refuse_problems(root: Path, problems: list[str]) -> None:
    """Refuse a data set with samples that cannot be made, listing the first few.

    Each problem names its file and its fix.
    """
    if problems:
        shown = f", the first {_SHOWN}" if len(problems) > _SHOWN else ""
        raise ValueError(f"{root}: {len(problems)} sample(s) cannot be used{shown}: "
                         + "; ".join(problems[:_SHOWN]))


class _Augmented:
    """Crops and flips fixed by (seed, epoch, index); subclasses list files and decode."""

    def __init__(self, crop: int | None, flips: bool, seed: int, epoch: int):
        if crop is not None and (isinstance(crop, bool) or not isinstance(crop, int)
                                 or crop < 2 or crop % 2):
            raise ValueError(f"crop = {crop!r}: give an even number of pixels >= 2 (crops "
                             "start and end on the 2 x 2 Bayer grid), or None for whole images")
        epoch_seed(seed, epoch)  # checks both
        self.crop, self.flips, self.seed, self.epoch = crop, bool(flips), seed, epoch

    def set_epoch(self, epoch: int) -> None:
        """Draw the crops and flips of ``epoch`` from now on."""
        epoch_seed(self.seed, epoch)
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self._items)

    def _index(self, index) -> int:
        index = operator.index(index)
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} is outside this data set of {len(self)} items")
        return index

    def augmentation(self, index: int, height: int, width: int) -> tuple[int, int, bool, bool]:
        """(top, left, flip left-right, flip up-down) of item ``index`` of an image this size.

        The four values are drawn every time (from a generator seeded by the epoch's seed and
        the index), so turning flips off leaves the crops where they were.
        """
        rng = np.random.default_rng([_CROP_STREAM, epoch_seed(self.seed, self.epoch), index])
        rows = cols = 0
        if self.crop is not None:
            rows, cols = (height - self.crop) // 2, (width - self.crop) // 2
        top, left = 2 * int(rng.integers(0, rows + 1)), 2 * int(rng.integers(0, cols + 1))
        mirror, upside_down = (bool(b) for b in rng.integers(0, 2, 2))
        return top, left, mirror and self.flips, upside_down and self.flips

    def _augmented(self, index: int, images: list[np.ndarray], names: list) -> list[np.ndarray]:
        """The same crop and flips on each image (H x W x 3, or F x H x W x 3)."""
        height, width = images[0].shape[-3:-1]
        for image, name in zip(images[1:], names[1:], strict=True):
            if image.shape[-3:-1] != (height, width):
                raise ValueError(f"{name} is {image.shape[-2]} x {image.shape[-3]} (width x "
                                 f"height) but {names[0]} is {width} x {height}; the files "
                                 "of one sample must have one size")
        if self.crop is not None and (height < self.crop or width < self.crop):
            raise ValueError(f"{names[0]}: {width} x {height} (width x height) is smaller than "
                             f"crop = {self.crop}; lower crop, or leave such images out")
        top, left, mirror, upside_down = self.augmentation(index, height, width)
        size_h, size_w = (self.crop, self.crop) if self.crop is not None else (height, width)
        out = []
        for image in images:
            part = image[..., top:top + size_h, left:left + size_w, :]
            if mirror:
                part = part[..., ::-1, :]
            if upside_down:
                part = part[..., ::-1, :, :]
            out.append(np.ascontiguousarray(part))  # no negative strides for torch
        return out


class SharpSequences(_Augmented):
    """Windows of ``frames`` consecutive sharp frames, for blur mode average.

    GoPro_Large's ``<seq>/sharp/*.png``, GOPRO_Large_all's ``GOPRxxxx_yy_zz/*.png`` and RSBlur's
    ``<session>/<id>/*.png`` (the sharp frames of one real blurred image), found as
    ``gpu-blur generate`` finds them
    (:func:`gpu_blur.discovery.find_sequences`), windows as ``--samples-per-sequence`` takes
    them, or ``stride`` frames apart (``blur.stride``; 0: ``frames``, side by side). Item:
    ``(index, frames)``, frames F x H x W x 3 (F = ``frames``), the stored codes (uint8 for
    8-bit PNGs), for blur mode average; :meth:`window` says which sequence an item's frames
    come from and where (its ``sequence_index`` is what a per-sequence scene's
    ``Synthesizer`` takes as ``sequences``). GOPRO_Large's ``sharp/`` frames are one per
    blurred image, with gaps between them (``gpu-blur generate`` refuses to average them):
    give GOPRO_Large_all's frames for realistic blur.

    Raises:
        ValueError: naming the folder when it holds no sequence of ``frames`` frames, or the
            sequences too short.
    """

    def __init__(self, root, frames: int = 9, *, samples_per_sequence: int | None = None,
                 stride: int = 0, crop: int | None = None, flips: bool = False, seed: int = 0,
                 epoch: int = 0):
        super().__init__(crop, flips, seed, epoch)
        root = _checked_root(root, "SharpSequences")
        if samples_per_sequence is not None and samples_per_sequence < 1:
            raise ValueError(f"samples_per_sequence = {samples_per_sequence}: must be >= 1")
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 0:
            raise ValueError(f"stride = {stride!r}: frames between windows' first frames, an "
                             "int >= 0 (0: frames, windows side by side)")
        if samples_per_sequence is not None and stride:
            raise ValueError("samples_per_sequence and stride both place the windows: give "
                             "one")
        sequences = find_sequences(root)
        if not sequences:
            raise ValueError(f"{root}: no sequence of sharp frames (GoPro's <seq>/sharp/*.png "
                             "or RSBlur's <session>/<id>/*.png) in it or its subfolders")
        self._items: list[SampleSpec] = list(sequence_samples(sequences, frames,
                                                              samples_per_sequence, stride))
        _refuse_problems(root, [s.problem for s in self._items if s.problem])

    def window(self, index) -> Window:
        """Item ``index``'s sequence (name and index) and its place there (window, first frame)."""
        return self._items[self._index(index)].window

    def __getitem__(self, index) -> tuple[int, np.ndarray]:
        index = self._index(index)
        paths = self._items[index].inputs
        frames = np.stack(self._augmented(index, [read_image(p) for p in paths], list(paths)))
        return index, frames


class Photos(_Augmented):
    """Sharp photos, for blur modes kernel and trajectory.

    Every image under ``root`` (in natural order), or the built-in photo when ``root`` is
    None (scikit-image's "coffee", 400 x 600), each ``samples_per_photo`` times (with other
    crops and draws). Item: ``(index, image)``, image H x W x 3, the stored codes (uint8 for
    8-bit files, as the built-in photo is).
    """

    def __init__(self, root=None, *, samples_per_photo: int = 1, crop: int | None = None,
                 flips: bool = False, seed: int = 0, epoch: int = 0):
        super().__init__(crop, flips, seed, epoch)
        if samples_per_photo < 1:
            raise ValueError(f"samples_per_photo = {samples_per_photo}: must be >= 1")
        folder = None if root is None else _checked_root(root, "Photos")
        try:
            found = find_samples(folder, "trajectory", 1, samples_per_photo)
        except ValueError as e:  # its words name the command's option
            raise ValueError(str(e).removeprefix("--input ")) from None
        self._items: list[SampleSpec] = found.take()

    def __getitem__(self, index) -> tuple[int, np.ndarray]:
        index = self._index(index)
        (path,) = self._items[index].inputs
        (image,) = self._augmented(index, [read_image(path)], [path])
        return index, image


class _Pairs(_Augmented):
    """Blurred images with their sharp references (and masks).

    The common part of :class:`BlurredImages` and :class:`RealBlurPairs`.
    """

    masks = False

    def __getitem__(self, index) -> tuple:
        index = self._index(index)
        sample: BlurredSample = self._items[index]
        paths = [sample.blurred] + ([sample.mask] if self.masks else [])
        paths += [sample.sharp or sample.blurred]
        return (index, *self._augmented(index, [read_image(p) for p in paths], paths))


class BlurredImages(_Pairs):
    """Already-blurred images with their saturation masks, for blur mode none.

    The RSBlur authors' layouts (:data:`gpu_blur.blurred_inputs.BLURRED_LAYOUTS`): GoPro_INTER_ABME
    ``<seq>/<id>/avg_inter_img/``, RSBlur ``<session>/<id>/avg65_img/`` and GoPro_U
    ``centroid_blurred_img/``, each image's mask under the same name in the ``*_mask_100/``
    folder beside it (8-bit codes: value / 255, as the authors read them) and its sharp
    reference in ``gt/`` or ``target_img/`` (without that folder, the blurred image again, as
    blur mode none takes it). Item: ``(index, blurred, mask, sharp)``, each H x W x 3 as
    stored (uint8 for 8-bit files); with ``masks=False`` (no saturation synthesis) ``(index,
    blurred, sharp)`` and no mask is read.

    Raises:
        ValueError: naming the folder when it holds none of these layouts, or the samples
            whose mask or sharp image is missing.
    """

    def __init__(self, root, *, masks: bool = True, crop: int | None = None,
                 flips: bool = False, seed: int = 0, epoch: int = 0):
        super().__init__(crop, flips, seed, epoch)
        root = _checked_root(root, "BlurredImages")
        self.masks = bool(masks)
        self._items: list[BlurredSample] = find_blurred(root, self.masks)
        if not self._items:
            raise ValueError(f"{root}: no {BLURRED_EXPECTED}, in it or its subfolders")
        _refuse_problems(root, [s.problem for s in self._items if s.problem])


class RealBlurPairs(_Pairs):
    """RealBlur's blurred/sharp evaluation pairs (RealBlur_J, RealBlur_R).

    ``<scene>/blur/blur_<n>.png`` with ``<scene>/gt/gt_<n>.png`` under ``root``, or the pairs a
    ``datalist`` names (the authors' ``<sharp> <blurred>`` text files, paths relative to
    ``root``), in the list's order. Item: ``(index, blurred, sharp)``, each H x W x 3 as
    stored (uint8 for RealBlur's 8-bit PNGs).

    Raises:
        ValueError: naming the folder or list when it gives no pair, or the pairs whose files
            are missing.
    """

    def __init__(self, root, datalist=None, *, crop: int | None = None, flips: bool = False,
                 seed: int = 0, epoch: int = 0):
        super().__init__(crop, flips, seed, epoch)
        root = _checked_root(root, "RealBlurPairs")
        self._items: list[BlurredSample] = (read_datalist(Path(datalist), root) if datalist
                                            else find_realblur_pairs(root))
        if not self._items:
            where = f"datalist {datalist}" if datalist else str(root)
            raise ValueError(f"{where}: no pair found (RealBlur's <scene>/blur/blur_<n>.png "
                             "with <scene>/gt/gt_<n>.png)")
        _refuse_problems(root, [s.problem for s in self._items if s.problem])
