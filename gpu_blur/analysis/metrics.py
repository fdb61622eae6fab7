"""Measures of blur-synthesis quality: PSNR, SSIM, residual KL divergence, noise level.

Supplementary material of RSBlur (Rim et al., ECCV 2022), Sec. 13 and Table 6: a synthesized
blurred image B_syn is compared with the real blurred image B_real of the same scene by PSNR,
SSIM and the KL divergence between the residual distributions (B_real - B_interp) and
(B_syn - B_interp), where B_interp (the average of frame-interpolated sharp frames) stands in
for the noise-free blurred image. Table 1 reports the noise level of each dataset by the
single-image estimator of Chen, Zhu and Heng (ICCV 2015), :func:`noise_level` here.

Images are numpy arrays, H x W (one channel) or H x W x C (channels last, e.g. RGB), with
values in ``[0, data_range]`` (``data_range=1.0`` for gpu_blur's float images, 255 for 8-bit
codes). Everything is computed in float64.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

__all__ = [
    "SSIM_K1",
    "SSIM_K2",
    "SSIM_SIGMA",
    "SSIM_TRUNCATE",
    "histogram_kl",
    "noise_level",
    "psnr",
    "residual_kl",
    "ssim",
    "ssim_window",
]

#: SSIM constants of Wang, Bovik, Sheikh, Simoncelli, "Image Quality Assessment: From Error
#: Visibility to Structural Similarity", IEEE TIP 13(4), 2004, Sec. III-C: C1 = (K1 L)^2,
#: C2 = (K2 L)^2 with L the data range, and an 11 x 11 circular-symmetric Gaussian window of
#: standard deviation 1.5 samples.
SSIM_K1 = 0.01
SSIM_K2 = 0.03
SSIM_SIGMA = 1.5
#: The Gaussian window reaches ``int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5) = 5`` samples from its
#: centre (11 taps), as scikit-image's ``structural_similarity`` truncates it.
SSIM_TRUNCATE = 3.5


def _as_images(a, b, data_range: float, names: tuple[str, str]) -> tuple[np.ndarray, np.ndarray]:
    """Two images of one shape as float64, checked to be finite and within [0, data_range]."""
    if not (isinstance(data_range, numbers.Real) and math.isfinite(data_range)
            and data_range > 0):
        raise ValueError(f"data_range={data_range!r}: must be a positive number (1.0 for float "
                         "images in [0, 1], 255 for 8-bit codes)")
    out = []
    for image, name in zip((a, b), names, strict=True):
        x = np.asarray(image)
        if x.ndim not in (2, 3) or x.size == 0:
            raise ValueError(f"{name}: expected an H x W or H x W x C image, got shape "
                             f"{x.shape}")
        if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
            raise ValueError(f"{name}: unsupported dtype {x.dtype}; pass numbers")
        x = x.astype(np.float64)
        if not np.isfinite(x).all():
            raise ValueError(f"{name}: {np.count_nonzero(~np.isfinite(x))} NaN or infinite "
                             "value(s); the metrics need finite images")
        low, high = float(x.min()), float(x.max())
        if low < 0 or high > data_range:
            raise ValueError(
                f"{name}: values span [{low:.6g}, {high:.6g}], outside [0, data_range = "
                f"{data_range:g}]; pass data_range=255 for 8-bit codes (65535 for 16-bit), or "
                "clip small overshoots with np.clip(x, 0, data_range)")
        out.append(x)
    if out[0].shape != out[1].shape:
        raise ValueError(f"{names[0]} has shape {out[0].shape} but {names[1]} has shape "
                         f"{out[1].shape}; compare images of the same size (crop or resize one)")
    return out[0], out[1]


def _as_mask(mask, shape: tuple[int, ...]) -> np.ndarray | None:
    """An H x W boolean mask for images of ``shape``, or None."""
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != shape[:2]:
        raise ValueError(f"mask: shape {mask.shape} does not match the images' H x W "
                         f"{shape[:2]}")
    mask = mask.astype(bool)
    if not mask.any():
        raise ValueError("mask: selects no pixel")
    return mask


def psnr(a, b, data_range: float = 1.0, mask=None) -> float:
    """Peak signal-to-noise ratio ``10 log10(data_range^2 / MSE)`` in dB.

    The mean squared error runs over every pixel and channel (over the pixels of ``mask``
    only, when given), as scikit-image's ``peak_signal_noise_ratio`` does without a mask.

    Args:
        a: reference image, H x W or H x W x C, values in [0, data_range].
        b: test image of the same shape.
        data_range: the largest possible value (1.0 for [0, 1] floats, 255 for 8-bit codes).
        mask: optional H x W booleans: the pixels that count (e.g. those an alignment warp
            kept inside the image).

    Returns:
        PSNR in dB; ``inf`` for identical images.
    """
    a, b = _as_images(a, b, data_range, ("a", "b"))
    mask = _as_mask(mask, a.shape)
    squared = (a - b) ** 2
    mse = float(np.mean(squared if mask is None else squared[mask]))
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(data_range * data_range / mse)


def ssim_window(sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE) -> np.ndarray:
    """The 1-D Gaussian taps of the SSIM window (its 2-D window is their outer product).

    Returns:
        ``2 r + 1`` float64 weights summing to 1, ``r = int(truncate * sigma + 0.5)``
        (11 taps for the defaults).
    """
    radius = int(truncate * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _filter_valid(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable weighted mean of a 2-D array, only where the window lies inside it.

    Returns:
        ``(H - n + 1) x (W - n + 1)`` array for ``n`` taps: output ``[i, j]`` is the window
        centred on input ``[i + r, j + r]``, so no border rule is needed.
    """
    n = taps.size
    rows = sum(w * x[k:x.shape[0] - n + 1 + k] for k, w in enumerate(taps))
    return sum(w * rows[:, k:x.shape[1] - n + 1 + k] for k, w in enumerate(taps))


def _ssim_map(x: np.ndarray, y: np.ndarray, data_range: float, taps: np.ndarray) -> np.ndarray:
    """SSIM at every pixel whose whole window lies in the 2-D images (Wang et al. Eq. 13)."""
    mu_x, mu_y = _filter_valid(x, taps), _filter_valid(y, taps)
    # Gaussian-weighted (co)variances, normalized by the weights' sum 1 (Wang et al. Eq. 14-16)
    var_x = _filter_valid(x * x, taps) - mu_x * mu_x
    var_y = _filter_valid(y * y, taps) - mu_y * mu_y
    cov_xy = _filter_valid(x * y, taps) - mu_x * mu_y
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    return ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)
            / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)))


def ssim(a, b, data_range: float = 1.0, mask=None) -> float:
    """Mean structural similarity (Wang et al. 2004) with an 11 x 11 Gaussian window.

    Convention (that of scikit-image's ``structural_similarity(a, b, data_range=...,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, channel_axis=-1)``):

    * window: Gaussian, sigma 1.5, 11 x 11 (:func:`ssim_window`); means, variances and the
      covariance are weighted by it, normalized by the weights' sum (not N - 1);
    * K1 = 0.01, K2 = 0.03, C1 = (K1 data_range)^2, C2 = (K2 data_range)^2;
    * the SSIM map is kept where the whole window lies inside the image (5 pixels are dropped
      along each edge), and averaged;
    * an H x W x C image gets one mean per channel (channels last), and the result is the mean
      of those: colour channels are not mixed.

    Args:
        a: reference image, H x W or H x W x C, values in [0, data_range]; H, W >= 11.
        b: test image of the same shape.
        data_range: the largest possible value (1.0 for [0, 1] floats, 255 for 8-bit codes).
        mask: optional H x W booleans: average the map over these pixels only (of those at
            least 5 pixels from every edge).

    Returns:
        Mean SSIM in [-1, 1]; 1 for identical images.
    """
    a, b = _as_images(a, b, data_range, ("a", "b"))
    mask = _as_mask(mask, a.shape)
    taps = ssim_window()
    r = taps.size // 2
    if min(a.shape[:2]) < taps.size:
        raise ValueError(f"ssim: images of {a.shape[0]} x {a.shape[1]} are smaller than the "
                         f"{taps.size} x {taps.size} Gaussian window; use images of at least "
                         f"{taps.size} x {taps.size}")
    inner = None if mask is None else mask[r:a.shape[0] - r, r:a.shape[1] - r]
    if inner is not None and not inner.any():
        raise ValueError(f"mask: selects no pixel at least {r} pixels from every edge, where "
                         "SSIM is defined")
    if a.ndim == 2:
        a, b = a[:, :, None], b[:, :, None]
    means = []
    for c in range(a.shape[2]):
        s = _ssim_map(a[:, :, c], b[:, :, c], data_range, taps)
        means.append(float(np.mean(s if inner is None else s[inner])))
    return float(np.mean(means))


def residual_kl(real, synth, interp, bins: int = 255, data_range: float = 1.0,
                smoothing: float = 1.0, mask=None) -> float:
    """KL divergence D(P_real || P_syn) of the residuals real - interp and synth - interp.

    RSBlur supplementary Sec. 13: the pixel-wise marginal distributions of (B_real - B_interp)
    and (B_syn - B_interp), as in the noise-synthesis works it cites. Every value of every
    pixel and channel (of ``mask``) is one sample; the histograms and the divergence are those
    of :func:`histogram_kl`, which states the binning, the smoothing and the direction.
    Identical residuals give exactly 0.

    Args:
        real: real blurred image B_real, H x W or H x W x C, in [0, data_range].
        synth: synthesized blurred image B_syn, same shape.
        interp: noise-free reference B_interp (e.g. the average of interpolated sharp
            frames), same shape.
        bins: bins per ``data_range`` (the bin width is ``data_range / bins``).
        data_range: the largest possible value (1.0 for [0, 1] floats, 255 for 8-bit codes).
        smoothing: pseudo-count added to every bin, >= 0.
        mask: optional H x W booleans: the pixels that count.

    Returns:
        The KL divergence in nats, >= 0.
    """
    real, interp = _as_images(real, interp, data_range, ("real", "interp"))
    synth, _ = _as_images(synth, interp, data_range, ("synth", "interp"))
    mask = _as_mask(mask, real.shape)
    residuals = [image - interp for image in (real, synth)]
    if mask is not None:
        residuals = [r[mask] for r in residuals]
    return histogram_kl(*residuals, bins=bins, data_range=data_range, smoothing=smoothing)


def histogram_kl(real_residuals, synth_residuals, bins: int = 255, data_range: float = 1.0,
                 smoothing: float = 1.0) -> float:
    """KL divergence D(P || Q) between the histograms of two sets of residual values.

    * binning: one common grid of bins of width ``data_range / bins`` centred on multiples of
      that width, ``2 bins + 1`` of them covering every residual in [-data_range,
      data_range]. With the default ``bins=255`` each bin holds exactly one 8-bit code
      difference and its edges lie halfway between codes, so rounding cannot move a value
      into the next bin;
    * smoothing: ``smoothing`` (default 1, add-one / Laplace) is added to every bin's count of
      both histograms before normalizing, ``p_i = (n_i + s) / (N + s B)``, so an empty bin
      gives no infinite term, as the histogram-KL evaluation code released with Abdelhamed,
      Brubaker, Brown, "Noise Flow", ICCV 2019, does (one per bin). ``smoothing=0`` gives the
      raw histograms (``inf`` when the synthesized residuals leave a bin empty that the real
      ones fill);
    * direction: forward and not symmetric, D(P || Q) = sum_i p_i log(p_i / q_i) with p the
      real and q the synthesized residuals, in nats, as Noise Flow (and RSBlur's Table 6,
      real first) state it.

    The value depends on the bin width and the smoothing (and, through the smoothing, a
    little on the sample count), so compare numbers computed with the same settings.

    Args:
        real_residuals: real residual values (any shape, flattened), in [-data_range,
            data_range].
        synth_residuals: synthesized residual values, same range; the counts may differ.
        bins: bins per ``data_range``, a positive integer.
        data_range: the largest possible image value.
        smoothing: pseudo-count added to every bin, >= 0.

    Returns:
        The KL divergence in nats, >= 0.
    """
    if not (isinstance(bins, (int, np.integer)) and bins >= 1):
        raise ValueError(f"bins={bins!r}: must be a positive integer (bins per data_range; 255 "
                         "gives one bin per 8-bit code)")
    if not (math.isfinite(smoothing) and smoothing >= 0):
        raise ValueError(f"smoothing={smoothing!r}: must be a finite pseudo-count >= 0")
    width = data_range / bins
    densities = []
    for values, name in ((real_residuals, "real residuals"),
                         (synth_residuals, "synthesized residuals")):
        values = np.asarray(values, dtype=np.float64).ravel()
        if values.size == 0:
            raise ValueError(f"{name}: no values")
        if not np.isfinite(values).all() or np.abs(values).max() > data_range:
            raise ValueError(f"{name}: values must be finite and within [-data_range, "
                             f"data_range] = [-{data_range:g}, {data_range:g}]; residuals of "
                             "images outside [0, data_range]?")
        index = np.rint(values / width).astype(np.int64) + bins
        counts = np.bincount(index, minlength=2 * bins + 1).astype(np.float64)
        densities.append((counts + smoothing) / (values.size + smoothing * counts.size))
    p, q = densities
    used = p > 0
    if np.any(q[used] == 0):
        return math.inf
    return float(max(np.sum(p[used] * np.log(p[used] / q[used])), 0.0))


def noise_level(image, patch_size: int = 8, stride: int = 3) -> float:
    """Standard deviation of additive white Gaussian noise, estimated from one image.

    Chen, Zhu, Heng, "An Efficient Statistical Method for Image Noise Level Estimation",
    ICCV 2015, as RSBlur's supplementary Table 1 uses it. Patches of a clean image lie near a
    low-dimensional subspace, so the smallest eigenvalues of the patch covariance belong to
    the noise alone; their number is chosen by the paper's mean-equals-median rule:

    1. cut the image into s overlapping ``patch_size x patch_size`` patches (all channels
       together, r = patch_size^2 C values each), every ``stride`` pixels along both axes,
       the last row and column of patches included;
    2. Sigma = (1/s) sum_t (x_t - mu)(x_t - mu)^T with mu the mean patch, and its eigenvalues
       lambda_1 <= ... <= lambda_r;
    3. for m = r, r - 1, ..., 1: tau = (1/m) sum_{i <= m} lambda_i; stop at the first m where
       as many of lambda_1..lambda_m lie above tau as below it (tau is their median);
    4. sigma = sqrt(tau).

    ``stride=3`` is that of the authors' released MATLAB code (``NoiseEstimation.m``, MIT
    licence, in its ``image2cols``), which takes the patch size as an argument; 8 is the
    usual choice of its ports. The estimate assumes signal-independent noise; for camera
    noise it is an average level. With few patches per value the noise eigenvalues spread
    (their mean exceeds their median) and the estimate runs low: pure noise measured up to
    1.7 % low at 400 x 400 x 3, 3.6 % at 256 x 256, 14 % at 128 x 128.

    Args:
        image: H x W or H x W x C array, any range (the result is in the same units; Table
            1's levels, 0.34 to 0.77, read as 8-bit codes, though the paper does not say).
        patch_size: side of the square patches, >= 2.
        stride: step between patches, >= 1.

    Returns:
        The estimated noise standard deviation, >= 0.
    """
    x = np.asarray(image)
    if x.ndim == 2:
        x = x[:, :, None]
    if x.ndim != 3 or x.size == 0:
        raise ValueError(f"noise_level: expected an H x W or H x W x C image, got shape "
                         f"{np.shape(image)}")
    x = x.astype(np.float64)
    if not np.isfinite(x).all():
        raise ValueError(f"noise_level: {np.count_nonzero(~np.isfinite(x))} NaN or infinite "
                         "value(s); the estimate needs a finite image")
    if patch_size < 2 or stride < 1:
        raise ValueError(f"noise_level: patch_size={patch_size} must be >= 2 and stride="
                         f"{stride} >= 1")
    height, width, channels = x.shape
    starts = []
    for n in (height, width):
        if n < patch_size:
            raise ValueError(f"noise_level: a {height} x {width} image is smaller than one "
                             f"{patch_size} x {patch_size} patch; pass a smaller patch_size")
        s = list(range(0, n - patch_size + 1, stride))
        if s[-1] != n - patch_size:
            s.append(n - patch_size)
        starts.append(np.array(s))
    rows, cols = starts
    dim = patch_size * patch_size * channels
    count = rows.size * cols.size
    if count <= dim:
        raise ValueError(f"noise_level: a {height} x {width} image gives {count} patches of "
                         f"{dim} values, too few for their covariance; use a larger image or "
                         "a smaller patch_size or stride")
    # Shifting the image leaves Sigma unchanged and keeps sum x x^T / s - mu mu^T accurate.
    x -= x.mean()
    windows = sliding_window_view(x, (patch_size, patch_size), axis=(0, 1))
    gram = np.zeros((dim, dim))
    total = np.zeros(dim)
    chunk = max(1, (1 << 22) // (cols.size * dim))  # about 32 MB of patches at a time
    for i in range(0, rows.size, chunk):
        patches = windows[np.ix_(rows[i:i + chunk], cols)].reshape(-1, dim)
        gram += patches.T @ patches
        total += patches.sum(axis=0)
    mean = total / count
    eigenvalues = np.linalg.eigvalsh(gram / count - np.outer(mean, mean))  # ascending
    for m in range(dim, 0, -1):
        smallest = eigenvalues[:m]
        tau = float(smallest.mean())
        if np.count_nonzero(smallest > tau) == np.count_nonzero(smallest < tau):
            break
    return math.sqrt(max(tau, 0.0))
