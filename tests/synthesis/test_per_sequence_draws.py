"""Per-sequence draws (issue 38): under blur.draws = "per-sequence" the windows of one frame
sequence share every per-image draw, keyed by (seed, sequence index), while the noise's pixels
stay keyed by each window's sample index, on the host path (numpy, tiles) and on the kernel
backends' device batches alike; blur.draws = "per-sample" is the draws of before."""

import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS

import gpu_blur
import gpu_blur.synthesis.resident
from gpu_blur.cameras import scene_camera
from gpu_blur.datasets import epoch_seed
from gpu_blur.params import draw_params
from gpu_blur.planning import plan
from gpu_blur.reference import rng
from gpu_blur.scene import SceneError, scene_from_dict
from gpu_blur.scheduler import Schedule

H, W = 24, 32
#: numpy (the host path) and each kernel backend's float32 (its device batches)
SPECS = ["numpy"] + [s for s in KERNEL_BACKEND_SPECS if s.endswith("/float32")]
#: every per-image draw a window of this scene makes, shared by the windows of a sequence
SHARED = ("alpha", "pattern", "red_gain", "blue_gain", "shot_noise_k", "read_noise_std",
          "jpeg_quality")


def scene(draws: str | None = "per-sequence", precision: str = "float64", **blur):
    settings = {"mode": "average", "frames": 3, **blur}
    if draws is not None:
        settings["draws"] = draws
    return scene_from_dict({"blur": settings, "saturation": {"mode": "on"},
                            "output": {"precision": precision, "bits": 8,
                                       "jpeg_quality": [40, 95]}})


def backend_of(spec: str) -> tuple[str, str]:
    name, _, precision = spec.partition("/")
    return name, precision or "float64"


def same_frames(count: int) -> np.ndarray:
    """``count`` windows of the same three frames: only their draws can tell them apart."""
    frames = np.random.default_rng(3).integers(0, 256, (3, H, W, 3), dtype=np.uint8)
    return np.ascontiguousarray(np.broadcast_to(frames, (count, 3, H, W, 3)))


def shared_draws(params: dict) -> dict:
    return {k: params[k] for k in SHARED}


@pytest.mark.parametrize("spec", SPECS)
def test_windows_of_one_sequence_share_their_draws_and_differ_in_their_noise(spec):
    name, precision = backend_of(spec)
    synth = gpu_blur.Synthesizer(scene(precision=precision), backend=name, seed=5)
    out = synth(same_frames(3), indices=[10, 11, 12], sequences=[4, 4, 4], codes=True)
    first = shared_draws(out.params[0])
    assert all(shared_draws(p) == first for p in out.params)
    assert all(np.array_equal(out.sharp[0], s) for s in out.sharp)
    # the same frames and draws: the noise alone differs, keyed by each sample index
    blurred = [out.blurred[b].astype(int) for b in range(3)]
    for a in range(3):
        for b in range(a + 1, 3):
            assert np.count_nonzero(blurred[a] != blurred[b]) > blurred[a].size // 4
    for b, index in enumerate([10, 11, 12]):  # each window as generate makes it, one by one
        one = gpu_blur.synthesize(list(same_frames(1)[0]), synth.scene, seed=5,
                                  sample_index=index, sequence_index=4, backend=name,
                                  codes=True)
        assert np.array_equal(one.blurred, out.blurred[b]) and one.params == out.params[b]


@pytest.mark.parametrize("spec", SPECS)
def test_two_sequences_draw_apart(spec):
    name, precision = backend_of(spec)
    synth = gpu_blur.Synthesizer(scene(precision=precision), backend=name, seed=5)
    out = synth(same_frames(2), indices=[0, 1], sequences=[0, 1], codes=True)
    one, two = (shared_draws(p) for p in out.params)
    assert all(one[k] != two[k] for k in ("alpha", "red_gain", "blue_gain", "shot_noise_k",
                                           "read_noise_std"))


def test_a_sequence_s_draws_are_its_own_stream_not_a_sample_s():
    s = scene()
    sample_plan = plan(s)
    camera = scene_camera(s, "numpy")
    drawn = draw_params(s, sample_plan, camera, seed=9, sample_index=123, sequence_index=2,
                        image_shape=(H, W))
    alone = draw_params(s, sample_plan, camera, seed=9, sample_index=0, sequence_index=2,
                        image_shape=(H, W))
    assert drawn == alone  # the sample index plays no part
    u = rng.image_uniforms(9, 2, rng.Stream.PARAMS, 10, rng.Keyed.SEQUENCE)
    lo, hi = s.saturation.alpha
    assert drawn["alpha"] == lo + (hi - lo) * u[0]  # DRAW_INDEX["alpha"] of the sequence
    per_sample = draw_params(scene("per-sample"), sample_plan, camera, seed=9,
                             sample_index=2, image_shape=(H, W))
    assert per_sample["alpha"] != drawn["alpha"]


def test_per_sample_draws_are_those_of_a_scene_without_the_key_and_ignore_sequences():
    frames = list(same_frames(1)[0])
    before = gpu_blur.synthesize(frames, scene(None), seed=3, sample_index=7)
    for sequence in (None, 0, 7, 99):
        now = gpu_blur.synthesize(frames, scene("per-sample"), seed=3, sample_index=7,
                                  sequence_index=sequence)
        assert np.array_equal(now.blurred, before.blurred) and now.params == before.params
    synth = gpu_blur.Synthesizer(scene("per-sample"), seed=3)
    batch = synth(same_frames(2), indices=[7, 8], sequences=[5, 5])
    assert batch.params[0] == before.params and batch.params[1] != before.params


def test_host_path_tiles_keep_the_sequence_s_draws():
    s = scene()
    whole = gpu_blur.Synthesizer(s, seed=4)(same_frames(3), indices=[0, 1, 2],
                                            sequences=[1, 1, 1])
    tiled = gpu_blur.Synthesizer(s, seed=4, schedule=Schedule((16, 16)))(
        same_frames(3), indices=[0, 1, 2], sequences=[1, 1, 1])
    assert tiled.params == whole.params
    assert np.array_equal(tiled.blurred, whole.blurred)


@pytest.mark.parametrize("spec", [s for s in SPECS if s != "numpy"][:1])
def test_a_device_batch_in_parts_takes_each_part_s_sequences(spec, monkeypatch):
    monkeypatch.setattr(gpu_blur.synthesis.resident, "STREAMED_BYTES", 0)
    name, precision = backend_of(spec)
    synth = gpu_blur.Synthesizer(scene(precision=precision), backend=name, seed=8)
    frames = same_frames(6)
    held = synth.pinned(frames.shape, np.uint8)
    held[...] = frames
    sequences = [0, 0, 0, 1, 1, 1]  # parts of STREAMED_SAMPLES (4): sequence 1 in both parts
    out = synth(held, indices=range(6), sequences=sequences, codes=True)
    whole = synth(frames, indices=range(6), sequences=sequences, codes=True)
    assert out.params == whole.params and np.array_equal(out.blurred, whole.blurred)
    assert shared_draws(out.params[2]) == shared_draws(out.params[0])
    assert shared_draws(out.params[3]) == shared_draws(out.params[5])
    assert shared_draws(out.params[3]) != shared_draws(out.params[2])


def test_per_sequence_draws_need_each_sample_s_sequence():
    frames = list(same_frames(1)[0])
    with pytest.raises(ValueError, match="give each sample's sequence index"):
        gpu_blur.synthesize(frames, scene(), sample_index=0)
    synth = gpu_blur.Synthesizer(scene())
    with pytest.raises(ValueError, match="give each sample's sequence index"):
        synth(same_frames(2), indices=[0, 1])
    with pytest.raises(ValueError, match=r"sequences: 1 sequence indices for a batch of 2"):
        synth(same_frames(2), indices=[0, 1], sequences=[0])
    with pytest.raises(ValueError, match=r"sequences\[1\] = 0.5: a sequence index is an int"):
        synth(same_frames(2), indices=[0, 1], sequences=[0, 0.5])


@pytest.mark.parametrize("key, value", [("draws", "per-sequence"), ("stride", 2)])
def test_the_keys_of_windows_need_blur_mode_average(key, value):
    with pytest.raises(SceneError, match=rf"blur.{key} = .* needs blur.mode = 'average'"):
        scene_from_dict({"blur": {key: value}})
    with pytest.raises(SceneError, match="blur.draws = 'per-window' is invalid"):
        scene_from_dict({"blur": {"mode": "average", "draws": "per-window"}})


def test_realistic_blur_takes_each_window_s_sequence():
    torch = pytest.importorskip("torch")
    from gpu_blur.torch import RealisticBlur

    blur = RealisticBlur(scene(), seed=2, backend="numpy", channels_first=False)
    frames = torch.from_numpy(same_frames(2))
    blurred, _ = blur(frames, indices=torch.tensor([0, 1]), sequences=torch.tensor([3, 3]))
    direct = gpu_blur.Synthesizer(scene(), seed=epoch_seed(2, 0))(
        same_frames(2), indices=[0, 1], sequences=[3, 3])
    assert np.array_equal(blurred.numpy(), direct.blurred)
    with pytest.raises(ValueError, match="give each sample's sequence index"):
        blur(frames, indices=torch.tensor([0, 1]))
