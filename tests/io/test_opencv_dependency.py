"""gpu_blur needs OpenCV's main build, not contrib, so it installs beside albumentations with
one cv2 (issue 38; albumentations#1139, #1293)."""

import importlib.metadata
import re
import sys
from pathlib import Path

import cv2
import pytest

ROOT = Path(__file__).resolve().parents[2]

#: The PyPI distributions that each install a ``cv2`` package of their own.
OPENCV = {"opencv-python", "opencv-python-headless", "opencv-contrib-python",
          "opencv-contrib-python-headless"}

if sys.version_info >= (3, 11):
    import tomllib
else:
    tomllib = pytest.importorskip("tomli")


def distribution(requirement: str) -> str:
    return re.match(r"[A-Za-z0-9._-]+", requirement)[0].lower().replace("_", "-")


def test_pyproject_asks_for_opencv_python_headless_and_no_other_opencv():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [*project["dependencies"], *(r for extra in project["optional-dependencies"]
                                          .values() for r in extra)]
    assert {distribution(r) for r in wanted} & OPENCV == {"opencv-python-headless"}


def test_the_installed_metadata_asks_for_no_contrib_build():
    names = {distribution(r) for r in importlib.metadata.requires("gpu_blur") or ()}
    assert names & OPENCV == {"opencv-python-headless"}, (
        "reinstall gpu_blur (pip install -e .): its metadata predates the switch")


def test_the_constraints_pin_the_same_distribution():
    pins = [line.split("==")[0].lower() for line in
            (ROOT / "tests" / "constraints.txt").read_text().splitlines()
            if "==" in line and not line.startswith("#")]
    assert [p for p in pins if p in OPENCV] == ["opencv-python-headless"]


def test_every_opencv_function_the_package_calls_is_in_the_installed_build():
    used = set()
    for folder in ("gpu_blur", "bench"):
        for path in (ROOT / folder).rglob("*.py"):
            used |= set(re.findall(r"\bcv2\.([A-Za-z_][A-Za-z0-9_]*)", path.read_text()))
    assert "DISOpticalFlow_create" in used
    assert sorted(name for name in used if not hasattr(cv2, name)) == []
