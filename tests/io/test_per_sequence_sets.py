"""Video sets (issue 38): blur.stride places a sequence's windows, blur.draws = "per-sequence"
gives all of them one draw of the camera's settings, the manifest says each window's sequence
and place, and resume, --devices and Ray write a serial run's bytes."""

import json

import cv2
import numpy as np
import pytest
from conftest import manifest_lines

from gpu_blur.cli import main
from gpu_blur.datasets import SharpSequences
from gpu_blur.discovery import find_samples

#: what a window's manifest line says of its place
PLACE = ("sequence", "sequence_index", "window", "first_frame")
#: the per-image draws of the scene below (saturation on, RAW round trip, JPEG)
DRAWN = ("alpha", "pattern", "red_gain", "blue_gain", "shot_noise_k", "read_noise_std",
         "jpeg_quality")


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """Two GoPro-style sequences of 7 frames, 16 x 20: ``moving`` (random frames) and
    ``still`` (one frame 7 times, so its windows differ only by their draws), and the scene
    file maker."""
    root = tmp_path_factory.mktemp("video")
    rng = np.random.default_rng(4)
    still = rng.integers(0, 256, (16, 20, 3), np.uint8)
    for name in ("moving", "still"):
        folder = root / "in" / name / "sharp"
        folder.mkdir(parents=True)
        for i in range(7):
            frame = rng.integers(0, 256, (16, 20, 3), np.uint8) if name == "moving" else still
            cv2.imwrite(str(folder / f"{i:03d}.png"), frame)

    def scene(**blur):
        path = root / f"scene_{'_'.join(f'{k}{v}' for k, v in blur.items())}.toml"
        keys = "".join(f"{k} = {json.dumps(v)}\n" for k, v in blur.items())
        path.write_text('[blur]\nmode = "average"\nframes = 3\n' + keys
                        + '[saturation]\nmode = "on"\n[output]\njpeg_quality = [40, 95]\n')
        return path

    return root / "in", scene


def args(video, out, *extra, **blur):
    folder, scene = video
    return ["generate", "--input", str(folder), "--output", str(out), "--seed", "3",
            "--scene", str(scene(**blur)), "--quiet", *extra]


PER_SEQUENCE = {"stride": 2, "draws": "per-sequence"}


@pytest.fixture(scope="module")
def serial(video, tmp_path_factory):
    """The per-sequence set made in one process (3 windows of each sequence)."""
    out = tmp_path_factory.mktemp("serial") / "out"
    assert main(args(video, out, "--io-threads", "1", **PER_SEQUENCE)) == 0
    return out


def files(out):
    """{relative path: bytes} of every sample file of the set in ``out`` (in its folders)."""
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.parent != out}


def drawn(line):
    return {k: line["params"][k] for k in DRAWN}


def image(out, path):
    return cv2.imread(str(out / path), cv2.IMREAD_UNCHANGED)


def assert_same_set(out, reference):
    assert files(out) == files(reference)
    for name in ("manifest.jsonl", "run.json"):
        assert (out / name).read_bytes() == (reference / name).read_bytes()


def test_windows_of_a_sequence_share_their_draws_and_differ_in_their_noise(serial):
    lines = manifest_lines(serial)
    assert [tuple(x[k] for k in PLACE) for x in lines] == [
        ("moving", 0, 0, 0), ("moving", 0, 1, 2), ("moving", 0, 2, 4),
        ("still", 1, 0, 0), ("still", 1, 1, 2), ("still", 1, 2, 4)]
    assert [x["name"] for x in lines] == ["moving/000", "moving/002", "moving/004",
                                          "still/000", "still/002", "still/004"]
    moving, still = lines[:3], lines[3:]
    for sequence in (moving, still):
        assert all(drawn(x) == drawn(sequence[0]) for x in sequence)
    assert all(drawn(moving[0])[k] != drawn(still[0])[k]
               for k in ("alpha", "red_gain", "blue_gain", "shot_noise_k", "read_noise_std"))
    # the still sequence's windows: the same frames and draws, so only the noise tells them
    # apart, and it does (keyed by the sample index)
    sharp = [image(serial, x["sharp"]) for x in still]
    blurred = [image(serial, x["blurred"]).astype(int) for x in still]
    assert all(np.array_equal(s, sharp[0]) for s in sharp)
    for a, b in ((0, 1), (1, 2), (0, 2)):
        assert np.count_nonzero(blurred[a] != blurred[b]) > blurred[a].size // 4


def test_per_sample_draws_are_the_draws_of_before(video, tmp_path):
    before, now = tmp_path / "before", tmp_path / "now"
    assert main(args(video, before)) == 0  # a scene without the new keys
    assert main(args(video, now, draws="per-sample", stride=0)) == 0
    assert files(now) == files(before)
    old, new = manifest_lines(before), manifest_lines(now)
    assert [x["params"] for x in new] == [x["params"] for x in old]
    # windows side by side, as before: 7 // 3 per sequence; each its own draws
    assert [(x["sequence"], x["window"], x["first_frame"]) for x in new] == [
        ("moving", 0, 0), ("moving", 1, 3), ("still", 0, 0), ("still", 1, 3)]
    assert drawn(new[0]) != drawn(new[1]) and drawn(new[2]) != drawn(new[3])


def test_a_stride_overlaps_windows_and_the_set_says_so(video, tmp_path, capsys):
    out = tmp_path / "out"
    folder, _ = video
    assert main(args(video, out, stride=1)[:-1]) == 0  # without --quiet: the lines it prints
    printed = capsys.readouterr()
    printed = printed.out + printed.err
    assert "2 sequences, 14 frames -> 10 samples" in printed
    assert "windows 1 frames apart (blur.stride)" in printed
    lines = manifest_lines(out)
    assert [x["first_frame"] for x in lines] == [0, 1, 2, 3, 4] * 2
    assert [len(x["inputs"]) for x in lines] == [3] * 10
    assert lines[1]["inputs"][0].endswith("001.png")
    assert find_samples(folder, "average", 3, stride=9).total == 2  # beyond: the first only


def test_a_stride_and_samples_per_sequence_are_refused_together(video, tmp_path, capsys):
    assert main(args(video, tmp_path / "out", "--samples-per-sequence", "2", stride=2)) == 2
    err = capsys.readouterr().err
    assert "--samples-per-sequence 2 and blur.stride = 2" in err and "give one" in err


def test_a_per_sequence_set_resumes_to_the_serial_run_s_bytes(video, serial, tmp_path):
    out = tmp_path / "out"
    assert main(args(video, out, "--limit", "2", **PER_SEQUENCE)) == 0  # mid-sequence
    lines = (out / "manifest.jsonl").read_text().splitlines(keepends=True)
    (out / "manifest.jsonl").write_text(lines[0])  # the second window made again, too
    assert main(args(video, out, "--resume", **PER_SEQUENCE)) == 0
    assert_same_set(out, serial)


def test_a_set_made_before_the_window_keys_resumes(video, tmp_path):
    out = tmp_path / "out"
    assert main(args(video, out, "--limit", "2")) == 0
    run = json.loads((out / "run.json").read_text())
    for key in ("draws", "stride"):  # what a set made before them records
        del run["scene"]["blur"][key]
    (out / "run.json").write_text(json.dumps(run, indent=1) + "\n")
    assert main(args(video, out, "--resume")) == 0
    assert len(manifest_lines(out)) == 4
    assert main(args(video, out, "--resume", draws="per-sequence")) == 2  # that changes draws


@pytest.mark.slow
def test_device_workers_write_the_serial_run_s_per_sequence_set(video, serial, tmp_path):
    out = tmp_path / "out"
    assert main(args(video, out, "--devices", "numpy,numpy", **PER_SEQUENCE)) == 0
    assert_same_set(out, serial)


@pytest.mark.slow
def test_ray_writes_the_serial_run_s_per_sequence_set(video, serial, tmp_path):
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        out = tmp_path / "out"
        assert main(args(video, out, "--ray", "auto", "--ray-batch", "2", **PER_SEQUENCE)) == 0
    finally:
        ray.shutdown()
    assert_same_set(out, serial)


def test_sharp_sequences_give_the_windows_a_set_makes_and_their_place(video, serial):
    folder, _ = video
    data = SharpSequences(folder, 3, stride=2)
    lines = manifest_lines(serial)
    assert len(data) == len(lines)
    for index, line in enumerate(lines):
        assert data.window(index).manifest() == {k: line[k] for k in PLACE}
    assert data.window(4).first_frame == 2 and data[4][1].shape == (3, 16, 20, 3)
    with pytest.raises(ValueError, match="both place the windows"):
        SharpSequences(folder, 3, stride=2, samples_per_sequence=2)
    with pytest.raises(ValueError, match="stride = -1"):
        SharpSequences(folder, 3, stride=-1)
