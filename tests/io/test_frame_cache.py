import threading
import time

import numpy as np
import pytest

from gpu_blur.frame_cache import CacheCounts, FrameCache


class CountingReader:
    """A reader that returns a frame per file (its bytes' length as the value) and counts calls."""

    def __init__(self, delay: float = 0.0, fail: bool = False):
        self.calls: list[str] = []
        self.delay, self.fail = delay, fail
        self.lock = threading.Lock()

    def __call__(self, path):
        with self.lock:
            self.calls.append(path.name)
        time.sleep(self.delay)
        if self.fail:
            raise ValueError(f"{path}: corrupt")
        return np.full((4, 4, 3), len(path.read_bytes()), dtype=np.uint8)


def frames(tmp_path, count):
    paths = []
    for i in range(count):
        paths.append(tmp_path / f"{i}.png")
        paths[-1].write_bytes(b"x" * (i + 1))
    return paths


def test_a_frame_read_twice_is_decoded_once_and_read_only(tmp_path):
    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(1 << 20), CountingReader()
    first, again = cache.read(path, reader), cache.read(path, reader)
    assert again is first and reader.calls == ["0.png"]
    assert not first.flags.writeable
    with pytest.raises(ValueError):
        first[0, 0, 0] = 7
    counts = cache.counts()
    assert (counts.hits, counts.misses, counts.evicted) == (1, 1, 0)
    assert counts.summary() == ("frame cache: 1 decoded, 1 served decoded (50 % of 2 reads), "
                                "0 evicted")
    cache.read(path, reader)
    assert cache.counts() - counts == CacheCounts(hits=1, misses=0, evicted=0)


def test_each_reader_of_a_file_gets_its_own_array(tmp_path):
    # --jpeg-decoder gpu keeps a JPEG's checked bytes, a sample with files of other formats
    # the same file's pixels: neither is served the other's
    (path,) = frames(tmp_path, 1)
    cache, pixels = FrameCache(1 << 20), CountingReader()

    def raw(p):
        return np.frombuffer(p.read_bytes(), np.uint8)

    assert cache.read(path, raw).shape == (1,)
    assert cache.read(path, pixels).shape == (4, 4, 3) and pixels.calls == ["0.png"]
    assert cache.read(path, raw).shape == (1,) and cache.read(path, pixels).shape == (4, 4, 3)
    assert pixels.calls == ["0.png"]


def test_the_least_recently_used_frame_leaves_first_past_the_budget(tmp_path):
    a, b, c = frames(tmp_path, 3)
    cache, reader = FrameCache(2 * 48), CountingReader()  # two 4 x 4 x 3 uint8 frames
    cache.read(a, reader)
    cache.read(b, reader)
    cache.read(a, reader)  # a is now the most recent
    cache.read(c, reader)  # b leaves
    cache.read(a, reader)
    cache.read(b, reader)
    assert reader.calls == ["0.png", "1.png", "2.png", "1.png"]
    assert cache.counts().evicted == 2


def test_a_replaced_file_is_decoded_again(tmp_path):
    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(1 << 20), CountingReader()
    assert cache.read(path, reader)[0, 0, 0] == 1
    path.write_bytes(b"yyy")
    assert cache.read(path, reader)[0, 0, 0] == 3
    assert len(reader.calls) == 2


def test_threads_asking_for_one_frame_at_once_share_one_decode(tmp_path):
    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(1 << 20), CountingReader(delay=0.2)
    got = []
    threads = [threading.Thread(target=lambda: got.append(cache.read(path, reader)))
               for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert reader.calls == ["0.png"] and len(got) == 8
    assert all(frame is got[0] for frame in got)


def test_samples_sharing_a_file_take_no_io_thread_to_wait_for_its_decode(tmp_path,
                                                                       monkeypatch):
    # two I/O threads; sample A reads files f and g, sample B f and h, and f's decode lasts
    # until h is decoded: had B's read of f taken a thread to wait for A's decode of f, no
    # thread would be left for h
    from concurrent.futures import ThreadPoolExecutor

    import gpu_blur.generate as generate
    from gpu_blur.discovery import SampleSpec
    from gpu_blur.timings import PoolTimes

    f, g, h = frames(tmp_path, 3)
    h_decoded, counting = threading.Event(), CountingReader()

    def reader(path):
        if path == f:
            assert h_decoded.wait(10), "h was never decoded"
        image = counting(path)
        if path == h:
            h_decoded.set()
        return image

    monkeypatch.setattr(generate, "read_image", reader)
    cache, times = FrameCache(1 << 20), PoolTimes(2)
    with ThreadPoolExecutor(2) as pool:
        samples = [generate._Inputs(SampleSpec(i, f"s{i}", files), pool, times, cache)
                   for i, files in enumerate([(f, g), (f, h)])]
        a, b = (sample.checked.result(timeout=20) for sample in samples)
    assert sorted(counting.calls) == ["0.png", "1.png", "2.png"]  # each file decoded once
    assert a[0] is b[0] and times.calls["decode"] == 3
    assert cache.counts() == CacheCounts(hits=1, misses=3, evicted=0)


def test_an_abandoned_decode_fails_its_waiters_and_the_next_claim_decodes_again(tmp_path):
    from concurrent.futures import CancelledError

    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(1 << 20), CountingReader()
    first, decode = cache.claim(path, reader)
    waiting, none = cache.claim(path, reader)  # in flight: the same future, nothing to run
    assert waiting is first and none is None
    decode.abandon()  # its task was cancelled: the run stopped
    with pytest.raises(CancelledError, match="not decoded, the run stopped"):
        waiting.result(timeout=1)
    again, decode = cache.claim(path, reader)
    assert decode is not None and again is not first
    decode()
    assert again.result(timeout=1)[0, 0, 0] == 1 and reader.calls == ["0.png"]


def test_a_failed_decode_reaches_every_waiter_and_is_not_kept(tmp_path):
    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(1 << 20), CountingReader(delay=0.2, fail=True)
    errors = []

    def read():
        try:
            cache.read(path, reader)
        except ValueError as error:
            errors.append(str(error))

    threads = [threading.Thread(target=read) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == [f"{path}: corrupt"] * 4 and len(reader.calls) == 1
    reader.fail, reader.delay = False, 0.0
    assert cache.read(path, reader)[0, 0, 0] == 1  # tried again, not a kept failure


def test_a_zero_budget_decodes_every_read_and_a_negative_one_is_refused(tmp_path):
    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(0), CountingReader()
    cache.read(path, reader)
    cache.read(path, reader)
    assert len(reader.calls) == 2 and cache.counts().misses == 2
    with pytest.raises(ValueError, match="frame cache budget: -1 bytes; give 0 or more"):
        FrameCache(-1)


def test_a_frame_larger_than_the_budget_is_served_but_not_kept(tmp_path):
    (path,) = frames(tmp_path, 1)
    cache, reader = FrameCache(10), CountingReader()
    cache.read(path, reader)
    cache.read(path, reader)
    assert len(reader.calls) == 2


def sequence(folder, count):
    """One sequence of ``count`` small noisy frames (GoPro-style ``<seq>/sharp/``)."""
    import cv2

    rng = np.random.default_rng(3)
    (folder / "seq" / "sharp").mkdir(parents=True)
    for i in range(count):
        frame = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / "seq" / "sharp" / f"{i:03d}.png"), frame)
    return folder


def set_bytes(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name not in ("run.json",)}


@pytest.mark.parametrize("io_threads", [1, 2])
def test_overlapping_windows_decode_each_frame_once_and_write_the_same_set(tmp_path,
                                                                          io_threads):
    import gpu_blur

    source = sequence(tmp_path / "in", 6)
    scene = {"blur": {"mode": "average", "frames": 3}}
    made = {}
    for cache in ("0", None):  # none, then the default
        out = tmp_path / f"out_{cache}"
        report = gpu_blur.generate_set(out, input=source, scene=scene, seed=5,
                                       samples_per_sequence=4, io_threads=io_threads,
                                       frame_cache=cache)
        made[cache] = set_bytes(out), report.summary
    assert made["0"][0] == made[None][0]
    assert not any(line.startswith("frame cache") for line in made["0"][1])
    # 4 windows of 3 frames spread over 6 frames: 12 reads of 6 files
    assert "frame cache: 6 decoded, 6 served decoded (50 % of 12 reads), 0 evicted" in made[None][1]


def test_a_bad_frame_cache_size_names_the_option(tmp_path):
    import gpu_blur

    with pytest.raises(ValueError, match="--frame-cache: 'lots' is not a memory size"):
        gpu_blur.generate_set(tmp_path / "out", frame_cache="lots")
