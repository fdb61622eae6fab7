import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import correlate

import gpu_blur
from gpu_blur.constants import A7R3_CRF_POLYNOMIAL, SRGB_TO_XYZ, XYZ_TO_SRGB, rsblur_data
from gpu_blur.planning import plan
from gpu_blur.scene import scene_from_dict, toml_loads
from gpu_blur.testing import assert_close

SCENES = Path(gpu_blur.__file__).parent / "data" / "scenes"


def scene_with(base: str | None = None, **sections):
    data = toml_loads((SCENES / base).read_text()) if base else {}
    for section, values in sections.items():
        data.setdefault(section, {}).update(values)
    return scene_from_dict(data)


# ---- a literal transcription of RSBLUR_PIPELINE.md Sec. 3 (PyTorch chain), noise off ----

def eotf(x):
    a = np.abs(x)
    return np.sign(x) * np.where(a < 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)


def oetf(x):
    a = np.abs(x)
    return np.sign(x) * np.where(a < 0.0031308, 12.92 * a, 1.055 * a ** (1 / 2.4) - 0.055)


def malvar_filters():
    """The four 5 x 5 filters built from the note's words (Sec. 5.6), all / 8."""
    g = np.zeros((5, 5))
    g[2, 2] = 4
    g[2, 1] = g[2, 3] = g[1, 2] = g[3, 2] = 2
    g[2, 0] = g[2, 4] = g[0, 2] = g[4, 2] = -1
    row = np.zeros((5, 5))
    row[2, 2] = 5
    row[2, 1] = row[2, 3] = 4
    row[2, 0] = row[2, 4] = -1
    row[1, 1] = row[1, 3] = row[3, 1] = row[3, 3] = -1
    row[0, 2] = row[4, 2] = 0.5
    diag = np.zeros((5, 5))
    diag[2, 2] = 6
    diag[1, 1] = diag[1, 3] = diag[3, 1] = diag[3, 3] = 2
    diag[2, 0] = diag[2, 4] = diag[0, 2] = diag[4, 2] = -1.5
    return g / 8, row / 8, row.T / 8, diag / 8


def pytorch_chain(blurred, mask, sharp, alpha, pattern, red, blue):
    h, w, _ = blurred.shape
    b_lin = np.clip(eotf(blurred) + alpha * mask, 0, 1)
    b_sat = b_lin.copy()
    m_lin2xyz_row = SRGB_TO_XYZ.T  # stored transposed: xyz_row = lin_row @ M
    xyz2cam = np.array(rsblur_data()["a7r3"]["xyz_to_camera"])
    xyz = b_lin.reshape(-1, 3) @ m_lin2xyz_row
    cam = np.einsum("ij,nj->ni", xyz2cam, xyz).reshape(h, w, 3)  # apply_cmatrix
    letters = {"R": 0, "G": 1, "B": 2}
    packed = np.stack([cam[p // 2::2, p % 2::2, letters[pattern[p]]] for p in range(4)], -1)
    gains = np.array([{"R": red, "G": 1.0, "B": blue}[c] for c in pattern])
    packed = packed * (1 / gains)  # inverse WB
    packed = packed * gains  # WB (noise off in between)
    raw = np.zeros((h, w))
    for p in range(4):  # pixel_shuffle
        raw[p // 2::2, p % 2::2] = packed[..., p]
    site = np.empty((h, w), dtype="<U1")
    for p in range(4):
        site[p // 2::2, p % 2::2] = pattern[p]
    r_rows = np.any(site == "R", axis=1)[:, None] & np.ones((1, w), bool)
    b_rows = np.any(site == "B", axis=1)[:, None] & np.ones((1, w), bool)
    g_k, row_k, col_k, diag_k = malvar_filters()
    conv = {k: correlate(raw, f, mode="constant") for k, f in
            (("g", g_k), ("row", row_k), ("col", col_k), ("diag", diag_k))}
    rgb = np.zeros((h, w, 3))
    rgb[..., 1] = np.where(site == "G", raw, conv["g"])
    rgb[..., 0] = np.select([site == "R", (site == "G") & r_rows, (site == "G") & b_rows,
                             site == "B"], [raw, conv["row"], conv["col"], conv["diag"]])
    rgb[..., 2] = np.select([site == "B", (site == "G") & b_rows, (site == "G") & r_rows,
                             site == "R"], [raw, conv["row"], conv["col"], conv["diag"]])
    cam2xyz = np.linalg.inv(xyz2cam)
    xyz = np.einsum("ij,nj->ni", cam2xyz, rgb.reshape(-1, 3))
    lin = (xyz @ XYZ_TO_SRGB.T).reshape(h, w, 3)
    out = np.clip(oetf(lin), 0, 1)
    out = np.where(b_sat >= 1.0, b_sat, out)
    poly = np.polynomial.polynomial.polyval
    out = np.clip(poly(eotf(out), A7R3_CRF_POLYNOMIAL), 0, 1)
    gt = np.clip(poly(eotf(sharp), A7R3_CRF_POLYNOMIAL), 0, 1)
    return out[4:-4, 4:-4], gt[4:-4, 4:-4]


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_realblur_j_scene_reproduces_the_authors_pytorch_chain(coffee_rgb, pattern):
    blurred = coffee_rgb[100:164, 300:396]
    sharp = coffee_rgb[101:165, 301:397]
    mask = np.round(np.random.default_rng(5).uniform(0, 1, blurred.shape) ** 4 * 255) / 255
    scene = scene_with("realblur_j.toml", noise={"model": "none"}, isp={"round_trip": "always"})
    fixed = {"alpha": 1.3, "pattern": pattern, "red_gain": 2.1, "blue_gain": 1.7}
    result = gpu_blur.synthesize({"blurred": blurred, "mask": mask, "sharp": sharp}, scene,
                                 overrides=fixed)
    expected, expected_gt = pytorch_chain(blurred, mask, sharp, 1.3, pattern, 2.1, 1.7)
    assert result.blurred.shape == expected.shape == (56, 88, 3)
    assert np.any(expected == 1.0)  # the saturated restore is exercised
    # the result is float32: compare within float32 rounding of values in [0, 1]
    assert_close(result.blurred, expected.astype(np.float32), "pipeline_realblur_j",
                 "independent")
    assert_close(result.sharp, expected_gt.astype(np.float32), "pipeline_realblur_j",
                 "independent")


@pytest.mark.parametrize("camera", ["a7r3", "rsblur-0003", "srgb"])
@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_white_balance_and_colour_steps_cancel_with_noise_off(camera, pattern):
    colour = np.array([0.2, 0.45, 0.7])
    flat = np.broadcast_to(colour, (12, 16, 3))
    scene = scene_with(noise={"model": "none"}, isp={"round_trip": "always"},
                       blur={"mode": "none"}, camera={"name": camera},
                       output={"bits": 0}, saturation={"mode": "off"})
    result = gpu_blur.synthesize({"blurred": flat}, scene, overrides={"pattern": pattern})
    assert result.plan.raw_round_trip
    assert_close(result.blurred, np.broadcast_to(colour, flat.shape).astype(np.float32),
                 "pipeline_wb_color_cancel")


def test_same_seed_and_sample_give_identical_output_and_another_sample_differs(coffee_rgb):
    photo = coffee_rgb[:96, :128]
    scene = scene_with(blur={"steps": 5})
    a = gpu_blur.synthesize([photo], scene, seed=7, sample_index=3)
    b = gpu_blur.synthesize([photo], scene, seed=7, sample_index=3)
    c = gpu_blur.synthesize([photo], scene, seed=7, sample_index=4)
    d = gpu_blur.synthesize([photo], scene, seed=8, sample_index=3)
    assert np.array_equal(a.blurred, b.blurred) and a.params.keys() == b.params.keys()
    assert all(np.array_equal(a.params[k], b.params[k]) for k in a.params)
    assert not np.array_equal(a.blurred, c.blurred)
    assert not np.array_equal(a.blurred, d.blurred)
    assert a.params["red_gain"] != c.params["red_gain"]


def test_every_drawn_value_is_reported_and_can_be_fixed(coffee_rgb):
    photo = coffee_rgb[:64, :64]
    scene = scene_with(blur={"steps": 3}, saturation={"mode": "on"})
    drawn = gpu_blur.synthesize([photo], scene, seed=1)
    assert {"alpha", "pattern", "red_gain", "blue_gain", "shot_noise_k", "read_noise_std",
            "extent_px", "homographies"} <= set(drawn.params)
    a7r3 = rsblur_data()["a7r3"]
    assert 0.25 <= drawn.params["alpha"] <= 1.75
    assert 1.9 <= drawn.params["red_gain"] <= 2.4 and 1.5 <= drawn.params["blue_gain"] <= 1.9
    assert 0.5 <= drawn.params["shot_noise_k"] / a7r3["shot_noise_k"] <= 1.5
    assert 0.5 <= drawn.params["read_noise_std"] / a7r3["read_noise_std"] <= 1.5
    fixed = gpu_blur.synthesize([photo], scene, seed=1, overrides={"red_gain": 2.0})
    assert fixed.params["red_gain"] == 2.0
    # fixing one value shifts no other draw
    assert all(np.array_equal(fixed.params[k], drawn.params[k]) for k in drawn.params
               if k != "red_gain")


def test_overrides_that_are_unknown_or_unused_are_refused(coffee_rgb):
    photo = coffee_rgb[:32, :32]
    with pytest.raises(ValueError, match="unknown override 'gamma'"):
        gpu_blur.synthesize([photo], scene_with(blur={"steps": 2}), overrides={"gamma": 1})
    with pytest.raises(ValueError, match="'shot_noise_k' is not used"):
        gpu_blur.synthesize([photo], scene_with(noise={"model": "none"}, blur={"steps": 2}),
                            overrides={"shot_noise_k": 1e-4})


def test_params_of_skipped_stages_are_neither_drawn_nor_reported(coffee_rgb):
    scene = scene_with("minimal.toml", blur={"steps": 3})
    result = gpu_blur.synthesize([coffee_rgb[:32, :32]], scene)
    assert set(result.params) == {"extent_px", "homographies"}
    assert not result.plan.raw_round_trip


def test_auto_saturation_is_skipped_when_no_pixel_reaches_the_clip_level():
    dim = np.full((16, 16, 3), 0.5)
    result = gpu_blur.synthesize([dim], scene_with(blur={"steps": 2}))
    assert not result.plan.kept("saturate") and "alpha" not in result.params
    bright = dim.copy()
    bright[3, 4, 1] = 1.0
    result = gpu_blur.synthesize([bright], scene_with(blur={"steps": 2}))
    assert result.plan.kept("saturate") and "alpha" in result.params


def test_the_sample_plan_is_built_once_and_a_skipped_saturation_takes_no_alpha(monkeypatch):
    from gpu_blur.synthesis import draws

    calls = []
    monkeypatch.setattr(draws, "plan", lambda *a, **k: calls.append(k) or plan(*a, **k))
    dim = np.full((16, 16, 3), 0.5)
    result = gpu_blur.synthesize([dim], scene_with(blur={"steps": 2}),
                                 overrides={"alpha": 1.0})
    assert calls == [{"saturated": False, "size": (16, 16), "interpolation_factors": None}]
    assert not result.plan.kept("saturate") and "alpha" not in result.params


def test_saturated_channels_are_exactly_one_after_noise():
    image = np.full((16, 16, 3), 0.3)
    mask = np.zeros_like(image)
    mask[4:8, 4:8, 0] = 1.0  # red saturates there, with alpha >= 0.25 and B_lin > 0.07
    scene = scene_with(blur={"mode": "none"}, saturation={"mode": "on"}, output={"bits": 0})
    result = gpu_blur.synthesize({"blurred": image, "mask": mask}, scene, seed=2)
    assert np.all(result.blurred[4:8, 4:8, 0] == 1.0)
    assert np.all(result.blurred[..., 1:] < 1.0)


def test_averaging_uses_the_middle_frame_as_sharp_and_counts_saturation_per_channel():
    frames = [np.full((8, 8, 3), v) for v in (0.1, 0.2, 0.3)]
    frames[0][..., 2] = 1.0
    scene = scene_with("minimal.toml", blur={"mode": "average", "frames": 3},
                       output={"bits": 0, "crf": "srgb"})
    result = gpu_blur.synthesize(frames, scene)
    assert np.array_equal(result.sharp, frames[1].astype(np.float32))
    assert np.allclose(result.mask[..., 2], 1 / 3) and np.all(result.mask[..., :2] == 0)


def test_a_sample_with_another_frame_count_than_blur_frames_is_refused():
    frames = [np.full((8, 8, 3), 0.5)] * 4
    scene = scene_with("minimal.toml", blur={"mode": "average", "frames": 3})
    with pytest.raises(ValueError, match=r"blur.frames = 3 \(the scene\) but this sample has "
                       r"4 frames: pass 3, or set blur.frames = 4"):
        gpu_blur.synthesize(frames, scene)
    with pytest.raises(ValueError, match="but this sample has 4 frames"):
        gpu_blur.Synthesizer(scene)(np.stack(frames)[None])


def test_odd_sizes_lose_the_last_row_and_column_only_with_a_raw_round_trip():
    photo = np.full((7, 9, 3), 0.4)
    raw = gpu_blur.synthesize([photo], scene_with(blur={"steps": 2}))
    assert raw.blurred.shape == raw.sharp.shape == (6, 8, 3)
    plain = gpu_blur.synthesize([photo], scene_with("minimal.toml", blur={"steps": 2}))
    assert plain.blurred.shape == (7, 9, 3)


def test_quantized_output_lies_on_the_8_bit_grid(coffee_rgb):
    result = gpu_blur.synthesize([coffee_rgb[:32, :32]], scene_with(blur={"steps": 2}))
    codes = result.blurred.astype(np.float64) * 255
    assert np.allclose(codes, np.round(codes), atol=1e-4)


def test_kernel_mode_reads_a_kernel_file_relative_to_the_scene(tmp_path, coffee_rgb):
    kernel = np.zeros((5, 5))
    kernel[2, :] = 1
    np.save(tmp_path / "k.npy", kernel)
    (tmp_path / "scene.toml").write_text('[blur]\nmode = "kernel"\nkernel = "k.npy"\n'
                                         '[noise]\nmodel = "none"\n[saturation]\nmode = "off"\n')
    result = gpu_blur.synthesize([coffee_rgb[:32, :32]], tmp_path / "scene.toml")
    assert "kernel" in result.params and result.params["kernel"].shape == (5, 5)
    assert result.blurred.shape == (32, 32, 3)


def test_synthesis_result_is_float32_in_unit_range(coffee_rgb):
    result = gpu_blur.synthesize([coffee_rgb[:48, :48]], scene_with(blur={"steps": 3}), seed=3)
    for image in (result.blurred, result.sharp, result.mask):
        assert image.dtype == np.float32 and image.min() >= 0 and image.max() <= 1
    assert dataclasses.is_dataclass(result)


def test_gaussian_noise_model_adds_srgb_noise_of_the_drawn_std():
    flat = np.full((128, 128, 3), 0.5)
    scene = scene_with(blur={"mode": "none"}, noise={"model": "gaussian"}, output={"bits": 0})
    result = gpu_blur.synthesize({"blurred": flat}, scene, seed=4)
    assert not result.plan.raw_round_trip
    std = result.params["gaussian_std"]
    assert 0.5 * 0.011211179037436594 <= std <= 1.5 * 0.011211179037436594
    residual = result.blurred.astype(np.float64) - 0.5
    n = residual.size  # the sample std's standard error is std / sqrt(2 n); allow 5 of them
    assert abs(residual.std() - std) <= 5 * std / np.sqrt(2 * n)
    assert abs(residual.mean()) <= 5 * std / np.sqrt(n)


def test_crop_applies_to_output_sharp_and_mask_alike(coffee_rgb):
    scene = scene_with(blur={"steps": 3}, output={"crop": 4})
    result = gpu_blur.synthesize([coffee_rgb[:40, :48]], scene)
    assert result.blurred.shape == result.sharp.shape == result.mask.shape == (32, 40, 3)


@pytest.mark.parametrize("retone", [False, True])
def test_8_bit_frames_give_the_sharp_reference_of_their_float_values(retone, coffee_rgb):
    # 8-bit in and out without re-toning takes the sharp frame's codes directly; it must be
    # the quantized float path's result bit for bit (and the re-toned path still runs)
    codes = np.round(coffee_rgb[:64, :96] * 255).astype(np.uint8)
    frames = [np.roll(codes, i, axis=1) for i in range(3)]
    output = {"bits": 8, "crf": "a7r3" if retone else "none"}
    scene = scene_from_dict({"blur": {"mode": "average", "frames": 3}, "output": output})
    from_codes = gpu_blur.synthesize(frames, scene, seed=3)
    from_floats = gpu_blur.synthesize([f / 255.0 for f in frames], scene, seed=3)
    assert from_codes.plan.kept("retone") == retone
    assert from_codes.sharp.dtype == np.float32
    assert np.array_equal(from_codes.sharp, from_floats.sharp)
    assert np.array_equal(from_codes.blurred, from_floats.blurred)


@pytest.mark.parametrize("crf", ["a7r3", "a7r3-lut", "srgb", "none"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("bits", [0, 8, 16])
def test_sharp_reference_from_codes_is_the_curve_of_every_pixel_bitwise(crf, dtype, bits):
    """render_sharp evaluates the curve once per code and gathers: the same values."""
    from gpu_blur.cameras import scene_camera
    from gpu_blur.image_arrays import unit_values
    from gpu_blur.reference.output import quantize
    from gpu_blur.synthesis.host import _render_values, render_sharp

    scene = scene_from_dict({"output": {"crf": crf, "bits": bits}})
    top = np.iinfo(dtype).max
    codes = np.random.default_rng(5).integers(0, top + 1, (24, 32, 3), dtype=dtype)
    codes[0, :2] = ((0,), (top,))  # both ends of the table
    p, camera = plan(scene), scene_camera(scene)
    got = render_sharp(p, camera, codes)
    expected = _render_values(p, camera, unit_values(codes))
    expected = (quantize(expected, bits) if bits else expected).astype(np.float32)
    assert got.dtype == np.float32 and got.shape == codes.shape
    assert np.array_equal(got, expected)
    if crf == "srgb" and bits == 8 and dtype is np.uint8:  # 8-bit sRGB in and out: c / 255
        assert np.array_equal(got, codes.astype(np.float32) / np.float32(255))


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_integer_codes_in_chunks_equal_the_rounding_formula_on_every_value(bits, dtype):
    from gpu_blur.reference import output

    rng = np.random.default_rng(bits)
    top = 2**bits - 1
    edges = np.array([-1.0, -0.0, 0.0, 1.0, 1.5, 0.5 / top, 1.5 / top, (top - 0.5) / top])
    halves = (np.arange(top) + 0.5) / top  # every rounding boundary between two codes
    values = np.concatenate([edges, halves, np.nextafter(halves, 2), np.nextafter(halves, -1),
                             rng.uniform(-0.1, 1.1, 3 * output.CODE_CHUNK + 17)])
    image = values.astype(dtype)
    want = np.floor(np.clip(image.astype(np.float64), 0, 1) * top + 0.5).astype(
        np.uint8 if bits == 8 else np.uint16)
    assert np.array_equal(output.to_integers(image, bits), want)
    rows = image.size // 3
    assert np.array_equal(output.to_integers(image[:3 * rows].reshape(rows, 3), bits),
                          want[:3 * rows].reshape(rows, 3))  # the shape is kept
    assert np.array_equal(output.to_integers(image[::3], bits), want[::3])  # a strided view
