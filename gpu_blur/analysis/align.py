"""Geometric alignment of a synthesized blurred image to a real one (ECC homography).

RSBlur supplementary Sec. 6: the two camera modules of the capture rig are slightly
misaligned, so for each real blurred image the authors synthesize a blurred image from its
sharp frames, estimate a homography between the real and the synthesized image with the
enhanced correlation coefficient (ECC) method of Evangelidis and Psarakis ("Parametric Image
Alignment Using Enhanced Correlation Coefficient Maximization", IEEE TPAMI 30(10), 2008), and
warp the sharp frames with it. Here ECC is OpenCV's ``cv2.findTransformECC`` with
``MOTION_HOMOGRAPHY`` on grayscale float32 images, optionally coarse to fine over a Gaussian
pyramid.

Convention: the homography ``H`` maps a pixel ``(x, y)`` of the reference (real) image to
the position ``H (x, y, 1)^T`` (homogeneous) in the moving (synthesized) image, as
``findTransformECC`` returns it; :func:`warp_to_reference` samples the moving image there, so
its output lies on the reference's pixel grid. Pixel centres are at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gpu_blur.image_reading import opencv_reason

__all__ = [
    "DEFAULT_GAUSS_SIZE",
    "DEFAULT_LEVELS",
    "DEFAULT_MAX_ITERATIONS",
    "DEFAULT_STEP_PX",
    "MIN_LEVEL_SIDE",
    "Alignment",
    "AlignmentError",
    "align_ecc",
    "corner_displacement",
    "inside_mask",
    "warp_to_reference",
]

#: ECC iterations per pyramid level before it is reported as not converged. RSBlur's
#: evaluation script uses 100 (RSBLUR_PIPELINE.md, section 9).
DEFAULT_MAX_ITERATIONS = 100
#: Convergence: the last update moved every image corner by less than this many pixels (full
#: resolution; a level halved k times uses 2^k times this in its own pixels). OpenCV
#: resamples the moving image at 1/32-pixel positions (INTER_BITS = 5) inside ECC, so on noisy
#: images the updates end in a cycle of a few thousandths of a pixel (measured 0.004 to 0.009
#: px on the 400 x 600 coffee photo with 8-bit noise of sigma 3 codes) in which the
#: correlation moves by about 1e-4 from one iteration to the next: a threshold on the
#: correlation's change (OpenCV's own test) would never stop there, a step below half that
#: grid does.
DEFAULT_STEP_PX = 1.0 / 64.0
#: Side of the Gaussian filter ECC applies to both images first (OpenCV's default, and the
#: "gauss filter 5" of RSBlur's evaluation script).
DEFAULT_GAUSS_SIZE = 5
#: Pyramid levels: 1 aligns at full resolution only; each further level halves the images.
DEFAULT_LEVELS = 3
#: A pyramid level is built only while its shorter side stays at least this many pixels.
MIN_LEVEL_SIDE = 64


class AlignmentError(RuntimeError):
    """ECC could not align the images (OpenCV stopped it, or the images cannot be aligned)."""


@dataclass(frozen=True)
class Alignment:
    """What :func:`align_ecc` found, and how it got there.

    Attributes:
        homography: 3 x 3 float64, reference pixel -> moving-image pixel (normalized so that
            ``H[2, 2] = 1``).
        correlation: the ECC criterion (zero-mean normalized correlation, in [-1, 1]) between
            the reference and the moving image warped by ``homography``, both Gaussian-filtered
            as ECC sees them, over the reference pixels that map inside the moving image.
        iterations: ECC iterations run at each pyramid level, coarsest first.
        converged: whether the full-resolution level stopped because an update moved the
            image corners by less than ``step_px``, rather than at ``max_iterations``.
        levels: pyramid levels used (1: full resolution only).
    """

    homography: np.ndarray
    correlation: float
    iterations: tuple[int, ...]
    converged: bool
    levels: int

    def to_dict(self) -> dict:
        """A JSON-ready record of the alignment."""
        return {"homography": self.homography.tolist(), "correlation": self.correlation,
                "iterations": list(self.iterations), "converged": self.converged,
                "levels": self.levels}


def _gray(image, name: str) -> np.ndarray:
    """H x W float32 luma (Rec. 601 weights, OpenCV's RGB2GRAY) of an H x W or H x W x 3 image.

    uint8 and uint16 codes are scaled to [0, 1]; floats are taken as they are.
    """
    x = np.asarray(image)
    if x.ndim not in (2, 3) or (x.ndim == 3 and x.shape[2] not in (1, 3)) or x.size == 0:
        raise ValueError(f"{name}: expected an H x W or H x W x 3 (RGB) image, got shape "
                         f"{x.shape}")
    if x.dtype == np.uint8:
        x = x / 255.0
    elif x.dtype == np.uint16:
        x = x / 65535.0
    elif not np.issubdtype(x.dtype, np.floating):
        raise ValueError(f"{name}: unsupported dtype {x.dtype}; use uint8, uint16 or floats")
    x = np.asarray(x, dtype=np.float32)
    if not np.isfinite(x).all():
        raise ValueError(f"{name}: {np.count_nonzero(~np.isfinite(x))} NaN or infinite "
                         "value(s); ECC needs a finite image")
    if x.ndim == 3:
        x = x[:, :, 0] if x.shape[2] == 1 else cv2.cvtColor(x, cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(x)


def _level_count(side: int, levels: int) -> int:
    """Levels to build: at most ``levels``, while the shortest side stays >= MIN_LEVEL_SIDE."""
    count = 1
    while count < levels and side // 2 >= MIN_LEVEL_SIDE:
        side //= 2
        count += 1
    return count


def _rescale(homography: np.ndarray, factor: float) -> np.ndarray:
    """The same motion on images scaled by ``factor``: S H S^-1, S = diag(f, f, 1).

    cv2.pyrDown maps a pixel centre x of the finer image to about x / 2 of the coarser one;
    the half-pixel offset this ignores only shifts the next level's starting point.
    """
    scale = np.diag([factor, factor, 1.0])
    return scale @ homography @ np.linalg.inv(scale)


def _correlation(reference: np.ndarray, moving: np.ndarray, homography: np.ndarray,
                 gauss_size: int) -> float:
    """ECC's criterion at ``homography`` on the Gaussian-filtered images (see Alignment)."""
    ksize = (gauss_size, gauss_size)
    ref = cv2.GaussianBlur(reference, ksize, 0) if gauss_size > 0 else reference
    mov = cv2.GaussianBlur(moving, ksize, 0) if gauss_size > 0 else moving
    warped = cv2.warpPerspective(mov, homography.astype(np.float32),
                                 reference.shape[::-1],
                                 flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    valid = inside_mask(homography, reference.shape, moving.shape)
    return float(cv2.computeECC(ref, warped, valid.astype(np.uint8)))


def _ecc_level(reference: np.ndarray, moving: np.ndarray, start: np.ndarray,
               max_iterations: int, step_px: float, gauss_size: int, where: str
               ) -> tuple[np.ndarray, int, bool]:
    """Run ECC one iteration per call, so the iterations and the stopping reason are known.

    Each ``findTransformECC`` call with a count of 1 makes one Gauss-Newton update of the
    homography; the loop stops once an update moves every corner of the reference image by
    less than ``step_px`` pixels, or after ``max_iterations`` updates.
    """
    criteria = (cv2.TERM_CRITERIA_COUNT, 1, 0.0)
    warp = start.astype(np.float32)
    for iteration in range(1, max_iterations + 1):
        try:
            _, updated = cv2.findTransformECC(reference, moving, warp.copy(),
                                              cv2.MOTION_HOMOGRAPHY, criteria, None, gauss_size)
        except cv2.error as e:
            raise AlignmentError(
                f"ECC failed at iteration {iteration}{where}, on {reference.shape[0]} x "
                f"{reference.shape[1]} images (OpenCV: {opencv_reason(e)}); the images may be "
                "flat (no texture), share too little content, or be too far apart for ECC to "
                "start: check they show the same scene, crop them to the overlap, or pass an "
                "initial homography") from None
        step = corner_displacement(updated, warp, reference.shape)
        warp = updated
        if step < step_px:
            return warp.astype(np.float64), iteration, True
    return warp.astype(np.float64), max_iterations, False


def align_ecc(reference, moving, *, levels: int = DEFAULT_LEVELS,
              max_iterations: int = DEFAULT_MAX_ITERATIONS, step_px: float = DEFAULT_STEP_PX,
              gauss_size: int = DEFAULT_GAUSS_SIZE, initial=None) -> Alignment:
    """Estimate the homography that aligns ``moving`` to ``reference`` by ECC.

    For RSBlur's alignment (supplementary Sec. 6), ``reference`` is the real blurred image and
    ``moving`` the blurred image synthesized from its sharp frames; the sharp frames are then
    warped with :func:`warp_to_reference`.

    Both images are reduced to grayscale float32. With ``levels > 1`` ECC first runs on images
    halved ``levels - 1`` times (``cv2.pyrDown``), then refines at each finer level from the
    coarser result, which tolerates larger motion; levels whose shorter side would drop below
    :data:`MIN_LEVEL_SIDE` pixels are not built. A coarse level stops once its updates move
    the corners by less than ``step_px`` full-resolution pixels; the finest level refines.

    Args:
        reference: H x W or H x W x 3 RGB image (uint8, uint16, or floats).
        moving: image of the same scene, any size.
        levels: pyramid levels, >= 1.
        max_iterations: ECC iterations per level, >= 1.
        step_px: convergence threshold, > 0: the last update moved every image corner by
            less than this many pixels (:data:`DEFAULT_STEP_PX`).
        gauss_size: odd side of the Gaussian filter ECC applies first (0 for none).
        initial: optional 3 x 3 starting homography at full resolution (default identity).

    Returns:
        The :class:`Alignment`. A run that reaches ``max_iterations`` at full resolution is
        returned with ``converged=False``; check it before trusting the homography.

    Raises:
        AlignmentError: when OpenCV stops ECC (e.g. a flat image, or the correlation would
            decrease: images that do not overlap), with its reason.
        ValueError: for bad images or arguments.
    """
    ref = _gray(reference, "reference")
    mov = _gray(moving, "moving")
    if levels < 1 or max_iterations < 1:
        raise ValueError(f"levels={levels} and max_iterations={max_iterations} must be >= 1")
    if not step_px > 0:
        raise ValueError(f"step_px={step_px}: must be > 0")
    if gauss_size < 0 or (gauss_size > 0 and gauss_size % 2 == 0):
        raise ValueError(f"gauss_size={gauss_size}: must be 0 (no filter) or odd")
    start = np.eye(3) if initial is None else np.asarray(initial, dtype=np.float64)
    if start.shape != (3, 3) or not np.isfinite(start).all():
        raise ValueError(f"initial: expected a finite 3 x 3 homography, got shape {start.shape}")
    count = _level_count(min(*ref.shape, *mov.shape), levels)
    refs, movs = [ref], [mov]
    for _ in range(count - 1):
        refs.append(cv2.pyrDown(refs[-1]))
        movs.append(cv2.pyrDown(movs[-1]))
    warp = _rescale(start / start[2, 2], 0.5 ** (count - 1))
    iterations = []
    converged = False
    for level in range(count - 1, -1, -1):
        # the same step in full-resolution pixels: coarse levels only need to get close
        warp, used, converged = _ecc_level(
            refs[level], movs[level], warp, max_iterations, step_px * 2 ** level, gauss_size,
            f" at pyramid level {count - level} of {count}" if count > 1 else "")
        iterations.append(used)
        if level:
            warp = _rescale(warp, 2.0)
    warp = warp / warp[2, 2]
    return Alignment(homography=warp, correlation=_correlation(ref, mov, warp, gauss_size),
                     iterations=tuple(iterations), converged=converged, levels=count)


def inside_mask(homography, reference_shape, moving_shape) -> np.ndarray:
    """Reference pixels that ``homography`` maps inside the moving image.

    Args:
        homography: 3 x 3, reference pixel -> moving-image pixel.
        reference_shape: (H, W, ...) of the reference image.
        moving_shape: (H, W, ...) of the moving image.

    Returns:
        H x W booleans on the reference grid: True where the mapped position lies within
        ``[0, W_moving - 1] x [0, H_moving - 1]`` (no border rule was needed there).
    """
    h = np.asarray(homography, dtype=np.float64)
    rows, cols = reference_shape[:2]
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
        v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    return ((w > 0) & (u >= 0) & (u <= moving_shape[1] - 1)
            & (v >= 0) & (v <= moving_shape[0] - 1))


def warp_to_reference(image, homography, reference_shape, *,
                      interpolation: str = "linear") -> tuple[np.ndarray, np.ndarray]:
    """Resample an image of the moving camera onto the reference's pixel grid.

    Output pixel ``(x, y)`` takes the image's value at ``H (x, y, 1)^T`` (``cv2.warpPerspective``
    with ``WARP_INVERSE_MAP``). Border rule: positions outside the image read its mirror image
    about the edge pixels (``cv2.BORDER_REFLECT``: ``cba|abcd``), so the output has no black
    wedge; the returned mask marks the pixels whose position lies inside the image (bilinear
    reads no mirrored value there; cubic still does within 2 px of the edge), for metrics over
    valid pixels only.

    Args:
        image: H' x W' or H' x W' x C image of the moving camera (e.g. a sharp frame), any
            dtype OpenCV warps (uint8, uint16, float32, float64).
        homography: 3 x 3, reference pixel -> moving-image pixel (:attr:`Alignment.homography`).
        reference_shape: (H, W, ...) of the reference image: the output's size.
        interpolation: "linear" (stays within the input's range) or "cubic" (sharper, may
            overshoot the input's range; RSBlur's evaluation script uses it).

    Returns:
        ``(warped, mask)``: the image on the reference grid (same dtype and channels) and an
        H x W boolean mask of the pixels that map inside ``image``.
    """
    flags = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}.get(interpolation)
    if flags is None:
        raise ValueError(f"interpolation={interpolation!r}: choose 'linear' or 'cubic'")
    h = np.asarray(homography, dtype=np.float64)
    if h.shape != (3, 3) or not np.isfinite(h).all():
        raise ValueError(f"homography: expected a finite 3 x 3 matrix, got shape {h.shape}")
    image = np.asarray(image)
    rows, cols = reference_shape[:2]
    warped = cv2.warpPerspective(image, h, (cols, rows), flags=flags | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REFLECT)
    if image.ndim == 3 and warped.ndim == 2:  # OpenCV drops a single channel axis
        warped = warped[:, :, None]
    return warped, inside_mask(h, reference_shape, image.shape)


def corner_displacement(estimated, expected, shape) -> float:
    """Largest distance, in pixels, between where two homographies map the image's corners.

    How far apart two homographies are over an image, in the units that matter for alignment.

    Args:
        estimated: 3 x 3 homography.
        expected: 3 x 3 homography.
        shape: (H, W, ...) of the image whose corners ``(0, 0)``, ``(W - 1, 0)``,
            ``(0, H - 1)``, ``(W - 1, H - 1)`` are mapped.

    Returns:
        The largest of the four distances between the two mapped positions, in pixels.
    """
    rows, cols = shape[:2]
    corners = np.array([[0, 0, 1], [cols - 1, 0, 1], [0, rows - 1, 1],
                        [cols - 1, rows - 1, 1]], dtype=np.float64).T
    a = np.asarray(estimated, dtype=np.float64) @ corners
    b = np.asarray(expected, dtype=np.float64) @ corners
    return float(np.max(np.hypot(*(a[:2] / a[2] - b[:2] / b[2]))))
