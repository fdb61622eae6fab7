"""Blur by one spatially invariant kernel (GoPro_U; pipeline notes section 2B).

``B = I * K`` and ``M = [I >= 1] * K`` with one kernel ``K`` for the image and its saturation
indicator (:func:`gpu_blur.reference.average.saturation_indicator`); random kernels are
momentum random walks after Boracchi & Foi (IEEE TIP 2012). See
:mod:`gpu_blur.reference.blur` for the conventions shared by the blur kinds.
"""

from __future__ import annotations

import math

import numpy as np

from gpu_blur.reference import fixedmath
from gpu_blur.reference.lazy_scipy import scipy_function
from gpu_blur.reference.sampling import as_image, as_uniforms

__all__ = [
    "GOPRO_U_KERNEL_SIZES",
    "KERNEL_UNIFORMS",
    "KERNEL_WALK_STEPS",
    "KERNEL_WALK_VALUES",
    "convolve_kernel",
    "kernel_halo",
    "kernel_walk_values",
    "normalize_kernel",
    "random_motion_kernel",
]

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
#: Values :func:`kernel_walk_values` gives a kernel: a radius per step, then the sines and then
#: the cosines of each step's Gaussian angle, each step's shake turn and the start direction.
KERNEL_WALK_VALUES = (KERNEL_WALK_STEPS - 1) + 2 * (2 * (KERNEL_WALK_STEPS - 1) + 1)


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

    Computed as a product of real FFTs (``numpy.fft.rfft2``; the product in real operations) of
    the mirror-padded image and the kernel, padded to 5-smooth lengths of at least
    ``H + 2 r_y`` by ``W + 2 r_x``, which avoids wrap-around. The absolute error is a few
    ``1e-16`` times ``max |image|`` (well inside ``1e-12`` relative for kernels up to 65 x 65
    on 2-megapixel images).

    Args:
        image: ``H x W``, or ``H x W x C`` (any ``C``), finite values.
        kernel: ``kh x kw`` non-negative weights, odd sides; normalised to sum 1 here.

    Returns:
        float64 array of the input's shape.

    Raises:
        ValueError: see :func:`normalize_kernel`, or for a bad image.
    """
    img = as_image(image)
    k = normalize_kernel(kernel)
    ry, rx = k.shape[0] // 2, k.shape[1] // 2
    stack = img if img.ndim == 3 else img[:, :, None]
    h, w, _ = stack.shape
    padded = np.pad(stack, ((ry, ry), (rx, rx), (0, 0)), mode="reflect")
    next_fast_len = scipy_function("scipy.fft", "next_fast_len", "convolve_kernel")
    fft_shape = (next_fast_len(h + 2 * ry), next_fast_len(w + 2 * rx))
    spectrum = np.fft.rfft2(padded, s=fft_shape, axes=(0, 1))
    kernel_spectrum = np.fft.rfft2(k, s=fft_shape)[:, :, None]
    # the complex product in real operations, one rounding each: numpy's complex multiply
    # takes another SIMD path (with fused a * b + c) on another CPU
    ar, ai, br, bi = spectrum.real, spectrum.imag, kernel_spectrum.real, kernel_spectrum.imag
    product = np.empty(np.broadcast_shapes(spectrum.shape, kernel_spectrum.shape), complex)
    product.real = ar * br - ai * bi
    product.imag = ar * bi + ai * br
    full = np.fft.irfft2(product, s=fft_shape, axes=(0, 1))
    # circular index n = y + 2 r_y reads padded rows n - i in [0, h + 2 r_y): no wrap-around
    out = np.ascontiguousarray(full[2 * ry : 2 * ry + h, 2 * rx : 2 * rx + w])
    return out.reshape(img.shape)


def kernel_walk_values(uniforms) -> np.ndarray:
    """The elementary functions' values that random kernels' walks need, many kernels at once.

    Per row of uniforms (:func:`random_motion_kernel`'s layout): the Box-Muller radii
    ``sqrt(-2 log u)`` of the steps' Gaussians, then the sines and then the cosines of their
    angles, of the shake turns' and of the start direction. Through :mod:`fixedmath` (the same
    bits on every CPU), whose cost on a kernel's few hundred values is its per-call numpy
    overhead: one call for a batch's kernels costs about what one kernel's does, and an
    elementwise function gives each value the same bits whatever lies beside it.

    Args:
        uniforms: ``(..., KERNEL_UNIFORMS)`` uniforms in (0, 1), a row per kernel.

    Returns:
        ``(..., KERNEL_WALK_VALUES)`` float64, a row per kernel.
    """
    u = np.asarray(uniforms, dtype=np.float64)
    n = KERNEL_WALK_STEPS
    steps = u[..., 5:].reshape(*u.shape[:-1], n - 1, 4)
    radius = np.sqrt(-2.0 * fixedmath.log(steps[..., 0]))
    angles = np.concatenate([
        2.0 * math.pi * steps[..., 1],
        math.pi + 2.0 * KERNEL_SHAKE_TURN_SPREAD_RAD * (steps[..., 3] - 0.5),
        2.0 * math.pi * u[..., :1],
    ], axis=-1)
    sines, cosines = fixedmath.sincos(angles)
    return np.concatenate([radius, sines, cosines], axis=-1)


def random_motion_kernel(uniforms, size: int, walk=None) -> np.ndarray:
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
        walk: this row of :func:`kernel_walk_values` (made for many kernels at once), or
            None: made here from ``uniforms``.

    Returns:
        ``size x size`` float64, non-negative, summing to 1, centroid at ``(size // 2,
        size // 2)`` (row, column), ``kernel[row, col]`` with rows along y.

    Raises:
        ValueError: for a wrong count of uniforms, values outside (0, 1), a bad size, or walk
            values not of shape ``(KERNEL_WALK_VALUES,)``.
    """
    u = as_uniforms(uniforms, KERNEL_UNIFORMS, "random_motion_kernel")
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
    sigma = KERNEL_JITTER_MAX * u[1]
    kappa = KERNEL_PULL_MAX * u[2]
    p_shake = KERNEL_SHAKE_PROBABILITY_MAX * u[3]
    extent = KERNEL_EXTENT_MIN + (1.0 - KERNEL_EXTENT_MIN) * u[4]
    steps = u[5:].reshape(n - 1, 4)

    # Gaussian pairs by Box-Muller, the shake turns and the start direction (theta_0)
    walk = kernel_walk_values(u) if walk is None else np.asarray(walk, dtype=np.float64)
    if walk.shape != (KERNEL_WALK_VALUES,):
        raise ValueError(f"random_motion_kernel needs ({KERNEL_WALK_VALUES},) walk values; got "
                         f"shape {walk.shape}")
    radius, gauss_sin, turn_sin, (start_sin,), gauss_cos, turn_cos, (start_cos,) = np.split(
        walk, np.cumsum([n - 1, n - 1, n - 1, 1, n - 1, n - 1]))
    shake = steps[:, 2] < p_shake

    # the walk on Python floats in the complex plane written as (x, y) pairs, each operation
    # one IEEE rounding (no complex type: its product may be fused into a * b + c elsewhere)
    gx, gy = (radius * gauss_cos).tolist(), (radius * gauss_sin).tolist()
    tx, ty, shake = turn_cos.tolist(), turn_sin.tolist(), shake.tolist()
    sigma, kappa = float(sigma), float(kappa)
    vx, vy = step_len * float(start_cos), step_len * float(start_sin)
    px = py = 0.0
    walk_x, walk_y = [px], [py]
    for j in range(n - 1):
        if shake[j]:
            vx, vy = vx * tx[j] - vy * ty[j], vx * ty[j] + vy * tx[j]
        else:
            speed = math.sqrt(vx * vx + vy * vy)
            cx = vx + speed * (sigma * gx[j] - kappa * px)
            cy = vy + speed * (sigma * gy[j] - kappa * py)
            mag = math.sqrt(cx * cx + cy * cy)
            if mag > 0.0:
                vx, vy = cx * (step_len / mag), cy * (step_len / mag)
        px, py = px + vx, py + vy
        walk_x.append(px)
        walk_y.append(py)
    path_x, path_y = np.array(walk_x), np.array(walk_y)

    # upper bound on the final scale, to choose the sampling density
    centre = (size - 1) / 2.0
    side = max(np.ptp(path_x), np.ptp(path_y))
    scale_bound = centre / (0.5 * side)
    per_step = max(1, math.ceil(scale_bound * step_len / KERNEL_SAMPLE_SPACING_PX))
    n_samples = (n - 1) * per_step
    t = (np.arange(n_samples) + 0.5) / per_step  # midpoints of equal slices, in walk steps
    knots = np.arange(n, dtype=np.float64)
    sx = np.interp(t, knots, path_x)
    sy = np.interp(t, knots, path_y)

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

