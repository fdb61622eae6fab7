"""glibc's malloc as gpu-blur generate sets it (gpu_blur.allocator)."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from gpu_blur.allocator import ENV, SETTINGS, keep_freed_memory
from gpu_blur.cli import main


class FakeLibc:
    """mallopt that records its calls and answers ``answer`` (1: done, 0: refused)."""

    def __init__(self, answer: int = 1):
        self.calls: list[tuple[int, int]] = []
        self.answer = answer

    def mallopt(self, parameter: int, value: int) -> int:
        self.calls.append((parameter, value))
        return self.answer


def test_keep_sets_the_mmap_threshold_the_trim_threshold_and_the_top_pad():
    libc = FakeLibc()
    said = keep_freed_memory({}, libc)
    assert libc.calls == list(SETTINGS.items())
    assert dict(libc.calls) == {-3: 32 << 20, -1: 1 << 30, -2: 64 << 20}  # malloc.h's numbers
    assert said == "malloc: freed memory kept for the next image (glibc, mallopt)"


def test_glibc_leaves_the_allocator_as_it_is():
    libc = FakeLibc()
    assert keep_freed_memory({ENV: "glibc"}, libc) == "malloc: glibc's own settings " \
        "(GPU_BLUR_MALLOC=glibc)"
    assert libc.calls == []


def test_a_users_own_malloc_variables_are_left_to_work():
    libc = FakeLibc()
    said = keep_freed_memory({"MALLOC_ARENA_MAX": "2", "MALLOC_TRIM_THRESHOLD_": "0"}, libc)
    assert said == "malloc: as MALLOC_ARENA_MAX, MALLOC_TRIM_THRESHOLD_ set it"
    assert libc.calls == []


def test_a_refused_setting_is_said_and_the_rest_left_alone():
    libc = FakeLibc(answer=0)
    said = keep_freed_memory({}, libc)
    assert said == f"malloc: glibc refused mallopt(-3, {32 << 20}); its own settings"
    assert libc.calls == [(-3, 32 << 20)]


def test_an_unknown_choice_is_refused_naming_the_variable_and_the_choices():
    with pytest.raises(ValueError, match=r"GPU_BLUR_MALLOC='fast': use keep .* or glibc"):
        keep_freed_memory({ENV: "fast"}, FakeLibc())


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_this_process_takes_the_settings_on_glibc():
    code = ("from gpu_blur.allocator import keep_freed_memory; import numpy as np; "
            "print(keep_freed_memory({})); a = [np.ones(7 << 20, np.uint8) for _ in range(3)]; "
            "print(sum(int(x.sum()) for x in a))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    assert done.stdout.split("\n")[:2] == [
        "malloc: freed memory kept for the next image (glibc, mallopt)", str(3 * (7 << 20))]


def test_generate_refuses_an_unknown_choice_before_any_work(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(ENV, "fast")
    out = tmp_path / "set"
    assert main(["generate", "--input", str(tmp_path), "--output", str(out)]) == 2
    assert "gpu-blur: error: GPU_BLUR_MALLOC='fast': use keep" in capsys.readouterr().err
    assert not out.exists()
