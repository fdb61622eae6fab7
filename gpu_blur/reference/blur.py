"""The blur stage in linear RGB: one module per kind of blur, and what they share.

This is the offline half of RSBlur (Rim et al., "Realistic Blur Synthesis for Learning Image
Deblurring", ECCV 2022), which the authors describe only in GitHub issues #2, #4 and #6 of
``rimchang/RSBlur`` (pipeline notes, section 2). The scene's ``blur.mode`` picks the kind:

* ``average``: :mod:`gpu_blur.reference.average`, the plain mean of the linearised frames and,
  per channel, the fraction of saturated frames (RSBlur "syn", section 2A);
* ``average`` with ``blur.interpolation > 1``: :mod:`gpu_blur.reference.interpolate`, more
  frames per exposure from optical flow before averaging;
* ``kernel``: :mod:`gpu_blur.reference.motion_kernel`, one kernel for the image and its
  saturation indicator (GoPro_U, section 2B);
* ``trajectory``: :mod:`gpu_blur.reference.shake`, warps along a random camera rotation.

:func:`blur_halo` says how much context each kind reads; the other names here are the entry
points the backends call, defined in those modules.

The mask feeds the saturation step of pipeline section 5.8, ``clip(B + alpha * M, 0, 1)``,
the local scaling of supplementary section 12, ``clip[(I_nsat + alpha I_sat) * K]``, in which
``I_sat`` is the saturated part of the sharp image: so the mask is the blur of the indicator.

Conventions shared by the blur kinds:
    * Images are linear RGB ``H x W x 3`` float64 (the caller linearises sRGB frames first);
      where said, ``H x W`` and ``H x W x C`` are accepted too and the shape is kept.
    * Pixel ``(x, y)`` (column, row) has its centre at the integer coordinates ``(x, y)``.
    * A value is saturated when its linear value is ``>= 1``
      (:data:`gpu_blur.reference.average.SATURATION_LEVEL`). The RSBlur issue tests ``== 1``
      on 8-bit frames, where no linear value exceeds 1, so the two agree there; ``>= 1`` also
      counts values above 1 from float inputs.
    * Boundary rule of kernels and interpolated frames: mirror **without** repeating the edge
      pixel, i.e. numpy's ``pad(mode="reflect")``, OpenCV's ``BORDER_REFLECT_101`` and scipy's
      ``"mirror"``: ``... c b | a b c ... | b a ...``. The extension is periodic with period
      ``2 (n - 1)``, so it is defined arbitrarily far outside; an axis of length 1 is constant
      (:mod:`gpu_blur.reference.sampling`). Camera shake, whose path can leave the photo by
      many pixels, reads only the photo instead (:func:`~gpu_blur.reference.shake.shake_blur`,
      "Edges"): a mirror would show reflected copies of the content near the edges.
    * Randomness arrives as 1-D arrays of uniforms in the open interval (0, 1), drawn by the
      caller; ``KERNEL_UNIFORMS`` and ``SHAKE_UNIFORMS`` say how many each function consumes,
      always exactly that many, whatever the draws turn out to be.
    * Sums are plain float64 sums. For ``n`` non-negative terms the relative error of a plain
      running sum is at most ``(n - 1) u`` with ``u = 2**-53`` (Higham, "Accuracy and Stability
      of Numerical Algorithms", 2nd ed., section 4.2): below ``1.2e-13`` for 1,000 frames.
"""

from __future__ import annotations

from gpu_blur.reference.average import FrameAccumulator, saturation_indicator
from gpu_blur.reference.interpolate import interpolation_halo
from gpu_blur.reference.motion_kernel import convolve_kernel, kernel_halo, normalize_kernel
from gpu_blur.reference.shake import shake_blur, shake_halo

__all__ = [
    "FrameAccumulator",
    "blur_halo",
    "convolve_kernel",
    "normalize_kernel",
    "saturation_indicator",
    "shake_blur",
]


def blur_halo(mode: str, params: dict, height: int, width: int) -> int:
    """Pixels of context the blur stage reads around an output region.

    Args:
        mode: the blur variant: ``"average"`` and ``"none"`` are pointwise, ``"kernel"`` needs
            the kernel's radius, ``"trajectory"`` the camera path's largest displacement;
            ``"average"`` with interpolated frames reads along its optical flows
            (:func:`gpu_blur.reference.interpolate.interpolation_halo`).
        params: the sample's parameters (``kernel`` or ``homographies``; ``flows`` for
            interpolated frames).
        height: full image height.
        width: full image width.
    """
    if mode == "average" and params.get("flows") is not None:
        return interpolation_halo(params["flows"])
    if mode == "kernel":
        return kernel_halo(normalize_kernel(params["kernel"]))
    if mode == "trajectory":
        return shake_halo(params["homographies"], height, width)
    return 0
