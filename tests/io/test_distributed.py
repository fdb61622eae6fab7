"""Samples made by one process per device (--devices) or on a Ray cluster (--ray) give the
files and manifest of a serial run, byte for byte (issue 6).

The manifests are compared byte for byte: executors finish samples in any order, but the
driver writes the lines in sample order; no field is ignored, since every field is the
driver's (seed, backend, device) or the sample's own.
"""

import dataclasses
import gc
import multiprocessing
import os
import pickle
import re
import sys
import threading
import types
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import files, manifest_lines

import gpu_blur
from gpu_blur import distributed, shared_results
from gpu_blur.cli import main
from gpu_blur.discovery import SampleSpec, find_samples
from gpu_blur.distributed import parse_devices, run_devices, run_ray
from gpu_blur.file_writing import write_image
from gpu_blur.generate import Job, Saved, for_driver, run_serial
from gpu_blur.scene import load_scene, scene_from_dict
from gpu_blur.testhooks import TEST_FAIL_ONCE
from gpu_blur.timings import PoolTimes


def _opencl_usable():
    try:
        from gpu_blur.backends.opencl import opencl_devices
    except ImportError:
        return []
    return [d for d in opencl_devices() if d.usable]


def _warp_devices():
    try:
        from gpu_blur.backends.warp import warp_devices
    except ImportError:
        return None
    return warp_devices()


OPENCL = _opencl_usable()
WARP = _warp_devices()
CUDA = [d["spec"] for d in WARP or [] if d["spec"].startswith("warp:cuda")]
OPENCL_GPUS = [d.spec for d in OPENCL if d.kind == "GPU"]


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """Two small photos and a truncated one; 2 samples each: 4 good, 2 failed (bad input)."""
    folder = tmp_path_factory.mktemp("in")
    rng = np.random.default_rng(0)
    for name in ("a", "b", "c"):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(0, 256, (24, 32, 3), np.uint8))
    (folder / "c.png").write_bytes((folder / "c.png").read_bytes()[:60])
    scene = folder.parent / "scene.toml"
    scene.write_text("[blur]\nsteps = 3\n")  # the full default chain, 3 camera poses
    return folder, scene


def args(photos, out, *extra):
    folder, scene = photos
    return ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--samples-per-photo", "2", "--quiet", *extra]


@pytest.fixture(scope="module")
def reference(photos, tmp_path_factory):
    """The serial run's folder, per backend (made once)."""
    made = {}

    def get(backend="numpy"):
        if backend not in made:
            out = tmp_path_factory.mktemp("serial") / "out"
            assert main(args(photos, out, "--backend", backend)) == 1  # c.png's samples fail
            made[backend] = out
        return made[backend]

    return get


@pytest.fixture(scope="module")
def ray_local():
    """One local Ray instance on 2 CPUs for the module; `--ray auto` uses it."""
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def shards(out):
    """{name: bytes} of a WebDataset set's shards."""
    return {p.name: p.read_bytes() for p in sorted(out.glob("shard-*.tar"))}


def assert_same_set(out, reference):
    assert files(out) == files(reference)
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()
    lines = manifest_lines(out)
    assert (out / "run.json").read_bytes() == (reference / "run.json").read_bytes()
    failed = [x for x in lines if x["status"] == "failed"]
    assert [x["index"] for x in failed] == [4, 5] and "truncated PNG" in failed[0]["error"]
    assert [x["status"] for x in lines[:4]] == ["ok"] * 4


EXECUTORS = [
    pytest.param("numpy", ["--devices", "numpy,numpy"], id="devices-2-numpy"),
    pytest.param("numpy", ["--devices", "numpy,numpy", "--io-threads", "1"],
                 id="devices-2-numpy-writing-in-turn"),
    pytest.param("numpy", ["--ray", "auto"], id="ray-numpy"),
    pytest.param("opencl", ["--devices", ",".join([OPENCL[0].spec] * 2) if OPENCL else ""],
                 id="devices-2-opencl", marks=pytest.mark.skipif(
                     not OPENCL, reason="no usable OpenCL device")),
    pytest.param("warp:cpu", ["--devices", "warp:cpu,warp:cpu"], id="devices-2-warp-cpu",
                 marks=pytest.mark.skipif(WARP is None, reason="warp-lang not installed")),
    pytest.param(CUDA[:1], ["--devices", ",".join(CUDA)], id="devices-every-cuda-gpu",
                 marks=pytest.mark.skipif(len(CUDA) < 2, reason="fewer than 2 CUDA GPUs")),
    pytest.param(OPENCL_GPUS[:1], ["--devices", ",".join(OPENCL_GPUS)],
                 id="devices-every-opencl-gpu", marks=pytest.mark.skipif(
                     len(OPENCL_GPUS) < 2, reason="fewer than 2 OpenCL GPUs")),
]


@pytest.mark.slow
@pytest.mark.parametrize("backend, executor", EXECUTORS)
def test_every_executor_writes_the_files_and_manifest_of_a_serial_run(
        request, tmp_path, photos, reference, backend, executor):
    if "--ray" in executor:
        request.getfixturevalue("ray_local")
    if backend == "opencl":
        backend = OPENCL[0].spec
    if isinstance(backend, list):  # several GPUs against a serial run on the first
        backend = backend[0]
    out = tmp_path / "out"
    assert main(args(photos, out, "--backend", backend, *executor)) == 1
    assert_same_set(out, reference(backend))


def test_a_device_worker_decoding_ahead_in_threads_writes_the_serial_run_s_set(
        tmp_path, photos, reference, monkeypatch):
    monkeypatch.setattr(distributed, "default_io_threads", lambda: 4)  # 4 decoding threads
    out = tmp_path / "out"
    assert main(args(photos, out, "--backend", "numpy", "--devices", "numpy")) == 1
    assert_same_set(out, reference("numpy"))


def test_device_workers_writing_a_png_set_count_their_decoding_and_writing_in_the_summary(
        tmp_path, photos):
    folder, scene = photos
    report = gpu_blur.generate_set(tmp_path / "out", input=folder, scene=scene,
                                   samples_per_photo=2, devices="numpy,numpy", io_threads=4)
    threads = next(line for line in report.summary if line.startswith("I/O threads"))
    cache = next(line for line in report.summary if line.startswith("frame cache"))
    # --io-threads shared by the workers, 2 each, decoding and writing; the files that the
    # workers' caches decoded (a photo read by both of its samples in one worker, once)
    files = re.match(r"I/O threads \(4\): decoding [\d.]+ s \((\d+) files, [\d.]+ ms each\), "
                     r"encoding and writing ([\d.]+) s", threads)
    decoded = re.match(r"frame cache: (\d+) decoded, (\d+) served decoded", cache)
    assert files and decoded, (threads, cache)
    assert files[1] == decoded[1] and int(decoded[1]) + int(decoded[2]) == 6
    assert float(files[2]) > 0  # the 4 made samples' files, in the workers
    assert report.bound.startswith("bound by: ") and report.summary[-1] == report.bound
    # the images never crossed: only the lines
    handoff = next(line for line in report.summary if line.startswith("hand-off"))
    assert re.fullmatch(
        r"hand-off: the workers wrote their samples' files; the driver's thread [\d.]+ s "
        r"\([\d.]+ ms a sample\) taking their manifest lines and [\d.]+ s waiting for the "
        r"workers", handoff), handoff


def test_a_devices_run_into_a_container_counts_its_workers_decoding_and_its_hand_off(
        tmp_path, photos):
    folder, scene = photos
    report = gpu_blur.generate_set(tmp_path / "out", input=folder, scene=scene,
                                   samples_per_photo=2, devices="numpy,numpy", io_threads=4,
                                   format="webdataset")
    threads = next(line for line in report.summary if line.startswith("I/O threads"))
    # the driver's 4 writing threads (a shard is written through the driver) and each
    # worker's 2 decoding threads (--io-threads shared by the workers)
    assert re.match(r"I/O threads \(8\): decoding [\d.]+ s \(\d+ files", threads), threads
    # what handing the results to the driver cost each side, a sample at a time
    handoff = next(line for line in report.summary if line.startswith("hand-off"))
    assert re.fullmatch(
        r"hand-off: the workers' making threads [\d.]+ s \([\d.]+ ms a sample\) handing "
        r"results over, the driver's thread [\d.]+ s \([\d.]+ ms a sample\) taking them "
        r"and [\d.]+ s waiting for the workers", handoff), handoff


@pytest.mark.parametrize("memfd", [True, False], ids=["anonymous-file", "no-anonymous-file"])
def test_a_devices_run_with_a_full_dev_shm_writes_the_serial_set_and_says_how_it_went(
        tmp_path, photos, monkeypatch, capsys, memfd):
    if memfd and not shared_results.MEMFD:
        pytest.skip("anonymous files: Linux")
    # a container's samples go through the driver: a PNG set's are written by the workers
    serial = tmp_path / "serial"
    assert main(args(photos, serial, "--format", "webdataset")) == 1
    monkeypatch.setattr(shared_results, "SharedMemory", FullSharedMemory)  # the driver's
    monkeypatch.setattr(shared_results, "MEMFD", memfd)
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(args(photos, out, "--format", "webdataset", "--devices", "numpy,numpy")) == 1
    assert shards(out) == shards(serial) and len(shards(out)) == 1
    assert (out / "manifest.jsonl").read_bytes() == (serial / "manifest.jsonl").read_bytes()
    handoff = next(line for line in capsys.readouterr().out.splitlines()
                   if line.startswith("hand-off"))
    # in anonymous files, nothing through the pipes; else the 4 made samples, of the 6 taken
    # (the 2 failed ones are small messages anyway)
    piped = ("; 4 of 6 samples came through the workers' pipes, no shared memory being had "
             "(a full or small /dev/shm? `df -h /dev/shm`; in Docker, `--shm-size`)")
    assert handoff.endswith(piped) != memfd, handoff


def test_a_devices_run_times_both_sides_of_handing_each_sample_to_the_driver(
        photos, monkeypatch):
    monkeypatch.setattr(distributed, "default_io_threads", lambda: 4)  # 2 a worker
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy", bits=8)
    specs = find_samples(folder, "trajectory", 1, 2).take()
    times = PoolTimes(2)
    made = list(run_devices(job, specs, ["numpy", "numpy"], pool_times=times))
    handoff = times.handoff
    assert handoff["samples"] == len(made) == len(specs)
    assert handoff["piped"] == 0  # every sample through shared memory
    # the workers' packing (into shared memory), the driver's taking and its waits
    assert handoff["packing"] > 0 and handoff["receiving"] > 0 and handoff["waiting"] > 0
    again = pickle.loads(pickle.dumps(times))  # as a worker's pool crosses to the driver
    total = PoolTimes(1)
    total.add(again)
    total.add(again)
    assert total.handoff == {key: 2 * value for key, value in handoff.items()}


def test_a_worker_sends_the_codes_the_writer_writes_and_no_unsaved_mask(tmp_path, photos):
    folder, scene_path = photos
    spec = find_samples(folder, "trajectory", 1, 2).take()[0]
    full = run_serial(Job(load_scene(scene_path), 3, "numpy"), [spec])
    _, made, _ = next(full)
    job = Job(load_scene(scene_path), 3, "numpy", bits=8, with_mask=False)
    sent = pickle.loads(pickle.dumps(for_driver(job, made)))
    assert sent.blurred.dtype == np.uint8 and sent.mask is None
    assert len(pickle.dumps(sent)) < len(pickle.dumps(made)) / 3
    for name in ("blurred", "sharp"):
        write_image(tmp_path / f"full_{name}.png", getattr(made, name), 8)
        write_image(tmp_path / f"sent_{name}.png", getattr(sent, name), 8)
        assert ((tmp_path / f"sent_{name}.png").read_bytes()
                == (tmp_path / f"full_{name}.png").read_bytes())
    kept = for_driver(Job(load_scene(scene_path), 3, "numpy", bits=8, with_mask=True), made)
    np.testing.assert_array_equal(kept.mask, made.mask)


def test_devices_write_the_serial_run_s_masks_and_16_bit_images(tmp_path, photos):
    folder, scene_path = photos
    scene = tmp_path / "scene16.toml"
    scene.write_text(scene_path.read_text() + "[output]\nbits = 16\n")
    outs = []
    for extra in ([], ["--devices", "numpy,numpy"]):
        out = tmp_path / f"out{len(outs)}"
        argv = args(photos, out, "--backend", "numpy", "--save", "mask", *extra)
        argv[argv.index("--scene") + 1] = str(scene)
        assert main(argv) == 1  # c.png's samples fail
        outs.append(out)
    masks = [{f.name: f.read_bytes() for f in sorted((out / "mask").iterdir())} for out in outs]
    assert len(masks[1]) == 4 and masks[1] == masks[0]
    assert files(outs[1]) == files(outs[0])


def test_a_ray_task_whose_worker_dies_is_retried_and_the_run_completes(
        ray_local, tmp_path, photos, reference, monkeypatch):
    marker = tmp_path / "died-once"
    monkeypatch.setenv(TEST_FAIL_ONCE, f"2:{marker}")
    out = tmp_path / "out"
    assert main(args(photos, out, "--ray", "auto")) == 1  # only c.png's samples fail
    assert marker.exists()  # the first attempt at sample 2 did kill its worker
    assert_same_set(out, reference())


def test_a_ray_task_failing_past_its_retries_stops_the_run_and_resume_finishes_it(
        ray_local, tmp_path, photos, reference, monkeypatch, capsys):
    marker = tmp_path / "died-once"
    monkeypatch.setenv(TEST_FAIL_ONCE, f"2:{marker}")
    out = tmp_path / "out"
    assert main(args(photos, out, "--ray", "auto", "--retries", "0")) == 2
    err = capsys.readouterr().err
    assert "sample 2 (b_0): the Ray task failed 1 time(s) (--retries 0)" in err
    assert "run the same command with --resume" in err
    assert 2 not in [x["index"] for x in manifest_lines(out)]
    assert main(args(photos, out, "--ray", "auto", "--resume")) == 1
    assert_same_set(out, reference())


def test_run_ray_in_batches_yields_the_serial_results_with_the_callers_specs(
        ray_local, photos):
    folder, scene_path = photos
    scene = load_scene(scene_path)
    specs = find_samples(folder, "trajectory", 1, 2).take()
    job = Job(scene, 3, "numpy")
    serial = {s.index: (s, r, e) for s, r, e in run_serial(job, specs)}
    got = list(run_ray(job, specs, batch=4))
    assert sorted(s.index for s, _, _ in got) == [s.index for s in specs]
    for spec, result, error in got:
        want_spec, want, want_error = serial[spec.index]
        assert spec is specs[spec.index] and error == want_error
        if want is None:
            assert result is None
            continue
        np.testing.assert_array_equal(result.blurred, want.blurred)
        np.testing.assert_array_equal(result.sharp, want.sharp)
        np.testing.assert_array_equal(result.mask, want.mask)
        assert pickle.dumps(result.params) == pickle.dumps(want.params)


def test_ray_without_ray_installed_says_how_to_install_it(tmp_path, photos, monkeypatch,
                                                          capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    out = tmp_path / "out"
    assert main(args(photos, out, "--ray", "auto")) == 2
    assert "--ray needs Ray, which is not installed: pip install 'gpu_blur[ray]'" in (
        capsys.readouterr().err)
    assert not out.exists()  # refused before any work


@pytest.mark.parametrize("extra, message", [
    (["--devices", "opencl:9:9"], "--devices opencl:9:9: not a numpy device (--backend numpy)"),
    (["--devices", "cuda:0"], "--devices cuda:0: not a numpy device"),
    (["--devices", "numpy,,numpy"], "--devices 'numpy,,numpy': an empty device name"),
    pytest.param(["--backend", "opencl", "--devices", "opencl:9:9"],
                 "--devices opencl:9:9: no such device; opencl devices here: ",
                 marks=pytest.mark.skipif(not OPENCL, reason="no usable OpenCL device")),
    pytest.param(["--backend", "warp:cpu", "--devices", "warp:cpu,warp:cuda:99"],
                 "--devices warp:cuda:99: no such device; warp devices here: ",
                 marks=pytest.mark.skipif(WARP is None, reason="warp-lang not installed")),
    (["--retries", "2"], "--gpus-per-task, --retries and --ray-batch apply to --ray"),
])
def test_bad_device_options_are_refused_before_any_work(tmp_path, photos, capsys, extra,
                                                        message):
    out = tmp_path / "out"
    assert main(args(photos, out, *extra)) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
    assert not multiprocessing.active_children()  # workers started early were stopped


def test_devices_workers_start_before_the_set_up_and_stop_when_it_refuses_the_run(
        tmp_path, photos, reference, monkeypatch):
    started = []

    class Recorded(distributed.DeviceWorkers):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            started.append(self)

    monkeypatch.setattr(distributed, "DeviceWorkers", Recorded)
    out = tmp_path / "out"
    assert main(args(photos, out, "--devices", "numpy,numpy")) == 1
    assert_same_set(out, reference("numpy"))  # made by the workers started early
    assert len(started) == 1 and not multiprocessing.active_children()
    # the folder holds a set now: refused after the workers started, which stop
    assert main(args(photos, out, "--devices", "numpy,numpy")) == 2
    assert len(started) == 2 and not multiprocessing.active_children()
    # a resume makes the two failed samples again (c.png is still cut)
    assert main(args(photos, out, "--devices", "numpy,numpy", "--resume")) == 1
    assert len(started) == 3 and not multiprocessing.active_children()
    assert_same_set(out, reference("numpy"))


def test_devices_all_starts_its_workers_early_and_anew_when_counted_otherwise(
        tmp_path, photos, reference, monkeypatch):
    started, stops, out = [], [], tmp_path / "out"

    class Recorded(distributed.DeviceWorkers):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            started.append((self, out.exists()))  # the set's folder: made by the set-up

        def stop(self, finished=False):
            stops.append((len(started), self.devices, finished))
            super().stop(finished)

    monkeypatch.setattr(distributed, "DeviceWorkers", Recorded)
    monkeypatch.setattr(distributed, "usable_cores", lambda: 2)  # --devices all: two workers
    assert main(args(photos, out, "--devices", "all")) == 1
    assert_same_set(out, reference("numpy"))
    # started before the set-up, as counted, and they made the set
    assert [(w.devices, later) for w, later in started] == [(["numpy", "numpy"], False)]
    # counted as one device where all stands for two: it stops, two start for the run
    monkeypatch.setattr(distributed, "counted_devices", lambda backend: ["numpy"])
    started.clear(), stops.clear()
    out = tmp_path / "out2"
    assert main(args(photos, out, "--devices", "all")) == 1
    assert_same_set(out, reference("numpy"))
    assert [(w.devices, later) for w, later in started] == [(["numpy"], False),
                                                            (["numpy", "numpy"], True)]
    assert stops[0] == (1, ["numpy"], False)  # stopped before the run's started
    assert not multiprocessing.active_children()


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="no CPU affinity here")
def test_devices_all_with_numpy_is_a_worker_per_core_this_process_may_use(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 128)  # the host's; the process may use 2
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 5})
    assert parse_devices("all", "numpy") == ["numpy", "numpy"]


def test_counted_devices_guess_all_without_opening_a_runtime(monkeypatch):
    monkeypatch.setattr(distributed, "usable_cores", lambda: 3)
    assert distributed.counted_devices("numpy") == ["numpy"] * 3
    assert distributed.counted_devices("opencl") is None
    assert distributed.counted_devices("opencl:0:0") is None
    for count, names in ((2, ["warp:cuda:0", "warp:cuda:1"]), (0, None), (None, None)):
        monkeypatch.setattr(distributed, "_cuda_device_count", lambda count=count: count)
        assert distributed.counted_devices("warp") == names
        assert distributed.counted_devices("warp:cpu") == names


class FakeCuda:
    """libcuda's cuInit and cuDeviceGetCount answering ``init`` and ``count``."""

    def __init__(self, init: int, count: int):
        self.init, self.count = init, count

    def cuInit(self, flags):  # noqa: N802 (the driver API's name)
        return self.init

    def cuDeviceGetCount(self, pointer):  # noqa: N802
        pointer._obj.value = self.count
        return 0


def test_the_cuda_count_comes_from_the_driver_and_none_without_one(monkeypatch):
    import ctypes

    monkeypatch.setattr(ctypes, "CDLL", lambda name: FakeCuda(0, 4))
    assert distributed._cuda_device_count() == 4
    monkeypatch.setattr(ctypes, "CDLL", lambda name: FakeCuda(100, 0))  # no device
    assert distributed._cuda_device_count() is None

    def missing(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(ctypes, "CDLL", missing)
    assert distributed._cuda_device_count() is None


def test_devices_and_ray_exclude_each_other(tmp_path, photos):
    with pytest.raises(SystemExit):
        main(args(photos, tmp_path / "out", "--devices", "all", "--ray", "auto"))


def test_devices_all_is_every_usable_device_of_the_backend():
    assert parse_devices("all", "numpy") == ["numpy"] * distributed.usable_cores()
    if OPENCL:
        from gpu_blur.backends.opencl import device_rank

        ranked = sorted(OPENCL, key=device_rank)  # the order `opencl` picks in
        gpus = [d.spec for d in ranked if d.kind == "GPU"]
        assert parse_devices("all", "opencl") == (gpus or [d.spec for d in ranked])
    if WARP is not None:
        cuda = [d["spec"] for d in WARP if d["spec"].startswith("warp:cuda")]
        assert parse_devices("all", "warp:cpu") == (cuda or ["warp:cpu"])


def test_a_device_that_cannot_open_stops_the_run_before_any_sample(photos):
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy")
    specs = find_samples(folder, "trajectory", 1, 1).take()
    with pytest.raises(RuntimeError, match="--devices nosuch: unknown backend 'nosuch'"):
        next(run_devices(job, specs, ["numpy", "nosuch"]))


def test_a_job_pickles(photos):
    _, scene_path = photos
    job = Job(load_scene(scene_path), 7, "opencl:0:0", (16, 16))
    assert pickle.loads(pickle.dumps(job)) == job


def test_a_device_workers_own_error_stops_the_run_naming_the_sample_with_its_traceback(photos):
    folder, scene_path = photos
    # a bug: a scene that is no Scene (the worker opens its backend, then load_scene fails)
    not_a_scene = types.SimpleNamespace(output=types.SimpleNamespace(precision="float32"))
    job = Job(not_a_scene, 0, "numpy")
    specs = find_samples(folder, "trajectory", 1, 1).take()
    with pytest.raises(RuntimeError) as e:
        list(run_devices(job, specs, ["numpy"]))
    assert str(e.value).startswith("the worker on numpy failed on sample 0 (a), not for a "
                                   "fault of the sample:\nTraceback (most recent call last):")


# -- results through shared memory (gpu_blur.shared_results) ---------------------------------

@pytest.fixture
def blocks_made(monkeypatch):
    """The names of the shared-memory blocks this process (the driver) makes from now on."""
    made = []

    class Recorded(SharedMemory):
        def __init__(self, name=None, create=False, size=0):
            super().__init__(name, create, size)
            if create:
                made.append(self.name)

    monkeypatch.setattr(shared_results, "SharedMemory", Recorded)
    return made


def left_behind(names):
    """Those of ``names`` that still exist as shared memory."""
    left = []
    for name in names:
        try:
            block = SharedMemory(name)
        except FileNotFoundError:
            continue
        block.close()
        block.unlink()  # for the next tests; this one fails
        left.append(name)
    return left


def assert_same_result(got, want, timings=True):
    """Two Synthesis objects hold the same bytes: arrays by dtype, shape and bytes, every other
    field pickled (``timings`` False: but the seconds measured, which differ run to run)."""
    assert (got is None) == (want is None)
    if want is None:
        return
    for field in dataclasses.fields(want):
        a, b = getattr(got, field.name), getattr(want, field.name)
        if isinstance(b, np.ndarray):
            assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes()), field
        elif timings or field.name != "timings":
            assert pickle.dumps(a) == pickle.dumps(b), field.name


def handed_over(results):
    """``results`` through an Outbox (a thread standing in for the worker) and Blocks."""
    driver, worker = multiprocessing.Pipe()
    outbox = shared_results.Outbox(worker, lambda message: pytest.fail(f"{message!r}"))

    def send():
        for result in results:
            worker.send(("sample", outbox.pack(result)))
        worker.send(("done", None))

    thread = threading.Thread(target=send)
    thread.start()
    blocks, got = shared_results.Blocks(), []
    try:
        while True:
            kind, value = driver.recv()
            if kind == shared_results.ASK:
                blocks.answer(driver, *value)
            elif kind == "sample":
                shell, layout = value
                got.append(shell if layout is None else blocks.receive(driver, shell, layout))
            else:
                break
        thread.join()
        return got, len(blocks)
    finally:
        outbox.close()
        blocks.close()


RAW_SCENE = {"blur": {"steps": 3}, "noise": {"model": "poisson-gaussian"}}


@pytest.mark.parametrize("bits, extras", [(8, ()), (16, ("mask", "raw")), (0, ("mask",))],
                         ids=["8-bit", "16-bit-mask-raw", "float32-mask"])
def test_a_result_through_shared_memory_is_the_made_result_byte_for_byte(
        photos, blocks_made, bits, extras):
    folder, _ = photos
    scene = scene_from_dict({**RAW_SCENE, "output": {"bits": bits}})
    job = Job(scene, 5, "numpy", with_raw="raw" in extras, bits=bits,
              with_mask="mask" in extras)
    specs = find_samples(folder, "trajectory", 1, 1).take()  # a, b, c (truncated: fails)
    made = [for_driver(job, result) for _, result, _ in run_serial(job, [*specs, specs[0]])]
    assert made[2] is None and made[0].blurred.dtype == {8: np.uint8, 16: np.uint16,
                                                         0: np.float32}[bits]
    got, in_use = handed_over(made)
    for g, want in zip(got, made, strict=True):
        assert_same_result(g, want)
    assert (got[0].raw is not None, got[0].mask is not None) == ("raw" in extras,
                                                                 "mask" in extras)
    assert in_use == len(blocks_made) == 2  # two blocks, reused: 3 samples went through them
    assert left_behind(blocks_made) == []


class FullSharedMemory(SharedMemory):
    """Shared memory where /dev/shm is full: making a block fails (posix_fallocate's ENOSPC)."""

    def __init__(self, name=None, create=False, size=0):
        if create:
            raise OSError(28, "No space left on device")
        super().__init__(name, create, size)


@pytest.mark.skipif(not shared_results.MEMFD, reason="anonymous files: Linux")
def test_where_dev_shm_is_full_results_go_through_anonymous_shared_memory_and_leave_nothing(
        photos, monkeypatch):
    monkeypatch.setattr(shared_results, "SharedMemory", FullSharedMemory)
    folder, _ = photos
    job = Job(scene_from_dict(RAW_SCENE), 5, "numpy", bits=8, with_mask=False)
    specs = find_samples(folder, "trajectory", 1, 1).take()
    made = [for_driver(job, result) for _, result, _ in run_serial(job, specs)]
    gc.collect()  # descriptors earlier tests left to the collector go now, not mid-count
    descriptors = len(os.listdir("/proc/self/fd"))
    got, in_use = handed_over(made)
    assert in_use == 2  # the two blocks, anonymous files passed to the worker's side
    for g, want in zip(got, made, strict=True):
        assert_same_result(g, want)
    del got  # the arrays were copied out; every descriptor of the blocks is closed
    assert len(os.listdir("/proc/self/fd")) == descriptors


def test_where_no_shared_memory_can_be_had_results_go_whole_through_the_pipe(photos,
                                                                            monkeypatch):
    monkeypatch.setattr(shared_results, "SharedMemory", FullSharedMemory)
    monkeypatch.setattr(shared_results, "MEMFD", False)  # nor an anonymous file
    folder, _ = photos
    job = Job(scene_from_dict(RAW_SCENE), 5, "numpy", bits=8, with_mask=False)
    specs = find_samples(folder, "trajectory", 1, 1).take()
    made = [for_driver(job, result) for _, result, _ in run_serial(job, specs)]
    got, in_use = handed_over(made)
    assert in_use == 0
    for g, want in zip(got, made, strict=True):
        assert_same_result(g, want)


def test_devices_hand_a_serial_run_s_16_bit_samples_masks_and_mosaics_through_shared_memory(
        photos, blocks_made):
    folder, _ = photos
    scene = scene_from_dict({**RAW_SCENE, "output": {"bits": 16}})
    job = Job(scene, 5, "numpy", with_raw=True, bits=16, with_mask=True)
    specs = find_samples(folder, "trajectory", 1, 2).take()  # c's two samples fail
    got = {spec.index: (spec, result, error) for spec, result, error
           in run_devices(job, specs, ["numpy", "numpy"])}
    for spec, result, error in run_serial(job, specs):
        assert got[spec.index][0] is spec and got[spec.index][2] == error
        assert_same_result(got[spec.index][1], for_driver(job, result), timings=False)
    assert [got[i][1] is None for i in range(6)] == [False] * 4 + [True] * 2
    assert len(blocks_made) >= 2 and left_behind(blocks_made) == []  # one or two per worker


def started_devices(photos, samples_per_photo=4):
    """A run on two numpy workers, its first sample received; (the generator, its workers)."""
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy", bits=8)
    specs = find_samples(folder, "trajectory", 1, samples_per_photo).take()
    before = set(multiprocessing.active_children())
    results = run_devices(job, specs, ["numpy", "numpy"])
    next(results)
    return results, [p for p in multiprocessing.active_children() if p not in before]


def test_a_run_stopped_early_leaves_no_shared_memory_and_no_worker(photos, blocks_made):
    results, workers = started_devices(photos)
    assert len(workers) == 2 and blocks_made
    results.close()  # what Ctrl-C, SetInterrupted or an error in the driver do
    assert not any(w.is_alive() for w in workers)
    assert left_behind(blocks_made) == []


def test_a_worker_killed_mid_run_stops_it_and_leaves_no_shared_memory(photos, blocks_made):
    # enough samples that the killed worker still has some to make on a fast host (with 4 a
    # photo, a 16-core host's worker had made all of its own before the kill)
    results, workers = started_devices(photos, samples_per_photo=32)
    assert blocks_made
    workers[0].kill()
    with pytest.raises(RuntimeError, match="the worker on numpy died"):
        list(results)
    assert not any(w.is_alive() for w in workers)
    assert left_behind(blocks_made) == []


def folder_writes(out, bits=8):
    """What the driver hands device workers to write a PNG set in ``out`` (its pid)."""
    from gpu_blur.dataset import FolderWrites, SampleFiles

    return FolderWrites(SampleFiles(out, bits, "fast", (), os.getpid()),
                        {"seed": 0, "backend": "numpy", "device": "host"})


def test_device_workers_writing_a_png_set_send_no_image_through_shared_memory(
        tmp_path, photos, reference, blocks_made):
    out = tmp_path / "out"
    assert main(args(photos, out, "--backend", "numpy", "--devices", "numpy,numpy",
                     "--io-threads", "4")) == 1
    assert_same_set(out, reference("numpy"))
    assert blocks_made == []  # the images never left the workers


def test_device_workers_send_each_written_sample_s_line_and_write_its_files(tmp_path, photos):
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy", bits=8)
    specs = find_samples(folder, "trajectory", 1, 2).take()
    out = tmp_path / "out"
    (out / "blur").mkdir(parents=True)
    (out / "sharp").mkdir()
    made = sorted(run_devices(job, specs, ["numpy", "numpy"], writes=folder_writes(out),
                              io_threads=4), key=lambda sample: sample[0].index)
    written = [(spec, saved) for spec, saved, error in made if error is None]
    assert len(written) == 4 and all(isinstance(saved, Saved) for _, saved in written)
    for spec, saved in written:
        assert saved.error is None and saved.line["index"] == spec.index
        for key in ("blurred", "sharp"):  # the files the line names, of the sizes it says
            assert (out / saved.line[key]).stat().st_size == saved.line["bytes"][key]
    assert not [p for p in out.rglob(".*") if p.is_file()]  # no temporary file left


def test_a_worker_that_cannot_write_sends_the_error_for_the_driver_to_stop_on(
        tmp_path, photos):
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy", bits=8)
    specs = find_samples(folder, "trajectory", 1, 2).take()[:2]
    out = tmp_path / "out"
    out.mkdir()
    (out / "blur").write_text("a file where the blur/ folder goes")
    made = list(run_devices(job, specs, ["numpy"], writes=folder_writes(out)))
    assert len(made) == 2
    for _, saved, error in made:
        assert error is None and saved.line is None
        assert isinstance(saved.error, FileExistsError), saved.error


def test_a_worker_whose_driver_is_gone_renames_no_file_into_the_folder(tmp_path, photos):
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy", bits=8)
    spec = find_samples(folder, "trajectory", 1, 2).take()[0]
    _, result, _ = next(run_serial(job, [spec]))
    out = tmp_path / "out"
    out.mkdir()  # the driver's writer made it
    # the driver that started this "worker" is not its parent any more (it was killed)
    saved = distributed._write_made(folder_writes(out), os.getppid() + 1, spec, result)
    assert saved.line is None and "driver process is gone" in str(saved.error)
    assert [p for p in out.rglob("*") if p.is_file()] == []  # nor its temporary file
    kept = distributed._write_made(folder_writes(out), os.getppid(), spec, result)
    assert kept.error is None and (out / kept.line["blurred"]).is_file()


def test_a_stopped_run_removes_the_temporary_files_of_the_samples_its_workers_were_writing(
        tmp_path, photos):
    folder, scene_path = photos
    job = Job(load_scene(scene_path), 0, "numpy", bits=8)
    specs = find_samples(folder, "trajectory", 1, 2).take()[:4]  # a's and b's
    out = tmp_path / "out"
    for sub in ("blur", "sharp"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    writes = folder_writes(out)
    # one thread a worker: each is sent two samples at once, so all four are out
    results = run_devices(job, specs, ["numpy", "numpy"], writes=writes, io_threads=2)
    first, _, _ = next(results)
    # what a worker terminated mid-write leaves: temporary files of the samples in flight
    planted = [t for spec in specs if spec is not first for t in writes.files.temporaries(spec)
               if t.parent.name in ("blur", "sharp")]
    for temporary in planted:
        temporary.write_bytes(b"cut")
    results.close()  # Ctrl-C, an error in the driver
    assert len(planted) == 6 and not [p for p in out.rglob(".*") if p.is_file()]


def test_samples_sharing_inputs_go_to_one_worker_in_runs_of_consecutive_samples():
    def spec(index, *frames):
        return SampleSpec(index, f"s{index}", tuple(Path(f"{f}.png") for f in frames))

    windows = [spec(i, i, i + 1, i + 2) for i in range(40)]  # one sequence, stride 1
    photos = [spec(40 + i, f"p{i}") for i in range(3)]  # one sample per photo
    runs = distributed._Runs(windows + photos, 2)

    def take(worker, count):
        return [runs.next(worker).index for _ in range(count)]

    n = distributed.RUN_SAMPLES  # 16: runs 0-15, 16-31, 32-39, then a photo each
    assert take(0, 1) + take(1, 1) == [0, n]
    assert take(0, n) == [*range(1, n), 2 * n]  # its run's rest, then the next run
    assert take(1, n + 1) == [*range(n + 1, 2 * n), 40, 41]
    assert take(0, 8) == [*range(2 * n + 1, 40), 42]
    assert runs.next(0) is None and runs.next(1) is None
    few = distributed._Runs(windows[:4], 2)  # no more than an equal share in one run
    assert [few.next(0).index, few.next(0).index, few.next(1).index] == [0, 1, 2]


@pytest.mark.parametrize("threads", [2, 8])
def test_each_device_worker_decodes_overlapping_windows_once_through_its_frame_cache(
        tmp_path, monkeypatch, threads):
    # the samples sent ahead to a worker grow with its decoding threads (the host's cores
    # shared among the workers): one a worker, as on a 2-core host (each worker makes its
    # samples in turn), or four, each worker running the one-device pipeline
    monkeypatch.setattr(distributed, "default_io_threads", lambda: threads)
    rng = np.random.default_rng(1)
    sequence = tmp_path / "in" / "seq" / "sharp"
    sequence.mkdir(parents=True)
    for i in range(6):
        cv2.imwrite(str(sequence / f"{i:03d}.png"), rng.integers(0, 256, (16, 20, 3), np.uint8))
    scene = {"blur": {"mode": "average", "frames": 3, "steps": 3}}
    sets = {executor: gpu_blur.generate_set(tmp_path / executor, input=tmp_path / "in",
                                            scene=scene, samples_per_sequence=4,
                                            devices=devices)
            for executor, devices in (("serial", None), ("devices", "numpy,numpy"))}
    cached = next(line for line in sets["devices"].summary if line.startswith("frame cache"))
    if threads == 2:  # windows 0-1 to one worker, 2-3 to the other: 4 frames each, 2 read twice
        assert cached == "frame cache: 8 decoded, 4 served decoded (33 % of 12 reads), 0 evicted"
    else:  # eight samples sent ahead to each: the first worker may take every window
        decoded = int(re.match(r"frame cache: (\d+) decoded, (\d+) served", cached)[1])
        assert 6 <= decoded <= 8, cached

    def written(out):  # every file: blur/, sharp/, manifest.jsonl, run.json
        return {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*")
                if p.is_file()}

    assert written(tmp_path / "devices") == written(tmp_path / "serial")


def test_a_workers_device_png_streams_cross_to_the_driver_and_write_the_same_files(
        tmp_path, photos):
    # streams deflated on a worker's GPU lie over its page-locked blocks: they cross as bytes
    from gpu_blur.dataset import SampleFiles
    from gpu_blur.png_codecs import filtered_rows, huffman_zlib

    folder, scene_path = photos
    spec = find_samples(folder, "trajectory", 1, 2).take()[0]
    job = Job(load_scene(scene_path), 3, "numpy", bits=8, with_mask=False)
    _, made, _ = next(run_serial(job, [spec]))
    made = for_driver(job, made)
    streams = {}
    for name in ("blurred", "sharp"):
        stream = memoryview(huffman_zlib(filtered_rows(getattr(made, name))))
        streams[name] = (stream[:2], stream[2:-4], stream[-4:])  # as the device's parts
    with_streams = dataclasses.replace(made, png=streams)
    sent = pickle.loads(pickle.dumps(with_streams))
    assert all(len(parts) == 1 and isinstance(parts[0], bytes) for parts in sent.png.values())
    files = SampleFiles(tmp_path, 8, "fast", (), 1)
    paths = {"blurred": "b.png", "sharp": "s.png", "arrays": "p.npz"}
    _, from_streams = files.encode(spec, sent, {}, paths)
    _, encoded = files.encode(spec, made, {}, paths)
    assert from_streams == encoded
    other = dataclasses.replace(made, png={"blurred": (b"x",)})  # the stream is what is written
    assert files.encode(spec, other, {}, paths)[1]["blurred"] != encoded["blurred"]
