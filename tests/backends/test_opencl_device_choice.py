"""Which OpenCL device ``opencl`` picks, what ``gpu-blur devices`` says of each, and the device
line every ``generate`` run starts with."""

import types

import pytest

opencl = pytest.importorskip("gpu_blur.backends.opencl")
from gpu_blur.cli import main  # noqa: E402
from gpu_blur.distributed import parse_devices  # noqa: E402

POCL = "Portable Computing Language"
INTEL = "Intel(R) OpenCL"


def device(spec, platform, kind="CPU", problem=""):
    return opencl.DeviceInfo(spec, platform, f"{platform} device", kind, True, 2**30,
                             not problem, problem)


@pytest.fixture
def present(monkeypatch):
    """Make these devices the ones present (in this platform order); select_device then hands
    back a stand-in for the cl.Device, as no such platforms exist here."""

    def install(*devices):
        monkeypatch.setattr(opencl, "opencl_devices", lambda: list(devices))
        platforms = [types.SimpleNamespace(get_devices=lambda p=p: [f"cl device {p}"])
                     for p in range(len(devices))]
        monkeypatch.setattr(opencl.cl, "get_platforms", lambda: platforms)

    return install


def test_opencl_picks_intels_cpu_runtime_before_pocl_whatever_the_platform_order(present):
    # installing Debian's PoCL put it at platform 0 before Intel's runtime (4.5 to 15 times
    # slower per sample here); the rule, not the platform number, decides
    present(device("opencl:0:0", POCL), device("opencl:1:0", INTEL),
            device("opencl:2:0", POCL))
    assert opencl.select_device("opencl")[1].spec == "opencl:1:0"


def test_opencl_picks_a_gpu_before_any_cpu_runtime(present):
    present(device("opencl:0:0", INTEL), device("opencl:1:0", POCL),
            device("opencl:2:0", "NVIDIA CUDA", kind="GPU"))
    assert opencl.select_device("opencl")[1].spec == "opencl:2:0"


def test_opencl_never_picks_a_device_that_cannot_build(present):
    present(device("opencl:0:0", "NVIDIA CUDA", kind="GPU", problem="error: no compiler"),
            device("opencl:1:0", INTEL, problem="error: unknown target CPU 'generic'"),
            device("opencl:2:0", POCL))
    assert opencl.select_device("opencl")[1].spec == "opencl:2:0"


def test_no_device_that_can_build_is_an_error_naming_each_and_why(present):
    present(device("opencl:0:0", POCL, problem="error: unknown target CPU 'generic'"))
    with pytest.raises(opencl.OpenCLError, match=r"opencl:0:0 .*unknown target CPU 'generic'"):
        opencl.select_device("opencl")


def test_devices_all_lists_cpu_runtimes_in_the_order_opencl_picks(present):
    present(device("opencl:0:0", POCL), device("opencl:1:0", "Other CPU"),
            device("opencl:2:0", INTEL))
    assert parse_devices("all", "opencl") == ["opencl:2:0", "opencl:0:0", "opencl:1:0"]


def test_devices_command_lists_an_unusable_device_with_its_reason(present, capsys):
    present(device("opencl:0:0", INTEL),
            device("opencl:1:0", POCL, problem="error: unknown target CPU 'generic'"))
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "opencl:0:0       CPU Intel(R) OpenCL device (Intel(R) OpenCL); fp64 yes" in out
    assert ("opencl:1:0       CPU Portable Computing Language device (Portable Computing "
            "Language); fp64 yes; 1.0 GiB; cannot build kernels: error: unknown target CPU "
            "'generic'") in out


def test_generate_starts_by_printing_the_device_it_runs_on(tmp_path, capsys, quick_scene):
    assert main(["generate", "--output", str(tmp_path / "set"), "--limit", "1", "--scene",
                 str(quick_scene), "--quiet"]) == 0
    assert capsys.readouterr().err.splitlines()[0] == "device: numpy float64 (host CPU)"


@pytest.mark.skipif(not [d for d in opencl.opencl_devices() if d.usable],
                    reason="no usable OpenCL device")
def test_generate_with_opencl_prints_the_device_the_rule_picked(tmp_path, capsys):
    chosen = opencl.best_device(opencl.opencl_devices())
    assert main(["generate", "--output", str(tmp_path / "set"), "--limit", "1", "--quiet",
                 "--backend", "opencl"]) == 0
    line = capsys.readouterr().err.splitlines()[0]
    assert line == f"device: {chosen.spec} {chosen.name} ({chosen.platform}), float32"


def test_a_device_rank_is_kind_then_known_runtime():
    gpu = device("opencl:3:0", POCL, kind="GPU")
    ranked = sorted([device("opencl:0:0", "Other"), device("opencl:1:0", POCL),
                     device("opencl:2:0", INTEL), gpu], key=opencl.device_rank)
    assert [d.spec for d in ranked] == ["opencl:3:0", "opencl:2:0", "opencl:1:0", "opencl:0:0"]
