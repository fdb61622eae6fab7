from pathlib import Path

import pytest

import gpu_blur
from gpu_blur.planning import plan
from gpu_blur.scene import FIELDS, SceneError, load_scene, scene_from_dict

SCENES = sorted((Path(gpu_blur.__file__).parent / "data" / "scenes").glob("*.toml"))


def test_empty_scene_takes_every_default():
    scene = load_scene()
    for section, fields in FIELDS.items():
        for key, field in fields.items():
            assert getattr(getattr(scene, section), key) == field.default


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.name)
def test_shipped_example_scenes_load_and_plan(path):
    scene = load_scene(path)
    assert str(plan(scene))


@pytest.mark.parametrize("data, message", [
    ({"nosie": {}}, "unknown section [nosie]"),
    ({"noise": {"levle": 1}}, "unknown key noise.levle; [noise] keys are model"),
    ({"blur": {"mode": "motion"}}, "blur.mode = 'motion' is invalid; allowed: 'average'"),
    ({"blur": {"frames": 2.5}}, "blur.frames = 2.5 is invalid; allowed: int"),
    ({"blur": {"frames": True}}, "blur.frames = True is invalid"),
    ({"saturation": {"alpha": [1.5, 0.5]}}, "low <= high"),
    ({"saturation": {"alpha": 1.0}}, "a [low, high] pair"),
    ({"output": {"bits": 12}}, "output.bits = 12 is invalid; allowed: 0 | 8 | 16"),
    ({"noise": {"shot_noise_k": -1e-4}}, "allowed: int or float >= 1e-09 (Poisson gain K"),
])
def test_bad_values_are_named_with_what_is_allowed(data, message):
    with pytest.raises(SceneError, match=None) as e:
        scene_from_dict(data, "my.toml")
    assert str(e.value).startswith("my.toml: ") and message in str(e.value)


def test_scene_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "broken.toml"
    bad.write_text("[blur\nmode = 1")
    with pytest.raises(SceneError, match=r"broken\.toml: not valid TOML"):
        load_scene(bad)
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "none.toml")


@pytest.mark.parametrize("text, message", [
    ("[blur]\nsteps = " + "[" * 5000 + "]" * 5000, "not valid TOML: arrays or tables are nested "
                                                    "too deeply (more than about"),
    ("a = " + "{b = " * 3000 + "1" + "}" * 3000, "not valid TOML: arrays or tables are nested too"),
    (b'[camera]\nname = "a7r3"\n# r\xe9glages\n', "not UTF-8 text (byte 0xE9 on line 3 cannot be "
                                                   "decoded); save the file as UTF-8"),
    ("[blur]\nsteps = 1" + "0" * 5000, "not valid TOML: Exceeds the limit (4300 digits)"),
], ids=["deep-arrays", "deep-tables", "latin-1", "5000-digits"])
def test_scene_files_that_do_not_parse_are_named_by_the_command(tmp_path, capsys, text, message):
    from gpu_blur.cli import main

    path = tmp_path / "s.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(SceneError) as e:
        load_scene(path)
    assert str(e.value).startswith(f"scene file {path}: {message}")
    assert main(["plan", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"gpu-blur: error: scene file {path}: {message}")
    assert len(err.splitlines()) == 1


def test_plan_without_noise_skips_the_raw_round_trip_unless_asked():
    scene = scene_from_dict({"noise": {"model": "none"}})
    p = plan(scene)
    assert not p.raw_round_trip and not p.kept("demosaic")
    assert "no RAW round trip" in p["mosaic"].reason
    forced = plan(scene_from_dict({"noise": {"model": "none"}, "isp": {"round_trip": "always"}}))
    assert forced.raw_round_trip and not forced.kept("poisson_gaussian_noise")


def test_plan_gaussian_noise_runs_in_srgb_without_raw():
    p = plan(scene_from_dict({"noise": {"model": "gaussian"}}))
    assert p.kept("gaussian_noise") and not p.raw_round_trip


def test_plan_saturation_auto_depends_on_the_sample():
    scene = load_scene()
    assert plan(scene).kept("saturate")
    assert not plan(scene, saturated=False).kept("saturate")
    assert not plan(scene, saturated=False).kept("restore_saturated")
    assert plan(scene, saturated=True).kept("restore_saturated")


def test_plan_crf_none_keeps_linear_output_and_skips_retone():
    p = plan(scene_from_dict({"output": {"crf": "none"}}))
    assert not p.kept("tone") and not p.kept("retone")
    assert plan(scene_from_dict({"output": {"crf": "a7r3"}})).kept("retone")
