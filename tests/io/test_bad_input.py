"""Bad input gets a clear error that names the file or value and the way out (issue 5).

Small images and the numpy backend throughout: what is checked is the refusal, not the maths.
"""

import json
import math
import os
import struct
import zlib

import cv2
import numpy as np
import pytest
import simplejpeg

import gpu_blur
from gpu_blur.cli import main
from gpu_blur.image_reading import read_image
from gpu_blur.kernel_files import check_kernel, read_kernel
from gpu_blur.scene import SceneError, load_scene, scene_from_dict


def make_scene(**sections):
    """The default scene with 3 camera poses (fast on small images), plus ``sections``."""
    data = {"blur": {"steps": 3}}
    for section, values in sections.items():
        data.setdefault(section, {}).update(values)
    return scene_from_dict(data)


def random_rgb(seed=0, shape=(24, 32), dtype=np.uint8):
    top = np.iinfo(dtype).max
    return np.random.default_rng(seed).integers(0, top + 1, (*shape, 3), dtype=dtype)


def save(path, image):
    """Write an RGB(A) or grayscale array with OpenCV (which wants BGR order)."""
    if image.ndim == 3:
        image = image[:, :, [2, 1, 0, 3][:image.shape[2]]]
    assert cv2.imwrite(str(path), image)
    return path


def write_photos(folder, n, shape=(24, 32), first_seed=0):
    folder.mkdir(parents=True, exist_ok=True)
    return [save(folder / f"p{i}.png", random_rgb(first_seed + i, shape)) for i in range(n)]


def manifest(out):
    return [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]


# ---- image files ---------------------------------------------------------------------------

@pytest.mark.parametrize("keep", [0.5, -12, 30], ids=["half", "no-IEND", "header-only"])
def test_a_truncated_png_is_refused_naming_the_file(tmp_path, keep):
    path = save(tmp_path / "cut.png", random_rgb())
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep) if isinstance(keep, float) else keep])
    with pytest.raises(ValueError) as e:
        read_image(path)
    assert str(path) in str(e.value) and "truncated PNG" in str(e.value)
    assert "re-export or re-copy the file" in str(e.value)


def test_a_corrupt_png_is_refused_naming_the_file(tmp_path):
    path = save(tmp_path / "bad.png", random_rgb())
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside the compressed pixels: libpng's checksum fails
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="not a readable image") as e:
        gpu_blur.synthesize([path], make_scene())
    assert str(path) in str(e.value)


def test_a_truncated_jpeg_is_refused_though_opencv_would_decode_it_grey(tmp_path):
    path = save(tmp_path / "cut.jpg", random_rgb())
    data = path.read_bytes()
    assert cv2.imread(str(path)) is not None
    path.write_bytes(data[:len(data) // 2])
    with pytest.raises(ValueError, match="truncated JPEG") as e:
        read_image(path)
    assert str(path) in str(e.value)
    path.write_bytes(data + b"trailing bytes after the end-of-image marker are allowed")
    assert read_image(path).shape == (24, 32, 3)


@pytest.mark.parametrize("content, message", [
    (b"", "the file is empty"),
    (b"this is not an image", "not a readable image"),
])
def test_empty_files_and_non_images_are_refused(tmp_path, content, message):
    path = tmp_path / "x.png"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as e:
        read_image(path)
    assert str(path) in str(e.value)
    with pytest.raises(ValueError, match=f"{tmp_path / 'none.png'}: no such file"):
        read_image(tmp_path / "none.png")


def claim_size(data, fmt, width, height):
    """A small image file's bytes with its header doctored to say ``width`` x ``height``."""
    data = bytearray(data)
    if fmt == "png":  # IHDR, then its CRC again (libpng checks it)
        struct.pack_into(">II", data, 16, width, height)
        struct.pack_into(">I", data, 29, zlib.crc32(bytes(data[12:29])))
    elif fmt == "jpg":  # the baseline frame header OpenCV writes
        struct.pack_into(">HH", data, data.find(b"\xff\xc0") + 5, height, width)
    elif fmt == "bmp":
        struct.pack_into("<ii", data, 18, width, height)
    else:  # TIFF: the ImageWidth (256) and ImageLength (257) entries of the IFD, SHORT or LONG
        for tag, value in ((256, width), (257, height)):
            at = [data.find(struct.pack("<HHI", tag, kind, 1)) for kind in (3, 4)]
            pos, kind = max(at), 3 if at[0] >= 0 else 4
            struct.pack_into("<H" if kind == 3 else "<I", data, pos + 8, value)
    return bytes(data)


@pytest.mark.parametrize("fmt", ["png", "jpg", "tiff", "bmp"])
def test_a_small_file_claiming_a_huge_image_is_refused_before_decoding(tmp_path, monkeypatch,
                                                                       fmt):
    monkeypatch.delenv("GPU_BLUR_MAX_PIXELS", raising=False)
    path = save(tmp_path / f"bomb.{fmt}", random_rgb())
    path.write_bytes(claim_size(path.read_bytes(), fmt, 40000, 40000))

    def decoded(*args, **kwargs):
        raise AssertionError("decoded before its size was checked")

    monkeypatch.setattr(cv2, "imdecode", decoded)
    monkeypatch.setattr(simplejpeg, "decode_jpeg", decoded)  # _damage's strict decode
    with pytest.raises(ValueError) as e:
        read_image(path)
    message = str(e.value)
    assert message.startswith(f"{path}: is 40000 x 40000 pixels (1,600,000,000, 4.8 GB ")
    assert "more than the 268,435,456 an image may hold; scale it down or crop it" in message
    assert message.endswith("GPU_BLUR_MAX_PIXELS=1600000000")


@pytest.mark.parametrize("fmt", ["png", "jpg", "tiff", "bmp", "webp"])
def test_gpu_blur_max_pixels_sets_the_pixel_budget(tmp_path, monkeypatch, fmt):
    path = save(tmp_path / f"small.{fmt}", random_rgb())  # 32 x 24: 768 pixels
    monkeypatch.setenv("GPU_BLUR_MAX_PIXELS", "767")
    with pytest.raises(ValueError, match=r"is 32 x 24 pixels \(768\), more than the 767 .*"
                                         "GPU_BLUR_MAX_PIXELS=768$") as e:
        read_image(path)
    assert str(e.value).startswith(f"{path}: ")
    monkeypatch.setenv("GPU_BLUR_MAX_PIXELS", "768")
    assert read_image(path).shape == (24, 32, 3)


@pytest.mark.parametrize("value", ["lots", "0", "1e9"])
def test_a_bad_gpu_blur_max_pixels_is_refused_naming_it(tmp_path, monkeypatch, value):
    path = save(tmp_path / "small.png", random_rgb())
    monkeypatch.setenv("GPU_BLUR_MAX_PIXELS", value)
    with pytest.raises(ValueError, match=f"environment variable GPU_BLUR_MAX_PIXELS = "
                                         f"'{value}' is invalid; allowed: int >= 1 .*set it to "
                                         "a number of pixels"):
        read_image(path)


def test_grayscale_is_expanded_to_three_equal_channels(tmp_path):
    gray = random_rgb()[:, :, 0]
    image = read_image(save(tmp_path / "gray.png", gray))
    assert image.shape == (24, 32, 3) and all(np.array_equal(image[..., c], gray)
                                              for c in range(3))
    from_file = gpu_blur.synthesize([tmp_path / "gray.png"], make_scene(), seed=1)
    from_array = gpu_blur.synthesize([np.repeat(gray[..., None], 3, axis=2)], make_scene(),
                                     seed=1)
    assert np.array_equal(from_file.blurred, from_array.blurred)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_an_opaque_alpha_channel_is_dropped(tmp_path, dtype):
    rgb = random_rgb(dtype=dtype)
    rgba = np.dstack([rgb, np.full(rgb.shape[:2], np.iinfo(dtype).max, dtype)])
    image = read_image(save(tmp_path / "rgba.png", rgba))
    assert image.dtype == dtype and np.array_equal(image, rgb)


def test_transparent_pixels_are_refused_with_count_place_and_way_out(tmp_path):
    rgba = np.dstack([random_rgb(), np.full((24, 32), 255, np.uint8)])
    rgba[5, 7, 3] = 0
    rgba[9, 1, 3] = 128
    path = save(tmp_path / "cutout.png", rgba)
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([path], make_scene())
    message = str(e.value)
    assert str(path) in message and "2 of 768 pixels are not fully opaque" in message
    assert "first at row 5, column 7" in message and "flatten" in message


def test_16_bit_pngs_are_read_as_16_bit_codes(tmp_path):
    codes = random_rgb(3, dtype=np.uint16)
    path = save(tmp_path / "deep.png", codes)
    image = read_image(path)
    assert image.dtype == np.uint16 and np.array_equal(image, codes)
    scene = make_scene(output={"bits": 16})
    from_file = gpu_blur.synthesize([path], scene, seed=2)
    from_float = gpu_blur.synthesize([codes / 65535.0], scene, seed=2)
    np.testing.assert_allclose(from_file.blurred, from_float.blurred, rtol=0, atol=1e-6)
    np.testing.assert_allclose(from_file.sharp, from_float.sharp, rtol=0, atol=1e-6)
    # an 8-bit image and its 16-bit copy (code * 257) are the same values
    eight = random_rgb(4)
    a = gpu_blur.synthesize([save(tmp_path / "8.png", eight)], scene, seed=2)
    b = gpu_blur.synthesize([save(tmp_path / "16.png", eight.astype(np.uint16) * 257)], scene,
                            seed=2)
    np.testing.assert_allclose(a.blurred, b.blurred, rtol=0, atol=1e-6)


def test_frames_of_different_sizes_name_both_files(tmp_path):
    frames = write_photos(tmp_path, 3)
    save(frames[1], random_rgb(9, shape=(24, 30)))
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize(frames, make_scene(blur={"mode": "average", "frames": 3}))
    message = str(e.value)
    assert f"{frames[1]} is 30 x 24 (width x height) but {frames[0]} is 32 x 24" in message
    assert "same size" in message


# ---- arrays --------------------------------------------------------------------------------

def test_nan_and_inf_in_a_float_array_are_counted_and_located():
    image = np.full((8, 8, 3), 0.5)
    image[1, 2, 0] = image[6, 6, 2] = np.nan
    image[3, 4, 1] = np.inf
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([image], make_scene())
    message = str(e.value)
    assert message.startswith("frame 0: 2 NaN and 1 infinite value(s), the first at row 1, "
                              "column 2, channel 0")
    assert "np.nan_to_num" in message


def test_negative_and_too_large_floats_are_counted_and_located():
    image = np.full((8, 8, 3), 0.5)
    image[2, 3, 1], image[4, 0, 0], image[7, 7, 2] = -0.25, -1e-9, -0.1
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([image], make_scene())
    assert ("3 negative value(s), the lowest -0.25, the first at row 2, column 3, channel 1"
            in str(e.value)) and "np.clip(x, 0, 1)" in str(e.value)
    with pytest.raises(ValueError, match=r"blurred image: 192 value\(s\) above 1, the high") as e:
        gpu_blur.synthesize({"blurred": np.full((8, 8, 3), 200.0)},
                            make_scene(blur={"mode": "none"}))
    assert "uint8" in str(e.value)


@pytest.mark.parametrize("image, message", [
    (np.zeros((8, 8)), "got shape (8, 8): for a grayscale image repeat it"),
    (np.zeros((8, 8, 3), np.int64), "unsupported dtype int64"),
    (np.zeros((0, 8, 3)), "the image is empty"),
])
def test_arrays_of_the_wrong_shape_or_type_say_what_is_expected(image, message):
    with pytest.raises(ValueError, match="frame 0") as e:
        gpu_blur.synthesize([image], make_scene())
    assert message in str(e.value)


# ---- scene, kernel, camera, Bayer pattern ----------------------------------------------------

@pytest.mark.parametrize("data, message", [  # what tests/synthesis/test_scene.py does not cover
    ({"noise": {"spread": 1.5}}, "noise.spread = 1.5 is invalid; allowed: int or float <= 1"),
    ({"blur": 3}, "blur must be a [blur] table"),
    ({"blur": {"mode": "kernel", "kernel_size": [4, 4]}}, "holds no odd size"),
    ({"isp": {"pattern": "RGBG"}}, "isp.pattern = 'RGBG' is invalid; allowed: 'random' | "
                                   "'RGGB'"),
])
def test_more_bad_scene_values_are_named_with_what_is_allowed(data, message):
    with pytest.raises(SceneError) as e:
        scene_from_dict(data, "my.toml")
    assert str(e.value).startswith("my.toml: ") and message in str(e.value)


def test_generate_stops_at_an_unknown_scene_key_naming_the_file(tmp_path, capsys):
    scene = tmp_path / "typo.toml"
    scene.write_text("[blur]\nstep = 3\n")
    assert main(["generate", "--output", str(tmp_path / "o"), "--scene", str(scene)]) == 2
    err = capsys.readouterr().err
    assert f"scene file {scene}: unknown key blur.step" in err and "steps" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kernel, message", [
    (np.zeros((5, 5)), "its weights sum to 0; a blur kernel needs some positive weight"),
    (np.array([[0, 1, 0], [0, 2, 0], [0, -1, 0]], float),
     "holds 1 negative weight(s), the lowest -1; a blur kernel is non-negative: clip them"),
    (np.full((3, 3), np.nan), "holds 9 NaN or infinite weight(s)"),
    (np.ones((4, 4)), "is 4 x 4; a kernel needs odd sides"),
], ids=["zero-sum", "negative", "nan", "even"])
def test_a_bad_kernel_file_is_named(tmp_path, capsys, kernel, message):
    np.save(tmp_path / "k.npy", kernel)
    scene_file = tmp_path / "s.toml"
    scene_file.write_text('[blur]\nmode = "kernel"\nkernel = "k.npy"\n')
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([random_rgb()], load_scene(scene_file))
    assert f"blur.kernel = '{tmp_path / 'k.npy'}'" in str(e.value) and message in str(e.value)
    # the command fails before making any sample (every sample would fail alike)
    photos = tmp_path / "in"
    write_photos(photos, 2)
    out = tmp_path / "out"
    assert main(["generate", "--input", str(photos), "--output", str(out), "--scene",
                 str(scene_file), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"scene file {scene_file}: blur.kernel" in err and message in err
    assert not out.exists()


@pytest.mark.parametrize("suffix", [".npy", ".png"])
def test_a_kernel_wider_than_the_kernel_side_limit_is_refused(tmp_path, suffix):
    path = tmp_path / f"wide{suffix}"
    kernel = np.zeros((3, 513), np.uint8)
    kernel[1, 256] = 255
    np.save(path, kernel) if suffix == ".npy" else save(path, kernel)
    with pytest.raises(ValueError) as e:
        read_kernel(path)
    assert str(e.value) == (
        f"blur.kernel = '{path}': is 3 x 513; allowed sides: int <= 511 (pixels a side of a "
        "given kernel, a read per pixel and tap: 511 x 511 is 261,121 taps; measured "
        "camera-shake kernels span tens of pixels, 511 is a quarter of a 1920-pixel frame): "
        "crop it to the rows and columns that hold its weight, or scale it down with the "
        "images it blurs")
    with pytest.raises(ValueError, match=r"overrides\['kernel'\]: is 3 x 513; allowed sides"):
        check_kernel(kernel.astype(float), "overrides['kernel']")
    np.save(path.with_suffix(".npy"), kernel[:, 1:-1])  # 511 wide: read
    assert read_kernel(path.with_suffix(".npy")).shape == (3, 511)


@pytest.mark.parametrize("shape, version, message", [
    ((60001, 60001), "1_0", "is 60001 x 60001; allowed sides: int <= 511"),
    ((501, 501), "2_0", "its header gives a 501 x 501 array of float64 (2,008,008 bytes) but "
                        "64 bytes follow it: the file is truncated or its header damaged; save "
                        "the kernel with np.save again"),
], ids=["too-wide", "more-than-the-file"])
def test_an_npy_kernel_is_refused_from_its_header_before_loading(tmp_path, shape, version,
                                                                  message):
    path = tmp_path / "claims.npy"
    with path.open("wb") as f:
        header = {"descr": "<f8", "fortran_order": False, "shape": shape}
        getattr(np.lib.format, f"write_array_header_{version}")(f, header)
        f.write(bytes(64))
    with pytest.raises(ValueError) as e:
        read_kernel(path)
    assert str(e.value).startswith(f"blur.kernel = '{path}': {message}")


def test_a_bad_kernel_override_is_named():
    scene = make_scene(blur={"mode": "kernel"}, noise={"model": "none"})
    with pytest.raises(ValueError, match=r"overrides\['kernel'\]: holds 9 negative weight"):
        gpu_blur.synthesize([random_rgb()], scene, overrides={"kernel": -np.ones((3, 3))})


@pytest.mark.parametrize("kernel, words", [
    (np.ones((3, 3)) + 1j, "holds complex128 values; kernel weights are real (the imaginary "
                           "part would be lost): pass np.real(k) or np.abs(k)"),
    (np.ones((3, 3), bool), "holds bool values, not numbers; kernel weights are integers or "
                            "floats: pass k.astype(np.float64)"),
    (np.full((3, 3), "1"), "holds <U1 values, not numbers"),
])
def test_a_kernel_of_no_real_numbers_is_refused_not_cast(tmp_path, kernel, words):
    np.save(tmp_path / "k.npy", kernel)
    with pytest.raises(ValueError) as e:
        read_kernel(tmp_path / "k.npy")
    assert str(e.value).startswith(f"blur.kernel = '{tmp_path / 'k.npy'}': {words}")
    scene = make_scene(blur={"mode": "kernel"}, noise={"model": "none"})
    with pytest.raises(ValueError) as e:
        gpu_blur.Synthesizer(scene, overrides={"kernel": kernel})
    assert str(e.value).startswith(f"overrides['kernel']: {words}")
    np.save(tmp_path / "k.npy", np.ones((3, 3), np.int16))  # integers are weights
    assert read_kernel(tmp_path / "k.npy").dtype == np.float64


@pytest.mark.parametrize("name, value, words", [
    ("alpha", math.nan, "overrides['alpha'] = nan is invalid; allowed: a finite int or float"),
    ("alpha", 1e308, "overrides['alpha'] = 1e+308 is invalid; allowed: int or float <= 100"),
    ("alpha", "1", "overrides['alpha'] = '1' is invalid; allowed: int or float >= 0"),
    ("jpeg_quality", 0.5, "overrides['jpeg_quality'] = 0.5 is invalid; allowed: int >= 1"),
    ("pattern", 3, "overrides['pattern'] = 3 is not a Bayer pattern; allowed: RGGB"),
    ("kernel", -np.ones((3, 3)), "overrides['kernel']: holds 9 negative weight(s)"),
    ("homographies", np.eye(3)[None] * 1j, "overrides['homographies'] must be a finite n x 3 "
                                           "x 3 array (1 <= n <= 8192, as blur.steps) of "
                                           "camera poses; got values that are not real"),
])
def test_every_override_is_checked_up_front_whether_or_not_its_stage_runs(name, value, words):
    # auto saturation skips a photo that does not clip, and no stage here uses jpeg_quality,
    # a pattern, a kernel or poses: each was accepted unchecked
    scene = make_scene(blur={"mode": "none"}, saturation={"mode": "auto"},
                       noise={"model": "none"})
    with pytest.raises(ValueError) as e:
        gpu_blur.Synthesizer(scene, overrides={name: value})
    assert str(e.value).startswith(words)
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize({"blurred": np.full((8, 8, 3), 0.5)}, scene, overrides={name: value})
    assert str(e.value).startswith(words)


def test_overrides_that_are_not_a_mapping_are_refused():
    with pytest.raises(TypeError, match=r"overrides: a mapping of parameter names to values "
                                        r"\(e.g. \{'alpha': 1.0\}\); got a list"):
        gpu_blur.Synthesizer(make_scene(), overrides=[("alpha", 1.0)])


def test_an_unknown_input_of_blur_mode_none_is_refused_naming_the_known_ones():
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize({"blurred": np.full((8, 8, 3), 0.5), "masks": np.zeros((8, 8, 3))},
                            make_scene(blur={"mode": "none"}))
    assert str(e.value) == ("blur.mode = none: unknown input 'masks'; the inputs are 'blurred', "
                            "'mask' (optional) and 'sharp' (optional)")


def test_an_unknown_camera_lists_the_cameras_there_are(tmp_path, capsys):
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([random_rgb()], make_scene(camera={"name": "nikon"}))
    assert "camera.name = 'nikon': unknown camera 'nikon'" in str(e.value)
    assert "a7r3" in str(e.value) and ".toml/.json camera file" in str(e.value)
    scene_file = tmp_path / "s.toml"
    scene_file.write_text('[camera]\nname = "mine.toml"\n')
    assert main(["generate", "--output", str(tmp_path / "out"), "--scene", str(scene_file),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"scene file {scene_file}: camera.name = 'mine.toml'" in err
    assert f"camera file {tmp_path / 'mine.toml'}: cannot read it" in err


def test_an_unknown_bayer_pattern_override_lists_the_patterns():
    with pytest.raises(ValueError) as e:
        gpu_blur.synthesize([random_rgb()], make_scene(), overrides={"pattern": "RGBG"})
    assert "overrides['pattern'] = 'RGBG' is not a Bayer pattern; allowed: RGGB | BGGR" in str(
        e.value)
    lower = gpu_blur.synthesize([random_rgb()], make_scene(), overrides={"pattern": "bggr"})
    assert lower.params["pattern"] == "BGGR"


# ---- the command: setup errors stop it, bad samples do not ------------------------------------

def test_an_output_folder_that_cannot_be_created_stops_the_command(tmp_path, capsys):
    write_photos(tmp_path / "in", 1)
    (tmp_path / "file").write_text("a file, not a folder")
    out = tmp_path / "file" / "sub"  # fails for every user, root included
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"--output {out}: cannot create or write the folder" in err and "writable" in err


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="root writes into read-only folders (the test above covers root)")
def test_a_read_only_output_folder_stops_the_command(tmp_path, capsys):
    write_photos(tmp_path / "in", 1)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(locked),
                     "--quiet"]) == 2
    finally:
        locked.chmod(0o700)
    assert f"--output {locked}: cannot create or write the folder" in capsys.readouterr().err


@pytest.mark.parametrize("make, message", [
    (lambda p: p.mkdir(), "the folder is empty"),
    (lambda p: None, "no such folder"),
    (lambda p: p.write_text("x"), "is a file, not a folder"),
    (lambda p: (p / "notes").mkdir(parents=True), "no images (.png"),
])
def test_an_input_without_images_stops_the_command(tmp_path, capsys, make, message):
    make(tmp_path / "in")
    assert main(["generate", "--input", str(tmp_path / "in"), "--output",
                 str(tmp_path / "out"), "--quiet"]) == 2
    assert f"--input {tmp_path / 'in'}: {message}" in capsys.readouterr().err


@pytest.mark.parametrize("args, message", [
    (["--seed", "-1"], "--seed -1: must lie in [0, 2**64)"),
    (["--tile", "0", "64"], "--tile 0 64: rows and columns must be >= 1"),
])
def test_bad_options_stop_the_command_before_any_sample(tmp_path, capsys, args, message):
    write_photos(tmp_path / "in", 1)
    assert main(["generate", "--input", str(tmp_path / "in"), "--output",
                 str(tmp_path / "out"), "--quiet", *args]) == 2
    assert message in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_bad_photos_are_listed_as_failed_and_the_good_ones_are_made(tmp_path, capsys):
    photos = write_photos(tmp_path / "in", 4)
    photos[1].write_bytes(photos[1].read_bytes()[:100])
    save(photos[2], np.dstack([random_rgb(), np.zeros((24, 32), np.uint8)]))
    scene = tmp_path / "s.toml"
    scene.write_text("[blur]\nsteps = 3\n")
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--scene", str(scene), "--quiet"]) == 1
    lines = manifest(out)
    assert [(x["index"], x["name"], x["status"]) for x in lines] == [
        (0, "p0", "ok"), (1, "p1", "failed"), (2, "p2", "failed"), (3, "p3", "ok")]
    assert lines[1]["inputs"] == [str(photos[1])] and "truncated PNG" in lines[1]["error"]
    assert "not fully opaque" in lines[2]["error"] and "blurred" not in lines[2]
    assert sorted(p.name for p in (out / "blur").iterdir()) == ["000000_p0.png",
                                                                "000003_p3.png"]
    captured = capsys.readouterr()
    assert "wrote 2 samples" in captured.out
    assert "2 of 4 samples failed" in captured.err and "--resume" in captured.err
    assert f"sample 1 (p1): {photos[1]}: truncated PNG" in captured.err


def test_bad_sequences_are_listed_as_failed_and_the_good_ones_are_made(tmp_path, capsys):
    root = tmp_path / "in"
    write_photos(root / "A" / "sharp", 6)
    odd = write_photos(root / "B" / "sharp", 3, first_seed=10)
    save(odd[2], random_rgb(shape=(24, 30)))
    write_photos(root / "C" / "sharp", 2, first_seed=20)  # fewer than blur.frames
    write_photos(root / "D" / "sharp", 3, first_seed=30)
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 3\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(root), "--output", str(out), "--scene",
                 str(scene), "--quiet"]) == 1
    lines = manifest(out)
    assert [(x["name"], x["status"]) for x in lines] == [
        ("A/p0", "ok"), ("A/p3", "ok"), ("B/p0", "failed"), ("C/p0", "failed"), ("D/p0", "ok")]
    assert f"{odd[2]} is 30 x 24 (width x height)" in lines[2]["error"]
    assert lines[3]["error"].startswith("sequence C has 2 frame(s) in ")
    assert "fewer than blur.frames = 3" in lines[3]["error"] and len(lines[3]["inputs"]) == 2
    assert "2 of 5 samples failed" in capsys.readouterr().err


def test_only_too_short_sequences_stop_the_command(tmp_path, capsys):
    write_photos(tmp_path / "in" / "A" / "sharp", 2)
    scene = tmp_path / "s.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 3\n')
    assert main(["generate", "--input", str(tmp_path / "in"), "--output",
                 str(tmp_path / "out"), "--scene", str(scene), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no <seq>/sharp/ folder with at least 3 images (blur.frames); A has 2" in err


# ---- hostile files: sizes before decoding, regular files only, parse errors named -----------

def encoded(fmt):
    """A 32 x 24 image in ``fmt`` as OpenCV writes it (VP8X: a WebP with transparency)."""
    image, ext, params = random_rgb(), f".{fmt.split('-')[0]}", []
    if fmt.startswith("webp"):
        params = [cv2.IMWRITE_WEBP_QUALITY, 101 if fmt == "webp-lossless" else 80]
        if fmt == "webp-extended":
            image = np.dstack([image, np.full((24, 32), 200, np.uint8)])
    if fmt in ("pgm", "pbm"):
        image = image[:, :, 0]
    if fmt == "pfm":
        image = image.astype(np.float32) / 255
    ok, data = cv2.imencode(ext, image, params)
    assert ok
    return data.tobytes()


def claim_more(data, fmt, width, height):
    """A small file of ``fmt`` (:func:`encoded`), its header doctored to ``width`` x ``height``."""
    data = bytearray(data)
    if fmt == "gif":  # the logical screen
        struct.pack_into("<HH", data, 6, width, height)
    elif fmt == "webp-lossless":  # VP8L: 14 bits each of width - 1 and height - 1
        rest = struct.unpack_from("<I", data, 21)[0] & ~0x0FFFFFFF
        struct.pack_into("<I", data, 21, rest | (width - 1) | (height - 1) << 14)
    elif fmt == "webp-lossy":  # VP8's frame header: 14 bits each (and a scale)
        struct.pack_into("<HH", data, 26, width, height)
    elif fmt == "webp-extended":  # VP8X's canvas: 24 bits each of width - 1 and height - 1
        data[24:30] = (width - 1).to_bytes(3, "little") + (height - 1).to_bytes(3, "little")
    elif fmt == "pam":
        data = data.replace(b"WIDTH 32", b"WIDTH %d" % width).replace(b"HEIGHT 24",
                                                                      b"HEIGHT %d" % height)
    else:  # PNM and PFM: the first two numbers after the magic number (a comment between)
        data = data[:3] + b"# made by a test\n" + data[3:].replace(b"32 24", b"%d %d" % (
            width, height), 1)
    return bytes(data)


def not_decoded(*args, **kwargs):
    raise AssertionError("decoded before its size was checked")


HEADER_FORMATS = ["gif", "webp-lossless", "webp-lossy", "webp-extended", "ppm", "pgm", "pbm",
                  "pam", "pfm"]


@pytest.mark.parametrize("fmt", HEADER_FORMATS)
def test_gif_webp_and_pnm_files_are_refused_from_their_header_before_decoding(
        tmp_path, monkeypatch, fmt):
    from gpu_blur.image_reading import _header_size

    data = encoded(fmt)
    assert _header_size(data) == (32, 24)  # as OpenCV decodes it
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2] == (24, 32)
    path = tmp_path / "bomb.png"  # OpenCV goes by the bytes, not the name
    path.write_bytes(claim_more(data, fmt, 4000, 3000))
    monkeypatch.setattr(cv2, "imdecode", not_decoded)
    monkeypatch.setenv("GPU_BLUR_MAX_PIXELS", "1000000")
    with pytest.raises(ValueError) as e:
        read_image(path)
    assert str(e.value).startswith(f"{path}: is 4000 x 3000 pixels (12,000,000), more than the "
                                   "1,000,000 an image may hold; scale it down or crop it")


def test_a_35_byte_gif_claiming_8192_x_8192_costs_no_memory(tmp_path, monkeypatch):
    gif = (b"GIF89a" + struct.pack("<HHBBB", 8192, 8192, 0x80, 0, 0) + bytes(6) + b","
           + struct.pack("<HHHHB", 0, 0, 1, 1, 0) + b"\x02\x02\x4c\x01\x00;")
    path = tmp_path / "bomb.png"
    path.write_bytes(gif)
    assert len(gif) == 35
    monkeypatch.setattr(cv2, "imdecode", not_decoded)
    monkeypatch.setenv("GPU_BLUR_MAX_PIXELS", str(8192 * 8192 - 1))
    with pytest.raises(ValueError, match=r"bomb\.png: is 8192 x 8192 pixels \(67,108,864\)"):
        read_image(path)
    monkeypatch.setenv("GPU_BLUR_MAX_PIXELS", str(8192 * 8192))
    with pytest.raises(AssertionError, match="decoded"):  # within the budget: decoded
        read_image(path)


@pytest.mark.parametrize("ext, data", [
    (".hdr", None), (".ras", None),
    (".jp2", b"\0\0\0\x0cjP  \r\n\x87\n" + bytes(64)),  # a JPEG 2000 file's signature box
    (".png", b"\x89PNG\r\n\x1a\n" + bytes(4) + b"IEND" + bytes(4)),  # a PNG without IHDR
])
def test_files_whose_header_gives_no_size_are_refused_before_decoding(tmp_path, monkeypatch,
                                                                       ext, data):
    path = tmp_path / f"other{ext}"
    if data is None:  # OpenCV reads and writes these, but their size is not read here
        image = random_rgb()
        assert cv2.imwrite(str(path), image.astype(np.float32) / 255 if ext == ".hdr" else image)
    else:
        path.write_bytes(data)
    monkeypatch.setattr(cv2, "imdecode", not_decoded)
    with pytest.raises(ValueError) as e:
        read_image(path)
    assert str(e.value).startswith(f"{path}: not a readable image (no width and height in its "
                                   "header: gpu_blur reads PNG, JPEG, TIFF, BMP, GIF, WebP and "
                                   "PNM/PAM/PFM); convert it to PNG")


def in_a_thread(load, *args):
    """What ``load(*args)`` raises (None if nothing) within 20 s: a FIFO's reader would wait on."""
    import threading

    raised = []

    def run():
        try:
            load(*args)
        except Exception as e:
            raised.append(e)
        else:
            raised.append(None)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(20)
    assert raised, f"{load.__name__} is still waiting on the FIFO"
    return raised[0]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_or_a_folder_is_refused_wherever_a_file_is_read(tmp_path, capsys):
    from gpu_blur.cameras import load_camera

    for name in ("f.toml", "cam.toml", "cam.json", "k.npy", "k.png", "p.png"):
        os.mkfifo(tmp_path / name)
    for load, name, where in [(load_scene, "f.toml", "scene file "),
                              (load_camera, "cam.toml", "camera file "),
                              (load_camera, "cam.json", "camera file "),
                              (read_kernel, "k.npy", "blur.kernel = '"),
                              (read_kernel, "k.png", "blur.kernel = '"), (read_image, "p.png", "")]:
        path = tmp_path / name
        error = in_a_thread(load, path)
        quote = "'" if where.endswith("'") else ""
        assert str(error) == (f"{where}{path}{quote}: is a named pipe (FIFO), not a regular file; "
                              "give the path of a file")
    (tmp_path / "folder.toml").mkdir()
    assert "is a folder, not a regular file" in str(in_a_thread(load_scene, tmp_path /
                                                                 "folder.toml"))
    # a scene naming a camera file that is a FIFO stops the command (exit 2)
    scene = tmp_path / "s.toml"
    scene.write_text('[camera]\nname = "cam.toml"\n')
    assert in_a_thread(lambda: main(["plan", str(scene)]) == 2 or pytest.fail("status")) is None
    assert (f"camera file {tmp_path / 'cam.toml'}: is a named pipe (FIFO), not a regular file"
            in capsys.readouterr().err)


def deep(depth, opening="[", closing="]"):
    return opening * depth + closing * depth


@pytest.mark.parametrize("name, text, message", [
    ("deep.json", '{"color": ' + deep(100_000) + "}",
     "not valid JSON: arrays or objects are nested too deeply (more than about"),
    ("deep.toml", "x = " + deep(5000), "not valid TOML: arrays or tables are nested too deeply"),
    ("latin1.toml", b'name = "Kamera f\xfcr Test"\n', "not UTF-8 text (byte 0xFC on line 1 cannot "
                                                      "be decoded); save the file as UTF-8"),
    ("huge.toml", "[color]\ncamera_to_linear = [[1" + "0" * 400 + ", 0, 0], [0, 1, 0], [0, 0, 1]]",
     "color.camera_to_linear = [[1000"),
    ("huge.json", '{"color": {"xyz_to_camera": [[1, 0, 0], [0, -1' + "0" * 400 + ", 0], "
     "[0, 0, 1]]}}", "color.xyz_to_camera = [[1, 0, 0], [0, -1000"),
    ("nan.toml", "[color]\nccm_xyz = [[1, 0, 0], [0, nan, 0], [0, 0, 1]]",
     "color.ccm_xyz = [[1, 0, 0], [0, nan, 0], [0, 0, 1]] is invalid; expected a 3 x 3 list of "
     "numbers, each finite"),
])
def test_camera_files_that_do_not_parse_or_overflow_are_named(tmp_path, capsys, name, text,
                                                              message):
    from gpu_blur.cameras import load_camera

    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ValueError) as e:
        load_camera(path)
    assert str(e.value).startswith(f"camera file {path}: ") and message in str(e.value)
    if name.startswith("huge"):
        assert str(e.value).endswith("is invalid; expected a 3 x 3 list of numbers, each finite")
    scene = tmp_path / "s.toml"
    scene.write_text(f'[camera]\nname = "{name}"\n')
    assert main(["plan", str(scene)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"gpu-blur: error: scene file {scene}: camera.name = '{name}': camera "
                          f"file {path}: ") and message in err and "Traceback" not in err


@pytest.mark.parametrize("header", [
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3), ",  # a bracket left open
    "{'descr': '<f8', 'fortran_order': False, 'shape': ((3, 3)}",
    "{'descr': '<f8', 'fortran_order': False, 'shape': (0, 3)}",
    "{'descr': '<f8', 'fortran_order': False, 'shape': (-3, 3)}",
])
def test_a_broken_npy_header_is_named(tmp_path, header):
    text = header.encode()
    text += b" " * (63 - (10 + len(text)) % 64) + b"\n"
    path = tmp_path / "k.npy"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + bytes(72))
    with pytest.raises(ValueError) as e:
        read_kernel(path)
    message = str(e.value)
    assert message.startswith(f"blur.kernel = '{path}': ")
    if "(3" in header:
        assert message.endswith("not a numpy array file (its header is no valid Python "
                                "literal); save the kernel with np.save")
    else:
        assert "a kernel needs at least one row and column of weights" in message
