"""Input checks: a sample's inputs read, laid out, sized and checked before any pass.

:class:`Inputs` is one sample's inputs, as read (:func:`gather`, :func:`synthesize`'s) or
split from a batch (:mod:`gpu_blur.synthesis.batches`); a kernel backend's device checks them
by counts (:meth:`~gpu_blur.synthesis.resident.ResidentPath.prepared`), or by the batch's own
reductions where it lies (:class:`ValueRanges`), the host path here (:func:`checked_on_host`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from gpu_blur import arrays
from gpu_blur.backends import OnDevice
from gpu_blur.image_arrays import check_image, check_layout, in_unit_range, unit_values
from gpu_blur.image_reading import read_image
from gpu_blur.planning import raw_round_trip
from gpu_blur.scene import FROM_NAME, Scene

__all__ = ["Inputs", "ValueRanges", "bad_values", "check_codes", "checked", "checked_on_host",
           "codes_only", "even", "frame_count", "gather", "kept_size", "reaches_clip_level",
           "sample_indices"]


class ValueRanges:
    """Each sample's lowest and highest value in a batch's float inputs, one reduction each.

    Measured where the batch lies, by its own library
    (:meth:`~gpu_blur.synthesis.batches.BatchIO.value_ranges`); the device path reads them
    instead of counting those inputs on the kernel backend's device. NaN anywhere in a
    sample's input makes both of its values NaN (the reductions propagate it).

    Args:
        keys: the inputs measured, of ``frames``, ``mask`` and ``sharp``.
        read: returns {key: B x 2 float64 array, each sample's (lowest, highest)}; called
            once, when first needed (it may wait for the device that reduced them).
    """

    def __init__(self, keys, read: Callable[[], dict[str, np.ndarray]]):
        self.keys = frozenset(keys)
        self._read, self._values = read, None

    def flags(self, key: str, b: int) -> tuple[bool, bool, bool]:
        """(bad, clips, above 0) of sample ``b``'s input ``key``, as the device's counts say.

        bad: a value NaN, infinite or outside [0, 1]; clips: one at or above 1.0 (the clip
        level of float values); above 0: one above 0 (a mask's "anything to saturate").
        """
        if self._values is None:
            self._values = self._read()
        lowest, highest = self._values[key][b]
        return not in_unit_range(lowest, highest), bool(highest >= 1), bool(highest > 0)


@dataclasses.dataclass
class Inputs:
    """One sample's inputs: frames (a stack for mode average), mask, sharp, and their names.

    Host arrays as stored (:func:`gpu_blur.image_arrays.check_layout`), or after
    :meth:`~gpu_blur.synthesis.resident.ResidentPath.put`,
    :class:`~gpu_blur.backends.OnDevice` values. ``ranges``: (the batch's
    :class:`ValueRanges`, this sample's place in it) where its float inputs were measured.
    """

    frames: object
    mask: object
    sharp: object
    names: dict
    label: str = ""
    saturated: bool = False
    ranges: tuple[ValueRanges, int] | None = None


def gather(inputs, scene: Scene) -> Inputs:
    """``synthesize``'s inputs, read, laid out as the blur mode wants, values unchecked.

    Frames keep their stored dtype (uint8/uint16 codes, or floats in [0, 1]).
    """
    mode = scene.blur.mode
    if mode == "none":
        if not isinstance(inputs, Mapping) or "blurred" not in inputs:
            raise ValueError("blur.mode = none takes a mapping {'blurred': image, 'mask': "
                             "optional mask, 'sharp': optional sharp image}")
        unknown = [k for k in inputs if k not in ("blurred", "mask", "sharp")]
        if unknown:
            raise ValueError(f"blur.mode = none: unknown input {unknown[0]!r}; the inputs are "
                             "'blurred', 'mask' (optional) and 'sharp' (optional)")
        given = [k for k in ("blurred", "mask", "sharp") if inputs.get(k) is not None]
        names = {k: _name(inputs[k], "blurred image" if k == "blurred" else k) for k in given}
        loaded = {k: _load(inputs[k], names[k]) for k in given}
        _same_shape(list(loaded.values()), [_name(inputs[k], k) for k in given])
        return Inputs([loaded["blurred"]], loaded.get("mask"), loaded.get("sharp"),
                       {"frames": [names["blurred"]], "mask": names.get("mask"),
                        "sharp": names.get("sharp")})
    if isinstance(inputs, (str, Path, np.ndarray)):
        inputs = [inputs]
    if not isinstance(inputs, Sequence) or len(inputs) == 0:
        raise ValueError(f"blur.mode = {mode} needs a non-empty list of images")
    if mode != "average" and len(inputs) != 1:
        raise ValueError(f"blur.mode = {mode} blurs one photo; got {len(inputs)} images")
    if mode == "average":
        frame_count(len(inputs), scene)
    names = [_name(x, f"frame {i}") for i, x in enumerate(inputs)]
    frames = [_load(x, n) for x, n in zip(inputs, names, strict=True)]
    _same_shape(frames, names)
    if len({f.dtype for f in frames}) > 1:  # one dtype per sample
        frames = [unit_values(check_image(f, n)) for f, n in zip(frames, names, strict=True)]
    return Inputs(frames, None, None, {"frames": names})


def _load(item, what: str) -> np.ndarray:
    """An input as stored (uint8/uint16 codes, or floats), its layout checked."""
    if isinstance(item, (str, Path)):
        return check_layout(read_image(item), str(item))
    arrays.check_dense(item, what)
    return check_layout(np.asarray(item), what)


def _name(item, what: str) -> str:
    """How messages name an input: its file, else its role (``frame 2``)."""
    return str(item) if isinstance(item, (str, Path)) else what


def _same_shape(images, names):
    for img, name in zip(images[1:], names[1:], strict=True):
        if img.shape != images[0].shape:
            raise ValueError(f"{name} is {img.shape[1]} x {img.shape[0]} (width x height) but "
                             f"{names[0]} is {images[0].shape[1]} x {images[0].shape[0]}; all "
                             "inputs of a sample must have the same size: crop or resize the "
                             "odd one, or leave it out")


def frame_count(count: int, scene: Scene) -> None:
    """Refuse a sample of mode average whose frame count is not the scene's ``blur.frames``.

    Under ``blur.frames = "from-name"`` every count is the scene's: the sequence's name set it
    when the window was cut (:func:`gpu_blur.discovery.frames_from_name`).
    """
    wanted = scene.blur.frames
    if count != wanted and wanted != FROM_NAME:
        where = f"scene file {scene.path}" if scene.path else "the scene"
        raise ValueError(f"blur.frames = {wanted} ({where}) but this sample has {count} "
                         f"frames: pass {wanted}, or set blur.frames = {count}")


def check_codes(scene: Scene, codes: bool) -> None:
    """Refuse ``codes=True`` for a scene without 8- or 16-bit output."""
    if codes and scene.output.bits not in (8, 16):
        raise ValueError(f"codes=True returns the output's 8- or 16-bit codes; this scene has "
                         f"output.bits = {scene.output.bits} (0 keeps float values): "
                         "set output.bits = 8 or 16, or leave codes out")


def kept_size(scene: Scene, shape) -> tuple[int, int]:
    """The (height, width) of ``... x H x W x 3`` inputs that a sample keeps.

    The RAW round trip keeps even sides (the Bayer 2 x 2 cell), and refuses less than 2 x 2.
    """
    h, w = shape[-3:-1]
    if raw_round_trip(scene):
        h, w = h - h % 2, w - w % 2
        if h < 2 or w < 2:
            raise ValueError(f"input of {tuple(shape[-3:-1])} is too small for the Bayer "
                             "steps (need at least 2 x 2)")
    return h, w


def checked_on_host(scene: Scene, item: Inputs) -> Inputs:
    """A sample's host inputs checked, of one dtype, cut to the size it keeps, clip-tested."""
    names, label = item.names, item.label
    try:
        frames = [check_image(f, n) for f, n in zip(item.frames, names["frames"],
                                                    strict=True)]
        mask = None if item.mask is None else unit_values(check_image(item.mask,
                                                                      names["mask"]))
        sharp = (frames[len(frames) // 2] if item.sharp is None
                 else check_image(item.sharp, names["sharp"]))
    except ValueError as e:
        raise ValueError(f"{label}{e}") from None
    if len({f.dtype for f in frames}) > 1:
        frames = [unit_values(f) for f in frames]
    h, w = kept_size(scene, frames[0].shape)
    frames = [f[:h, :w] for f in frames]
    sharp = sharp[:h, :w]
    mask = None if mask is None else mask[:h, :w]
    return Inputs(frames, mask, sharp, names, label, reaches_clip_level(frames, mask))


def checked() -> None:
    """Nothing left to check (:meth:`~gpu_blur.synthesis.synthesizer.Synthesizer._prepared`)."""


def bad_values(image: OnDevice, item: Inputs, key: str):
    """Raise check_image's message for a device input whose counts found bad values."""
    names = item.names
    host = image.numpy(image.dtype)
    parts = [host] if host.ndim == 3 else list(host)
    labels = ([names["frames"][0]] if host.ndim == 3 else names["frames"]) \
        if key == "frames" else [names[key]]
    for part, name in zip(parts, labels, strict=True):
        try:
            check_image(part, name)
        except ValueError as e:
            raise ValueError(f"{item.label}{e}") from None
    raise ValueError(f"{item.label}{key}: values outside [0, 1] or not finite")


def reaches_clip_level(frames, mask) -> bool:
    """Whether any input pixel reaches the clip level (auto saturation runs only then)."""
    if mask is not None:
        return bool(np.any(np.asarray(mask) > 0))
    top = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}.get(frames[0].dtype, 1.0)
    return any(bool(np.any(f >= top)) for f in frames)


def codes_only(item: Inputs) -> bool:
    """Whether a sample's host inputs are all 8/16-bit codes (no values to check)."""
    inputs = [*item.frames] if isinstance(item.frames, list) else [item.frames]
    return all(x.dtype.kind == "u" for x in [*inputs, item.mask, item.sharp] if x is not None)


def even(image, like: OnDevice):
    """A host mask or sharp image cut to the frames' (even) size."""
    if isinstance(image, np.ndarray):
        h, w = like.shape[-3:-1]
        return np.ascontiguousarray(image[:h, :w])
    return image


def sample_indices(indices, first_index, count: int, name: str = "indices",
                   what: str = "sample index") -> list[int]:
    """A batch's sample indices as Python ints, each checked: a float is refused, not cut.

    ``name`` and ``what``: the argument and what it holds, for messages (a batch's
    ``sequences``, its sequence indices, are checked alike).
    """
    if indices is None:
        if not _whole(first_index) or not 0 <= first_index <= 2**32 - count:
            raise ValueError(f"first_index = {first_index!r}: needs an int, 0 <= first_index "
                             f"and first_index + {count} (the batch) <= 2**32")
        return list(range(int(first_index), int(first_index) + count))
    if hasattr(indices, "tolist"):  # a numpy, torch or CuPy array: its values as Python's
        indices = indices.tolist()
    if isinstance(indices, str) or not isinstance(indices, Sequence):
        raise ValueError(f"{name}: one {what} per sample, a list or 1-D array of ints; "
                         f"got {indices!r}")
    if len(indices) != count:
        many = what.removesuffix("index") + "indices"
        raise ValueError(f"{name}: {len(indices)} {many} for a batch of {count}; give one per "
                         "sample")
    for b, index in enumerate(indices):
        if not _whole(index) or not 0 <= index < 2**32:
            raise ValueError(f"{name}[{b}] = {index!r}: a {what} is an int in "
                             "[0, 2**32); pass ints (a float index is not rounded)")
    return [int(index) for index in indices]


def _whole(x) -> bool:
    """Whether ``x`` is an int (Python's or numpy's; a bool is not)."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)
