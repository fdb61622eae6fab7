"""The RSBlur authors' RealBlur-J training-time chain as plain PyTorch ops: the port a user
would write, the other half of ``bench/realblur_j_side_by_side.py``.

Written from the stage list of the authors' PyTorch dataset (RSBLUR_PIPELINE.md Sec. 3,
steps 4 to 19; the crop and augmentation of steps 1 to 3 are left to the caller) and the
component specifications of its Sec. 5. Rim et al., "Realistic Blur Synthesis for Learning
Image Deblurring", ECCV 2022; code rimchang/RSBlur @ ae33a6c,
``Uformer-RSBlur/dataset/dataset_RealisticDeblur.py`` and ``Uformer-RSBlur/ISP/``.

Images are B x 3 x H x W float32 tensors (channels first, RGB, sRGB in [0, 1]) on any torch
device; H and W must be even (the Bayer 2 x 2 cell). Everything runs batched on the inputs'
device in float32, as the authors' code does; only the per-sample parameters differ by sample.
The noise comes from torch's own generators, so it cannot equal gpu_blur's counter-based
stream value for value; with ``noise=False`` the chain is deterministic and agrees with
gpu_blur's numpy float64 reference (``tests/synthesis/test_torch_chain.py``).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

# Constants from the authors' .mat files (rsblur_constants.json, converted with scipy at
# float64). Row-vector matrices: out_row = in_row @ M; column-vector: out = M @ in.
M_LIN2XYZ = (  # row vector; M_lin2xyz.mat (textbook sRGB/D65 -> XYZ, transposed)
    (0.41245643908969226, 0.21267285140562256, 0.019333895582329303),
    (0.3575760776439089, 0.7151521552878178, 0.11919202588130294),
    (0.1804374832663989, 0.07217499330655956, 0.9503040785363677),
)
M_XYZ2LIN = (  # row vector; M_xyz2lin.mat
    (3.2404541621141045, -0.9692660305051868, 0.055643430959114726),
    (-1.537138512797716, 1.8760108454466942, -0.20402591351675384),
    (-0.4985314095560159, 0.04155601753034981, 1.0572251882231791),
)
A7R3_XYZ2CAM = (  # column vector; a7r3_xyz2cam.mat (LibRaw ILCE-7RM3, rows rescaled)
    (1.6954175654007513, -0.4716018438697571, -0.12843298725852076),
    (-0.4883823389175844, 1.213030589789571, 0.23067161253953877),
    (-0.126723194569989, 0.21350242146585263, 0.8329529616901491),
)
A7R3_CAM2XYZ = (  # column vector; a7r3_cam2xyz.mat (the inverse of A7R3_XYZ2CAM)
    (0.6650923260252906, 0.25284924515444734, 0.03252842882026215),
    (0.2612682992175355, 0.9659493702356229, -0.2272176694531588),
    (0.034217069886958246, -0.20912425248442337, 1.263737182597465),
)
#: A7R3 response, linear -> rendered, ascending powers (a7r3_polynomial_alpha.mat).
A7R3_CRF = (-0.009522800674779798, 8.698515984522277, -45.15782051645196, 150.71180861706543,
            -308.1978292223731, 368.308116880222, -235.16339845543246, 61.83222409587268)
#: RealBlur noise levels (dataset_RealisticDeblur.py): K ~ U(0.5, 1.5) * beta1 and the read
#: noise standard deviation ~ U(0.5, 1.5) * beta2, one draw per image.
BETA1_SHOT_K, BETA2_READ_STD = 8.8915e-5, 2.9430e-5
#: Per-image ranges of the other draws (dataset_RealisticDeblur.py __getitem__).
ALPHA_RANGE, RED_GAIN_RANGE, BLUE_GAIN_RANGE = (0.25, 1.75), (1.9, 2.4), (1.5, 1.9)
PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
BORDER = 4  # pixels cropped from every side at the end

# Malvar, He and Cutler 2004, the four 5 x 5 kernels (all / 8, each summing to 1), as the
# paper's figure and the authors' Demosaicing_malvar2004_pytorch.py hold them.
_MALVAR = (
    (  # G at R and B sites
        (0, 0, -1, 0, 0),
        (0, 0, 2, 0, 0),
        (-1, 2, 4, 2, -1),
        (0, 0, 2, 0, 0),
        (0, 0, -1, 0, 0)),
    (  # R at G in an R row / B column; B at G in a B row / R column
        (0, 0, 0.5, 0, 0),
        (0, -1, 0, -1, 0),
        (-1, 4, 5, 4, -1),
        (0, -1, 0, -1, 0),
        (0, 0, 0.5, 0, 0)),
    (  # its transpose: R at G in a B row / R column; B at G in an R row / B column
        (0, 0, -1, 0, 0),
        (0, -1, 4, -1, 0),
        (0.5, 0, 5, 0, 0.5),
        (0, -1, 4, -1, 0),
        (0, 0, -1, 0, 0)),
    (  # R at B sites; B at R sites
        (0, 0, -1.5, 0, 0),
        (0, 2, 0, 2, 0),
        (-1.5, 0, 6, 0, -1.5),
        (0, 2, 0, 2, 0),
        (0, 0, -1.5, 0, 0)),
)


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """The sRGB EOTF (MATLAB ``rgb2lin``), odd in x, no clip."""
    a = x.abs()
    y = torch.where(a < 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)
    return torch.copysign(y, x)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """The sRGB OETF (MATLAB ``lin2rgb``), odd in x, no clip."""
    a = x.abs()
    y = torch.where(a < 0.0031308, 12.92 * a, 1.055 * a ** (1 / 2.4) - 0.055)
    return torch.copysign(y, x)


def a7r3_retone(srgb: torch.Tensor) -> torch.Tensor:
    """Decode sRGB, then render with the A7R3 polynomial (Horner), clipped to [0, 1]."""
    lin = srgb_to_linear(srgb)
    y = torch.full_like(lin, A7R3_CRF[-1])
    for c in A7R3_CRF[-2::-1]:
        y = y * lin + c
    return y.clamp(0.0, 1.0)


def _row_vector(x: torch.Tensor, m) -> torch.Tensor:
    """out[c] = sum_k x[k] * m[k][c] over the channel axis (B x 3 x H x W)."""
    return torch.einsum("bkhw,kc->bchw", x, torch.tensor(m, dtype=x.dtype, device=x.device))


def _column_vector(x: torch.Tensor, m) -> torch.Tensor:
    """out[c] = sum_k m[c][k] * x[k] (the authors' ``apply_cmatrix``)."""
    return torch.einsum("ck,bkhw->bchw", torch.tensor(m, dtype=x.dtype, device=x.device), x)


def _per_sample(value, batch: int, device, name: str) -> torch.Tensor:
    """A number or B numbers as a B x 1 x 1 x 1 float32 tensor on ``device``."""
    t = torch.as_tensor(value, dtype=torch.float32, device=device).reshape(-1)
    if t.numel() == 1:
        t = t.expand(batch)
    if t.numel() != batch:
        raise ValueError(f"{name} holds {t.numel()} values for a batch of {batch}; give one "
                         f"number or one per sample")
    return t.reshape(batch, 1, 1, 1)


def _pattern_channels(pattern, batch: int, device) -> torch.Tensor:
    """B x 4 channel index (0 R, 1 G, 2 B) of the 2 x 2 cell's offsets (0,0),(0,1),(1,0),(1,1)."""
    names = [pattern] * batch if isinstance(pattern, str) else list(pattern)
    if len(names) != batch:
        raise ValueError(f"pattern holds {len(names)} names for a batch of {batch}; give one "
                         f"name or one per sample")
    rows = []
    for name in names:
        if str(name).upper() not in PATTERNS:
            raise ValueError(f"pattern {name!r} is not a Bayer pattern; allowed: "
                             f"{', '.join(PATTERNS)}")
        rows.append(["RGB".index(letter) for letter in str(name).upper()])
    return torch.tensor(rows, dtype=torch.long, device=device)


def mosaic(cam: torch.Tensor, channels: torch.Tensor) -> torch.Tensor:
    """B x 3 x H x W camera RGB -> B x 4 x H/2 x W/2 packed Bayer planes.

    Plane p holds offset (p // 2, p % 2) of each 2 x 2 cell, from the channel the sample's
    pattern puts there (the authors' ``mosaic_bayer``).
    """
    cells = torch.stack([cam[:, :, i::2, j::2] for i in (0, 1) for j in (0, 1)], dim=1)
    b, _, _, h, w = cells.shape
    index = channels[:, :, None, None, None].expand(b, 4, 1, h, w)
    return cells.gather(2, index).squeeze(2)


def demosaic_malvar2004(cfa: torch.Tensor, channels: torch.Tensor) -> torch.Tensor:
    """Malvar-He-Cutler 2004 on a B x 1 x H x W mosaic: zero padding (conv2d padding 2), no
    clip, as the authors' ``Demosaic.forward``. Returns B x 3 x H x W."""
    weight = torch.tensor(_MALVAR, dtype=cfa.dtype, device=cfa.device).unsqueeze(1) / 8
    g_at_rb, rb_row, rb_col, rb_diag = F.conv2d(cfa, weight, padding=2).unbind(1)
    b, _, h, w = cfa.shape
    # each sample's channel per pixel, from its 2 x 2 cell
    cell = channels.reshape(b, 2, 2)
    site = cell.repeat(1, h // 2, w // 2)
    is_r, is_b = site == 0, site == 2
    # "R row": a row holding R samples; "R column" likewise (and B)
    r_row = (cell == 0).any(2).repeat(1, h // 2)[:, :, None]
    r_col = (cell == 0).any(1).repeat(1, w // 2)[:, None, :]
    b_row = (cell == 2).any(2).repeat(1, h // 2)[:, :, None]
    b_col = (cell == 2).any(1).repeat(1, w // 2)[:, None, :]
    raw = cfa[:, 0]
    zero = torch.zeros_like(raw)
    green = torch.where(is_r | is_b, g_at_rb, raw)
    red = torch.where(is_r, raw, zero)
    red = torch.where(r_row & b_col, rb_row, red)
    red = torch.where(b_row & r_col, rb_col, red)
    red = torch.where(b_row & b_col, rb_diag, red)
    blue = torch.where(is_b, raw, zero)
    blue = torch.where(b_row & r_col, rb_row, blue)
    blue = torch.where(r_row & b_col, rb_col, blue)
    blue = torch.where(r_row & r_col, rb_diag, blue)
    return torch.stack([red, green, blue], dim=1)


def _noise_level(value, beta: float, batch: int, generator, device, name: str) -> torch.Tensor:
    """The given level(s), or one draw per sample from U(0.5, 1.5) * beta."""
    if value is not None:
        return _per_sample(value, batch, device, name)
    u = torch.rand(batch, generator=generator, device=device)
    return (beta * (0.5 + u)).reshape(batch, 1, 1, 1)


def random_parameters(batch: int, generator: torch.Generator | None = None) -> dict:
    """One draw per sample from the authors' ranges (on the host, as their loader draws):
    ``alpha``, ``red_gain``, ``blue_gain`` (B float32 tensors) and ``pattern`` (B names)."""
    u = torch.rand(4, batch, generator=generator)

    def span(row, lo_hi):
        return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * u[row]

    return {"alpha": span(0, ALPHA_RANGE), "red_gain": span(1, RED_GAIN_RANGE),
            "blue_gain": span(2, BLUE_GAIN_RANGE),
            "pattern": [PATTERNS[min(int(v * 4), 3)] for v in u[3].tolist()]}


def realblur_j_chain(blurred: torch.Tensor, mask: torch.Tensor, sharp: torch.Tensor, *,
                     alpha, red_gain, blue_gain, pattern: str | Sequence[str],
                     shot_noise_k=None, read_noise_std=None,
                     generator: torch.Generator | None = None,
                     noise: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The authors' RealBlur-J chain, steps 4 to 19, on a batch.

    Args:
        blurred: B x 3 x H x W float32 sRGB blurred images in [0, 1], H and W even.
        mask: B x 3 x H x W float32 saturation masks in [0, 1].
        sharp: B x 3 x H x W float32 sRGB ground truth in [0, 1].
        alpha: saturation boost, one number or B (the authors: U(0.25, 1.75)).
        red_gain: white-balance red gain, one or B (U(1.9, 2.4)).
        blue_gain: white-balance blue gain, one or B (U(1.5, 1.9)).
        pattern: Bayer pattern name (RGGB, BGGR, GRBG, GBRG), one or B.
        shot_noise_k: Poisson gain K, one or B; None draws U(0.5, 1.5) * 8.8915e-5.
        read_noise_std: read-noise standard deviation, one or B; None draws U(0.5, 1.5) *
            2.9430e-5.
        generator: torch generator on the inputs' device for the noise and its levels.
        noise: False skips the Poisson-Gaussian noise (the chain is then deterministic).

    Returns:
        (blurred, sharp), each B x 3 x (H - 8) x (W - 8) float32 in [0, 1] on the inputs'
        device: the synthetic input and the ground truth, both re-toned with the A7R3 response.
    """
    if blurred.ndim != 4 or blurred.shape[1] != 3 or blurred.shape[2] % 2 or blurred.shape[3] % 2:
        raise ValueError(f"blurred must be B x 3 x H x W with even H and W; got shape "
                         f"{tuple(blurred.shape)}")
    for name, t in (("mask", mask), ("sharp", sharp)):
        if t.shape != blurred.shape:
            raise ValueError(f"{name} has shape {tuple(t.shape)} but blurred has "
                             f"{tuple(blurred.shape)}; give them the same shape")
    batch, device = blurred.shape[0], blurred.device
    channels = _pattern_channels(pattern, batch, device)
    alpha = _per_sample(alpha, batch, device, "alpha")
    # gains per channel (R, G, B), then per packed plane through the sample's pattern
    gains = torch.cat([_per_sample(red_gain, batch, device, "red_gain"), torch.ones_like(alpha),
                       _per_sample(blue_gain, batch, device, "blue_gain")], dim=1)
    plane_gain = gains.reshape(batch, 3).gather(1, channels)[:, :, None, None]

    lin = srgb_to_linear(blurred)                                        # 4
    saturated = (lin + alpha * mask).clamp(0.0, 1.0)                    # 5
    cam = _column_vector(_row_vector(saturated, M_LIN2XYZ), A7R3_XYZ2CAM)  # 6, 7 (no clip)
    raw = mosaic(cam, channels) / plane_gain                            # 8, 9
    if noise:                                                           # 10
        k = _noise_level(shot_noise_k, BETA1_SHOT_K, batch, generator, device, "shot_noise_k")
        std = _noise_level(read_noise_std, BETA2_READ_STD, batch, generator, device,
                           "read_noise_std")
        # rates are >= 0 for in-gamut input (the A7R3 rgb2cam is all positive); clamp anyway
        shot = torch.poisson((raw / k).clamp_min(0.0), generator=generator)
        raw = k * shot + std * torch.randn(raw.shape, generator=generator, device=device)
    cfa = F.pixel_shuffle(raw * plane_gain, 2)                          # 11, 12
    rgb = demosaic_malvar2004(cfa, channels)                            # 13 (no clip)
    lin_out = _row_vector(_column_vector(rgb, A7R3_CAM2XYZ), M_XYZ2LIN)  # 14, 15
    out = linear_to_srgb(lin_out).clamp(0.0, 1.0)                       # 16
    out = torch.where(saturated >= 1.0, saturated, out)                 # 17
    out, gt = a7r3_retone(out), a7r3_retone(sharp)                      # 18
    crop = (slice(None), slice(None), slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    return out[crop], gt[crop]                                          # 19
