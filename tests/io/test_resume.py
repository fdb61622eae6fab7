"""A killed or partly failed ``gpu-blur generate`` resumes to exactly the set an uninterrupted
run makes, without touching finished samples (issue 5)."""

import hashlib
import json
import os
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
from conftest import files, manifest_lines

import gpu_blur
from gpu_blur.cli import main
from gpu_blur.dataset import DatasetWriter
from gpu_blur.testhooks import TEST_SLEEP_AFTER


def args(photos, out, *extra):
    folder, scene = photos
    return ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--samples-per-photo", "4", "--quiet", *extra]


def stamps(out, lines):
    """(mtime in ns, inode) of each file of the given manifest lines: a rewrite changes both."""
    paths = [out / x[k] for x in lines for k in ("blurred", "sharp", "arrays")]
    return {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in paths}


def complete_lines(path):
    text = path.read_text() if path.exists() else ""
    return text.count("\n")


def test_a_killed_run_resumes_to_the_set_an_uninterrupted_run_makes(tmp_path, photos):
    reference = tmp_path / "reference"
    assert main(args(photos, reference)) == 0
    expected = manifest_lines(reference)
    assert len(expected) == 8

    out = tmp_path / "out"
    log = (tmp_path / "killed.log").open("w")
    env = {**os.environ, TEST_SLEEP_AFTER: "2"}  # it sleeps once sample 2 is recorded
    run = subprocess.Popen([sys.executable, "-m", "gpu_blur.cli", *args(photos, out)],
                           env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while complete_lines(out / "manifest.jsonl") < 3:
            assert run.poll() is None, (tmp_path / "killed.log").read_text()
            assert time.monotonic() < deadline, "the run never reached sample 2"
            time.sleep(0.05)
        assert run.poll() is None  # asleep after sample 2: killed mid-way
    finally:
        run.kill()  # SIGKILL
        run.wait()
        log.close()
    done = manifest_lines(out)
    assert [x["index"] for x in done] == [0, 1, 2] and done == expected[:3]
    before = stamps(out, done)

    # what a kill at a worse moment leaves: a torn last line, temporary files (named with the
    # killed run's pid, which the lock file records), and the next sample's image written
    # (complete or not) without its manifest line
    with (out / "manifest.jsonl").open("a") as f:
        f.write(json.dumps(expected[3])[:60])
    for path in (expected[3]["blurred"], expected[3]["arrays"]):
        name = os.path.basename(path)
        (out / path).with_name(f".{name}.{run.pid}.part{name[-4:]}").write_bytes(b"x")
    (out / expected[3]["blurred"]).write_bytes(b"\x89PNG half an image")

    assert main(args(photos, out, "--resume")) == 0
    assert stamps(out, done) == before  # finished samples untouched
    assert manifest_lines(out) == expected
    assert files(out) == files(reference)  # byte for byte, and no stray temporary file


def test_resume_retries_failed_samples_and_keeps_the_rest(tmp_path, photos, capsys):
    folder, _ = photos
    good = (folder / "b.png").read_bytes()
    (folder / "b.png").write_bytes(good[:50])
    out = tmp_path / "out"
    assert main(args(photos, out)) == 1
    first = manifest_lines(out)
    assert [x["status"] for x in first] == ["ok"] * 4 + ["failed"] * 4
    assert "truncated PNG" in first[4]["error"]
    assert main(args(photos, out, "--resume")) == 1  # still broken: tried again, still listed
    assert manifest_lines(out) == first
    before = stamps(out, first[:4])
    capsys.readouterr()

    (folder / "b.png").write_bytes(good)
    assert main(args(photos, out, "--resume")) == 0
    assert "4 of 8 samples done, 4 to make (4 failed before" in capsys.readouterr().out
    assert stamps(out, first[:4]) == before
    reference = tmp_path / "reference"
    assert main(args(photos, reference)) == 0
    assert manifest_lines(out) == manifest_lines(reference)
    assert files(out) == files(reference)


def test_resuming_a_finished_set_changes_nothing_and_an_empty_folder_starts_one(tmp_path,
                                                                              photos):
    out = tmp_path / "out"
    assert main(args(photos, out, "--resume", "--limit", "2")) == 0  # nothing there yet
    lines = manifest_lines(out)
    before, text = stamps(out, lines), (out / "manifest.jsonl").read_text()
    assert main(args(photos, out, "--resume", "--limit", "2")) == 0
    assert stamps(out, lines) == before and (out / "manifest.jsonl").read_text() == text
    assert main(args(photos, out, "--resume", "--limit", "3")) == 0  # a larger limit adds
    assert [x["index"] for x in manifest_lines(out)] == [0, 1, 2]


@pytest.mark.parametrize("change, message", [
    (["--seed", "7"], "another --seed: seed = 0 (this run: 7)"),
    (["--samples-per-photo", "2"], "another --samples-per-photo: samples_per_photo = 4 "
                                   "(this run: 2)"),
    ("scene", "another --scene: scene.noise.model = 'poisson-gaussian' (this run: 'none')"),
    ("input", "another --input: input = "),
])
def test_resume_refuses_a_run_with_other_settings(tmp_path, photos, capsys, change, message):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1")) == 0
    text = (out / "manifest.jsonl").read_text()
    folder, scene = photos
    if change == "scene":
        scene.write_text('[blur]\nsteps = 3\n[noise]\nmodel = "none"\n')
        change = []
    elif change == "input":
        other = tmp_path / "other"
        other.mkdir()
        (other / "a.png").write_bytes((folder / "a.png").read_bytes())
        change, photos = [], (other, scene)
    capsys.readouterr()
    assert main(args(photos, out, "--limit", "1", "--resume", *change)) == 2
    err = capsys.readouterr().err
    assert message in err and f"resume with what {out / 'run.json'} records" in err
    assert (out / "manifest.jsonl").read_text() == text


def test_resume_refuses_another_backend(tmp_path):
    run = {"seed": 0, "scene": {}, "backend": "numpy", "input": "in", "samples_per_photo": 1}
    DatasetWriter(tmp_path, 8, run).close()
    with pytest.raises(ValueError, match="another --backend: backend = 'numpy' "
                                         r"\(this run: 'opencl'\)"):
        DatasetWriter(tmp_path, 8, {**run, "backend": "opencl"}, resume=True)


def test_resume_refuses_when_the_input_folder_changed_under_the_indices(tmp_path, photos,
                                                                        capsys):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    folder, _ = photos
    (folder / "a.png").rename(folder / "c.png")  # b's samples now come first
    failed_before = (out / "manifest.jsonl").read_text()
    assert main(args(photos, out, "--resume")) == 2
    err = capsys.readouterr().err
    assert "sample 0 of" in err and "is 'a_0'" in err and "now gives 'b_0'" in err
    assert "the input folder changed" in err
    assert (out / "manifest.jsonl").read_text() == failed_before


def test_an_existing_set_needs_resume_or_overwrite(tmp_path, photos, capsys):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1")) == 0
    assert main(args(photos, out, "--limit", "1")) == 2
    err = capsys.readouterr().err
    assert "--resume to finish that set" in err and "--overwrite to replace it" in err
    (out / "run.json").unlink()
    assert main(args(photos, out, "--limit", "1", "--resume")) == 2
    assert "run.json is missing" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: not allowed together
        main(args(photos, out, "--resume", "--overwrite"))


def test_resume_trusts_no_manifest_line_that_names_other_files_or_indices(tmp_path, photos,
                                                                           capsys):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "4")) == 0
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    outside = tmp_path / "outside.png"
    outside.write_bytes((out / lines[0]["blurred"]).read_bytes())
    lines[0]["blurred"] = "../outside.png"  # exists, but outside the set
    lines[1]["sharp"] = str(outside)  # absolute
    lines[2]["arrays"] = lines[3]["arrays"]  # another sample's file
    forged = [{**lines[3], "index": i} for i in (-1, True, 10**30, 8)]  # 8 samples: 0 to 7
    (out / "manifest.jsonl").write_text(
        "".join(json.dumps(x) + "\n" for x in [*lines, *forged]))
    capsys.readouterr()
    assert main(args(photos, out, "--resume", "--limit", "4")) == 0
    assert "1 of 4 samples done, 3 to make (0 failed before, to retry; 4 torn" in (
        capsys.readouterr().out)
    assert outside.exists()  # neither trusted nor removed
    reference = tmp_path / "reference"
    assert main(args(photos, reference, "--limit", "4")) == 0
    assert manifest_lines(out) == manifest_lines(reference)
    assert files(out) == files(reference)


CAMERA = ("[color]\ncamera_to_linear = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n"
          "[white_balance]\nred = [1.8, 2.2]\nblue = 1.6\n")


@pytest.mark.parametrize("key", ["camera.name", "blur.kernel"])
def test_resume_refuses_a_camera_or_kernel_file_whose_contents_changed(tmp_path, photos,
                                                                       capsys, key):
    folder, scene = photos
    if key == "camera.name":
        changed = tmp_path / "cam.toml"
        changed.write_text(CAMERA)
        scene.write_text('[camera]\nname = "cam.toml"\n[blur]\nsteps = 3\n')
    else:
        changed = tmp_path / "k.npy"
        np.save(changed, np.ones((3, 3)))
        scene.write_text('[blur]\nmode = "kernel"\nkernel = "k.npy"\n')
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1")) == 0
    old = hashlib.sha256(changed.read_bytes()).hexdigest()
    if key == "camera.name":
        changed.write_text(CAMERA.replace("blue = 1.6", "blue = 1.7"))
    else:
        np.save(changed, np.ones((5, 5)))
    new = hashlib.sha256(changed.read_bytes()).hexdigest()
    capsys.readouterr()
    assert main(args(photos, out, "--limit", "2", "--resume")) == 2
    assert (f"made with another camera or kernel file contents: files.{key} = '{old}' "
            f"(this run: '{new}')") in capsys.readouterr().err
    assert len(manifest_lines(out)) == 1


@pytest.mark.parametrize("key, recorded, message", [
    ("device", "opencl:1:0 an older GPU (a runtime), float32",
     "another device behind --backend: device = 'opencl:1:0 an older GPU (a runtime), "
     "float32' (this run: 'numpy float64 (host CPU)')"),
    ("libraries", {"gpu_blur": gpu_blur.__version__, "numpy": "1.0.0",
                   "opencv": cv2.__version__},
     f"another library version: libraries.numpy = '1.0.0' (this run: '{np.__version__}')"),
])
def test_resume_refuses_another_device_or_library_version(tmp_path, photos, capsys, key,
                                                          recorded, message):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1")) == 0
    run = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**run, key: recorded}))
    capsys.readouterr()
    assert main(args(photos, out, "--limit", "2", "--resume")) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("edit, message", [
    ({"scene": 5}, "another --scene: scene = 5 (this run: {'blur': "),
    ({"scene": {"blur": 5}}, "another --scene: scene.blur = 5 (this run: {"),
    ({"libraries": [1]}, "another library version: libraries = [1] (this run: {"),
    ([1, 2], "holds a JSON list, not the object gpu-blur writes"),
])
def test_a_hand_edited_run_json_is_refused_with_a_message(tmp_path, photos, capsys, edit,
                                                          message):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1")) == 0
    run = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**run, **edit} if isinstance(edit, dict)
                                             else edit))
    capsys.readouterr()
    assert main(args(photos, out, "--limit", "1", "--resume")) == 2
    err = capsys.readouterr().err
    assert message in err and "with --overwrite" in err


def test_resume_refuses_a_missing_manifest_and_removes_no_sample(tmp_path, photos, capsys):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "3")) == 0
    (out / "manifest.jsonl").unlink()
    before = files(out)
    assert main(args(photos, out, "--resume", "--limit", "1")) == 2
    assert f"--resume: {out / 'manifest.jsonl'} is missing" in capsys.readouterr().err
    assert files(out) == before


def test_resume_refuses_a_manifest_damaged_before_its_last_line(tmp_path, photos, capsys):
    # a kill cuts only the last line; a line that is not JSON before it is damage, and
    # dropping it would remove a finished sample
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "3")) == 0
    lines = (out / "manifest.jsonl").read_text().splitlines(keepends=True)
    lines[1] = lines[1][:40] + "\n"
    (out / "manifest.jsonl").write_text("".join(lines))
    before = files(out)
    assert main(args(photos, out, "--resume", "--limit", "3")) == 2
    assert "manifest.jsonl, line 2, is not JSON: the manifest is damaged" in (
        capsys.readouterr().err)
    assert files(out) == before


@pytest.mark.parametrize("damage", ["empty", "cut"])
def test_resume_makes_again_a_sample_whose_file_was_cut_short(tmp_path, photos, capsys,
                                                                damage):
    # each line records its files' sizes: a file a crash left empty or short is made again
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "3")) == 0
    lines = manifest_lines(out)
    assert lines[1]["bytes"]["blurred"] == (out / lines[1]["blurred"]).stat().st_size
    victim = out / lines[1]["sharp"]
    data = victim.read_bytes()
    victim.write_bytes(b"" if damage == "empty" else data[:len(data) // 2])
    capsys.readouterr()
    assert main(args(photos, out, "--resume", "--limit", "3")) == 0
    assert "2 of 3 samples done, 1 to make" in capsys.readouterr().out
    assert victim.read_bytes() == data


def test_a_set_made_before_interpolation_regions_resumes_where_they_do_not_apply(tmp_path,
                                                                                photos):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    run = json.loads((out / "run.json").read_text())
    del run["scene"]["blur"]["interpolation_region"]  # as a set of the version before wrote it
    (out / "run.json").write_text(json.dumps(run))
    assert main(args(photos, out, "--resume")) == 0  # camera shake: regions do not apply


def test_an_auto_interpolation_set_made_before_regions_resumes_only_without_them():
    from gpu_blur.run_record import set_keys

    old = {"blur": {"mode": "average", "interpolation": "auto"}}
    with_regions = {"blur": {"mode": "average", "interpolation": "auto",
                             "interpolation_region": 64}}
    without = {"blur": {"mode": "average", "interpolation": "auto", "interpolation_region": 0}}
    assert set_keys(old) != set_keys(with_regions)  # the old set had one factor per gap
    assert set_keys(old) == set_keys(without)


def backend_args(photos, out, *extra):
    return args(photos, out, "--backend", "numpy", *extra)


@pytest.mark.parametrize("damage", ["empty", "all NUL", "NUL tail", "bad line", "bad last line"])
def test_resume_refuses_a_damaged_manifest_and_removes_nothing(tmp_path, photos, capsys,
                                                               damage):
    # after a power loss the manifest may be empty or NULs while every sample is there; the
    # input changed too (a.png renamed): a resume once removed all 8 samples (issue 35)
    out = tmp_path / "out"
    assert main(backend_args(photos, out)) == 0
    manifest = out / "manifest.jsonl"
    text = manifest.read_bytes()
    lines = text.splitlines(keepends=True)
    manifest.write_bytes({"empty": b"", "all NUL": b"\0" * len(text),
                          "NUL tail": b"".join(lines[:3]) + b"\0" * 700,
                          "bad line": b"".join([*lines[:2], b"{}}\n", *lines[3:]]),
                          "bad last line": b"".join(lines[:-1]) + b"{}}\n"}[damage])
    folder, _ = photos
    (folder / "a.png").rename(folder / "c.png")
    before, damaged = files(out), manifest.read_bytes()
    capsys.readouterr()
    assert main(backend_args(photos, out, "--resume")) == 2
    (error,) = [x for x in capsys.readouterr().err.splitlines() if "error" in x]
    assert f"gpu-blur: error: --resume: {manifest}" in error and "--overwrite" in error
    assert "nothing was changed" in error
    assert files(out) == before and manifest.read_bytes() == damaged


def test_resume_refuses_to_drop_finished_samples_the_input_no_longer_gives(tmp_path, photos,
                                                                           capsys):
    out = tmp_path / "out"
    assert main(backend_args(photos, out)) == 0
    folder, _ = photos
    (folder / "b.png").unlink()  # the input now gives samples 0 to 3 only
    before, text = files(out), (out / "manifest.jsonl").read_text()
    capsys.readouterr()
    assert main(backend_args(photos, out, "--resume")) == 2
    assert f"manifest.jsonl lists none of 12 sample file(s) in {out} that this run would not " \
           "make again (blur/000004_b_0.png, " in capsys.readouterr().err
    assert files(out) == before and (out / "manifest.jsonl").read_text() == text


def test_a_resume_that_remakes_earlier_samples_leaves_the_manifest_in_sample_order(tmp_path,
                                                                                   photos):
    folder, _ = photos
    good = (folder / "a.png").read_bytes()
    (folder / "a.png").write_bytes(good[:50])  # samples 0 to 3 fail, 4 to 7 are made
    out = tmp_path / "out"
    assert main(backend_args(photos, out)) == 1
    (folder / "a.png").write_bytes(good)
    assert main(backend_args(photos, out, "--resume")) == 0
    reference = tmp_path / "reference"
    assert main(backend_args(photos, reference)) == 0
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()


def test_an_emptied_manifest_over_the_same_input_makes_every_sample_again(tmp_path, photos):
    # a manifest emptied before its first line (a run stopped early) or by a power loss: every
    # file there is one this run makes again, so it is replaced, never just removed
    out = tmp_path / "out"
    assert main(backend_args(photos, out)) == 0
    (out / "manifest.jsonl").write_bytes(b"")
    assert main(backend_args(photos, out, "--resume")) == 0
    reference = tmp_path / "reference"
    assert main(backend_args(photos, reference)) == 0
    assert files(out) == files(reference)
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()
