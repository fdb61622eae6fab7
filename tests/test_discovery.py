"""Which samples an input folder gives, in which order, and how many (issue 13)."""

import json

import cv2
import numpy as np
import pytest

from gpu_blur.cli import main
from gpu_blur.dataset import discover, find_sequences


def write_frames(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(len(names))
    for name in names:
        cv2.imwrite(str(folder / name), rng.integers(0, 256, (16, 16, 3), np.uint8))


def test_frames_numbered_without_zeros_are_averaged_in_numeric_order(tmp_path):
    write_frames(tmp_path / "in" / "A" / "sharp", [f"{i}.png" for i in range(12)])
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 12\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--scene", str(scene), "--quiet"]) == 0
    (line,) = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    frames = [p.rsplit("/", 1)[1] for p in line["inputs"]]
    assert frames == [f"{i}.png" for i in range(12)]  # text order: 0, 1, 10, 11, 2, ...
    assert frames[len(frames) // 2] == "6.png"  # the sharp reference's frame


def test_sequences_and_photos_are_in_natural_order(tmp_path):
    for seq in ("s10", "s2", "s1"):
        write_frames(tmp_path / "seqs" / seq / "sharp", ["9.png", "10.png"])
    assert [(name, [p.name for p in frames]) for name, frames in
            find_sequences(tmp_path / "seqs")] == [
        ("s1", ["9.png", "10.png"]), ("s2", ["9.png", "10.png"]), ("s10", ["9.png", "10.png"])]
    write_frames(tmp_path / "photos", ["img10.png", "img9.png", "img01.png", "img1.png"])
    write_frames(tmp_path / "photos" / "img2", ["a.png"])
    assert [s.name for s in discover(tmp_path / "photos", "trajectory", 1)] == [
        "img01", "img1", "img2/a", "img9", "img10"]


def test_a_limit_makes_only_the_samples_it_takes(tmp_path):
    write_frames(tmp_path / "in" / "A" / "sharp", [f"{i:06d}.png" for i in range(9)])
    specs = discover(tmp_path / "in", "average", 3, samples_per_sequence=300_000_000, limit=3)
    assert [(s.index, s.name) for s in specs] == [(0, "A/000000"), (1, "A/000000_1"),
                                                  (2, "A/000000_2")]
    assert discover(tmp_path / "in", "average", 3, samples_per_sequence=7, limit=5) == (
        discover(tmp_path / "in", "average", 3, samples_per_sequence=7)[:5])
    write_frames(tmp_path / "photos", ["a.png", "b.png"])
    specs = discover(tmp_path / "photos", "trajectory", 1, samples_per_photo=300_000_000,
                     limit=2)
    assert [(s.index, s.name) for s in specs] == [(0, "a_0"), (1, "a_1")]


@pytest.mark.parametrize("option", ["--samples-per-photo", "--samples-per-sequence"])
def test_a_sample_count_beyond_reason_is_refused_at_once_unless_limited(tmp_path, capsys,
                                                                        option):
    sequence = option == "--samples-per-sequence"
    write_frames(tmp_path / "in" / "A" / "sharp", [f"{i}.png" for i in range(9 if sequence
                                                                              else 1)])
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 3\nsteps = 3\n' if sequence
                     else "[blur]\nsteps = 3\n")
    command = ["generate", "--input", str(tmp_path / "in"), "--output", str(tmp_path / "out"),
               "--scene", str(scene), "--quiet", option, "300000000"]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert "the input gives 300,000,000 samples, more than the 10,000,000 one run makes" in err
    assert "pass --limit" in err and not (tmp_path / "out").exists()
    assert main([*command, "--limit", "2"]) == 0
