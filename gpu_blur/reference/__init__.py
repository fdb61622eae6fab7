"""The numpy float64 reference of every stage: the truth every kernel backend is checked against.

One module per concern; the names below are the stages' names in every backend.
"""

from gpu_blur.reference.average import FrameAccumulator, average_frames, saturation_indicator
from gpu_blur.reference.bayer import (
    BayerPattern,
    inverse_white_balance,
    mosaic,
    site_gains,
    white_balance,
)
from gpu_blur.reference.color import (
    adapt_d50_to_d65,
    adapt_d65_to_d50,
    apply_matrix,
    camera_to_linear_matrix,
    camera_to_xyz,
    correct_xyz,
    linear_to_xyz,
    uncorrect_xyz,
    xyz_to_camera,
    xyz_to_linear,
)
from gpu_blur.reference.demosaic import demosaic_bilinear, demosaic_malvar2004
from gpu_blur.reference.motion_kernel import convolve_kernel, random_motion_kernel
from gpu_blur.reference.noise import add_gaussian_srgb, add_poisson_gaussian
from gpu_blur.reference.output import crop_border, quantize
from gpu_blur.reference.poisson_counts import poisson
from gpu_blur.reference.rng import Stream, philox4x32
from gpu_blur.reference.saturation import restore_saturated, synthesize_saturation
from gpu_blur.reference.shake import camera_shake_homographies, shake_blur, warp_homography
from gpu_blur.reference.transfer import (
    gamma_to_linear,
    inverse_lookup_crf,
    linear_to_gamma,
    linear_to_srgb,
    lookup_crf,
    polynomial_crf,
    retone,
    srgb_to_linear,
)

__all__ = [
    "BayerPattern", "FrameAccumulator", "Stream", "adapt_d50_to_d65", "adapt_d65_to_d50",
    "add_gaussian_srgb", "add_poisson_gaussian", "apply_matrix", "average_frames",
    "camera_shake_homographies", "camera_to_linear_matrix", "camera_to_xyz", "convolve_kernel",
    "correct_xyz", "crop_border", "demosaic_bilinear", "demosaic_malvar2004",
    "gamma_to_linear", "inverse_lookup_crf", "inverse_white_balance", "linear_to_gamma",
    "linear_to_srgb", "linear_to_xyz", "lookup_crf", "mosaic", "philox4x32", "poisson",
    "polynomial_crf", "quantize", "random_motion_kernel", "restore_saturated", "retone",
    "saturation_indicator", "shake_blur", "site_gains", "srgb_to_linear",
    "synthesize_saturation", "uncorrect_xyz", "warp_homography", "white_balance",
    "xyz_to_camera", "xyz_to_linear",
]
