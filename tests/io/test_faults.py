"""Faults a run must survive (issue 13): a sample's own error fails that sample only, signals
end the worker processes, and damaged JPEG data is refused.

Small images and the numpy backend throughout.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import TEST_DATA

import gpu_blur.generate
from gpu_blur.cli import main
from gpu_blur.discovery import SampleSpec
from gpu_blur.generate import Job, make_sample
from gpu_blur.image_reading import read_image
from gpu_blur.reference.flow import optical_flow
from gpu_blur.scene import scene_from_dict
from gpu_blur.testhooks import TEST_SLEEP_AFTER


def manifest(out):
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    return sorted(lines, key=lambda x: x["index"])


# ---- a sample's own error fails that sample -----------------------------------------------

@pytest.mark.parametrize("shape", [(4, 4), (1, 7), (15, 40)], ids=["4x4", "1x7", "15x40"])
def test_dis_flow_needs_frames_of_16_pixels_and_names_the_size(shape):
    # OpenCV 5.0.0 raised cv2.error on 4 x 4 and 1 x 7 and crashed (segmentation fault) on 15 x 40
    rng = np.random.default_rng(0)
    frame = rng.random((*shape, 3))
    with pytest.raises(ValueError) as e:
        optical_flow(frame, frame, "dis")
    assert f"frames of {shape[0]} x {shape[1]} pixels" in str(e.value)
    assert "at least 16 x 16" in str(e.value) and "blur.flow = 'farneback'" in str(e.value)
    assert optical_flow(frame, frame, "farneback").shape == (*shape, 2)
    grown = rng.random((max(shape[0], 16), max(shape[1], 16), 3))
    assert optical_flow(grown, np.roll(grown, 1, axis=1), "dis").shape == (*grown.shape[:2], 2)


def write_sequence(folder, shape, seed):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:06d}.png"), rng.integers(0, 256, (*shape, 3), np.uint8))


@pytest.mark.parametrize("executor", [[], ["--devices", "numpy,numpy"]],
                         ids=["serial", "devices"])
def test_frames_too_small_for_the_flow_fail_their_sample_and_the_run_goes_on(
        tmp_path, capsys, executor):
    write_sequence(tmp_path / "in" / "a_big" / "sharp", (24, 32), 0)
    write_sequence(tmp_path / "in" / "b_tiny" / "sharp", (4, 4), 1)
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 3\ninterpolation = 2\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--scene", str(scene), "--quiet", *executor]) == 1
    big, tiny = manifest(out)
    assert big["status"] == "ok" and (out / big["blurred"]).is_file()
    assert tiny["status"] == "failed"
    assert "frames of 4 x 4 pixels (H x W) are too small for blur.flow = 'dis'" in tiny["error"]
    assert "1 of 2 samples failed" in capsys.readouterr().err


@pytest.fixture
def job():
    return Job(scene_from_dict({"blur": {"steps": 3}}), 0, "numpy")


SPEC = SampleSpec(index=3, name="p", inputs=("p.png",))


def test_only_opencv_and_memory_errors_of_a_sample_fail_that_sample(job, monkeypatch):
    errors = [
        (cv2.error("OpenCV(5.0.0) /io/x.cpp:1: error: (-201:Incorrect size of input array) "
                   "The input image is too small in function 'calc'\n"),
         "OpenCV refused this sample's data: The input image is too small"),
        (MemoryError("Unable to allocate 7.5 GiB for an array"),
         "out of memory (Unable to allocate 7.5 GiB for an array): this sample needs more"),
        (TypeError("a bug"), None),  # gpu_blur's fault: it surfaces
        (KeyboardInterrupt(), None),
    ]
    for error, message in errors:
        def synthesize(*args, error=error, **kwargs):
            raise error

        monkeypatch.setattr(gpu_blur.generate, "synthesize", synthesize)
        if message is None:
            with pytest.raises(type(error)):
                make_sample(job, SPEC)
        else:
            spec, result, reason = make_sample(job, SPEC)
            assert spec is SPEC and result is None and reason.startswith(message)


# ---- damaged JPEG data is refused ---------------------------------------------------------

ROCKET = TEST_DATA / "rocket.jpg"


def scan_middle(data):
    """A byte offset in the middle of a JPEG's (first) entropy-coded data."""
    start = data.index(b"\xff\xda")
    return start + (len(data) - start) // 2


def assert_refused(path, data, message):
    path.write_bytes(data)
    with pytest.raises(ValueError) as e:
        read_image(path)
    assert str(e.value).startswith(f"{path}: corrupt JPEG (") and message in str(e.value)
    assert "re-export or re-copy the file" in str(e.value)


def test_a_real_jpeg_with_a_bad_marker_inside_its_image_data_is_refused(tmp_path):
    data = ROCKET.read_bytes()
    assert read_image(ROCKET).shape == (427, 640, 3)
    middle = scan_middle(data)
    inserted = data[:middle] + b"\xff\x37" + data[middle:]
    overwritten = data[:middle] + bytes([0x12, 0xFF, 0xD8, 0x34]) + data[middle + 4:]
    for bad in (inserted, overwritten):  # OpenCV decodes both, the lower half garbled
        assert cv2.imdecode(np.frombuffer(bad, np.uint8), cv2.IMREAD_COLOR) is not None
    assert_refused(tmp_path / "marker.jpg", inserted,
                   f"marker 0xFF37 at byte {middle} cannot stand there")
    assert_refused(tmp_path / "soi.jpg", overwritten, f"marker 0xFFD8 at byte {middle + 1}")


def test_a_real_jpeg_with_damaged_huffman_data_is_refused(tmp_path):
    data = ROCKET.read_bytes()
    middle = scan_middle(data)
    # 16 bytes overwritten: the marker structure is intact (no 0xFF among them), so only
    # decoding finds the damage; OpenCV decodes it without a word
    damaged = data[:middle] + bytes(range(0x60, 0x70)) + data[middle + 16:]
    assert cv2.imdecode(np.frombuffer(damaged, np.uint8), cv2.IMREAD_COLOR) is not None
    assert_refused(tmp_path / "huffman.jpg", damaged, "Corrupt JPEG data")


JPEG_OPTIONS = {
    "baseline": [],
    "progressive": [cv2.IMWRITE_JPEG_PROGRESSIVE, 1],
    "restart-intervals": [cv2.IMWRITE_JPEG_RST_INTERVAL, 4],
    "progressive-444-restart-intervals": [
        cv2.IMWRITE_JPEG_PROGRESSIVE, 1, cv2.IMWRITE_JPEG_RST_INTERVAL, 3,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444],
}


@pytest.mark.parametrize("options", JPEG_OPTIONS.values(), ids=JPEG_OPTIONS.keys())
def test_whole_jpegs_are_read_and_damaged_ones_refused(tmp_path, rocket_rgb, options):
    bgr = np.rint(rocket_rgb[:, :, ::-1] * 255).astype(np.uint8)
    data = cv2.imencode(".jpg", bgr, options)[1].tobytes()
    path = tmp_path / "x.jpg"
    path.write_bytes(data + b"data after the end of the image, e.g. a second image")
    assert np.array_equal(read_image(path), cv2.imread(str(path))[:, :, ::-1])
    middle = scan_middle(data)
    assert_refused(path, data[:middle] + b"\xff\x37" + data[middle:], "cannot stand there")
    if cv2.IMWRITE_JPEG_RST_INTERVAL in options:  # restart markers show what is missing
        assert_refused(path, data[:middle] + data[middle + 2000:],
                       "image data is missing or damaged")
        assert_refused(path, data[:middle] + bytes(1000) + data[middle + 1000:],
                       "image data is missing or damaged")


@pytest.mark.parametrize("data, pos, interval, mcus, want", [
    # fill bytes before the end marker: the scan ends at the first of them
    (b"\x12\xff\x00\x34\xff\xff\xff\xd9", 0, 0, None, (4, None)),
    (b"\x12\xff\xd0\x34\xff\xd1\x56\xff\xd9", 0, 2, 6, (7, None)),
    (b"\x12\xff\xd0\x34\xff\xd2\x56\xff\xd9", 0, 2, 6,
     (4, "restart marker RST2 at byte 4 where RST1 is due: image data is missing or damaged")),
    (b"\x12\xff\xd0\x34\xff\xd9", 0, 0, None,
     (1, "restart marker at byte 1 without a restart interval")),
    (b"\x12\xff\xd0\x34\xff\xd9", 0, 4, 40,
     (4, "1 restart markers where its 40 MCUs in intervals of 4 need 9: image data is missing "
         "or damaged")),
    (b"\x12\xff\x00\x34\xff\xff", 0, 0, None, (6, None)),  # data ends inside a run
    (b"\x12\x34\x56", 0, 0, None, (3, None)),  # no marker at all
    (b"\xff\x00\xff\xd9", 2, 0, None, (2, None)),  # from the given position on
])
def test_a_scans_stuffed_bytes_restart_markers_and_end_are_read_from_every_0xff_run(
        data, pos, interval, mcus, want):
    from gpu_blur.image_reading import _jpeg_scan

    assert _jpeg_scan(data, pos, interval, mcus) == want


# ---- no command writes over its own inputs (align and compare: test_align, test_metrics) ---

@pytest.mark.parametrize("option", ["--chart", "--reference"])
def test_calibrate_refuses_to_write_its_camera_file_over_an_input(tmp_path, capsys, option):
    from importlib import resources

    from gpu_blur.analysis.calibrate import COLORCHECKER24

    chart = tmp_path / "chart.json"
    chart.write_text(json.dumps({"rgb": np.random.default_rng(0).uniform(0.05, 0.9, (24, 3))
                                 .tolist()}))
    reference = tmp_path / "reference.json"
    reference.write_text((resources.files("gpu_blur") / "data" / COLORCHECKER24).read_text())
    target = chart if option == "--chart" else reference
    before = target.read_bytes()
    assert main(["calibrate", "--chart", str(chart), "--reference", str(reference),
                 "--output", str(target), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert f"--output {target}: it would write {target}, which is {option} {target}" in err
    assert "give --output a new camera file name" in err
    assert target.read_bytes() == before


# ---- signals end the worker processes -----------------------------------------------------

def parent_of(pid):
    """The parent process id of ``pid`` from /proc, or None once it is gone (or a zombie)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    state, ppid = stat.rsplit(")", 1)[1].split()[:2]
    return None if state == "Z" else int(ppid)


def children_of(pid):
    return [int(p.name) for p in Path("/proc").iterdir()
            if p.name.isdigit() and parent_of(p.name) == pid]


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGKILL],
                         ids=["SIGTERM", "SIGHUP", "SIGKILL"])
def test_a_signal_to_a_devices_run_ends_its_workers_and_keeps_finished_samples(tmp_path,
                                                                             photos, signum):
    folder, scene = photos
    out = tmp_path / "out"
    command = [sys.executable, "-m", "gpu_blur.cli", "generate", "--input", str(folder),
               "--output", str(out), "--scene", str(scene), "--samples-per-photo", "4",
               "--quiet", "--devices", "numpy,numpy"]
    env = {**os.environ, TEST_SLEEP_AFTER: "1"}  # the driver sleeps once sample 1 is recorded
    log = tmp_path / "log"
    with log.open("w") as sink:  # a file, not a pipe: workers left alive would hold a pipe open
        run = subprocess.Popen(command, env=env, stdout=sink, stderr=subprocess.STDOUT)
    workers = []
    try:
        deadline = time.monotonic() + 60
        while '"index": 1,' not in ((out / "manifest.jsonl").read_text()
                                    if (out / "manifest.jsonl").exists() else ""):
            assert run.poll() is None, log.read_text()
            assert time.monotonic() < deadline, "the run never reached sample 1"
            time.sleep(0.05)
        workers = children_of(run.pid)  # the two workers and multiprocessing's tracker
        assert len(workers) >= 2
        run.send_signal(signum)
        run.wait(timeout=30)
        if signum == signal.SIGKILL:
            assert run.returncode == -signal.SIGKILL
        else:
            assert run.returncode == 128 + signum, log.read_text()
            assert "run the same command with --resume" in log.read_text()
        deadline = time.monotonic() + 10
        while any(parent_of(pid) is not None for pid in workers):
            assert time.monotonic() < deadline, [parent_of(pid) for pid in workers]
            time.sleep(0.05)
    finally:
        run.kill()
        for pid in workers:
            if parent_of(pid) is not None:
                os.kill(pid, signal.SIGKILL)
    kept = manifest(out)
    assert 1 in [x["index"] for x in kept]
    assert all(x["status"] == "ok" and (out / x["blurred"]).is_file() for x in kept)
