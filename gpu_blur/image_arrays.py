"""Images in memory: their layout and values checked, codes to [0, 1], RGB and BGR order."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["check_image", "check_layout", "in_unit_range", "refuse_values", "swap_red_blue",
           "to_unit", "unit_values"]


def swap_red_blue(image: np.ndarray) -> np.ndarray:
    """An H x W x 3 image with its first and last channels swapped (OpenCV's BGR <-> RGB).

    A new contiguous array of the same values: OpenCV's ``cvtColor`` for uint8, uint16 and
    float32 (a permutation; about 15 times faster than copying numpy's reversed view, 0.9
    against 16 ms for 1920 x 1200 uint8 on a 2-core VM), numpy for other dtypes.
    """
    if image.dtype in (np.uint8, np.uint16, np.float32):
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image[:, :, ::-1])


def _where(mask: np.ndarray) -> str:
    """'row r, column c, channel k' of the first True entry of an H x W x 3 mask."""
    row, col, ch = np.unravel_index(int(np.argmax(mask)), mask.shape)
    return f"row {row}, column {col}, channel {ch}"


def to_unit(image: np.ndarray, what: str = "image") -> np.ndarray:
    """uint8 / uint16 codes or floats in [0, 1] -> float64 in [0, 1], H x W x 3.

    Raises:
        ValueError: as :func:`check_image`.
    """
    return unit_values(check_image(image, what))


def unit_values(image: np.ndarray) -> np.ndarray:
    """A checked image (:func:`check_image`) as float64 in [0, 1]: codes / (2^bits - 1)."""
    if image.dtype == np.uint8:
        return image / 255.0
    if image.dtype == np.uint16:
        return image / 65535.0
    return np.asarray(image, dtype=np.float64)


def check_layout(image, what: str = "image") -> np.ndarray:
    """An H x W x 3 RGB input of uint8, uint16 or float values; the values are not read.

    Raises:
        ValueError: naming ``what`` and the way out, for a wrong shape or dtype.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        hint = (": for a grayscale image repeat it, np.repeat(x[..., None], 3, axis=2)"
                if image.ndim == 2 else "")
        raise ValueError(f"{what}: expected an H x W x 3 RGB array, got shape {image.shape}"
                         f"{hint}")
    if image.size == 0:
        raise ValueError(f"{what}: the image is empty (shape {image.shape})")
    if image.dtype not in (np.uint8, np.uint16) and not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"{what}: unsupported dtype {image.dtype}; use uint8, uint16 or float "
                         "in [0, 1] (e.g. x.astype(np.uint8) for 0..255 integers)")
    return image


def check_image(image: np.ndarray, what: str = "image") -> np.ndarray:
    """An H x W x 3 RGB input as stored: uint8 or uint16 codes, or float64 values in [0, 1].

    Frames stay in their integer codes until a backend reads them (kernels upload 1 or 2
    bytes per value and divide on the device); floats are checked and made float64. Kernel
    backends make the same checks where a batch lies (``KernelBackend.inspect`` on the
    device, or the batch's own reductions: :mod:`gpu_blur.synthesis.batches`) and come here
    only for the message.

    Floats cost the float64 copy and two reductions (their lowest and highest: NaN anywhere
    makes both NaN), over float32 values as stored; only an image that fails them is read
    again, to count and locate what is wrong (:func:`refuse_values`).

    Raises:
        ValueError: naming ``what``, with how many bad values there are, where the first is,
            and the way out, for a wrong shape or dtype, NaN or infinity, or floats outside
            [0, 1].
    """
    image = check_layout(image, what)
    if image.dtype in (np.uint8, np.uint16):
        return image
    # float32 and float64 are reduced as stored (numpy's SIMD loops; float32 is exact in
    # float64); other floats as the float64 they become (float16 has no fast loop)
    x = image if image.dtype in (np.float32, np.float64) else image.astype(np.float64)
    if not in_unit_range(x.min(), x.max()):
        refuse_values(x, what)
    return image.astype(np.float64) if x is image else x


def in_unit_range(lowest, highest) -> bool:
    """Whether values whose lowest and highest are these all lie in [0, 1].

    False when either is NaN (a NaN-propagating reduction's result for a NaN anywhere):
    every comparison with NaN is false. -0.0 passes, as ``x < 0`` passes it.
    """
    return bool(lowest >= 0) and bool(highest <= 1)


def refuse_values(image: np.ndarray, what: str = "image") -> None:
    """Raise :func:`check_image`'s message for a float H x W x 3 image with a bad value.

    The slow path, for an image already known to fail: counts NaN and infinities, negatives
    or values above 1 (in that order of precedence), and where the first lies.

    Raises:
        ValueError: that message; nothing is raised for an image of finite values in [0, 1].
    """
    x = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(x)
    if not finite.all():
        nan = int(np.count_nonzero(np.isnan(x)))
        inf = x.size - int(np.count_nonzero(finite)) - nan
        raise ValueError(
            f"{what}: {nan} NaN and {inf} infinite value(s), the first at "
            f"{_where(~finite)}; float images must be finite sRGB values in [0, 1]: fix "
            "what produced them, or replace them (np.nan_to_num(x, nan=0.0, posinf=1.0, "
            "neginf=0.0))")
    if x.min() < 0:
        low = x < 0
        raise ValueError(
            f"{what}: {np.count_nonzero(low)} negative value(s), the lowest "
            f"{x.min():.6g}, the first at {_where(low)}; float images must be sRGB values "
            "in [0, 1] (not mean-subtracted or normalized data): clip rounding errors "
            "with np.clip(x, 0, 1)")
    if x.max() > 1:
        high = x > 1
        raise ValueError(
            f"{what}: {np.count_nonzero(high)} value(s) above 1, the highest "
            f"{x.max():.6g}, the first at {_where(high)}; float images must be sRGB values "
            "in [0, 1]: pass 0..255 data as uint8 (or divide it by 255), clip small "
            "overshoots with np.clip(x, 0, 1)")

