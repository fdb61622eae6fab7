"""The output folder of ``gpu-blur generate`` belongs to one run at a time, and holds only the
set's own files (issue 13)."""

import errno
import io
import json
import os
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
from conftest import files, manifest_lines

from gpu_blur import dataset
from gpu_blur.cli import main
from gpu_blur.dataset import DatasetWriter, SampleSpec
from gpu_blur.imageio import write_image
from gpu_blur.testhooks import TEST_SLEEP_AFTER


def args(photos, out, *extra):
    folder, scene = photos
    return ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--samples-per-photo", "2", "--quiet", *extra]


def test_a_second_run_on_a_folder_being_written_stops_at_once_naming_the_holder(
        tmp_path, photos, capsys):
    out = tmp_path / "out"
    env = {**os.environ, TEST_SLEEP_AFTER: "0"}  # holds the folder, asleep after sample 0
    first = subprocess.Popen([sys.executable, "-m", "gpu_blur.cli", *args(photos, out)],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not (out / "manifest.jsonl").is_file() or not (
                out / "manifest.jsonl").read_text().endswith("\n"):
            assert first.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        text = (out / "manifest.jsonl").read_text()
        for again in ([], ["--resume"], ["--overwrite"]):
            assert main(args(photos, out, *again)) == 2
            err = capsys.readouterr().err
            assert f"--output {out}: another gpu-blur run is writing it" in err
            assert f"pid {first.pid} on " in err
        assert (out / "manifest.jsonl").read_text() == text  # nothing touched
    finally:
        first.kill()  # SIGKILL: its lock file stays, but locks nothing
        first.wait()
    assert (out / dataset.LOCK).is_file()
    assert main(args(photos, out, "--resume")) == 0
    reference = tmp_path / "reference"
    assert main(args(photos, reference)) == 0
    assert files(out) == files(reference) and manifest_lines(out) == manifest_lines(reference)


def test_temporary_names_hold_the_process_id(tmp_path, monkeypatch):
    written = []
    real = cv2.imwrite
    monkeypatch.setattr(cv2, "imwrite", lambda name, data: written.append(name)
                        or real(name, data))
    write_image(tmp_path / "x.png", np.zeros((2, 2, 3)), 8)
    assert written == [str(tmp_path / f".x.png.{os.getpid()}.part.png")]
    assert [p.name for p in tmp_path.iterdir()] == ["x.png"]


def test_resume_removes_only_temporary_files_of_its_own_naming(tmp_path, photos):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "2")) == 0
    ours = [out / "blur" / ".000002_b_0.png.4242.part.png", out / ".manifest.jsonl.17.part",
            out / "params" / ".000003_b_1.npz.9.part.npz"]
    theirs = [out / ".notes.part", out / ".run.json.bak.part", out / "draft.part"]
    for path in ours + theirs:
        path.write_bytes(b"x")
    assert main(args(photos, out, "--resume", "--limit", "2")) == 0
    assert not any(p.exists() for p in ours)
    assert all(p.exists() for p in theirs)


def test_overwrite_replaces_the_whole_older_set(tmp_path, photos):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    assert len(list((out / "blur").iterdir())) == 4
    assert main(args(photos, out, "--overwrite", "--limit", "1")) == 0
    reference = tmp_path / "reference"
    assert main(args(photos, reference, "--limit", "1")) == 0
    assert files(out) == files(reference)  # no image of the older, longer set is left
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()


def test_resume_removes_sample_files_no_manifest_line_lists(tmp_path, photos):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    lines = (out / "manifest.jsonl").read_text().splitlines(keepends=True)
    (out / "manifest.jsonl").write_text("".join(lines[:2]))  # as if killed after sample 1
    assert main(args(photos, out, "--resume", "--limit", "2")) == 0
    reference = tmp_path / "reference"
    assert main(args(photos, reference, "--limit", "2")) == 0
    assert files(out) == files(reference)


@pytest.mark.parametrize("again", [[], ["--resume"], ["--overwrite"]])
def test_files_gpu_blur_did_not_write_in_the_sets_folders_are_never_removed(
        tmp_path, photos, capsys, again):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    before = files(out)
    (out / "blur" / "notes.txt").write_text("mine")
    (out / "sharp" / "holiday.png").write_bytes(b"mine")
    capsys.readouterr()
    assert main(args(photos, out, *again)) == 2
    err = capsys.readouterr().err
    assert f"{out / 'blur' / 'notes.txt'}, {out / 'sharp' / 'holiday.png'}: not a file " \
           "gpu-blur wrote" in err and "move these out, or choose another --output" in err
    assert files(out) == {**before, "blur/notes.txt": b"mine", "sharp/holiday.png": b"mine"}


def test_a_folder_with_sample_files_but_no_manifest_needs_resume_or_overwrite(
        tmp_path, photos, capsys):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    (out / "manifest.jsonl").unlink()
    (out / "run.json").unlink()
    assert main(args(photos, out)) == 2
    err = capsys.readouterr().err
    assert f"--output {out} holds a set already (12 sample file(s) in blur, sharp, params)" in err
    assert main(args(photos, out, "--overwrite", "--limit", "1")) == 0
    assert len(list((out / "blur").iterdir())) == 1


def test_an_output_folder_inside_the_input_is_not_read_back_as_input(tmp_path, photos,
                                                                     capsys):
    folder, scene = photos
    out = folder / "set"
    assert main(args(photos, out)) == 0
    assert main(args(photos, out, "--resume")) == 0
    assert "4 of 4 samples done, 0 to make" in capsys.readouterr().out
    assert {x["inputs"][0] for x in manifest_lines(out)} == {str(folder / "a.png"),
                                                             str(folder / "b.png")}


@pytest.mark.parametrize("inside", [False, True])
def test_an_input_that_is_the_output_or_inside_it_is_refused(tmp_path, photos, capsys,
                                                             inside):
    folder, _ = photos
    out = folder.parent if inside else folder
    before = sorted(folder.iterdir())
    assert main(args(photos, out)) == 2
    assert f"--input {folder} is --output {out} or lies inside it" in capsys.readouterr().err
    assert sorted(folder.iterdir()) == before and not (out / "blur").exists()


class FullDisk(io.StringIO):
    """A manifest on a full disk: lines go into a buffer that can never be written out."""

    def flush(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def close(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_keeps_the_message_that_names_the_sample_and_the_way_out(
        tmp_path, photos, capsys, monkeypatch):
    opened = DatasetWriter.__init__

    def on_a_full_disk(self, *a, **k):
        opened(self, *a, **k)
        self.manifest.close()
        self.manifest = FullDisk()

    monkeypatch.setattr(DatasetWriter, "__init__", on_a_full_disk)
    out = tmp_path / "out"
    assert main(args(photos, out)) == 2
    err = capsys.readouterr().err
    assert f"--output {out}: cannot write sample 0 (a_0): [Errno {errno.ENOSPC}] No space " \
           "left on device; the samples finished so far are kept" in err
    assert "run the same command with --resume" in err
    monkeypatch.undo()
    writer = DatasetWriter(out, 8, overwrite=True)  # and the folder's lock was released
    writer.manifest.close()
    writer.manifest = FullDisk()
    with pytest.raises(OSError, match=f"{out / 'manifest.jsonl'}: cannot write its last lines "
                                      r"\(No space left on device\); the samples it lists"):
        writer.close()
    DatasetWriter(out, 8, overwrite=True).close()  # released by the failing close too


def test_manifest_lines_are_written_in_sample_order_whatever_order_samples_finish(tmp_path):
    specs = [SampleSpec(i, f"p{i}", (tmp_path / f"p{i}.png",)) for i in range(4)]
    writer = DatasetWriter(tmp_path / "out", 8, specs=specs)
    for i in (2, 0, 3):  # as workers finish them; sample 1 is still being made
        writer.fail(specs[i], "bad input", {})
    writer.close()  # a run stopped here: 2 and 3 wait for 1, so only 0 is listed
    lines = (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()
    assert [json.loads(x)["index"] for x in lines] == [0]
    writer = DatasetWriter(tmp_path / "out", 8, specs=specs, overwrite=True)
    for i in (3, 1, 2, 0):
        writer.fail(specs[i], "bad input", {})
    writer.close()
    lines = (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()
    assert [json.loads(x)["index"] for x in lines] == [0, 1, 2, 3]
