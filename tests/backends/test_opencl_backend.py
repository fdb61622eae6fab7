"""The OpenCL backend's device handling, build errors and plan-driven compilation."""

import dataclasses
import subprocess
import sys
import zipfile

import pytest
from conftest import KERNEL_BACKEND_SPECS, ROOT

opencl = pytest.importorskip("gpu_blur.backends.opencl")
from gpu_blur.backends.kernel import pass_config  # noqa: E402
from gpu_blur.cli import main  # noqa: E402
from gpu_blur.planning import plan  # noqa: E402
from gpu_blur.scene import scene_from_dict  # noqa: E402

needs_device = pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no usable OpenCL device")


def test_no_platform_error_says_how_to_get_an_opencl_runtime(monkeypatch):
    monkeypatch.setattr(opencl, "opencl_devices", lambda: [])
    with pytest.raises(opencl.OpenCLError, match="pip install pocl-binary-distribution"):
        opencl.OpenCLBackend("opencl")


@needs_device
def test_fp64_on_a_device_without_it_is_refused(monkeypatch):
    real = opencl.opencl_devices()
    monkeypatch.setattr(opencl, "opencl_devices",
                        lambda: [dataclasses.replace(d, fp64=False) for d in real])
    with pytest.raises(opencl.OpenCLError, match="has no fp64"):
        opencl.OpenCLBackend("opencl", "float64")


@needs_device
def test_failed_build_reports_the_compiler_log_and_the_defines():
    backend = opencl.OpenCLBackend("opencl")
    with pytest.raises(opencl.OpenCLError) as e:
        backend.program("to_raw.cl", {"GB_STAGE_MOSAIC": "1", "uint2": "undefined_type"})
    message = str(e.value)
    assert "kernels/opencl/to_raw.cl" in message and "compiler log" in message
    assert "-Duint2=undefined_type" in message and "-DGB_STAGE_MOSAIC=1" in message


def test_unknown_device_names_the_ones_present():
    with pytest.raises((opencl.OpenCLError, ValueError), match="opencl:9:9"):
        opencl.OpenCLBackend("opencl:9:9")


def test_only_the_stages_a_plan_keeps_are_compiled_in():
    noiseless = plan(scene_from_dict({"noise": {"model": "none"}}), saturated=False)
    assert opencl.config_defines(pass_config(noiseless, "to_raw")) == {}
    full = plan(scene_from_dict({"isp": {"demosaic": "bilinear", "border": "zero"},
                                 "output": {"crf": "a7r3-lut", "bits": 16}}), saturated=True)
    assert opencl.config_defines(pass_config(full, "to_raw")) == {
        f"GB_STAGE_{name}": "1" for name in (
            "SATURATE", "LINEAR_TO_CAMERA", "MOSAIC", "INVERSE_WHITE_BALANCE",
            "POISSON_GAUSSIAN_NOISE", "WHITE_BALANCE")}
    finish = opencl.config_defines(pass_config(full, "finish"))
    assert finish["GB_DEMOSAIC_BILINEAR"] == "1" and finish["GB_ZERO_BORDER"] == "1"
    assert finish["GB_RETONE_LOOKUP"] == "1" and finish["GB_QUANTIZE_BITS"] == "16"
    assert "GB_STAGE_GAUSSIAN_NOISE" not in finish


def test_crop_is_no_define_of_the_finish_pass():
    cropped = plan(scene_from_dict({"output": {"crop": 4}}))
    assert cropped.kept("crop")
    assert "GB_STAGE_CROP" not in opencl.config_defines(pass_config(cropped, "finish"))


def test_devices_command_lists_numpy_and_every_opencl_device(capsys):
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("numpy")
    for d in opencl.opencl_devices():
        assert d.spec in out and ("fp64 yes" in out or "fp64 no" in out)


@needs_device
def test_generate_with_the_opencl_backend_writes_a_set(tmp_path):
    out = tmp_path / "set"
    assert main(["generate", "--output", str(out), "--backend", "opencl", "--limit", "1",
                 "--quiet", "--tile", "128", "200"]) == 0
    line = (out / "manifest.jsonl").read_text()
    assert '"backend": "opencl"' in line and '"device": "opencl ' in line


@pytest.mark.slow
def test_the_wheel_carries_the_kernel_sources(tmp_path):
    root = ROOT
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                    str(tmp_path), str(root)], check=True)
    (wheel,) = tmp_path.glob("gpu_blur-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    sources = {p.relative_to(root / "kernels").as_posix()
               for p in (root / "kernels").rglob("*") if p.suffix in (".cl", ".h")}
    assert sources and {f"gpu_blur/kernels/{s}" for s in sources} <= set(names)
