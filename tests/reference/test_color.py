import json

import numpy as np
import pytest

from gpu_blur import cameras
from gpu_blur.constants import D50_TO_D65, D65_TO_D50, SRGB_TO_XYZ, XYZ_TO_SRGB, rsblur_data
from gpu_blur.reference import color
from gpu_blur.testing import assert_close


@pytest.fixture
def image():
    return np.random.default_rng(3).uniform(-0.1, 1.1, (16, 24, 3))


def test_srgb_xyz_matrices_are_inverses(image):
    assert_close(color.xyz_to_linear(color.linear_to_xyz(image)), image, "color_round_trip")
    assert_close(SRGB_TO_XYZ @ XYZ_TO_SRGB, np.eye(3), "color_matrix", "independent")
    assert_close(D65_TO_D50 @ D50_TO_D65, np.eye(3), "color_matrix", "independent")


def test_a7r3_matrix_chain_equals_composed_camera_to_linear(image):
    xyz_to_cam = np.array(rsblur_data()["a7r3"]["xyz_to_camera"])
    cam = cameras.get_camera("a7r3")
    # Eq. 8 step by step: lin -> XYZ -> camera; and Eq. 5 back.
    stepwise_cam = color.xyz_to_camera(color.linear_to_xyz(image), xyz_to_cam)
    assert_close(color.apply_matrix(image, cam.linear_to_camera), stepwise_cam, "color_matrix",
                 "independent")
    stepwise_lin = color.xyz_to_linear(color.camera_to_xyz(stepwise_cam, xyz_to_cam))
    assert_close(stepwise_lin, image, "color_round_trip")


def test_a7r3_maps_srgb_white_to_camera_white():
    # The authors normalised the LibRaw matrix so sRGB white is camera (1, 1, 1) (Brooks et al.).
    cam = cameras.get_camera("a7r3")
    assert_close(cam.linear_to_camera @ np.ones(3), np.ones(3), "color_matrix", "independent")


@pytest.mark.parametrize("session", [f"{i:04d}" for i in range(1, 20)])
def test_rsblur_session_lin2cam_matches_the_authors_derived_matrix(session):
    s = rsblur_data()["rsblur"]["sessions"][session]
    expected_column = np.array(s["check_linear_to_camera_row"]).T
    cam = cameras.get_camera(f"rsblur-{session}")
    assert_close(cam.linear_to_camera, expected_column, "color_matrix", "independent")


def test_rsblur_ccm_chain_step_by_step_equals_composed_matrix(image):
    ccm = np.array(rsblur_data()["rsblur"]["sessions"]["0007"]["ccm_row"]).T
    cam = cameras.get_camera("rsblur-0007")
    stepwise = color.xyz_to_linear(color.correct_xyz(color.linear_to_xyz(image), ccm, True))
    assert_close(color.apply_matrix(image, cam.camera_to_linear), stepwise, "color_matrix",
                 "independent")
    back = color.xyz_to_linear(color.uncorrect_xyz(color.linear_to_xyz(stepwise), ccm, True))
    assert_close(back, image, "color_round_trip")


@pytest.mark.parametrize("name", cameras.preset_names())
def test_every_preset_round_trips_linear_through_camera(name, image):
    cam = cameras.get_camera(name)
    there = color.apply_matrix(image, cam.linear_to_camera)
    assert_close(color.apply_matrix(there, cam.camera_to_linear), image, "color_round_trip")


def test_near_singular_matrix_is_refused_with_its_condition_number():
    m = np.diag([1.0, 1.0, 1e-7])
    with pytest.raises(ValueError, match="condition number 1e\\+07"):
        color.checked_inverse(m, "test matrix")
    with pytest.raises(ValueError, match="finite"):
        color.checked_inverse(np.full((3, 3), np.nan))


def test_presets_are_made_once_and_their_matrices_are_read_only():
    # a Synthesizer per synthesize call meets the same preset (no JSON read, no inverse, and
    # the kernel backends' per-camera work is found again); nobody can change it under others
    for name in cameras.preset_names():
        camera = cameras.get_camera(name)
        assert cameras.get_camera(name) is camera
        for matrix in (camera.camera_to_linear, camera.linear_to_camera):
            with pytest.raises(ValueError, match="read-only"):
                matrix[0, 0] = 2.0


def test_identity_camera_leaves_colours_alone(image):
    cam = cameras.get_camera("srgb")
    assert np.array_equal(color.apply_matrix(image, cam.linear_to_camera), image)


def test_camera_file_loads_and_bad_one_names_file_and_key(tmp_path):
    good = tmp_path / "cam.toml"
    good.write_text('[color]\nxyz_to_camera = [[1.2, -0.2, 0.0], [-0.1, 1.1, 0.0], '
                    '[0.0, 0.1, 0.9]]\n[white_balance]\nred = [2.0, 2.2]\nblue = 1.7\n'
                    '[noise]\nshot_noise_k = 1e-4\nread_noise_std = 1e-3\n')
    cam = cameras.get_camera(str(good))
    assert cam.name == "cam" and cam.white_balance.blue_range == (1.7, 1.7)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"color": {"ccm_xyz": [[1, 2], [3, 4]]}}))
    with pytest.raises(ValueError, match=r"bad\.json: color\.ccm_xyz .* 3 x 3"):
        cameras.get_camera(str(bad))
    with pytest.raises(ValueError, match="unknown camera 'nikon'.*a7r3"):
        cameras.get_camera("nikon")


def test_wb_list_draws_each_pair_in_proportion_to_its_rows():
    wb = cameras.get_camera("a7r3-wb-list").white_balance
    u = (np.arange(3639) + 0.5) / 3639
    drawn = [wb.draw(x, 0.5) for x in u]
    counts = {pair: drawn.count(pair) for pair in set(drawn)}
    assert counts == {(r, b): n for r, b, n in wb.pairs}
