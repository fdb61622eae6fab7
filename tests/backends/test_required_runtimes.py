"""GPU_BLUR_REQUIRE (set by .ci/run): a required OpenCL runtime that is missing fails the run."""

import pytest
from conftest import missing_required, pytest_sessionstart

opencl = pytest.importorskip("gpu_blur.backends.opencl")

POCL = opencl.DeviceInfo("opencl:0:0", "Portable Computing Language", "pthread-cpu", "CPU",
                         True, 2**30, True, "")
INTEL = opencl.DeviceInfo("opencl:1:0", "Intel(R) OpenCL", "cpu", "CPU", True, 2**30, True, "")
BOTH = ["opencl:0:0/float32", "opencl:0:0/float64", "opencl:1:0/float32", "opencl:1:0/float64"]


def test_required_runtimes_whose_tests_run_are_no_problem():
    assert missing_required("pocl,intel", [POCL, INTEL], BOTH) == []


def test_a_missing_pocl_is_named():
    assert missing_required("pocl,intel", [INTEL], BOTH[2:]) == [
        "pocl (Portable Computing Language): no device the tests run on (none installed)"]


def test_a_pocl_that_cannot_build_or_whose_float64_is_left_out_is_missing():
    broken = opencl.DeviceInfo("opencl:0:0", "Portable Computing Language", "pthread-cpu",
                               "CPU", True, 2**30, False, "error: unknown target CPU 'generic'")
    assert "unknown target CPU 'generic'" in missing_required("pocl", [broken], [])[0]
    assert missing_required("pocl", [POCL], ["opencl:0:0/float32"]) != []


def test_an_unknown_name_is_refused():
    assert missing_required("pocl,nvidia", [POCL], BOTH[:2]) == [
        "unknown name 'nvidia' (known: pocl, intel)"]


def test_the_session_fails_not_skips_when_a_required_runtime_is_missing(monkeypatch):
    monkeypatch.setenv("GPU_BLUR_REQUIRE", "pocl")
    monkeypatch.setattr(opencl, "opencl_devices", lambda: [INTEL])
    with pytest.raises(pytest.UsageError, match="GPU_BLUR_REQUIRE=pocl: pocl"):
        pytest_sessionstart(None)
    monkeypatch.setenv("GPU_BLUR_REQUIRE", "")
    pytest_sessionstart(None)  # not required: nothing to check


def test_a_second_cpu_device_of_the_same_runtime_is_left_out():
    from conftest import one_cpu_device_per_runtime

    pip_pocl = opencl.DeviceInfo("opencl:2:0", "Portable Computing Language", "pthread-cpu",
                                 "CPU", True, 2**30, True, "")
    gpus = [opencl.DeviceInfo(f"opencl:3:{i}", "NVIDIA CUDA", "H200", "GPU", True, 2**30, True,
                              "") for i in range(2)]
    assert one_cpu_device_per_runtime([POCL, INTEL, pip_pocl, *gpus]) == [POCL, INTEL, *gpus]
