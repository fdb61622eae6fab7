"""The Warp backend's devices, on-device results and command-line use."""

import numpy as np
import pytest

wp = pytest.importorskip("warp")
import gpu_blur  # noqa: E402
from gpu_blur.backends.warp import WarpBackend, warp_devices  # noqa: E402
from gpu_blur.cli import main  # noqa: E402
from gpu_blur.scene import scene_from_dict  # noqa: E402

SCENE = {"blur": {"mode": "trajectory"}, "output": {"bits": 0}}


def test_warp_names_cpu_and_cuda_devices():
    specs = [d["spec"] for d in warp_devices()]
    assert "warp:cpu" in specs
    default = WarpBackend("warp")
    assert default.wp_device == ("cuda:0" if wp.is_cuda_available() else "cpu")
    with pytest.raises(ValueError, match="no Warp device 'warp:cuda:99'; present: warp:cpu"):
        WarpBackend("warp:cuda:99")


@pytest.mark.parametrize("device", [d["spec"] for d in warp_devices()])
def test_on_device_result_equals_the_host_result(device, coffee_rgb):
    photo = coffee_rgb[100:164, 200:296]
    scene = scene_from_dict(SCENE)
    host = gpu_blur.synthesize([photo], scene, seed=2, backend=device)
    kept = gpu_blur.synthesize([photo], scene, seed=2, backend=device, on_device=True)
    assert isinstance(kept.blurred, wp.array) and kept.blurred.shape == (64, 96, 3)
    assert str(kept.blurred.device) == device.split(":", 1)[1]
    assert np.array_equal(kept.blurred.numpy(), host.blurred)


@pytest.mark.parametrize("device", [d["spec"] for d in warp_devices()])
@pytest.mark.parametrize("mode", ["kernel", "none"])
def test_replayed_launches_give_each_sample_its_own_values(device, mode, coffee_rgb):
    # a backend replays its recorded launches with only the changed arguments: samples run
    # after others must equal the same samples run first on a fresh backend
    scene = scene_from_dict({"blur": {"mode": mode}, "output": {"bits": 0}})
    photo = coffee_rgb[:64, :96]
    given = {"blurred": photo} if mode == "none" else [photo]

    def make(backend, index):
        return gpu_blur.synthesize(given, scene, seed=2, sample_index=index,
                                   backend=backend).blurred

    shared = WarpBackend(device)
    runs = [make(shared, i) for i in (0, 1, 2, 0)]
    for got, index in zip(runs, (0, 1, 2, 0), strict=True):
        assert np.array_equal(got, make(WarpBackend(device), index)), index
    assert not np.array_equal(runs[0], runs[1])


def test_a_recorded_launch_tells_reals_apart_by_their_bits():
    from gpu_blur.backends.warp import Launches

    assert Launches._key(-0.0) != Launches._key(0.0)
    assert Launches._key(np.float32(np.nan)) == Launches._key(np.float32(np.nan))
    assert Launches._key(np.float32(1.0)) != Launches._key(np.float64(1.0))


@pytest.mark.parametrize("device", [d["spec"] for d in warp_devices()])
def test_torch_takes_the_on_device_result_without_a_copy(device, coffee_rgb):
    torch = pytest.importorskip("torch")
    result = gpu_blur.synthesize([coffee_rgb[:64, :96]], scene_from_dict(SCENE), seed=2,
                                 backend=device, on_device=True)
    tensor = torch.from_dlpack(result.blurred)
    assert tensor.data_ptr() == result.blurred.ptr  # the same memory: no copy
    assert tensor.device.type == ("cuda" if "cuda" in device else "cpu")
    assert tuple(tensor.shape) == (64, 96, 3)


def test_on_device_is_refused_where_it_cannot_hold(coffee_rgb):
    photo = coffee_rgb[:32, :32]
    with pytest.raises(ValueError, match="on_device=True needs"):
        gpu_blur.synthesize([photo], scene_from_dict(SCENE), on_device=True)  # numpy
    with pytest.raises(ValueError, match="on_device=True needs"):
        gpu_blur.synthesize([photo], scene_from_dict(SCENE), backend="warp:cpu", tile=(16, 16),
                            on_device=True)


def test_generate_with_the_warp_backend_writes_a_set(tmp_path):
    out = tmp_path / "set"
    assert main(["generate", "--output", str(out), "--backend", "warp:cpu", "--limit", "1",
                 "--quiet"]) == 0
    model = WarpBackend("warp:cpu").model
    assert f'"device": "{model}"' in (out / "manifest.jsonl").read_text()


def test_devices_command_lists_warp(capsys):
    assert main(["devices"]) == 0
    assert "warp:cpu" in capsys.readouterr().out


@pytest.mark.parametrize("device", [d["spec"] for d in warp_devices()])
def test_a_wp_array_stack_of_frames_averages_like_a_list_of_frames(device, coffee_rgb):
    # frames already in memory Warp reaches (the device, or pinned host memory on CUDA) run in
    # one launch without a host copy; the result is that of the same frames as numpy arrays
    from gpu_blur.backends import to_host
    from gpu_blur.cameras import get_camera
    from gpu_blur.params import draw_params
    from gpu_blur.planning import plan
    from gpu_blur.tiling import Region

    codes = np.round(coffee_rgb[100:164, 200:296] * 255).astype(np.uint8)
    frames = np.stack([np.roll(codes, 2 * i, axis=1) for i in range(6)])
    scene = scene_from_dict({"blur": {"mode": "average", "frames": 6}})
    p = plan(scene, saturated=True)
    params = draw_params(scene, p, get_camera("a7r3"), seed=2, sample_index=0,
                         image_shape=codes.shape[:2])
    backend = WarpBackend(device)
    region = Region.whole(*codes.shape[:2])
    alias = device.split(":", 1)[1]
    places = [alias] + (["cpu"] if alias != "cpu" else [])  # pinned host memory on CUDA
    expected = [to_host(x) for x in backend.accumulate(p, params, list(frames), None, region)]
    for place in places:
        stack = wp.array(frames, dtype=wp.uint8, device=place, pinned=place != alias)
        got = [to_host(x) for x in backend.accumulate(p, params, stack, None, region)]
        for a, b in zip(got, expected, strict=True):
            assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="run whole images"):
        backend.accumulate(p, params, wp.array(frames, dtype=wp.uint8, device=alias), None,
                           Region(0, 0, 32, 32, *codes.shape[:2]))
