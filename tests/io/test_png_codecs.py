"""PNG codecs (issue 39): every write mode and every decoder give back the source's codes.

Writing: ``output.png`` = fast (numpy's Sub filter + Huffman-only deflate, zlib-ng's or
Python's zlib's, the same bytes), fastest (ISA-L) or small (the smallest of OpenCV's libpng
files and the fast one). Reading: libdeflate's or ISA-L's inflate and numpy for files of
None/Sub/Up rows, OpenCV for the rest and for anything they refuse. Each test runs with each
inflater and, with deflate, isal and zlib-ng patched away, without them, so it passes either
way.
"""

import hashlib
import struct
import zlib

import cv2
import numpy as np
import pytest

from gpu_blur import file_writing, png_codecs
from gpu_blur.file_writing import encode_image, write_image
from gpu_blur.image_reading import read_image
from gpu_blur.run_record import set_keys
from gpu_blur.scene import SceneError, scene_from_dict

INFLATERS = {"libdeflate": png_codecs._libdeflate_inflater, "isal": png_codecs._isal_inflater}


def use_inflater(name, monkeypatch):
    """Have decode_png inflate with ``name`` (a key of INFLATERS) alone."""
    inflater = INFLATERS[name]()
    if inflater is None:
        pytest.skip(f"{name}'s Python package is not installed")
    monkeypatch.setattr(png_codecs, "_inflater", lambda: inflater)
    return name


@pytest.fixture(params=list(INFLATERS))
def inflater(request, monkeypatch):
    """Decoding by libdeflate's inflate, then by ISA-L's."""
    return use_inflater(request.param, monkeypatch)


@pytest.fixture(params=[*INFLATERS, "absent"])
def libraries(request, monkeypatch):
    """Decoding by libdeflate's or ISA-L's inflate, or with both missing (OpenCV only).

    "absent" also treats zlib-ng and isal as missing for writing (Python's zlib); the others
    write with them as installed.
    """
    if request.param != "absent":
        return use_inflater(request.param, monkeypatch)
    monkeypatch.setattr(png_codecs, "_zlib_ng", lambda: None)
    monkeypatch.setattr(png_codecs, "_isal", lambda: None)
    monkeypatch.setattr(png_codecs, "_inflater", lambda: None)
    return request.param


def codes(bits, shape=(37, 53, 3), seed=0):
    """Random codes with a smooth part, so that matches and filters both get exercised."""
    dtype = np.uint8 if bits == 8 else np.uint16
    top = np.iinfo(dtype).max
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, top + 1, shape, dtype=np.uint64)
    ramp = np.linspace(0, top, shape[1]).reshape(1, -1, *[1] * (len(shape) - 2))
    ramp = (ramp * np.ones(shape)).astype(np.uint64)
    half = shape[0] // 2
    noise[:half] = ramp[:half]
    return noise.astype(dtype)


def opencv_rgb(data):
    """OpenCV's decode (IMREAD_UNCHANGED), colour in RGB(A) order."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image.ndim == 3:
        image = image[:, :, [2, 1, 0, 3][:image.shape[2]]]
    return image


def spng_rgb(data):
    """pyspng's decode (when installed) with the alpha it adds to 16-bit RGB and grey dropped."""
    import pyspng

    image = pyspng.load(data)
    if data[24] == 16 and data[25] in (0, 2):
        image = image[:, :, 0] if data[25] == 0 else image[:, :, :3]
    return image


def decoders():
    found = {"opencv": opencv_rgb, "png_codecs": lambda d: png_codecs.decode_png(d)}
    try:
        import pyspng  # noqa: F401
    except ImportError:
        pass
    else:
        found["pyspng"] = spng_rgb
    return found


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("shape", [(37, 53, 3), (37, 53, 4), (37, 53), (1, 1, 3), (5, 1)],
                         ids=["rgb", "rgba", "grey", "one-pixel", "one-column"])
@pytest.mark.parametrize("mode", list(png_codecs.PNG_MODES))
def test_every_mode_decodes_to_the_source_with_every_decoder(libraries, bits, shape, mode):
    source = codes(bits, shape)
    data = png_codecs.encode_png(source, mode)
    assert data.startswith(png_codecs.PNG_SIGNATURE)
    for name, decode in decoders().items():
        image = decode(data)
        if image is None:  # png_codecs.decode_png: a file it leaves to OpenCV
            assert name == "png_codecs" and (mode == "small" or libraries == "absent")
            continue
        assert image.dtype == source.dtype and np.array_equal(image, source), name


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("mode", list(png_codecs.PNG_MODES))
def test_written_outputs_read_back_as_the_codes_written(libraries, tmp_path, bits, mode):
    source = codes(bits, seed=bits)
    path = tmp_path / f"out_{mode}.png"
    write_image(path, source, bits, png=mode)
    assert np.array_equal(read_image(path), source)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left
    assert encode_image(source, bits, png=mode) == path.read_bytes()


def test_fast_is_the_default_and_small_is_the_smaller_on_a_smooth_16_bit_image():
    source = codes(16, (64, 96, 3))
    source[:] = source[:32][:1]  # every row the ramp
    assert encode_image(source, 16) == encode_image(source, 16, png="fast")
    assert len(png_codecs.encode_png(source, "small")) < len(png_codecs.encode_png(source,
                                                                                   "fast"))


@pytest.mark.parametrize("bits", [8, 16])
def test_small_is_never_larger_than_fast(bits):
    noise = codes(bits, (64, 96, 3), seed=5)  # all noise: libpng's level 6 finds little
    noise[:] = np.random.default_rng(5).integers(0, 2**bits, noise.shape)
    for source in (noise, codes(bits, (64, 96, 3))):
        small, fast = (png_codecs.encode_png(source, m) for m in ("small", "fast"))
        assert len(small) <= len(fast)
    grey_alpha = codes(bits, (8, 9, 2))  # OpenCV writes no grey + alpha: small is fast's file
    assert png_codecs.encode_png(grey_alpha, "small") == png_codecs.encode_png(grey_alpha)


#: sha256 (first 32 hex digits) of the fast file of codes(bits, (64, 96, 3), seed=11): zlib's
#: Huffman-only stream, whoever writes it.
FAST_FILE_DIGESTS = {8: "70a10847fbe98dad2dc7c72ca28168b4", 16: "85a182e31dad7ce552caa97beeeea386"}


@pytest.mark.bits
@pytest.mark.parametrize("bits", [8, 16])
def test_fast_files_are_the_recorded_bytes_with_zlib_ng_or_pythons_zlib(bits, monkeypatch):
    """The fast mode's bytes depend on the pixels alone: zlib-ng and Python's zlib write the
    same Huffman-only stream (ISA-L's deflate did not always: on an H200 host it once wrote
    another stream of the same rows)."""
    source = codes(bits, (64, 96, 3), seed=11)
    made = {"zlib-ng": png_codecs.encode_png(source, "fast")}
    monkeypatch.setattr(png_codecs, "_zlib_ng", lambda: None)
    made["zlib"] = png_codecs.encode_png(source, "fast")
    assert {k: hashlib.sha256(v).hexdigest()[:32] for k, v in made.items()} == {
        "zlib-ng": FAST_FILE_DIGESTS[bits], "zlib": FAST_FILE_DIGESTS[bits]}


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("seed", [0, 1])
def test_zlib_ng_and_pythons_zlib_write_one_huffman_stream(bits, seed, monkeypatch):
    """Noisy rows long enough for several deflate blocks: the same stream either way."""
    if png_codecs._zlib_ng() is None:
        pytest.skip("zlib-ng is not installed")
    noise = np.random.default_rng(seed).integers(0, 2**bits, (300, 400, 3)).astype(
        np.uint8 if bits == 8 else np.uint16)
    rows = png_codecs.filtered_rows(noise, "sub")
    streams = [png_codecs.huffman_zlib(rows)]  # zlib-ng's
    monkeypatch.setattr(png_codecs, "_zlib_ng", lambda: None)
    streams.append(png_codecs.huffman_zlib(rows))  # Python's zlib's
    assert streams[0] == streams[1]
    assert zlib.decompress(streams[0]) == rows.tobytes()


def test_a_stream_given_in_parts_makes_the_file_of_the_whole_stream():
    source = codes(8, (48, 64, 3), seed=5)
    stream = png_codecs.huffman_zlib(png_codecs.filtered_rows(source, "sub"))
    whole = png_codecs.png_file(source, stream)
    for cuts in ([], [0], [1, 7], [len(stream) // 2, len(stream)]):
        bounds = [0, *cuts, len(stream)]
        parts = [stream[a:b] for a, b in zip(bounds, bounds[1:], strict=False)]
        assert png_codecs.png_file(source, parts) == whole
    assert png_codecs.encode_png(source, "fast") == whole
    assert np.array_equal(png_codecs.decode_png(whole), source)


def test_fastest_compresses_the_fast_rows_with_isal_or_is_fast_without_it(monkeypatch):
    source = codes(8, (64, 96, 3), seed=11)
    isal = png_codecs._isal()
    if isal is None:
        pytest.skip("isal is not installed")
    rows = png_codecs.filtered_rows(source, "sub")
    fastest = png_codecs.encode_png(source, "fastest")
    assert fastest == png_codecs.png_file(source, isal.compress(rows, 1))
    assert fastest != png_codecs.encode_png(source, "fast")  # another deflate, same rows
    assert "may vary" in png_codecs.encoder_name("fastest")
    monkeypatch.setattr(png_codecs, "_isal", lambda: None)
    assert png_codecs.encode_png(source, "fastest") == png_codecs.encode_png(source, "fast")
    assert png_codecs.encoder_name("fastest") == png_codecs.encoder_name("fast")


@pytest.mark.parametrize("size", [0, 1, 65_534, 65_535, 65_536, 3 * 65_535 + 7])
def test_stored_blocks_make_the_zlib_stream_of_the_data(size):
    data = np.random.default_rng(size).integers(0, 256, size, np.uint8).tobytes()
    stream = png_codecs.stored_zlib(data)
    assert zlib.decompress(stream) == data
    blocks = max(1, -(-size // 65_535))
    assert len(stream) == 2 + 5 * blocks + size + 4  # header, block heads, data, Adler-32


def test_stored_files_are_the_unfiltered_rows_uncompressed():
    source = codes(16, (37, 53, 3), seed=4)
    data = png_codecs.encode_png(source, "stored")
    rows = png_codecs.filtered_rows(source, "none").tobytes()
    assert rows in data and len(data) < len(rows) + 100  # the rows as they are, once
    assert np.array_equal(png_codecs.decode_png(data), source)


def test_an_unknown_png_mode_is_refused_naming_the_modes():
    modes = "fast, fastest, small, stored"
    with pytest.raises(ValueError, match=f"PNG mode 'tiny': expected one of {modes}"):
        encode_image(codes(8), 8, png="tiny")
    with pytest.raises(SceneError, match="output.png"):
        scene_from_dict({"output": {"png": "tiny"}})
    assert scene_from_dict({"output": {"png": "small"}}).output.png == "small"
    assert scene_from_dict({}).output.png == png_codecs.DEFAULT_PNG_MODE == "fast"


def test_a_resume_takes_either_png_mode():
    old = {"output": {"bits": 8}}  # a set made before output.png
    assert set_keys(old) == set_keys({"output": {"bits": 8, "png": "small"}})
    assert set_keys(old) == set_keys({"output": {"bits": 8, "png": "fast"}})


@pytest.mark.parametrize("shape", [(21, 30, 3), (21, 30, 4), (21, 30)],
                         ids=["rgb", "rgba", "grey"])
@pytest.mark.parametrize("bits", [8, 16])
def test_read_image_gives_opencvs_pixels_through_either_decoder(libraries, tmp_path, shape,
                                                                 bits):
    source = codes(bits, shape, seed=3)
    if len(shape) == 3 and shape[2] == 4:
        source[:, :, 3] = np.iinfo(source.dtype).max  # opaque: read_image drops it
    path = tmp_path / "in.png"
    path.write_bytes(png_codecs.encode_png(source, "small"))
    want = source[:, :, :3] if source.ndim == 3 else np.repeat(source[:, :, None], 3, axis=2)
    image = read_image(path)
    assert image.dtype == source.dtype and image.flags.c_contiguous
    assert np.array_equal(image, want)


def chunks(data):
    """(type, start, length) of each chunk."""
    pos, found = 8, []
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        found.append((kind, pos, length))
        pos += 12 + length
    return found


def with_chunk_before_idat(data, kind, body):
    idat = next(start for k, start, _ in chunks(data) if k == b"IDAT")
    return data[:idat] + png_codecs.chunk(kind, body) + data[idat:]


def test_a_damaged_idat_is_refused_naming_the_file(libraries, tmp_path):
    data = bytearray(png_codecs.encode_png(codes(8), "fast"))
    kind, start, length = next(c for c in chunks(data) if c[0] == b"IDAT")
    data[start + 8 + length // 2] ^= 0xFF  # inside the compressed pixels; its CRC is now wrong
    assert png_codecs.decode_png(bytes(data)) is None  # left to OpenCV, which refuses it
    path = tmp_path / "bad.png"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="not a readable image") as e:
        read_image(path)
    assert str(path) in str(e.value) and "re-export or re-copy the file" in str(e.value)


def test_other_files_go_through_opencv():
    """tRNS (OpenCV makes it an alpha channel), interlacing, 1-bit grey, Paeth rows."""
    eight = png_codecs.encode_png(codes(8), "fast")
    assert png_codecs.decode_png(with_chunk_before_idat(eight, b"tRNS", bytes(6))) is None
    for bits in (8, 16):
        source = codes(bits)
        paeth = png_codecs.png_file(source, zlib.compress(
            png_codecs.filtered_rows(source, "paeth").tobytes()))
        assert png_codecs.decode_png(paeth) is None
        assert np.array_equal(opencv_rgb(paeth), source)
    interlaced = bytearray(eight)
    interlaced[28] = 1
    struct.pack_into(">I", interlaced, 29, zlib.crc32(bytes(interlaced[12:29])))
    assert png_codecs.decode_png(bytes(interlaced)) is None
    ok, palette = cv2.imencode(".png", codes(8, (8, 8)), [cv2.IMWRITE_PNG_BILEVEL, 1])
    assert png_codecs.decode_png(palette.tobytes()) is None  # a 1-bit grey file
    assert png_codecs.decode_png(b"\xff\xd8" + eight[2:]) is None  # not a PNG signature


def test_transparent_pixels_are_refused_through_isal_too(tmp_path):
    rgba = codes(8, (9, 11, 4))
    rgba[:, :, 3] = 255
    rgba[4, 7, 3] = 0
    path = tmp_path / "cutout.png"
    path.write_bytes(png_codecs.encode_png(rgba, "fast"))
    with pytest.raises(ValueError, match=r"1 of 99 pixels are not fully opaque .*row 4, "
                                         r"column 7"):
        read_image(path)


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("shape", [(37, 53, 3), (37, 53, 4), (37, 53), (1, 1, 3)],
                         ids=["rgb", "rgba", "grey", "one-pixel"])
def test_each_filter_and_rows_of_mixed_filters_decode_to_the_source(libraries, bits, shape):
    source = codes(bits, shape, seed=7)
    rows = {kind: png_codecs.filtered_rows(source, kind) for kind in ("none", "sub", "up")}
    mixed = rows["sub"].copy()
    mixed[1::3], mixed[2::3] = rows["up"][1::3], rows["none"][2::3]
    for kind, filtered in [*rows.items(), ("mixed", mixed)]:
        data = png_codecs.png_file(source, zlib.compress(filtered.tobytes(), 1))
        assert np.array_equal(opencv_rgb(data), source), (bits, kind)
        image = png_codecs.decode_png(data)
        if libraries != "absent":
            assert image.dtype == source.dtype and np.array_equal(image, source), kind
        else:
            assert image is None


def test_a_stream_of_the_wrong_length_or_checksum_goes_to_opencv(inflater):
    source = codes(8)
    rows = png_codecs.filtered_rows(source).tobytes()
    for stream in (zlib.compress(rows[:-5]), zlib.compress(rows + bytes(5)),
                   zlib.compress(rows)[:-1] + bytes([zlib.compress(rows)[-1] ^ 1])):
        assert png_codecs.decode_png(png_codecs.png_file(source, stream)) is None


def test_a_stream_inflating_past_its_header_is_never_inflated_whole(inflater):
    import tracemalloc

    source = codes(8, shape=(4, 4, 3))
    rows = png_codecs.filtered_rows(source).tobytes()
    bomb = png_codecs.png_file(source, zlib.compress(rows + bytes(64 << 20), 9))  # 64 MiB more
    assert len(bomb) < 100_000
    tracemalloc.start()
    try:
        assert png_codecs.decode_png(bomb) is None
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20  # the rows and one byte, not 64 MiB


@pytest.mark.parametrize("bits", [8, 16])
def test_generate_writes_the_same_pixels_in_either_mode(tmp_path, bits):
    from gpu_blur.cli import main

    photos = tmp_path / "in"
    photos.mkdir()
    for i in range(2):
        (photos / f"p{i}.png").write_bytes(png_codecs.encode_png(codes(8, (24, 32, 3), i)))
    made = {}
    for mode in png_codecs.PNG_MODES:
        scene = tmp_path / f"{mode}.toml"
        scene.write_text(f"[blur]\nsteps = 3\n[output]\nbits = {bits}\npng = '{mode}'\n")
        out = tmp_path / mode
        assert main(["generate", "--input", str(photos), "--output", str(out), "--scene",
                     str(scene), "--save", "mask", "--quiet"]) == 0
        made[mode] = {p.relative_to(out).as_posix(): p.read_bytes()
                      for p in sorted(out.rglob("*.png"))}
    fast = made["fast"]
    assert len(fast) == 6  # blur, sharp, mask of 2 samples
    for mode, files in made.items():
        assert sorted(files) == sorted(fast)
        assert all(files[name] == png_codecs.encode_png(opencv_rgb(files[name]), mode)
                   for name in files)  # written by that mode
        for name in fast:
            assert np.array_equal(opencv_rgb(fast[name]), opencv_rgb(files[name])), name
        assert mode == "fast" or any(fast[name] != files[name] for name in fast)


def in_idat_chunks(data, sizes):
    """``data`` (a file of one IDAT chunk) with its stream in chunks of these sizes, the
    rest in a last one."""
    kind, start, length = next(c for c in chunks(data) if c[0] == b"IDAT")
    stream, cuts = data[start + 8:start + 8 + length], [0]
    for size in sizes:
        cuts.append(min(cuts[-1] + size, length))
    cuts.append(length)
    parts = [png_codecs.chunk(b"IDAT", stream[a:b])
             for a, b in zip(cuts, cuts[1:], strict=False)]
    return data[:start] + b"".join(parts) + data[start + 12 + length:]


@pytest.mark.parametrize("layout", ["one", "even", "even, last empty", "uneven", "first empty"])
def test_an_idat_stream_in_any_chunks_decodes_to_its_source(layout, inflater):
    """Chunks of one size (as libpng and OpenCV write them) or of any others."""
    source = codes(8, (40, 60, 3), seed=3)
    data = png_codecs.encode_png(source, "fast")
    length = next(c for c in chunks(data) if c[0] == b"IDAT")[2]
    sizes = {"one": [], "even": [97] * (length // 97), "even, last empty": [length // 4] * 4,
             "uneven": [50, 97, 13, 200], "first empty": [0, 64, 64]}[layout]
    split = in_idat_chunks(data, sizes)
    parts = png_codecs._idat(split)[4]
    assert len(parts) == len(sizes) + 1 and len(split) == len(data) + 12 * len(sizes)
    assert b"".join(parts) == png_codecs._idat(data)[4][0]
    assert np.array_equal(png_codecs.decode_png(split), source)


def test_only_a_stored_idat_crc_damaged_decodes_to_the_intact_pixels(inflater):
    """png_codecs._idat checks the zlib stream's Adler-32, not each IDAT chunk's CRC."""
    source = codes(8)
    data = bytearray(png_codecs.encode_png(source, "fast"))
    kind, start, length = next(c for c in chunks(data) if c[0] == b"IDAT")
    data[start + 8 + length] ^= 0xFF  # the CRC's first byte; the pixels' bytes untouched
    assert np.array_equal(png_codecs.decode_png(bytes(data)), source)
    data[start + 12] ^= 0x01  # and now one byte of the stream itself
    assert png_codecs.decode_png(bytes(data)) is None


def test_beyond_isals_slots_decoding_goes_to_opencv(tmp_path, monkeypatch):
    """Through ISA-L decode_png decodes a few files at a time; read_image gives the rest to
    OpenCV. Through libdeflate there is no such limit."""
    use_inflater("isal", monkeypatch)
    source = codes(8)
    path = tmp_path / "in.png"
    path.write_bytes(png_codecs.encode_png(source, "fast"))
    taken = 0
    while png_codecs._ISAL_SLOTS.acquire(blocking=False):
        taken += 1
    try:
        assert taken >= 1 and png_codecs.decode_png(path.read_bytes()) is None
        assert np.array_equal(read_image(path), source)
        if INFLATERS["libdeflate"]() is not None:
            use_inflater("libdeflate", monkeypatch)
            assert np.array_equal(png_codecs.decode_png(path.read_bytes()), source)
    finally:
        for _ in range(taken):
            png_codecs._ISAL_SLOTS.release()


def test_encoded_images_encode_an_image_seen_before_once_with_the_same_bytes(monkeypatch):
    calls = []
    encode = file_writing.encode_image
    monkeypatch.setattr(file_writing, "encode_image", lambda *a: calls.append(1) or encode(*a))
    memo = file_writing.EncodedImages()
    a, b = codes(8, (24, 32, 3), seed=1), codes(8, (24, 32, 3), seed=2)
    first = memo.encode(a, 8)
    assert memo.encode(a.copy(), 8) == first == encode_image(a, 8) and len(calls) == 1
    assert memo.encode(a.astype(np.float32) / 255, 8) == first  # the same codes as floats
    assert memo.encode(b, 8) == encode_image(b, 8) and len(calls) == 2
    assert memo.encode(a, 8, png="stored") == encode_image(a, 8, png="stored")  # its own key
    assert memo.encode(a, 16) == encode_image(a, 16)  # other codes, another key
    assert memo.hits == 2 and len(calls) == 4


def test_encoded_images_keep_at_most_their_limit_and_pickle_empty():
    import pickle

    images = [codes(8, (24, 32, 3), seed=s) for s in range(3)]
    one = len(encode_image(images[0], 8))
    memo = file_writing.EncodedImages(limit=2 * one + one // 2)  # room for two such files
    for image in images:
        memo.encode(image, 8)
    memo.encode(images[2], 8)
    memo.encode(images[0], 8)  # the oldest was dropped: encoded again
    assert memo.hits == 1 and memo._held <= memo.limit and len(memo._files) == 2
    copy = pickle.loads(pickle.dumps(memo))
    assert (copy.limit, copy.hits, len(copy._files)) == (memo.limit, 0, 0)
