"""``gpu-blur generate`` on one device decodes ahead and writes behind in I/O threads
(``--io-threads``, issue 15): the same bytes as one thread doing each step in turn, bad inputs
failing only their samples with the same messages, and nothing lost or half-written when a
write fails or the run is stopped.

Small images and the numpy backend throughout.
"""

import errno
import os
import re
import threading
import time

import cv2
import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS, files, manifest_lines

import gpu_blur.backends
import gpu_blur.dataset
import gpu_blur.file_writing
import gpu_blur.generate
import gpu_blur.notices
import gpu_blur.staging
import gpu_blur.synthesis.inputs
import gpu_blur.testhooks
from gpu_blur.cli import main
from gpu_blur.dataset import LOCK

IO_THREAD = "gpu-blur-io"


def args(folder, scene, out, *extra):
    return ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--quiet", *extra]


@pytest.fixture
def bad_photos(tmp_path):
    """Six photos of 24 x 32, three of them bad: truncated, empty, float values above 1."""
    folder = tmp_path / "in"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b", "c", "d"):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(0, 256, (24, 32, 3), np.uint8))
    (folder / "b.png").write_bytes((folder / "b.png").read_bytes()[:60])
    (folder / "e.png").write_bytes(b"")
    cv2.imwrite(str(folder / "f.tiff"), np.full((24, 32, 3), 1.5, np.float32))
    scene = tmp_path / "s.toml"
    scene.write_text("[blur]\nsteps = 3\n")
    return folder, scene


@pytest.fixture
def bad_sequences(tmp_path):
    """Three 3-frame sequences: a good one, one with a frame of another size, one with NaN."""
    folder = tmp_path / "seqs"
    rng = np.random.default_rng(1)
    for name in ("a_good", "b_sizes", "c_nan"):
        (folder / name / "sharp").mkdir(parents=True)
        for i in range(3):
            shape = (20, 28) if name == "b_sizes" and i == 2 else (24, 32)
            cv2.imwrite(str(folder / name / "sharp" / f"{i}.png"),
                        rng.integers(0, 256, (*shape, 3), np.uint8))
    frame = rng.random((24, 32, 3)).astype(np.float32)
    frame[3, 4, 1] = np.nan
    (folder / "c_nan" / "sharp" / "1.png").unlink()
    cv2.imwrite(str(folder / "c_nan" / "sharp" / "1.tiff"), frame)
    scene = tmp_path / "avg.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 3\n')
    return folder, scene


def written(out):
    """{relative path: bytes} of every file in ``out`` but its lock (which names the run)."""
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name != LOCK}


def assert_same_set(out, reference):
    assert written(out) == written(reference)  # manifest, run.json, samples; no stray file


def add_long_sequence(folder, seed: int) -> None:
    """A fourth sequence, ``d_long``: ten random 24 x 32 frames, so that windows overlap."""
    rng = np.random.default_rng(seed)
    (folder / "d_long" / "sharp").mkdir(parents=True)
    for i in range(10):
        cv2.imwrite(str(folder / "d_long" / "sharp" / f"{i}.png"),
                    rng.integers(0, 256, (24, 32, 3), np.uint8))


@pytest.mark.parametrize("backend", ["numpy", *KERNEL_BACKEND_SPECS[:1]])
def test_io_threads_write_the_bytes_of_one_thread_and_fail_only_bad_photos(
        tmp_path, bad_photos, monkeypatch, backend):
    folder, scene = bad_photos
    run = ["--backend", backend.split("/")[0]]
    assert main(args(folder, scene, tmp_path / "one", *run, "--io-threads", "1")) == 1
    readers, writers = set(), set()
    read, write = gpu_blur.generate.read_image, gpu_blur.dataset.encode_image

    def reading(path):
        readers.add(threading.current_thread().name.startswith(IO_THREAD))
        return read(path)

    def writing(*a):
        writers.add(threading.current_thread().name.startswith(IO_THREAD))
        return write(*a)

    monkeypatch.setattr(gpu_blur.generate, "read_image", reading)
    monkeypatch.setattr(gpu_blur.dataset, "encode_image", writing)
    assert main(args(folder, scene, tmp_path / "three", *run, "--io-threads", "3")) == 1
    assert readers == {True} and writers == {True}  # decoded and written in the pool
    assert_same_set(tmp_path / "three", tmp_path / "one")
    errors = {x["name"]: x.get("error") for x in manifest_lines(tmp_path / "one")}
    assert errors["a"] is None and errors["c"] is None and errors["d"] is None
    assert errors["b"].startswith(f"{folder / 'b.png'}: truncated PNG")
    assert errors["e"].startswith(f"{folder / 'e.png'}: the file is empty")
    assert errors["f"].startswith(f"{folder / 'f.tiff'}: ") and "above 1" in errors["f"]


def test_io_threads_write_the_bytes_of_one_thread_and_fail_only_bad_sequences(
        tmp_path, bad_sequences):
    folder, scene = bad_sequences
    assert main(args(folder, scene, tmp_path / "one", "--io-threads", "1")) == 1
    assert main(args(folder, scene, tmp_path / "three", "--io-threads", "3")) == 1
    assert_same_set(tmp_path / "three", tmp_path / "one")
    errors = {x["name"].split("/")[0]: x.get("error") for x in manifest_lines(tmp_path / "one")}
    assert errors["a_good"] is None
    sharp = folder / "b_sizes" / "sharp"
    assert errors["b_sizes"].startswith(f"{sharp / '2.png'} is 28 x 20 (width x height) but "
                                        f"{sharp / '0.png'} is 32 x 24")
    assert errors["c_nan"].startswith(f"{folder / 'c_nan' / 'sharp' / '1.tiff'}: 1 NaN")


@pytest.mark.parametrize("threads", ["1", "3"])
def test_a_failing_write_stops_the_run_and_loses_nothing(tmp_path, photos, monkeypatch,
                                                         capsys, threads):
    folder, scene = photos
    reference = tmp_path / "reference"
    assert main(args(folder, scene, reference, "--samples-per-photo", "4")) == 0
    expected = (reference / "manifest.jsonl").read_text().splitlines(keepends=True)
    write_new = gpu_blur.file_writing.write_new

    def write_fails_on_sample_3(path, data):
        if path.name.startswith(".000003_"):
            with open(path, "wb") as f:  # half an image under the temporary name
                f.write(data[:len(data) // 2])
            raise OSError(errno.EIO, os.strerror(errno.EIO), str(path))
        return write_new(path, data)

    monkeypatch.setattr(gpu_blur.file_writing, "write_new", write_fails_on_sample_3)
    out = tmp_path / "out"
    run = args(folder, scene, out, "--samples-per-photo", "4", "--io-threads", threads)
    assert main(run) == 2
    assert "cannot write sample 3 (a_3)" in capsys.readouterr().err
    assert (out / "manifest.jsonl").read_text().splitlines(keepends=True) == expected[:3]
    made = files(reference)
    for name, data in files(out).items():  # listed or not, every file is whole
        assert data == made[name], name
    monkeypatch.undo()
    assert main([*run, "--resume"]) == 0
    assert_same_set(out, reference)


def test_ctrl_c_writes_the_samples_made_and_resume_finishes_the_set(tmp_path, photos,
                                                                    monkeypatch):
    folder, scene = photos
    reference = tmp_path / "reference"
    assert main(args(folder, scene, reference, "--samples-per-photo", "4")) == 0
    write = gpu_blur.dataset.encode_image

    def slowly(*a):  # writes lag behind synthesis, so made samples queue up
        time.sleep(0.05)
        return write(*a)

    def ctrl_c_after(index):  # Ctrl-C once sample 1 is recorded
        if index == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(gpu_blur.dataset, "encode_image", slowly)
    monkeypatch.setattr(gpu_blur.testhooks, "sleep_after", ctrl_c_after)
    out = tmp_path / "out"
    run = args(folder, scene, out, "--samples-per-photo", "4", "--io-threads", "3")
    assert main(run) == 130
    kept = manifest_lines(out)  # 0, 1 and those made before the stop, written on the way out
    assert [x["index"] for x in kept] == list(range(len(kept))) and len(kept) >= 3
    made = files(reference)
    assert set(files(out)) == {x[k] for x in kept for k in ("blurred", "sharp", "arrays")}
    for name, data in files(out).items():
        assert data == made[name], name
    monkeypatch.undo()
    assert main([*run, "--resume"]) == 0
    assert_same_set(out, reference)


@pytest.mark.parametrize("slow, threads, bound", [
    ("read_image", "2", "bound by: decode (synthesis waited"),
    ("encode_image", "2", "bound by: encode/write (synthesis waited"),
    (None, "2", "bound by: synthesis (synthesizing"),
    ("read_image", "1", "bound by: decode ("),
])
def test_the_summary_says_which_stage_bounded_the_run(tmp_path, photos, monkeypatch, capsys,
                                                      slow, threads, bound):
    folder, scene = photos
    users = {"read_image": [gpu_blur.generate, gpu_blur.synthesis.inputs],  # pipelined, serial
             "encode_image": [gpu_blur.dataset]}.get(slow, [])
    for module in users:
        work = getattr(module, slow)

        def slowly(*a, work=work):
            time.sleep(0.25)
            return work(*a)

        monkeypatch.setattr(module, slow, slowly)
    if slow is None:  # synthesis is slow
        make = gpu_blur.generate.synthesize

        def slowly(*a, **k):
            time.sleep(0.25)
            return make(*a, **k)

        monkeypatch.setattr(gpu_blur.generate, "synthesize", slowly)
    assert main(args(folder, scene, tmp_path / "out", "--io-threads", threads)) == 0
    out = capsys.readouterr().out
    assert bound in out, out
    # an encode-bound run of compressed PNGs is told of the fastest and stored modes
    encode_bound = slow == "encode_image" and threads == "2"
    assert ('output.png = "stored" (now "fast") writes these' in out) == encode_bound
    assert ('output.png = "fastest" compresses with ISA-L' in out) == encode_bound
    wall = float(re.search(r"where the time went \(([\d.]+) s\):", out)[1])
    spent = re.findall(r"^  [a-z]+ +([\d.]+) s +[\d.]+ %", out, re.MULTILINE)
    assert len(spent) == 6 and sum(map(float, spent)) == pytest.approx(wall, abs=0.01)
    assert ("I/O threads (2): decoding" in out) == (threads == "2")
    if threads == "2" and slow is not None:  # the bound's own figure: 0.25 s a sample or more
        what = "decoding a sample's inputs" if slow == "read_image" else "encoding and writing"
        figure = re.search(rf"{what}.* took a thread ([\d.]+) ms and .* ([\d.]+) ms, so 2 "
                           r"threads make at most ([\d.]+) samples/s", out)
        assert figure and float(figure[1]) >= 250 and float(figure[3]) <= 8, out
        # the same two threads do both: their ceiling counts both times
        both = (float(figure[1]) + float(figure[2])) / 1e3
        assert float(figure[3]) == pytest.approx(2 / both, abs=0.06), out


def test_the_io_threads_ceiling_counts_the_decodes_and_the_writes_they_both_do():
    from gpu_blur.timings import PoolTimes

    pool = PoolTimes(16)
    pool.busy, pool.calls, pool.samples = {"decode": 96.0, "write": 36.0}, {
        "decode": 2304, "write": 256}, 256
    assert pool.ceiling("decode") == (
        "decoding a sample's inputs took a thread 375.0 ms and encoding and writing it 140.6 "
        "ms, so 16 threads make at most 31.0 samples/s: more cores, more")
    assert pool.ceiling("write").startswith(
        "encoding and writing a sample took a thread 140.6 ms and decoding its inputs 375.0 "
        "ms, so 16 threads make at most 31.0 samples/s")
    pool.add_handoff(samples=256)  # --devices workers decoded, the driver's threads wrote
    assert pool.ceiling("decode") == ("decoding a sample's inputs took a thread 375.0 ms, so 16 "
                                      "threads make at most 42.7 samples/s: more cores, more")
    assert PoolTimes(2).ceiling("write") == "the threads wrote nothing"


@pytest.mark.parametrize("extra, message", [
    (["--io-threads", "0"], "--io-threads 0: must be >= 1"),
    (["--io-threads", "0", "--devices", "numpy,numpy"], "--io-threads 0: must be >= 1"),
])
def test_bad_io_threads_are_refused_before_any_work(tmp_path, photos, capsys, extra, message):
    folder, scene = photos
    assert main(args(folder, scene, tmp_path / "out", *extra)) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def kernel_backend():
    """The first kernel backend the suite runs (a CPU device here): its pinned memory is
    plain host memory, but its arrays end in a PinnedHost block as on a GPU."""
    from gpu_blur.backends import get_backend

    name, _, precision = KERNEL_BACKEND_SPECS[0].partition("/")
    return name, get_backend(name, precision or "float32")


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
def test_pinned_stack_finds_frames_staged_one_after_another_in_one_block():
    from gpu_blur.backends import pinned_stack

    _, backend = kernel_backend()
    stack = backend.pinned((3, 4, 5, 3), np.uint8)
    stack[:] = np.arange(stack.size, dtype=np.uint8).reshape(stack.shape)
    found = pinned_stack(tuple(stack), backend)
    assert found.shape == (3, 4, 5, 3) and np.shares_memory(found, stack)
    assert np.array_equal(found, stack)
    assert pinned_stack(list(stack[1:]), backend).shape == (2, 4, 5, 3)
    assert pinned_stack([stack[1], stack[0], stack[2]], backend) is None  # out of order
    assert pinned_stack([stack[0], stack[2]], backend) is None  # a gap
    assert pinned_stack([f.copy() for f in stack], backend) is None  # pageable memory
    assert pinned_stack(list(stack), object()) is None  # another backend's memory
    assert pinned_stack([stack[0][:, :4]], backend) is None  # not contiguous
    assert pinned_stack(stack[0], backend) is None  # one image, not a list


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
def test_lent_results_are_lent_again_only_once_every_array_over_them_is_gone(monkeypatch):
    from gpu_blur.backends import pinned_owner
    from gpu_blur.staging import LentResults

    _, backend = kernel_backend()
    locked, pinned = [], backend.pinned
    monkeypatch.setattr(backend, "pinned",
                        lambda shape, dtype: locked.append(shape) or pinned(shape, dtype))
    results = LentResults(backend, limit=400)
    codes, floats = ((2, 4, 5, 3), np.uint8), ((2, 4, 5), np.float32)  # 120 and 160 bytes
    first = results.take([codes, floats])
    assert [(a.shape, a.dtype) for a in first] == [(codes[0], np.uint8), (floats[0], np.float32)]
    assert all(pinned_owner(a) is backend for a in first)
    a, b = (x.ctypes.data for x in first)
    kept = first[0][1]  # a view of one sample keeps block a lent
    del first
    (second,) = results.take([codes])
    assert second.ctypes.data == b  # the free block that fits; a is still lent
    assert results.take([floats]) is None  # a third block would pass the 400 bytes
    del kept, second
    again = results.take([codes, floats])
    assert [x.ctypes.data for x in again] == [a, b]  # each the smallest free block that fits
    assert locked == [(120,), (160,)]  # page-locked once each


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
def test_lent_results_taken_back_by_the_cyclic_gc_inside_a_take_do_not_deadlock():
    import gc

    from gpu_blur.staging import LentResults

    _, backend = kernel_backend()
    results = LentResults(backend, limit=1000)
    codes = ((2, 4, 5, 3), np.uint8)
    cycle = [results.take([codes])[0]]
    cycle.append(cycle)  # only the cyclic GC frees it, whenever it runs
    address = cycle[0].ctypes.data
    del cycle

    class Collecting(list):  # the GC runs while take() walks the free blocks, lock held
        def __iter__(self):
            gc.collect()
            return super().__iter__()

    results._free = Collecting(results._free)
    got = []
    taking = threading.Thread(target=lambda: got.append(results.take([codes])), daemon=True)
    taking.start()
    taking.join(10)
    assert not taking.is_alive(), "take() deadlocked on its own lock"
    assert got[0][0].ctypes.data == address  # the block the GC gave back, lent again


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
def test_lent_results_that_cannot_be_page_locked_lend_nothing_and_keep_their_free_blocks(
        monkeypatch):
    from gpu_blur.staging import LentResults

    _, backend = kernel_backend()
    results = LentResults(backend, limit=400)
    codes = ((2, 4, 5, 3), np.uint8)  # 120 bytes
    free = results.take([codes])[0].ctypes.data  # page-locked, then given back
    monkeypatch.setattr(backend, "pinned", lambda shape, dtype: (_ for _ in ()).throw(
        MemoryError("no page-locked memory left")))
    with pytest.raises(MemoryError):
        results.take([codes, codes])  # the free block, and one that cannot be locked
    monkeypatch.undo()
    again = results.take([codes, codes, codes])  # the limit still holds 280 more bytes
    assert again[0].ctypes.data == free and results.take([codes]) is None


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
@pytest.mark.parametrize("batch_fails, draws", [(False, "per-sample"), (True, "per-sample"),
                                                (False, "per-sequence")])
def test_inputs_staged_in_pinned_memory_make_the_bytes_of_unstaged_ones(
        tmp_path, bad_sequences, monkeypatch, batch_fails, draws):
    """On a GPU the I/O threads copy each sample's frames into page-locked slots and a slot's
    samples are made as one batch; forced here on a CPU kernel backend: the same set, bad
    samples too, and when a batch fails its samples are made one by one."""
    folder, scene = bad_sequences
    add_long_sequence(folder, seed=2)
    if draws == "per-sequence":  # a batch's samples keyed by their sequences
        scene.write_text(scene.read_text() + 'draws = "per-sequence"\n')
    name, backend = kernel_backend()
    run = ("--backend", name, "--samples-per-sequence", "8", "--save", "mask")
    assert main(args(folder, scene, tmp_path / "one", *run, "--io-threads", "1")) == 1
    batches, stacks, lent, lent_bytes = [], [], [], []
    make_batch, stack = gpu_blur.generate.make_batch, gpu_blur.backends.pinned_stack
    module = gpu_blur.backends.warp if name.startswith("warp") else gpu_blur.backends.opencl

    class Refusing:  # a Synthesizer whose batches fail
        def __init__(self, synthesizer):
            self.result_shape = synthesizer.result_shape
            self.result_dtypes = synthesizer.result_dtypes

        def __call__(self, *args, **kwargs):
            raise ValueError("sample 1 of 3: refused")

    def batched(job, synthesizer, specs, batch, results=None):
        made = make_batch(job, Refusing(synthesizer) if batch_fails else synthesizer, specs,
                          batch, results)
        batches.append(len(specs) if made else 0)
        for _, result, _ in made or []:  # the results lie in page-locked memory lent for them
            lent.append(gpu_blur.backends.pinned_owner(result.blurred) is backend
                        and gpu_blur.backends.pinned_owner(result.mask) is backend)
            lent_bytes.append(result.blurred.nbytes + result.sharp.nbytes + result.mask.nbytes)
        return made

    def spied(frames, owner):
        found = stack(frames, owner)
        stacks.append(found is not None)
        return found

    monkeypatch.setattr(gpu_blur.generate, "make_batch", batched)
    monkeypatch.setattr(module, "pinned_stack", spied)
    staged = []
    monkeypatch.setattr(gpu_blur.generate, "pinned_staging", lambda job: staged.append(
        gpu_blur.staging.PinnedStaging(backend, 2, 3)) or staged[-1])
    assert main(args(folder, scene, tmp_path / "staged", *run, "--io-threads", "3")) == 1
    assert len(batches) >= 2  # the first batch of each slot goes one by one (allocating)
    assert (sum(batches) == 0) if batch_fails else (sum(batches) >= 6)
    assert all(lent) and len(lent) == sum(batches)
    if not batch_fails:  # blocks come back once written (at most 6 samples wait to be):
        assert staged[0].results._held < sum(lent_bytes)  # later batches reuse them
    if batch_fails:
        assert sum(stacks) >= 6  # one by one, each from its staged stack
    assert_same_set(tmp_path / "staged", tmp_path / "one")


WARP_CPU = "warp:cpu/float32" in KERNEL_BACKEND_SPECS


@pytest.mark.skipif(not WARP_CPU, reason="Warp's CPU device is not among the suite's backends")
def test_overlapping_windows_made_from_frames_kept_on_the_device_give_the_bytes_of_one_thread(
        tmp_path, bad_sequences, monkeypatch):
    """On a Warp GPU, samples that share a frame with an earlier one are made from frames kept
    on the device (each uploaded once) instead of page-locked slots; forced here on Warp's CPU
    device: the same set as one thread, bad samples too."""
    from gpu_blur.backends import get_backend

    folder, scene = bad_sequences
    add_long_sequence(folder, seed=3)
    run = ("--backend", "warp:cpu", "--samples-per-sequence", "8", "--save", "mask")
    assert main(args(folder, scene, tmp_path / "one", *run, "--io-threads", "1")) == 1
    backend = get_backend("warp:cpu", "float32")
    kept, device_batches = [], []
    batch_of = gpu_blur.staging.DeviceFrames.batch_of

    def spied(self, samples):
        kept.append(self)
        batch = batch_of(self, samples)
        device_batches.append(0 if batch is None else len(samples))
        return batch

    monkeypatch.setattr(gpu_blur.staging.DeviceFrames, "batch_of", spied)
    monkeypatch.setattr(gpu_blur.generate, "pinned_staging",
                        lambda job: gpu_blur.staging.PinnedStaging(backend, 2, 3))
    assert main(args(folder, scene, tmp_path / "kept", *run, "--io-threads", "3")) == 1
    assert_same_set(tmp_path / "kept", tmp_path / "one")
    # four sequences of 8 windows: all but each sequence's first share frames; the good ones
    # (a_good, d_long) come from the device, the bad ones are made one by one and fail
    assert sum(device_batches) >= 2 * 7 - 2
    frames = 3 + 10  # a_good's and d_long's: each uploaded once (the cache keeps them all)
    assert kept and kept[0].uploads <= frames


def one_thread_then_device_pngs(tmp_path, bad_sequences, monkeypatch, seed: int,
                                extra: tuple = ()) -> tuple:
    """``(folder, scene, run)``: the reference set ``one`` made by one thread on Warp's CPU
    device, then the next runs forced to batch their samples (slots of 3) and deflate their
    PNGs on the device, as on a Warp GPU."""
    from gpu_blur.backends import get_backend
    from gpu_blur.png_device import DevicePngs

    folder, scene = bad_sequences
    add_long_sequence(folder, seed=seed)
    run = ("--backend", "warp:cpu", "--samples-per-sequence", "8", *extra)
    assert main(args(folder, scene, tmp_path / "one", *run, "--io-threads", "1")) == 1
    backend = get_backend("warp:cpu", "float32")
    monkeypatch.setattr(DevicePngs, "for_backend", staticmethod(lambda backend, scene: True))
    monkeypatch.setattr(gpu_blur.generate, "pinned_staging",
                        lambda job: gpu_blur.staging.PinnedStaging(backend, 2, 3))
    return folder, scene, run


@pytest.mark.skipif(not WARP_CPU, reason="Warp's CPU device is not among the suite's backends")
@pytest.mark.parametrize("extra", [(), ("--save", "mask", "--format", "webdataset")])
def test_pngs_deflated_on_the_device_give_the_bytes_the_host_writes(tmp_path, bad_sequences,
                                                                   monkeypatch, capsys, extra):
    """On a Warp GPU a batch's 8-bit PNGs are deflated on the device and the I/O threads only
    put the files together; forced here on Warp's CPU device: the same set as one thread's,
    whose files the host encoded, bad samples too; with masks (16-bit: the host's) and in
    WebDataset shards as well."""
    import gpu_blur.file_writing

    folder, scene, run = one_thread_then_device_pngs(tmp_path, bad_sequences, monkeypatch, 5,
                                                     extra)
    from_streams = []
    png_file = gpu_blur.file_writing.png_file
    monkeypatch.setattr(gpu_blur.file_writing, "png_file",
                        lambda codes, idat: from_streams.append(1) or png_file(codes, idat))
    capsys.readouterr()
    assert main(args(folder, scene, tmp_path / "device", *run, "--io-threads", "3")) == 1
    assert_same_set(tmp_path / "device", tmp_path / "one")
    assert len(from_streams) >= 2 * 12  # blurred and sharp of the batched samples
    said = re.search(r"\((\d+) PNG files deflated on the GPU\)", capsys.readouterr().out)
    assert said and int(said[1]) == len(from_streams)


@pytest.mark.skipif(not WARP_CPU, reason="Warp's CPU device is not among the suite's backends")
def test_a_device_deflate_that_fails_leaves_the_files_to_the_host_and_says_so(
        tmp_path, bad_sequences, monkeypatch, capsys):
    from gpu_blur.png_device import DeviceDeflate

    folder, scene, run = one_thread_then_device_pngs(tmp_path, bad_sequences, monkeypatch, 6)
    calls = []

    def failing(self, *args):  # the second batch's kernels do not build, say
        calls.append(1)
        if len(calls) > 2:
            raise RuntimeError("Warp CUDA error: no kernel image for this device")
        return deflate(self, *args)

    deflate = DeviceDeflate.deflate
    monkeypatch.setattr(DeviceDeflate, "deflate", failing)
    monkeypatch.setattr(gpu_blur.notices, "verbosity", lambda: gpu_blur.notices.NORMAL)
    capsys.readouterr()
    assert main(args(folder, scene, tmp_path / "device", *run, "--io-threads", "3")) == 1
    assert_same_set(tmp_path / "device", tmp_path / "one")
    out = capsys.readouterr()
    assert out.err.count("no kernel image for this device") == 1  # one notice
    assert "the host encodes the files from here on" in out.err
    assert len(calls) == 3  # no deflate tried after the failure
    said = re.search(r"\((\d+) PNG files deflated on the GPU\)", out.out)
    assert said and int(said[1]) == 2 * 3  # the first batch's


@pytest.mark.skipif(not WARP_CPU, reason="Warp's CPU device is not among the suite's backends")
def test_device_frames_upload_each_frame_once_and_keep_at_most_their_limit():
    from gpu_blur.backends import get_backend
    from gpu_blur.staging import DeviceFrames

    rng = np.random.default_rng(4)
    frames = [rng.integers(0, 256, (4, 6, 3), np.uint8) for _ in range(4)]
    kept = DeviceFrames(get_backend("warp:cpu", "float32"), limit=3 * frames[0].nbytes)
    windows = [tuple(frames[0:2]), tuple(frames[1:3])]
    batch = kept.batch_of(windows)
    assert batch.shape == (2, 2, 4, 6, 3)
    assert np.array_equal(batch.flatten().numpy().reshape(batch.shape),
                          np.stack([np.stack(w) for w in windows]))
    assert kept.uploads == 3  # frames[1] once for both windows
    assert np.array_equal(kept.batch_of([tuple(frames[1:4])]).flatten().numpy(),
                          np.stack(frames[1:4]).reshape(-1))
    assert kept.uploads == 4  # frames[3] new; frames[0], least recently used, goes
    kept.batch_of([(frames[0],)])
    assert kept.uploads == 5
    same = np.array(frames[1])  # equal values, another array: another frame
    kept.batch_of([(same,)])
    assert kept.uploads == 6
    assert kept.batch_of([(frames[0],), None]) is None
    assert kept.batch_of([(frames[0],), (frames[0][:2],)]) is None  # two shapes
    assert kept.batch_of([(frames[0][:, :5],)]) is None  # an odd side
    assert kept.batch_of([(frames[0],), (frames[0], frames[1])]) is None  # two counts
