"""What a process pays before any work: ``import gpu_blur`` and ``gpu-blur --help``.

scipy's FFT and optimizer are imported where they are used (they took 0.5-0.9 s of every
start, more than the rest of the package with numpy), and no device library is imported until
a backend asks for it. Read from ``sys.modules`` of a fresh process, not from timings.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gpu_blur.analysis.calibrate import response
from gpu_blur.reference import motion_kernel

#: Libraries no start may import: scipy (all of it) and the device libraries.
HEAVY = ("scipy", "torch", "torchvision", "warp", "pyopencl", "cupy")

#: Prints which of HEAVY a fresh process has imported after running ``code``.
PROBE = """
import contextlib, json, sys
{code}
print(json.dumps(sorted(n for n in sys.modules if n.partition(".")[0] in {heavy!r})))
"""


def loaded_after(code: str, tmp_path) -> list[str]:
    out = subprocess.run([sys.executable, "-c", PROBE.format(code=code, heavy=HEAVY)],
                         capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.parametrize("code", [
    "import gpu_blur",
    "import gpu_blur.cli",
    # the parser imports every subcommand's module (calibrate's reads its help from the fit)
    "from gpu_blur.cli import main\nwith contextlib.suppress(SystemExit): main(['--help'])",
    "from gpu_blur.cli import main\nwith contextlib.suppress(SystemExit): "
    "main(['generate', '--help'])",
])
def test_importing_gpu_blur_loads_no_fft_or_device_library(code, tmp_path):
    assert loaded_after(code, tmp_path) == []


def test_the_probe_sees_a_heavy_import(tmp_path):
    assert "scipy.fft" in loaded_after("import scipy.fft", tmp_path)


def test_a_missing_scipy_is_named_with_its_fix_where_it_is_first_needed(monkeypatch):
    for name in ("scipy", "scipy.fft", "scipy.optimize"):
        monkeypatch.setitem(sys.modules, name, None)  # as when scipy is not installed
    with pytest.raises(ModuleNotFoundError, match=r"convolve_kernel needs scipy.*pip install "
                       r"scipy, or reinstall gpu_blur"):
        motion_kernel.convolve_kernel(np.ones((4, 4)), np.ones((3, 3)))
    with pytest.raises(ModuleNotFoundError, match=r"camera response fit needs scipy.*pip "
                       r"install scipy, or reinstall gpu_blur"):
        response._least_squares_with_inequalities(np.eye(2), np.ones(2), np.eye(2), np.zeros(2))
