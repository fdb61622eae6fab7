"""PNG streams deflated on the device (gpu_blur.png_device) are zlib's, byte for byte.

On Warp's CPU device, against :func:`gpu_blur.png_codecs.huffman_zlib` of the same Sub-filtered
rows, for images that reach each branch of zlib's block writer: stored, fixed-code and
dynamic blocks, code lengths over 15 bits repaired, a stream that fills its last block to the
byte (so zlib ends it with an empty block), 1 to 4 channels, several images a call.
"""

import numpy as np
import pytest

from gpu_blur.png_codecs import filtered_rows, huffman_zlib

wp = pytest.importorskip("warp")

from gpu_blur.png_device import DeviceDeflate, blocks_of  # noqa: E402
from gpu_blur.warp_kernels import deflate  # noqa: E402

KINDS = {0: "stored", 1: "fixed", 2: "dynamic"}


@pytest.fixture(scope="module")
def encoder():
    wp.init()
    return DeviceDeflate("cpu")


def made(encoder, images: np.ndarray) -> tuple[list[bytes], set[str]]:
    """The streams of ``images`` (N x H x W [x C] uint8) and the kinds of block they hold."""
    n, h, w = images.shape[:3]
    channels = images.shape[3] if images.ndim == 4 else 1
    codes = wp.array(np.ascontiguousarray(images).reshape(-1), dtype=wp.uint8, device="cpu")
    streams = encoder.streams(codes, n, h, w, channels)
    blocks = n * blocks_of(h * (1 + w * channels))  # the rows of this call's blocks
    info = encoder._scratch[2]["info"].numpy()[:blocks]
    return streams, {KINDS[int(kind)] for kind in info[:, 0]}


def expected(image: np.ndarray) -> bytes:
    return huffman_zlib(filtered_rows(image))


def grey_row(differences: np.ndarray) -> np.ndarray:
    """A 1 x W grey image whose Sub-filtered row is ``[1, *differences]``."""
    return (np.cumsum(differences, dtype=np.int64) % 256).astype(np.uint8)[None, :]


def test_noisy_photo_rows_deflate_to_zlibs_bytes_in_dynamic_blocks(encoder):
    rng = np.random.default_rng(1)
    ramp = np.linspace(0, 200, 320)[None, :, None] + np.linspace(0, 40, 240)[:, None, None]
    image = np.clip(ramp + rng.normal(0, 4, (240, 320, 3)), 0, 255).astype(np.uint8)
    streams, kinds = made(encoder, image[None])
    assert blocks_of(240 * (1 + 320 * 3)) > 10
    assert kinds == {"dynamic"}
    assert streams[0] == expected(image)


def test_incompressible_rows_go_in_stored_blocks_as_zlib_stores_them(encoder):
    image = np.random.default_rng(2).integers(0, 256, (1, 90, 200, 3), dtype=np.uint8)
    streams, kinds = made(encoder, image)
    assert "stored" in kinds
    assert streams[0] == expected(image[0])


def test_a_few_bytes_take_the_fixed_codes_as_zlib_chooses(encoder):
    image = np.random.default_rng(4).integers(0, 144, (1, 1, 16), dtype=np.uint8)
    streams, kinds = made(encoder, image)
    assert kinds == {"fixed"}
    assert streams[0] == expected(image[0])


def test_codes_longer_than_15_bits_are_repaired_as_zlib_repairs_them(encoder):
    # counts 1, 1, 2, 3, 5, ... (Fibonacci; the 1s the row's filter byte and the end-of-block
    # code): an optimal code 18 bits deep, capped at 15
    fib = [1, 1]
    while len(fib) < 19:
        fib.append(fib[-1] + fib[-2])
    differences = np.repeat(np.arange(2, 19), fib[2:])
    np.random.default_rng(3).shuffle(differences)
    image = grey_row(differences)
    streams, kinds = made(encoder, image[None])
    lengths = encoder._scratch[2]["trees"][2].numpy()[0, :257]  # the literal tree's
    assert kinds == {"dynamic"} and lengths.max() == 15
    assert streams[0] == expected(image)


@pytest.mark.parametrize("literals", [deflate.BLOCK, 2 * deflate.BLOCK, deflate.BLOCK + 1])
def test_streams_ending_on_a_block_boundary_end_with_zlibs_empty_block(encoder, literals):
    differences = np.random.default_rng(literals).integers(0, 9, literals - 1)
    image = grey_row(differences)
    assert blocks_of(literals) == literals // deflate.BLOCK + 1
    streams, _ = made(encoder, image[None])
    assert streams[0] == expected(image)


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_images_of_each_channel_count_in_one_call_each_get_zlibs_stream(encoder, channels):
    rng = np.random.default_rng(channels)
    images = np.clip(rng.normal(100, 8, (3, 70, 130, channels)), 0, 255).astype(np.uint8)
    images[1] = 0  # a flat image: one byte value only
    images = images if channels > 1 else images[..., 0]
    streams, _ = made(encoder, images)
    for image, stream in zip(images, streams, strict=True):
        assert stream == expected(image)
    fewer, _ = made(encoder, images[2:])  # in the scratch of three
    assert fewer == streams[2:]


def test_a_failed_batchs_queued_streams_go_to_no_later_batch():
    from types import SimpleNamespace

    from gpu_blur.backends import OnDevice
    from gpu_blur.png_device import DevicePngs

    def lend(arrays):
        return [np.zeros(shape, dtype) for shape, dtype in arrays]

    pngs = DevicePngs(SimpleNamespace(wp_device="cpu"), lend)
    rng = np.random.default_rng(6)
    first, second = (rng.integers(0, 256, (2, 8, 10, 3), dtype=np.uint8) for _ in range(2))

    def on_device(images):
        return OnDevice(wp.array(images.reshape(-1), dtype=wp.uint8, device="cpu"),
                        images.shape, None, np.uint8)

    pngs.start()
    pngs.queue("blurred", on_device(first), 2)  # then the batch fails: never taken
    pngs.start()
    pngs.queue("blurred", on_device(second), 2)
    taken = pngs.take()
    assert [b"".join(sample["blurred"]) for sample in taken] == [expected(i) for i in second]


def test_random_images_of_many_sizes_and_noise_levels_deflate_to_zlibs_bytes(encoder):
    rng = np.random.default_rng(7)
    for _ in range(24):
        h, w, channels = int(rng.integers(1, 90)), int(rng.integers(1, 400)), int(
            rng.integers(1, 5))
        spread = float(rng.choice([0.3, 2, 10, 60, 200]))
        images = np.clip(rng.normal(rng.integers(0, 256), spread, (2, h, w, channels)), 0,
                         255).astype(np.uint8)
        images[:, :, ::3] = rng.integers(0, 256)  # runs of one value in every third column
        images = images if channels > 1 else images[..., 0]
        streams, _ = made(encoder, images)
        for image, stream in zip(images, streams, strict=True):
            assert stream == expected(image), (h, w, channels, spread)
