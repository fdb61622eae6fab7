"""Which samples an input folder gives, in which order, and how many (issue 13)."""

import json
import os

import cv2
import numpy as np
import pytest

from gpu_blur.cli import main
from gpu_blur.discovery import find_samples, find_sequences


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
    assert [s.name for s in find_samples(tmp_path / "photos", "trajectory", 1).take()] == [
        "img01", "img1", "img2/a", "img9", "img10"]


def test_a_limit_makes_only_the_samples_it_takes(tmp_path):
    write_frames(tmp_path / "in" / "A" / "sharp", [f"{i:06d}.png" for i in range(9)])
    specs = find_samples(tmp_path / "in", "average", 3, samples_per_sequence=300_000_000).take(3)
    assert [(s.index, s.name) for s in specs] == [(0, "A/000000"), (1, "A/000000_1"),
                                                  (2, "A/000000_2")]
    assert find_samples(tmp_path / "in", "average", 3, samples_per_sequence=7).take(5) == (
        find_samples(tmp_path / "in", "average", 3, samples_per_sequence=7).take()[:5])
    write_frames(tmp_path / "photos", ["a.png", "b.png"])
    specs = find_samples(tmp_path / "photos", "trajectory", 1,
                         samples_per_photo=300_000_000).take(2)
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


def generate(folder, out, scene, *extra):
    return main(["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
                 "--backend", "numpy", "--quiet", *extra])


def lines_of(out):
    """The manifest's lines, read as UTF-8 (strictly) and JSON: (name, status, error)."""
    text = (out / "manifest.jsonl").read_bytes().decode()
    return [(x["name"], x["status"], x.get("error", "")) for x in map(json.loads,
                                                                      text.splitlines())]


@pytest.mark.parametrize("mode", ["trajectory", "average"])
def test_a_path_that_is_not_utf8_fails_only_its_samples(tmp_path, mode):
    # a frame or a sequence folder named in Latin-1 stopped the whole run, every resume too
    # (issue 35); its samples fail, named with \xNN for the byte, and the run goes on
    folder = tmp_path / "in"
    odd = os.fsencode(folder) + (b"/caf\xe9.png" if mode == "trajectory" else b"/caf\xe9/sharp")
    if mode == "trajectory":
        write_frames(folder, ["a.png", "b.png"])
        png = (folder / "a.png").read_bytes()
    else:
        for seq in ("A", "B"):
            write_frames(folder / seq / "sharp", ["0.png", "1.png"])
        png = (folder / "A" / "sharp" / "0.png").read_bytes()
        os.makedirs(odd)
        odd += b"/0.png"
        with open(odd[:-5] + b"1.png", "wb") as f:
            f.write(png)
    with open(odd, "wb") as f:
        f.write(png)
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nsteps = 3\n' if mode == "trajectory"
                     else '[blur]\nmode = "average"\nframes = 2\n')
    out = tmp_path / "out"
    assert generate(folder, out, scene) == 1
    lines = lines_of(out)
    name = "caf\\xe9" if mode == "trajectory" else "caf\\xe9/0"
    made = ["a", "b"] if mode == "trajectory" else ["A/0", "B/0"]
    assert [x[:2] for x in lines] == [(n, "ok") for n in made] + [(name, "failed")]
    assert "caf\\xe9" in lines[2][2] and ": the path is not UTF-8" in lines[2][2]
    assert generate(folder, out, scene, "--resume") == 1
    assert lines_of(out) == lines


def test_a_loop_of_links_fails_only_its_sample(tmp_path):
    folder = tmp_path / "in"
    write_frames(folder, ["a.png", "b.png"])
    (folder / "sub").mkdir()
    (folder / "sub" / "loop").symlink_to("loop")
    (folder / "x.png").symlink_to("x.png")
    for seq in ("A", "B"):  # and in a sequence: a frame and a folder that loop
        write_frames(folder / "seqs" / seq / "sharp", ["0.png", "1.png", "2.png", "3.png"])
    (folder / "seqs" / "A" / "sharp" / "2.png").unlink()
    (folder / "seqs" / "A" / "sharp" / "2.png").symlink_to("2.png")
    (folder / "seqs" / "C").symlink_to("C")
    scene = tmp_path / "s.toml"
    scene.write_text("[blur]\nsteps = 3\n")
    out = tmp_path / "out"
    assert generate(folder, out, scene, "--frames-as-photos") == 1  # photos and sequences
    failed = [x[0] for x in lines_of(out) if x[1] == "failed"]
    assert failed == ["seqs/A/sharp/2", "x"] and len(lines_of(out)) == 11
    scene.write_text('[blur]\nmode = "average"\nframes = 2\n')
    assert generate(folder / "seqs", tmp_path / "seqs", scene) == 1
    assert [x[:2] for x in lines_of(tmp_path / "seqs")] == [
        ("A/0", "ok"), ("A/2", "failed"), ("B/0", "ok"), ("B/2", "ok")]
