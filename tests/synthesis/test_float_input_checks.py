"""Float inputs' value checks: cheap when the values are good, today's words when they are not.

A float batch is checked where it lies: a torch batch by torch's (CUDA) or numpy's (host
memory, Warp's CPU device) reductions, each sample's lowest and highest value
(``BatchIO.value_ranges``); other batches on a kernel backend by the device's counts; the host
path by ``check_image``'s two reductions. Whoever checks, a bad value raises the same
message, naming the sample, what is wrong and where, and the fix.
"""

import numpy as np
import pytest
import torch

import gpu_blur
from gpu_blur import image_arrays
from gpu_blur.scene import scene_from_dict
from gpu_blur.synthesis import batches

H, W, B = 12, 16, 4
BAD = {"NaN": np.nan, "+inf": np.inf, "-inf": -np.inf, "below 0": -0.25, "above 1": 1.5}
FLOATS = (np.float16, np.float32, np.float64)
#: (array type, backend): torch's reductions on the host, the device's counts (a batch put
#: sample by sample; a device batch), the host path
ROUTES = (("torch", "warp:cpu"), ("numpy", "warp:cpu"), ("warp", "warp:cpu"),
          ("torch", "numpy"), ("numpy", "opencl"))
SCENES = {"none": "realblur_j",  # a blurred image and its mask
          "kernel": scene_from_dict({"blur": {"mode": "kernel", "kernel_size": [3, 5]},
                                     "saturation": {"mode": "auto"}}),
          "average": scene_from_dict({"blur": {"mode": "average", "frames": 3}})}
_synths: dict = {}


def synth(mode: str, backend: str) -> gpu_blur.Synthesizer:
    """One Synthesizer per scene and backend for the module (kernels are built once)."""
    if (mode, backend) not in _synths:
        _synths[mode, backend] = gpu_blur.Synthesizer(SCENES[mode], backend=backend, seed=3)
    return _synths[mode, backend]


def good(mode: str, dtype=np.float32, count: int = B) -> dict:
    """Float inputs in [0, 1] of ``mode``: {"batch": ..., "mask": ... (mode none)}."""
    rng = np.random.default_rng(11)
    shape = (count, 3, H, W, 3) if mode == "average" else (count, H, W, 3)
    given = {"batch": rng.random(shape).astype(dtype)}
    if mode == "none":
        given["mask"] = (rng.random((count, H, W, 3)) < 0.1).astype(dtype)
    return given


def as_type(given: dict, lib: str) -> dict:
    """The inputs as numpy arrays, torch CPU tensors or ``wp.array`` on Warp's CPU device."""
    if lib == "torch":
        return {k: torch.from_numpy(v) for k, v in given.items()}
    if lib == "warp":
        import warp as wp

        return {k: wp.array(v.astype(np.float32), device="cpu") for k, v in given.items()}
    return given


def host(x) -> np.ndarray:
    """A result (numpy, torch or ``wp.array``) as a numpy array."""
    return x if isinstance(x, np.ndarray) else x.numpy()


def message(mode: str, lib: str, backend: str, given: dict) -> str:
    """What a Synthesizer says of ``given`` (it must refuse it)."""
    arrays = as_type(given, lib)
    with pytest.raises(ValueError) as e:
        synth(mode, backend)(arrays["batch"], mask=arrays.get("mask"))
    return str(e.value)


def words(image: np.ndarray, name: str) -> str:
    """check_image's message for one input of one sample: the words every route must give."""
    with pytest.raises(ValueError) as e:
        image_arrays.check_image(image, name)
    return str(e.value)


@pytest.mark.parametrize("dtype", FLOATS, ids=lambda d: np.dtype(d).name)
@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("b", [0, 1, B - 1], ids=["first", "middle", "last"])
@pytest.mark.parametrize("key", ["batch", "mask"])
def test_a_bad_float_names_its_sample_in_todays_words(dtype, bad, b, key):
    given = good("none", dtype)
    given[key][b, 5, 7, 2] = BAD[bad]
    want = f"sample {b} of {B}: " + words(given[key][b], "blurred" if key == "batch" else key)
    assert "row 5, column 7, channel 2" in want
    for lib, backend in ROUTES:
        if lib == "warp" and dtype != np.float32:
            continue  # a wp.array batch holds the backend's precision
        assert message("none", lib, backend, given) == want, (lib, backend)


def test_the_words_themselves_are_unchanged():
    given = good("none")
    given["mask"][2, 1, 3, 0] = np.nan
    given["mask"][2, 4, 4, 1] = -np.inf
    assert message("none", "torch", "warp:cpu", given) == (
        "sample 2 of 4: mask: 1 NaN and 1 infinite value(s), the first at row 1, column 3, "
        "channel 0; float images must be finite sRGB values in [0, 1]: fix what produced "
        "them, or replace them (np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0))")
    given = good("kernel")
    given["batch"][3, 0, 1, 2] = -0.5
    given["batch"][3, 2, 2, 2] = -0.75
    assert message("kernel", "torch", "warp:cpu", given) == (
        "sample 3 of 4: photo: 2 negative value(s), the lowest -0.75, the first at row 0, "
        "column 1, channel 2; float images must be sRGB values in [0, 1] (not "
        "mean-subtracted or normalized data): clip rounding errors with np.clip(x, 0, 1)")
    given = good("kernel")
    given["batch"][0, 11, 15, 0] = 255.0
    assert message("kernel", "numpy", "numpy", given) == (
        "sample 0 of 4: photo: 1 value(s) above 1, the highest 255, the first at row 11, "
        "column 15, channel 0; float images must be sRGB values in [0, 1]: pass 0..255 data "
        "as uint8 (or divide it by 255), clip small overshoots with np.clip(x, 0, 1)")


@pytest.mark.parametrize("bad", BAD)
def test_a_frame_stack_names_its_sample_and_frame(bad):
    given = good("average")
    given["batch"][1, 2, 3, 4, 0] = BAD[bad]
    want = "sample 1 of 4: " + words(given["batch"][1, 2], "frame 2")
    for lib, backend in ROUTES:
        if lib != "warp":  # a wp.array has at most 4 dimensions
            assert message("average", lib, backend, given) == want, (lib, backend)


def test_with_several_bad_samples_the_device_paths_name_the_same_one():
    # the device paths look input by input (every sample's image, then every mask): torch's
    # reductions name the one the device's counts name
    given = good("none")
    given["mask"][0, 1, 1, 1] = 2.0
    given["batch"][2, 3, 3, 0] = np.nan
    given["batch"][3, 0, 0, 0] = -1.0
    said = {message("none", lib, "warp:cpu", given) for lib in ("torch", "numpy", "warp")}
    assert said == {"sample 2 of 4: " + words(given["batch"][2], "blurred")}


@pytest.mark.parametrize("mode", ["none", "kernel"])
def test_good_floats_give_the_same_bits_and_clip_tests_whoever_checks(mode):
    # auto saturation's clip test reads the same ranges: a sample reaching 1.0 (or with a
    # mask above 0) is planned as clipping, the others are not
    blur = {"mode": mode, "kernel_size": [3, 5]} if mode == "kernel" else {"mode": mode}
    scene = scene_from_dict({"blur": blur, "saturation": {"mode": "auto"},
                             "output": {"crop": 2}})
    given = good(mode)
    given["batch"] = np.minimum(given["batch"], np.float32(0.99))
    given["batch"][0, 2, 3, 1] = 1.0
    if mode == "none":
        given["mask"][1:3] = 0.0
    results = []
    for lib, backend in (("torch", "warp:cpu"), ("numpy", "warp:cpu"), ("warp", "warp:cpu")):
        arrays = as_type(given, lib)
        out = gpu_blur.Synthesizer(scene, backend=backend, seed=4)(arrays["batch"],
                                                                   mask=arrays.get("mask"))
        results.append(([p.kept("saturate") for p in out.plans], host(out.blurred),
                        host(out.sharp)))
    clips = results[0][0]
    assert clips[0] and not all(clips)
    for other in results[1:]:
        assert other[0] == clips
        assert np.array_equal(other[1], results[0][1]) and np.array_equal(other[2],
                                                                          results[0][2])


def test_a_torch_float_batch_is_reduced_once_and_counted_on_no_device(monkeypatch):
    # torch CPU floats on Warp's CPU device: one ValueRanges a batch over both inputs, read
    # once, and no image handed to the device's counts (no inspect launch, no count copy)
    made, reads, counted = [], [], []
    host_ranges = batches._host_ranges

    def measured(floats):
        ranges = host_ranges(floats)
        read = ranges._read
        ranges._read = lambda: reads.append(1) or read()
        made.append(sorted(ranges.keys))
        return ranges

    monkeypatch.setattr(batches, "_host_ranges", measured)
    s = gpu_blur.Synthesizer("realblur_j", backend="warp:cpu", seed=3)
    inspect = s.runner.inspect_queued
    s.runner.inspect_queued = lambda images: counted.append(len(images)) or inspect(images)
    arrays = as_type(good("none", count=6), "torch")
    s(arrays["batch"], mask=arrays["mask"])
    assert made == [["frames", "mask"]] and reads == [1] and counted == [0]
    codes = {k: torch.from_numpy((v.numpy() * 255).astype(np.uint8)) for k, v in arrays.items()}
    s(codes["batch"], mask=codes["mask"])  # 8-bit codes: nothing to measure, nothing counted
    assert len(made) == 1 and counted == [0, 0]


def test_a_good_float_image_is_read_once_more_than_its_copy(monkeypatch):
    # check_image's fast path: min and max, then the float64 copy; the slow path (counting and
    # locating) runs only for an image that fails them
    slow = []
    refuse = image_arrays.refuse_values
    monkeypatch.setattr(image_arrays, "refuse_values",
                        lambda x, what: slow.append(what) or refuse(x, what))
    for dtype in FLOATS:
        image = np.random.default_rng(1).random((H, W, 3)).astype(dtype)
        checked = image_arrays.check_image(image, "photo")
        assert checked.dtype == np.float64 and np.array_equal(checked, image.astype(np.float64))
        assert checked is not image
    assert slow == []
    image[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="photo: 1 NaN"):
        image_arrays.check_image(image, "photo")
    assert slow == ["photo"]


def test_in_unit_range_refuses_nan_and_takes_negative_zero():
    assert image_arrays.in_unit_range(-0.0, 1.0)
    assert not image_arrays.in_unit_range(np.nan, np.nan)
    assert not image_arrays.in_unit_range(0.0, np.nan)
    assert not image_arrays.in_unit_range(-np.inf, 0.5)
    assert not image_arrays.in_unit_range(0.0, np.inf)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@cuda
@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("b", [0, 2, B - 1])
def test_a_torch_cuda_batch_names_the_sample_warp_on_cuda_names(bad, b):
    given = good("none")
    given["mask"][b, 4, 5, 1] = BAD[bad]
    s = gpu_blur.Synthesizer("realblur_j", backend="warp:cuda:0", seed=3)
    on_gpu = {k: torch.from_numpy(v).cuda() for k, v in given.items()}
    with pytest.raises(ValueError) as e:
        s(on_gpu["batch"], mask=on_gpu["mask"])
    assert str(e.value) == f"sample {b} of {B}: " + words(given["mask"][b], "mask")


@cuda
def test_a_torch_cuda_batch_takes_one_reduction_an_input_and_one_wait(monkeypatch):
    calls = {"aminmax": 0, "synchronize": 0}
    aminmax, synchronize = torch.aminmax, torch.cuda.Event.synchronize

    def counted(name, f):
        def call(*a, **k):
            calls[name] += 1
            return f(*a, **k)
        return call

    monkeypatch.setattr(torch, "aminmax", counted("aminmax", aminmax))
    monkeypatch.setattr(torch.cuda.Event, "synchronize", counted("synchronize", synchronize))
    given = good("none", count=8)
    s = gpu_blur.Synthesizer("realblur_j", backend="warp:cuda:0", seed=3)
    on_gpu = {k: torch.from_numpy(v).cuda() for k, v in given.items()}
    counted_images = []
    inspect = s.runner.inspect_queued
    s.runner.inspect_queued = lambda images: counted_images.append(len(images)) or inspect(
        images)
    out = s(on_gpu["batch"], mask=on_gpu["mask"])
    assert calls == {"aminmax": 2, "synchronize": 1} and counted_images == [0]
    # host arrays on the same device: counted there, the same bits
    plain = gpu_blur.Synthesizer("realblur_j", backend="warp:cuda:0", seed=3)(
        given["batch"], mask=given["mask"])
    assert np.array_equal(out.blurred.cpu().numpy(), plain.blurred)
    assert np.array_equal(out.sharp.cpu().numpy(), plain.sharp)


def test_torchs_ends_give_each_samples_lowest_and_highest_of_each_input():
    # the reductions a torch CUDA batch's checks run, here on CPU tensors: aminmax propagates
    # NaN, and the 2K x B ends come back per input as B x 2 (lowest, highest)
    rng = np.random.default_rng(2)
    floats = {"frames": torch.from_numpy(rng.random((3, 4, 5, 3)).astype(np.float32)),
              "mask": torch.from_numpy(rng.random((3, 4, 5, 3)).astype(np.float32))}
    floats["frames"][1, 2, 3, 0] = float("nan")
    floats["mask"][2, 0, 0, 2] = -3.0
    ranges = batches._ends_by_key(batches._torch_ends(floats).numpy(), floats)
    for key, x in floats.items():
        x = x.numpy()
        want = np.array([(s.min(), s.max()) for s in x], np.float64)
        np.testing.assert_array_equal(ranges[key], want)
    assert np.isnan(ranges["frames"][1]).all() and ranges["mask"][2, 0] == -3.0
    flags = gpu_blur.synthesis.inputs.ValueRanges(floats, lambda: ranges).flags
    assert [flags("frames", b)[0] for b in range(3)] == [False, True, False]
    assert [flags("mask", b)[0] for b in range(3)] == [False, False, True]


@pytest.mark.parametrize("bad", BAD)
def test_batches_checked_by_torchs_reductions_name_the_sample(monkeypatch, bad):
    # the CUDA route's reductions and unpacking, run on the host: every input's ends from
    # torch.aminmax name the same sample in the same words as the device's counts
    def by_torch(floats):
        tensors = {key: torch.from_numpy(x) for key, x in floats.items()}
        return gpu_blur.synthesis.inputs.ValueRanges(floats, lambda: batches._ends_by_key(
            batches._torch_ends(tensors).numpy(), floats))

    monkeypatch.setattr(batches, "_host_ranges", by_torch)
    for key, b in (("batch", 0), ("mask", 2), ("batch", B - 1)):
        given = good("none")
        given[key][b, 6, 2, 1] = BAD[bad]
        want = f"sample {b} of {B}: " + words(given[key][b],
                                               "blurred" if key == "batch" else key)
        s = gpu_blur.Synthesizer("realblur_j", backend="warp:cpu", seed=3)
        assert message("none", "torch", "warp:cpu", given) == want
        arrays = as_type(good("none"), "torch")
        assert s(arrays["batch"], mask=arrays["mask"]).blurred.shape[0] == B
