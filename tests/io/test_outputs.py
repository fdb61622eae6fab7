"""Outputs beyond the pair: the JPEG stage, the saturation mask and the RAW mosaic (issue 16)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import tifffile
from conftest import BACKEND_SPECS

import gpu_blur
from gpu_blur.cameras import scene_camera
from gpu_blur.cli import main
from gpu_blur.outputs import RAW_BLACK_LEVEL, RAW_WHITE_LEVEL, jpeg_round_trip, raw_codes
from gpu_blur.params import DRAW_INDEX, draw_params
from gpu_blur.planning import StageName, plan
from gpu_blur.reference import rng
from gpu_blur.reference.bayer import BayerPattern
from gpu_blur.reference.output import to_integers
from gpu_blur.scene import SceneError, scene_from_dict
from gpu_blur.scheduler import _passes
from gpu_blur.tiling import Region

PHOTOS = np.random.default_rng(5).integers(0, 256, (2, 30, 44, 3), dtype=np.uint8)
#: one float32 run per backend family (numpy, each OpenCL device, each Warp device)
FLOAT32_SPECS = [s for s in BACKEND_SPECS if s == "numpy" or s.endswith("/float32")]


def _scene(**output):
    return scene_from_dict({"blur": {"mode": "kernel", "kernel_size": [3, 5]},
                            "output": output})


# -- JPEG ------------------------------------------------------------------------------------------

def test_jpeg_quality_comes_from_its_own_slot_and_moves_no_other_draw():
    plain, jpeg = _scene(), _scene(jpeg_quality=[20, 95])
    camera = scene_camera(plain)
    for index in range(40):
        kwargs = {"seed": 11, "sample_index": index, "image_shape": (30, 44)}
        before = draw_params(plain, plan(plain, saturated=True), camera, **kwargs)
        after = draw_params(jpeg, plan(jpeg, saturated=True), camera, **kwargs)
        quality = after.pop("jpeg_quality")
        assert json.dumps({k: np.asarray(v).tolist() for k, v in before.items()}) == \
            json.dumps({k: np.asarray(v).tolist() for k, v in after.items()})
        u = rng.image_uniforms(11, index, rng.Stream.PARAMS, len(DRAW_INDEX))
        assert quality == 20 + int(u[DRAW_INDEX["jpeg_quality"]] * 76)
        assert 20 <= quality <= 95


def test_jpeg_stage_is_the_round_trip_of_the_quantized_output_and_reproducible():
    synth = gpu_blur.Synthesizer(_scene(jpeg_quality=[30, 60], crop=3), seed=4)
    out = synth(PHOTOS)
    plain = gpu_blur.Synthesizer(_scene(crop=3), seed=4)(PHOTOS)
    np.testing.assert_array_equal(out.sharp, plain.sharp)  # the target is left as it is
    for b in range(len(PHOTOS)):
        quality = out.params[b]["jpeg_quality"]
        assert 30 <= quality <= 60
        np.testing.assert_array_equal(out.blurred[b],
                                      jpeg_round_trip(plain.blurred[b], quality))
        assert not np.array_equal(out.blurred[b], plain.blurred[b])
    again = gpu_blur.Synthesizer(_scene(jpeg_quality=[30, 60], crop=3), seed=4)(PHOTOS)
    np.testing.assert_array_equal(again.blurred, out.blurred)
    one = synth.sample([PHOTOS[1]], 1)  # synthesize's path: the same stage
    np.testing.assert_array_equal(one.blurred, out.blurred[1])


@pytest.mark.parametrize("backend", ["numpy", "warp:cpu", "opencl"])
def test_jpeg_stage_acts_on_channels_last_images_whatever_layout_the_batch_comes_in(backend):
    import torch

    scene = _scene(jpeg_quality=[30, 60], crop=3)
    last = gpu_blur.Synthesizer(scene, backend=backend, seed=4)(PHOTOS)
    first = gpu_blur.Synthesizer(scene, backend=backend, seed=4, channels_first=True)(
        torch.from_numpy(np.ascontiguousarray(PHOTOS.transpose(0, 3, 1, 2))))
    assert isinstance(first.blurred, torch.Tensor) and first.blurred.shape[1] == 3
    np.testing.assert_array_equal(first.blurred.numpy().transpose(0, 2, 3, 1), last.blurred)


def test_jpeg_round_trip_is_opencv_4_2_0_at_the_quality():
    codes = PHOTOS[0]
    ok, data = cv2.imencode(".jpg", codes[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 40,
                                                         cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                                         cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420])
    expected = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)[:, :, ::-1]
    got = jpeg_round_trip(codes / 255.0, 40)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(np.rint(got * 255).astype(np.uint8), expected)


@pytest.mark.parametrize("spec", [s for s in FLOAT32_SPECS if s != "numpy"])
def test_jpeg_output_is_equal_on_numpy_and_a_kernel_backend(spec):
    # sRGB in, sRGB out, nothing random before the JPEG: every backend gives the input codes,
    # so any difference would be the JPEG stage's
    scene = scene_from_dict({"blur": {"mode": "none"}, "noise": {"model": "none"},
                             "saturation": {"mode": "off"},
                             "output": {"jpeg_quality": [50, 90]}})
    outs = [gpu_blur.Synthesizer(scene, backend=name, seed=2)(PHOTOS)
            for name in ("numpy", spec.split("/")[0])]
    np.testing.assert_array_equal(outs[0].blurred, outs[1].blurred)
    assert [p["jpeg_quality"] for p in outs[0].params] == \
        [p["jpeg_quality"] for p in outs[1].params]
    assert not np.array_equal(outs[0].blurred, PHOTOS / np.float32(255))


@pytest.mark.parametrize("output, message", [
    ({"jpeg_quality": [0, 90]}, "output.jpeg_quality = [0, 90] is invalid; allowed: [low, high], "
                                "each int >= 1"),
    ({"jpeg_quality": [50, 101]}, "each int <= 100"),
    ({"jpeg_quality": [90, 80]}, "output.jpeg_quality = [90, 80] is invalid; allowed: low <= "
                                 "high"),
    ({"jpeg_quality": [50.5, 90]}, "each int >= 1"),
    ({"jpeg_quality": 90}, "allowed: a [low, high] pair of int"),
    ({"jpeg_quality": [70, 90], "bits": 16}, "output.jpeg_quality = [70, 90] needs "
                                             "output.bits = 8 (it is 16)"),
    ({"jpeg_quality": [70, 90], "bits": 0}, "set output.bits = 8, or leave "
                                            "output.jpeg_quality out"),
])
def test_bad_jpeg_quality_is_refused_naming_the_file_and_key(output, message):
    with pytest.raises(SceneError) as e:
        scene_from_dict({"output": output}, "my.toml")
    assert str(e.value).startswith("my.toml: output.jpeg_quality = ")
    assert message in str(e.value)


def test_jpeg_quality_override_is_held_to_its_range():
    with pytest.raises(ValueError, match=r"overrides\['jpeg_quality'\] = 0 is invalid; "
                                         r"allowed: int >= 1"):
        gpu_blur.Synthesizer(_scene(jpeg_quality=[70, 90]), overrides={"jpeg_quality": 0})
    fixed = gpu_blur.Synthesizer(_scene(jpeg_quality=[70, 90]), overrides={"jpeg_quality": 5})
    assert [p["jpeg_quality"] for p in fixed(PHOTOS).params] == [5, 5]


def test_jpeg_stage_reaches_device_batches():
    wp = pytest.importorskip("warp")  # a test dependency: there whenever the suite runs
    scene = _scene(jpeg_quality=[30, 60])
    on_device = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=4)(
        wp.array(PHOTOS, dtype=wp.uint8, device="cpu"))
    assert isinstance(on_device.blurred, wp.array)
    host = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=4)(PHOTOS)
    np.testing.assert_array_equal(on_device.blurred.numpy(), host.blurred)


def test_on_device_results_refuse_the_host_jpeg_stage():
    with pytest.raises(ValueError, match=r"no output.jpeg_quality \(a host stage\)"):
        gpu_blur.synthesize([PHOTOS[0]], _scene(jpeg_quality=[70, 90]), backend="warp:cpu",
                            on_device=True)


def test_plan_lists_the_jpeg_stage_kept_or_skipped_with_why():
    stage = plan(_scene(jpeg_quality=[70, 90]))[StageName.JPEG]
    assert stage.kept and stage.pass_ == "host" and "[70, 90]" in stage.reason
    assert "4:2:0" in stage.reason
    skipped = plan(_scene())[StageName.JPEG]
    assert not skipped.kept and skipped.reason == "output.jpeg_quality not set"
    assert "skip jpeg" in str(plan(_scene()))


# -- RAW and mask from the API -------------------------------------------------------------------

@pytest.mark.parametrize("spec", FLOAT32_SPECS)
def test_with_raw_returns_the_to_raw_pass_output_with_its_metadata(spec):
    name = spec.split("/")[0]
    scene = _scene(crop=3)
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=6, with_raw=True)
    out = synth(PHOTOS, first_index=10)
    assert out.raw.shape == (2, 24, 38) and out.raw.dtype == np.float32
    for b in range(2):
        params, sample_plan = out.params[b], out.plans[b]
        _, _, image, _, _ = _passes(synth.runner, sample_plan, params, synth.camera,
                                    [PHOTOS[b]], None, Region.whole(30, 44),
                                    Region.whole(30, 44), 6, 10 + b)
        held = gpu_blur.backends.to_host(image, np.float32)[3:-3, 3:-3]
        np.testing.assert_array_equal(out.raw[b], held)
        info = out.raw_info[b]
        assert info["cfa_pattern"] == BayerPattern(params["pattern"]).shifted(3, 3).value
        assert info["wb_gains"] == [params["red_gain"], 1.0, params["blue_gain"]]
        np.testing.assert_array_equal(info["camera_to_linear"], synth.camera.camera_to_linear)
        assert (info["black_level"], info["white_level"]) == (RAW_BLACK_LEVEL, RAW_WHITE_LEVEL)
        one = synth.sample([PHOTOS[b]], 10 + b)
        np.testing.assert_array_equal(one.raw, out.raw[b])
        assert one.raw_info == info


def test_raw_of_a_tiled_run_equals_the_whole_image_run():
    whole = gpu_blur.synthesize([PHOTOS[0]], _scene(), seed=1, with_raw=True)
    tiled = gpu_blur.synthesize([PHOTOS[0]], _scene(), seed=1, with_raw=True, tile=(16, 18))
    assert tiled.tiles > 1
    np.testing.assert_array_equal(tiled.raw, whole.raw)


def test_with_raw_needs_the_raw_round_trip():
    scene = scene_from_dict({"noise": {"model": "gaussian"}}, "g.toml")
    with pytest.raises(ValueError, match=r"with_raw: scene has no RAW round trip \(noise.model "
                                         r"= 'gaussian', isp.round_trip = 'auto'\); set"):
        gpu_blur.Synthesizer(scene, with_raw=True)
    assert gpu_blur.synthesize([PHOTOS[0]], scene).raw is None


# -- generate --save -----------------------------------------------------------------------------

@pytest.fixture
def photo_folder(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    for i, photo in enumerate(PHOTOS):
        cv2.imwrite(str(folder / f"p{i}.png"), photo[:, :, ::-1])
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nmode = "kernel"\nkernel_size = [3, 5]\n[output]\ncrop = 3\n'
                     "jpeg_quality = [40, 80]\n")
    return folder, scene


def test_generate_save_mask_raw_writes_what_the_pipeline_held(tmp_path, photo_folder):
    folder, scene_path = photo_folder
    out = tmp_path / "set"
    assert main(["generate", "--input", str(folder), "--output", str(out), "--scene",
                 str(scene_path), "--seed", "9", "--save", "raw,mask", "--quiet"]) == 0
    lines = [json.loads(t) for t in (out / "manifest.jsonl").read_text().splitlines()]
    assert len(lines) == 2
    synth = gpu_blur.Synthesizer(scene_path, seed=9, with_raw=True)
    for line in lines:
        made = synth.sample(str(folder / f"{line['name']}.png"), line["index"])
        assert line["params"]["jpeg_quality"] == made.params["jpeg_quality"]
        assert "jpeg" in line["stages"]
        # the mask: 16-bit PNG codes of the pipeline's mask, cropped like the pair
        mask = cv2.imread(str(out / line["mask"]), cv2.IMREAD_UNCHANGED)[:, :, ::-1]
        assert mask.dtype == np.uint16 and mask.shape == made.blurred.shape
        np.testing.assert_array_equal(mask, to_integers(made.mask, 16))
        # the RAW: a CFA DNG whose codes give back the pipeline's mosaic
        info = line["raw_info"]
        assert info == json.loads(json.dumps(made.raw_info))
        with tifffile.TiffFile(out / line["raw"]) as dng:
            page = dng.pages[0]
            codes = page.asarray()
            tags = {tag.code: tag.value for tag in page.tags}
        assert codes.dtype == np.uint16 and codes.shape == made.raw.shape
        np.testing.assert_array_equal(codes, raw_codes(made.raw, made.raw_info))
        gains = np.array(info["wb_gains"])
        channel = np.array(["RGB".index(c) for c in info["cfa_pattern"]]).reshape(2, 2)
        sites = np.tile(channel, (codes.shape[0] // 2 + 1, codes.shape[1] // 2 + 1))
        sites = sites[:codes.shape[0], :codes.shape[1]]
        back = (codes - 2048.0) / 2**14 * gains[sites]
        np.testing.assert_allclose(back, made.raw, rtol=0, atol=0.5 / 2**14 * gains.max())
        assert info["cfa_pattern"] == BayerPattern(made.params["pattern"]).shifted(3, 3).value
        assert tags[33422] == bytes("RGB".index(c) for c in info["cfa_pattern"])
        assert tags[262] == 32803  # PhotometricInterpretation: CFA
        assert (tags[50714], tags[50717]) == (RAW_BLACK_LEVEL, RAW_WHITE_LEVEL)
        neutral = np.array(tags[50728], float).reshape(3, 2)
        np.testing.assert_allclose(neutral[:, 0] / neutral[:, 1], 1 / gains, atol=1e-6)
        assert info["wb_gains"] == [made.params["red_gain"], 1.0, made.params["blue_gain"]]


def test_generate_save_refuses_raw_without_the_round_trip_and_unknown_names(tmp_path, capsys):
    scene = tmp_path / "g.toml"
    scene.write_text('[noise]\nmodel = "gaussian"\n')
    assert main(["generate", "--output", str(tmp_path / "a"), "--scene", str(scene),
                 "--save", "raw", "--quiet"]) == 2
    assert f"--save raw: scene file {scene} has no RAW round trip" in capsys.readouterr().err
    assert main(["generate", "--output", str(tmp_path / "b"), "--save", "mask,jpeg",
                 "--quiet"]) == 2
    assert "--save mask,jpeg: 'jpeg' is not an output; allowed: a comma list of mask, raw" in \
        capsys.readouterr().err


def test_a_set_recorded_before_output_jpeg_quality_existed_resumes(tmp_path, photos, capsys):
    folder, quick = photos
    out = tmp_path / "set"
    run = ["generate", "--input", str(folder), "--output", str(out), "--quiet"]
    assert main([*run, "--scene", str(quick), "--limit", "1"]) == 0
    record = json.loads((out / "run.json").read_text())
    del record["scene"]["output"]["jpeg_quality"]  # as gpu_blur recorded it before the key
    (out / "run.json").write_text(json.dumps(record))
    assert main([*run, "--scene", str(quick), "--limit", "2", "--resume"]) == 0
    scene = tmp_path / "j.toml"
    scene.write_text(quick.read_text() + "[output]\njpeg_quality = [70, 90]\n")
    assert main([*run, "--limit", "2", "--resume", "--scene", str(scene)]) == 2
    assert "scene.output.jpeg_quality = None (this run: [70, 90])" in capsys.readouterr().err
