import contextlib
import io
import json

import cv2
import numpy as np
import pytest
from conftest import BACKEND_SPECS, QUICK_SCENE

import gpu_blur
from gpu_blur.cli import main


def write_sequence(folder, n, size=(24, 32), seed=0):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:06d}.png"), rng.integers(0, 256, (*size, 3), np.uint8))


@pytest.fixture(scope="module")
def built_in_set(tmp_path_factory):
    """``generate --limit 2 --seed 5`` on the built-in photo, the quick scene (the default chain,
    3 camera poses): (set folder, scene file, what it printed on stdout). Made once for the
    tests that read it."""
    folder = tmp_path_factory.mktemp("built_in")
    scene = folder / "quick.toml"
    scene.write_text(QUICK_SCENE)
    out = folder / "set"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["generate", "--output", str(out), "--limit", "2", "--seed", "5",
                     "--scene", str(scene), "--quiet"]) == 0
    return out, scene, printed.getvalue()


def test_generate_on_the_built_in_photo_writes_pairs_and_a_manifest(built_in_set):
    out, _, printed = built_in_set
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [x["index"] for x in lines] == [0, 1]
    for line in lines:
        blurred = cv2.imread(str(out / line["blurred"]), cv2.IMREAD_UNCHANGED)
        sharp = cv2.imread(str(out / line["sharp"]), cv2.IMREAD_UNCHANGED)
        assert blurred.shape == sharp.shape == (400, 600, 3) and blurred.dtype == np.uint8
        assert {"alpha", "pattern", "red_gain", "shot_noise_k"} <= set(line["params"])
        assert line["status"] == "ok" and line["inputs"] == ["built-in: coffee.png"]
        with np.load(out / line["arrays"]) as arrays:
            assert arrays["homographies"].shape[1:] == (3, 3)
    assert lines[0]["params"] != lines[1]["params"]
    assert "wrote 2 samples" in printed


def test_manifest_names_the_device_that_made_each_sample(tmp_path, photos, monkeypatch):
    # with --devices, workers hold other devices than the driver's backend: each line says the
    # device of the sample's own Synthesis (here a stand-in executor renames it)
    import dataclasses

    import gpu_blur
    from gpu_blur import distributed

    real = distributed.pick_executor

    def renaming(args, precision):
        executor = real(args, precision)

        def run(job, specs):
            for spec, result, error in executor(job, specs):
                yield spec, dataclasses.replace(result, device=f"worker {spec.index}"), error
        return run

    monkeypatch.setattr(distributed, "pick_executor", renaming)
    folder, scene = photos
    out = tmp_path / "set"
    assert main(["generate", "--input", str(folder), "--scene", str(scene), "--output",
                 str(out), "--limit", "2", "--quiet"]) == 0
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [x["device"] for x in lines] == ["worker 0", "worker 1"]
    # and a sample made here names this process's device
    from gpu_blur.backends import get_backend
    from gpu_blur.scene import scene_from_dict

    alone = gpu_blur.synthesize([np.zeros((8, 8, 3))], scene_from_dict({}), backend="numpy")
    assert alone.device == get_backend("numpy").model != ""


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_a_sample_names_its_device_model_not_the_device_s_number_on_this_host(spec):
    # two GPUs of one model make the same bits, so a set's manifest must not depend on which
    # of them made a sample (sets byte-identical whatever the number of GPUs)
    from gpu_blur.backends import get_backend
    from gpu_blur.scene import scene_from_dict

    name, _, precision = spec.partition("/")
    backend = get_backend(name, precision or "float64")
    made = gpu_blur.synthesize([np.zeros((8, 8, 3))], scene_from_dict({}), backend=backend)
    assert made.device == backend.model
    assert backend.model.split()[0] == backend.name
    assert not any(part.startswith(("opencl:", "warp:")) for part in backend.model.split())


def test_generate_is_reproducible_for_a_seed(tmp_path, built_in_set):
    made, scene, _ = built_in_set
    out = tmp_path / "again"
    assert main(["generate", "--output", str(out), "--limit", "1", "--quiet", "--seed", "5",
                 "--scene", str(scene)]) == 0
    (a,) = (out / "blur").iterdir()
    assert a.read_bytes() == (made / "blur" / a.name).read_bytes()


def test_generate_reads_gopro_sequences_in_windows_of_frames(tmp_path):
    write_sequence(tmp_path / "in" / "GOPR0001" / "sharp", 7)
    write_sequence(tmp_path / "in" / "GOPR0002" / "sharp", 3, seed=1)
    (tmp_path / "s.toml").write_text('[blur]\nmode = "average"\nframes = 3\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--scene", str(tmp_path / "s.toml"), "--quiet"]) == 0
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [x["name"] for x in lines] == ["GOPR0001/000000", "GOPR0001/000003",
                                          "GOPR0002/000000"]
    assert [len(x["inputs"]) for x in lines] == [3, 3, 3]


def test_generate_refuses_to_overwrite_an_existing_set(tmp_path, photos, capsys):
    folder, scene = photos
    out = tmp_path / "set"
    run = ["generate", "--input", str(folder), "--scene", str(scene), "--output", str(out),
           "--limit", "1", "--quiet"]
    assert main(run) == 0
    assert main(run) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main([*run, "--overwrite"]) == 0


@pytest.mark.parametrize("args, message", [
    (["--input", "nowhere"], "--input nowhere: no such folder"),
    (["--scene", "missing.toml"], "scene file missing.toml does not exist"),
])
def test_generate_errors_name_the_bad_path(tmp_path, capsys, args, message):
    assert main(["generate", "--output", str(tmp_path / "o"), *args]) == 2
    assert message in capsys.readouterr().err


def test_generate_reports_a_bad_scene_value_with_file_key_and_choices(tmp_path, capsys):
    scene = tmp_path / "bad.toml"
    scene.write_text('[noise]\nmodel = "poison"\n')
    assert main(["generate", "--output", str(tmp_path / "o"), "--scene", str(scene)]) == 2
    err = capsys.readouterr().err
    assert str(scene) in err and "noise.model = 'poison'" in err and "'poisson-gaussian'" in err


def test_plan_prints_kept_and_skipped_stages_with_reasons(capsys, tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text('[noise]\nmodel = "none"\n')
    assert main(["plan", str(scene)]) == 0
    out = capsys.readouterr().out
    assert "skip mosaic" in out and "noise.model = none: no RAW round trip" in out
    assert "run  tone" in out


def test_scene_and_cameras_commands_list_what_is_available(capsys):
    assert main(["scene"]) == 0
    assert "[noise]" in capsys.readouterr().out
    assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert "a7r3" in out and "rsblur-0019" in out and "srgb" in out


@pytest.mark.parametrize("size, message", [
    ("100000x100000", "--size '100000x100000' is invalid; allowed: at most 268,435,456 pixels "
                      "(the pixel budget of an input image; 10,000,000,000 would be made in "
                      "memory)"),
    ("1" + "0" * 5000 + "x2", "is invalid; allowed: WxH in pixels, e.g. 480x320"),
    ("４８x32", "--size '４８x32' is invalid; allowed: WxH in pixels"),  # digits, not ASCII
])
def test_plan_cost_holds_size_to_the_pixel_budget(capsys, monkeypatch, size, message):
    from gpu_blur.analysis import stage_cost

    monkeypatch.delenv("GPU_BLUR_MAX_PIXELS", raising=False)
    monkeypatch.setattr(stage_cost, "stage_costs", lambda *a: pytest.fail("allocated"))
    assert main(["plan", "minimal", "--cost", "--size", size]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gpu-blur: error: --size ") and message in err
    assert len(err.splitlines()) == 1


def run_closed(*command):
    """``gpu-blur *command`` run with its stdout and stderr closed (``>&- 2>&-``)."""
    import subprocess
    import sys

    return subprocess.run(["bash", "-c", 'exec "$@" >&- 2>&-', "-", sys.executable, "-m",
                           "gpu_blur.cli", *command], timeout=300).returncode


def test_generate_with_stdout_and_stderr_closed_makes_its_samples(tmp_path, photos):
    out = tmp_path / "set"
    assert run_closed("generate", "--input", str(photos[0]), "--output", str(out), "--limit",
                      "1", "--scene", "minimal") == 0
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [x["status"] for x in lines] == ["ok"]
    assert cv2.imread(str(out / lines[0]["blurred"])).shape == (24, 32, 3)
    assert run_closed("plan", str(tmp_path / "none.toml")) == 2  # errors: the status says it


def device_worker(tmp_path, photos=1, size=(24, 32)):
    """A device worker process on numpy started as generate's driver starts it, and its pipe."""
    import multiprocessing
    import os

    from gpu_blur import distributed
    from gpu_blur.discovery import find_samples
    from gpu_blur.generate import Job
    from gpu_blur.scene import scene_from_dict

    rng = np.random.default_rng(0)
    (tmp_path / "in").mkdir()
    for i in range(photos):
        cv2.imwrite(str(tmp_path / "in" / f"p{i}.png"), rng.integers(0, 256, (*size, 3),
                                                                       np.uint8))
    specs = find_samples(tmp_path / "in", "trajectory", 1, 1).take()
    context = multiprocessing.get_context("spawn")
    conn, child = context.Pipe()
    job = Job(scene_from_dict({"blur": {"steps": 3}}), 0, "numpy")
    worker = context.Process(target=distributed._device_worker, daemon=True,
                             args=(job, os.getpid(), child, 1, os.getcwd()))
    with distributed._driver_signals_blocked():
        worker.start()
    child.close()
    return worker, conn, specs


def test_a_device_worker_whose_driver_is_gone_ends_quietly(tmp_path, capfd):
    import time

    worker, conn, specs = device_worker(tmp_path, size=(400, 600))  # about 1 s a sample
    assert conn.recv()[0] == "open"
    conn.send(("setup", (False, 0, None)))  # no shared memory, frame cache or writing
    conn.send(specs[0])
    time.sleep(0.3)
    conn.close()  # the driver is gone while the worker makes the sample
    worker.join(60)
    assert worker.exitcode == 0
    assert "Error" not in capfd.readouterr().err


def test_ctrl_c_while_a_device_worker_starts_prints_no_traceback(tmp_path, capfd):
    import os
    import signal
    import time

    worker, conn, specs = device_worker(tmp_path)
    end = time.monotonic() + 3  # Ctrl-C reaches the process group: here the worker alone
    while time.monotonic() < end and not conn.poll(0.01):
        os.kill(worker.pid, signal.SIGINT)
    assert conn.recv()[0] == "open"
    conn.send(("setup", (False, 0, None)))  # no shared memory, frame cache or writing
    os.kill(worker.pid, signal.SIGINT)  # ignored once it runs
    conn.send(specs[0])
    assert conn.recv()[0] == "sample"
    conn.close()
    worker.join(60)
    assert worker.exitcode == 0
    err = capfd.readouterr().err
    assert "KeyboardInterrupt" not in err and "Traceback" not in err
