"""What a new user meets first: a missing extra, Warp's notices, the Python entry points."""

import subprocess
import sys

import gpu_blur

#: Runs the CLI in a process where a module cannot be imported (as without its extra).
WITHOUT = """
import sys
sys.modules[{module!r}] = None  # import fails with ModuleNotFoundError, as when not installed
from gpu_blur.cli import main
sys.exit(main({argv!r}))
"""


def _without(module: str, argv: list[str], tmp_path):
    code = WITHOUT.format(module=module, argv=argv)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=tmp_path)


def test_a_backend_whose_extra_is_missing_says_how_to_install_it(tmp_path):
    for module, backend, extra in (("warp", "warp", "warp"), ("pyopencl", "opencl", "opencl")):
        out = _without(module, ["generate", "--output", "out", "--backend", backend], tmp_path)
        assert out.returncode == 2, out.stderr
        assert f"pip install 'gpu_blur[{extra}]'" in out.stderr
        assert "Traceback" not in out.stderr
        assert not (tmp_path / "out").exists()


def test_warp_says_nothing_about_a_missing_cuda_driver_or_psutil():
    out = subprocess.run([sys.executable, "-m", "gpu_blur.cli", "devices"], capture_output=True,
                         text=True)
    assert out.returncode == 0 and "warp:" in out.stdout
    assert "CUDA warning" not in out.stdout + out.stderr and "psutil" not in out.stderr


def test_plan_takes_a_scene_file_or_a_built_in_scene_name():
    assert not gpu_blur.plan("realblur_j").kept("blur")
    assert gpu_blur.plan({"blur": {"mode": "kernel"}}).kept("blur")
