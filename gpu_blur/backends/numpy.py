"""The numpy backend: runs a plan with the float64 reference stages.

It follows the backend protocol (:mod:`gpu_blur.backends`): the accumulate pass always works
on the whole image and returns the asked region (the reference is the truth, not a memory
saver); the other passes work on the region they are given.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur.backends.flows import UnitFrames, gap_regions, interpolation_factor, with_flows
from gpu_blur.cameras import Camera
from gpu_blur.planning import Plan, StageName
from gpu_blur.reference import bayer, blur, demosaic, noise, transfer
from gpu_blur.reference.color import apply_matrix
from gpu_blur.reference.interpolate import interpolated_average
from gpu_blur.reference.optics import vignette
from gpu_blur.reference.output import quantize
from gpu_blur.reference.saturation import restore_saturated, synthesize_saturation
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

__all__ = ["DEMOSAIC", "NumpyBackend", "S", "retone"]

S = StageName
DEMOSAIC = {"malvar2004": demosaic.demosaic_malvar2004, "bilinear": demosaic.demosaic_bilinear}


class NumpyBackend:
    """float64 reference execution of a plan (the truth kernel backends are checked against)."""

    name = "numpy"
    precision = "float64"
    device = model = "numpy float64 (host CPU)"
    uses_cuda = False
    device_arrays = False

    def device_array(self, values: np.ndarray) -> np.ndarray:
        """The result as it is (a host array: the numpy backend has no device)."""
        return values

    # The passes, timed as the backend's compute ("kernels", gpu_blur.timings).
    def accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region: Region) -> tuple[np.ndarray, np.ndarray]:
        """Linearize and blur; return (linear, saturation mask) over ``region``.

        Args:
            plan: the sample's plan.
            params: its drawn parameters (``kernel``, ``homographies``; ``flows`` with
                interpolated frames, computed here when missing).
            frames: full-size sRGB frames, H x W x 3 uint8/uint16 codes or floats in [0, 1]
                (:func:`gpu_blur.image_arrays.check_image`), read one at a time (mode average), or
                one photo (kernel, trajectory), or the blurred image (none).
            mask: blur mode none only: the saturation mask that came with the image.
            region: the part of the image to return.
        """
        with timer("kernels"):
            return self._accumulate(plan, params, frames, mask, region)

    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear: np.ndarray,
               mask: np.ndarray, origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[np.ndarray, np.ndarray]:
        """Saturation, vignetting, Lin2Cam, mosaic, inverse WB, noise, WB.

        ``origin`` is the (row, column) of the image's first pixel in the whole image: it keeps
        the Bayer phase and the noise draws of a tile those of the whole image.

        Returns:
            (image, saturated): the white-balanced noisy H x W RAW mosaic when the plan has
            the RAW round trip, else the H x W x 3 linear image; and ``B_sat``, H x W x 3.
        """
        with timer("kernels"):
            return self._to_raw(plan, params, camera, linear, mask, origin, seed=seed,
                                sample_index=sample_index)

    def finish(self, plan: Plan, params: dict, camera: Camera, image: np.ndarray,
               saturated: np.ndarray, view: Region, out: Region, *, seed: int,
               sample_index: int) -> np.ndarray:
        """Demosaic, Cam2Lin, tone, sRGB noise, saturated restore, re-tone, quantize.

        ``image`` and ``saturated`` are what :meth:`to_raw` returned for ``view``; the result
        covers ``out``, which lies within ``view`` at least the demosaic halo away from every
        edge of ``view`` that is not an edge of the full image.

        Returns:
            ``out.h x out.w x 3`` float64 in [0, 1] (on the 8/16-bit grid when quantized).
        """
        with timer("kernels"):
            return self._finish(plan, params, camera, image, saturated, view, out, seed=seed,
                                sample_index=sample_index)

    def _accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                    mask: np.ndarray | None, region: Region) -> tuple[np.ndarray, np.ndarray]:
        """The accumulate pass, untimed."""
        mode = plan.variant(S.BLUR) or "none"
        if mode == "average" and interpolation_factor(plan) > 1:
            params = with_flows(plan, params, frames)
            linear, sat_mask = interpolated_average(
                UnitFrames(frames), gap_regions(plan, params, len(frames) - 1), params["flows"])
        elif mode == "average":
            acc = blur.FrameAccumulator(*frames[0].shape[:2])
            for frame in frames:
                acc.add(transfer.image_to_linear(frame))
            linear, sat_mask = acc.result()
        else:
            first = transfer.image_to_linear(frames[0])
            if mode == "kernel":
                kernel = params["kernel"]
                linear, sat_mask = (blur.convolve_kernel(first, kernel),
                                    blur.convolve_kernel(blur.saturation_indicator(first), kernel))
            elif mode == "trajectory":
                linear, sat_mask = blur.shake_blur(first, params["homographies"])
            else:
                linear = first
                sat_mask = np.zeros_like(first) if mask is None else np.asarray(mask, np.float64)
        return region.of(linear), region.of(sat_mask)

    def _to_raw(self, plan: Plan, params: dict, camera: Camera, linear: np.ndarray,
                mask: np.ndarray, origin: tuple[int, int] = (0, 0), *, seed: int,
                sample_index: int) -> tuple[np.ndarray, np.ndarray]:
        """The to_raw pass, untimed."""
        raw, sat = self.sensor_raw(plan, params, camera, linear, mask, origin)
        if raw is None:
            return sat, sat
        return self.noisy_raw(plan, params, raw, origin, seed=seed,
                              sample_index=sample_index), sat

    def sensor_raw(self, plan: Plan, params: dict, camera: Camera, linear: np.ndarray,
                   mask: np.ndarray, origin: tuple[int, int] = (0, 0)):
        """The to_raw pass up to the noise: (RAW mosaic before noise or None, saturated).

        The mosaic is the inverse-white-balanced sensor value Poisson-Gaussian noise draws
        from (None without a RAW round trip); ``saturated`` is ``B_sat`` (vignetted when the
        plan keeps it), H x W x 3. Untimed.
        """
        sat = (synthesize_saturation(linear, mask, params["alpha"]) if plan.kept(S.SATURATE)
               else np.asarray(linear, dtype=np.float64))
        if plan.kept(S.VIGNETTING):
            strength, full_h, full_w = plan[S.VIGNETTING].values
            sat = vignette(sat, strength, int(full_h or 0), int(full_w or 0), origin)
        if not plan.raw_round_trip:
            return None, sat
        cam = apply_matrix(sat, camera.linear_to_camera)
        if plan[S.LINEAR_TO_CAMERA].options["clip"]:
            cam = np.clip(cam, 0.0, 1.0)
        pattern = bayer.BayerPattern(params["pattern"])
        raw = bayer.inverse_white_balance(bayer.mosaic(cam, pattern, origin), pattern,
                                          params["red_gain"], params["blue_gain"],
                                          origin=origin)
        return raw, sat

    def noisy_raw(self, plan: Plan, params: dict, raw: np.ndarray,
                  origin: tuple[int, int] = (0, 0), *, seed: int,
                  sample_index: int) -> np.ndarray:
        """The to_raw pass from :meth:`sensor_raw`'s mosaic: noise (when kept), white balance.

        Untimed.
        """
        if plan.kept(S.POISSON_GAUSSIAN_NOISE):
            raw = noise.add_poisson_gaussian(
                raw, params["shot_noise_k"], params["read_noise_std"], seed=seed,
                sample_index=sample_index, origin=origin,
                poisson_normal_above=plan.poisson_normal_above)
        pattern = bayer.BayerPattern(params["pattern"])
        return bayer.white_balance(raw, pattern, params["red_gain"], params["blue_gain"],
                                   origin=origin)

    def _finish(self, plan: Plan, params: dict, camera: Camera, image: np.ndarray,
                saturated: np.ndarray, view: Region, out: Region, *, seed: int,
                sample_index: int) -> np.ndarray:
        """The finish pass, untimed."""
        if plan.raw_round_trip:
            options = plan[S.DEMOSAIC].options
            pattern = bayer.BayerPattern(params["pattern"])
            rgb = DEMOSAIC[options["method"]](image, pattern, border=options["border"],
                                              origin=view.origin)
            if options["clip"]:
                rgb = np.clip(rgb, 0.0, 1.0)
            image = apply_matrix(rgb, camera.camera_to_linear)
        inner = out.within(view)
        image, saturated = image[inner], saturated[inner]
        if plan.kept(S.TONE):
            image = transfer.linear_to_srgb(image)
        image = np.clip(image, 0.0, 1.0)
        if plan.kept(S.GAUSSIAN_NOISE):
            image = np.clip(noise.add_gaussian_srgb(
                image, params["gaussian_std"], seed=seed, sample_index=sample_index,
                origin=out.origin), 0.0, 1.0)
        if plan.kept(S.RESTORE_SATURATED):
            image = restore_saturated(image, saturated)
        image = self.retone(plan, camera, image)
        if plan.kept(S.QUANTIZE):
            image = quantize(image, plan[S.QUANTIZE].options["bits"])
        return image

    def retone(self, plan: Plan, camera: Camera, image: np.ndarray) -> np.ndarray:
        """The final re-toning, when the plan keeps it (:func:`retone`)."""
        return retone(plan, camera, image)


def retone(plan: Plan, camera: Camera, image: np.ndarray) -> np.ndarray:
    """The final re-toning (A7R3 or the camera's fitted response), when the plan keeps it.

    Every backend's ``retone`` (the sharp reference's tone curve, on the host in float64).

    Args:
        plan: the sample's plan.
        camera: its camera (``output.crf = "camera"`` re-tones with its response).
        image: sRGB values in [0, 1], any shape.
    """
    if plan.kept(S.RETONE):
        options = plan[S.RETONE].options
        return transfer.retone(image, options["crf"], options["table_size"],
                               plan.retone_coefficients(camera))
    return image
