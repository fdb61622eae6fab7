"""The output folder of ``gpu-blur generate`` belongs to one run at a time, and holds only the
set's own files (issue 13)."""

import errno
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import files, manifest_lines

import gpu_blur.file_writing
import gpu_blur.image_arrays
import gpu_blur.image_reading
from gpu_blur import dataset
from gpu_blur.cli import main
from gpu_blur.dataset import DatasetWriter
from gpu_blur.discovery import SampleSpec
from gpu_blur.file_writing import write_image
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
    real = gpu_blur.file_writing.write_new
    monkeypatch.setattr(gpu_blur.file_writing, "write_new", lambda path, data: written.append(path)
                        or real(path, data))
    write_image(tmp_path / "x.png", np.zeros((2, 2, 3)), 8)
    assert written == [tmp_path / f".x.png.{os.getpid()}.part.png"]
    assert [p.name for p in tmp_path.iterdir()] == ["x.png"]


@pytest.mark.parametrize("write", [
    lambda path: write_image(path, np.zeros((2, 2, 3)), 8),
    lambda path: gpu_blur.file_writing.write_text(path, "{}"),
    lambda path: dataset.save_arrays(path, {"kernel": np.ones((3, 3))}),
], ids=["image", "text", "arrays"])
def test_a_link_planted_at_a_temporary_name_is_not_written_through(tmp_path, write):
    # someone who can write the output folder links the temporary name to another file: the
    # link is replaced by a new file, and the other file keeps its contents
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    final = out / "x.png"
    gpu_blur.file_writing.temporary_path(final).symlink_to(victim)
    write(final)
    assert victim.read_text() == "precious"
    assert final.is_file() and not final.is_symlink()
    assert sorted(p.name for p in out.iterdir()) == ["x.png"]


def test_only_temporary_files_of_a_run_the_lock_file_records_are_removed(tmp_path, photos,
                                                                         capsys):
    # a temporary name holds the pid of the run that made it, and the lock file records the
    # runs on the folder: a file that merely looks like one is never removed (issue 35)
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "2")) == 0
    pid = os.getpid()  # main() ran in this process
    # a finished run leaves no lock file: this one records a run of this pid killed mid-way
    (out / dataset.LOCK).write_text(f"pid {pid} on here, started 2020-01-01\n")
    ours = [out / "blur" / f".000002_b_0.png.{pid}.part.png",
            out / f".manifest.jsonl.{pid}.part.jsonl",
            out / "params" / f".000003_b_1.npz.{pid}.part.npz"]
    theirs = [out / ".notes.part", out / ".run.json.bak.part", out / "draft.part",
              out / ".123456_backup.part", out / f".123456_backup.{pid}.part",
              out / ".manifest.jsonl.4242.part.jsonl", out / f".000002_b_0.png.{pid}.part.png"]
    for path in ours + theirs:
        path.write_bytes(b"x")
    assert main(args(photos, out, "--resume", "--limit", "2")) == 0
    assert not any(p.exists() for p in ours)
    assert main(args(photos, out, "--overwrite", "--limit", "2")) == 0
    assert all(p.read_bytes() == b"x" for p in theirs)
    # in the set's folders such a file is no file of the set: refused, and kept
    stranger = out / "blur" / ".000002_b_0.png.4242.part.png"
    stranger.write_bytes(b"x")
    capsys.readouterr()
    for again in (["--resume"], ["--overwrite"]):
        assert main(args(photos, out, "--limit", "2", *again)) == 2
        assert f"{stranger}: not a file gpu-blur wrote" in capsys.readouterr().err
    assert stranger.read_bytes() == b"x"


def test_the_lock_file_keeps_a_killed_runs_pid_until_its_temporaries_are_removed(tmp_path,
                                                                                 photos):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1")) == 0
    (out / dataset.LOCK).write_text("pid 4242 on elsewhere, started 2020-01-01\n")  # killed
    left = out / "blur" / ".000001_a_1.png.4242.part.png"
    left.write_bytes(b"x")
    (out / "blur" / "notes.txt").write_text("mine")
    assert main(args(photos, out, "--resume", "--limit", "2")) == 2  # refused: nothing done
    assert left.exists()
    (out / "blur" / "notes.txt").unlink()
    assert main(args(photos, out, "--resume", "--limit", "2")) == 0  # the record was kept
    assert not left.exists()
    assert not (out / dataset.LOCK).exists()  # its temporaries gone, so is the record


def test_a_new_set_in_a_users_folder_removes_none_of_their_files(tmp_path, photos):
    out = tmp_path / "mine"
    out.mkdir()
    theirs = [out / ".123456_backup.part", out / f".manifest.jsonl.{os.getpid()}.part.jsonl",
              out / "notes.txt"]
    for path in theirs:
        path.write_bytes(b"x")
    assert main(args(photos, out, "--limit", "1")) == 0
    assert all(p.read_bytes() == b"x" for p in theirs)


def test_overwrite_replaces_the_whole_older_set(tmp_path, photos):
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    assert len(list((out / "blur").iterdir())) == 4
    assert main(args(photos, out, "--overwrite", "--limit", "1")) == 0
    reference = tmp_path / "reference"
    assert main(args(photos, reference, "--limit", "1")) == 0
    assert files(out) == files(reference)  # no image of the older, longer set is left
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()


def test_resume_replaces_sample_files_no_manifest_line_lists_and_keeps_others(tmp_path, photos,
                                                                               capsys):
    # files no line lists are those of samples a stopped run was writing, made again, or
    # finished samples whose lines are gone: those this run would not make are kept (issue 35)
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    lines = (out / "manifest.jsonl").read_text().splitlines(keepends=True)
    (out / "manifest.jsonl").write_text("".join(lines[:2]))  # as if lines 2 to 3 were lost
    before = files(out)
    assert main(args(photos, out, "--resume", "--limit", "2")) == 2
    assert "lists none of 6 sample file(s) in" in capsys.readouterr().err
    assert files(out) == before
    assert main(args(photos, out, "--resume")) == 0  # all made: the files are replaced
    reference = tmp_path / "reference"
    assert main(args(photos, reference)) == 0
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


@pytest.mark.parametrize("flag", [[], ["--overwrite"], ["--resume"]])
def test_sample_files_without_a_manifest_or_run_json_are_neither_replaced_nor_removed(
        tmp_path, photos, capsys, flag):
    # files named like a set's, with nothing saying gpu-blur made them (a user's own files,
    # or a set whose records are gone): refused whatever the flag, and left as they are
    out = tmp_path / "out"
    assert main(args(photos, out)) == 0
    (out / "manifest.jsonl").unlink()
    (out / "run.json").unlink()
    before = files(out)
    assert main(args(photos, out, *flag)) == 2
    err = capsys.readouterr().err
    assert (f"--output {out}: 12 sample file(s) in blur, sharp, params named like a set's, but "
            "no manifest.jsonl or run.json") in err
    assert files(out) == before


def test_an_output_folder_inside_the_input_is_not_read_back_as_input(tmp_path, photos,
                                                                     capsys):
    folder, scene = photos
    out = folder / "set"
    assert main(args(photos, out)) == 0
    assert main(args(photos, out, "--resume")) == 0
    assert "4 of 4 samples done, 0 to make" in capsys.readouterr().out
    assert {x["inputs"][0] for x in manifest_lines(out)} == {str(folder / "a.png"),
                                                             str(folder / "b.png")}


def test_a_set_an_earlier_run_wrote_inside_the_input_is_not_read_as_input(tmp_path, photos):
    folder, scene = photos
    assert main(args(photos, folder / "first")) == 0
    second = tmp_path / "second"
    assert main(args(photos, second)) == 0
    assert {x["inputs"][0] for x in manifest_lines(second)} == {str(folder / "a.png"),
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


def test_made_samples_whose_lines_wait_are_not_counted_as_written(tmp_path):
    # what a stop reports: "interrupted after N new samples" counts the lines listed, not
    # those that wait for an earlier sample (dropped at close, made again on resume)
    specs = [SampleSpec(i, f"p{i}", (tmp_path / f"p{i}.png",)) for i in range(4)]
    writer = DatasetWriter(tmp_path / "out", 8, specs=specs)
    made = [{"index": i, "name": f"p{i}", "status": "ok"} for i in range(4)]
    writer.add(made[2])
    assert writer.held_back == 1
    writer.add(made[0])  # listed; 2 still waits for 1
    assert writer.held_back == 1
    writer.fail(specs[3], "bad input", {})  # a failed sample waits too, but was not made
    assert writer.held_back == 1
    writer.add(made[1])  # 1, 2 and 3 listed
    assert writer.held_back == 0
    writer.close()
    lines = (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()
    assert [json.loads(x)["index"] for x in lines] == [0, 1, 2, 3]


@pytest.mark.parametrize("kind", ["symlink", "hardlink"])
def test_a_lock_file_that_leads_to_another_file_is_refused_and_that_file_kept(
        tmp_path, photos, capsys, kind):
    out = tmp_path / "out"
    out.mkdir()
    precious = tmp_path / "precious.txt"
    precious.write_text("precious")
    if kind == "symlink":
        (out / dataset.LOCK).symlink_to(precious)
    else:
        os.link(precious, out / dataset.LOCK)
    assert main(args(photos, out)) == 2
    assert "the lock file is " in capsys.readouterr().err
    assert precious.read_text() == "precious"


def test_long_and_odd_sample_names_give_file_names_a_set_can_hold(tmp_path, photos):
    # a 240-character photo name and one with a newline: file names under 255 bytes (a hash
    # keeps long ones apart), and the set resumes and is replaced like any other
    folder, scene = photos
    long_name = "p" * 236 + "_end"
    (folder / "a.png").rename(folder / f"{long_name}.png")
    (folder / "b.png").rename(folder / "line\nbreak.png")
    out = tmp_path / "out"
    run = ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
           "--quiet"]
    assert main(run) == 0
    names = sorted(p.name for p in (out / "blur").iterdir())
    assert len(names) == 2 and all(len(n.encode()) <= 200 for n in names)
    assert any(n[7:].startswith("p" * 100) and "~" in n for n in names)
    assert {x["name"] for x in manifest_lines(out)} == {long_name, "line\nbreak"}
    assert main([*run, "--resume"]) == 0
    assert main([*run, "--overwrite"]) == 0
    assert sorted(p.name for p in (out / "blur").iterdir()) == names


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
def test_red_and_blue_swap_as_numpys_reversed_channels_whatever_the_layout(dtype):
    # images are read and written through OpenCV's BGR order: the swap is a permutation
    rng = np.random.default_rng(3)
    image = (rng.random((9, 14, 4)) * 1000).astype(dtype)
    for view in (image[:, :, :3], image[:, ::2, 1:], np.ascontiguousarray(image[:, :, :3])):
        got = gpu_blur.image_arrays.swap_red_blue(view)
        assert got.dtype == view.dtype and got.flags.c_contiguous
        assert np.array_equal(got, view[:, :, ::-1])
    path = Path(gpu_blur.image_reading.__file__).parent / "data" / "coffee.png"
    rgb = gpu_blur.image_reading.read_image(path)
    assert np.array_equal(rgb, cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[:, :, ::-1])
