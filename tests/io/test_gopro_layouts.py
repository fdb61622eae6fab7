"""GoPro's layouts (issue 38): GOPRO_Large's sharp frames are refused for averaging unless
forced, GOPRO_Large_all's frames are averaged ``yy`` at a time (blur.frames = "from-name"), a
photo mode over frame sequences is refused unless asked, and generate says what it found."""

import json
import shutil

import cv2
import numpy as np
import pytest

import gpu_blur
from gpu_blur.cli import main
from gpu_blur.datasets import SharpSequences
from gpu_blur.discovery import find_samples
from gpu_blur.planning import plan
from gpu_blur.scene import describe_fields, load_scene


def write_frames(folder, count, first=0, seed=0):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(first, first + count):
        cv2.imwrite(str(folder / f"{i:06d}.png"), rng.integers(0, 256, (16, 24, 3), np.uint8))


@pytest.fixture
def gopro_large(tmp_path):
    """GOPRO_Large-shaped: <seq>/blur/, <seq>/blur_gamma/ and <seq>/sharp/, 4 frames each."""
    root = tmp_path / "GOPRO_Large" / "train"
    for n, seq in enumerate(("GOPR0372_07_00", "GOPR0374_11_00")):
        for sub in ("blur", "blur_gamma", "sharp"):
            write_frames(root / seq / sub, 4, seed=n)
    return root


@pytest.fixture
def gopro_large_all(tmp_path):
    """GOPRO_Large_all-shaped: every frame in <seq>/, 15 and 23 of them (numbered from 1)."""
    root = tmp_path / "GOPRO_Large_all" / "train"
    write_frames(root / "GOPR0372_07_00", 15, first=1, seed=1)
    write_frames(root / "GOPR0384_11_00", 23, first=1, seed=2)
    return root


def scene_file(tmp_path, text, name="s.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


AVERAGE = '[blur]\nmode = "average"\nframes = {}\n'


def generate(root, out, *extra):
    return main(["generate", "--input", str(root), "--output", str(out), "--quiet", *extra])


def files(out):
    """{relative path: bytes} of every file a set holds under its folders."""
    return {p.relative_to(out).as_posix(): p.read_bytes()
            for p in sorted(out.rglob("*")) if p.is_file() and p.parent != out}


def manifest(out):
    return [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]


def test_averaging_gopro_large_sharp_frames_is_refused_with_the_reason_and_the_fix(
        tmp_path, gopro_large, capsys):
    scene = scene_file(tmp_path, AVERAGE.format(2))
    out = tmp_path / "out"
    assert generate(gopro_large, out, "--scene", str(scene)) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == (
        f"gpu-blur: error: --input {gopro_large}: GOPR0372_07_00/sharp/ sits beside "
        "GOPR0372_07_00/blur/ as in GOPRO_Large (2 such sequence(s)), whose sharp frames are "
        "the ground truth of blurs averaged already, one per blurred image with gaps between "
        "them (DeepDeblur_release#22), so averaging them makes ghosted blur; average "
        "GOPRO_Large_all's frames instead (every frame, GOPRxxxx_yy_zz/*.png) with "
        f'blur.frames = "from-name" (scene file {scene}), or pass --average-gopro-large-sharp '
        "to average these anyway")
    assert not out.exists()  # refused before the output folder is made
    # the same refusal from Python, which names the keyword's option
    with pytest.raises(ValueError, match="--average-gopro-large-sharp"):
        gpu_blur.generate_set(out, input=gopro_large, scene=scene)


def test_forced_gopro_large_averages_its_sharp_frames_as_any_sharp_folder(tmp_path,
                                                                         gopro_large):
    scene = scene_file(tmp_path, AVERAGE.format(2))
    assert generate(gopro_large, tmp_path / "forced", "--scene", str(scene),
                    "--average-gopro-large-sharp") == 0
    lines = manifest(tmp_path / "forced")
    assert [x["name"] for x in lines] == ["GOPR0372_07_00/000000", "GOPR0372_07_00/000002",
                                          "GOPR0374_11_00/000000", "GOPR0374_11_00/000002"]
    assert [p.rsplit("/", 2)[-2:] for p in lines[1]["inputs"]] == [
        ["sharp", "000002.png"], ["sharp", "000003.png"]]
    # without blur/ beside sharp/ it is no GOPRO_Large: the same samples, byte for byte
    for seq in gopro_large.iterdir():
        shutil.rmtree(seq / "blur")
    assert generate(gopro_large, tmp_path / "plain", "--scene", str(scene)) == 0
    assert files(tmp_path / "forced") == files(tmp_path / "plain")
    assert manifest(tmp_path / "forced") == manifest(tmp_path / "plain")


def test_gopro_large_all_from_name_averages_yy_consecutive_frames_per_blur(
        tmp_path, gopro_large_all, capsys):
    scene = scene_file(tmp_path, AVERAGE.format('"from-name"'))
    out = tmp_path / "out"
    assert generate(gopro_large_all, out, "--scene", str(scene)) == 0
    lines = manifest(out)
    used = [(x["name"], [int(p[-10:-4]) for p in x["inputs"]]) for x in lines]
    assert used == [  # 15 frames: two blurs of 7 (frame 15 left over); 23: two blurs of 11
        ("GOPR0372_07_00/000001", list(range(1, 8))),
        ("GOPR0372_07_00/000008", list(range(8, 15))),
        ("GOPR0384_11_00/000001", list(range(1, 12))),
        ("GOPR0384_11_00/000012", list(range(12, 23)))]
    assert all(x["status"] == "ok" for x in lines)
    assert json.loads((out / "run.json").read_text())["scene"]["blur"]["frames"] == "from-name"
    err = capsys.readouterr().err.splitlines()
    assert err[1:3] == [
        f"input: {gopro_large_all}: GOPRO_Large_all (GOPRxxxx_yy_zz/*.png); 2 sequences, "
        "38 frames -> 4 samples",
        "blur: average of yy consecutive frames per sample, yy from each sequence's name "
        "GOPRxxxx_yy_zz (blur.frames = 'from-name'; here 7 to 11)"]
    # windows spread by --samples-per-sequence take yy frames too
    specs = find_samples(gopro_large_all, "average", "from-name", samples_per_sequence=2).take()
    assert [len(s.inputs) for s in specs] == [7, 7, 11, 11]
    assert [s.inputs[0].stem for s in specs] == ["000001", "000009", "000001", "000013"]


def test_from_name_gives_the_bytes_of_the_same_count_given_as_a_number(tmp_path,
                                                                       gopro_large_all):
    shutil.rmtree(gopro_large_all / "GOPR0384_11_00")  # one sequence, yy = 7
    named = scene_file(tmp_path, AVERAGE.format('"from-name"'), "named.toml")
    seven = scene_file(tmp_path, AVERAGE.format(7), "seven.toml")
    assert generate(gopro_large_all, tmp_path / "named", "--scene", str(named)) == 0
    assert generate(gopro_large_all, tmp_path / "seven", "--scene", str(seven)) == 0
    assert files(tmp_path / "named") == files(tmp_path / "seven")
    assert manifest(tmp_path / "named") == manifest(tmp_path / "seven")


def test_from_name_names_the_folder_whose_name_gives_no_count(tmp_path, gopro_large_all,
                                                              capsys):
    write_frames(gopro_large_all / "my_clip" / "sharp", 9)
    scene = scene_file(tmp_path, AVERAGE.format('"from-name"'))
    assert generate(gopro_large_all, tmp_path / "out", "--scene", str(scene)) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"gpu-blur: error: scene file {scene}: blur.frames = 'from-name' takes each "
        "sequence's frames per blur from its folder's name GOPRxxxx_yy_zz (yy, as "
        "GOPRO_Large_all names them: DeepDeblur_release#59), but sequence folder "
        f"{gopro_large_all / 'my_clip'} is not named in that form; rename the folder, or set "
        "blur.frames to a number of frames")
    # and a sequence shorter than its yy fails alone, saying so
    shutil.rmtree(gopro_large_all / "my_clip")
    write_frames(gopro_large_all / "GOPR0999_09_00", 4)
    assert generate(gopro_large_all, tmp_path / "short", "--scene", str(scene)) == 1
    failed = [x for x in manifest(tmp_path / "short") if x["status"] == "failed"]
    assert [x["name"] for x in failed] == ["GOPR0999_09_00/000000"]
    assert "fewer than the 9 its name asks for (blur.frames = 'from-name')" in failed[0]["error"]


def test_from_name_is_a_count_of_averaged_frames_only(tmp_path, capsys):
    bad = scene_file(tmp_path, '[blur]\nframes = "from-name"\n')
    assert main(["generate", "--output", str(tmp_path / "out"), "--scene", str(bad)]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"gpu-blur: error: scene file {bad}: blur.frames = 'from-name' needs blur.mode = "
        "'average' (it is 'trajectory'): it counts the frames averaged per blur; allowed for "
        "this mode: a number, or set blur.mode = 'average'")
    typo = scene_file(tmp_path, AVERAGE.format('"from_name"'))
    assert main(["generate", "--output", str(tmp_path / "out"), "--scene", str(typo)]) == 2
    err = capsys.readouterr().err
    assert "blur.frames = 'from_name' is invalid; allowed: int >= 1 and <= 1024" in err
    assert err.rstrip().endswith(", or 'from-name'")
    (frames,) = [x for x in describe_fields().splitlines() if x.startswith("frames = ")]
    assert "or 'from-name': yy of each sequence folder named GOPRxxxx_yy_zz" in frames
    reason = plan(load_scene({"blur": {"mode": "average", "frames": "from-name",
                                       "interpolation": 8}}))["blur"].reason
    assert reason.startswith("mean of (yy - 1) x 8 + 1 linear frames")


@pytest.mark.parametrize("layout", ["gopro_large", "rsblur"])
def test_a_photo_mode_over_frame_sequences_is_refused_unless_asked(tmp_path, gopro_large,
                                                                   layout, capsys):
    if layout == "rsblur":
        root = tmp_path / "RSBlur_sharps"
        for sample in ("000001", "000002"):
            write_frames(root / "0001" / sample, 3)
            write_frames(root / "0001" / sample / "gt", 1)
        held = ("2 frame sequence(s) (RSBlur frames (<session>/<id>/*.png); 6 frames, the "
                "first 0001/000001)")
    else:
        root = gopro_large
        held = ("2 frame sequence(s) (GOPRO_Large (<seq>/sharp/ beside <seq>/blur/); 8 frames, "
                "the first GOPR0372_07_00)")
    out = tmp_path / "out"
    assert generate(root, out, "--limit", "2") == 2  # the default scene: camera shake
    error = capsys.readouterr().err.splitlines()[-1]
    assert error.startswith(f"gpu-blur: error: --input {root}: holds {held} but blur.mode = "
                            "'trajectory' (the default scene) blurs single photos, so each "
                            "frame would become a sample of its own; set blur.mode = 'average'")
    assert error.endswith("or pass --frames-as-photos to blur each frame as a photo")
    assert ("GOPRO_Large_all" in error) == (layout == "gopro_large") and not out.exists()
    scene = scene_file(tmp_path, '[blur]\nmode = "kernel"\n')
    assert generate(root, out, "--limit", "2", "--scene", str(scene)) == 2
    assert "blur.mode = 'kernel'" in capsys.readouterr().err
    # asked: each frame is a photo, as before
    assert generate(root, out, "--limit", "2", "--frames-as-photos") == 0
    names = [x["name"] for x in manifest(out)]
    assert names == (["GOPR0372_07_00/blur/000000", "GOPR0372_07_00/blur/000001"]
                     if layout == "gopro_large" else ["0001/000001/000000", "0001/000001/000001"])


def test_photos_are_not_sequences_and_one_image_in_a_sharp_folder_is_no_sequence(tmp_path,
                                                                                   capsys):
    root = tmp_path / "photos"
    write_frames(root / "holiday", 2)
    write_frames(root / "portraits" / "sharp", 1)
    assert generate(root, tmp_path / "out", "--limit", "1") == 0
    assert capsys.readouterr().err.splitlines()[1:3] == [
        f"input: {root}: photos, frame sequences (<seq>/sharp/*.png) among them; 1 sequence, "
        "3 photos -> 3 samples, taking 1 (--limit)",
        "blur: trajectory: camera shake over each photo"]


def test_generate_says_what_it_found_and_the_blur_mode_before_it_starts(tmp_path,
                                                                        gopro_large_all,
                                                                        capsys, quick_scene):
    assert main(["generate", "--output", str(tmp_path / "a"), "--limit", "1", "--scene",
                 str(quick_scene), "--quiet"]) == 0
    assert capsys.readouterr().err.splitlines()[:3] == [
        "device: numpy float64 (host CPU)",
        "input: the built-in photo (coffee.png) -> 4 samples, taking 1 (--limit)",
        "blur: trajectory: camera shake over each photo"]
    scene = scene_file(tmp_path, AVERAGE.format(5) + "interpolation = 2\n")
    found = []
    report = gpu_blur.generate_set(tmp_path / "b", input=gopro_large_all, scene=scene,
                                   limit=1, on_input=found.append)
    assert report.made == 1
    (seen,) = found
    assert (seen.layout, seen.sequences, seen.images, seen.samples, seen.taking) == (
        "GOPRO_Large_all (GOPRxxxx_yy_zz/*.png)", 2, 38, 7, 1)
    assert seen.lines() == (
        f"input: {gopro_large_all}: GOPRO_Large_all (GOPRxxxx_yy_zz/*.png); 2 sequences, 38 "
        "frames -> 7 samples, taking 1 (--limit)",
        "blur: average of 5 consecutive frames per sample, the frame rate raised 2x by "
        "interpolation")
    kernel = scene_file(tmp_path, '[blur]\nmode = "kernel"\n', "k.toml")
    gpu_blur.generate_set(tmp_path / "c", scene=kernel, limit=1, on_input=found.append)
    assert found[-1].lines()[1] == ("blur: kernel: each photo convolved with a random motion "
                                    "kernel per sample")


def test_the_data_sets_read_gopro_large_all_sequences(gopro_large_all):
    frames = SharpSequences(gopro_large_all, frames=7)
    assert len(frames) == 2 + 3  # 15 // 7 and 23 // 7 windows
    index, first = frames[0]
    assert index == 0 and first.shape == (7, 16, 24, 3)
