"""gpu_blur.datasets: the published layouts as training data sets, crops and flips (issue 16)."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from gpu_blur.datasets import (
    BlurredImages,
    Photos,
    RealBlurPairs,
    SharpSequences,
    epoch_seed,
)
from gpu_blur.image_reading import read_image


def write_image(path, seed, size=(16, 16)):
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.random.default_rng(seed).integers(0, 256, (*size, 3), np.uint8)
    cv2.imwrite(str(path), image)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


@pytest.fixture
def trees(tmp_path):
    """One small tree per layout: GoPro_Large, RSBlur (frames and averages), GoPro_INTER_ABME,
    GoPro_U, RealBlur_J (folders and a datalist)."""
    for seq in ("GOPR0372_07_00", "GOPR0374_11_00"):
        for i in range(6):
            write_image(tmp_path / "GOPRO_Large" / seq / "sharp" / f"{i:06d}.png", i)
    rsblur = tmp_path / "RSBlur" / "0001"
    for sample in ("000001", "000002"):
        for i in range(3):
            write_image(rsblur / sample / f"{i:05d}.png", 10 + i)
        write_image(rsblur / sample / "avg65_img" / "avg_blur.png", 20)
        write_image(rsblur / sample / "avg65_mask_100" / "avg_blur.png", 21)
        write_image(rsblur / sample / "gt" / "gt_sharp.png", 22)
    abme = tmp_path / "GoPro_INTER_ABME" / "GOPR0372_07_00" / "000001"
    write_image(abme / "avg_inter_img" / "avg_blur.png", 30)
    write_image(abme / "avg_inter_mask_100" / "avg_blur.png", 31)
    write_image(abme / "gt" / "gt_sharp.png", 32)
    gopro_u = tmp_path / "GoPro_U"
    write_image(gopro_u / "centroid_blurred_img" / "1_x_kernel_5_blurred.png", 40)
    write_image(gopro_u / "centroid_blurred_mask_100" / "1_x_kernel_5_blurred.png", 41)
    write_image(gopro_u / "target_img" / "1_x_kernel_5_gt.png", 42)
    realblur = tmp_path / "RealBlur_J" / "scene001"
    for n in (2, 10, 1):
        write_image(realblur / "blur" / f"blur_{n}.png", 50 + n)
        write_image(realblur / "gt" / f"gt_{n}.png", 60 + n)
    (tmp_path / "RealBlur_J_test_list.txt").write_text(
        "RealBlur_J/scene001/gt/gt_10.png RealBlur_J/scene001/blur/blur_10.png \n"
        "RealBlur_J/scene001/gt/gt_2.png RealBlur_J/scene001/blur/blur_2.png \n")
    return tmp_path


def test_each_layout_gives_its_items_as_stored_codes_with_the_index(trees):
    gopro = SharpSequences(trees / "GOPRO_Large", frames=3)
    assert len(gopro) == 4  # two windows of 3 in each 6-frame sequence
    index, frames = gopro[3]
    assert index == 3 and frames.shape == (3, 16, 16, 3) and frames.dtype == np.uint8
    assert np.array_equal(frames[0], read_image(
        trees / "GOPRO_Large" / "GOPR0374_11_00" / "sharp" / "000003.png"))
    rsblur_frames = SharpSequences(trees / "RSBlur", frames=3)
    assert len(rsblur_frames) == 2 and rsblur_frames[1][1].shape == (3, 16, 16, 3)
    for folder in ("RSBlur", "GoPro_INTER_ABME", "GoPro_U"):
        index, blurred, mask, sharp = BlurredImages(trees / folder)[0]
        assert index == 0 and blurred.shape == mask.shape == sharp.shape == (16, 16, 3)
    u = trees / "GoPro_U"
    _, blurred, mask, sharp = BlurredImages(u)[0]
    assert np.array_equal(mask, read_image(
        u / "centroid_blurred_mask_100" / "1_x_kernel_5_blurred.png"))
    assert np.array_equal(sharp, read_image(u / "target_img" / "1_x_kernel_5_gt.png"))
    assert len(BlurredImages(trees / "RSBlur", masks=False)[0]) == 3  # index, blurred, sharp
    pairs = RealBlurPairs(trees / "RealBlur_J")
    assert [p.name for p in pairs._items] == [f"scene001/blur_{n}" for n in (1, 2, 10)]
    listed = RealBlurPairs(trees, trees / "RealBlur_J_test_list.txt")
    _, blurred, sharp = listed[0]  # the list's order: blur_10 first
    assert np.array_equal(blurred, read_image(trees / "RealBlur_J/scene001/blur/blur_10.png"))
    assert np.array_equal(sharp, read_image(trees / "RealBlur_J/scene001/gt/gt_10.png"))
    assert len(Photos()) == 1 and Photos(samples_per_photo=3)[2][1].shape == (400, 600, 3)


def test_crops_and_flips_are_fixed_by_seed_epoch_and_index_on_even_offsets(trees):
    kwargs = {"crop": 8, "flips": True, "seed": 5}
    data = BlurredImages(trees / "RSBlur", **kwargs)
    first = [data[i] for i in range(len(data))]
    again = BlurredImages(trees / "RSBlur", **kwargs)
    assert all(np.array_equal(a, b) for x, y in zip(first, [again[0], again[1]], strict=True)
               for a, b in zip(x[1:], y[1:], strict=True))
    index, blurred, mask, sharp = first[1]
    assert blurred.shape == mask.shape == sharp.shape == (8, 8, 3) and index == 1
    top, left, mirror, upside_down = data.augmentation(1, 16, 16)
    whole = read_image(trees / "RSBlur/0001/000002/avg65_img/avg_blur.png")
    want = whole[top:top + 8, left:left + 8]
    want = want[:, ::-1] if mirror else want
    want = want[::-1] if upside_down else want
    assert np.array_equal(blurred, want)  # the same crop and flips on each of its images
    draws = set()
    for epoch in range(16):
        data.set_epoch(epoch)
        draws.add(data.augmentation(1, 16, 16))
    assert all(top % 2 == 0 and left % 2 == 0 for top, left, _, _ in draws)
    assert len(draws) > 8  # epochs differ (9 x 9 offsets x 4 flips to draw from)
    assert {(m, u) for _, _, m, u in draws} == {(False, False), (False, True), (True, False),
                                                (True, True)}
    no_flips = BlurredImages(trees / "RSBlur", crop=8, seed=5)
    assert no_flips.augmentation(1, 16, 16)[:2] == BlurredImages(
        trees / "RSBlur", **kwargs).augmentation(1, 16, 16)[:2]  # flips move no crop
    assert no_flips.augmentation(1, 16, 16)[2:] == (False, False)
    assert data.augmentation(0, 16, 16) != BlurredImages(
        trees / "RSBlur", crop=8, flips=True, seed=6, epoch=15).augmentation(0, 16, 16)


def test_bad_folders_settings_and_files_are_refused_naming_them(trees, tmp_path):
    with pytest.raises(ValueError, match=r"BlurredImages .*nowhere: no such folder"):
        BlurredImages(tmp_path / "nowhere")
    with pytest.raises(ValueError, match=r"no already-blurred images in avg_inter_img/"):
        BlurredImages(trees / "GOPRO_Large")
    with pytest.raises(ValueError, match="crop = 7: give an even number"):
        SharpSequences(trees / "GOPRO_Large", frames=3, crop=7)
    with pytest.raises(ValueError, match=r"2 sample\(s\) cannot be used: sequence "
                                         r"GOPR0372_07_00 has 6 frame\(s\) .*fewer than "
                                         r"blur.frames = 7"):
        SharpSequences(trees / "GOPRO_Large", frames=7)
    (trees / "GoPro_U/centroid_blurred_mask_100/1_x_kernel_5_blurred.png").unlink()
    with pytest.raises(ValueError, match=r"1 sample\(s\) cannot be used: .*no saturation mask "
                                         r".*centroid_blurred_mask_100/1_x_kernel_5_blurred"):
        BlurredImages(trees / "GoPro_U")
    assert len(BlurredImages(trees / "GoPro_U", masks=False)) == 1
    with pytest.raises(ValueError, match=r"avg_blur.png: 16 x 16 \(width x height\) is smaller "
                                         r"than crop = 18"):
        BlurredImages(trees / "RSBlur", crop=18)[0]
    with pytest.raises(IndexError, match="index 2 is outside this data set of 2 items"):
        BlurredImages(trees / "RSBlur")[2]
    (trees / "RealBlur_J/scene001/gt/gt_2.png").unlink()
    with pytest.raises(ValueError, match=r"blur_2.png: its ground truth .*gt_2.png is missing"):
        RealBlurPairs(trees / "RealBlur_J")
    with pytest.raises(ValueError, match=r"test_list.txt, line 2: .*gt_2.png not found"):
        RealBlurPairs(trees, trees / "RealBlur_J_test_list.txt")


@pytest.mark.parametrize("way", ["dot-dot", "absolute", "link"])
def test_datalist_paths_outside_the_data_folder_are_refused_naming_the_line(trees, way):
    root, outside = trees / "RealBlur_J", trees / "GoPro_U" / "target_img" / "1_x_kernel_5_gt.png"
    if way == "link":
        (root / "elsewhere").symlink_to(outside.parent)
    path = {"dot-dot": "../GoPro_U/target_img/1_x_kernel_5_gt.png", "absolute": str(outside),
            "link": "elsewhere/1_x_kernel_5_gt.png"}[way]
    datalist = trees / "list.txt"
    datalist.write_text("scene001/../scene001/gt/gt_10.png scene001/blur/blur_10.png\n"
                        f"{path} scene001/blur/blur_2.png\n")
    with pytest.raises(ValueError) as e:
        RealBlurPairs(root, datalist)
    assert str(e.value) == (
        f"{datalist}, line 2: {path} leads outside the data folder {root.resolve()} (to "
        f"{outside.resolve()}); "
        "datalist paths are relative to the data folder and stay in it: fix the line, or pass "
        "the folder that holds the files as the data folder")
    datalist.write_text("scene001/../scene001/gt/gt_10.png scene001/blur/blur_10.png\n")
    assert len(RealBlurPairs(root, datalist)) == 1  # a '..' that stays inside is read


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
def test_a_datalist_that_is_a_named_pipe_is_refused_not_waited_on(trees):
    fifo = trees / "list.txt"
    os.mkfifo(fifo)  # reading one without a writer blocks forever
    with pytest.raises(ValueError, match=r"datalist .*list.txt: is a named pipe"):
        RealBlurPairs(trees / "RealBlur_J", fifo)


def test_the_module_needs_no_torch():
    code = ("import sys, gpu_blur.datasets; "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


torch = pytest.importorskip("torch")


def test_dataloader_workers_give_the_items_of_the_data_set(trees):
    data = SharpSequences(trees / "GOPRO_Large", frames=3, crop=8, flips=True, seed=2)
    data.set_epoch(3)
    loader = torch.utils.data.DataLoader(data, batch_size=2, num_workers=2)
    batches = list(loader)
    assert [b[0].tolist() for b in batches] == [[0, 1], [2, 3]]
    for index, frames in batches:
        for i, stack in zip(index.tolist(), frames, strict=True):
            assert torch.equal(stack, torch.from_numpy(data[i][1]))


def test_the_transform_fed_by_a_data_set_equals_the_batch_api(trees):
    from gpu_blur import Synthesizer
    from gpu_blur.scene import scene_from_dict
    from gpu_blur.torch import RealisticBlur

    scene = scene_from_dict({"blur": {"mode": "none"}, "saturation": {"mode": "on"}})
    data = BlurredImages(trees / "RSBlur", crop=8, flips=True, seed=1, epoch=2)
    index, blurred, mask, sharp = next(iter(torch.utils.data.DataLoader(data, batch_size=2)))
    out, out_sharp = RealisticBlur(scene, seed=1, backend="warp:cpu", channels_first=False)(
        blurred, mask, sharp, indices=index, epoch=2)
    items = [data[i] for i in (0, 1)]
    want = Synthesizer(scene, backend="warp:cpu", seed=epoch_seed(1, 2))(
        np.stack([x[1] for x in items]), mask=np.stack([x[2] for x in items]),
        sharp=np.stack([x[3] for x in items]), indices=[0, 1])
    assert np.array_equal(out.numpy(), want.blurred)
    assert np.array_equal(out_sharp.numpy(), want.sharp)
