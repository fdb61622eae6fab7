"""Numbers of the RSBlur pipeline, loaded once from ``gpu_blur/data/rsblur.json``.

Every value there carries its source: the authors' repository ``rimchang/RSBlur`` at commit
``ae33a6c`` (Rim et al., "Realistic Blur Synthesis for Learning Image Deblurring", ECCV 2022).
Matrices are 3 x 3 float64 in column convention (``out = M @ in``).
"""

from __future__ import annotations

import functools
import json
from importlib import resources

import numpy as np

__all__ = ["A7R3_CRF_POLYNOMIAL", "A7R3_CRF_TABLE_X255", "D50_TO_D65", "D65_TO_D50",
           "GAUSSIAN_SRGB_NOISE_STD", "SRGB_TO_XYZ", "XYZ_TO_SRGB", "rsblur_data"]


@functools.cache
def rsblur_data() -> dict:
    """The parsed ``rsblur.json`` (read once)."""
    return json.loads(resources.files("gpu_blur").joinpath("data/rsblur.json").read_text())


def _matrix(key: str) -> np.ndarray:
    m = np.array(rsblur_data()[key]["value"], dtype=np.float64)
    m.setflags(write=False)
    return m


#: Linear sRGB (D65) -> CIE XYZ, the textbook IEC 61966-2-1 matrix as stored by the authors.
SRGB_TO_XYZ = _matrix("srgb_to_xyz")
#: CIE XYZ -> linear sRGB (D65); the exact inverse of SRGB_TO_XYZ (to 2e-16).
XYZ_TO_SRGB = _matrix("xyz_to_srgb")
#: Chromatic adaptation of XYZ from D65 to D50 (MATLAB-derived, RSBlur TF ISP).
D65_TO_D50 = _matrix("d65_to_d50")
#: Chromatic adaptation of XYZ from D50 to D65.
D50_TO_D65 = _matrix("d50_to_d65")
#: Standard deviation of the sRGB-domain Gaussian noise model before the +-50 % draw
#: (SRN-Deblur-RSBlur models/model.py, ``noise_synthesis=gaussian``).
GAUSSIAN_SRGB_NOISE_STD = float(rsblur_data()["gaussian_srgb_noise_std"]["value"])
#: Sony A7R3 camera response, linear -> rendered, degree-7 polynomial in ascending powers
#: (supplementary Sec. 7, Eq. 6; RSBlur ``a7r3_polynomial_alpha.mat``).
A7R3_CRF_POLYNOMIAL = np.array(rsblur_data()["a7r3"]["crf_polynomial"], dtype=np.float64)
#: The same response as a 2,551-node table: rendered x 255 at linear x 255 = 0.0, 0.1, ..., 255.0
#: (RSBlur ``lookup_table.mat``; strictly increasing, within 0.0072 of the polynomial).
A7R3_CRF_TABLE_X255 = np.array(rsblur_data()["a7r3"]["crf_lookup_srgb_x255"], dtype=np.float64)
for _a in (A7R3_CRF_POLYNOMIAL, A7R3_CRF_TABLE_X255):
    _a.setflags(write=False)
