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
    staging.size_for(frames(0))  # would hang here if it allocated on this thread
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
    staging.size_for(frames(0))
    given = frames(3)
    assert staging.fill(1, 0, given) is given  # handed back as it is, no hang
    with pytest.raises(RuntimeError, match="out of memory"):
        staging.batch_of(1, [given], frames=True)
    with pytest.raises(RuntimeError, match="out of memory"):
        staging.release(0)
