"""Side by side: our demosaicing and kernel blur against what a user would pick instead."""

from __future__ import annotations

import statistics

import numpy as np

from gpu_blur.analysis.bench.measure import finite_or_none, median_time
from gpu_blur.analysis.bench.workload import SAMPLE_INDEX, SEED

__all__ = ["BORDER_PX", "KERNEL_SIZE", "PATTERN", "demosaic_side_by_side",
           "kernel_blur_side_by_side"]

#: Side-by-side demosaic errors leave out this many pixels at every edge: border rules differ
#: (OpenCV's own border handling; ours mirrors the mosaic keeping the Bayer phase).
BORDER_PX = 8
#: Side-by-side kernel blur: a random motion kernel of this size (the largest GoPro_U size,
#: scene key blur.kernel_size).
KERNEL_SIZE = 29
#: The side-by-side mosaic's Bayer order.
PATTERN = "RGGB"


def _compare(name: str, covers: str, times: list[float], output: np.ndarray,
             expected: np.ndarray, megapixels: float, border: int = 0) -> dict:
    """A side-by-side row: median time and errors against ``expected`` (values clipped)."""
    from gpu_blur.analysis.metrics import psnr

    inner = (slice(border, expected.shape[0] - border), slice(border, expected.shape[1] - border))
    got = np.asarray(output, np.float64)[inner]
    want = expected[inner]
    median = statistics.median(times)
    # PSNR takes values in [0, 1]: float32 sums of values <= 1 may end a rounding above
    return {"method": name, "covers": covers, "median_s": round(median, 6),
            "ms_per_megapixel": round(median * 1e3 / megapixels, 4),
            "max_abs_error": float(np.max(np.abs(got - want))),
            "psnr_db": finite_or_none(psnr(np.clip(want, 0, 1), np.clip(got, 0, 1)))}


def _bayer_code(cv2, suffix: str = "") -> int:
    """OpenCV's code for an RGGB mosaic to RGB.

    OpenCV names its Bayer codes after the second row's second and third pixels, so RGGB is
    ``COLOR_BayerBG2RGB``; OpenCV 4.5+ also offers the top-left name ``COLOR_BayerRGGB2RGB``.
    """
    return getattr(cv2, f"COLOR_BayerRGGB2RGB{suffix}", None) or getattr(
        cv2, f"COLOR_BayerBG2RGB{suffix}")


def demosaic_side_by_side(frame: np.ndarray, backends: dict[str, dict], runs: int) -> list[dict]:
    """Demosaicing methods on one mosaic, against our float64 Malvar 2004.

    The mosaic is the linear middle frame sampled through an RGGB filter array (values in
    [0, 1]). Every output is clipped to [0, 1] (what an image keeps); errors leave out
    :data:`BORDER_PX` pixels at every edge, where the methods' border rules differ.
    """
    import cv2

    from gpu_blur.backends import get_backend, to_host
    from gpu_blur.cameras import get_camera
    from gpu_blur.image_arrays import unit_values
    from gpu_blur.planning import plan
    from gpu_blur.reference import bayer, demosaic, transfer
    from gpu_blur.scene import scene_from_dict
    from gpu_blur.tiling import Region

    raw = bayer.mosaic(transfer.srgb_to_linear(unit_values(frame)), PATTERN)
    h, w = raw.shape
    mp = h * w / 1e6
    expected = np.clip(demosaic.demosaic_malvar2004(raw, PATTERN), 0.0, 1.0)
    rows = []

    def add(name, covers, run, scale=1.0):
        times, out = median_time(run, runs)
        rows.append(_compare(name, covers, times, np.clip(np.asarray(out) * scale, 0, 1),
                             expected, mp, BORDER_PX))

    add("gpu_blur numpy Malvar 2004 (float64)", "demosaic",
        lambda: demosaic.demosaic_malvar2004(raw, PATTERN))
    add("gpu_blur numpy bilinear (float64)", "demosaic",
        lambda: demosaic.demosaic_bilinear(raw, PATTERN))
    # The finish pass alone, with nothing after the demosaic but an identity Cam2Lin and the
    # clip to [0, 1]: camera "srgb", no tone curve, no saturation, float output.
    only = plan(scene_from_dict({"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                                 "camera": {"name": "srgb"}, "noise": {"model": "none"},
                                 "isp": {"round_trip": "always"},
                                 "output": {"crf": "none", "bits": 0}}))
    camera, whole, blank = get_camera("srgb"), Region.whole(h, w), np.zeros((h, w, 3))
    for spec in backends:
        if spec == "numpy":
            continue
        runner = get_backend(spec, "float32")
        add(f"gpu_blur {spec} Malvar 2004 (float32)", "upload, demosaic, download",
            lambda runner=runner: to_host(runner.finish(
                only, {"pattern": PATTERN}, camera, raw, blank, whole, whole, seed=SEED,
                sample_index=SAMPLE_INDEX)))
    codes = np.round(raw * 65535).astype(np.uint16)
    add("OpenCV demosaicing, bilinear (uint16)", "demosaic",
        lambda: cv2.demosaicing(codes, _bayer_code(cv2)), 1 / 65535)
    add("OpenCV demosaicing, edge-aware (uint16)", "demosaic",
        lambda: cv2.demosaicing(codes, _bayer_code(cv2, "_EA")), 1 / 65535)
    try:
        from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004
    except ImportError:
        rows.append({"method": "colour-demosaicing Malvar 2004", "covers": "",
                     "note": "not installed (pip install colour-demosaicing)"})
    else:
        add("colour-demosaicing Malvar 2004 (float64)", "demosaic",
            lambda: demosaicing_CFA_Bayer_Malvar2004(raw, PATTERN))
    return rows


def kernel_blur_side_by_side(frame: np.ndarray, backends: dict[str, dict],
                             runs: int) -> list[dict]:
    """Our kernel blur against ``cv2.filter2D`` (BORDER_REFLECT_101), one motion kernel.

    The kernel is a random motion kernel of :data:`KERNEL_SIZE` (the scene's own draw for the
    benchmark's seed and sample index); the image is the linear middle frame. Errors against
    our float64 FFT convolution (:func:`gpu_blur.reference.motion_kernel.convolve_kernel`),
    same border rule, whole image.
    """
    import cv2

    from gpu_blur.backends import get_backend, to_host
    from gpu_blur.image_arrays import unit_values
    from gpu_blur.planning import plan
    from gpu_blur.reference import motion_kernel, rng, transfer
    from gpu_blur.scene import scene_from_dict
    from gpu_blur.tiling import Region

    linear = transfer.srgb_to_linear(unit_values(frame))
    h, w = linear.shape[:2]
    mp = h * w / 1e6
    uniforms = rng.image_uniforms(SEED, SAMPLE_INDEX, rng.Stream.KERNEL,
                                  motion_kernel.KERNEL_UNIFORMS)
    kernel = motion_kernel.random_motion_kernel(uniforms, KERNEL_SIZE)
    expected = motion_kernel.convolve_kernel(linear, kernel)
    rows = []

    def add(name, covers, run):
        times, out = median_time(run, runs)
        rows.append(_compare(name, covers, times, out, expected, mp))

    add("gpu_blur numpy FFT convolution (float64)", "blur", lambda: motion_kernel.convolve_kernel(
        linear, kernel))
    kernel_plan = plan(scene_from_dict({"blur": {"mode": "kernel"}}))
    whole = Region.whole(h, w)
    for spec in backends:
        if spec == "numpy":
            continue
        runner = get_backend(spec, "float32")
        add(f"gpu_blur {spec} kernel blur (float32)",
            "upload uint8, linearize, blur image and saturation mask, download image",
            lambda runner=runner: to_host(runner.accumulate(
                kernel_plan, {"kernel": kernel}, [frame], None, whole)[0]))
    # filter2D correlates: flip the kernel for a convolution
    flipped = np.ascontiguousarray(kernel[::-1, ::-1] / kernel.sum())
    for dtype in (np.float32, np.float64):
        image, taps = linear.astype(dtype), flipped.astype(dtype)
        add(f"OpenCV filter2D ({np.dtype(dtype).name})", "blur", lambda image=image, taps=taps:
            cv2.filter2D(image, -1, taps, borderType=cv2.BORDER_REFLECT_101))
    return rows
