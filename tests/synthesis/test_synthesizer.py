"""The batch API: gpu_blur.Synthesizer against synthesize, array types, layouts, bad input."""

import dataclasses
import re

import numpy as np
import pytest
import torch
from conftest import BACKEND_SPECS, KERNEL_BACKEND_SPECS

import gpu_blur
from gpu_blur.scene import scene_from_dict

H, W = 36, 34


def scene_for(mode: str, **output):
    if mode == "none":
        return gpu_blur.load_scene("realblur_j")
    data = {"blur": {"mode": mode}, "saturation": {"mode": "auto"}, "output": output}
    if mode == "average":
        data["blur"]["frames"] = 3
    if mode == "kernel":
        data["blur"]["kernel_size"] = [3, 5]
    return scene_from_dict(data)


def batch_for(mode: str, count: int, rng, dtype=np.uint8) -> dict:
    """A batch for ``mode``: uint8 codes (with clipped pixels) or floats in [0, 1]."""
    shape = (count, 3, H, W, 3) if mode == "average" else (count, H, W, 3)
    codes = rng.integers(0, 256, size=shape, dtype=np.uint8)
    codes[0, ..., 2, 3, :] = 255  # the first sample reaches the clip level, the rest need not
    images = codes if dtype == np.uint8 else (codes / 255.0).astype(dtype)
    if mode != "none":
        return {"batch": images}
    mask = (rng.random((count, H, W, 3)) < 0.1).astype(dtype)
    return {"batch": images, "mask": mask}


def one_sample(mode: str, given: dict, b: int):
    if mode == "average":
        return list(given["batch"][b])
    if mode == "none":
        return {"blurred": given["batch"][b], "mask": given["mask"][b]}
    return given["batch"][b]


def spec_parts(spec: str):
    name, _, precision = spec.partition("/")
    return name, precision or "float64"


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("mode", ["average", "kernel", "trajectory", "none"])
def test_a_batch_equals_synthesize_sample_by_sample_bit_for_bit(spec, mode):
    name, precision = spec_parts(spec)
    scene = scene_for(mode, precision=precision)
    given = batch_for(mode, 3, np.random.default_rng(1))
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=7, with_mask=True)
    out = synth(given["batch"], mask=given.get("mask"), first_index=5)
    assert out.blurred.shape == out.sharp.shape == out.mask.shape
    for b in range(3):
        one = gpu_blur.synthesize(one_sample(mode, given, b), scene, seed=7, sample_index=5 + b,
                                  backend=name)
        assert np.array_equal(out.blurred[b], one.blurred), b
        assert np.array_equal(out.sharp[b], one.sharp), b
        assert np.array_equal(out.mask[b], one.mask), b
        assert out.params[b].keys() == one.params.keys()
        assert out.plans[b] == one.plan


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("output", [{"bits": 8}, {"bits": 16},
                                    {"bits": 8, "jpeg_quality": [60, 90]},
                                    {"bits": 8, "tile": True}])
def test_codes_are_the_integers_of_the_float_results(spec, output):
    # made on the device where the sample runs there; after the JPEG stage, and in tiles,
    # on the host: to_integers of the float results either way
    from gpu_blur.reference.output import to_integers

    name, precision = spec_parts(spec)
    output = dict(output)
    tile = (16, 16) if output.pop("tile", False) else None
    scene = scene_for("trajectory", precision=precision, **output)
    photo = batch_for("trajectory", 1, np.random.default_rng(18))["batch"][0]
    floats = gpu_blur.synthesize(photo, scene, seed=4, sample_index=3, backend=name, tile=tile)
    codes = gpu_blur.synthesize(photo, scene, seed=4, sample_index=3, backend=name, tile=tile,
                                codes=True)
    for key in ("blurred", "sharp"):
        want = to_integers(getattr(floats, key), output["bits"])
        assert getattr(codes, key).dtype == want.dtype
        assert np.array_equal(getattr(codes, key), want), key


def six_stacks(spec: str, streamed: bool, monkeypatch, data_seed: int, options: dict,
               **output):
    """A Synthesizer of blur mode average on ``spec`` and a batch of 6 stacks of uint8 frames.

    ``streamed``: any pinned batch of codes goes in parts (STREAMED_BYTES 0).
    """
    import gpu_blur.synthesis.resident

    if streamed:
        monkeypatch.setattr(gpu_blur.synthesis.resident, "STREAMED_BYTES", 0)
    name, precision = spec_parts(spec)
    scene = scene_for("average", precision=precision, **output)
    frames = batch_for("average", 6, np.random.default_rng(data_seed))["batch"]
    return gpu_blur.Synthesizer(scene, backend=name, **options), frames


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("output", [{"bits": 8}, {"bits": 16},
                                    {"bits": 8, "jpeg_quality": [60, 90]}])
def test_a_batchs_codes_equal_synthesizes_codes_sample_by_sample(spec, output):
    # made on the device for the whole batch where it runs there, after the JPEG stage on
    # the host; the mask stays float32
    name, precision = spec_parts(spec)
    scene = scene_for("kernel", precision=precision, **output)
    photos = batch_for("kernel", 3, np.random.default_rng(22))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=6, with_mask=True)
    got = synth(photos, first_index=4, codes=True)
    floats = synth(photos, first_index=4)
    assert got.mask.dtype == np.float32 and np.array_equal(got.mask, floats.mask)
    for b in range(3):
        one = gpu_blur.synthesize(photos[b], scene, seed=6, sample_index=4 + b, backend=name,
                                  codes=True)
        for key in ("blurred", "sharp"):
            assert getattr(got, key).dtype == getattr(one, key).dtype
            assert np.array_equal(getattr(got, key)[b], getattr(one, key)), (b, key)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("streamed", [False, True])
def test_codes_go_into_out_arrays_in_pinned_memory_without_staging(spec, streamed,
                                                                   monkeypatch):
    # uint8 out= arrays in the backend's pinned memory take the codes straight from the
    # device, in parts when the batch streams; plain arrays the same codes through staging
    synth, frames = six_stacks(spec, streamed, monkeypatch, 23, {"seed": 2}, bits=8)
    name = spec_parts(spec)[0]
    plain = synth(frames, codes=True)
    held = synth.pinned(frames.shape, np.uint8)
    held[...] = frames
    out = [synth.pinned(plain.blurred.shape, np.uint8) for _ in range(2)]
    seen = []  # OpenCL: staging buffers asked for; Warp: host arrays copied into directly
    spied = "_host_view" if name.startswith("warp") else "_staging_buffer"
    real = getattr(synth.runner, spied)
    monkeypatch.setattr(synth.runner, spied, lambda x, *a: seen.append(x) or real(x, *a))
    got = synth(held, out=out, codes=True)
    assert got.blurred is out[0] and got.sharp is out[1]
    assert np.array_equal(out[0], plain.blurred) and np.array_equal(out[1], plain.sharp)
    if spied == "_host_view":
        copied = {x.ctypes.data for x in seen}
        step = gpu_blur.synthesis.resident.STREAMED_SAMPLES if streamed else 6  # each part's start
        assert all(o[b].ctypes.data in copied for o in out for b in range(0, 6, step))
    else:
        assert seen == []
    mine = [np.zeros_like(plain.blurred) for _ in range(2)]
    synth(frames, out=mine, codes=True)
    assert np.array_equal(mine[0], plain.blurred) and np.array_equal(mine[1], plain.sharp)


@pytest.mark.parametrize("name", ["warp:cpu", "opencl"])
def test_codes_fetched_at_once_reuse_one_device_buffer(name, monkeypatch):
    # a new device buffer for each batch's codes costs more than their download on a GPU:
    # host-bound codes are made in a kept buffer; a device batch's codes are new arrays
    scene = scene_for("kernel", precision="float32", bits=8)
    photos = batch_for("kernel", 3, np.random.default_rng(26))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=1)
    buffers = []
    to_codes = synth.runner.to_codes
    monkeypatch.setattr(synth.runner, "to_codes",
                        lambda values, bits, into=None: buffers.append(into)
                        or to_codes(values, bits, into))
    first = synth(photos, codes=True)
    again = synth(photos, codes=True)
    one = synth.sample(photos[0], codes=True)
    assert len(buffers) == 6 and all(b is not None for b in buffers)
    assert all(b is buffers[0] for b in buffers[:4])  # blurred and sharp, both batches
    assert np.array_equal(again.blurred, first.blurred)
    assert np.array_equal(again.sharp, first.sharp)
    assert np.array_equal(one.blurred, first.blurred[0])
    if name == "warp:cpu":  # a batch on the Warp device: its codes are new device arrays
        import warp as wp

        handed = synth(wp.array(photos, device="cpu"), codes=True)
        assert buffers[6] is None and buffers[7] is None
        assert np.array_equal(handed.blurred.numpy(), first.blurred)


@pytest.mark.parametrize("name", ["warp:cpu", "opencl", "numpy"])
def test_codes_of_a_torch_batch_come_back_as_torch_codes(name):
    scene = scene_for("kernel", precision="float32", bits=16)
    photos = batch_for("kernel", 2, np.random.default_rng(24))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=1, channels_first=True)
    first = np.ascontiguousarray(photos.transpose(0, 3, 1, 2))
    plain = synth(first, codes=True)
    got = synth(torch.from_numpy(first), codes=True)
    assert got.blurred.dtype == torch.uint16 and got.blurred.shape == plain.blurred.shape
    assert np.array_equal(got.blurred.numpy(), plain.blurred)
    assert np.array_equal(got.sharp.numpy(), plain.sharp)


def test_a_batchs_codes_need_8_or_16_bits_and_out_arrays_of_their_dtype():
    photos = batch_for("kernel", 2, np.random.default_rng(25))["batch"]
    with pytest.raises(ValueError, match=r"codes=True .* output.bits = 0"):
        gpu_blur.Synthesizer(scene_for("kernel", bits=0), backend="numpy")(photos, codes=True)
    synth = gpu_blur.Synthesizer(scene_for("kernel", bits=8), backend="warp:cpu")
    shape = synth(photos).blurred.shape
    with pytest.raises(ValueError, match=re.escape("out= blurred: needs a writeable uint8")):
        synth(photos, out=[np.zeros(shape, np.float32)] * 2, codes=True)


def test_codes_need_an_output_of_8_or_16_bits():
    photo = batch_for("kernel", 1, np.random.default_rng(19))["batch"][0]
    with pytest.raises(ValueError, match=r"codes=True .* output.bits = 0"):
        gpu_blur.synthesize(photo, scene_for("kernel", bits=0), codes=True)


@pytest.mark.parametrize("name", ["warp:cpu", "opencl", "numpy"])
def test_numpy_torch_and_warp_batches_give_the_same_bits_and_come_back_as_they_came(name):
    import warp as wp

    scene = scene_for("none", precision="float32")
    given = batch_for("none", 2, np.random.default_rng(2), dtype=np.float32)
    synth = gpu_blur.Synthesizer(scene, backend=name)
    ref = synth(given["batch"], mask=given["mask"])
    as_torch = synth(torch.from_numpy(given["batch"]), mask=torch.from_numpy(given["mask"]))
    assert isinstance(as_torch.blurred, torch.Tensor) and as_torch.blurred.device.type == "cpu"
    assert np.array_equal(as_torch.blurred.numpy(), ref.blurred)
    assert np.array_equal(as_torch.sharp.numpy(), ref.sharp)
    as_warp = synth(wp.array(given["batch"], device="cpu"),
                    mask=wp.array(given["mask"], device="cpu"))
    assert isinstance(as_warp.blurred, wp.array)
    assert np.array_equal(as_warp.blurred.numpy(), ref.blurred)


def test_channels_first_batches_come_back_channels_first():
    scene = scene_for("trajectory", precision="float32")
    photos = batch_for("trajectory", 2, np.random.default_rng(3))["batch"]
    last = gpu_blur.Synthesizer(scene, backend="warp:cpu")(torch.from_numpy(photos))
    first = gpu_blur.Synthesizer(scene, backend="warp:cpu", channels_first=True)(
        torch.from_numpy(photos).permute(0, 3, 1, 2))
    assert first.blurred.shape == (2, 3, H, W)
    assert torch.equal(first.blurred.permute(0, 2, 3, 1), last.blurred)


@pytest.mark.parametrize("name", ["numpy", "opencl", "warp:cpu"])
def test_float16_and_float64_batches_give_what_their_float32_values_give(name):
    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 2, np.random.default_rng(4), dtype=np.float16)["batch"]
    synth = gpu_blur.Synthesizer(scene, backend=name)
    half = synth(photos)
    single = synth(photos.astype(np.float32))
    assert np.array_equal(half.blurred, single.blurred)
    assert np.array_equal(synth(photos.astype(np.float64)).blurred, single.blurred)


@pytest.mark.parametrize("name", ["numpy", "opencl", "warp:cpu"])
@pytest.mark.parametrize("bad, words", [(np.nan, "1 NaN and 0 infinite value(s)"),
                                        (-0.5, "1 negative value(s), the lowest -0.5"),
                                        (3.0, "1 value(s) above 1, the highest 3")])
def test_a_bad_value_names_its_sample_and_where_it_is(name, bad, words):
    scene = scene_for("average", precision="float32")
    frames = batch_for("average", 3, np.random.default_rng(5), dtype=np.float32)["batch"]
    frames[1, 2, 4, 5, 1] = bad
    with pytest.raises(ValueError) as e:
        gpu_blur.Synthesizer(scene, backend=name)(frames)
    assert str(e.value).startswith("sample 1 of 3: frame 2: " + words)
    assert "row 4, column 5, channel 1" in str(e.value)


@pytest.mark.parametrize("name", ["numpy", "opencl", "warp:cpu"])
def test_a_bad_value_leaves_out_arrays_untouched_and_the_next_batch_whole(name):
    """Kernel backends read their input checks back after queueing the batch's passes; a bad
    value still raises before any result leaves: out= arrays keep what they held, and the next
    batch (on the buffers the failed one used) equals a fresh Synthesizer's."""
    scene = scene_for("none", precision="float32")
    given = batch_for("none", 2, np.random.default_rng(7), dtype=np.float32)
    fresh = gpu_blur.Synthesizer(scene, backend=name)(given["batch"], mask=given["mask"])
    synth = gpu_blur.Synthesizer(scene, backend=name)
    out = [np.full(fresh.blurred.shape, 7.0, np.float32) for _ in range(2)]
    mask = given["mask"].copy()
    mask[1, 3, 4, 0] = np.inf
    with pytest.raises(ValueError, match="sample 1 of 2: mask: 0 NaN and 1 infinite"):
        synth(given["batch"], mask=mask, out=out)
    assert all(np.all(o == 7.0) for o in out)
    again = synth(given["batch"], mask=given["mask"], out=out)
    assert np.array_equal(again.blurred, fresh.blurred)
    assert np.array_equal(again.sharp, fresh.sharp)


def test_a_mask_of_another_shape_or_type_is_refused_by_name():
    scene = scene_for("none")
    given = batch_for("none", 2, np.random.default_rng(6))
    synth = gpu_blur.Synthesizer(scene)
    with pytest.raises(ValueError, match=r"mask has shape \(2, 20, 34, 3\) but the batch"):
        synth(given["batch"], mask=given["mask"][:, :20])
    with pytest.raises(ValueError, match="mask is a torch array but the batch is numpy"):
        synth(given["batch"], mask=torch.from_numpy(given["mask"]))
    with pytest.raises(ValueError, match="takes B x H x W x 3 batches; got shape"):
        synth(given["batch"][0])
    with pytest.raises(ValueError, match=r"input of \(1, 34\) is too small for the Bayer"):
        synth(given["batch"][:, :1], mask=given["mask"][:, :1])
    with pytest.raises(ValueError, match="call once per size for mixed sizes"):
        synth([given["batch"][0], given["batch"][1, :20]])
    with pytest.raises(ValueError, match="mask= is for blur.mode = none"):
        gpu_blur.Synthesizer(scene_for("kernel"))(given["batch"], mask=given["mask"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (run on the GPU "
                    "machine; CI has none)")
@pytest.mark.parametrize("dtype", [np.float32, np.uint8, np.uint16])
@pytest.mark.parametrize("mode", ["average", "none"])
def test_cuda_tensors_stay_on_the_gpu_and_give_what_host_arrays_give(mode, dtype):
    scene = scene_for(mode, precision="float32")
    given = batch_for(mode, 2, np.random.default_rng(7), dtype=np.float32)
    if dtype != np.float32:
        top = np.iinfo(dtype).max
        given = {k: np.round(v * top).astype(dtype) for k, v in given.items()}
    synth = gpu_blur.Synthesizer(scene, backend="warp:cuda:0", with_mask=True)
    host = synth(given["batch"], mask=given.get("mask"))
    cuda = synth(torch.from_numpy(given["batch"]).cuda(),
                 mask=None if mode != "none" else torch.from_numpy(given["mask"]).cuda())
    for name in ("blurred", "sharp", "mask"):
        tensor = getattr(cuda, name)
        assert tensor.is_cuda
        assert np.array_equal(tensor.cpu().numpy(), getattr(host, name)), name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (run on the GPU "
                    "machine; CI has none)")
def test_cupy_arrays_come_back_as_cupy_arrays_on_the_gpu():
    cupy = pytest.importorskip("cupy")
    scene = scene_for("trajectory", precision="float32")
    photos = batch_for("trajectory", 2, np.random.default_rng(9))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="warp:cuda:0")
    out = synth(cupy.asarray(photos))
    assert isinstance(out.blurred, cupy.ndarray)
    assert np.array_equal(cupy.asnumpy(out.blurred), synth(photos).blurred)


@pytest.mark.parametrize("spec", [s for s in BACKEND_SPECS if s != "numpy"])
@pytest.mark.parametrize("mode, dtype", [("average", np.float32), ("trajectory", np.float32),
                                         ("none", np.float32), ("none", np.uint8)])
def test_device_resident_runs_equal_runs_from_host_memory_in_tiles(spec, mode, dtype):
    """Inputs put on the device (no tile) and streamed from the host in tiles: same bits.

    A uint8 mask is divided on the device (unit_values) and on the host (image_arrays.unit_values).
    """
    name, precision = spec_parts(spec)
    scene = scene_for(mode, precision=precision)
    given = batch_for(mode, 1, np.random.default_rng(8), dtype=dtype)
    inputs = one_sample(mode, given, 0)
    whole = gpu_blur.synthesize(inputs, scene, seed=3, backend=name)
    tiled = gpu_blur.synthesize(inputs, scene, seed=3, backend=name, tile=(16, 20))
    assert tiled.tiles > 1
    for key in ("blurred", "sharp", "mask"):
        assert np.array_equal(getattr(whole, key), getattr(tiled, key)), key


def test_indices_in_any_order_give_those_samples():
    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 3, np.random.default_rng(10))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=2)
    shuffled = synth(photos, indices=[7, 2, 40])
    for b, index in enumerate([7, 2, 40]):
        one = gpu_blur.synthesize(photos[b], scene, seed=2, sample_index=index,
                                  backend="warp:cpu")
        assert np.array_equal(shuffled.blurred[b], one.blurred)
    with pytest.raises(ValueError, match="indices: 2 sample indices for a batch of 3"):
        synth(photos, indices=[1, 2])


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_out_arrays_receive_the_batch_and_are_what_comes_back(spec):
    name, precision = spec_parts(spec)
    scene = scene_for("none", precision=precision)
    given = batch_for("none", 2, np.random.default_rng(5), dtype=np.float32)
    synth = gpu_blur.Synthesizer(scene, backend=name, with_mask=True)
    ref = synth(given["batch"], mask=given["mask"])
    out = [np.full(ref.blurred.shape, np.nan, np.float32) for _ in range(3)]
    got = synth(given["batch"], mask=given["mask"], out=out)
    assert got.blurred is out[0] and got.sharp is out[1] and got.mask is out[2]
    for mine, want in zip(out, (ref.blurred, ref.sharp, ref.mask), strict=True):
        assert np.array_equal(mine, want)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_channels_first_out_arrays_take_channels_first_results(spec):
    name, precision = spec_parts(spec)
    scene = scene_for("trajectory", precision=precision)
    photos = batch_for("trajectory", 2, np.random.default_rng(3))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend=name, channels_first=True)
    first = np.ascontiguousarray(photos.transpose(0, 3, 1, 2))
    ref = synth(first)
    out = [np.zeros(ref.blurred.shape, np.float32) for _ in range(2)]
    synth(first, out=out)
    assert np.array_equal(out[0], ref.blurred) and np.array_equal(out[1], ref.sharp)


@pytest.mark.parametrize("mode, size, channels_first", [
    ("average", (H, W), False), ("none", (H - 1, W + 3), False), ("kernel", (H, W), True)])
def test_result_shape_and_dtypes_are_those_of_the_results_out_arrays_take(mode, size,
                                                                         channels_first):
    scene = scene_for(mode, precision="float32")  # realblur_j for none: RAW round trip, crop 4
    given = batch_for(mode, 2, np.random.default_rng(6))
    given = {k: v[..., :size[0], :size[1], :] for k, v in given.items()}  # odd sides too
    if channels_first:
        given = {k: np.ascontiguousarray(np.moveaxis(v, -1, -3)) for k, v in given.items()}
    synth = gpu_blur.Synthesizer(scene, backend="numpy", channels_first=channels_first,
                                 with_mask=True)
    for codes in (False, True) if scene.output.bits else (False,):  # realblur_j: floats
        got = synth(**given, codes=codes)
        results = [got.blurred, got.sharp, got.mask]
        assert {r.shape for r in results} == {synth.result_shape(given["batch"].shape)}
        assert [r.dtype for r in results] == synth.result_dtypes(codes)


@pytest.mark.parametrize("bad, words", [
    (lambda shape: [np.zeros(shape, np.float32)], "out= takes 2 arrays, (blurred, sharp)"),
    (lambda shape: [np.zeros(shape, np.float64)] * 2, "needs a writeable float32 numpy"),
    (lambda shape: [np.zeros(shape[1:], np.float32)] * 2, "of shape (2, 36, 34, 3)"),
    (lambda shape: [torch.zeros(shape)] * 2, "got a Tensor"),
])
def test_bad_out_arrays_are_refused_naming_what_they_need(bad, words):
    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 2, np.random.default_rng(4))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="numpy")
    with pytest.raises(ValueError, match=re.escape(words)):
        synth(photos, out=bad(photos.shape))


@pytest.mark.parametrize("spec", [s for s in BACKEND_SPECS if s != "numpy"])
@pytest.mark.parametrize("mode", ["average", "none"])
def test_pinned_staging_and_direct_copies_give_the_same_batch(spec, mode):
    # overlap=True moves inputs and results through pinned buffers copied by threads;
    # overlap=False copies straight from and to the caller's arrays
    from gpu_blur.backends import get_backend

    name, precision = spec_parts(spec)
    scene = scene_for(mode, precision=precision)
    given = batch_for(mode, 3, np.random.default_rng(8), dtype=np.float32)
    kind = type(get_backend(name, precision))
    got = []
    for overlap in (True, False):
        synth = gpu_blur.Synthesizer(scene, backend=kind(name, precision, overlap=overlap),
                                     seed=3, with_mask=True, channels_first=mode == "none")
        batch = given["batch"]
        if mode == "none":
            batch = np.ascontiguousarray(batch.transpose(0, 3, 1, 2))
        out = synth(batch, mask=None if mode != "none" else np.ascontiguousarray(
            given["mask"].transpose(0, 3, 1, 2)))
        got.append((out.blurred, out.sharp, out.mask))
    for pinned, direct in zip(*got, strict=True):
        assert np.array_equal(pinned, direct)


def overlapping_outs(shape):
    """(out=, the overlap's message) pairs: results that would overwrite each other."""
    whole = np.zeros((2 * shape[0] + 1, *shape[1:]), np.float32)
    same = np.zeros(shape, np.float32)
    return [
        ([same, same], "out= sharp shares memory with out= blurred; one result would "
                       "overwrite the other: pass an array of its own for each"),
        ([whole[:shape[0]], whole[1:shape[0] + 1]], "out= sharp shares memory with out= "
                                                     "blurred"),  # offset by a sample
        ([whole[:shape[0]], whole[shape[0]:2 * shape[0]]], None),  # side by side: fine
        ([np.lib.stride_tricks.as_strided(same, strides=(0, *same.strides[1:])),
          np.zeros(shape, np.float32)], "out= blurred: its elements overlap"),
    ]


def test_out_arrays_sharing_memory_are_refused_before_any_is_written():
    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 2, np.random.default_rng(4), dtype=np.float32)["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="numpy")
    ref = synth(photos)
    for out, words in overlapping_outs(photos.shape):
        if words is None:
            synth(photos, out=out)
            assert np.array_equal(out[0], ref.blurred) and np.array_equal(out[1], ref.sharp)
            continue
        with pytest.raises(ValueError, match=re.escape(words)):
            synth(photos, out=out)
        assert not out[0].any() and not out[1].any()
    # an input written over while it is read
    with pytest.raises(ValueError, match=re.escape(
            "out= blurred shares memory with the batch input; results would overwrite the "
            "inputs they are made from: pass an array of its own")):
        synth(photos, out=[photos, np.zeros_like(photos)])
    given = batch_for("none", 2, np.random.default_rng(5), dtype=np.float32)
    synth = gpu_blur.Synthesizer(scene_for("none"), backend="numpy", with_mask=True)
    out = [np.zeros(synth(given["batch"]).blurred.shape, np.float32) for _ in range(2)]
    with pytest.raises(ValueError, match="out= mask shares memory with the mask input"):
        synth(given["batch"], mask=given["mask"], out=[*out, given["mask"][:, 4:-4, 4:-4]])
    with pytest.raises(ValueError, match="out= mask shares memory with out= blurred"):
        synth(given["batch"], mask=given["mask"], out=[*out, out[0]])


@pytest.mark.parametrize("indices, words", [
    ([0.5, 1], "indices[0] = 0.5: a sample index is an int in [0, 2**32); pass ints (a float "
               "index is not rounded)"),
    (np.array([1.0, 2.0]), "indices[0] = 1.0: a sample index is an int"),
    (torch.tensor([3.5, 1.0]), "indices[0] = 3.5: a sample index is an int"),
    ([1, True], "indices[1] = True: a sample index is an int"),
    ([1, 2**32], "indices[1] = 4294967296: a sample index is an int in [0, 2**32)"),
    (7, "indices: one sample index per sample, a list or 1-D array of ints; got 7"),
])
def test_sample_indices_that_are_not_ints_are_refused_not_truncated(indices, words):
    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 2, np.random.default_rng(4))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="numpy")
    with pytest.raises(ValueError, match=re.escape(words)):
        synth(photos, indices=indices)
    with pytest.raises(ValueError, match=re.escape("first_index = 0.5: needs an int, 0 <= "
                                                   "first_index and first_index + 2 (the "
                                                   "batch) <= 2**32")):
        synth(photos, first_index=0.5)
    ints = synth(photos, indices=[3, 9])
    for same in (np.array([3, 9], np.uint32), torch.tensor([3, 9]), (np.int64(3), 9)):
        again = synth(photos, indices=same)
        assert np.array_equal(again.blurred, ints.blurred)


@pytest.mark.parametrize("make, words", [
    (lambda x: x.to("meta"), "batch: a tensor on the meta device holds no values; pass one on "
                             "the CPU or a CUDA device"),
    (lambda x: x.to_sparse(), "batch: a torch.sparse_coo tensor; pass a dense one "
                              "(x.to_dense())"),
])
def test_meta_and_sparse_tensors_are_refused_by_name(make, words):
    scene = scene_for("kernel", precision="float32")
    photos = torch.from_numpy(batch_for("kernel", 2, np.random.default_rng(4))["batch"])
    with pytest.raises(ValueError, match=re.escape(words)):
        gpu_blur.Synthesizer(scene, backend="numpy")(make(photos))
    with pytest.raises(ValueError, match=re.escape(words.replace("batch", "frame 0"))):
        gpu_blur.synthesize([make(photos[0])], scene)


def test_out_is_refused_for_batches_that_are_neither_numpy_nor_on_the_backends_device():
    scene = scene_for("kernel", precision="float32")
    photos = torch.from_numpy(batch_for("kernel", 2, np.random.default_rng(4))["batch"])
    with pytest.raises(ValueError, match="out= is for numpy batches and batches on the "):
        gpu_blur.Synthesizer(scene, backend="numpy")(photos, out=[np.zeros(1)] * 2)


@pytest.mark.parametrize("codes", [False, True])
def test_a_batch_on_the_warp_device_fills_out_arrays_with_the_numpy_batchs_results(codes):
    # what generate's frames kept on the GPU do: a device batch, results into host arrays
    import warp as wp

    scene = scene_for("kernel", precision="float32", bits=8)
    photos = batch_for("kernel", 2, np.random.default_rng(4))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=3)
    ref = synth(photos, codes=codes)
    shape = synth.result_shape(photos.shape)
    out = [np.full(shape, 7, dtype) for dtype in synth.result_dtypes(codes=codes)]
    got = synth(wp.array(photos, device="cpu"), out=out, codes=codes)
    assert got.blurred is out[0] and got.sharp is out[1]
    assert np.array_equal(out[0], ref.blurred) and np.array_equal(out[1], ref.sharp)


def test_a_strided_destination_receives_every_copied_value():
    from gpu_blur.backends import copy_values

    into = np.zeros((2, 3, 4, 5), np.float32)
    view = np.moveaxis(into, 1, -1)  # channels-first storage seen channels-last: strided
    values = np.arange(view.size, dtype=np.float32)
    copy_values(view, values)
    assert np.array_equal(view.reshape(-1), values)


@pytest.mark.parametrize("sizes", [[5, 5, 5], [3_000_001] * 3, [1_000_003, 7]])
def test_parts_are_copied_one_after_another_whatever_their_sizes(sizes):
    # small parts in one piece, large ones in slices on the copy threads, converted
    from gpu_blur.backends import copy_values

    parts = [np.arange(n, dtype=np.uint8) + i for i, n in enumerate(sizes)]
    into = np.zeros(sum(sizes), np.float32)
    copy_values(into, parts)
    assert np.array_equal(into, np.concatenate(parts).astype(np.float32))


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("mode", ["average", "kernel", "trajectory"])
def test_skipping_auto_saturation_gives_the_bits_of_saturation_on_where_nothing_clips(
        spec, mode):
    """Auto saturation skips a sample whose input never reaches the clip level: there the
    saturate and restore stages are identities (a zero mask, nothing at 1), so the output is
    what running them gives, bit for bit."""
    name, precision = spec_parts(spec)
    images = batch_for(mode, 2, np.random.default_rng(8))["batch"]
    images = np.minimum(images, 254)  # no value at the clip level
    out = {}
    for saturation in ("auto", "on"):
        scene = scene_for(mode, precision=precision)
        scene = dataclasses.replace(
            scene, saturation=dataclasses.replace(scene.saturation, mode=saturation))
        synth = gpu_blur.Synthesizer(scene, backend=name, seed=3, with_mask=True)
        out[saturation] = synth(images)
    assert not any(p.kept("saturate") for p in out["auto"].plans)
    assert all(p.kept("saturate") for p in out["on"].plans)
    assert np.array_equal(out["auto"].blurred, out["on"].blurred)
    assert np.array_equal(out["auto"].mask, out["on"].mask)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("mode", ["average", "kernel", "trajectory", "none"])
def test_a_batch_of_clipped_and_unclipped_samples_equals_synthesize_with_its_plans_and_draws(
        spec, mode):
    """A kernel backend's batch runs every sample as if it clipped and reads the clip test
    after its passes are queued; a sample that does not clip still gets auto saturation's
    skip: synthesize's bits, plan and draws (no alpha)."""
    name, precision = spec_parts(spec)
    scene = scene_for(mode, precision=precision)
    scene = dataclasses.replace(scene, saturation=dataclasses.replace(scene.saturation,
                                                                      mode="auto"))
    given = batch_for(mode, 4, np.random.default_rng(21))
    given["batch"][1:3] = np.minimum(given["batch"][1:3], 254)  # samples 1 and 2 never clip
    if mode == "none":
        given["mask"][1:3] = 0
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=2, with_mask=True,
                                 overrides={"alpha": 1.25})
    out = synth(given["batch"], mask=given.get("mask"), indices=[9, 3, 0, 7])
    assert [p.kept("saturate") for p in out.plans] == [True, False, False, True]
    for b, index in enumerate([9, 3, 0, 7]):
        one = gpu_blur.synthesize(one_sample(mode, given, b), scene, seed=2, sample_index=index,
                                  backend=name, overrides={"alpha": 1.25})
        assert out.plans[b] == one.plan, b
        assert out.params[b].keys() == one.params.keys(), b
        for key, value in one.params.items():
            assert np.array_equal(out.params[b][key], value), (b, key)
        assert np.array_equal(out.blurred[b], one.blurred), b
        assert np.array_equal(out.sharp[b], one.sharp), b
        assert np.array_equal(out.mask[b], one.mask), b


@pytest.mark.parametrize("name", ["warp:cpu", "opencl"])
def test_batches_after_others_equal_batches_of_a_fresh_synthesizer(name):
    # a resident batch reuses the last batch's device buffers when its size repeats: nothing of
    # an earlier batch (another size, another plan mix, another count) may reach a later one
    scene = scene_for("kernel")
    rng = np.random.default_rng(4)
    first, second = batch_for("kernel", 3, rng), batch_for("kernel", 3, rng)
    smaller = batch_for("kernel", 2, rng)["batch"][:, :20, :18]
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=3, with_mask=True)
    synth(first["batch"], first_index=0)
    synth(np.ascontiguousarray(smaller), first_index=3)
    synth(first["batch"][:2], first_index=5)
    again = synth(second["batch"], first_index=7)
    fresh = gpu_blur.Synthesizer(scene, backend=name, seed=3, with_mask=True)(
        second["batch"], first_index=7)
    for got, want in ((again.blurred, fresh.blurred), (again.sharp, fresh.sharp),
                      (again.mask, fresh.mask)):
        assert np.array_equal(got, want)


def test_a_batched_launch_whose_slots_are_too_small_is_refused_before_it_runs():
    from gpu_blur.backends import get_backend
    from gpu_blur.backends.kernel import Drawn
    from gpu_blur.cameras import get_camera
    from gpu_blur.planning import plan
    from gpu_blur.tiling import Region

    backend = get_backend("warp:cpu")
    p = plan(scene_for("kernel"), size=(4, 4))
    rgb, mosaic = backend.slots(2, 48), backend.slots(2, 16)
    samples = [Drawn({}, 0, 0), Drawn({}, 1, 2)]  # slot 2 of two
    with pytest.raises(ValueError, match="linear has 2 slot"):
        backend.to_raw_batch(p, get_camera("srgb"), samples, rgb, rgb, rgb, mosaic, (0, 0),
                             (4, 4), seed=0)
    short = backend.slots(1, 47)  # a slot one value short
    with pytest.raises(ValueError, match="saturated has 1 slot"):
        backend.finish_batch(p, get_camera("srgb"), samples[:1], mosaic, short,
                             Region.whole(4, 4), Region.whole(4, 4), rgb, seed=0)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("streamed", [False, True])
def test_batches_and_out_arrays_in_pinned_memory_give_the_plain_batch(spec, streamed,
                                                                      monkeypatch):
    # Synthesizer.pinned memory is copied straight to and from the device; a batch of codes
    # in it goes in parts (STREAMED_SAMPLES) when its samples are large enough (0 here)
    synth, frames = six_stacks(spec, streamed, monkeypatch, 9, {"seed": 4, "with_mask": True})
    plain = synth(frames)
    held = synth.pinned(frames.shape, np.uint8)
    held[...] = frames
    out = [synth.pinned(plain.blurred.shape) for _ in range(3)]
    got = synth(held, out=out)
    assert got.blurred is out[0] and got.sharp is out[1] and got.mask is out[2]
    for mine, want in zip(out, (plain.blurred, plain.sharp, plain.mask), strict=True):
        assert np.array_equal(mine, want)
    fresh = synth(held)  # pinned inputs, new outputs
    assert np.array_equal(fresh.blurred, plain.blurred)
    assert np.array_equal(fresh.sharp, plain.sharp)


def test_only_this_backends_contiguous_pinned_arrays_of_the_travel_dtype_go_direct():
    from gpu_blur.backends import get_backend

    runner, other = get_backend("opencl", "float32"), get_backend("warp:cpu", "float32")
    mine = runner.pinned((4, 6, 8, 3), np.uint8)
    assert runner._direct(mine, np.uint8) and runner._direct(mine[1:3], np.uint8)
    assert not runner._direct(mine[:, ::2], np.uint8)  # strided: through staging
    assert not runner._direct(mine, np.float32)
    assert not runner._direct(np.empty((4, 6, 8, 3), np.uint8), np.uint8)
    assert not runner._direct(other.pinned((4, 6, 8, 3), np.uint8), np.uint8)
    assert isinstance(gpu_blur.Synthesizer(backend="numpy").pinned((2, 3)), np.ndarray)


def test_pinned_inputs_and_out_arrays_skip_the_staging_buffers(monkeypatch):
    from gpu_blur.backends.opencl import OpenCLBackend

    runner = OpenCLBackend("opencl", "float32", overlap=True)
    staged = []
    real = runner._staging_buffer
    monkeypatch.setattr(runner, "_staging_buffer", lambda *a: staged.append(a) or real(*a))
    synth = gpu_blur.Synthesizer(scene_for("average", precision="float32"), backend=runner)
    frames = batch_for("average", 2, np.random.default_rng(2))["batch"]
    shape = synth(frames).blurred.shape
    assert staged  # plain arrays go through pinned staging buffers
    held = synth.pinned(frames.shape, np.uint8)
    held[...] = frames
    out = [synth.pinned(shape) for _ in range(2)]
    staged.clear()
    synth(held, out=out)
    assert staged == []


def test_a_batch_in_one_device_buffer_runs_each_input_pass_once_with_the_same_bits():
    # a wp.array (or torch/CuPy) batch on the Warp device: its samples lie back to back, so
    # the checks, linearize and the sharp reference launch once for the batch, not per
    # sample, and the results come back in the batch's own buffers
    import collections

    import warp as wp

    scene = scene_for("none", precision="float32")
    given = batch_for("none", 4, np.random.default_rng(6), dtype=np.float32)
    synth = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=2, with_mask=True)
    plain = synth(given["batch"], mask=given["mask"])  # host arrays: sample by sample
    launches = collections.Counter()
    launch = synth.runner._launch
    synth.runner._launch = lambda k, name, *a: launches.update([name]) or launch(k, name, *a)
    got = synth(wp.array(given["batch"], device="cpu"), mask=wp.array(given["mask"],
                                                                       device="cpu"))
    assert launches == {"inspect": 2, "linearize_values": 1, "render_sharp": 1, "to_raw": 1,
                        "finish": 1}
    # the results are the batch's own buffers: the next batch must not write into them
    synth(wp.array(given["batch"], device="cpu"), mask=wp.array(given["mask"], device="cpu"),
          first_index=4)
    for mine, want in zip((got.blurred, got.sharp, got.mask),
                          (plain.blurred, plain.sharp, plain.mask), strict=True):
        assert np.array_equal(mine.numpy(), want)
    bad = given["mask"].copy()
    bad[2, 5, 6, 1] = np.nan
    with pytest.raises(ValueError, match=r"^sample 2 of 4: mask: 1 NaN and 0 infinite .* row "
                                         r"5, column 6, channel 1"):
        synth(wp.array(given["batch"], device="cpu"), mask=wp.array(bad, device="cpu"))


def test_evenly_spaced_device_images_are_found_and_others_are_not():
    import warp as wp

    from gpu_blur.backends import OnDevice, get_backend

    runner = get_backend("warp:cpu", "float32")
    stacks = wp.array(np.arange(4 * 3 * 2 * 5 * 3, dtype=np.float32).reshape(4, 3, 10, 3),
                      device="cpu")
    flat = stacks.flatten()
    n = 10 * 3

    def image(start):
        return OnDevice(flat[start:start + n], (2, 5, 3), None)

    middles = [image(b * 3 * n + n) for b in range(4)]  # frame 1 of each 3-frame stack
    data, stride = runner.spaced(middles)
    assert stride == 3 * n and np.array_equal(data.numpy()[stride:stride + n],
                                              flat.numpy()[4 * n:5 * n])
    assert runner.consecutive(middles) is None  # spaced, not back to back
    assert runner.consecutive([image(b * n) for b in range(4)]).shape == (4, 2, 5, 3)
    assert runner.spaced([image(0), image(n), image(3 * n)]) is None  # uneven
    assert get_backend("opencl", "float32").spaced(middles) is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (run on the GPU "
                    "machine; CI has none)")
def test_inputs_written_on_a_side_stream_are_read_only_once_written():
    # a non-default torch stream does not synchronize with Warp's: the batch waits for the
    # caller's current stream, so a prefetcher's late writes are what the passes read
    scene = scene_for("none", precision="float32")
    given = batch_for("none", 2, np.random.default_rng(12), dtype=np.float32)
    synth = gpu_blur.Synthesizer(scene, backend="warp:cuda:0")
    images, masks = (torch.from_numpy(given[k]).cuda() for k in ("batch", "mask"))
    want = synth(images, mask=masks)
    x, m = torch.zeros_like(images), torch.zeros_like(masks)
    torch.cuda.synchronize()
    side = torch.cuda.Stream()
    with torch.cuda.stream(side):
        torch.cuda._sleep(200_000_000)  # the writes below land long after the call starts
        x.copy_(images)
        m.copy_(masks)
        got = synth(x, mask=m)
    torch.cuda.synchronize()
    assert torch.equal(got.blurred, want.blurred) and torch.equal(got.sharp, want.sharp)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (run on the GPU "
                    "machine; CI has none)")
def test_results_handed_over_on_the_gpu_are_read_on_the_callers_stream_once_made():
    # the call returns once the checks are read, its passes still running: the caller's
    # current stream (here not the default one) waits for them before its next work. Warp's
    # stream is held back first, so the passes start only as the call returns.
    import warp as wp

    scene = gpu_blur.scene.load_scene("realblur_j")
    given = batch_for("none", 8, np.random.default_rng(14), dtype=np.float32)
    images, masks = (torch.from_numpy(np.ascontiguousarray(
        np.broadcast_to(given[k][:, :1, :1], (8, 1200, 1920, 3)))).cuda()
        for k in ("batch", "mask"))
    synth = gpu_blur.Synthesizer(scene, backend="warp:cuda:0")
    synth(images, mask=masks)  # kernels built, buffers made
    torch.cuda.synchronize()
    side = torch.cuda.Stream()
    with torch.cuda.stream(wp.stream_to_torch(wp.get_stream("cuda:0"))):
        torch.cuda._sleep(200_000_000)
    with torch.cuda.stream(side):
        got = synth(images, mask=masks, first_index=8)
        read_at_once = got.blurred.clone(), got.sharp.clone()
    torch.cuda.synchronize()
    want = synth(images.cpu().numpy(), mask=masks.cpu().numpy(), first_index=8)
    for early, name in zip(read_at_once, ("blurred", "sharp"), strict=True):
        assert np.array_equal(early.cpu().numpy(), getattr(want, name)), name


def test_a_device_batch_returns_without_waiting_for_its_passes():
    # results handed over on the device: the host waits for the checks' counts, not for
    # the passes (the next batch's host work overlaps them); numpy results are waited for
    import warp as wp

    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 3, np.random.default_rng(15))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=2)
    waits = []
    wait = synth.runner.wait
    synth.runner.wait = lambda: waits.append(1) or wait()
    plain = synth(photos)
    assert waits
    waits.clear()
    got = synth(wp.array(photos, device="cpu"))
    assert not waits
    assert np.array_equal(got.blurred.numpy(), plain.blurred)
    assert np.array_equal(got.sharp.numpy(), plain.sharp)


def test_a_device_batch_counts_each_sample_in_one_launch_for_the_clip_test():
    # auto saturation plans each sample by its own counts: one inspect launch for a device
    # batch still gives a row per sample (the first sample clips, the others need not)
    import collections

    import warp as wp

    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 4, np.random.default_rng(13))["batch"]
    synth = gpu_blur.Synthesizer(scene, backend="warp:cpu", seed=5)
    plain = synth(photos)
    launches = collections.Counter()
    launch = synth.runner._launch
    synth.runner._launch = lambda k, name, *a: launches.update([name]) or launch(k, name, *a)
    got = synth(wp.array(photos, device="cpu"))
    assert launches["inspect"] == 1 and launches["linearize"] == 1
    assert [p.kept("saturate") for p in got.plans] == [p.kept("saturate") for p in plain.plans]
    assert [p.kept("saturate") for p in got.plans][0]
    assert np.array_equal(got.blurred.numpy(), plain.blurred)
    assert np.array_equal(got.sharp.numpy(), plain.sharp)


@pytest.mark.parametrize("name", ["warp:cpu", "opencl"])
def test_a_batch_reads_auto_saturations_clip_test_after_queuing_every_pass(name):
    # the host reads the counts once the passes are queued, so the device never idles while
    # the host draws and launches (a sample is planned from its counts afterwards)
    scene = scene_for("kernel", precision="float32")
    photos = batch_for("kernel", 3, np.random.default_rng(16))["batch"]
    photos[1] = np.minimum(photos[1], 254)
    synth = gpu_blur.Synthesizer(scene, backend=name, seed=2)
    launched, seen = [], []
    launch, inspect = synth.runner._launch, synth.runner.inspect_queued
    synth.runner._launch = lambda k, kname, *a: launched.append(kname) or launch(k, kname, *a)

    def inspect_queued(images):
        counts = inspect(images)
        return lambda: seen.extend(launched) or counts()

    synth.runner.inspect_queued = inspect_queued
    got = synth(photos)
    assert "to_raw" in seen and "finish" in seen, seen
    assert [p.kept("saturate") for p in got.plans] == [True, False, True]


def test_frame_stacks_lying_back_to_back_average_in_one_launch_with_the_same_bits():
    # a device batch of 8-bit frame stacks (torch or CuPy on a Warp device: B x F x H x W x
    # 3, beyond a wp.array's dimensions, so built here from one flat buffer) sums every
    # sample's frames in one exact launch; each sample equals its own accumulate
    import collections

    import warp as wp

    from gpu_blur.backends import OnDevice, get_backend
    from gpu_blur.backends.kernel import Drawn
    from gpu_blur.planning import plan
    from gpu_blur.tiling import Region

    runner = get_backend("warp:cpu", "float32")
    scene = scene_for("average", precision="float32")
    frames = batch_for("average", 3, np.random.default_rng(14))["batch"]  # 3 x 3 x H x W x 3
    flat = wp.array(frames.reshape(-1), device="cpu")
    size = frames[0].size
    stacks = [OnDevice(flat[b * size:(b + 1) * size], frames.shape[1:], None,
                       np.dtype(np.uint8)) for b in range(3)]
    sample_plan = plan(scene, size=(H, W))
    plans, drawn = [sample_plan] * 3, [Drawn({}, b, b) for b in range(3)]
    n = H * W * 3
    linear, mask = runner.slots(3, n), runner.slots(3, n)
    wants = [runner.accumulate(sample_plan, {}, stack, None, Region.whole(H, W))
             for stack in stacks]  # one sample at a time (and the code tables made)
    launches = collections.Counter()
    launch = runner._launch
    runner._launch = lambda k, name, *a: launches.update([name]) or launch(k, name, *a)
    try:
        runner.accumulate_batch(plans, drawn, [(s, None) for s in stacks], linear, mask)
    finally:
        runner._launch = launch
    assert launches == {"blur_average_exact": 1}
    for b, want in enumerate(wants):
        for got, one in zip((linear, mask), want, strict=True):
            assert np.array_equal(runner.slot_image(got, b, (H, W, 3)).numpy(np.float32),
                                  one.numpy(np.float32))


@pytest.mark.parametrize("streamed", [False, True])
@pytest.mark.parametrize("lent", [True, False])
def test_png_streams_deflated_on_the_device_are_zlibs_of_the_batchs_codes(
        streamed, lent, monkeypatch):
    # a Warp GPU deflates each exported image's PNG rows (output.png fast); forced on
    # Warp's CPU device here. Past the page-locked limit an image gets no stream: the host
    # encodes it
    pytest.importorskip("warp")
    import gpu_blur.staging
    from gpu_blur.png_codecs import filtered_rows, huffman_zlib
    from gpu_blur.png_device import DevicePngs

    monkeypatch.setattr(DevicePngs, "for_backend", staticmethod(lambda backend, scene: True))
    synth, frames = six_stacks("warp:cpu/float32", streamed, monkeypatch, 31, {"seed": 4},
                               bits=8)
    if not lent:
        monkeypatch.setattr(gpu_blur.staging.LentResults, "take", lambda self, arrays: None)
    batch = frames
    if streamed:  # codes in the backend's pinned memory go in parts
        batch = synth.pinned(frames.shape, np.uint8)
        batch[...] = frames
    counts = []
    queue = DevicePngs.queue
    monkeypatch.setattr(DevicePngs, "queue", lambda self, name, codes, count: counts.append(
        count) or queue(self, name, codes, count))
    got = synth(batch, codes=True, png=True)
    assert len(got.png) == 6 and sum(counts) == 12 and (len(counts) > 2) == streamed
    for b in range(6):
        if not lent:
            assert got.png[b] == {}
            continue
        for key in ("blurred", "sharp"):
            made = b"".join(got.png[b][key])
            assert made == huffman_zlib(filtered_rows(getattr(got, key)[b])), (b, key)
    assert synth(frames, codes=True).png is None  # not asked for
