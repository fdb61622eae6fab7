"""The numpy backend: runs a plan with the float64 reference stages, whole image at a time."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from gpu_blur.cameras import Camera
from gpu_blur.plan import Plan
from gpu_blur.reference import bayer, blur, demosaic, noise, transfer
from gpu_blur.reference.color import apply_matrix
from gpu_blur.reference.saturation import restore_saturated, synthesize_saturation

DEMOSAIC = {"malvar2004": demosaic.demosaic_malvar2004, "bilinear": demosaic.demosaic_bilinear}


class NumpyBackend:
    """float64 reference execution of a plan (the truth kernel backends are checked against)."""

    name = "numpy"

    def accumulate(self, plan: Plan, params: dict, frames: Iterable[np.ndarray],
                   mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Linearize and blur.

        Args:
            plan: the sample's plan.
            params: its drawn parameters (``kernel``, ``homographies``).
            frames: sRGB frames in [0, 1], H x W x 3, consumed one at a time (mode average), or
                one photo (kernel, trajectory), or the blurred image (none).
            mask: blur mode none only: the saturation mask that came with the image.

        Returns:
            (linear blurred image, saturation mask), H x W x 3 float64 each.
        """
        mode = plan.variant("blur") or "none"
        frames = iter(frames)
        first = transfer.srgb_to_linear(next(frames))
        if mode == "average":
            acc = blur.FrameAccumulator(*first.shape[:2])
            acc.add(first)
            for frame in frames:
                acc.add(transfer.srgb_to_linear(frame))
            return acc.result()
        if mode == "kernel":
            kernel = params["kernel"]
            return (blur.convolve_kernel(first, kernel),
                    blur.convolve_kernel(blur.saturation_indicator(first), kernel))
        if mode == "trajectory":
            return blur.shake_blur(first, params["homographies"])
        if mask is None:
            mask = np.zeros_like(first)
        return first, np.asarray(mask, dtype=np.float64)

    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear: np.ndarray,
               mask: np.ndarray, origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[np.ndarray, np.ndarray]:
        """Saturation, Lin2Cam, mosaic, inverse WB, noise, WB.

        ``origin`` is the (row, column) of the image's first pixel in the whole image: it keeps
        the Bayer phase and the noise draws of a tile those of the whole image.

        Returns:
            (image, saturated): the white-balanced noisy H x W RAW mosaic when the plan has
            the RAW round trip, else the H x W x 3 linear image; and ``B_sat``, H x W x 3.
        """
        sat = (synthesize_saturation(linear, mask, params["alpha"]) if plan.kept("saturate")
               else linear)
        if not plan.raw_round_trip:
            return sat, sat
        cam = apply_matrix(sat, camera.linear_to_camera)
        if plan["linear_to_camera"].options["clip"]:
            cam = np.clip(cam, 0.0, 1.0)
        pattern = bayer.BayerPattern(params["pattern"])
        gains = (params["red_gain"], params["blue_gain"])
        raw = bayer.inverse_white_balance(bayer.mosaic(cam, pattern, origin), pattern, *gains,
                                          origin=origin)
        if plan.kept("poisson_gaussian_noise"):
            raw = noise.add_poisson_gaussian(
                raw, params["shot_noise_k"], params["read_noise_std"], seed=seed,
                sample_index=sample_index, origin=origin)
        return bayer.white_balance(raw, pattern, *gains, origin=origin), sat

    def finish(self, plan: Plan, params: dict, camera: Camera, image: np.ndarray,
               saturated: np.ndarray, origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> np.ndarray:
        """Demosaic, Cam2Lin, tone, sRGB noise, saturated restore, re-tone.

        ``image`` and ``saturated`` are what :meth:`to_raw` returned.

        Returns:
            H x W x 3 float64 in [0, 1] (crop and quantization are left to the caller).
        """
        if plan.raw_round_trip:
            options = plan["demosaic"].options
            pattern = bayer.BayerPattern(params["pattern"])
            rgb = DEMOSAIC[options["method"]](image, pattern, border=options["border"],
                                              origin=origin)
            if options["clip"]:
                rgb = np.clip(rgb, 0.0, 1.0)
            image = apply_matrix(rgb, camera.camera_to_linear)
        if plan.kept("tone"):
            image = transfer.linear_to_srgb(image)
        image = np.clip(image, 0.0, 1.0)
        if plan.kept("gaussian_noise"):
            image = np.clip(noise.add_gaussian_srgb(
                image, params["gaussian_std"], seed=seed, sample_index=sample_index,
                origin=origin), 0.0, 1.0)
        if plan.kept("restore_saturated"):
            image = restore_saturated(image, saturated)
        return self.retone(plan, image)

    def retone(self, plan: Plan, image: np.ndarray) -> np.ndarray:
        """The final re-toning with the A7R3 response, when the plan keeps it."""
        if plan.kept("retone"):
            return transfer.retone(image, plan["retone"].options["crf"])
        return image
