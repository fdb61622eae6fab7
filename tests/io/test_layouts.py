"""The published layouts of already-blurred images, and gpu-blur generate over them (issue 16)."""

import cv2
import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS, manifest_lines

import gpu_blur
from gpu_blur.blurred_inputs import find_blurred
from gpu_blur.cli import main
from gpu_blur.discovery import find_samples
from gpu_blur.image_reading import read_image

SCENE = '[blur]\nmode = "none"\n[saturation]\nmode = "on"\n'


def write_image(path, seed, bright=False):
    """A 16 x 16 8-bit PNG (BGR on disk); ``bright``: its top rows at 255 (clipped)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.random.default_rng(seed).integers(0, 200, (16, 16, 3), np.uint8)
    if bright:
        image[:4] = 255
    cv2.imwrite(str(path), image)


def write_sample(base, blurred_dir, mask_dir, sharp_rel, name="avg_blur.png", seed=0,
                 mask=True):
    """One sample of a layout under ``base``: blurred, mask (unless not), sharp (if named)."""
    write_image(base / blurred_dir / name, seed, bright=True)
    if mask:
        write_image(base / mask_dir / name, seed + 1)
    if sharp_rel:
        write_image(base / sharp_rel, seed + 2)


@pytest.fixture
def layouts(tmp_path):
    """A tree holding all three layouts, two GoPro_INTER_ABME samples first."""
    root = tmp_path / "in"
    abme = root / "GoPro_INTER_ABME" / "GOPR0372_07_00"
    for seed, sample in enumerate(["000002", "000010"]):
        write_sample(abme / sample, "avg_inter_img", "avg_inter_mask_100", "gt/gt_sharp.png",
                     seed=10 * seed)
    write_sample(root / "GoPro_U", "centroid_blurred_img", "centroid_blurred_mask_100",
                 "target_img/7_GOPR0386_11_00_000298_kernel_9_gt.png",
                 name="7_GOPR0386_11_00_000298_kernel_9_blurred.png", seed=30)
    rsblur = root / "RSBlur" / "0001" / "000001"
    write_sample(rsblur, "avg65_img", "avg65_mask_100", "gt/gt_sharp.png", seed=40)
    write_image(rsblur / "real_blur" / "real_blur.png", 50)  # not an averaged image
    write_image(rsblur / "00001.png", 51)  # a sharp frame: not read in mode none
    return root


def test_each_published_layout_gives_its_blurred_image_mask_and_sharp_reference(layouts):
    found = find_blurred(layouts)
    abme = layouts / "GoPro_INTER_ABME" / "GOPR0372_07_00"
    gopro_u, rsblur = layouts / "GoPro_U", layouts / "RSBlur" / "0001" / "000001"
    u_name = "7_GOPR0386_11_00_000298_kernel_9"
    assert [(s.name, s.blurred, s.mask, s.sharp, s.problem) for s in found] == [
        ("GoPro_INTER_ABME/GOPR0372_07_00/000002/avg_blur",
         abme / "000002/avg_inter_img/avg_blur.png",
         abme / "000002/avg_inter_mask_100/avg_blur.png", abme / "000002/gt/gt_sharp.png", None),
        ("GoPro_INTER_ABME/GOPR0372_07_00/000010/avg_blur",
         abme / "000010/avg_inter_img/avg_blur.png",
         abme / "000010/avg_inter_mask_100/avg_blur.png", abme / "000010/gt/gt_sharp.png", None),
        (f"GoPro_U/{u_name}_blurred", gopro_u / f"centroid_blurred_img/{u_name}_blurred.png",
         gopro_u / f"centroid_blurred_mask_100/{u_name}_blurred.png",
         gopro_u / f"target_img/{u_name}_gt.png", None),
        ("RSBlur/0001/000001/avg_blur", rsblur / "avg65_img/avg_blur.png",
         rsblur / "avg65_mask_100/avg_blur.png", rsblur / "gt/gt_sharp.png", None)]
    specs = find_samples(layouts, "none", 1).take()
    assert [s.roles for s in specs] == [("blurred", "mask", "sharp")] * 4
    assert [s.inputs for s in specs] == [(s.blurred, s.mask, s.sharp) for s in found]


def test_a_missing_mask_or_sharp_image_is_that_sample_s_problem_naming_the_file(tmp_path):
    root = tmp_path / "RSBlur"
    write_sample(root / "0001" / "000001", "avg65_img", "avg65_mask_100", "gt/gt_sharp.png",
                 mask=False)
    write_sample(root / "0001" / "000002", "avg65_img", "avg65_mask_100", None)
    (root / "0001" / "000002" / "gt").mkdir()  # a sharp folder without its image
    write_sample(root / "0001" / "000003", "avg65_img", "avg65_mask_100", None)
    first, second, third = find_blurred(root)
    assert first.mask is None and first.problem.startswith(
        f"{first.blurred}: no saturation mask {root / '0001/000001/avg65_mask_100/avg_blur.png'}")
    assert "saturation.mode = off" in first.problem
    assert second.sharp is None and f"{root / '0001/000002/gt'} holds 0 images" in second.problem
    assert third.problem is None and third.sharp is None  # no gt/: the blurred is the reference
    # saturation off: masks are not looked for, and a missing one is no problem
    assert [(s.mask, s.problem is None) for s in find_blurred(root, masks=False)] == [
        (None, True), (None, False), (None, True)]


def test_generate_refuses_mode_none_on_a_folder_with_no_layout_naming_what_it_expects(
        tmp_path, capsys):
    write_image(tmp_path / "in" / "photo.png", 0)
    scene = tmp_path / "none.toml"
    scene.write_text(SCENE)
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(tmp_path / "o"),
                 "--scene", str(scene), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "blur.mode = none found no already-blurred images in avg_inter_img/" in err
    assert "avg65_img/ (masks in avg65_mask_100/, RSBlur)" in err


def rgb(path):
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)


@pytest.mark.parametrize("backend", ["numpy", *KERNEL_BACKEND_SPECS[:1]])
def test_generate_mode_none_makes_each_sample_from_its_blurred_image_mask_and_sharp(
        tmp_path, layouts, backend):
    backend = backend.split("/")[0]
    scene = tmp_path / "none.toml"
    scene.write_text(SCENE)
    out = tmp_path / "out"
    assert main(["generate", "--input", str(layouts), "--output", str(out), "--scene",
                 str(scene), "--backend", backend, "--seed", "3", "--quiet"]) == 0
    lines = manifest_lines(out)
    assert [x["input_roles"] for x in lines] == [["blurred", "mask", "sharp"]] * 4
    for line, spec in zip(lines, find_samples(layouts, "none", 1).take(), strict=True):
        assert line["inputs"] == [str(p) for p in spec.inputs]
        blurred, mask, sharp = (rgb(p) for p in spec.inputs)
        want = gpu_blur.synthesize({"blurred": blurred, "mask": mask, "sharp": sharp}, scene,
                                   seed=3, sample_index=line["index"], backend=backend)
        assert np.array_equal(read_image(out / line["blurred"]),
                              np.round(want.blurred * 255).astype(np.uint8))
        assert np.array_equal(read_image(out / line["sharp"]),
                              np.round(want.sharp * 255).astype(np.uint8))
        # the mask was read (value / 255) and used: without it the sample differs
        maskless = gpu_blur.synthesize({"blurred": blurred, "sharp": sharp}, scene, seed=3,
                                       sample_index=line["index"], backend=backend)
        assert not np.array_equal(maskless.blurred, want.blurred)


def test_mode_none_without_masks_needs_saturation_off_and_then_reads_none(tmp_path, layouts):
    for mask in layouts.rglob("*_mask_100/*.png"):
        mask.unlink()
    scene = tmp_path / "none.toml"
    scene.write_text(SCENE)
    run = ["generate", "--input", str(layouts), "--scene", str(scene), "--quiet"]
    assert main([*run, "--output", str(tmp_path / "on")]) == 1
    lines = manifest_lines(tmp_path / "on")
    assert {x["status"] for x in lines} == {"failed"}
    assert all("no saturation mask" in x["error"] for x in lines)
    scene.write_text(SCENE.replace('"on"', '"off"'))
    assert main([*run, "--output", str(tmp_path / "off")]) == 0
    assert [x["input_roles"] for x in manifest_lines(tmp_path / "off")] == [
        ["blurred", "sharp"]] * 4


def test_mode_none_over_devices_writes_the_files_of_a_serial_run(tmp_path, layouts):
    scene = tmp_path / "none.toml"
    scene.write_text(SCENE)
    run = ["generate", "--input", str(layouts), "--scene", str(scene), "--quiet"]
    assert main([*run, "--output", str(tmp_path / "serial")]) == 0
    assert main([*run, "--output", str(tmp_path / "two"), "--devices", "numpy,numpy"]) == 0
    written = [{p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
                if p.is_file() and p.suffix in (".png", ".jsonl")}
               for out in (tmp_path / "two", tmp_path / "serial")]
    assert written[0] == written[1] and len(written[0]) == 9  # 4 x blur, sharp; manifest
