"""Scenes and cameras by name, and the listings that help choose them (gpu-blur scene, cameras)."""

import os
import subprocess
import sys

import pytest

from gpu_blur.cli import main
from gpu_blur.scene import builtin_scenes, load_scene, scene_from_dict


def test_the_scene_command_prints_the_default_scene_as_toml_that_loads(tmp_path, capsys):
    assert main(["scene"]) == 0
    path = tmp_path / "my.toml"
    path.write_text(capsys.readouterr().out)
    scene = load_scene(path)
    assert scene.to_dict() == scene_from_dict({}).to_dict()


@pytest.mark.parametrize("name", ["realblur_j", "realblur_j.toml"])
def test_a_built_in_scene_is_named_without_its_path(capsys, name):
    assert main(["plan", name]) == 0
    assert "blur.mode = none" in capsys.readouterr().out
    assert load_scene(name).path == builtin_scenes()["realblur_j"]


def test_a_scene_file_of_ones_own_wins_over_a_built_in_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "rsblur.toml").write_text('[blur]\nmode = "kernel"\n')
    assert load_scene("rsblur.toml").blur.mode == "kernel"
    assert load_scene("rsblur").blur.mode == "average"  # no file named rsblur


def test_an_unknown_scene_name_lists_the_built_in_ones(capsys):
    assert main(["plan", "realblur"]) == 2
    err = capsys.readouterr().err
    assert "scene file realblur does not exist" in err and "realblur_j, rsblur" in err


def test_plan_refuses_a_camera_that_generate_refuses(tmp_path, capsys):
    path = tmp_path / "scene.toml"
    path.write_text('[camera]\nname = "sony"\n')
    assert main(["plan", str(path)]) == 2
    assert "unknown camera 'sony'" in capsys.readouterr().err


def test_cameras_lists_the_noise_levels_and_white_balance_ranges(capsys):
    assert main(["cameras"]) == 0
    lines = capsys.readouterr().out.splitlines()
    a7r3 = next(line for line in lines if line.startswith("a7r3 "))
    assert "8.891e-05" in a7r3 and "1.90-2.40" in a7r3 and "1.50-1.90" in a7r3


def test_cameras_into_a_pipe_closed_early_ends_without_an_error():
    read, write = os.pipe()
    os.close(read)  # the reader has gone (as head -1 has after its line)
    try:
        out = subprocess.run([sys.executable, "-m", "gpu_blur.cli", "cameras"], stdout=write,
                             stderr=subprocess.PIPE, text=True)
    finally:
        os.close(write)
    assert out.stderr == "" and out.returncode == 141  # 128 + SIGPIPE, as a shell tool's
