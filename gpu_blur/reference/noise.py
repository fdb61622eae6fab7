"""Sensor noise: heteroscedastic Poisson-Gaussian on the RAW mosaic, and Gaussian noise in sRGB.

The model is RSBlur's (Rim, Kim, Lee, Lee and Cho, "Realistic blur synthesis for learning image
deblurring", ECCV 2022, §4 and supplementary; code ``utils.py:add_Poisson_noise_random`` in the
PyTorch release and ``ISP.add_Poisson_noise_random`` in SRN-Deblur-RSBlur), applied to the
linear camera RAW mosaic after inverse white balance::

    x' = K * Poisson(x / K) + sigma_r * N(0, 1)       Var[x'] = K * x + sigma_r**2

with one ``(K, sigma_r)`` per image, each uniform within +-50 % of a per-data-set level
(:func:`draw_noise_levels`). Every draw comes from :mod:`gpu_blur.reference.rng` counters at
the pixel's global coordinates, so a tile gets exactly the draws the whole image would.
"""

from __future__ import annotations

import math

import numpy as np

from gpu_blur.reference.poisson_counts import poisson, require_finite
from gpu_blur.reference.rng import Stream, pixel_normals

__all__ = [
    "SRGB_GAUSSIAN_BASE_STD",
    "add_gaussian_srgb",
    "add_poisson_gaussian",
    "draw_noise_levels",
]

#: Base standard deviation of the Gaussian-only sRGB variant, in [0, 1] sRGB units
#: (SRN-Deblur-RSBlur ``models/model.py``, option ``gaussian``: sigma ~ U(0.5, 1.5) * this).
SRGB_GAUSSIAN_BASE_STD = 0.011211179037436594


def _check_origin(origin) -> tuple[int, int]:
    try:
        row, col = (int(v) for v in origin)
    except (TypeError, ValueError):
        raise ValueError(f"origin must be (row, col) integers; got {origin!r}") from None
    if row < 0 or col < 0 or any(v != int(v) for v in origin):
        raise ValueError(f"origin must be non-negative integer (row, col); got {origin!r}")
    return row, col


def _global_coordinates(shape: tuple[int, int], origin) -> tuple[np.ndarray, np.ndarray]:
    """Global row and column index arrays, shapes ``(H, 1)`` and ``(1, W)``."""
    row, col = _check_origin(origin)
    y = np.arange(row, row + shape[0], dtype=np.int64)[:, None]
    x = np.arange(col, col + shape[1], dtype=np.int64)[None, :]
    return y, x


def _check_level(value, name: str, *, positive: bool, meaning: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number ({meaning}); got {value!r}") from None
    ok = math.isfinite(value) and (value > 0 if positive else value >= 0)
    if not ok:
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be finite and {bound} ({meaning}); got {value!r}")
    return value


def add_poisson_gaussian(
    raw: np.ndarray,
    shot_noise_k: float,
    read_noise_std: float,
    *,
    seed: int,
    sample_index: int,
    origin: tuple[int, int] = (0, 0),
    poisson_normal_above: float | None = None,
) -> np.ndarray:
    """Add heteroscedastic Poisson-Gaussian noise to a RAW mosaic.

    Per sample, with ``n = poisson(max(x, 0) / K)`` (stream SHOT_NOISE; with
    ``poisson_normal_above`` set, rates above it use the normal approximation, see
    :func:`~gpu_blur.reference.poisson_counts.poisson`) and ``z`` the first normal of
    :func:`~gpu_blur.reference.rng.pixel_normals` (stream READ_NOISE)::

        x' = K * n + sigma_r * z

    so ``E[x'] = x`` and ``Var[x'] = K * x + sigma_r**2`` for ``x >= 0``. ``sigma_r`` is a
    standard deviation, not a variance (RSBlur authors' clarification, Aug 2024 commits). The
    result is not clipped: negative values from the Gaussian term are kept, as in RSBlur.

    Args:
        raw: float array ``(H, W)``, the linear camera RAW mosaic in [0, 1] after inverse white
            balance (one value per photosite).
        shot_noise_k: K > 0, the shot-noise gain in units of the [0, 1] signal (one photon
            count is worth K of signal); RSBlur beta1 (RealBlur 8.8915e-5, RSBlur 1.0e-4).
        read_noise_std: sigma_r >= 0, the read-noise standard deviation in [0, 1] signal units;
            RSBlur beta2 (RealBlur 2.9430e-5, RSBlur 9.1504e-4).
        seed: 64-bit seed of the data set.
        sample_index: sample number in ``[0, 2**32)``.
        origin: ``(row, col)`` of ``raw[0, 0]`` in the full image, so a tile draws what the
            whole image draws at the same photosites.
        poisson_normal_above: ``None`` (scene ``noise.poisson = "exact"``) or the Poisson rate,
            in counts, above which counts are a rounded normal (``noise.poisson = "normal"``,
            ``noise.normal_above``).

    Returns:
        float64 array ``(H, W)``.

    Raises:
        ValueError: on a bad shape, non-finite input, K / sigma_r out of range, or a bad
            ``poisson_normal_above``.
    """
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2:
        raise ValueError(f"raw must be an (H, W) mosaic; got shape {raw.shape}")
    k = _check_level(
        shot_noise_k,
        "shot_noise_k",
        positive=True,
        meaning="K is the shot-noise gain in units of the [0, 1] signal",
    )
    sigma_r = _check_level(
        read_noise_std,
        "read_noise_std",
        positive=False,
        meaning="the read-noise standard deviation in units of the [0, 1] signal",
    )
    require_finite(raw, "raw", hint="; the Poisson rate x / K must be finite")
    y, x = _global_coordinates(raw.shape, origin)
    rate = np.maximum(raw, 0.0) / k
    counts = poisson(rate, seed, sample_index, y, x, stream=Stream.SHOT_NOISE,
                     normal_above=poisson_normal_above)
    z = pixel_normals(seed, sample_index, Stream.READ_NOISE, y, x, count=1)[..., 0]
    return k * counts + sigma_r * z


def add_gaussian_srgb(
    image: np.ndarray,
    std: float,
    *,
    seed: int,
    sample_index: int,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Add i.i.d. Gaussian noise to an sRGB image: ``image + std * N(0, 1)`` per channel.

    The Gaussian-only variant of SRN-Deblur-RSBlur (``models/model.py``, option ``gaussian``),
    where the pipeline draws ``std ~ U(0.5, 1.5) * 0.011211179037436594``
    (:data:`SRGB_GAUSSIAN_BASE_STD`); this function takes the drawn value. Channels R, G, B use
    normals 0, 1, 2 of :func:`~gpu_blur.reference.rng.pixel_normals` on stream SRGB_NOISE. No
    clipping (the pipeline clips afterwards).

    Args:
        image: float array ``(H, W, 3)``, sRGB in [0, 1].
        std: standard deviation >= 0, in [0, 1] sRGB units.
        seed: 64-bit seed of the data set.
        sample_index: sample number in ``[0, 2**32)``.
        origin: ``(row, col)`` of ``image[0, 0]`` in the full image.

    Returns:
        float64 array ``(H, W, 3)``.
    """
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"image must be (H, W, 3) sRGB; got shape {image.shape}")
    std = _check_level(std, "std", positive=False, meaning="noise standard deviation in sRGB")
    y, x = _global_coordinates(image.shape[:2], origin)
    z = pixel_normals(seed, sample_index, Stream.SRGB_NOISE, y, x, count=3)
    return image + std * z


def draw_noise_levels(
    u_shot: float,
    u_read: float,
    shot_noise_k: float,
    read_noise_std: float,
    spread: float = 0.5,
) -> tuple[float, float]:
    """Per-image noise levels from two uniforms, RSBlur's ``U(0.5 beta, 1.5 beta)`` draw.

    ``K = shot_noise_k * (1 - spread + 2 * spread * u_shot)`` and likewise ``sigma_r`` from
    ``u_read``: uniform on ``[(1 - spread) beta, (1 + spread) beta]`` when ``u`` is uniform on
    [0, 1] (PyTorch ``add_Poisson_noise_random``, TF ``ISP.add_Poisson_noise_random``).

    Args:
        u_shot: uniform in [0, 1] for K (e.g. from ``image_uniforms(..., Stream.PARAMS, ...)``).
        u_read: uniform in [0, 1] for sigma_r.
        shot_noise_k: beta1 > 0, the central shot-noise gain in [0, 1] signal units.
        read_noise_std: beta2 >= 0, the central read-noise standard deviation.
        spread: half-width of the range as a fraction of beta, in [0, 1].

    Returns:
        ``(K, sigma_r)`` as floats.
    """
    for name, u in (("u_shot", u_shot), ("u_read", u_read)):
        if not 0.0 <= float(u) <= 1.0:
            raise ValueError(f"{name} must be a uniform in [0, 1]; got {u!r}")
    if not 0.0 <= float(spread) <= 1.0:
        raise ValueError(f"spread must lie in [0, 1] so K stays >= 0; got {spread!r}")
    beta1 = _check_level(
        shot_noise_k,
        "shot_noise_k",
        positive=True,
        meaning="K is the shot-noise gain in units of the [0, 1] signal",
    )
    beta2 = _check_level(
        read_noise_std,
        "read_noise_std",
        positive=False,
        meaning="the read-noise standard deviation in units of the [0, 1] signal",
    )
    spread = float(spread)
    k = beta1 * (1.0 - spread + 2.0 * spread * float(u_shot))
    sigma_r = beta2 * (1.0 - spread + 2.0 * spread * float(u_read))
    if not k > 0.0:
        raise ValueError(
            f"K = {k!r} from u_shot = {u_shot!r} and spread = {spread!r}; K must be > 0 "
            "(spread 1 needs u_shot > 0, which uniform_from_bits guarantees)"
        )
    return k, sigma_r
