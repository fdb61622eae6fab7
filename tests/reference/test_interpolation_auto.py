"""Adaptive frame interpolation: ``blur.interpolation = "auto"`` (reference.interpolate, 6-7).

The motion measure and the per-gap factor; still gaps get no flows; per-gap factors weigh every
gap the same time; one factor in every gap gives the fixed factor's bits on every backend; the
factors reach the sample's params; the scene key and its limit. Regions: a still part of a
moving sequence gets factor 1; each region averages with the bits of its own factors applied
to the whole frame, on every backend; tiles cutting regions give the whole image's bits.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS

from gpu_blur.discovery import default_photo
from gpu_blur.image_arrays import unit_values
from gpu_blur.image_reading import read_image
from gpu_blur.planning import plan
from gpu_blur.reference import flow
from gpu_blur.reference.flow import gap_factor, gap_motion, sequence_flows
from gpu_blur.reference.interpolate import gap_weights, interpolated_average
from gpu_blur.reference.transfer import srgb_to_linear
from gpu_blur.scene import SceneError, scene_from_dict
from gpu_blur.synthesis import Synthesizer

#: Frames cut from the built-in photo: 96 x 160 pixels.
H, W = 96, 160
#: Pixels the content moves per frame in the moving part of :func:`still_then_pan`.
PAN_PX = 6


def panned(offsets) -> list[np.ndarray]:
    """uint8 frames: windows of the photo ``offsets[i]`` pixels right of the first."""
    photo = read_image(default_photo())
    return [np.ascontiguousarray(photo[100:100 + H, 40 + x:40 + x + W]) for x in offsets]


def still_then_pan(still: int = 3, moving: int = 3) -> list[np.ndarray]:
    """uint8 frames: ``still`` gaps without motion, then ``moving`` gaps panning PAN_PX each."""
    return panned([0] * (still + 1) + [PAN_PX * (i + 1) for i in range(moving)])


def average_scene(interpolation, tolerance: float = 1.0, frames: int = 7,
                  precision: str = "float64"):
    return scene_from_dict({"blur": {"mode": "average", "frames": frames,
                                     "interpolation": interpolation,
                                     "interpolation_tolerance": tolerance},
                            "saturation": {"mode": "off"}, "noise": {"model": "none"},
                            "output": {"precision": precision}})


def synthesizer(scene_args: tuple, spec: str) -> Synthesizer:
    """A Synthesizer for a backend spec ``name[/precision]`` of conftest."""
    name, _, precision = spec.partition("/")
    return Synthesizer(average_scene(*scene_args, precision=precision or "float64"),
                       backend=name)


def test_gap_factor_is_the_fewest_that_keep_the_step_under_the_tolerance():
    assert gap_factor(0.0, 1.0) == 1
    assert gap_factor(1.0, 1.0) == 1
    assert gap_factor(1.5, 1.0) == 2
    assert gap_factor(4.0, 1.0) == 4
    assert gap_factor(4.1, 1.0) == 8
    assert gap_factor(100.0, 1.0) == 8  # the most offered, though the step stays above
    assert gap_factor(6.0, 3.0) == 2
    with pytest.raises(ValueError, match="tolerance must be > 0"):
        gap_factor(1.0, 0.0)


def test_gap_motion_measures_a_pan_and_zero_without_motion():
    frames = [unit_values(f) for f in still_then_pan(1, 1)]
    assert gap_motion(frames[0], frames[0]) == 0.0
    assert abs(gap_motion(frames[1], frames[2]) - PAN_PX) < 1.0


def test_still_gaps_get_factor_1_and_no_flow_is_computed_for_them(monkeypatch):
    frames = [unit_values(f) for f in still_then_pan(2, 2)]
    factors = flow.adaptive_factors(frames, 1.0)
    assert factors == (1, 1, 8, 8)
    calls, grays = [], []
    real_flow, real_gray = flow._flow, flow.gray8
    monkeypatch.setattr(flow, "_flow", lambda a, b, m: calls.append(1) or real_flow(a, b, m))
    monkeypatch.setattr(flow, "gray8", lambda f: grays.append(1) or real_gray(f))
    flows = sequence_flows(frames, "dis", factors)
    assert len(calls) == 4  # forward and backward of the two moving gaps only
    assert len(grays) == 4  # frames 0 (for the size), 2, 3 and 4, each once
    assert not flows[:2].any() and flows[2:].any()


def test_flows_from_stored_codes_are_the_flows_from_their_values():
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, axis=2)
    assert np.array_equal(flow.gray8(codes), flow.gray8(codes / 255.0))
    frames = still_then_pan(0, 2)
    from gpu_blur.backends.flows import UnitFrames

    assert np.array_equal(sequence_flows(UnitFrames(frames)),
                          sequence_flows([unit_values(f) for f in frames]))
    assert np.array_equal(flow.region_factors(UnitFrames(frames), 1.0, SIDE).factors,
                          flow.region_factors([unit_values(f) for f in frames], 1.0,
                                                     SIDE).factors)


def test_flows_made_in_threads_are_each_pairs_own_flow(monkeypatch):
    frames = [unit_values(f) for f in still_then_pan(0, 3)]
    flows = sequence_flows(frames)
    for i in range(3):
        assert np.array_equal(flows[i, 0], flow.optical_flow(frames[i], frames[i + 1]))
        assert np.array_equal(flows[i, 1], flow.optical_flow(frames[i + 1], frames[i]))
    monkeypatch.setattr(flow.os, "cpu_count", lambda: 1)  # one thread: the same bits
    assert np.array_equal(sequence_flows(frames), flows)


def test_gap_weights_give_every_gap_the_time_of_the_largest_factor():
    assert gap_weights((1, 2, 8)) == ((8, 4, 1), 25)
    assert gap_weights((4, 4)) == ((1, 1), 9)
    assert gap_weights(()) == ((), 1)


def test_mixed_factors_average_each_gap_over_equal_time():
    # three flat frames, flows zero: the intermediate at t = 1/2 of gap 1 is the sRGB blend
    values = (0.2, 0.5, 0.9)
    frames = [np.full((4, 5, 3), v) for v in values]
    flows = np.zeros((2, 2, 4, 5, 2), np.float32)
    blurred, _ = interpolated_average(frames, (1, 2), flows)
    # gap 0 at factor 1 stands for 2 frames of gap 1's rate, the last frame for 1: 5 in all
    lin = [float(srgb_to_linear(np.float64(v))) for v in (0.2, 0.5, 0.7, 0.9)]
    expected = (2 * lin[0] + lin[1] + lin[2] + lin[3]) / 5
    np.testing.assert_allclose(blurred, expected, rtol=1e-14)


@pytest.mark.parametrize("factor", [2, 8])
def test_one_factor_in_every_gap_is_the_fixed_factor_bit_for_bit_in_the_reference(factor):
    frames = [unit_values(f) for f in still_then_pan(1, 2)]
    flows = sequence_flows(frames)
    fixed = interpolated_average(frames, factor, flows)
    per_gap = interpolated_average(frames, (factor,) * 3, flows)
    for a, b in zip(fixed, per_gap, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("spec", ["numpy", *KERNEL_BACKEND_SPECS])
def test_auto_with_every_gap_at_8_gives_the_bits_of_factor_8(spec):
    frames = still_then_pan(0, 3)  # every gap moves: a tiny tolerance asks 8x everywhere
    auto = synthesizer(("auto", 1e-3, 4), spec).sample(frames)
    fixed = synthesizer((8, 1.0, 4), spec).sample(frames)
    assert auto.params["interpolation_factors"] == [8, 8, 8]
    assert np.array_equal(auto.blurred, fixed.blurred)
    assert np.array_equal(auto.mask, fixed.mask)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_kernel_backends_average_mixed_factors_as_the_reference(spec):
    frames = panned([0, 0, 1, 9])  # still, slow, fast: intermediates of weights 1 and 4
    reference = synthesizer(("auto", 1.0, 4), "numpy").sample(frames)
    kernel = synthesizer(("auto", 1.0, 4), spec).sample(frames)
    assert reference.params["interpolation_factors"] == [1, 2, 8]
    assert kernel.params["interpolation_factors"] == [1, 2, 8]
    # 8-bit outputs of a float32 kernel and the float64 reference: at most one code apart
    assert np.abs(kernel.blurred - reference.blurred).max() <= 1 / 255 + 1e-6


def test_auto_without_motion_runs_the_plain_average():
    frames = still_then_pan(3, 0)
    auto = Synthesizer(average_scene("auto", 1.0, 4), backend="numpy").sample(frames)
    plain = Synthesizer(average_scene(1, frames=4), backend="numpy").sample(frames)
    assert auto.params["interpolation_factors"] == [1, 1, 1]
    assert np.array_equal(auto.blurred, plain.blurred)


def test_scene_takes_auto_with_a_positive_tolerance_in_mode_average_only():
    stage = plan(average_scene("auto", 0.5))["blur"]
    assert stage.options == {"interpolation": "auto", "flow": "dis", "tolerance": 0.5,
                             "region": 64}
    assert "0.5 px a step" in stage.reason
    with pytest.raises(SceneError, match="interpolation_tolerance = 0 is invalid"):
        average_scene("auto", 0)
    with pytest.raises(SceneError, match="needs blur.mode = 'average'"):
        scene_from_dict({"blur": {"mode": "trajectory", "interpolation": "auto"}})


def test_generate_records_the_factors_of_each_sample_in_the_manifest(tmp_path):
    import json

    import cv2

    from gpu_blur.cli import main

    folder = tmp_path / "in" / "GOPR0001" / "sharp"
    folder.mkdir(parents=True)
    for i, frame in enumerate(still_then_pan(1, 1)):
        cv2.imwrite(str(folder / f"{i:06d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    scene = tmp_path / "auto.toml"
    scene.write_text('[blur]\nmode = "average"\nframes = 3\ninterpolation = "auto"\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--scene", str(scene), "--quiet"]) == 0
    (line,) = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert line["status"] == "ok" and "flows" not in line["params"]
    assert line["params"]["interpolation_factors"] == [1, 8]
    # each gap's factor per 64 px region (96 x 160: 2 x 3 regions) in the arrays file
    assert "interpolation_regions" not in line["params"]
    arrays = np.load(out / line["arrays"])
    regions = arrays["interpolation_regions"]
    assert regions.shape == (2, 2, 3) and regions.dtype == np.uint8
    assert (regions[0] == 1).all() and regions[1].max() == 8
    assert "frame-rate factor" in str(arrays["interpolation_regions_convention"])
    # what the sample skipped and why
    assert line["skipped"]["gaussian_noise"] == "noise.model = poisson-gaussian"


def test_the_sample_plan_shows_the_factors_it_ran():
    result = synthesizer(("auto", 1.0, 4), "numpy").sample(still_then_pan(2, 1))
    assert result.plan["blur"].options["factors"] == (1, 1, 8)
    assert "this sample's factors per gap: 1, 1, 8" in str(result.plan)
    assert result.params["interpolation_factors"] == [1, 1, 8]


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_tiled_auto_with_spot_checks_equals_the_whole_image(spec):
    from gpu_blur.scheduler import Schedule

    frames = panned([0, 0, 1, 9])
    name, _, precision = spec.partition("/")
    scene = average_scene("auto", 1.0, 4, precision=precision or "float64")
    whole = Synthesizer(scene, backend=name).sample(frames)
    tiled = Synthesizer(scene, backend=name,
                        schedule=Schedule(tile=(48, 64), verify=1.0)).sample(frames)
    assert tiled.tiles == 6 and tiled.spot_checks == 6
    assert np.array_equal(tiled.blurred, whole.blurred)


# -- regions: each square of the frame gets its own factor per gap (module step 7) ----------
#: Region side of the tests below: 96 x 160 frames hold 3 x 5 regions.
SIDE = 32


def half_moving(gaps: int, moving_from: int = 0) -> list[np.ndarray]:
    """uint8 frames whose left half stays still and right half pans PAN_PX a frame.

    The right half starts panning at gap ``moving_from``.
    """
    photo = read_image(default_photo())
    still = photo[100:100 + H, 40:40 + W // 2]
    frames = []
    for i in range(gaps + 1):
        x = 40 + W // 2 + PAN_PX * max(0, i - moving_from)
        frames.append(np.ascontiguousarray(np.concatenate(
            [still, photo[100:100 + H, x:x + W // 2]], axis=1)))
    return frames


def region_scene(precision: str = "float64", side: int = SIDE, frames: int = 4):
    return scene_from_dict({"blur": {"mode": "average", "frames": frames,
                                     "interpolation": "auto", "interpolation_region": side},
                            "saturation": {"mode": "off"}, "noise": {"model": "none"},
                            "output": {"precision": precision}})


def test_still_regions_away_from_moving_ones_get_factor_1():
    frames = [unit_values(f) for f in half_moving(2)]
    regions = flow.region_factors(frames, 1.0, SIDE)
    assert regions.factors.shape == (2, 3, 5) and regions.factors.dtype == np.uint8
    # columns 0..79 stand still, 80..159 pan 6 px a frame: the region at 64..95 holds both,
    # the one at 32..63 takes its neighbour's factor, the one at 0..31 stays at 1
    assert (regions.factors[:, :, 0] == 1).all()
    assert (regions.factors[:, :, 1:] == 8).all()
    assert regions.gaps == (8, 8)
    own = flow.region_motion(frames[0], frames[1], SIDE)
    assert (own[:, :2] < 0.5).all() and (own[:, 3:] > 5).all()
    # without regions the whole frame takes the moving half's factor
    assert flow.adaptive_factors(frames, 1.0) == (8, 8)


def test_region_motion_of_the_whole_frame_is_the_gap_motion():
    frames = [unit_values(f) for f in half_moving(1)]
    assert flow.region_motion(*frames, 0)[0, 0] == gap_motion(*frames)
    with pytest.raises(ValueError, match="multiple of 16"):
        flow.region_motion(*frames, 24)


def test_a_sliver_past_the_shrunk_frame_takes_its_neighbours_motion():
    # 96 x 97 frames shrink by 2 (a quarter would be under 32 rows) to 48 x 48: the seventh
    # column of 16 px regions is column 96 alone, which no shrunk pixel covers
    frames = [unit_values(f)[:, :97] for f in half_moving(1)]
    motion = flow.region_motion(*frames, 16)
    assert motion.shape == (6, 7)
    assert np.array_equal(motion[:, 6], motion[:, 5])


def test_each_region_averages_bit_for_bit_as_a_frame_with_its_factors_everywhere():
    frames = [unit_values(f) for f in half_moving(2, moving_from=1)]
    flows = sequence_flows(frames)
    # gap 0 at 8x everywhere (so every region's largest is the sample's M = 8); gap 1 at 1x on
    # the left, 8x in the middle column, 4x on the right
    maps = np.empty((2, 3, 5), np.uint8)
    maps[0] = 8
    maps[1] = [1, 1, 8, 4, 4]
    blurred, mask = interpolated_average(frames, flow.RegionFactors(SIDE, maps), flows)
    for columns, gaps in ((slice(0, 64), (8, 1)), (slice(64, 96), (8, 8)),
                          (slice(96, 160), (8, 4))):
        own_blurred, own_mask = interpolated_average(frames, gaps, flows)
        assert np.array_equal(blurred[:, columns], own_blurred[:, columns])
        assert np.array_equal(mask[:, columns], own_mask[:, columns])


@pytest.mark.parametrize("spec", ["numpy", *KERNEL_BACKEND_SPECS])
def test_a_backend_averages_each_region_with_the_bits_of_its_factors_everywhere(spec):
    from conftest import make_backend

    from gpu_blur.backends.flows import FACTORS_KEY, REGIONS_KEY
    from gpu_blur.tiling import Region

    frames = half_moving(2, moving_from=1)
    flows = sequence_flows([unit_values(f) for f in frames])
    maps = np.empty((2, 3, 5), np.uint8)
    maps[0] = 8
    maps[1] = [1, 1, 8, 4, 4]
    backend = make_backend(spec)
    scene = region_scene(spec.partition("/")[2] or "float64", frames=3)
    whole = Region.whole(H, W)

    def averaged(factors, regions=None):
        params = {"flows": flows, FACTORS_KEY: list(factors)}
        if regions is not None:
            params[REGIONS_KEY] = regions
        sample_plan = plan(scene if regions is not None else scene_without_regions(scene),
                           interpolation_factors=factors)
        return backend.accumulate(sample_plan, params, frames, None, whole)

    linear, mask = averaged((8, 8), maps)
    for columns, gaps in ((slice(0, 64), (8, 1)), (slice(64, 96), (8, 8)),
                          (slice(96, 160), (8, 4))):
        own_linear, own_mask = averaged(gaps)
        assert np.array_equal(linear[:, columns], own_linear[:, columns])
        assert np.array_equal(mask[:, columns], own_mask[:, columns])


def scene_without_regions(scene):
    import dataclasses

    return dataclasses.replace(scene, blur=dataclasses.replace(scene.blur,
                                                               interpolation_region=0))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_kernel_backends_average_regions_as_the_reference(spec):
    frames = half_moving(3, moving_from=1)
    name, _, precision = spec.partition("/")
    reference = Synthesizer(region_scene(), backend="numpy").sample(frames)
    kernel = Synthesizer(region_scene(precision or "float64"), backend=name).sample(frames)
    assert np.array_equal(reference.params["interpolation_regions"],
                          kernel.params["interpolation_regions"])
    assert (reference.params["interpolation_regions"][:, :, 0] == 1).all()
    assert np.abs(kernel.blurred - reference.blurred).max() <= 1 / 255 + 1e-6


@pytest.mark.parametrize("spec", ["numpy", *KERNEL_BACKEND_SPECS])
def test_tiles_across_regions_give_the_whole_image_bit_for_bit(spec):
    from gpu_blur.scheduler import Schedule

    frames = half_moving(3, moving_from=1)
    name, _, precision = spec.partition("/")
    scene = region_scene(precision or "float64")
    whole = Synthesizer(scene, backend=name).sample(frames)
    # 40 x 56 tiles cut the 32 px regions anywhere
    tiled = Synthesizer(scene, backend=name, schedule=Schedule(tile=(40, 56))).sample(frames)
    assert tiled.tiles == 9
    assert np.array_equal(tiled.blurred, whole.blurred)
    assert np.array_equal(tiled.mask, whole.mask)


def test_scene_region_is_a_multiple_of_16_and_0_measures_whole_frames():
    with pytest.raises(SceneError, match="interpolation_region = 24 is invalid"):
        region_scene(side=24)
    frames = half_moving(2)
    result = Synthesizer(region_scene(side=0, frames=3), backend="numpy").sample(frames)
    assert result.params["interpolation_factors"] == [8, 8]
    assert "interpolation_regions" not in result.params
    assert "in 32 px squares" in str(plan(region_scene()))
