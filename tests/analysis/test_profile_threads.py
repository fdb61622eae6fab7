"""bench/profile_threads.py sums py-spy's samples by process and thread group."""

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench" / "profile_threads.py"


@pytest.fixture(scope="module")
def profile_threads():
    spec = importlib.util.spec_from_file_location("profile_threads", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


DRIVER = 'process 10:"python -m gpu_blur.cli generate --devices a,b"'
WORKER = ('process 11:"/usr/bin/python -B -c from multiprocessing.spawn import spawn_main; '
          'spawn_main(tracker_fd=8) --multiprocessing-fork"')
TRACKER = 'process 12:"/usr/bin/python -c from multiprocessing.resource_tracker import main"'
RAW = [
    f"{DRIVER};thread (10): MainThread;run (gpu_blur/generation.py:550);"
    "_device_results (gpu_blur/distributed.py:470);wait (multiprocessing/connection.py:930) 30",
    f"{DRIVER};thread (21): gpu-blur-io_0;_worker (concurrent/futures/thread.py:83);"
    "save (gpu_blur/generation.py:480);encode_png (gpu_blur/png_codecs.py:200) 20",
    f"{DRIVER};thread (22): gpu-blur-io_1;_worker (concurrent/futures/thread.py:81) 10",
    f"{DRIVER};{WORKER};thread (11): MainThread;_device_worker (gpu_blur/distributed.py:300);"
    "pack (gpu_blur/shared_results.py:170);copyto (numpy/_core/multiarray.py:1) 40",
    f"{DRIVER};{TRACKER};thread (12): MainThread;main (multiprocessing/resource_tracker.py:2) 50",
    "a line py-spy did not write",
]


def test_samples_sum_per_process_and_pool_with_our_deepest_frame_and_the_leaf(profile_threads):
    rows = {(r["process"], r["group"]): r for r in profile_threads.summarize(RAW, rate=100)}
    # the resource tracker left out; a worker whose command line holds a ';' is one process
    assert set(rows) == {("10 (driver)", "MainThread"), ("10 (driver)", "gpu-blur-io"),
                         ("11 (worker)", "MainThread")}
    pool = rows["10 (driver)", "gpu-blur-io"]
    assert (pool["threads"], pool["seconds"]) == (2, pytest.approx(0.3))
    assert pool["where"] == {"encode_png (gpu_blur/png_codecs.py)": pytest.approx(0.2),
                             "outside": pytest.approx(0.1)}
    assert pool["leaf"] == {"encode_png (gpu_blur/png_codecs.py)": pytest.approx(0.2),
                            "_worker (concurrent/futures/thread.py)": pytest.approx(0.1)}
    worker = rows["11 (worker)", "MainThread"]
    assert worker["where"] == {"pack (gpu_blur/shared_results.py)": pytest.approx(0.4)}
    assert worker["leaf"] == {"copyto (numpy/_core/multiarray.py)": pytest.approx(0.4)}
    # most sampled first
    assert [r["seconds"] for r in profile_threads.summarize(RAW, rate=100)] == sorted(
        [r["seconds"] for r in rows.values()], reverse=True)
