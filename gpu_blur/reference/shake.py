"""Blur by camera shake: spatially varying blur from a small random camera rotation.

The sharp image and its saturation indicator are warped by the homographies ``K R_t K^-1`` of
the rotation and averaged, as in Whyte et al., "Non-uniform Deblurring for Shaken Images"
(CVPR 2010; IJCV 98, 2012). See :mod:`gpu_blur.reference.blur` for the
conventions shared by the blur kinds.
"""

from __future__ import annotations

import math

import numpy as np

from gpu_blur.reference import fixedmath
from gpu_blur.reference.average import saturation_indicator
from gpu_blur.reference.sampling import as_image, as_uniforms, bilinear_sample

__all__ = [
    "SHAKE_AUTO_STEPS_RANGE",
    "SHAKE_HARMONICS",
    "SHAKE_ROLL_MAX_DEG",
    "SHAKE_UNIFORMS",
    "auto_shake_steps",
    "camera_shake_homographies",
    "shake_blur",
    "shake_halo",
    "warp_homography",
]

# -- camera shake: a smooth random rotation over the exposure -------------------------------
#: Sine and cosine harmonics per rotation axis of the camera path.
SHAKE_HARMONICS = 3
#: Uniforms consumed by :func:`camera_shake_homographies`: a sine and a cosine amplitude per
#: harmonic for yaw, pitch and roll (in that order), then one for the roll's size.
SHAKE_UNIFORMS = 3 * 2 * SHAKE_HARMONICS + 1
#: Largest yaw or pitch (radians) the extent search may use; beyond it ``extent_px`` is refused.
SHAKE_ANGLE_MAX_RAD = math.radians(60.0)
#: Largest accepted ``roll_deg``.
SHAKE_ROLL_MAX_DEG = 30.0
#: Relative accuracy to which the centre's path extent is matched to ``extent_px``.
SHAKE_EXTENT_RTOL = 1e-13


def _intrinsics(height: int, width: int) -> tuple[float, float, float]:
    """Pinhole intrinsics ``(f, cx, cy)`` in pixels: ``f = max(H, W)``, centre of the image."""
    return float(max(height, width)), (width - 1) / 2.0, (height - 1) / 2.0


def _rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``R = R_z(roll) R_x(pitch) R_y(yaw)`` for arrays of angles (radians), ``(n, 3, 3)``.

    fixedmath's sines and fixed-order products: the same bits on every CPU.
    """
    sy_, cy_ = fixedmath.sincos(yaw)
    sp, cp = fixedmath.sincos(pitch)
    sr, cr = fixedmath.sincos(roll)
    one, zero = np.ones_like(yaw), np.zeros_like(yaw)
    r_yaw = np.stack(
        [
            np.stack([cy_, zero, sy_], -1),
            np.stack([zero, one, zero], -1),
            np.stack([-sy_, zero, cy_], -1),
        ],
        -2,
    )
    r_pitch = np.stack(
        [
            np.stack([one, zero, zero], -1),
            np.stack([zero, cp, -sp], -1),
            np.stack([zero, sp, cp], -1),
        ],
        -2,
    )
    r_roll = np.stack(
        [
            np.stack([cr, -sr, zero], -1),
            np.stack([sr, cr, zero], -1),
            np.stack([zero, zero, one], -1),
        ],
        -2,
    )
    return fixedmath.matmul3(fixedmath.matmul3(r_roll, r_pitch), r_yaw)


def _homographies(rot: np.ndarray, f: float, cx: float, cy: float) -> np.ndarray:
    """``H = K R K^-1``, computed as ``I + K (R - I) K^-1`` so that ``R = I`` gives exactly I."""
    k = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    k_inv = np.array([[1.0 / f, 0.0, -cx / f], [0.0, 1.0 / f, -cy / f], [0.0, 0.0, 1.0]])
    return np.eye(3) + fixedmath.matmul3(fixedmath.matmul3(k, rot - np.eye(3)), k_inv)


def _centre_extent(homographies: np.ndarray, cx: float, cy: float) -> float:
    """Bounding-box diagonal (pixels) of the image centre's positions under the homographies."""
    p = fixedmath.matvec3(homographies, np.array([cx, cy, 1.0]))
    x = p[:, 0] / p[:, 2]
    y = p[:, 1] / p[:, 2]
    return float(fixedmath.hypot(np.ptp(x), np.ptp(y)))


def camera_shake_homographies(
    uniforms, height: int, width: int, steps: int, extent_px: float, roll_deg: float
) -> np.ndarray:
    """Draw a smooth random camera rotation over the exposure, as homographies.

    Camera shake is modelled as a rotation of the camera about its centre, after Whyte et
    al., "Non-uniform Deblurring for Shaken Images" (CVPR 2010; IJCV 98, 2012), who argue
    that rotation dominates translation in hand shake (Koehler et al., ECCV 2012, recorded
    real 6-D shake trajectories for their benchmark). A scene point seen at pixel ``p`` in
    the sharp (reference) image is seen at ``H_t p`` at time ``t``, with
    ``H_t = K R_t K^-1``, ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]``, ``f = max(H, W)``
    pixels (a 53-degree field of view across the longer side), the principal point
    ``(cx, cy) = ((W - 1) / 2, (H - 1) / 2)``, and ``R_t = R_z(roll) R_x(pitch) R_y(yaw)``.

    Path model (ours): each angle is a short Fourier series over the exposure
    ``t in [-1/2, 1/2]``, ``a(t) = sum_{k=1..3} (alpha_k cos(pi k t) + beta_k sin(pi k t)) / k``
    with ``alpha_k, beta_k = 2 u - 1``, minus ``a(0)``: smooth, dominated by a sweep and a bend,
    and zero at mid-exposure, so the sharp image is the middle frame (like RSBlur's middle GT
    frame). The ``steps`` samples sit at the midpoints of equal time slices,
    ``t_s = (s + 1/2) / steps - 1/2``; for odd ``steps`` the middle one, ``s = steps // 2``, is
    exactly ``t = 0`` and exactly the identity (for even ``steps`` no sample is at ``t = 0``).
    ``steps = 1`` gives the identity alone. Each sample is a sharp copy, so a point moving more
    than about a pixel between samples shows as a row of dots, not a streak: take ``steps`` at
    least the path's length in pixels (the centre's arc length, which exceeds ``extent_px``
    when the path bends, and more where roll moves the corners further).

    Scaling: roll is scaled so ``max_s |roll(t_s)| = roll_deg * u_last``. Yaw and pitch share
    one factor, found by fixed-point iteration, so the **bounding-box diagonal** of the image
    centre's sampled positions ``H_s (cx, cy)`` equals ``extent_px`` to a relative
    ``SHAKE_EXTENT_RTOL`` (the centre moves with yaw and pitch only; roll turns its path).
    ``extent_px`` and ``roll_deg`` act independently: ``extent_px = 0`` with ``roll_deg > 0``
    still rolls the image about its centre.

    Args:
        uniforms: ``(SHAKE_UNIFORMS,)`` uniforms in (0, 1): cosine then sine amplitudes of
            harmonics 1..3 for yaw, then pitch, then roll (6 each), then the roll's size.
        height: image height ``H`` in pixels.
        width: image width ``W`` in pixels.
        steps: number of time samples, ``>= 1``.
        extent_px: the centre's path extent in pixels, ``>= 0``. Shake is small next to the
            focal length ``max(H, W)``; larger extents are honoured while yaw and pitch stay
            within 60 degrees and every frame keeps the image in front of the camera.
        roll_deg: bound on the roll in degrees, ``0 <= roll_deg <= 30``.

    Returns:
        ``(steps, 3, 3)`` float64 homographies mapping sharp-image pixel coordinates (x, y, 1)
        to their position at each time sample; ``H[2, 2]`` is not normalised to 1.

    Raises:
        ValueError: for bad arguments, a degenerate draw whose yaw and pitch vanish while
            ``extent_px > 0``, or an extent too large for the image (see ``extent_px``).
    """
    u = as_uniforms(uniforms, SHAKE_UNIFORMS, "camera_shake_homographies")
    if min(height, width) < 1:
        raise ValueError(f"image size must be positive; got {height} x {width}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1; got {steps}")
    f, cx, cy = _intrinsics(height, width)
    if not (math.isfinite(extent_px) and extent_px >= 0.0):
        raise ValueError(f"extent_px must be finite and >= 0; got {extent_px!r}")
    if not 0.0 <= roll_deg <= SHAKE_ROLL_MAX_DEG:
        raise ValueError(f"roll_deg must be in [0, {SHAKE_ROLL_MAX_DEG:g}]; got {roll_deg!r}")

    t = (np.arange(steps) + 0.5) / steps - 0.5
    k = np.arange(1, SHAKE_HARMONICS + 1, dtype=np.float64)
    amp = (2.0 * u[:-1] - 1.0).reshape(3, 2, SHAKE_HARMONICS)  # axis, (cos, sin), harmonic

    def series(axis: int, times: np.ndarray) -> np.ndarray:
        # harmonic by harmonic in a fixed order (no BLAS), fixedmath's sines
        sin_p, cos_p = fixedmath.sincos(math.pi * np.outer(times, k))
        a, b = amp[axis, 0] / k, amp[axis, 1] / k
        out = cos_p[:, 0] * a[0]
        for j in range(1, SHAKE_HARMONICS):
            out = out + cos_p[:, j] * a[j]
        for j in range(SHAKE_HARMONICS):
            out = out + sin_p[:, j] * b[j]
        return out

    zero = np.zeros(1)
    shapes = [series(axis, t) - series(axis, zero)[0] for axis in range(3)]
    yaw_shape, pitch_shape, roll_shape = shapes

    roll_peak = np.abs(roll_shape).max()
    roll_target = math.radians(roll_deg) * u[-1]
    roll = roll_shape * (roll_target / roll_peak) if roll_peak > 0 else np.zeros(steps)

    def homographies_for(scale: float) -> np.ndarray:
        return _homographies(_rotations(scale * yaw_shape, scale * pitch_shape, roll), f, cx, cy)

    if extent_px == 0.0 or steps == 1:
        return homographies_for(0.0)

    peak = max(np.abs(yaw_shape).max(), np.abs(pitch_shape).max())
    if not peak > 0.0:
        raise ValueError("degenerate draw: yaw and pitch are zero, extent_px cannot be met")
    scale = _solve_extent(
        lambda s: _centre_extent(homographies_for(s), cx, cy),
        extent_px,
        scale_max=SHAKE_ANGLE_MAX_RAD / peak,
        what=f"extent_px={extent_px!r} on a {height} x {width} image (f = {f:g} px)",
    )
    hom = homographies_for(scale)
    _check_in_front(hom, height, width)
    return hom


def _solve_extent(measure, target: float, scale_max: float, what: str) -> float:
    """Find ``s`` in ``(0, scale_max]`` with ``measure(s) = target`` to ``SHAKE_EXTENT_RTOL``.

    ``measure`` is the centre's path extent for yaw and pitch scaled by ``s``: close to linear
    for small angles, where a fixed-point step ``s <- s target / measure(s)`` converges in a
    few steps; if that stops contracting (large angles), bisection on ``[0, scale_max]``
    takes over (``measure(0) = 0``).
    """
    probe = 1e-4 * scale_max / SHAKE_ANGLE_MAX_RAD  # a peak angle of 1e-4 rad
    measured = measure(probe)
    if not measured > 0.0:
        raise ValueError("degenerate draw: the image centre does not move")
    scale = probe * target / measured
    error = math.inf
    for _ in range(30):
        if scale > scale_max:
            break
        measured = measure(scale)
        new_error = abs(measured - target)
        if new_error <= SHAKE_EXTENT_RTOL * target:
            return scale
        if not new_error < 0.5 * error:
            break
        error = new_error
        scale *= target / measured
    lo, hi = 0.0, scale_max
    if measure(hi) < target:
        raise ValueError(
            f"{what} needs a yaw or pitch beyond {math.degrees(SHAKE_ANGLE_MAX_RAD):g} degrees"
        )
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        measured = measure(mid)
        if abs(measured - target) <= SHAKE_EXTENT_RTOL * target:
            return mid
        if measured < target:
            lo = mid
        else:
            hi = mid
    raise RuntimeError(f"camera shake extent search did not converge for {what}")


def _check_in_front(homographies: np.ndarray, height: int, width: int) -> None:
    """Raise unless every frame's inverse map keeps the whole image in front of the camera.

    The third coordinate of ``H^-1 (x, y, 1)`` is affine in ``(x, y)``, so the four corners
    decide it for the whole image.
    """
    corners = np.array(
        [[0.0, width - 1.0, 0.0, width - 1.0], [0.0, 0.0, height - 1.0, height - 1.0], [1.0] * 4]
    )
    for m in fixedmath.inverse3(homographies):
        w = (m[2, 0] * corners[0] + m[2, 1] * corners[1]) + m[2, 2] * corners[2]
        if not (w > 0.0).all():
            raise ValueError(
                f"the camera rotation turns part of the {height} x {width} image behind the "
                "camera; lower extent_px or roll_deg"
            )


#: Output rows :func:`shake_blur` warps through every pose at a time: a band's float64
#: temporaries stay in cache (the built-in 600 x 400 photo's 77 poses: 3.6 -> 1.9 s here).
SHAKE_BAND_ROWS = 32


def _positions(inverse: np.ndarray, height: int, width: int,
               rows: range | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each output pixel samples: ``H^-1 (x, y, 1)`` dehomogenised, ``(px, py)``.

    ``inverse`` is ``H^-1`` (3 x 3), inverted once per pose by the caller (the same inverse
    for every band of rows). ``rows``: only those output rows (default all ``height``).
    Returns two ``len(rows) x width`` arrays.
    """
    rows = range(height) if rows is None else rows
    xs = np.arange(width, dtype=np.float64)[None, :]
    ys = np.arange(rows.start, rows.stop, dtype=np.float64)[:, None]
    den = inverse[2, 0] * xs + inverse[2, 1] * ys + inverse[2, 2]
    if not (den > 0).all():
        raise ValueError("homography maps part of the image through infinity (w <= 0)")
    px = (inverse[0, 0] * xs + inverse[0, 1] * ys + inverse[0, 2]) / den
    py = (inverse[1, 0] * xs + inverse[1, 1] * ys + inverse[1, 2]) / den
    if not (np.isfinite(px).all() and np.isfinite(py).all()):
        raise ValueError("homography maps pixels to non-finite positions")
    if max(np.abs(px).max(), np.abs(py).max()) >= 2.0**52:
        raise ValueError("homography maps pixels too far outside the image to mirror exactly")
    return px, py


def _warp_stack(stack: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """Warp an ``H x W x C`` float64 stack by a validated 3 x 3 homography (see warp_homography)."""
    h, w, c = stack.shape
    px, py = _positions(fixedmath.inverse3(homography), h, w)
    out = bilinear_sample(stack.reshape(h * w, c), h, w, px, py)
    return out.reshape(h, w, c)


def _inside_share(first: np.ndarray, frac: np.ndarray, n: int) -> np.ndarray:
    """The weight of the taps ``first``, ``first + 1`` (``1 - frac``, ``frac``) inside ``[0, n)``.

    Exactly 1 when both are inside (``0 <= first < n - 1``): a sample that reads only the
    image keeps its weight. Only the few samples with a tap outside are looked at further:
    ``frac`` when just the second tap is inside (``first = -1``), ``1 - frac`` when just the
    first is (``first = n - 1``), else 0.
    """
    share = np.ones(first.shape)
    edge = (first < 0) | (first >= n - 1)
    if edge.any():
        at, f = first[edge], frac[edge]
        share[edge] = np.where(at == -1, f, np.where(at == n - 1, 1.0 - f, 0.0))
    return share


def _planes(stack: np.ndarray) -> np.ndarray:
    """The stack and its saturation indicator as planes: ``(2 C, H W + 1)`` float64.

    Row ``k < C`` is channel ``k`` of ``stack`` (``H x W x C``) in row-major pixel order, row
    ``C + k`` its indicator ``[x >= 1]``; the last column is 0 in every row. Why this layout:
    a tap is one gather of a column per pixel (``np.take(..., axis=1)``), so the
    interpolation's products and sums run along long rows of pixels instead of over ``2 C``
    channels at a time; and a tap outside the image reads the zero column instead of being
    multiplied by an inside mask (which would make it ``x * 0``, ``-0`` for a negative finite
    ``x``: a sign that could not reach the output either, see :func:`_warp_inside`).
    """
    h, w, c = stack.shape
    n = h * w
    channels = stack.reshape(n, c).T
    planes = np.zeros((2 * c, n + 1))
    planes[:c, :n] = channels
    planes[c:, :n] = saturation_indicator(channels)
    return planes


def _warp_inside(planes: np.ndarray, inverse: np.ndarray, height: int, width: int,
                 rows: range) -> tuple[np.ndarray, np.ndarray]:
    """Warp the planes reading only pixels inside the image: ``(values, weights)`` of ``rows``.

    ``planes`` as :func:`_planes` lays them out, ``(P, H W + 1)``; ``inverse`` the pose's
    ``H^-1``. ``values`` (``P x len(rows) W``, the rows' pixels in row-major order) is the
    bilinear sample of the image extended by zeros, interpolated as
    :func:`~gpu_blur.reference.sampling.bilinear_sample` does (``a + f (b - a)`` along x, then
    y), and ``weights`` (``len(rows) W``) the share of the sample's bilinear weight that falls
    on pixels of the image: the bilinear sample of a certainty that is 1 inside, 0 outside.
    A sample whose four taps are inside gives the bilinear sample itself and weight exactly 1.

    A tap outside reads +0. Every value this makes differs from one made with a tap of -0
    (a masked ``x * 0``) only in the sign of a zero (``a + f (b - a)`` with a zero ``a`` or
    ``b`` is exact or a zero), and :func:`shake_blur`'s sums start at +0, which adding -0
    leaves +0 (a sum is -0 only when both terms are), so the sums never hold -0 and a zero's
    sign never shows.
    """
    outside = height * width  # the zero column of ``planes``
    px, py = _positions(inverse, height, width, rows)
    px, py = px.ravel(), py.ravel()
    x0, y0 = np.floor(px), np.floor(py)
    fx, fy = px - x0, py - y0
    xi, yi = x0.astype(np.intp), y0.astype(np.intp)
    # each tap's column and row: (inside the image, clamped offset), shared by two taps
    tap_cols = [((x >= 0) & (x < width), np.clip(x, 0, width - 1)) for x in (xi, xi + 1)]
    tap_rows = [((y >= 0) & (y < height), np.clip(y, 0, height - 1) * width)
                for y in (yi, yi + 1)]

    def taps(row: tuple, col: tuple) -> np.ndarray:
        index = row[1] + col[1]
        index[~(row[0] & col[0])] = outside
        return np.take(planes, index, axis=1)

    def lerp(a: np.ndarray, b: np.ndarray, f: np.ndarray) -> np.ndarray:
        b -= a
        b *= f
        a += b
        return a

    top = lerp(taps(tap_rows[0], tap_cols[0]), taps(tap_rows[0], tap_cols[1]), fx)
    bottom = lerp(taps(tap_rows[1], tap_cols[0]), taps(tap_rows[1], tap_cols[1]), fx)
    values = lerp(top, bottom, fy)
    weights = _inside_share(xi, fx, width) * _inside_share(yi, fy, height)
    return values, weights


def _as_homography(homography) -> np.ndarray:
    m = np.asarray(homography, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"homography must be 3 x 3; got {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError("homography must be finite")
    if not abs(fixedmath.det3(m)) >= 1e-300:
        raise ValueError("homography must be invertible")
    return m


def warp_homography(image, homography, border: str = "reflect") -> np.ndarray:
    """Warp an image by a homography, by inverse mapping with bilinear interpolation.

    Output pixel ``(x, y)`` (pixel centres at integer coordinates) takes the input's bilinear
    interpolation at ``H^-1 (x, y, 1)`` (dehomogenised), all in float64, so content at ``p``
    moves to ``H p``. The four neighbours of a position outside the image are mirrored without
    repeating the edge pixel (``BORDER_REFLECT_101``); the mirror is periodic with period
    ``2 (n - 1)``, so positions far outside tile the image with mirrored copies. A zero
    fractional part returns the input pixel exactly, so the identity and integer translations
    are exact.

    Args:
        image: ``H x W`` or ``H x W x C``, finite values.
        homography: ``3 x 3`` invertible, with ``H^-1`` keeping every output pixel in front of
            the camera (positive third coordinate).
        border: ``"reflect"`` (reflect-101; the only rule implemented).

    Returns:
        float64 array of the input's shape.

    Raises:
        ValueError: for an unknown border, a bad image or homography.
    """
    if border != "reflect":
        raise ValueError(f"border must be 'reflect' (reflect-101); got {border!r}")
    img = as_image(image)
    m = _as_homography(homography)
    stack = img if img.ndim == 3 else img[:, :, None]
    return _warp_stack(stack, m).reshape(img.shape)


def shake_blur(image, homographies) -> tuple[np.ndarray, np.ndarray]:
    """Spatially varying blur: the mean of the sharp image warped along a camera path.

    ``blurred = mean_t warp(image, H_t)`` and ``mask = mean_t warp([image >= 1], H_t)``, with
    bilinear inverse mapping as in :func:`warp_homography`. The mask is the same spatially
    varying blur applied to the sharp image's saturation indicator, i.e. the indicator
    convolved with each pixel's local kernel, just as the kernel case blurs ``[I >= 1]`` with
    ``K``; it is not the fraction of saturated warped frames (which :class:`FrameAccumulator`
    would give and which bilinear resampling would make depend on interpolated values). The
    image and the indicator are warped together as one ``2C``-channel stack, summed in float64
    one step at a time (no warped frame is kept; relative error ``<= (steps - 1) * 2**-53``).

    Edges: where a pixel's path leaves the photo, the camera saw content the photo does not
    hold, so nothing is made up for it (a mirrored border would show a reflected copy of the
    content near the edge). Each pixel averages what the photo holds along its path: the sum
    of its samples of the image extended by zeros over the sum of their weights on the image
    (each sample's bilinear weight that falls on pixels of the photo, 1 for a sample inside).
    This is normalized convolution (Knutsson and Westin, "Normalized and differential
    convolution", CVPR 1993) with a certainty of 1 on the photo and 0 outside. Blur near an
    edge is thus the part of the path inside the photo, and a pixel whose samples all lie
    inside gets the plain mean, exactly. A pixel with no weight on the photo at any pose gets
    0: that needs an even ``steps`` (no identity pose) too few for the path, never the odd
    automatic choice (:func:`auto_shake_steps`), whose middle pose is the identity.

    Args:
        image: sharp linear image, ``H x W x C`` (or ``H x W``), finite.
        homographies: ``(steps, 3, 3)``, e.g. from :func:`camera_shake_homographies`.

    Returns:
        ``(blurred, saturation_mask)``, float64, each of the image's shape.

    Raises:
        ValueError: for a bad image or homographies, or zero steps.
    """
    img = as_image(image)
    hom = np.asarray(homographies, dtype=np.float64)
    if hom.ndim != 3 or hom.shape[1:] != (3, 3) or hom.shape[0] < 1:
        raise ValueError(f"homographies must be (steps >= 1, 3, 3); got {hom.shape}")
    stack = img if img.ndim == 3 else img[:, :, None]
    h, w, c = stack.shape
    poses = [_as_homography(m) for m in hom]
    inverses = [fixedmath.inverse3(m) for m in poses]
    planes = _planes(stack)  # (2 C, H W + 1): image then indicator, one plane per channel
    total = np.zeros((2 * c, h * w))
    weight = np.zeros(h * w)
    # a band of rows through every pose at a time keeps its temporaries in cache; each
    # pixel's sum still runs over the poses in order
    for start in range(0, h, SHAKE_BAND_ROWS):
        rows = range(start, min(h, start + SHAKE_BAND_ROWS))
        pixels = slice(start * w, rows.stop * w)
        for inverse in inverses:
            values, weights = _warp_inside(planes, inverse, h, w, rows)
            total[:, pixels] += values
            weight[pixels] += weights
    seen = np.broadcast_to(weight > 0.0, total.shape)
    total = np.divide(total, weight, out=np.zeros_like(total), where=seen)
    return (
        np.ascontiguousarray(total[:c].T).reshape(img.shape),
        np.ascontiguousarray(total[c:].T).reshape(img.shape),
    )


def shake_halo(homographies, height: int, width: int) -> int:
    """Context pixels a tile needs on each side for :func:`shake_blur` with these homographies.

    The largest ``|H^-1 p - p|`` (per axis, in pixels) over every step and a grid of points
    ``p`` covering the image at most 8 pixels apart, edges and corners included, rounded up,
    plus 1 for the bilinear neighbour and 1 for the curvature between grid points (the maps
    are within a hair of affine for the accepted shakes, and an affine displacement peaks at
    a corner). The blur reads only pixels of the full image (:func:`shake_blur`, "Edges").

    Args:
        homographies: ``(steps, 3, 3)``.
        height: image height ``H`` in pixels.
        width: image width ``W`` in pixels.

    Returns:
        The halo in pixels (an int ``>= 1``).
    """
    hom = np.asarray(homographies, dtype=np.float64)
    if hom.ndim != 3 or hom.shape[1:] != (3, 3):
        raise ValueError(f"homographies must be (steps, 3, 3); got {hom.shape}")
    xs = np.linspace(0.0, width - 1.0, max(2, math.ceil((width - 1) / 8) + 1))
    ys = np.linspace(0.0, height - 1.0, max(2, math.ceil((height - 1) / 8) + 1))
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
    reach = 0.0
    for m in hom:
        q = fixedmath.matvec3(fixedmath.inverse3(_as_homography(m)), pts.T).T
        dx = np.abs(q[0] / q[2] - pts[0]).max()
        dy = np.abs(q[1] / q[2] - pts[1]).max()
        reach = max(reach, dx, dy)
    return math.ceil(reach) + 2


#: Dense sampling used to measure a camera path before choosing its number of poses.
SHAKE_PROBE_STEPS = 129
#: Fewest and most poses :func:`auto_shake_steps` chooses.
SHAKE_AUTO_STEPS_RANGE = (9, 1025)


def auto_shake_steps(uniforms, height: int, width: int, extent_px: float,
                     roll_deg: float) -> int:
    """Number of poses that keeps every pixel's step along the path within about one pixel.

    The path is drawn once with :data:`SHAKE_PROBE_STEPS` poses; the peak speed among the
    image centre and its four corners, ``v`` pixels per exposure, gives the smallest odd
    ``n >= v + 1`` within :data:`SHAKE_AUTO_STEPS_RANGE` (odd, so the middle pose is the
    identity). Fewer poses would show the blur as separate copies instead of a streak.
    """
    hom = camera_shake_homographies(uniforms, height, width, SHAKE_PROBE_STEPS, extent_px,
                                    roll_deg)
    points = np.array([[(width - 1) / 2, (height - 1) / 2, 1.0], [0, 0, 1.0],
                       [width - 1, 0, 1.0], [0, height - 1, 1.0], [width - 1, height - 1, 1.0]])
    p = fixedmath.matvec3(hom[:, None], points[None])  # (steps, points, 3)
    xy = p[..., :2] / p[..., 2:]
    # peak speed in pixels per exposure: the largest probe step times the number of steps
    d = np.diff(xy, axis=0)
    speed = float(fixedmath.hypot(d[..., 0], d[..., 1]).max()) * SHAKE_PROBE_STEPS
    n = math.ceil(speed) + 1
    n += 1 - n % 2
    lo, hi = SHAKE_AUTO_STEPS_RANGE
    return int(min(max(n, lo), hi))

