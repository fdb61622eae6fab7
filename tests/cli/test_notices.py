"""What gpu-blur says besides results: kernel-build notices, --quiet / --verbose, the summary."""

from __future__ import annotations

import time

import pytest
from conftest import KERNEL_BACKEND_SPECS

from gpu_blur import notices
from gpu_blur.cli import main

#: One float32 spec per kernel backend family present (a build notice is per device).
FLOAT32_KERNELS = [s for s in KERNEL_BACKEND_SPECS if s.endswith("/float32")]


@pytest.fixture
def fresh_process(monkeypatch):
    """As if no kernel had been built or announced in this process yet: new backends (each
    builds its OpenCL programs), Warp's modules not loaded by this process."""
    from gpu_blur.backends import get_backend

    get_backend.cache_clear()
    monkeypatch.setattr(notices, "_announced", set())
    try:
        from gpu_blur.backends import warp
    except ImportError:
        return
    monkeypatch.setattr(warp, "_LOADED", set())


def generate(photos, out, spec: str, *extra: str) -> int:
    folder, scene = photos
    return main(["generate", "--input", str(folder), "--output", str(out), "--scene",
                 str(scene), "--backend", spec.split("/")[0], *extra])


@pytest.mark.parametrize("spec", FLOAT32_KERNELS)
def test_generate_says_once_per_device_that_kernels_compile(spec, photos, tmp_path, capsys,
                                                            monkeypatch, fresh_process):
    monkeypatch.setattr(notices, "NOTICE_AFTER_S", 0.0)  # every build counts as slow
    assert generate(photos, tmp_path / "out", spec) == 0
    err = capsys.readouterr().err
    device = spec.split("/")[0]
    lines = [x for x in err.splitlines() if "gpu-blur: compiling kernels" in x]
    assert len(lines) == 1, err  # three passes built, one line
    assert f"compiling kernels for {device} on first use (seconds each; cached afterwards)" \
        in lines[0]


@pytest.mark.parametrize("spec", FLOAT32_KERNELS)
def test_quiet_generate_prints_no_notice_and_no_progress(spec, photos, tmp_path, capsys,
                                                         monkeypatch, fresh_process):
    monkeypatch.setattr(notices, "NOTICE_AFTER_S", 0.0)
    assert generate(photos, tmp_path / "out", spec, "--quiet") == 0
    captured = capsys.readouterr()
    assert "compiling" not in captured.err and "samples:" not in captured.err
    assert "device: " in captured.err and "wrote 2 samples" in captured.out


@pytest.mark.parametrize("spec", FLOAT32_KERNELS)
def test_verbose_generate_prints_each_build_with_its_time(spec, photos, tmp_path, capsys,
                                                          fresh_process):
    assert generate(photos, tmp_path / "out", spec, "--verbose") == 0
    err = capsys.readouterr().err
    device = spec.split("/")[0]
    built = [x for x in err.splitlines() if "gpu-blur: built " in x]
    names = (["kernels/opencl/accumulate.cl", "kernels/opencl/to_raw.cl",
              "kernels/opencl/finish.cl"] if device.startswith("opencl") else
             ["the linearize kernel", "the blur_trajectory_add kernel", "the to_raw kernel",
              "the finish kernel"])
    for name in names:
        assert any(f"built {name} for {device} in " in x and x.endswith(" s") for x in built), err


def test_a_build_is_announced_only_once_it_is_slow_and_once_per_device(capsys, monkeypatch,
                                                                       fresh_process):
    monkeypatch.setattr(notices, "NOTICE_AFTER_S", 0.05)
    with notices.verbosity_set(notices.NORMAL):
        with notices.building("a cached build", "dev:a"):
            pass  # done before the notice is due
        assert capsys.readouterr().err == ""
        for _ in range(2):
            with notices.building("a slow build", "dev:a"):
                time.sleep(0.3)
    assert capsys.readouterr().err == (
        "gpu-blur: compiling kernels for dev:a on first use (seconds each; cached afterwards)\n")


def test_the_library_says_nothing_unless_asked(capsys, monkeypatch, fresh_process):
    monkeypatch.delenv(notices.ENV, raising=False)
    monkeypatch.setattr(notices, "NOTICE_AFTER_S", 0.0)
    assert notices.verbosity() == notices.QUIET
    with notices.building("a build", "dev:a"):
        pass
    monkeypatch.setenv(notices.ENV, "2")  # GPU_BLUR_VERBOSITY=2 asks for everything
    with notices.building("a build", "dev:a"):
        pass
    assert capsys.readouterr().err.splitlines() == [
        "gpu-blur: compiling kernels for dev:a on first use (seconds each; cached afterwards)",
        "gpu-blur: built a build for dev:a in 0.00 s"]


def test_numpy_time_is_not_called_device_compute(photos, tmp_path, capsys):
    assert generate(photos, tmp_path / "out", "numpy", "--quiet") == 0
    out = capsys.readouterr().out
    kernels = [x for x in out.splitlines() if x.strip().startswith("kernels ")]
    assert len(kernels) == 1 and "the passes on the CPU (numpy float64 reference)" in kernels[0]
    assert "device" not in kernels[0]


def test_quiet_bench_shows_no_progress_bar(tmp_path, capsys):
    assert main(["bench", "--size", "64x48", "--backends", "numpy", "--knobs", "demosaic",
                 "--reference-runs", "1", "--output", str(tmp_path), "--tag", "t",
                 "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "steps" not in captured.err and "wrote " in captured.out
