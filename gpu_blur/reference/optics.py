"""Lens effects on the irradiance that reaches the sensor (float64 reference).

Vignetting: light falls off away from the optical centre. Goldman ("Vignette and exposure
calibration and compensation", IEEE TPAMI 32(12), 2010) models the attenuation as an even
polynomial of the radius, V(r) = 1 + a_2 r^2 + a_4 r^4 + a_6 r^6; the stage keeps its first
term, V = 1 - s (r / r_corner)^2, with one strength s (scene ``optics.vignetting``): 1 at the
centre, 1 - s at the image's corners. The centre is the image's centre, r is measured to pixel
centres in the whole image's coordinates, so a tile gets the values of the whole image.
"""

from __future__ import annotations

import numpy as np

__all__ = ["vignette", "vignetting_gain"]


def vignetting_gain(strength: float, full_h: int, full_w: int, rows, columns) -> np.ndarray:
    """1 - s (r / r_corner)^2 at pixels (rows, columns) of a full_h x full_w image.

    ``rows`` and ``columns`` are global pixel indices (broadcast together); r is the distance
    of the pixel's centre (row + 1/2, column + 1/2) from the image's centre (full_h / 2,
    full_w / 2), r_corner that of a corner of the image. Kernels evaluate the same expression
    in the same order.

    Raises:
        ValueError: for an empty image size (the plan was built without the image's size).
    """
    if full_h <= 0 or full_w <= 0:
        raise ValueError(f"vignetting needs the whole image's size, got {full_h} x {full_w}: "
                         "build the plan with size=(height, width)")
    cy, cx = 0.5 * full_h, 0.5 * full_w
    dy = (np.asarray(rows, dtype=np.float64) + 0.5) - cy
    dx = (np.asarray(columns, dtype=np.float64) + 0.5) - cx
    return 1.0 - strength * ((dx * dx + dy * dy) / (cx * cx + cy * cy))


def vignette(image: np.ndarray, strength: float, full_h: int, full_w: int,
             origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``image`` (H x W x 3, linear) times :func:`vignetting_gain`, its first pixel at ``origin``.

    ``origin`` is the (row, column) of that pixel in the full_h x full_w image.
    """
    h, w = image.shape[:2]
    rows = np.arange(origin[0], origin[0] + h)[:, None]
    columns = np.arange(origin[1], origin[1] + w)[None, :]
    gain = vignetting_gain(strength, full_h, full_w, rows, columns)
    return np.asarray(image, dtype=np.float64) * gain[:, :, None]
