"""Saturation synthesis (Rim et al., ECCV 2022, Sec. 4.2 of the paper; RSBlur pipeline note 5.8).

Sharp frames are clipped at the sensor's white level, so their blur lacks the bright streaks of
real blurred highlights. RSBlur restores them locally: the blurred linear image gets
``alpha * M`` added, ``M`` being the per-channel blurred saturation mask, then is clipped; after
the ISP, every channel at the clip level is set back to exactly 1 (no noise in saturated pixels).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ALPHA_RANGE", "restore_saturated", "synthesize_saturation"]

#: Range of alpha, drawn per image (RSBlur PyTorch and TF pipelines).
ALPHA_RANGE = (0.25, 1.75)


def synthesize_saturation(linear, mask, alpha: float) -> np.ndarray:
    """``B_sat = clip(B_lin + alpha * M, 0, 1)``.

    Args:
        linear: H x W x 3 linear blurred image.
        mask: H x W x 3 saturation mask in [0, 1] (per channel).
        alpha: highlight boost, drawn from U(0.25, 1.75) per image in RSBlur.

    Returns:
        H x W x 3 float64 in [0, 1]; values at the clip level are exactly 1.
    """
    linear = np.asarray(linear, dtype=np.float64)
    mask = np.asarray(mask, dtype=np.float64)
    if linear.shape != mask.shape:
        raise ValueError(f"image {linear.shape} and saturation mask {mask.shape} differ in shape")
    return np.clip(linear + alpha * mask, 0.0, 1.0)


def restore_saturated(rendered, saturated_linear) -> np.ndarray:
    """Set every channel whose synthesized linear value reached 1 to exactly 1.

    Args:
        rendered: H x W x 3 output of the ISP (any encoding with white at 1).
        saturated_linear: H x W x 3 ``B_sat`` before the RAW round trip.

    Returns:
        H x W x 3 float64.
    """
    rendered = np.asarray(rendered, dtype=np.float64)
    return np.where(np.asarray(saturated_linear) >= 1.0, 1.0, rendered)
