import json
import math
from importlib import resources

import colour  # colour-science, which the test extra's colour-demosaicing brings
import cv2
import numpy as np
import pytest

import gpu_blur
from gpu_blur.analysis import calibrate as cal
from gpu_blur.cameras import get_camera, load_camera
from gpu_blur.cli import main
from gpu_blur.constants import A7R3_CRF_POLYNOMIAL, SRGB_TO_XYZ, XYZ_TO_SRGB
from gpu_blur.reference.color import camera_to_linear_matrix
from gpu_blur.reference.transfer import linear_to_srgb, polynomial_crf, srgb_to_linear
from gpu_blur.scene import scene_from_dict
from gpu_blur.testing import assert_close

#: RAW noise of the noisy chart test: about RSBlur's read-noise std (9.2e-4).
RAW_NOISE_STD = 1e-3
#: Noisy chart fits drawn.
NOISE_DRAWS = 400
#: Each fitted value of each draw lies within this many first-order standard deviations
#: (the fit's Jacobian times RAW_NOISE_STD). Measured: at most 4.06 over 500 draws x 12 values.
NOISE_MAX_Z = 5.0
#: Measured std / first-order std of each value. Measured 0.96 to 1.04 over 500 draws; a std
#: from 400 draws has a relative sampling error of 1 / sqrt(800) = 3.5 %, so this is 4 of those.
NOISE_STD_RATIO = (0.85, 1.15)
#: The mean of the draws lies within this many standard errors of the truth (the fit is
#: unbiased to first order). Measured at most 2.4 over 500 draws x 12 values.
NOISE_BIAS_Z = 4.0
GAINS = np.array([2.1, 1.0, 1.7])
ALPHA = 1.6


def chart_camera(rng, reference, alpha=ALPHA, gains=GAINS):
    """A camera and the RAW chart it records: T near identity, made consistent with the chart.

    T maps the camera's white (R = G = B after white balance) onto the direction of the
    chart's mean neutral patch, so Eq. 1 recovers ``gains``; T is then scaled so that the
    first least-squares step of Eq. 2 (alpha with T = identity) recovers ``alpha``.
    """
    white = SRGB_TO_XYZ @ np.ones(3)
    neutral = reference.xyz[reference.neutral].mean(axis=0)
    t = np.eye(3) + rng.uniform(-0.2, 0.2, (3, 3))
    t += np.outer(neutral - t @ white, white) / (white @ white)
    unscaled = reference.xyz @ np.linalg.inv(t).T
    t *= np.sum(unscaled * unscaled) / np.sum(reference.xyz * unscaled)
    measured_xyz = reference.xyz @ np.linalg.inv(alpha * t).T
    return t, (measured_xyz @ XYZ_TO_SRGB.T) / gains


def fitted_values(fit):
    return np.concatenate([fit.gains[[0, 2]], [fit.alpha], fit.ccm_xyz.ravel()])


@pytest.fixture(scope="module")
def reference():
    return cal.load_chart_reference()


@pytest.fixture()
def chart(reference):
    return chart_camera(np.random.default_rng(1), reference)


def write_csv(path, rows, header="patch,r,g,b"):
    lines = [header] + [f"patch {i + 1}," + ",".join(repr(float(v)) for v in row)
                        for i, row in enumerate(rows)]
    path.write_text("\n".join(lines) + "\n")
    return path


# ---- the chart reference ----

def test_lab_to_xyz_matches_colour_science(reference):
    spec = json.loads((resources.files("gpu_blur") / "data" / cal.COLORCHECKER24)
                      .read_text())
    lab = np.array([p["lab"] for p in spec["patches"]])
    white = np.array(spec["lab_white_xyz"])
    expected = colour.Lab_to_XYZ(lab, colour.XYZ_to_xy(white))
    assert_close(cal.lab_to_xyz(lab, white), expected, "lab_to_xyz", "independent")


def test_colorchecker_reference_is_bradford_adapted_to_d65_with_six_neutral_patches(reference):
    assert len(reference.patch_names) == 24 and reference.patch_names[18].startswith("white")
    assert reference.neutral.tolist() == [False] * 18 + [True] * 6
    spec = json.loads((resources.files("gpu_blur") / "data" / cal.COLORCHECKER24)
                      .read_text())
    white = np.array(spec["lab_white_xyz"])
    d50 = colour.Lab_to_XYZ(np.array([p["lab"] for p in spec["patches"]]),
                            colour.XYZ_to_xy(white))
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    expected = colour.adaptation.chromatic_adaptation_VonKries(d50, white, d65,
                                                               transform="Bradford")
    assert_close(reference.xyz, expected, "chart_reference_d65", "independent")


# ---- chart fit ----

def test_chart_fit_recovers_gains_alpha_and_t_without_noise(reference, chart):
    t, raw = chart
    fit = cal.fit_chart(raw, reference)
    assert_close(fit.gains, GAINS, "chart_fit_exact")
    assert_close(fit.alpha, ALPHA, "chart_fit_exact")
    assert_close(fit.ccm_xyz, t, "chart_fit_exact")
    assert_close(fit.camera_to_linear, XYZ_TO_SRGB @ t @ SRGB_TO_XYZ, "chart_fit_exact")
    assert_close(fit.residual_xyz, np.zeros_like(raw), "chart_fit_exact")
    assert 1 < fit.condition_patches < cal.MAX_CHART_CONDITION


def test_chart_fit_with_raw_noise_stays_within_its_first_order_spread(reference, chart):
    t, raw = chart
    truth = np.concatenate([GAINS[[0, 2]], [ALPHA], t.ravel()])
    # first-order spread: Jacobian of the fitted values by central differences, times sigma
    step = 1e-6
    jacobian = np.array([
        (fitted_values(cal.fit_chart(raw + d, reference))
         - fitted_values(cal.fit_chart(raw - d, reference))) / (2 * step)
        for d in np.eye(raw.size).reshape(-1, *raw.shape) * step])
    expected_std = np.sqrt((jacobian**2).sum(axis=0)) * RAW_NOISE_STD
    rng = np.random.default_rng(7)
    draws = np.array([
        fitted_values(cal.fit_chart(raw + rng.normal(0.0, RAW_NOISE_STD, raw.shape), reference))
        for _ in range(NOISE_DRAWS)])
    z = np.abs(draws - truth) / expected_std
    assert z.max() <= NOISE_MAX_Z, z.max()
    ratio = draws.std(axis=0) / expected_std
    assert NOISE_STD_RATIO[0] <= ratio.min() and ratio.max() <= NOISE_STD_RATIO[1], ratio
    bias = np.abs(draws.mean(axis=0) - truth) / (draws.std(axis=0) / math.sqrt(NOISE_DRAWS))
    assert bias.max() <= NOISE_BIAS_Z, bias


def test_photometric_alignment_recovers_a_known_matrix(reference):
    rng = np.random.default_rng(3)
    t_p = np.eye(3) * 0.8 + rng.uniform(-0.1, 0.1, (3, 3))
    c2 = reference.xyz * rng.uniform(0.8, 1.2, reference.xyz.shape)
    assert_close(cal.fit_photometric_alignment(c2 @ t_p.T, c2), t_p, "chart_fit_exact")


# ---- degenerate input ----

def custom_reference(tmp_path, neutral):
    spec = json.loads((resources.files("gpu_blur") / "data" / cal.COLORCHECKER24)
                      .read_text())
    for p, flag in zip(spec["patches"], neutral, strict=True):
        p["neutral"] = flag
    path = tmp_path / "ref.json"
    path.write_text(json.dumps(spec))
    return cal.load_chart_reference(path)


def test_too_few_patches_are_refused_with_the_counts(tmp_path, reference, chart):
    path = write_csv(tmp_path / "short.csv", chart[1][:20])
    with pytest.raises(ValueError, match=r"short\.csv: 20 patches, too few: .* has 24"):
        cal.fit_chart(cal.read_patches(path), reference, str(path))


def test_a_chart_without_neutral_patches_is_refused(tmp_path, chart):
    with pytest.raises(ValueError, match="no patch is marked neutral"):
        cal.fit_chart(chart[1], custom_reference(tmp_path, [False] * 24))


def test_a_chart_of_only_neutral_patches_is_refused(tmp_path, chart):
    with pytest.raises(ValueError, match="all 24 patches are neutral"):
        cal.fit_chart(chart[1], custom_reference(tmp_path, [True] * 24))


@pytest.mark.parametrize("make_grey", [
    lambda raw: np.repeat(raw[:, 1:2], 3, axis=1),              # a grey image: rank 1
    lambda raw: np.column_stack([raw[:, 0], raw[:, 1], raw[:, 0] * 0.9]),  # rank 2
])
def test_rank_deficient_patch_colours_report_the_condition_number(reference, chart, make_grey):
    with pytest.raises(ValueError, match=r"rank-deficient: condition number (inf|\S+e\+\d+)"):
        cal.fit_chart(make_grey(chart[1]), reference, "grey.csv")


def test_nan_in_a_csv_names_the_file_line_and_column(tmp_path, chart):
    path = write_csv(tmp_path / "nan.csv", chart[1])
    lines = path.read_text().splitlines()
    lines[4] = "patch 4,0.1,nan,0.2"
    path.write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"nan\.csv line 5: g = 'nan' is not a finite number"):
        cal.read_patch_values(path)
    with pytest.raises(ValueError, match=r"patch 3 channel B is nan"):
        cal.fit_chart(np.where(np.arange(72).reshape(24, 3) == 8, np.nan, chart[1]))


@pytest.mark.parametrize("text, message", [
    ("red,green,blue\n0.1,0.2,0.3\n", r"line 1: the header has columns \['red', 'green', "
     r"'blue'\]; expected a header naming r, g, b \(missing r, g, b\)"),
    ("# measured 2024\nr,g,b\n0.1,0.2\n", r"line 3: 2 fields, the header has 3"),
    ("r,g,b\n0.1,0.2,bright\n", r"line 2: b = 'bright' is not a finite number"),
])
def test_wrong_csv_columns_name_the_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=r"bad\.csv " + message):
        cal.read_patch_values(path)


def test_json_entries_of_the_wrong_shape_are_named(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"rgb": [[0.1, 0.2, 0.3], [0.1, 0.2]]}))
    with pytest.raises(ValueError, match=r"bad\.json: entry 1 is \[0\.1, 0\.2\]; expected "
                       r"\[r, g, b\]"):
        cal.read_patch_values(path)


def test_response_samples_that_cover_too_little_report_the_condition_number():
    x = np.linspace(0.0, 0.4, 100)
    with pytest.raises(ValueError, match=r"cover too little of \[0, 1\].*condition number"):
        cal.fit_response(x, polynomial_crf(x, A7R3_CRF_POLYNOMIAL))
    with pytest.raises(ValueError, match="5 usable pairs"):
        cal.fit_response(np.linspace(0.1, 0.9, 5), np.linspace(0.2, 0.8, 5))


# ---- input files and images ----

def test_csv_and_json_patch_files_give_the_same_fit(tmp_path, reference, chart):
    raw = chart[1]
    csv_path = tmp_path / "raw.csv"
    rows = [f"{v[2]!r},{v[0]!r},ignored label,{v[1]!r}" for v in raw]
    csv_path.write_text("# camera RGB, black level subtracted\nB,R,patch,G\n\n"
                        + "\n".join(rows) + "\n")
    json_path = tmp_path / "raw.json"
    json_path.write_text(json.dumps({"rgb": raw.tolist()}))
    bare_path = tmp_path / "bare.json"
    bare_path.write_text(json.dumps(raw.tolist()))
    for path in (csv_path, json_path, bare_path):
        assert np.array_equal(cal.read_patches(path), raw)
    assert np.array_equal(cal.fit_chart(cal.read_patches(csv_path)).ccm_xyz,
                          cal.fit_chart(raw).ccm_xyz)


def chart_image(values, bits, patch=8, gap=3):
    """A 4 x 6 grid of flat patches on a dark surround, and boxes inside each patch."""
    scale = 2**bits - 1
    codes = np.round(values * scale).astype(np.uint16 if bits == 16 else np.uint8)
    image = np.full((4 * (patch + gap) + gap, 6 * (patch + gap) + gap, 3), 7, codes.dtype)
    boxes = []
    for i, code in enumerate(codes):
        y, x = gap + (i // 6) * (patch + gap), gap + (i % 6) * (patch + gap)
        image[y:y + patch, x:x + patch] = code
        boxes.append([x + 2, y + 2, patch - 4, patch - 4])
    return image, np.array(boxes), codes / scale


@pytest.mark.parametrize("bits, suffix", [(16, ".png"), (8, ".tif"), (16, ".tiff")])
def test_patches_sampled_from_an_image_are_the_box_means(tmp_path, chart, bits, suffix):
    raw = chart[1] / chart[1].max()
    image, boxes, expected = chart_image(raw, bits)
    path = tmp_path / f"chart{suffix}"
    assert cv2.imwrite(str(path), image[:, :, ::-1])
    boxes_csv = write_csv(tmp_path / "boxes.csv", boxes, header="patch,x,y,w,h")
    boxes_json = tmp_path / "boxes.json"
    boxes_json.write_text(json.dumps({"boxes": boxes.tolist()}))
    for box_file in (boxes_csv, boxes_json):
        assert_close(cal.read_patches(path, box_file), expected, "patch_sampling")
    fit = cal.fit_chart(cal.read_patches(path, boxes_csv))
    assert_close(fit.ccm_xyz, cal.fit_chart(expected).ccm_xyz, "patch_sampling")


def test_image_inputs_need_boxes_that_fit_inside(tmp_path, chart):
    image, boxes, _ = chart_image(chart[1] / chart[1].max(), 8)
    path = tmp_path / "chart.png"
    assert cv2.imwrite(str(path), image)
    with pytest.raises(ValueError, match=r"chart\.png is an image: give the patch boxes"):
        cal.read_patches(path)
    boxes[23, 0] = image.shape[1] - 2
    box_file = write_csv(tmp_path / "boxes.csv", boxes, header="patch,x,y,w,h")
    with pytest.raises(ValueError, match=r"box 24 \(x=67, .*does not lie inside the 69 x 47"):
        cal.read_patches(path, box_file)
    box_file.write_text("x,y,w,h\n1,2,0,3\n")
    with pytest.raises(ValueError, match=r"boxes\.csv line 2: box .* w, h >= 1"):
        cal.read_patch_boxes(box_file)


# ---- camera response ----

def bernstein_polynomial(b):
    """Power coefficients of a Bernstein polynomial, from numpy's polynomial algebra."""
    order = len(b) - 1
    x = np.polynomial.Polynomial([0.0, 1.0])
    total = sum(bk * math.comb(order, k) * x**k * (1 - x) ** (order - k)
                for k, bk in enumerate(b))
    return total.coef


def lowest_slope(coefficients, points=100_001):
    derivative = np.polynomial.polynomial.polyder(coefficients)
    return np.polynomial.polynomial.polyval(np.linspace(0.0, 1.0, points), derivative).min()


def test_response_fit_recovers_an_increasing_polynomial_exactly():
    # increasing Bernstein coefficients: a monotone order-7 curve from 0.02 to 0.98
    truth = bernstein_polynomial([0.02, 0.3, 0.5, 0.62, 0.72, 0.8, 0.9, 0.98])
    x = np.linspace(0.0, 1.0, 300)
    fit = cal.fit_response(x, polynomial_crf(x, truth))
    assert not fit.constrained and fit.left_out == 0
    assert_close(fit.coefficients, truth, "crf_fit_exact")


def test_response_fit_of_the_a7r3_curve_is_monotone_and_close_to_it():
    x = np.linspace(0.0, 1.0, 500)
    fit = cal.fit_response(x, polynomial_crf(x, A7R3_CRF_POLYNOMIAL))
    # the A7R3 polynomial dips near 0.862, so the plain fit is not monotone
    assert lowest_slope(A7R3_CRF_POLYNOMIAL) < -cal.MONOTONE_SLOPE_TOL
    assert fit.constrained and fit.left_out > 0  # clipped below 0.0011 and near 1
    assert lowest_slope(fit.coefficients) >= -cal.MONOTONE_SLOPE_TOL
    grid = np.linspace(0.0, 1.0, 100_001)
    assert_close(polynomial_crf(grid, fit.coefficients),
                 polynomial_crf(grid, A7R3_CRF_POLYNOMIAL), "crf_fit_a7r3")


def test_response_fit_of_srgb_is_monotone_within_its_toe_error():
    x = np.linspace(0.0, 1.0, 500)
    fit = cal.fit_response(x, linear_to_srgb(x))
    assert lowest_slope(fit.coefficients) >= -cal.MONOTONE_SLOPE_TOL
    grid = np.linspace(0.0, 1.0, 100_001)
    assert_close(polynomial_crf(grid, fit.coefficients), np.clip(linear_to_srgb(grid), 0, 1),
                 "crf_fit_srgb")


@pytest.mark.parametrize("coefficients", [A7R3_CRF_POLYNOMIAL, "srgb-fit"])
def test_inverse_table_inverts_the_response(coefficients):
    if isinstance(coefficients, str):
        x = np.linspace(0.0, 1.0, 500)
        coefficients = cal.fit_response(x, linear_to_srgb(x)).coefficients
    else:
        x = np.linspace(0.0, 1.0, 500)
        coefficients = cal.fit_response(x, polynomial_crf(x, coefficients)).coefficients
    table = cal.response_inverse_table(coefficients)
    assert np.all(np.diff(table) >= 0) and table[0] >= 0 and table[-1] <= 1
    low, high = polynomial_crf(np.array([0.0, 1.0]), coefficients)
    nodes = np.linspace(0.0, 1.0, table.size)
    inside = (nodes > low) & (nodes < high)
    assert_close(polynomial_crf(table[inside], coefficients), nodes[inside], "crf_inverse_nodes")
    # between nodes the curve is monotone, so it lands within one node step
    rendered = np.linspace(low, high, 20_001)
    back = polynomial_crf(cal.inverse_response(rendered, table), coefficients)
    assert np.abs(back - rendered).max() <= 1.0 / (table.size - 1)


def test_a_camera_the_loader_refuses_leaves_the_old_file_and_no_temporary_file(tmp_path):
    path = tmp_path / "cam.toml"
    path.write_text("old\n")
    bad = {"color": {"ccm_xyz": [[0.0, 0.0, 0.0]] * 3}, "white_balance": {"red": 2.0, "blue": 1.5}}
    with pytest.raises(ValueError, match=str(path)) as e:
        cal.write_camera_file(path, bad)
    assert ".part" not in str(e.value)  # the error names the file asked for
    assert path.read_text() == "old\n" and sorted(tmp_path.iterdir()) == [path]


# ---- the command ----

def test_cli_writes_a_camera_file_that_scenes_and_synthesize_use(tmp_path, capsys, chart):
    t, raw = chart
    patches = write_csv(tmp_path / "raw.csv", raw)
    out = tmp_path / "my_cam.toml"
    assert main(["calibrate", "--chart", str(patches), "--output", str(out)]) == 0
    printed = capsys.readouterr().out
    for text in ("white balance gains (Eq. 1): R 2.100000", "brightness alpha (Eq. 2): 1.6",
                 "colour correction T", "chart residual", "condition numbers: patches",
                 "wrote", 'name = "my_cam.toml"'):
        assert text in printed
    camera = get_camera("my_cam.toml", base_dir=tmp_path)
    assert camera.name == "my_cam"
    assert_close(camera.camera_to_linear, camera_to_linear_matrix(ccm=t), "chart_fit_exact")
    assert camera.white_balance.red_range == (pytest.approx(2.1),) * 2
    # a scene in that folder names it; WB and colour cancel with noise off
    scene = scene_from_dict({"camera": {"name": "my_cam.toml"}, "noise": {"model": "none"},
                             "isp": {"round_trip": "always"}, "blur": {"mode": "none"},
                             "saturation": {"mode": "off"}, "output": {"bits": 0}},
                            path=tmp_path / "scene.toml")
    flat = np.broadcast_to(np.array([0.2, 0.45, 0.7]), (8, 10, 3))
    result = gpu_blur.synthesize({"blurred": flat}, scene, overrides={"pattern": "GRBG"})
    assert_close(result.blurred, flat.astype(np.float32), "pipeline_wb_color_cancel")
    assert result.params["red_gain"] == pytest.approx(2.1)
    # and with noise on, from a scene file
    (tmp_path / "noisy.toml").write_text('[camera]\nname = "my_cam.toml"\n[blur]\nsteps = 2\n')
    photo = np.random.default_rng(0).integers(0, 256, (16, 20, 3), dtype=np.uint8)
    noisy = gpu_blur.synthesize([photo], tmp_path / "noisy.toml", backend="numpy")
    assert noisy.blurred.shape == (16, 20, 3) and noisy.params["blue_gain"] == pytest.approx(1.7)
    # an existing file is kept unless --overwrite
    assert main(["calibrate", "--chart", str(patches), "--output", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["calibrate", "--chart", str(patches), "--output", str(out), "--overwrite",
                 "--name", "bench-cam", "--shot-noise-k", "2e-4", "--read-noise-std",
                 "1e-3"]) == 0
    camera = load_camera(out)
    assert (camera.name, camera.shot_noise_k, camera.read_noise_std) == ("bench-cam", 2e-4, 1e-3)


def test_cli_fits_response_and_alignment_into_the_camera_file(tmp_path, capsys, reference,
                                                            chart):
    t, raw = chart
    other_t, other_raw = chart_camera(np.random.default_rng(2), reference, alpha=1.2)
    linear = np.linspace(0.0, 1.0, 75).reshape(25, 3)
    out = tmp_path / "cam.json"
    args = ["calibrate", "--chart", str(write_csv(tmp_path / "raw.csv", raw)),
            "--output", str(out), "--align-to", str(write_csv(tmp_path / "c1.csv", other_raw)),
            "--crf-linear", str(write_csv(tmp_path / "lin.csv", linear)),
            "--crf-rendered", str(write_csv(tmp_path / "jpg.csv", linear_to_srgb(linear)))]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "photometric alignment T_p" in printed and "response (Eq. 6, order 7)" in printed
    spec = json.loads(out.read_text())
    # both cameras see the chart exactly, so T_p maps one's corrected colours onto the
    # other's: the brightness ratio of the two photos
    t_p = np.array(spec["calibration"]["alignment"])
    assert_close(t_p, np.eye(3) * ALPHA / 1.2, "chart_fit_exact")
    assert_close(np.array(spec["color"]["ccm_xyz"]), t_p @ t, "chart_fit_exact")
    coefficients, table = cal.read_response(out)
    assert np.array_equal(coefficients,
                          cal.fit_response(linear, linear_to_srgb(linear)).coefficients)
    assert table.size == cal.INVERSE_TABLE_NODES and load_camera(out).name == "cam"
    assert np.array_equal(load_camera(out).response, coefficients)
    assert 'add [output] crf = "camera" to re-tone with its fitted response' in printed
    # the loop: generate a set with the fitted response, as gpu-blur compare would score it
    photo = np.random.default_rng(3).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "p.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    scene_file = tmp_path / "scene.toml"
    scene_file.write_text('[camera]\nname = "cam.json"\n[blur]\nsteps = 3\n'
                          '[output]\ncrf = "camera"\n')
    assert main(["generate", "--input", str(tmp_path / "photos"), "--output",
                 str(tmp_path / "set"), "--scene", str(scene_file), "--quiet"]) == 0
    (line,) = [json.loads(x) for x in (tmp_path / "set" / "manifest.jsonl").read_text()
               .splitlines()]
    assert "retone" in line["stages"] and line["status"] == "ok"

    def codes(name):
        return cv2.cvtColor(cv2.imread(str(tmp_path / "set" / line[name])), cv2.COLOR_BGR2RGB)

    toned = polynomial_crf(srgb_to_linear(photo / 255.0), coefficients)
    assert np.array_equal(codes("sharp"), np.floor(toned * 255 + 0.5).astype(np.uint8))
    blurred = gpu_blur.synthesize([photo], scene_file, seed=0, sample_index=line["index"])
    assert np.array_equal(codes("blurred"), np.rint(blurred.blurred * 255).astype(np.uint8))


def test_cli_errors_name_the_file_and_exit_2(tmp_path, capsys, chart):
    patches = write_csv(tmp_path / "raw.csv", chart[1][:10])
    assert main(["calibrate", "--chart", str(patches), "--output",
                 str(tmp_path / "c.toml")]) == 2
    assert "raw.csv: 10 patches, too few" in capsys.readouterr().err
    assert not (tmp_path / "c.toml").exists()
    assert main(["calibrate", "--chart", str(write_csv(tmp_path / "ok.csv", chart[1])),
                 "--output", str(tmp_path / "c.yaml")]) == 2
    assert "must end in .toml or .json" in capsys.readouterr().err
    assert list(tmp_path.glob(".*part*")) == []


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_cli_names_beyond_ascii_load_back_and_non_utf8_ones_are_refused(tmp_path, capsys, chart,
                                                                        suffix):
    # an emoji is beyond U+FFFF: JSON-style escapes write it as a surrogate pair TOML refuses
    patches = write_csv(tmp_path / "raw.csv", chart[1])
    out = tmp_path / f"cam{suffix}"
    name = 'cam 😀 "é" \\ \x7f'
    assert main(["calibrate", "--chart", str(patches), "--output", str(out),
                 "--name", name]) == 0
    assert load_camera(out).name == name
    # bytes that are not UTF-8 reach Python as lone surrogates, which no file can hold
    capsys.readouterr()
    assert main(["calibrate", "--chart", str(patches), "--output", str(out), "--overwrite",
                 "--name", "cam \udcff"]) == 2
    assert f"{out}: name = 'cam \\udcff' is invalid; expected text" in capsys.readouterr().err
    assert load_camera(out).name == name and list(tmp_path.glob(".*part*")) == []
