"""Colour spaces: linear sRGB <-> XYZ <-> camera RAW RGB.

Images are H x W x 3 float64 (any leading shape with a last axis of 3); matrices are 3 x 3
float64 in column convention, ``out = M @ in`` per pixel. The two camera models of the RSBlur
supplementary material:

* a camera matrix mapping XYZ to camera RGB (Sony A7R3 from LibRaw, Eq. 5 and 8):
  ``lin = M_XYZ2Lin @ T_A7R3 @ cam`` with ``T_A7R3 = inv(xyz_to_camera)``;
* an XYZ-space colour correction matrix T fitted on a colour chart (RSBlur sessions, Eq. 3 and
  7): ``lin = M_XYZ2Lin @ T @ M_Lin2XYZ @ cam``, in the RSBlur TF ISP wrapped in a D65 -> D50
  adaptation before T and D50 -> D65 after it.

Matrices are composed and inverted once, in float64, by :func:`camera_to_linear_matrix` and
:func:`checked_inverse`; the pipeline then applies one 3 x 3 per direction. Products and
inverses are :mod:`gpu_blur.reference.fixedmath`'s fixed-order sums (no BLAS or LAPACK, whose
kernels and FMA use depend on the CPU), so matrices and pixels have the same bits anywhere.
"""

from __future__ import annotations

import numpy as np

from gpu_blur.constants import D50_TO_D65, D65_TO_D50, SRGB_TO_XYZ, XYZ_TO_SRGB
from gpu_blur.reference import fixedmath

__all__ = ["MAX_CONDITION_NUMBER", "adapt_d50_to_d65", "adapt_d65_to_d50", "apply_matrix",
           "camera_to_linear_matrix", "camera_to_xyz", "checked_inverse", "correct_xyz",
           "linear_to_xyz", "uncorrect_xyz", "xyz_to_camera", "xyz_to_linear"]

#: Matrices worse conditioned than this are refused: their inverse would amplify float32
#: rounding in the kernels by more than a millionfold.
MAX_CONDITION_NUMBER = 1e6


def apply_matrix(image, matrix) -> np.ndarray:
    """Per-pixel ``out = M @ in``: ``out_i = (m_i0 in_0 + m_i1 in_1) + m_i2 in_2``.

    Args:
        image: (..., 3) float array.
        matrix: (3, 3) column-convention matrix.

    Returns:
        (..., 3) float64.
    """
    image = np.asarray(image, dtype=np.float64)
    matrix = np.asarray(matrix, dtype=np.float64)
    if image.shape[-1:] != (3,) or matrix.shape != (3, 3):
        raise ValueError(
            f"apply_matrix needs an (..., 3) image and a 3 x 3 matrix, got {image.shape} and "
            f"{matrix.shape}"
        )
    return fixedmath.matvec3(matrix, image)


def checked_inverse(matrix, what: str = "matrix") -> np.ndarray:
    """Invert a 3 x 3 matrix in float64, refusing singular or badly conditioned ones.

    The inverse is fixedmath's adjugate over determinant (fixed order); the 2-norm condition
    number (LAPACK's SVD) only decides the refusal.

    Raises:
        ValueError: naming ``what`` and the condition number when it exceeds
            :data:`MAX_CONDITION_NUMBER` or an entry is not finite.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise ValueError(f"{what} must be a finite 3 x 3 matrix, got {m.tolist()!r}")
    cond = np.linalg.cond(m)
    if not np.isfinite(cond) or cond > MAX_CONDITION_NUMBER:
        raise ValueError(
            f"{what} is near singular (condition number {cond:.3g} > {MAX_CONDITION_NUMBER:g}); "
            "check its values and their convention (column: out = M @ in)"
        )
    return fixedmath.inverse3(m)


def linear_to_xyz(linear) -> np.ndarray:
    """Linear sRGB (D65) -> CIE XYZ."""
    return apply_matrix(linear, SRGB_TO_XYZ)


def xyz_to_linear(xyz) -> np.ndarray:
    """CIE XYZ -> linear sRGB (D65)."""
    return apply_matrix(xyz, XYZ_TO_SRGB)


def adapt_d65_to_d50(xyz) -> np.ndarray:
    """Chromatic adaptation of XYZ from D65 to D50 (RSBlur TF ISP, ``M_d652d50``)."""
    return apply_matrix(xyz, D65_TO_D50)


def adapt_d50_to_d65(xyz) -> np.ndarray:
    """Chromatic adaptation of XYZ from D50 to D65 (RSBlur TF ISP, ``M_d502d65``)."""
    return apply_matrix(xyz, D50_TO_D65)


def xyz_to_camera(xyz, xyz_to_cam) -> np.ndarray:
    """XYZ -> camera RGB with a camera matrix (Eq. 8 without the sRGB step)."""
    return apply_matrix(xyz, xyz_to_cam)


def camera_to_xyz(camera, xyz_to_cam) -> np.ndarray:
    """Camera RGB -> XYZ with the float64 inverse of a camera matrix (Eq. 5's ``T_A7R3``)."""
    return apply_matrix(camera, checked_inverse(xyz_to_cam, "xyz_to_camera"))


def correct_xyz(xyz, ccm, adapt_d50: bool = False) -> np.ndarray:
    """Apply an XYZ-space colour correction matrix T (Eq. 3), optionally under D50 adaptation."""
    if adapt_d50:
        return adapt_d50_to_d65(apply_matrix(adapt_d65_to_d50(xyz), ccm))
    return apply_matrix(xyz, ccm)


def uncorrect_xyz(xyz, ccm, adapt_d50: bool = False) -> np.ndarray:
    """Undo an XYZ-space colour correction matrix, ``T^-1`` (Eq. 7)."""
    inverse = checked_inverse(ccm, "colour correction matrix")
    if adapt_d50:
        return adapt_d50_to_d65(apply_matrix(adapt_d65_to_d50(xyz), inverse))
    return apply_matrix(xyz, inverse)


def camera_to_linear_matrix(
    *, xyz_to_cam=None, ccm=None, adapt_d50: bool = False
) -> np.ndarray:
    """Compose the camera RGB -> linear sRGB matrix of the ISP's colour correction step.

    Give exactly one of:
        xyz_to_cam: a 3 x 3 XYZ -> camera matrix (Eq. 5: ``M_XYZ2Lin @ inv(xyz_to_cam)``).
        ccm: a 3 x 3 XYZ-space correction T (Eq. 3: ``M_XYZ2Lin @ T @ M_Lin2XYZ``); with
            ``adapt_d50`` T acts between D65 -> D50 and D50 -> D65 adaptations.

    Returns:
        (3, 3) float64, column convention. Its inverse (:func:`checked_inverse`) is Lin2Cam.
    """
    if (xyz_to_cam is None) == (ccm is None):
        raise ValueError("give exactly one of xyz_to_cam or ccm")
    if xyz_to_cam is not None:
        return fixedmath.matmul3(XYZ_TO_SRGB, checked_inverse(xyz_to_cam, "xyz_to_camera"))
    t = np.asarray(ccm, dtype=np.float64)
    checked_inverse(t, "colour correction matrix")
    if adapt_d50:
        t = fixedmath.matmul3(fixedmath.matmul3(D50_TO_D65, t), D65_TO_D50)
    return fixedmath.matmul3(fixedmath.matmul3(XYZ_TO_SRGB, t), SRGB_TO_XYZ)
