"""Blur synthesis in linear RGB: frame averaging, kernel convolution and camera-shake warps.

This is the offline half of RSBlur (Rim et al., "Realistic Blur Synthesis for Learning Image
Deblurring", ECCV 2022), which the authors describe only in GitHub issues #2, #4 and #6 of
``rimchang/RSBlur`` (pipeline notes, section 2):

* **Averaging** (RSBlur "syn", GoPro_INTER_ABME, section 2A): the blurred image is the plain,
  equally weighted mean of the linearised frames, and the saturation mask is, per channel, the
  fraction of frames whose linear value is saturated (neither "any channel" nor "all
  channels"). See :class:`FrameAccumulator` and :func:`average_frames`.
* **Kernel** (GoPro_U, section 2B): ``B = I * K`` and ``M = [I >= 1] * K`` with one kernel
  ``K`` for the image and its saturation indicator. See :func:`convolve_kernel`,
  :func:`random_motion_kernel` and :func:`saturation_indicator`.
* **Camera shake** (an extension for spatially varying blur): the sharp image and its
  indicator are warped by the homographies ``K R_t K^-1`` of a small random camera rotation
  and averaged, as in Whyte et al., "Non-uniform Deblurring for Shaken Images" (CVPR 2010;
  IJCV 98, 2012). See :func:`camera_shake_homographies`, :func:`warp_homography` and
  :func:`shake_blur`.

The mask feeds the saturation step of pipeline section 5.8, ``clip(B + alpha * M, 0, 1)``,
the local scaling of supplementary section 12, ``clip[(I_nsat + alpha I_sat) * K]``, in which
``I_sat`` is the saturated part of the sharp image: so the mask is the blur of the indicator.

Conventions:
    * Images are linear RGB ``H x W x 3`` float64 (the caller linearises sRGB frames first);
      where said, ``H x W`` and ``H x W x C`` are accepted too and the shape is kept.
    * Pixel ``(x, y)`` (column, row) has its centre at the integer coordinates ``(x, y)``.
    * A value is saturated when its linear value is ``>= 1`` (:data:`SATURATION_LEVEL`). The
      RSBlur issue tests ``== 1`` on 8-bit frames, where no linear value exceeds 1, so the two
      agree there; ``>= 1`` also counts values above 1 from float inputs.
    * Boundary rule everywhere: mirror **without** repeating the edge pixel, i.e. numpy's
      ``pad(mode="reflect")``, OpenCV's ``BORDER_REFLECT_101`` and scipy's ``"mirror"``:
      ``... c b | a b c ... | b a ...``. The extension is periodic with period ``2 (n - 1)``,
      so it is defined arbitrarily far outside; an axis of length 1 is constant.
    * Randomness arrives as 1-D arrays of uniforms in the open interval (0, 1), drawn by the
      caller; :data:`KERNEL_UNIFORMS` and :data:`SHAKE_UNIFORMS` say how many each function
      consumes, always exactly that many, whatever the draws turn out to be.
    * Sums are plain float64 sums. For ``n`` non-negative terms the relative error of a plain
      running sum is at most ``(n - 1) u`` with ``u = 2**-53`` (Higham, "Accuracy and Stability
      of Numerical Algorithms", 2nd ed., section 4.2): below ``1.2e-13`` for 1,000 frames.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

__all__ = [
    "GOPRO_U_KERNEL_SIZES",
    "KERNEL_UNIFORMS",
    "KERNEL_WALK_STEPS",
    "SATURATION_LEVEL",
    "SHAKE_HARMONICS",
    "SHAKE_UNIFORMS",
    "FrameAccumulator",
    "auto_shake_steps",
    "blur_halo",
    "average_frames",
    "camera_shake_homographies",
    "convolve_kernel",
    "kernel_halo",
    "normalize_kernel",
    "random_motion_kernel",
    "saturation_indicator",
    "shake_blur",
    "shake_halo",
    "warp_homography",
]

#: Linear value at or above which a channel counts as saturated (RSBlur issue #6: 8-bit 255).
SATURATION_LEVEL = 1.0

#: Kernel sizes of GoPro_U: the 13 odd sizes 5, 7, ..., 29, about 1,600 pairs each
#: (``datalist/GoPro/GoPro_U_train.txt`` of rimchang/RSBlur; pipeline notes section 2B).
GOPRO_U_KERNEL_SIZES: tuple[int, ...] = tuple(range(5, 30, 2))

# -- random motion kernel: a momentum random walk after Boracchi & Foi (IEEE TIP 2012) --------
#: Vertices of the random walk (the walk makes ``KERNEL_WALK_STEPS - 1`` equal-length steps).
KERNEL_WALK_STEPS = 64
#: Largest per-step standard deviation of the Gaussian turn, relative to the speed.
KERNEL_JITTER_MAX = 0.4
#: Largest centripetal pull, per step, relative to the speed, per unit distance from the start
#: (distances in units of the walk's total length).
KERNEL_PULL_MAX = 0.5
#: Largest per-step probability of an abrupt shake (a near reversal of the direction).
KERNEL_SHAKE_PROBABILITY_MAX = 0.03
#: Half-width (radians) of the uniform spread of an abrupt shake's turn around pi.
KERNEL_SHAKE_TURN_SPREAD_RAD = 0.5
#: The walk's largest distance from its centroid along x or y, as a fraction of the half-size
#: ``(size - 1) / 2``, is drawn uniformly from [KERNEL_EXTENT_MIN, 1).
KERNEL_EXTENT_MIN = 0.5
#: Largest spacing (pixels) between the samples of the path that are splatted onto the grid.
KERNEL_SAMPLE_SPACING_PX = 0.1
#: Uniforms consumed by :func:`random_motion_kernel`: 5 for the walk's parameters (initial
#: direction, jitter, pull, shake probability, extent), then 4 per step (a complex Gaussian from
#: two, a shake test, a shake turn).
KERNEL_UNIFORMS = 5 + 4 * (KERNEL_WALK_STEPS - 1)

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


# ------------------------------------------------------------------------------------------
# Validation helpers
# ------------------------------------------------------------------------------------------


def _as_image(image, name: str = "image") -> np.ndarray:
    """Return ``image`` as a finite float64 array of shape ``H x W`` or ``H x W x C``."""
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim not in (2, 3) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{name} must be H x W or H x W x C with H, W >= 1; got {arr.shape}")
    if arr.ndim == 3 and arr.shape[2] < 1:
        raise ValueError(f"{name} must have at least one channel; got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    return arr


def _as_uniforms(uniforms, count: int, name: str) -> np.ndarray:
    """Return ``uniforms`` as a float64 vector of ``count`` values in the open interval (0, 1)."""
    u = np.asarray(uniforms, dtype=np.float64)
    if u.shape != (count,):
        raise ValueError(f"{name} needs exactly ({count},) uniforms; got shape {u.shape}")
    if not ((u > 0.0) & (u < 1.0)).all():
        raise ValueError(f"{name} needs uniforms in the open interval (0, 1)")
    return u


def _reflect101_index(index: np.ndarray, n: int) -> np.ndarray:
    """Map integer indices into ``[0, n)`` by mirroring without repeating the edge pixel.

    Periodic with period ``2 (n - 1)``, so valid arbitrarily far outside. A length-1 axis maps
    everything to 0. Indices already inside are returned unchanged (as ``intp``).
    """
    index = index.astype(np.intp, copy=False)
    if n == 1:
        return np.zeros(index.shape, dtype=np.intp)
    if index.size and index.min() >= 0 and index.max() < n:
        return index
    period = 2 * (n - 1)
    m = np.mod(index, period)
    return np.where(m >= n, period - m, m)


def _next_fast_len(n: int) -> int:
    """Smallest 5-smooth integer (only factors 2, 3, 5) that is ``>= n``; fast for numpy.fft."""
    m = max(int(n), 1)
    while True:
        rest = m
        for prime in (2, 3, 5):
            while rest % prime == 0:
                rest //= prime
        if rest == 1:
            return m
        m += 1


# ------------------------------------------------------------------------------------------
# 1. Averaging and the saturation indicator
# ------------------------------------------------------------------------------------------


def saturation_indicator(linear) -> np.ndarray:
    """Per-channel saturation indicator ``[x >= 1]``.

    Args:
        linear: linear values, any shape.

    Returns:
        float64 array of the same shape: 1.0 where the value is ``>= SATURATION_LEVEL`` (1.0),
        else 0.0 (NaN counts as unsaturated).
    """
    return (np.asarray(linear, dtype=np.float64) >= SATURATION_LEVEL).astype(np.float64)


class FrameAccumulator:
    """Running mean of linear frames and per-channel fraction of saturated frames.

    RSBlur issue #6 (pipeline notes section 2A): ``B = mean_t(frame_t)`` with equal weights and
    ``M = mean_t([frame_t >= 1])`` per channel. Frames are added one at a time and not kept, so
    65 (RSBlur) or 1,000 frames cost the memory of two images. The image sum is a plain float64
    sum (relative error ``<= (n - 1) * 2**-53`` for non-negative frames, ``< 1.2e-13`` at
    ``n = 1000``); the saturation counts are float64 sums, exact integers unless a frame brings
    its own fractional indicator (an interpolated frame, :mod:`gpu_blur.reference.interpolate`).

    Args:
        height: frame height ``H`` in pixels.
        width: frame width ``W`` in pixels.
        channels: channels per frame ``C`` (3 for RGB).
    """

    def __init__(self, height: int, width: int, channels: int = 3) -> None:
        if min(height, width, channels) < 1:
            raise ValueError(f"frame shape must be positive; got ({height}, {width}, {channels})")
        self.shape: tuple[int, int, int] = (int(height), int(width), int(channels))
        self._sum = np.zeros(self.shape, dtype=np.float64)
        self._saturated = np.zeros(self.shape, dtype=np.float64)
        self._count = 0

    @property
    def count(self) -> int:
        """Number of frames added so far."""
        return self._count

    def add(self, frame_linear, saturated=None) -> None:
        """Add one linear frame.

        Args:
            frame_linear: ``H x W x C`` linear values (any real dtype; summed in float64).
            saturated: ``H x W x C`` saturated fraction of each value in [0, 1], or ``None``
                for ``[frame_linear >= 1]``.

        Raises:
            ValueError: if the frame's shape is not the accumulator's, or it is not finite.
        """
        frame = np.asarray(frame_linear, dtype=np.float64)
        if frame.shape != self.shape:
            raise ValueError(
                f"frame shape {frame.shape} does not match the accumulator's shape {self.shape}"
            )
        if not np.isfinite(frame).all():
            raise ValueError("frame must be finite (no NaN or inf)")
        self._sum += frame
        if saturated is None:
            self._saturated += frame >= SATURATION_LEVEL
        else:
            self._saturated += np.asarray(saturated, dtype=np.float64)
        self._count += 1

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(blurred, saturation_mask)``, both ``H x W x C`` float64.

        ``blurred`` is the mean of the frames; ``saturation_mask`` is, per pixel and channel,
        the mean of the frames' saturated fractions: the fraction of frames at or above
        :data:`SATURATION_LEVEL` (multiples of ``1 / n``) when every frame was tested by its
        value.

        Raises:
            ValueError: if no frame was added.
        """
        if self._count == 0:
            raise ValueError("cannot average zero frames")
        return self._sum / self._count, self._saturated / self._count


def average_frames(frames: Iterable) -> tuple[np.ndarray, np.ndarray]:
    """Average linear frames: RSBlur's offline averaging step (issue #6).

    Args:
        frames: an iterable of ``H x W x C`` linear frames of one shape (consumed once, never
            held all at once).

    Returns:
        ``(blurred, saturation_mask)``, see :meth:`FrameAccumulator.result`.

    Raises:
        ValueError: for zero frames, frames that are not ``H x W x C``, or differing shapes.
    """
    acc: FrameAccumulator | None = None
    for frame in frames:
        frame = np.asarray(frame, dtype=np.float64)
        if acc is None:
            if frame.ndim != 3:
                raise ValueError(f"frames must be H x W x C; got {frame.shape}")
            acc = FrameAccumulator(*frame.shape)
        acc.add(frame)
    if acc is None:
        raise ValueError("cannot average zero frames")
    return acc.result()


# ------------------------------------------------------------------------------------------
# 2. Kernel blur
# ------------------------------------------------------------------------------------------


def normalize_kernel(kernel) -> np.ndarray:
    """Validate a blur kernel and scale it to sum 1.

    Args:
        kernel: ``kh x kw`` non-negative weights with odd ``kh`` and ``kw``; the centre
            ``(kh // 2, kw // 2)`` is the origin.

    Returns:
        float64 ``kh x kw`` kernel summing to 1.

    Raises:
        ValueError: if the kernel is not 2-D, has an even side, holds NaN, inf or negative
            values, or sums to ``<= 0``.
    """
    k = np.asarray(kernel, dtype=np.float64)
    if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise ValueError(
            f"kernel must be 2-D with odd sides (its centre is the origin); got shape {k.shape}"
        )
    if not np.isfinite(k).all():
        raise ValueError("kernel must be finite (no NaN or inf)")
    if (k < 0).any():
        raise ValueError(f"kernel must be non-negative; its minimum is {k.min()!r}")
    total = k.sum()
    if not total > 0:
        raise ValueError(f"kernel must sum to a positive value; it sums to {total!r}")
    return k / total


def kernel_halo(kernel: np.ndarray | int) -> int:
    """Context pixels a tile needs on each side for :func:`convolve_kernel`.

    Args:
        kernel: the kernel (``kh x kw``, odd sides) or its odd size.

    Returns:
        ``max(kh, kw) // 2``. A tile must take its halo from the full image's mirrored
        extension, not from a mirror at the tile's own edge.
    """
    if isinstance(kernel, (int, np.integer)):
        if kernel < 1 or kernel % 2 == 0:
            raise ValueError(f"kernel size must be a positive odd integer; got {kernel}")
        return int(kernel) // 2
    shape = np.shape(kernel)
    if len(shape) != 2 or shape[0] % 2 == 0 or shape[1] % 2 == 0:
        raise ValueError(f"kernel must be 2-D with odd sides; got shape {shape}")
    return max(shape) // 2


def convolve_kernel(image, kernel) -> np.ndarray:
    """Blur with a spatially invariant kernel: ``out = image * normalize(kernel)``.

    A true convolution (the kernel is flipped), centred on the kernel's middle entry:
    ``out[y, x] = sum_{i, j} k[i, j] * img[y + r_y - i, x + r_x - j]`` with ``r = shape // 2``,
    so a kernel whose mass sits right of its centre moves content to the right. The output has
    the input's size ("same"); pixels outside are the mirror of the image without repeating
    the edge pixel (``BORDER_REFLECT_101``). RSBlur's issue #6 leaves the size and boundary
    conventions open (pipeline notes section 2B); these are our choice. Each channel is blurred
    independently; the saturation mask is made by calling this again on
    :func:`saturation_indicator` of the sharp image.

    Computed as a product of real FFTs (``numpy.fft.rfft2``) of the mirror-padded image and the
    kernel, padded to 5-smooth lengths of at least ``H + 2 r_y`` by ``W + 2 r_x``, which avoids
    wrap-around. The absolute error is a few ``1e-16`` times ``max |image|`` (well inside
    ``1e-12`` relative for kernels up to 65 x 65 on 2-megapixel images).

    Args:
        image: ``H x W``, or ``H x W x C`` (any ``C``), finite values.
        kernel: ``kh x kw`` non-negative weights, odd sides; normalised to sum 1 here.

    Returns:
        float64 array of the input's shape.

    Raises:
        ValueError: see :func:`normalize_kernel`, or for a bad image.
    """
    img = _as_image(image)
    k = normalize_kernel(kernel)
    ry, rx = k.shape[0] // 2, k.shape[1] // 2
    stack = img if img.ndim == 3 else img[:, :, None]
    h, w, _ = stack.shape
    padded = np.pad(stack, ((ry, ry), (rx, rx), (0, 0)), mode="reflect")
    fft_shape = (_next_fast_len(h + 2 * ry), _next_fast_len(w + 2 * rx))
    spectrum = np.fft.rfft2(padded, s=fft_shape, axes=(0, 1))
    spectrum *= np.fft.rfft2(k, s=fft_shape)[:, :, None]
    full = np.fft.irfft2(spectrum, s=fft_shape, axes=(0, 1))
    # circular index n = y + 2 r_y reads padded rows n - i in [0, h + 2 r_y): no wrap-around
    out = np.ascontiguousarray(full[2 * ry : 2 * ry + h, 2 * rx : 2 * rx + w])
    return out.reshape(img.shape)


def random_motion_kernel(uniforms, size: int) -> np.ndarray:
    """Draw a random camera-motion blur kernel, centred on its centroid.

    Path model, a momentum random walk after Boracchi & Foi, "Modeling the Performance of Image
    Restoration From Motion Blur", IEEE TIP 21(8), 2012 (their trajectory generator: a particle
    with inertia, Gaussian perturbations, a centripetal pull back to the start and rare abrupt
    "big shakes"); parameters and scaling are ours:

    1. ``x_0 = 0``, velocity ``v_0 = exp(i theta_0) / (N - 1)`` (complex plane,
       ``N = KERNEL_WALK_STEPS``, so the walk has unit length).
    2. Per step ``j = 1 .. N - 1``: with probability ``p`` an abrupt shake turns ``v`` by
       ``pi + delta``, ``delta`` uniform in ``(-0.5, 0.5)`` rad; otherwise
       ``v += |v| (sigma g_j - kappa x_{j-1})`` with ``g_j`` a standard complex Gaussian
       (Box-Muller; each part has variance 1). Then ``v`` is rescaled to length ``1 / (N - 1)``
       (constant speed, as in Boracchi & Foi) and ``x_j = x_{j-1} + v``.
    3. The polyline is sampled at the midpoints of equal time slices, about
       ``KERNEL_SAMPLE_SPACING_PX`` pixels apart or less; constant speed makes equal time
       equal length.
    4. The samples are scaled so their largest distance from their mean along x or y is
       ``e (size - 1) / 2``, and shifted so their mean lands on the centre pixel
       ``((size - 1) / 2, (size - 1) / 2)``; so the path fits inside the grid.
    5. Each sample splats weight ``1 / n_samples`` bilinearly onto the four pixels around it.
       Bilinear splatting keeps the first moment, so the kernel's centroid is the samples' mean:
       the centre pixel, to rounding (~1e-14 px), well within the half pixel asked for. This
       keeps the blurred image aligned with the sharp one, as RSBlur's GoPro_U
       ``centroid_blurred`` images suggest (pipeline notes section 2B).

    Uniform layout (``KERNEL_UNIFORMS`` = 257 values): ``u[0]`` initial direction
    ``theta_0 = 2 pi u``; ``u[1]`` jitter ``sigma = KERNEL_JITTER_MAX u``; ``u[2]`` pull
    ``kappa = KERNEL_PULL_MAX u``; ``u[3]`` shake probability
    ``p = KERNEL_SHAKE_PROBABILITY_MAX u``; ``u[4]`` extent
    ``e = KERNEL_EXTENT_MIN + (1 - KERNEL_EXTENT_MIN) u``; then per step four values: two for
    ``g_j``, one shake test (shake when ``u < p``), one for ``delta``. All are consumed even
    when unused (a step that does not shake still takes its turn's uniform).

    GoPro_U (RSBlur's kernel-based set) used the 13 odd sizes 5..29
    (:data:`GOPRO_U_KERNEL_SIZES`); its kernel generator is not published.

    Args:
        uniforms: ``(KERNEL_UNIFORMS,)`` uniforms in the open interval (0, 1).
        size: odd kernel side ``>= 3`` (pixels).

    Returns:
        ``size x size`` float64, non-negative, summing to 1, centroid at ``(size // 2,
        size // 2)`` (row, column), ``kernel[row, col]`` with rows along y.

    Raises:
        ValueError: for a wrong count of uniforms, values outside (0, 1), or a bad size.
    """
    u = _as_uniforms(uniforms, KERNEL_UNIFORMS, "random_motion_kernel")
    if (
        isinstance(size, bool)
        or not isinstance(size, (int, np.integer))
        or size < 3
        or size % 2 == 0
    ):
        raise ValueError(f"size must be an odd integer >= 3; got {size!r}")
    size = int(size)
    n = KERNEL_WALK_STEPS
    step_len = 1.0 / (n - 1)
    theta0 = 2.0 * math.pi * u[0]
    sigma = KERNEL_JITTER_MAX * u[1]
    kappa = KERNEL_PULL_MAX * u[2]
    p_shake = KERNEL_SHAKE_PROBABILITY_MAX * u[3]
    extent = KERNEL_EXTENT_MIN + (1.0 - KERNEL_EXTENT_MIN) * u[4]
    steps = u[5:].reshape(n - 1, 4)

    # complex Gaussians by Box-Muller, all at once
    radius = np.sqrt(-2.0 * np.log(steps[:, 0]))
    gauss = radius * np.exp(2j * math.pi * steps[:, 1])
    turn = np.exp(1j * (math.pi + 2.0 * KERNEL_SHAKE_TURN_SPREAD_RAD * (steps[:, 3] - 0.5)))
    shake = steps[:, 2] < p_shake

    path = np.empty(n, dtype=np.complex128)
    path[0] = 0.0
    v = step_len * complex(math.cos(theta0), math.sin(theta0))
    x = 0j
    for j in range(n - 1):
        if shake[j]:
            v = v * turn[j]
        else:
            candidate = v + abs(v) * (sigma * gauss[j] - kappa * x)
            mag = abs(candidate)
            if mag > 0.0:
                v = candidate * (step_len / mag)
        x = x + v
        path[j + 1] = x

    # upper bound on the final scale, to choose the sampling density
    centre = (size - 1) / 2.0
    side = max(np.ptp(path.real), np.ptp(path.imag))
    scale_bound = centre / (0.5 * side)
    per_step = max(1, math.ceil(scale_bound * step_len / KERNEL_SAMPLE_SPACING_PX))
    n_samples = (n - 1) * per_step
    t = (np.arange(n_samples) + 0.5) / per_step  # midpoints of equal slices, in walk steps
    knots = np.arange(n, dtype=np.float64)
    sx = np.interp(t, knots, path.real)
    sy = np.interp(t, knots, path.imag)

    sx -= sx.mean()
    sy -= sy.mean()
    reach = max(np.abs(sx).max(), np.abs(sy).max())
    scale = extent * centre / reach
    sx = np.clip(sx * scale + centre, 0.0, size - 1.0)
    sy = np.clip(sy * scale + centre, 0.0, size - 1.0)

    x0 = np.minimum(np.floor(sx), size - 2).astype(np.intp)
    y0 = np.minimum(np.floor(sy), size - 2).astype(np.intp)
    fx = sx - x0
    fy = sy - y0
    weight = 1.0 / n_samples
    flat = np.zeros(size * size, dtype=np.float64)
    base = y0 * size + x0
    for offset, wgt in (
        (0, (1.0 - fy) * (1.0 - fx)),
        (1, (1.0 - fy) * fx),
        (size, fy * (1.0 - fx)),
        (size + 1, fy * fx),
    ):
        flat += np.bincount(base + offset, weights=wgt * weight, minlength=size * size)
    kernel = flat.reshape(size, size)
    return kernel / kernel.sum()


# ------------------------------------------------------------------------------------------
# 3. Camera shake: homographies, warps and their average
# ------------------------------------------------------------------------------------------


def _intrinsics(height: int, width: int) -> tuple[float, float, float]:
    """Pinhole intrinsics ``(f, cx, cy)`` in pixels: ``f = max(H, W)``, centre of the image."""
    return float(max(height, width)), (width - 1) / 2.0, (height - 1) / 2.0


def _rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``R = R_z(roll) R_x(pitch) R_y(yaw)`` for arrays of angles (radians), ``(n, 3, 3)``."""
    cy_, sy_ = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
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
    return r_roll @ r_pitch @ r_yaw


def _homographies(rot: np.ndarray, f: float, cx: float, cy: float) -> np.ndarray:
    """``H = K R K^-1``, computed as ``I + K (R - I) K^-1`` so that ``R = I`` gives exactly I."""
    k = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    k_inv = np.array([[1.0 / f, 0.0, -cx / f], [0.0, 1.0 / f, -cy / f], [0.0, 0.0, 1.0]])
    return np.eye(3) + k @ (rot - np.eye(3)) @ k_inv


def _centre_extent(homographies: np.ndarray, cx: float, cy: float) -> float:
    """Bounding-box diagonal (pixels) of the image centre's positions under the homographies."""
    p = homographies @ np.array([cx, cy, 1.0])
    x = p[:, 0] / p[:, 2]
    y = p[:, 1] / p[:, 2]
    return float(math.hypot(np.ptp(x), np.ptp(y)))


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
    u = _as_uniforms(uniforms, SHAKE_UNIFORMS, "camera_shake_homographies")
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
        phase = math.pi * np.outer(times, k)
        return (np.cos(phase) @ (amp[axis, 0] / k)) + (np.sin(phase) @ (amp[axis, 1] / k))

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
    for m in homographies:
        if not (np.linalg.inv(m)[2] @ corners > 0.0).all():
            raise ValueError(
                f"the camera rotation turns part of the {height} x {width} image behind the "
                "camera; lower extent_px or roll_deg"
            )


def _bilinear_sample(
    flat: np.ndarray, height: int, width: int, px: np.ndarray, py: np.ndarray
) -> np.ndarray:
    """Sample ``flat`` (``(H W) x C`` rows of an image) bilinearly at float positions.

    Interpolates as ``a + f (b - a)`` along x, then along y, so a zero fraction returns the
    pixel exactly. Neighbours outside are mirrored (reflect-101), arbitrarily far out.
    """
    x0 = np.floor(px)
    y0 = np.floor(py)
    fx = (px - x0)[..., None]
    fy = (py - y0)[..., None]
    xi = x0.astype(np.intp)
    yi = y0.astype(np.intp)
    ix0 = _reflect101_index(xi, width)
    ix1 = _reflect101_index(xi + 1, width)
    row0 = _reflect101_index(yi, height) * width
    row1 = _reflect101_index(yi + 1, height) * width

    def lerp_x(row: np.ndarray) -> np.ndarray:
        left = np.take(flat, row + ix0, axis=0)
        right = np.take(flat, row + ix1, axis=0)
        right -= left
        right *= fx
        left += right
        return left

    top = lerp_x(row0)
    bottom = lerp_x(row1)
    bottom -= top
    bottom *= fy
    top += bottom
    return top


def _warp_stack(stack: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """Warp an ``H x W x C`` float64 stack by a validated 3 x 3 homography (see warp_homography)."""
    h, w, c = stack.shape
    inv = np.linalg.inv(homography)
    xs = np.arange(w, dtype=np.float64)[None, :]
    ys = np.arange(h, dtype=np.float64)[:, None]
    den = inv[2, 0] * xs + inv[2, 1] * ys + inv[2, 2]
    if not (den > 0).all():
        raise ValueError("homography maps part of the image through infinity (w <= 0)")
    px = (inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2]) / den
    py = (inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]) / den
    if not (np.isfinite(px).all() and np.isfinite(py).all()):
        raise ValueError("homography maps pixels to non-finite positions")
    if max(np.abs(px).max(), np.abs(py).max()) >= 2.0**52:
        raise ValueError("homography maps pixels too far outside the image to mirror exactly")
    out = _bilinear_sample(stack.reshape(h * w, c), h, w, px, py)
    return out.reshape(h, w, c)


def _as_homography(homography) -> np.ndarray:
    m = np.asarray(homography, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"homography must be 3 x 3; got {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError("homography must be finite")
    if abs(np.linalg.det(m)) < 1e-300:
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
    img = _as_image(image)
    m = _as_homography(homography)
    stack = img if img.ndim == 3 else img[:, :, None]
    return _warp_stack(stack, m).reshape(img.shape)


def shake_blur(image, homographies) -> tuple[np.ndarray, np.ndarray]:
    """Spatially varying blur: the mean of the sharp image warped along a camera path.

    ``blurred = mean_t warp(image, H_t)`` and ``mask = mean_t warp([image >= 1], H_t)``, with
    :func:`warp_homography` (bilinear, reflect-101). The mask is the same spatially varying
    blur applied to the sharp image's saturation indicator, i.e. the indicator convolved with
    each pixel's local kernel, just as the kernel case blurs ``[I >= 1]`` with ``K``; it is not
    the fraction of saturated warped frames (which :class:`FrameAccumulator` would give and
    which bilinear resampling would make depend on interpolated values). The image and the
    indicator are warped together as one ``2C``-channel stack, summed in float64 one step at a
    time (no warped frame is kept; relative error ``<= (steps - 1) * 2**-53``).

    Args:
        image: sharp linear image, ``H x W x C`` (or ``H x W``), finite.
        homographies: ``(steps, 3, 3)``, e.g. from :func:`camera_shake_homographies`.

    Returns:
        ``(blurred, saturation_mask)``, float64, each of the image's shape.

    Raises:
        ValueError: for a bad image or homographies, or zero steps.
    """
    img = _as_image(image)
    hom = np.asarray(homographies, dtype=np.float64)
    if hom.ndim != 3 or hom.shape[1:] != (3, 3) or hom.shape[0] < 1:
        raise ValueError(f"homographies must be (steps >= 1, 3, 3); got {hom.shape}")
    stack = img if img.ndim == 3 else img[:, :, None]
    c = stack.shape[2]
    both = np.concatenate([stack, saturation_indicator(stack)], axis=2)
    total = np.zeros_like(both)
    for m in hom:
        total += _warp_stack(both, _as_homography(m))
    total /= hom.shape[0]
    return (
        np.ascontiguousarray(total[:, :, :c]).reshape(img.shape),
        np.ascontiguousarray(total[:, :, c:]).reshape(img.shape),
    )


def shake_halo(homographies, height: int, width: int) -> int:
    """Context pixels a tile needs on each side for :func:`shake_blur` with these homographies.

    The largest ``|H^-1 p - p|`` (per axis, in pixels) over every step and a grid of points
    ``p`` covering the image at most 8 pixels apart, edges and corners included, rounded up,
    plus 1 for the bilinear neighbour and 1 for the curvature between grid points (the maps
    are within a hair of affine for the accepted shakes, and an affine displacement peaks at
    a corner). As for kernels, the halo must come from the full image's mirrored extension.

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
        q = np.linalg.inv(_as_homography(m)) @ pts
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
    p = np.einsum("sij,nj->sni", hom, points)
    xy = p[..., :2] / p[..., 2:]
    # peak speed in pixels per exposure: the largest probe step times the number of steps
    speed = float(np.linalg.norm(np.diff(xy, axis=0), axis=-1).max()) * SHAKE_PROBE_STEPS
    n = math.ceil(speed) + 1
    n += 1 - n % 2
    lo, hi = SHAKE_AUTO_STEPS_RANGE
    return int(min(max(n, lo), hi))


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
        from gpu_blur.reference.interpolate import interpolation_halo  # it imports this module

        return interpolation_halo(params["flows"])
    if mode == "kernel":
        return kernel_halo(normalize_kernel(params["kernel"]))
    if mode == "trajectory":
        return shake_halo(params["homographies"], height, width)
    return 0
