"""Every numeric setting is checked once, by gpu_blur.limits, wherever it is given (issue 13).

Scene keys, camera files, overrides and tile sizes: a value that is not a finite number in its
range is refused before any work, naming the file (or override), the key, the value and the
range. Small images and the numpy backend: what is checked is the refusal.
"""

import dataclasses
import json
import math

import numpy as np
import pytest

import gpu_blur
from gpu_blur.cameras import load_camera
from gpu_blur.cli import main
from gpu_blur.scene import FIELDS, SceneError, describe_fields, load_scene, scene_from_dict
from gpu_blur.scheduler import MIN_TILE

PHOTO = np.random.default_rng(1).integers(0, 256, (8, 8, 3), dtype=np.uint8)
IDENTITY = "[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]"


def beyond_each_end(limit):
    """Numbers just outside a limit, and the non-finite ones."""
    values = [math.nan, math.inf, -math.inf, limit.low - (1 if limit.integer else 1e-3)]
    if math.isfinite(limit.high):
        values.append(limit.high + (1 if limit.integer else limit.high * 1e-3))
    return values


NUMERIC_KEYS = [(section, key, field) for section, fields in FIELDS.items()
                for key, field in fields.items() if field.limit is not None]


@pytest.mark.parametrize("section, key, field", NUMERIC_KEYS,
                         ids=[f"{s}.{k}" for s, k, _ in NUMERIC_KEYS])
def test_every_numeric_scene_key_refuses_non_finite_and_out_of_range_values(section, key,
                                                                            field):
    for value in beyond_each_end(field.limit):
        given = [value, value] if field.pair else value
        with pytest.raises(SceneError) as e:
            scene_from_dict({section: {key: given}}, "my.toml")
        assert str(e.value).startswith(f"my.toml: {section}.{key} = "), str(e.value)
        assert "allowed:" in str(e.value) and field.limit.reason in str(e.value)


@pytest.mark.parametrize("data, message", [
    ({"blur": {"steps": 10**9}}, "blur.steps = 1000000000 is invalid; allowed: int <= 8192"),
    ({"blur": {"roll": 31}}, "blur.roll = 31 is invalid; allowed: int or float <= 30"),
    ({"blur": {"kernel_size": [5, 10**6]}}, "each int <= 255"),
    ({"saturation": {"alpha": [0.5, math.inf]}}, "each a finite int or float"),
    ({"noise": {"gaussian_std": math.nan}}, "noise.gaussian_std = nan is invalid"),
])
def test_costly_or_unusable_scene_values_are_refused_before_any_sample(data, message):
    with pytest.raises(SceneError, match=None) as e:
        scene_from_dict(data, "my.toml")
    assert message in str(e.value)


def test_gpu_blur_scene_lists_each_numeric_key_with_its_range():
    listed = describe_fields()
    for section, key, field in NUMERIC_KEYS:
        table = listed.split(f"[{section}]\n", 1)[1]
        line = table.split(f"{key} = ", 1)[1].split("\n", 1)[0]
        assert line.endswith(f"[{field.limit.describe()}]"), line


def test_a_scene_changed_in_python_meets_the_checks_of_a_file():
    scene = load_scene()
    with pytest.raises(SceneError, match=r"^scene: noise\.shot_noise_k = 0 is invalid"):
        dataclasses.replace(scene, noise=dataclasses.replace(scene.noise, shot_noise_k=0))


def test_synthesize_takes_a_scene_dict_and_checks_it():
    with pytest.raises(SceneError, match=r"noise\.read_noise_std = nan is invalid"):
        gpu_blur.synthesize({"blurred": PHOTO}, {"blur": {"mode": "none"},
                                                 "noise": {"read_noise_std": math.nan}})
    made = gpu_blur.synthesize({"blurred": PHOTO}, {"blur": {"mode": "none"}})
    assert made.blurred.shape == (8, 8, 3)


# ---- camera files ----------------------------------------------------------------------------

def camera_file(tmp_path, tables, top=""):
    """``cam.toml``: ``top`` (top-level keys), an identity [color], then ``tables``."""
    path = tmp_path / "cam.toml"
    path.write_text(f"{top}\n[color]\ncamera_to_linear = {IDENTITY}\n{tables}\n")
    return path


@pytest.mark.parametrize("text, key", [
    ("[noise]\nshot_noise = 1e-4", "noise.shot_noise"),
    ("[white_balance]\ngreen = 1.0", "white_balance.green"),
    ("[response]\npolynomial = [0.0, 1.0]\npolynom = [0.0, 1.0]", "response.polynom"),
    ("[colour]\nccm_xyz = 1", "colour"),
])
def test_a_camera_file_refuses_unknown_keys_naming_file_and_key(tmp_path, text, key):
    path = camera_file(tmp_path, text)
    with pytest.raises(ValueError) as e:
        load_camera(path)
    assert str(e.value).startswith(f"camera file {path}: unknown key {key}; ")


def test_a_camera_file_refuses_an_unknown_top_level_key(tmp_path):
    path = camera_file(tmp_path, "", top='nmae = "mine"')
    with pytest.raises(ValueError, match="unknown key nmae; top-level keys are name, source"):
        load_camera(path)


@pytest.mark.parametrize("top, tables, shown", [
    ("", '[noise]\nshot_noise_k = "x"', "noise.shot_noise_k = 'x' is invalid; allowed: int or "
                                        "float"),
    ("", '[white_balance]\nred = "a"', "white_balance.red = 'a' is invalid; allowed: int or "
                                       "float"),
    ("", '[white_balance]\npairs = "2, 1.5"', "white_balance.pairs = '2, 1.5' is invalid"),
    ("", "[white_balance]\npairs = [[2.0, 1.5, 1]]\nred = 2.0", "either pairs, or red and "
                                                                 "blue"),
    ("name = 5", "", "name = 5 is invalid; expected a string"),
])
def test_wrong_types_in_a_camera_file_get_a_value_error_naming_file_and_key(tmp_path, top,
                                                                            tables, shown):
    path = camera_file(tmp_path, tables, top)
    with pytest.raises(ValueError) as e:
        load_camera(path)
    assert str(e.value).startswith(f"camera file {path}: ") and shown in str(e.value)


@pytest.mark.parametrize("spec, shown", [
    ({"color": 5}, "[color] = 5 is invalid; expected a table of keys"),
    ({"color": {"camera_to_linear": [["1", 0, 0], [0, 1, 0], [0, 0, 1]]}},
     "color.camera_to_linear = [['1', 0, 0], [0, 1, 0], [0, 0, 1]] is invalid; expected a "
     "3 x 3 list of numbers"),
    ({"color": {"ccm_xyz": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "adapt_d50": 1}},
     "color.adapt_d50 = 1 is invalid; expected true or false"),
    ({"color": {"camera_to_linear": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
      "noise": {"shot_noise_k": 10**400}}, "noise.shot_noise_k = 1000"),
])
def test_wrong_tables_and_numbers_in_a_json_camera_file_are_named(tmp_path, spec, shown):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(spec))
    with pytest.raises(ValueError) as e:
        load_camera(path)
    assert str(e.value).startswith(f"camera file {path}: ") and shown in str(e.value)


@pytest.mark.parametrize("text, key", [
    ("[noise]\nshot_noise_k = 1e-40", "noise.shot_noise_k = 1e-40"),  # a float32 denormal
    ("[noise]\nshot_noise_k = 1.0", "noise.shot_noise_k = 1.0"),
    ("[noise]\nread_noise_std = nan", "noise.read_noise_std = nan"),
    ("[noise]\nread_noise_std = 1e38", "noise.read_noise_std = 1e+38"),
    ("[white_balance]\nred = 1e-37", "white_balance.red = 1e-37"),
    ("[white_balance]\nblue = [1.5, 100.0]", "white_balance.blue = 100.0"),
    ("[white_balance]\nblue = [2.0, 1.5]", "white_balance.blue = [2.0, 1.5]"),
    ("[white_balance]\npairs = [[2.0, 1.5, 0]]", "white_balance.pairs[0][2] (weight) = 0"),
])
def test_camera_numbers_outside_their_range_are_refused_with_the_range(tmp_path, text, key):
    path = camera_file(tmp_path, text)
    with pytest.raises(ValueError) as e:
        load_camera(path)
    assert str(e.value).startswith(f"camera file {path}: {key} is invalid")


def test_a_camera_matrix_that_scales_raw_far_beyond_one_is_refused(tmp_path):
    # Cam2Lin = I / 8: its inverse gives RAW values up to 8, where float32 kernels leave the
    # tolerance table (gpu_blur.limits)
    path = tmp_path / "dim.toml"
    path.write_text("[color]\ncamera_to_linear = [[0.125, 0, 0], [0, 0.125, 0], [0, 0, 0.125]]\n")
    with pytest.raises(ValueError, match=r"dim\.toml: color\.camera_to_linear: camera 'dim': "
                                         r"its Lin2Cam maps a \[0, 1\] colour to 8; allowed"):
        load_camera(path)


def test_a_bad_camera_file_stops_generate_before_any_sample(tmp_path, capsys):
    camera_file(tmp_path, "[white_balance]\nred = 1e-37")
    scene = tmp_path / "scene.toml"
    scene.write_text('[camera]\nname = "cam.toml"\n')
    out = tmp_path / "out"
    assert main(["generate", "--output", str(out), "--scene", str(scene), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"camera file {tmp_path / 'cam.toml'}: white_balance.red = 1e-37 is invalid" in err
    assert not out.exists()


# ---- overrides -------------------------------------------------------------------------------

class NoPasses:
    """A numpy backend that fails the test if any pass runs."""

    name, device, precision = "numpy", "numpy", "float64"

    def __getattr__(self, name):
        raise AssertionError(f"{name} ran: the override should be refused before any pass")


@pytest.mark.parametrize("name, value", [
    ("red_gain", 0.0), ("blue_gain", math.nan), ("shot_noise_k", 0.0),
    ("shot_noise_k", 1e-40), ("read_noise_std", 1e38), ("alpha", math.inf),
    ("red_gain", 1e39), ("kernel_size", 10**6),
])
def test_an_override_outside_its_range_is_refused_before_any_pass(name, value):
    mode = "kernel" if name == "kernel_size" else "none"
    scene = scene_from_dict({"blur": {"mode": mode}, "saturation": {"mode": "on"}})
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize({"blurred": PHOTO} if mode == "none" else [PHOTO], scene,
                            backend=NoPasses(), overrides={name: value})
    assert str(e.value).startswith(f"overrides[{name!r}] = {value!r} is invalid; allowed: ")


def test_a_homographies_override_has_at_most_the_poses_blur_steps_allows():
    poses = np.broadcast_to(np.eye(3), (8193, 3, 3))
    with pytest.raises(ValueError, match=r"1 <= n <= 8192, as blur.steps"):
        gpu_blur.synthesize([PHOTO], load_scene(), backend=NoPasses(),
                            overrides={"homographies": poses})


# ---- tiles -----------------------------------------------------------------------------------

@pytest.mark.parametrize("tile", [(1, 1), (8, 64), (64, MIN_TILE - 1)])
def test_tiles_below_the_minimum_are_refused(tile):
    with pytest.raises(ValueError, match=f"tile {tile[0]} {tile[1]}: rows and columns must be "
                                         f">= {MIN_TILE}: each tile costs"):
        gpu_blur.synthesize({"blurred": PHOTO}, {"blur": {"mode": "none"}}, tile=tile)


def test_the_command_refuses_a_tiny_tile_before_any_sample(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["generate", "--output", str(out), "--tile", "1", "1", "--quiet"]) == 2
    assert "--tile 1 1: rows and columns must be >= 16" in capsys.readouterr().err
    assert not out.exists()
