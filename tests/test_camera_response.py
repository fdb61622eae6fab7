"""A calibrated camera's fitted response: read from its camera file's [response] table."""

import numpy as np
import pytest

from gpu_blur.calibrate import read_response
from gpu_blur.cameras import get_camera, load_camera, preset_names
from gpu_blur.constants import A7R3_CRF_POLYNOMIAL

#: A response unlike A7R3's: y = 1.4 x - 0.4 x^2, increasing on [0, 1] from 0 to 1.
GENTLE = np.array([0.0, 1.4, -0.4])


def camera_file(path, polynomial=None, response_text=None):
    """A camera file (identity colour) with ``[response] polynomial``, written exactly."""
    lines = ["[color]", "camera_to_linear = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
             "[white_balance]", "red = [1.8, 2.2]", "blue = 1.6"]
    if polynomial is not None:
        lines += ["[response]", "polynomial = [" + ", ".join(repr(float(c)) for c in polynomial)
                  + "]"]
    if response_text is not None:
        lines.append(response_text)
    path.write_text("\n".join(lines) + "\n")
    return path


# -- the camera file ---------------------------------------------------------------------------

def test_load_camera_reads_the_response_polynomial_read_only(tmp_path):
    camera = load_camera(camera_file(tmp_path / "cam.toml", A7R3_CRF_POLYNOMIAL))
    assert camera.response.dtype == np.float64
    assert np.array_equal(camera.response, A7R3_CRF_POLYNOMIAL)
    assert not camera.response.flags.writeable
    assert load_camera(camera_file(tmp_path / "plain.toml")).response is None
    assert all(get_camera(name).response is None for name in preset_names())


@pytest.mark.parametrize("text, shown", [
    ("[response]\npolynomial = [0.5]", "response.polynomial = [0.5]"),
    ("[response]\npolynomial = [0.0, nan]", "response.polynomial = [0.0, nan]"),
    ("[response]\npolynomial = [0.0, inf, 1.0]", "response.polynomial = [0.0, inf, 1.0]"),
    ('[response]\npolynomial = ["0", "1"]', "response.polynomial = ['0', '1']"),
    ("[response]\npolynomial = [false, true]", "response.polynomial = [False, True]"),
    ("[response]\npolynomial = 1.0", "response.polynomial = 1.0"),
    ("[response]\nsource = 'no polynomial'", "response.polynomial = None"),
])
def test_load_camera_refuses_a_bad_response_naming_file_key_value_and_fix(tmp_path, text, shown):
    path = camera_file(tmp_path / "bad.toml", response_text=text)
    with pytest.raises(ValueError) as e:
        load_camera(path)
    message = str(e.value)
    assert str(path) in message and shown in message
    assert ">= 2 finite numbers" in message
    assert "rerun gpu-blur calibrate with --crf-linear and --crf-rendered" in message
    with pytest.raises(ValueError, match="response.polynomial"):
        read_response(path)


def test_a_response_that_is_not_a_table_is_refused(tmp_path):
    path = tmp_path / "flat.json"
    path.write_text('{"color": {"camera_to_linear": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, '
                    '"response": [0, 1]}')
    with pytest.raises(ValueError, match=r"flat.json: \[response\] = \[0, 1\] is invalid"):
        load_camera(path)


def test_read_response_shares_the_polynomial_with_load_camera(tmp_path):
    path = camera_file(tmp_path / "cam.toml", GENTLE,
                       response_text="inverse_linear = [0.0, 0.4, 1.0]")
    coefficients, table = read_response(path)
    assert np.array_equal(coefficients, load_camera(path).response)
    assert np.array_equal(table, [0.0, 0.4, 1.0])
    path = camera_file(tmp_path / "cam.toml", GENTLE,
                       response_text="inverse_linear = [0.0, 0.6, 0.4]")
    with pytest.raises(ValueError, match=r"response.inverse_linear = \[0.0, 0.6, 0.4\].*"
                                         "non-decreasing"):
        read_response(path)
    with pytest.raises(ValueError, match="no \\[response\\] table"):
        read_response(camera_file(tmp_path / "plain.toml"))
