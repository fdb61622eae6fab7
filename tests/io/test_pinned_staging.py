"""PinnedStaging: the slots' first memory is page-locked off the making thread."""

import threading

import numpy as np
import pytest

from gpu_blur.staging import PinnedStaging


class SlowPinning:
    """A backend whose ``pinned`` waits for ``go`` and records the thread it ran on."""

    def __init__(self, fail: bool = False):
        self.go, self.threads, self.fail = threading.Event(), [], fail

    def pinned(self, shape, dtype):
        self.threads.append(threading.current_thread())
        assert self.go.wait(10)
        if self.fail:
            raise RuntimeError("cudaMallocHost: out of memory")
        return np.zeros(shape, dtype)

    def wait(self):
        pass


def frames(value: int, count: int = 3) -> tuple[np.ndarray, ...]:
    return tuple(np.full((4, 5, 3), value + i, np.uint8) for i in range(count))


def test_size_for_returns_at_once_and_fill_waits_for_its_slot_memory():
    backend = SlowPinning()
    staging = PinnedStaging(backend, slots=2, batch=2)
    staging.size_for(sum(f.nbytes for f in frames(0)))  # returns while the slots allocate
    assert staging.sized
    filled = []
    filling = threading.Thread(target=lambda: filled.append(staging.fill(0, 1, frames(7))))
    filling.start()
    filling.join(0.2)
    assert filling.is_alive() and not filled  # the copy waits for the slot's memory
    backend.go.set()
    filling.join(10)
    assert threading.current_thread() not in backend.threads and len(backend.threads) == 2
    staged = filled[0]
    np.testing.assert_array_equal(np.stack(staged), np.stack(frames(7)))
    sample = staging.fill(0, 0, frames(1))
    batch = staging.batch_of(0, [sample, staged], frames=True)
    assert batch.shape == (2, 3, 4, 5, 3)
    np.testing.assert_array_equal(batch[1], np.stack(frames(7)))


def test_failed_first_allocation_leaves_samples_unstaged_and_is_raised_on_the_making_thread():
    backend = SlowPinning(fail=True)
    backend.go.set()
    staging = PinnedStaging(backend, slots=2, batch=2)
    staging.size_for(sum(f.nbytes for f in frames(0)))
    given = frames(3)
    assert staging.fill(1, 0, given) is given  # handed back as it is, no hang
    with pytest.raises(RuntimeError, match="out of memory"):
        staging.batch_of(1, [given], frames=True)
    with pytest.raises(RuntimeError, match="out of memory"):
        staging.release(0)


@pytest.mark.parametrize("kind", ["grey8", "grey16", "bgr8", "bgr16", "bgra8", "bgra16",
                                  "palette", "one-bit", "grey-alpha"])
def test_decoded_layout_from_the_png_header_is_what_read_image_gives(tmp_path, kind):
    """The slots are sized from the first frame's header before it is decoded."""
    import cv2
    from PIL import Image

    from gpu_blur.image_reading import decoded_layout, read_image

    rng = np.random.default_rng(0)
    path = tmp_path / f"{kind}.png"
    depth = np.uint16 if kind.endswith("16") else np.uint8
    channels = {"grey": 1, "bgr": 3, "bgra": 4}.get(kind.rstrip("0123456789"))
    if channels:
        image = rng.integers(0, np.iinfo(depth).max, (7, 5, channels), depth, endpoint=True)
        if channels == 4:
            image[..., 3] = np.iinfo(depth).max  # opaque: read_image drops it
        cv2.imwrite(str(path), image)
    else:
        mode = {"palette": "P", "one-bit": "1", "grey-alpha": "LA"}[kind]
        picture = Image.new(mode, (5, 7))
        if mode == "LA":
            picture.putalpha(255)
        picture.save(path)
    decoded = read_image(path)
    assert decoded_layout(path) == (decoded.shape, decoded.dtype)


def test_decoded_layout_is_none_where_the_header_cannot_tell(tmp_path):
    import cv2

    from gpu_blur.image_reading import decoded_layout

    cv2.imwrite(str(tmp_path / "a.jpg"), np.zeros((4, 4, 3), np.uint8))
    (tmp_path / "short.png").write_bytes(b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR")
    (tmp_path / "folder.png").mkdir()
    for name in ("a.jpg", "short.png", "folder.png", "missing.png"):
        assert decoded_layout(tmp_path / name) is None


def test_a_png_sample_is_sized_before_it_is_decoded_and_another_once_it_is(tmp_path):
    import types
    from concurrent.futures import Future

    import cv2

    from gpu_blur.generate import _sample_layout

    frame = np.zeros((6, 10, 3), np.uint16)
    cv2.imwrite(str(tmp_path / "a.png"), frame)
    cv2.imwrite(str(tmp_path / "b.png"), frame)
    cv2.imwrite(str(tmp_path / "a.jpg"), np.zeros((6, 10, 3), np.uint8))
    pending = Future()  # never decoded: a PNG sample must not wait for it
    png = types.SimpleNamespace(spec=types.SimpleNamespace(
        inputs=(tmp_path / "a.png", tmp_path / "b.png")), checked=pending)
    assert _sample_layout(png) == (2 * frame.nbytes, np.uint16)
    decoded = Future()
    decoded.set_result((np.zeros((6, 10, 3), np.uint8),))
    jpeg = types.SimpleNamespace(spec=types.SimpleNamespace(inputs=(tmp_path / "a.jpg",)),
                                 checked=decoded)
    assert _sample_layout(jpeg) == (180, np.uint8)
    failed = Future()
    failed.set_result(None)  # its checks failed: the next sample sizes the slots
    assert _sample_layout(types.SimpleNamespace(spec=jpeg.spec, checked=failed)) is None
