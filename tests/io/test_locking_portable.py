"""The output folder's lock imports and works without fcntl, and a finished run leaves no lock
file (issue 38; the complaint of issue 37)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gpu_blur import dataset, locking
from gpu_blur.cli import main
from gpu_blur.locking import LockHeld, earlier_pids, release_lock, take_lock

ROOT = Path(__file__).resolve().parents[2]

#: Run in a child first: fcntl hidden (as on Windows), and with ``emulate`` a stand-in msvcrt
#: whose locking() takes POSIX record locks on the same byte range, so the Windows code path
#: of gpu_blur.locking runs here. The stand-in is given to gpu_blur.locking alone: in
#: sys.modules it would make the standard library (subprocess) take this for Windows.
HIDE_FCNTL = textwrap.dedent("""
    import os, sys
    import fcntl as _posix
    class _Hidden:
        def find_spec(self, name, path=None, target=None):
            if name == "fcntl":
                raise ImportError("No module named 'fcntl' (hidden by the test)")
    sys.meta_path.insert(0, _Hidden())
    del sys.modules["fcntl"]
    if EMULATE:
        import types
        msvcrt = types.ModuleType("msvcrt")
        msvcrt.LK_UNLCK, msvcrt.LK_NBLCK = 0, 2
        def _locking(fd, mode, nbytes, _posix=_posix):
            start = os.lseek(fd, 0, os.SEEK_CUR)
            how = _posix.LOCK_UN if mode == msvcrt.LK_UNLCK else _posix.LOCK_EX | _posix.LOCK_NB
            _posix.lockf(fd, how, nbytes, start, os.SEEK_SET)
        msvcrt.locking = _locking
        import gpu_blur.locking
        gpu_blur.locking.msvcrt = msvcrt
    del _posix
""")


def child(code: str, *argv: str, emulate: bool = False) -> subprocess.CompletedProcess:
    script = HIDE_FCNTL.replace("EMULATE", str(emulate)) + textwrap.dedent(code)
    return subprocess.run([sys.executable, "-c", script, *argv], capture_output=True,
                          text=True, cwd=ROOT, timeout=120)


def test_the_data_sets_the_torch_side_and_the_writer_import_without_fcntl():
    run = child("""
        import gpu_blur.locking as locking
        assert locking.fcntl is None and locking.msvcrt is None
        import gpu_blur.datasets, gpu_blur.dataset, gpu_blur.generation, gpu_blur.cli
        import gpu_blur.torch
        print("imported")
    """)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "imported"


def test_without_fcntl_or_msvcrt_taking_the_lock_says_why(tmp_path):
    run = child(f"""
        from gpu_blur.locking import take_lock
        try:
            take_lock(__import__("pathlib").Path({str(tmp_path / "x.lock")!r}), "w", "f")
        except OSError as e:
            print(e)
    """)
    assert "no file locking on this platform (neither fcntl nor msvcrt)" in run.stdout, run.stderr


def test_the_windows_path_keeps_a_second_writer_out_and_names_the_holder(tmp_path):
    # the first process holds the lock (msvcrt's path, emulated) until its stdin closes; a
    # second one is refused naming it, and once the first releases, the file is gone and a
    # third takes it
    path = tmp_path / ".gpu_blur.lock"
    holder = subprocess.Popen(
        [sys.executable, "-c", HIDE_FCNTL.replace("EMULATE", "True") + textwrap.dedent(f"""
            import sys
            from pathlib import Path
            from gpu_blur.locking import take_lock, release_lock
            fd = take_lock(Path({str(path)!r}), "w", "f")
            print("held", flush=True)
            sys.stdin.read()
            release_lock(fd, Path({str(path)!r}))
        """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "held"
        second = child(f"""
            from pathlib import Path
            from gpu_blur.locking import take_lock, LockHeld
            try:
                take_lock(Path({str(path)!r}), "--output out", "wait")
            except LockHeld as e:
                print(e)
        """, emulate=True)
        assert f"--output out: another gpu-blur run is writing it (its lock file {path} " \
               f"says: pid {holder.pid} on " in second.stdout, second.stderr
        assert second.stdout.rstrip().endswith("; wait")
    finally:
        holder.communicate("", timeout=60)
    assert holder.returncode == 0 and not path.exists()
    third = child(f"""
        from pathlib import Path
        from gpu_blur.locking import take_lock, release_lock
        release_lock(take_lock(Path({str(path)!r}), "w", "f"), Path({str(path)!r}))
        print("ok")
    """, emulate=True)
    assert third.stdout.strip() == "ok", third.stderr


def test_a_set_is_made_and_resumed_without_fcntl(tmp_path, photos):
    folder, scene = photos
    out = tmp_path / "out"
    # one child makes the set, then resumes it (one start of Python and gpu_blur, not two)
    code = f"""
        from pathlib import Path
        from gpu_blur.cli import main
        from gpu_blur.dataset import LOCK
        command = ["generate", "--input", {str(folder)!r}, "--output", {str(out)!r},
                   "--scene", {str(scene)!r}, "--limit", "2", "--quiet"]
        for again in ([], ["--resume"]):
            assert main([*command, *again]) == 0, again
            assert not (Path({str(out)!r}) / LOCK).exists(), again
        print("made and resumed")
    """
    run = child(code, emulate=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().splitlines()[-1] == "made and resumed", run.stdout
    assert len((out / "manifest.jsonl").read_text().splitlines()) == 2
    assert not (out / dataset.LOCK).exists()


def test_a_finished_run_leaves_no_lock_file_and_a_refused_one_none_either(tmp_path, photos,
                                                                          capsys):
    folder, scene = photos
    out = tmp_path / "out"
    args = ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--limit", "1", "--quiet"]
    assert main(args) == 0
    assert not (out / dataset.LOCK).exists()
    assert main(args) == 2  # refused: a set is there already
    assert "holds a set already" in capsys.readouterr().err
    assert not (out / dataset.LOCK).exists()
    assert main([*args, "--resume"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["blur", "manifest.jsonl", "params",
                                                     "run.json", "sharp"]


def test_a_killed_runs_record_stays_until_its_temporary_files_are_removed(tmp_path, photos,
                                                                          capsys):
    folder, scene = photos
    out = tmp_path / "out"
    args = ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--quiet"]
    assert main([*args, "--limit", "1"]) == 0
    (out / dataset.LOCK).write_text("pid 4242 on elsewhere, started 2020-01-01\n")  # killed
    left = out / "blur" / ".000001_a_1.png.4242.part.png"
    left.write_bytes(b"x")
    (out / "blur" / "notes.txt").write_text("mine")
    assert main([*args, "--resume", "--limit", "2"]) == 2  # refused: nothing done
    assert "notes.txt: not a file gpu-blur wrote" in capsys.readouterr().err
    assert left.exists()
    record = (out / dataset.LOCK).read_text().splitlines()
    assert record[0].startswith(f"pid {os.getpid()} on ") and record[1].startswith("pid 4242 ")
    (out / "blur" / "notes.txt").unlink()
    assert main([*args, "--resume", "--limit", "2"]) == 0  # the record was kept
    assert not left.exists() and not (out / dataset.LOCK).exists()


def test_a_close_that_cannot_write_the_manifest_keeps_the_lock_file(tmp_path):
    out = tmp_path / "out"
    writer = dataset.DatasetWriter(out, 8)

    class FullDisk:
        def close(self):
            raise OSError(28, "No space left on device")

    writer.manifest.close()
    writer.manifest = FullDisk()
    with pytest.raises(OSError, match="cannot write its last lines"):
        writer.close()
    assert (out / dataset.LOCK).read_text().startswith(f"pid {os.getpid()} on ")
    dataset.DatasetWriter(out, 8, overwrite=True).close()  # released all the same
    assert not (out / dataset.LOCK).exists()


def test_a_process_that_opened_the_file_before_its_holder_removed_it_locks_the_new_one(
        tmp_path, monkeypatch):
    # B opens the lock file while A holds it; A finishes (removes the file, then lets go); B's
    # lock on the removed file would guard nothing, so B opens the name again, and a third
    # process is refused: one holder, of the file the name leads to
    path = tmp_path / "x.lock"
    first = take_lock(path, "w", "f")
    stale = os.open(path, os.O_RDWR)
    release_lock(first, path)
    assert not path.exists()
    opened = []
    real_open = locking._open
    monkeypatch.setattr(locking, "_open", lambda p: opened.append(p) or (
        stale if len(opened) == 1 else real_open(p)))
    second = take_lock(path, "w", "f")
    assert len(opened) == 2 and second != stale and path.is_file()
    assert os.fstat(second).st_ino == path.stat().st_ino
    monkeypatch.undo()
    with pytest.raises(LockHeld, match=f"pid {os.getpid()} on "):
        take_lock(path, "w", "f")
    release_lock(second, path)
    assert not path.exists()


def test_a_lock_file_that_records_an_earlier_holder_is_kept_on_release(tmp_path):
    path = tmp_path / "x.lock"
    path.write_text("pid 4242 on elsewhere, started 2020-01-01\n")
    fd = take_lock(path, "w", "f", keep_earlier=True)
    assert earlier_pids(fd) == {4242}
    release_lock(fd, path)
    assert path.read_text().splitlines()[1].startswith("pid 4242 ")
    release_lock(take_lock(path, "w", "f"), path)  # without keep_earlier: only its own line
    assert not path.exists()


def test_a_bench_run_leaves_no_lock_file(tmp_path, monkeypatch):
    from gpu_blur.analysis.bench import run

    monkeypatch.setattr(run, "run_benchmark", lambda *a, **k: {"rows": []})
    monkeypatch.setattr(run, "write_report", lambda report, output, tag: [])
    assert run.main(["--output", str(tmp_path), "--tag", "t", "--backends", "numpy"]) == 0
    assert list(tmp_path.iterdir()) == []


def test_processes_taking_and_releasing_one_lock_never_hold_it_together(tmp_path):
    # each holder makes a marker with O_EXCL and removes it before releasing (which removes
    # the lock file): a second holder at the same time would find the marker there
    code = textwrap.dedent(f"""
        import os, sys
        from pathlib import Path
        from gpu_blur.locking import LockHeld, release_lock, take_lock
        path, marker, held = Path({str(tmp_path / "x.lock")!r}), {str(tmp_path / "m")!r}, 0
        for _ in range(300):
            try:
                fd = take_lock(path, "w", "f")
            except LockHeld:
                continue
            os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            os.unlink(marker)
            release_lock(fd, path)
            held += 1
        print(held)
    """)
    runs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, cwd=ROOT) for _ in range(4)]
    results = [run.communicate(timeout=120) for run in runs]
    assert all(run.returncode == 0 for run in runs), [err for _, err in results]
    assert sum(int(out) for out, _ in results) > 0
    assert not (tmp_path / "x.lock").exists()
