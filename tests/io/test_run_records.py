"""What a generated set records of its run: schedule, spot checks, inputs, array conventions
(issue 18, item 9)."""

import json
import shutil

import cv2
import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS, manifest_lines

from gpu_blur import dataset, discovery
from gpu_blur.cli import main
from gpu_blur.testhooks import TEST_FAULT


@pytest.fixture
def photo(tmp_path, coffee_rgb):
    """A folder with one 48 x 64 crop of the built-in photo (the spoon's highlights)."""
    folder = tmp_path / "in"
    folder.mkdir()
    crop = (coffee_rgb[240:288, 330:394] * 255).round().astype(np.uint8)
    cv2.imwrite(str(folder / "spoon.png"), cv2.cvtColor(crop, cv2.COLOR_RGB2BGR))
    return folder


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
def test_run_json_and_manifest_record_tile_budget_verify_and_spot_checks(tmp_path, photo,
                                                                        monkeypatch):
    backend = KERNEL_BACKEND_SPECS[0].split("/")[0]
    args = ["generate", "--input", str(photo), "--backend", backend, "--quiet", "--tile", "24",
            "32", "--max-device-memory", "64M", "--verify", "0.5"]
    assert main([*args, "--output", str(tmp_path / "ok")]) == 0
    run = json.loads((tmp_path / "ok" / "run.json").read_text())
    assert (run["tile"], run["max_device_memory"], run["verify"]) == ([24, 32], 2**26, 0.5)
    [line] = manifest_lines(tmp_path / "ok")
    assert (line["tile"], line["max_device_memory"], line["verify"]) == ([24, 32], 2**26, 0.5)
    assert line["tiles"] == 4 and 1 <= line["spot_checked_tiles"] <= 4
    assert line["spot_check"] == "passed"

    monkeypatch.setenv(TEST_FAULT, "to_raw@3,3")
    assert main([*args[:-1], "1", "--output", str(tmp_path / "bad")]) == 1
    [line] = manifest_lines(tmp_path / "bad")
    assert line["status"] == "failed" and line["spot_check"] == "failed"


def test_a_sample_without_spot_checks_says_none(tmp_path, photo):
    assert main(["generate", "--input", str(photo), "--output", str(tmp_path / "o"),
                 "--quiet"]) == 0
    [line] = manifest_lines(tmp_path / "o")
    assert (line["tile"], line["max_device_memory"], line["verify"]) == (None, None, 0.0)
    assert (line["tiles"], line["spot_checked_tiles"], line["spot_check"]) == (1, 0, "none")


@pytest.mark.slow
def test_the_built_in_photo_is_recorded_by_name_and_resumes_from_another_install(
        tmp_path, monkeypatch, quick_scene):
    out = tmp_path / "set"
    run = ["generate", "--output", str(out), "--scene", str(quick_scene), "--quiet"]
    assert main([*run, "--limit", "1"]) == 0
    installed = str(discovery.default_photo())
    for name in ("manifest.jsonl", "run.json"):
        assert installed not in (out / name).read_text()
    assert manifest_lines(out)[0]["inputs"] == [discovery.BUILT_IN_INPUT]
    # the same set finished where gpu_blur is installed elsewhere
    moved = tmp_path / "elsewhere" / "coffee.png"
    moved.parent.mkdir()
    shutil.copy(installed, moved)
    monkeypatch.setattr(discovery, "default_photo", lambda: moved)
    assert main([*run, "--limit", "2", "--resume"]) == 0
    assert [x["inputs"] for x in manifest_lines(out)] == [[discovery.BUILT_IN_INPUT]] * 2


def test_params_files_hold_the_convention_of_each_array(tmp_path, photo):
    kernel = tmp_path / "k.toml"
    kernel.write_text('[blur]\nmode = "kernel"\n')
    for mode, scene, name in (("trajectory", [], "homographies"),
                              ("kernel", ["--scene", str(kernel)], "kernel")):
        out = tmp_path / mode
        assert main(["generate", "--input", str(photo), "--output", str(out), "--quiet",
                     *scene]) == 0
        with np.load(out / manifest_lines(out)[0]["arrays"]) as arrays:
            assert set(arrays.files) == {name, f"{name}_convention"}
            note = str(arrays[f"{name}_convention"])
        assert note == dataset.ARRAY_CONVENTIONS[name]
        assert "rows y and columns x" in note or "x is the column and y the row" in note
