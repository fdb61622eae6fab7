"""gpu_blur.torch.RealisticBlur: the batch API as a training-loop transform."""

import numpy as np
import pytest
import torch

import gpu_blur
from gpu_blur.scene import scene_from_dict
from gpu_blur.torch import RealisticBlur, epoch_seed


def photos(count=3, h=20, w=24):
    codes = np.random.default_rng(0).integers(0, 256, (count, 3, h, w), dtype=np.uint8)
    return torch.from_numpy(codes)


SCENE = scene_from_dict({"blur": {"mode": "kernel", "kernel_size": [3, 5]}})


def test_a_sample_is_fixed_by_seed_epoch_and_index():
    blur = RealisticBlur(SCENE, seed=4)
    batch = photos()
    blurred, sharp = blur(batch, indices=torch.tensor([9, 0, 5]), epoch=2)
    assert blurred.shape == sharp.shape == (3, 3, 20, 24) and blurred.dtype == torch.float32
    for b, index in enumerate([9, 0, 5]):
        one = gpu_blur.synthesize(batch[b].permute(1, 2, 0).numpy(), SCENE,
                                  seed=epoch_seed(4, 2), sample_index=index, backend="warp:cpu")
        assert np.array_equal(blurred[b].permute(1, 2, 0).numpy(), one.blurred)
    again, _ = RealisticBlur(SCENE, seed=4)(batch, indices=[9, 0, 5], epoch=2)
    assert torch.equal(again, blurred)
    other_epoch, _ = blur(batch, indices=[9, 0, 5], epoch=3)
    assert not torch.equal(other_epoch, blurred)


def test_without_indices_samples_are_numbered_in_call_order():
    batch = photos(2)
    blur = RealisticBlur(SCENE)
    first, _ = blur(batch)
    second, _ = blur(batch)
    by_index, _ = RealisticBlur(SCENE)(torch.cat([batch, batch]), indices=[0, 1, 2, 3])
    assert torch.equal(torch.cat([first, second]), by_index)


def test_frame_stacks_come_channels_first_too():
    scene = scene_from_dict({"blur": {"mode": "average", "frames": 3}})
    frames = photos(6).reshape(2, 3, 3, 20, 24)  # B x F x 3 x H x W
    blurred, sharp = RealisticBlur(scene)(frames)
    assert blurred.shape == (2, 3, 20, 24)
    assert torch.equal(sharp[0].permute(1, 2, 0),
                       frames[0, 1].permute(1, 2, 0).float() / 255)


def test_epoch_seeds_differ_and_bad_seeds_are_refused():
    assert len({epoch_seed(1, e) for e in range(1000)}) == 1000
    assert epoch_seed(1, 0) != epoch_seed(2, 0)
    with pytest.raises(ValueError, match="seed must be in"):
        epoch_seed(-1, 0)


def test_float_indices_are_refused_not_truncated():
    blur = RealisticBlur(SCENE, backend="numpy")
    with pytest.raises(ValueError, match=r"indices\[0\] = 0.5: a sample index is an int"):
        blur(photos(2), indices=torch.tensor([0.5, 1.0]))
    by_tensor, _ = blur(photos(2), indices=torch.tensor([0, 1]))
    by_list, _ = blur(photos(2), indices=[0, 1])
    assert torch.equal(by_tensor, by_list)


@pytest.mark.parametrize("make, words", [
    (lambda x: x.to("meta"), "batch: a tensor on the meta device holds no values"),
    (lambda x: x.to_sparse(), "batch: a torch.sparse_coo tensor; pass a dense one"),
])
def test_meta_and_sparse_batches_are_refused_by_name(make, words):
    with pytest.raises(ValueError, match=words):
        RealisticBlur(SCENE)(make(photos(2)))


def test_overrides_are_checked_when_the_transform_is_made():
    with pytest.raises(ValueError, match=r"overrides\['alpha'\] = nan is invalid"):
        RealisticBlur(SCENE, overrides={"alpha": float("nan")})


@pytest.mark.parametrize("backend", [None, "numpy"])
@pytest.mark.parametrize("bad, words", [
    (float("nan"), "1 NaN and 0 infinite value(s), the first at row 4, column 6, channel 1"),
    (float("-inf"), "0 NaN and 1 infinite value(s), the first at row 4, column 6, channel 1"),
    (-0.5, "1 negative value(s), the lowest -0.5, the first at row 4, column 6, channel 1"),
    (2.0, "1 value(s) above 1, the highest 2, the first at row 4, column 6, channel 1")])
def test_a_bad_float_in_a_channels_first_batch_names_its_sample(backend, bad, words):
    # float batches are checked by torch where they lie (Warp) or on the host (numpy): the same
    # words, with the sample and the place in its H x W x 3 image
    batch = photos(3).float() / 255
    batch[2, 1, 4, 6] = bad  # sample 2, channel 1, row 4, column 6
    blur = RealisticBlur(SCENE, backend=backend)
    with pytest.raises(ValueError) as e:
        blur(batch)
    assert str(e.value).startswith(f"sample 2 of 3: photo: {words}; float images must be")
    blurred, _ = blur(batch.nan_to_num(0.0).clamp(0, 1))  # the fix the message gives
    assert blurred.shape == (3, 3, 20, 24)
