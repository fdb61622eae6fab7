"""Reading and writing images: RGB order, integer codes to [0, 1] and back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from gpu_blur.reference.output import to_integers


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8- or 16-bit RGB image (PNG, JPEG, ...) as H x W x 3 in RGB order.

    Raises:
        ValueError: naming the file when it is missing, unreadable, or not 3-channel colour.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: not a readable image (corrupt, truncated or unknown format)")
    if image.ndim != 3 or image.shape[2] != 3:
        channels = 1 if image.ndim == 2 else image.shape[2]
        raise ValueError(f"{path}: has {channels} channel(s); gpu_blur needs RGB images "
                         "(convert grayscale or RGBA to RGB first)")
    return np.ascontiguousarray(image[:, :, ::-1])


def to_unit(image: np.ndarray, what: str = "image") -> np.ndarray:
    """uint8 / uint16 codes or floats in [0, 1] -> float64 in [0, 1], H x W x 3."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"{what}: expected an H x W x 3 RGB array, got shape {image.shape}")
    if image.dtype == np.uint8:
        return image / 255.0
    if image.dtype == np.uint16:
        return image / 65535.0
    if np.issubdtype(image.dtype, np.floating):
        x = image.astype(np.float64)
        if not np.all(np.isfinite(x)) or x.min() < 0 or x.max() > 1:
            raise ValueError(f"{what}: float images must be finite and within [0, 1]")
        return x
    raise ValueError(f"{what}: unsupported dtype {image.dtype}; use uint8, uint16 or float")


def write_image(path: str | Path, image: np.ndarray, bits: int) -> None:
    """Write an H x W x 3 RGB image in [0, 1]: PNG with 8/16 bits, or float32 TIFF for bits 0.

    The file appears complete or not at all (written to a temporary name, then renamed).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part{path.suffix}")
    if bits == 0:
        data = np.asarray(image, dtype=np.float32)[:, :, ::-1]
    else:
        data = to_integers(image, bits)[:, :, ::-1]
    if not cv2.imwrite(str(tmp), np.ascontiguousarray(data)):
        raise OSError(f"{path}: could not write the image")
    tmp.replace(path)


def read_kernel(path: str | Path) -> np.ndarray:
    """A blur kernel from ``.npy`` (2-D floats) or a grayscale image (PNG, ...), as float64.

    The kernel is not normalized here; the blur stage normalizes it to sum 1.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"blur.kernel = {str(path)!r}: no such file")
    if path.suffix.lower() == ".npy":
        try:
            kernel = np.load(path, allow_pickle=False)
        except ValueError as e:
            raise ValueError(f"blur.kernel = {str(path)!r}: not a numpy array file ({e})") from None
    else:
        kernel = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if kernel is None:
            raise ValueError(f"blur.kernel = {str(path)!r}: not a readable image")
    kernel = np.asarray(kernel, dtype=np.float64)
    if kernel.ndim != 2:
        raise ValueError(f"blur.kernel = {str(path)!r}: a kernel is 2-D (one channel), got "
                         f"shape {kernel.shape}")
    return kernel
