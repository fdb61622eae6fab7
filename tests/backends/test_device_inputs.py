"""Input images on the device: the checks' counts and the sharp reference, on every kernel backend.

``KernelBackend.inspect`` against numpy's counts of the same stored values, and
``KernelBackend.render_sharp`` against the host's float64 render (gpu_blur.synthesis.host), under
the tolerance table.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS, spec_backend, spec_dtype

from gpu_blur.backends import OnDevice, get_backend
from gpu_blur.backends.kernel import INSPECT_COLUMNS, INSPECT_ITEMS, Arg
from gpu_blur.cameras import scene_camera
from gpu_blur.image_arrays import unit_values
from gpu_blur.kernel_constants import INSPECT_LOADS
from gpu_blur.planning import StageName as S
from gpu_blur.planning import plan
from gpu_blur.reference.output import quantize
from gpu_blur.scene import load_scene, scene_from_dict
from gpu_blur.synthesis.host import _render_values, render_sharp
from gpu_blur.testing import assert_close, tolerance
from gpu_blur.tiling import Region

CODES = (np.dtype(np.uint8), np.dtype(np.uint16))


def backend_of(spec: str):
    name, _, precision = spec.partition("/")
    return get_backend(name, precision)


def stored(backend, image: np.ndarray) -> OnDevice:
    """``image`` on the backend's device as an input is stored: codes as they are, floats in the
    compute type."""
    codes = image.dtype in CODES
    data = backend._upload(image, image.dtype if codes else backend.np_real)
    return OnDevice(data, image.shape, backend._fetch, image.dtype if codes else None)


def numpy_counts(values: np.ndarray) -> list[int]:
    """INSPECT_COLUMNS counted by numpy on the values as stored."""
    if values.dtype in CODES:
        top = np.iinfo(values.dtype).max
        return [0, 0, 0, 0, np.count_nonzero(values == top), np.count_nonzero(values > 0)]
    return [np.count_nonzero(f(values)) for f in (
        np.isnan, np.isinf, lambda v: v < 0, lambda v: v > 1, lambda v: v >= 1,
        lambda v: v > 0)]


def planted_images(real) -> list[np.ndarray]:
    """Images with NaN, infinities, negatives, values above 1, the clip level and zeros planted
    at scattered places; sizes that are no multiple of anything, two above what the work items
    of one inspect launch load in their first round (INSPECT_LOADS x INSPECT_ITEMS)."""
    rng = np.random.default_rng(5)
    floats = rng.random((307, 293, 3)).astype(real)  # 269,853 values
    flat = floats.reshape(-1)
    planted = [(np.nan, 3), (np.inf, 2), (-np.inf, 1), (-0.25, 4), (-1e-30, 1), (1.5, 2),
               (np.nextafter(real(1), real(2)), 1), (1.0, 5), (-0.0, 3), (0.0, 2)]
    spots = iter(rng.permutation(flat.size))
    for value, times in planted:
        for _ in range(times):
            flat[next(spots)] = value
    codes8 = rng.integers(0, 255, (300, 301, 3), np.uint8)  # 270,900 values > INSPECT_ITEMS
    codes8.reshape(-1)[rng.permutation(codes8.size)[:17]] = 255
    codes16 = rng.integers(0, 65535, (37, 29, 3), np.uint16)
    codes16.reshape(-1)[rng.permutation(codes16.size)[:9]] = 65535
    codes16.reshape(-1)[:4] = 255  # the 8-bit top is no clip level in 16 bits
    mask = np.zeros((19, 23, 3), real)
    mask[3, 4, 1], mask[18, 0, 2] = 0.5, 1e-30  # positive, below the clip level
    return [floats, codes8, codes16, mask, np.zeros((2, 3, 3), np.uint8)]


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_inspect_counts_equal_numpy_counts(spec):
    backend = backend_of(spec)
    images = planted_images(backend.np_real)
    assert min(images[0].size, images[1].size) > INSPECT_LOADS * INSPECT_ITEMS
    counts = backend.inspect([stored(backend, x) for x in images])
    assert counts.dtype == np.int64 and counts.shape == (len(images), len(INSPECT_COLUMNS))
    np.testing.assert_array_equal(counts, [numpy_counts(x) for x in images])
    assert backend.inspect([]).shape == (0, len(INSPECT_COLUMNS))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_queued_inspects_read_in_any_order_each_give_their_own_counts(spec):
    # counts come back in pinned words kept across calls: a second inspect queued before the
    # first is read gets words of its own; one dropped unread gives the kept words back
    backend = backend_of(spec)
    images = planted_images(backend.np_real)
    on_device = [stored(backend, x) for x in images]
    made = []
    pinned = backend.pinned
    backend.pinned = lambda *a: made.append(a) or pinned(*a)
    first = backend.inspect_queued(on_device[:2])
    second = backend.inspect_queued(on_device[2:])
    np.testing.assert_array_equal(second(), [numpy_counts(x) for x in images[2:]])
    np.testing.assert_array_equal(first(), [numpy_counts(x) for x in images[:2]])
    kept = len(made)
    backend.inspect_queued(on_device[:1])  # dropped unread
    np.testing.assert_array_equal(backend.inspect(on_device[1:2]), [numpy_counts(images[1])])
    assert len(made) == kept  # the kept words served both


@pytest.mark.parametrize("spec", [s for s in KERNEL_BACKEND_SPECS if s.startswith("warp")])
@pytest.mark.parametrize("limit", ["int32", "below the span"])
def test_images_spaced_in_one_buffer_each_give_their_own_counts(spec, limit, monkeypatch):
    # evenly spaced images are inspected in one launch through one view over all of them;
    # where that view would pass the kernels' int32 indices (two separate allocations far
    # apart look evenly spaced too), each image is inspected on its own
    import gpu_blur.backends.warp as warp_backend

    backend = backend_of(spec)
    rng = np.random.default_rng(9)
    images = rng.random((3, 17, 19, 3)).astype(backend.np_real)
    images[1, 4, 5, 2], images[2, 0, 0, 0], images[2, 16, 18, 1] = np.nan, -0.5, 1.5
    stack = stored(backend, images)
    frames = [backend.frame(stack, i) for i in range(3)]
    if limit != "int32":
        monkeypatch.setattr(warp_backend, "MAX_BUFFER_VALUES", 2 * images[0].size)
    assert (backend.spaced(frames) is None) == (limit != "int32")
    np.testing.assert_array_equal(backend.inspect(frames), [numpy_counts(x) for x in images])


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_device_codes_are_to_integers_codes_of_every_value(spec, bits):
    # every code as the finish pass stores it (code / top in the compute type), random
    # values, values outside [0, 1], and in float32 values next to the rounding boundaries
    # (k + 1/2) / top (a float64 build rounds those exactly, where to_integers's own float64
    # arithmetic may not: no quantized output lies there)
    from gpu_blur.reference.output import to_integers

    backend = backend_of(spec)
    real = backend.np_real
    top = 2**bits - 1
    boundaries = ((np.arange(top) + 0.5) / top).astype(real)
    near = ([boundaries, np.nextafter(boundaries, real(0)), np.nextafter(boundaries, real(1))]
            if real == np.float32 else [])
    values = np.concatenate([
        (np.arange(top + 1) / top).astype(real), *near,
        np.random.default_rng(6).random(4099).astype(real),
        np.array([-0.25, -0.0, 1.5, 2.0], real)])
    values = values[:values.size // 3 * 3].reshape(-1, 1, 3)
    on_device = OnDevice(backend._upload(values, real), values.shape, backend._fetch)
    made = backend.to_codes(on_device, bits)
    assert made.dtype == (np.uint8 if bits == 8 else np.uint16)
    np.testing.assert_array_equal(made.numpy(made.dtype), to_integers(values, bits))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_inspect_counts_carry_into_their_high_word(spec):
    # a count of 2^32 or more (an image of 4 G values) needs the high word: start the clip
    # column 3 below 2^32 and add 10 counts
    backend = backend_of(spec)
    image = np.zeros((2, 5, 3), np.uint8)
    image.reshape(-1)[:10] = 255
    words = np.zeros((len(INSPECT_COLUMNS), 2), np.uint32)
    clip = INSPECT_COLUMNS.index("clip_level")
    words[clip, 0] = 2**32 - 3
    counts = backend._zeros(words.size, np.uint32)
    backend._write(counts, words.reshape(-1))
    with backend._timed():
        backend._launch(backend._input_kernels(None, np.uint8), "inspect", (1, 4),
                        stored(backend, image).data, Arg("index", image.size), Arg("index", 4),
                        counts, Arg("index", 0), Arg("index", 0))
    got = OnDevice(counts, words.shape, backend._fetch, np.uint32).numpy(np.int64)
    assert got[clip].tolist() == [7, 1]


#: Finish configurations: the example scenes' (realblur_j: A7R3 polynomial, float output;
#: rsblur and minimal: sRGB, 8 bits) and their neighbours (lookup table, tone off, 0 / 8 bits).
OUTPUTS = {
    "realblur_j": {"crf": "a7r3", "bits": 0},
    "polynomial_8": {"crf": "a7r3", "bits": 8},
    "polynomial_fast": {"crf": "a7r3", "bits": 0, "fast_math": True},
    "lookup_0": {"crf": "a7r3-lut", "bits": 0},
    "lookup_8": {"crf": "a7r3-lut", "bits": 8},
    "rsblur": {"crf": "srgb", "bits": 8},
    "srgb_0": {"crf": "srgb", "bits": 0},
    "linear_0": {"crf": "none", "bits": 0},
    "linear_8": {"crf": "none", "bits": 8},
}


def host_render(sample_plan, camera, image: np.ndarray) -> np.ndarray:
    """The host's float64 sharp reference (synthesis.host.render_sharp before its float32 cast)."""
    values = _render_values(sample_plan, camera, unit_values(image))
    if sample_plan.kept(S.QUANTIZE):
        values = quantize(values, sample_plan[S.QUANTIZE].options["bits"])
    return values


def sharp_photo(coffee_rgb, dtype, real) -> np.ndarray:
    """A 40 x 52 crop of the coffee photo with its clipped highlights, as ``dtype``; floats
    already rounded to the compute type ``real``."""
    crop = coffee_rgb[230:270, 340:392]
    if dtype == np.uint8:
        return np.rint(crop * 255).astype(np.uint8)
    if dtype == np.uint16:  # 16-bit codes between the 8-bit ones
        noise = np.random.default_rng(2).integers(0, 257, crop.shape)
        return np.clip(np.rint(crop * 65535) - noise, 0, 65535).astype(np.uint16)
    return crop.astype(real).astype(np.float64)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("source", ["uint8", "uint16", "float"])
@pytest.mark.parametrize("output", list(OUTPUTS))
def test_render_sharp_matches_the_host_render(spec, source, output, coffee_rgb):
    backend = backend_of(spec)
    scene = scene_from_dict({"output": {**OUTPUTS[output], "crop": 4}})
    image = sharp_photo(coffee_rgb, np.dtype(source) if source != "float" else None,
                        backend.np_real)
    h, w = image.shape[:2]
    sample_plan = plan(scene, saturated=True, size=(h, w))
    camera = scene_camera(scene, backend.name)
    out = Region(4, 4, h - 8, w - 8, h, w)
    got = backend.render_sharp(sample_plan, camera, stored(backend, image), out).numpy()
    ref = host_render(sample_plan, camera, out.of(image))
    dtype = spec_dtype(spec)
    if scene.output.fast_math and dtype == "float32":
        dtype = "float32-fast"
    if sample_plan.kept(S.QUANTIZE):
        # float32 rounding can move a value across a rounding boundary: one code at most, on
        # few values (finish's rule, tests/backends/test_backends.py)
        top = 2 ** sample_plan[S.QUANTIZE].options["bits"] - 1
        codes = np.abs(np.rint(got * top) - np.rint(ref * top))
        _, allowed = tolerance("quantize_code_changes", spec_backend(spec), dtype)
        assert codes.max() <= 1 and (codes > 0).mean() <= allowed, (codes > 0).mean()
    elif sample_plan.retone_curve:
        stage = "finish_crf_polynomial" if sample_plan.retone_curve == "polynomial" else "finish"
        assert_close(got, ref, stage, spec_backend(spec), dtype)
    elif sample_plan.kept(S.TONE):  # the stored sRGB values themselves
        np.testing.assert_array_equal(got, ref.astype(backend.np_real))
    else:  # linearize's EOTF (accumulate, blur mode none) of the stored values
        assert_close(got, ref, "accumulate", spec_backend(spec), dtype)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_render_sharp_of_8_bit_codes_to_8_bits_is_the_codes_themselves(spec, coffee_rgb):
    backend = backend_of(spec)
    scene = load_scene("rsblur")  # sRGB output, 8 bits, crop 4
    image = sharp_photo(coffee_rgb, np.uint8, None)
    h, w = image.shape[:2]
    sample_plan = plan(scene, saturated=True, size=(h, w))
    camera = scene_camera(scene, backend.name)
    c = scene.output.crop
    out = Region(c, c, h - 2 * c, w - 2 * c, h, w)
    got = backend.render_sharp(sample_plan, camera, stored(backend, image), out).numpy(
        backend.np_real)
    real = backend.np_real
    np.testing.assert_array_equal(got, out.of(image).astype(real) / real(255))
    if real == np.float32:  # what synthesize returns today, bit for bit
        np.testing.assert_array_equal(got, render_sharp(sample_plan, camera, out.of(image)))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS[:1])
def test_render_sharp_refuses_a_region_outside_the_image(spec):
    backend = backend_of(spec)
    scene = load_scene("rsblur")
    image = np.zeros((10, 12, 3), np.uint8)
    sample_plan = plan(scene, saturated=True, size=(10, 12))
    with pytest.raises(ValueError, match=r"region 4 x 8 at \(row 7, column 0\) does not lie "
                                         r"within the 10 x 12 image"):
        backend.render_sharp(sample_plan, scene_camera(scene, backend.name),
                             stored(backend, image), Region(7, 0, 4, 8, 10, 12))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS[:1])
def test_inspect_refuses_an_image_of_another_dtype(spec):
    backend = backend_of(spec)
    image = np.zeros((4, 5, 3), np.float16)
    data = OnDevice(backend._upload(image, np.float16), image.shape, backend._fetch, np.float16)
    with pytest.raises(ValueError, match="holds float16 values; the kernels read uint8, uint16 "
                                         "or float"):
        backend.inspect([data])
