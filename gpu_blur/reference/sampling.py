"""Shared by the blur kinds: argument checks, the reflect-101 border and bilinear sampling.

The border rule is that of kernels and interpolated frames (:mod:`gpu_blur.reference.blur`,
"Conventions"); camera shake reads only the photo (:func:`gpu_blur.reference.shake.shake_blur`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["as_image", "as_uniforms", "bilinear_sample", "reflect101_index"]


def as_image(image, name: str = "image") -> np.ndarray:
    """Return ``image`` as a finite float64 array of shape ``H x W`` or ``H x W x C``."""
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim not in (2, 3) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{name} must be H x W or H x W x C with H, W >= 1; got {arr.shape}")
    if arr.ndim == 3 and arr.shape[2] < 1:
        raise ValueError(f"{name} must have at least one channel; got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return arr


def as_uniforms(uniforms, count: int, name: str) -> np.ndarray:
    """Return ``uniforms`` as a float64 vector of ``count`` values in the open interval (0, 1)."""
    u = np.asarray(uniforms, dtype=np.float64)
    if u.shape != (count,):
        raise ValueError(f"{name} needs exactly ({count},) uniforms; got shape {u.shape}")
    if not ((u > 0.0) & (u < 1.0)).all():
        raise ValueError(f"{name} needs uniforms in the open interval (0, 1)")
    return u


def reflect101_index(index: np.ndarray, n: int) -> np.ndarray:
    """Map integer indices into ``[0, n)`` by mirroring without repeating the edge pixel.

    Periodic with period ``2 (n - 1)``, so valid arbitrarily far outside. A length-1 axis maps
    everything to 0. Indices already inside are returned unchanged (as ``intp``).
    """
    index = index.astype(np.intp, copy=False)
    if n == 1:
        return np.zeros(index.shape, dtype=np.intp)
    if index.size and index.min() >= 0 and index.max() < n:
        return index
    period = 2 * (n - 1)
    m = np.mod(index, period)
    return np.where(m >= n, period - m, m)


def bilinear_sample(
    flat: np.ndarray, height: int, width: int, px: np.ndarray, py: np.ndarray
) -> np.ndarray:
    """Sample ``flat`` (``(H W) x C`` rows of an image) bilinearly at float positions.

    Interpolates as ``a + f (b - a)`` along x, then along y, so a zero fraction returns the
    pixel exactly. Neighbours outside are mirrored (reflect-101), arbitrarily far out.
    """
    x0 = np.floor(px)
    y0 = np.floor(py)
    fx = (px - x0)[..., None]
    fy = (py - y0)[..., None]
    xi = x0.astype(np.intp)
    yi = y0.astype(np.intp)
    ix0 = reflect101_index(xi, width)
    ix1 = reflect101_index(xi + 1, width)
    row0 = reflect101_index(yi, height) * width
    row1 = reflect101_index(yi + 1, height) * width

    def lerp_x(row: np.ndarray) -> np.ndarray:
        left = np.take(flat, row + ix0, axis=0)
        right = np.take(flat, row + ix1, axis=0)
        right -= left
        right *= fx
        left += right
        return left

    top = lerp_x(row0)
    bottom = lerp_x(row1)
    bottom -= top
    bottom *= fy
    top += bottom
    return top
