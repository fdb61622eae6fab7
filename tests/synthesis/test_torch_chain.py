"""bench/torch_chain.py, the plain PyTorch port of the authors' RealBlur-J chain, against
gpu_blur's numpy float64 reference on the built-in RealBlur-J scene."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from conftest import ROOT

import gpu_blur
from gpu_blur.scene import scene_from_dict, scene_path, toml_loads
from gpu_blur.testing import assert_close

_PATH = ROOT / "bench" / "torch_chain.py"
_SPEC = importlib.util.spec_from_file_location("torch_chain", _PATH)
torch_chain = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(torch_chain)

H, W = 48, 64


def realblur_j(**changes) -> gpu_blur.Scene:
    """The built-in RealBlur-J scene with some sections' keys changed."""
    data = toml_loads(scene_path("realblur_j").read_text())
    for section, keys in changes.items():
        data.setdefault(section, {}).update(keys)
    return scene_from_dict(data)


def reference(blurred, mask, sharp, scene, overrides) -> tuple[np.ndarray, np.ndarray]:
    r = gpu_blur.synthesize({"blurred": blurred, "mask": mask, "sharp": sharp}, scene,
                            backend="numpy", overrides=overrides)
    return r.blurred, r.sharp


def chw(images: list[np.ndarray]) -> torch.Tensor:
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2)


def hwc(batch: torch.Tensor) -> np.ndarray:
    """B x H x W x 3 float64 (numpy sums a strided float32 view naively: 3e-4 off in a std)."""
    return batch.permute(0, 2, 3, 1).numpy().astype(np.float64)


def test_torch_chain_matches_numpy_reference_without_noise_for_every_pattern(coffee_rgb):
    # one batch, one sample per Bayer pattern, each with its own alpha and gains: crops of the
    # photo (its spoon and cup rim clip) with a sparse mask in 1/255 steps, as the authors' PNGs
    g = np.random.default_rng(7)
    scene = realblur_j(noise={"model": "none"}, isp={"round_trip": "always"})
    corners = [(40, 200), (101, 333), (250, 17), (330, 530)]
    blurred = [coffee_rgb[y:y + H, x:x + W].astype(np.float32) for y, x in corners]
    sharp = [coffee_rgb[y + 3:y + 3 + H, x + 5:x + 5 + W].astype(np.float32)
             for y, x in corners]
    codes = g.integers(0, 256, (4, H, W, 3)) * (g.uniform(0, 1, (4, H, W, 3)) < 0.3)
    mask = list((codes / 255).astype(np.float32))
    params = {"alpha": [0.3, 1.0, 1.5, 1.75], "red_gain": [1.9, 2.1, 2.4, 2.2],
              "blue_gain": [1.5, 1.9, 1.6, 1.8], "pattern": list(torch_chain.PATTERNS)}

    out, gt = torch_chain.realblur_j_chain(chw(blurred), chw(mask), chw(sharp), noise=False,
                                           **params)

    assert out.shape == gt.shape == (4, 3, H - 8, W - 8) and out.dtype == torch.float32
    for b in range(4):
        overrides = {k: v[b] for k, v in params.items()}
        want_out, want_gt = reference(blurred[b], mask[b], sharp[b], scene, overrides)
        assert_close(hwc(out)[b], want_out, "pipeline_realblur_j", "torch", "float32")
        assert_close(hwc(gt)[b], want_gt, "pipeline_realblur_j", "torch", "float32")


def test_torch_chain_noise_has_the_reference_noise_level():
    # a flat grey with fixed noise levels: each channel's noise std (over the interior, after
    # Malvar and the A7R3 re-toning) as the numpy reference's, which draws its own noise
    grey = np.full((256, 256, 3), 0.4, np.float32)
    zero = np.zeros_like(grey)
    fixed = {"alpha": 1.0, "red_gain": 2.1, "blue_gain": 1.7, "pattern": "RGGB",
             "shot_noise_k": 1.2e-4, "read_noise_std": 4e-5}
    want, _ = reference(grey, zero, grey, realblur_j(), fixed)
    out, _ = torch_chain.realblur_j_chain(chw([grey]), chw([zero]), chw([grey]),
                                          generator=torch.Generator().manual_seed(3), **fixed)
    want_std = want.astype(np.float64).std(axis=(0, 1))
    assert_close(hwc(out)[0].std(axis=(0, 1)), want_std, "noise_std_realblur_j", "torch",
                 "float32")
    quiet, _ = torch_chain.realblur_j_chain(chw([grey]), chw([zero]), chw([grey]), noise=False,
                                            **fixed)
    assert hwc(quiet)[0].std(axis=(0, 1)).max() < 1e-6


@pytest.mark.parametrize("bad, message", [
    ({"pattern": "RGBG"}, "is not a Bayer pattern"),
    ({"alpha": [1.0, 1.0, 1.0]}, "alpha holds 3 values for a batch of 2"),
])
def test_torch_chain_refuses_bad_parameters_naming_them(bad, message):
    x = torch.zeros(2, 3, 8, 8)
    args = {"alpha": 1.0, "red_gain": 2.0, "blue_gain": 1.7, "pattern": "RGGB"} | bad
    with pytest.raises(ValueError, match=message):
        torch_chain.realblur_j_chain(x, x, x, noise=False, **args)
