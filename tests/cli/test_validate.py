"""`gpu-blur validate` and the test suite run the same conformance checks (gpu_blur.conformance).

Every check of the package's list runs here on every backend, so a green suite and a green
``validate`` mean the same thing; the command's own behaviour (tables, JSON, exit status) is
checked on numpy, where it takes a second.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import BACKEND_SPECS, make_backend, spec_backend, spec_dtype

from gpu_blur import backends, tolerances
from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.cli import main
from gpu_blur.conformance import checks


@pytest.mark.parametrize("name", [c.name for c in checks.CHECKS])
@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_conformance_check_passes(spec, name):
    item = next(c for c in checks.CHECKS if c.name == name)
    target = checks.Target(make_backend(spec).backend, spec_backend(spec), spec_dtype(spec))
    outcomes = checks.run_check(item, target)
    failed = [f"{o.stage}: {o.detail}" for o in outcomes if o.passed is False]
    assert not failed, "; ".join(failed)
    assert any(o.passed for o in outcomes) or not target.kernels and item.kernels_only


def test_every_tolerance_row_has_its_line_in_tolerances_py():
    sources = checks.row_sources()
    assert set(sources) == set(tolerances.TOLERANCES)
    lines = open(tolerances.__file__).read().splitlines()
    for (stage, _, _), (line, _) in sources.items():
        assert f'"{stage}"' in lines[line - 1], (stage, line)
    line, claim = sources[("accumulate", "opencl", "float32")]
    assert '("accumulate", "float32")' in lines[line - 1] and claim == "measured 4.6e-7"


def test_validate_quick_on_numpy_exits_0_with_a_table_and_json(tmp_path, capsys):
    out = tmp_path / "report.json"
    assert main(["validate", "--backend", "numpy", "--quick", "--json", str(out)]) == 0
    printed = capsys.readouterr()
    assert "== numpy: float64 (host CPU)" in printed.out
    assert "tolerances.py:" in printed.out and "every check passed" in printed.out
    assert "[1/" in printed.err  # progress, one line per check
    report = json.loads(out.read_text())
    assert report["passed"] and report["quick"] and report["failed"] == 0
    (device,) = report["devices"]
    assert device["libraries"]["numpy"] == np.__version__
    stages = {r["stage"] for r in device["rows"]}
    assert {"srgb_to_linear", "accumulate", "to_raw", "saturate", "finish",
            "poisson counts", "blurred", "pipeline"} <= stages


class BrokenToRaw:
    """The numpy backend with a wrong RAW value at one pixel, as a miscompiled kernel gives."""

    def __init__(self):
        self.backend = NumpyBackend()

    def __getattr__(self, name):
        return getattr(self.backend, name)

    def to_raw(self, *args, **kwargs):
        image, saturated = self.backend.to_raw(*args, **kwargs)
        image = np.array(image)
        image[1, 1] += 1e-3
        return image, saturated


def test_a_backend_with_a_wrong_pass_fails_validate_naming_the_stage(monkeypatch, capsys,
                                                                       tmp_path):
    monkeypatch.setattr(backends, "get_backend", lambda name, precision="float32": BrokenToRaw())
    out = tmp_path / "report.json"
    assert main(["validate", "--backend", "numpy", "--quick", "--json", str(out)]) == 1
    printed = capsys.readouterr().out
    assert "FAIL numpy float64 to_raw: Lin2Cam, mosaic, WB, saturation (no noise) " \
           "[to_raw]: to_raw on numpy/float64: 1 of" in printed
    failed = {r["stage"] for r in json.loads(out.read_text())["devices"][0]["rows"]
              if r["passed"] is False}
    assert "to_raw" in failed and "accumulate" not in failed


@pytest.mark.parametrize("argv", [
    ["--backend", "opencl:99:0"],
    ["--backend", "nonsense"],
    ["--backend", "numpy", "--precision", "float16"],
    ["--backend", "numpy", "--against", "numpy"],
])
def test_usage_errors_exit_2_before_any_check(argv, capsys):
    try:
        status = main(["validate", "--quick", *argv])
    except SystemExit as e:  # argparse
        status = e.code
    assert status == 2
    printed = capsys.readouterr()
    assert "error" in printed.err and "[1/" not in printed.err


KERNEL_DEVICES = list(dict.fromkeys(s.split("/")[0] for s in BACKEND_SPECS if s != "numpy"))


@pytest.mark.skipif(len(KERNEL_DEVICES) < 2, reason="needs two kernel devices")
def test_validate_against_compares_two_devices_directly(tmp_path, capsys):
    a, b = KERNEL_DEVICES[:2]
    out = tmp_path / "against.json"
    assert main(["validate", "--backend", a, "--against", b, "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    (device,) = report["devices"]
    assert device["against"]["backend"] == b
    stages = {r["stage"] for r in device["rows"]}
    assert {"philox words", "uniforms", "poisson counts", "cross_backend"} <= stages
