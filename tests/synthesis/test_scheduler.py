"""The host-side scheduler: memory budgets, spot checks, discovery of sequences, timings."""

import json
import re

import cv2
import numpy as np
import pytest
from conftest import BACKEND_SPECS, KERNEL_BACKEND_SPECS, make_backend, spec_backend, spec_dtype

import gpu_blur
from gpu_blur.backends import FRAMES_PER_LAUNCH
from gpu_blur.backends.numpy import NumpyBackend
from gpu_blur.cameras import scene_camera
from gpu_blur.cli import main
from gpu_blur.discovery import find_samples
from gpu_blur.scene import scene_from_dict
from gpu_blur.scheduler import (
    MIN_TILE,
    SPOT_CHECK_FAILED,
    Footprint,
    Schedule,
    SpotCheckError,
    parse_bytes,
    spot_check_tiles,
)
from gpu_blur.testhooks import TEST_FAULT
from gpu_blur.testing import tolerance
from gpu_blur.tiling import Region
from gpu_blur.timings import CATEGORIES

SEED, SAMPLE = 4, 17


@pytest.fixture(scope="module")
def small(coffee_rgb):
    """A 48 x 64 crop with clipped highlights (the spoon)."""
    return np.ascontiguousarray(coffee_rgb[240:288, 330:394])


def scene_for(spec, **sections):
    settings = {"output": {"precision": spec_dtype(spec)}}
    for name, values in sections.items():
        settings.setdefault(name, {}).update(values)
    return scene_from_dict(settings)


# -- memory budget -> tiles -------------------------------------------------------------------

@pytest.mark.parametrize("text, count", [("65536", 65536), ("64K", 2**16), ("512M", 2**29),
                                         ("2G", 2**31), ("1.5GiB", 3 * 2**29), ("3mb", 3 * 2**20),
                                         (4096, 4096)])
def test_memory_sizes_parse_with_binary_suffixes(text, count):
    assert parse_bytes(text) == count


@pytest.mark.parametrize("text", ["12X", "", "-5M", "0", "M"])
def test_bad_memory_sizes_are_refused_naming_the_value(text):
    with pytest.raises(ValueError, match="memory size|not a memory size"):
        parse_bytes(text)


def test_the_budget_formula_counts_halos_precision_and_streamed_frames():
    def footprint(**changes):
        base = {"height": 1000, "width": 1500, "mode": "trajectory", "raw_round_trip": True,
                "demosaic_halo": 2, "blur_halo": 10, "itemsize": 4}
        return Footprint(**{**base, **changes})

    f = footprint()
    # to_raw of a 100 x 100 tile: view (100 + 2 * 2 + 2)^2 pixels, 10 values each
    assert f.pass_bytes(100, 100)["to_raw"] == 10 * 106 * 106 * 4 + 9 * 4
    # accumulate (trajectory): 3 (S b + 2 S s + 6 V s) + 2 V s, S the view grown by the blur
    # halo, 2 V s the poses' weight sums; a float frame uploads in the compute type (b = s),
    # an 8-bit one in its codes (b = 1)
    assert f.pass_bytes(100, 100)["accumulate"] == 3 * 4 * (3 * 126 * 126 + 6 * 106 * 106) + (
        2 * 106 * 106 * 4)
    assert footprint(source_itemsize=1).pass_bytes(100, 100)["accumulate"] == 3 * (
        126 * 126 + 2 * 126 * 126 * 4 + 6 * 106 * 106 * 4) + 2 * 106 * 106 * 4
    assert footprint(blur_halo=30).tile_bytes(100, 100) > f.tile_bytes(100, 100)
    assert footprint(itemsize=8).tile_bytes(100, 100) == pytest.approx(
        2 * f.tile_bytes(100, 100), rel=0.01)
    # average of 9 8-bit frames: two stacks of FRAMES_PER_LAUNCH frames taking turns, a
    # compensated sum (sum, compensation, uint32 counts), linear + mask
    a = footprint(mode="average", blur_halo=0, frames=9, source_itemsize=1)
    assert a.pass_bytes(100, 100)["accumulate"] == 3 * 106 * 106 * (
        2 * FRAMES_PER_LAUNCH + 4 * 4 + 4)
    # as many frames as one stack holds: no running sums, one launch
    few = footprint(mode="average", blur_halo=0, frames=FRAMES_PER_LAUNCH, source_itemsize=1)
    assert few.pass_bytes(100, 100)["accumulate"] == 3 * 106 * 106 * (FRAMES_PER_LAUNCH + 2 * 4)
    # sides are clipped to the image: a tile as large as the image needs no more than it
    assert f.tile_bytes(5000, 5000) == f.tile_bytes(1000, 1500)


@pytest.mark.parametrize("budget", [300_000, 2_000_000, 9_000_000])
def test_the_budget_gives_the_largest_tile_that_fits(budget):
    f = Footprint(1000, 1500, "trajectory", True, 2, 10, 4)
    rows, cols = f.tile_for_budget(budget)
    assert f.tile_bytes(rows, cols) <= budget
    assert MIN_TILE <= rows <= 1000 and MIN_TILE <= cols <= 1500
    # one pixel more on either side does not fit
    grown = [f.tile_bytes(min(rows + 1, 1000), cols), f.tile_bytes(rows, min(cols + 1, 1500))]
    assert max(grown) > budget or (rows, cols) == (1000, 1500)
    assert f.tile_for_budget(f.tile_bytes(1000, 1500)) is None  # the whole image fits


@pytest.mark.parametrize("spec", BACKEND_SPECS)
def test_a_budget_smaller_than_the_image_completes_bit_for_bit(spec, small):
    scene = scene_for(spec)
    backend = spec.split("/")[0]
    whole = gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE, backend=backend)
    footprint = Footprint.of(whole.plan, whole.params, 48, 64, make_backend(spec).precision)
    budget = footprint.tile_bytes(24, 24)
    assert budget < footprint.tile_bytes(48, 64)
    tiled = gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE,
                                backend=backend, max_device_memory=budget)
    assert tiled.tiles > 1
    assert np.array_equal(tiled.blurred, whole.blurred)
    # an explicit tile wins over the budget
    explicit = gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE,
                                   backend=backend, tile=(48, 64), max_device_memory=budget)
    assert explicit.tiles == 1


def test_numpy_runs_its_whole_image_accumulate_pass_once_for_tiles_and_checks(small,
                                                                             monkeypatch):
    scene = scene_for("numpy")
    kw = {"seed": SEED, "sample_index": SAMPLE}
    whole = gpu_blur.synthesize([small], scene, **kw)
    calls = []
    real = NumpyBackend._accumulate
    monkeypatch.setattr(NumpyBackend, "_accumulate",
                        lambda self, *a: calls.append(a[-1]) or real(self, *a))
    tiled = gpu_blur.synthesize([small], scene, tile=(16, 16), verify=1.0, **kw)
    assert tiled.tiles == 12 and tiled.spot_checks == 12
    assert len(calls) == 1  # the run's, which is also the spot checks' reference pass
    assert np.array_equal(tiled.blurred, whole.blurred)


def test_a_budget_too_small_for_the_smallest_tile_names_the_minimum(small):
    scene = scene_from_dict({})
    whole = gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE)
    need = Footprint.of(whole.plan, whole.params, 48, 64, "float64").tile_bytes(16, 16)
    with pytest.raises(ValueError) as info:
        gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE,
                            max_device_memory=need - 1)
    message = str(info.value)
    assert "too small" in message and f"sample {SAMPLE}" in message
    assert f"{need:,} bytes" in message and "16 x 16" in message
    gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE, max_device_memory=need)


def test_generate_refuses_a_budget_below_any_tile_before_any_sample(tmp_path, capsys):
    assert main(["generate", "--output", str(tmp_path / "o"), "--max-device-memory", "2K",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--max-device-memory 2K" in err and "allow at least" in err
    assert not (tmp_path / "o" / "manifest.jsonl").exists()


# -- spot checks ---------------------------------------------------------------------------

def test_spot_checked_tiles_are_a_deterministic_fraction():
    chosen = spot_check_tiles(SEED, SAMPLE, 2000, 0.1)
    assert chosen == spot_check_tiles(SEED, SAMPLE, 2000, 0.1)
    assert 140 <= len(chosen) <= 260  # 200 expected, 5 standard deviations either side
    assert chosen != spot_check_tiles(SEED, SAMPLE + 1, 2000, 0.1)
    assert spot_check_tiles(SEED, SAMPLE, 50, 1.0) == list(range(50))
    assert spot_check_tiles(SEED, SAMPLE, 50, 0.0) == []
    with pytest.raises(ValueError, match="verify"):
        Schedule(verify=1.5)


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("case", [
    {},  # camera shake, Poisson-Gaussian noise, 8-bit output
    {"output": {"bits": 16, "crf": "a7r3"}, "noise": {"model": "gaussian"},
     "blur": {"mode": "kernel"}},
])
def test_spot_checks_pass_clean_runs(spec, case, small):
    scene = scene_for(spec, **case)
    result = gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE,
                                 backend=spec.split("/")[0], tile=(20, 30), verify=1.0)
    assert result.tiles == result.spot_checks == 9
    assert result.timings["checks"] > 0


@pytest.mark.parametrize("spec", [s for s in KERNEL_BACKEND_SPECS if s.endswith("float32")])
@pytest.mark.bits
def test_spot_checks_of_fast_maths_use_its_wider_rows(spec, small):
    # fast sRGB curves move the linear image by up to 3.3e-6 (Intel's OpenCL), over the float32
    # accumulate row (1e-6): a clean fast-maths run must still pass its checks
    scene = scene_for(spec, blur={"mode": "average", "frames": 1},
                      output={"fast_math": True, "crf": "a7r3", "bits": 0})
    result = gpu_blur.synthesize([small], scene, seed=SEED, sample_index=SAMPLE,
                                 backend=spec.split("/")[0], tile=(24, 32), verify=1.0)
    assert result.tiles == result.spot_checks == 4


@pytest.mark.parametrize("spec", [s for s in KERNEL_BACKEND_SPECS if s.endswith("float32")])
@pytest.mark.parametrize("sampler", [{}, {"poisson": "normal", "normal_above": 10.0}],
                         ids=["exact", "normal"])
def test_spot_checks_accept_poisson_counts_moved_by_float32_rates(spec, sampler, small):
    # float32 rates land on the other side of a Poisson count's step now and then (one count,
    # or a PTRS rejection decision); the check accepts exactly what the reference draws, with
    # the plan's sampler, for a rate within the to_raw row
    frames = [small, small[:, ::-1].copy()]
    scene = scene_for(spec, blur={"mode": "average", "frames": 2}, noise=sampler)
    device, reference = make_backend(spec), NumpyBackend()
    moved = 0
    for seed in range(4):
        result = gpu_blur.synthesize(frames, scene, seed=seed, sample_index=SAMPLE,
                                     backend=spec.split("/")[0], verify=1.0)
        assert result.spot_checks == 1
        camera = scene_camera(scene)
        linear, mask = device.accumulate(result.plan, result.params, frames, None,
                                         Region.whole(48, 64))
        got, _ = device.to_raw(result.plan, result.params, camera, linear, mask, seed=seed,
                               sample_index=SAMPLE)
        ref, _ = reference.to_raw(result.plan, result.params, camera, linear, mask, seed=seed,
                                  sample_index=SAMPLE)
        _, atol = tolerance("to_raw", spec_backend(spec), "float32")
        moved += int((np.abs(got - ref) > atol).sum())
    if moved == 0:
        pytest.skip("no Poisson count moved on this device: nothing to accept")


@pytest.fixture(scope="module")
def clean_runs():
    """spec -> the blurred image of the fault cases' run without a fault (the same for each)."""
    return {}


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
@pytest.mark.parametrize("fault, tile, pass_", [
    ("accumulate@5,7", "rows 0..15, columns 0..19", "accumulate pass's linear image"),
    ("to_raw@30,45", "rows 16..31, columns 40..59", "to_raw pass's RAW mosaic"),
    ("finish@47,63", "rows 32..47, columns 60..63", "finish pass's 8-bit image"),
])
def test_spot_checks_catch_a_planted_kernel_fault(spec, fault, tile, pass_, small, monkeypatch,
                                                  clean_runs):
    scene = scene_for(spec)
    run = {"seed": SEED, "sample_index": SAMPLE, "backend": spec.split("/")[0],
           "tile": (16, 20)}
    if spec not in clean_runs:
        clean_runs[spec] = gpu_blur.synthesize([small], scene, **run).blurred
    clean = clean_runs[spec]
    monkeypatch.setenv(TEST_FAULT, fault)
    faulty = gpu_blur.synthesize([small], scene, **run).blurred  # unchecked: silently wrong
    assert not np.array_equal(faulty, clean)
    with pytest.raises(SpotCheckError) as info:
        gpu_blur.synthesize([small], scene, verify=1.0, **run)
    message = str(info.value)
    assert message.startswith(SPOT_CHECK_FAILED) and f"sample {SAMPLE}" in message
    assert tile in message and pass_ in message
    assert info.value.sample_index == SAMPLE and info.value.region is not None


def small_photos(folder, crop, count=2):
    folder.mkdir(parents=True)
    for i in range(count):
        image = np.roll(crop, 5 * i, axis=1)
        cv2.imwrite(str(folder / f"p{i}.png"),
                    cv2.cvtColor((image * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))


@pytest.mark.skipif(not KERNEL_BACKEND_SPECS, reason="no kernel backend here")
def test_generate_verify_fails_samples_and_strict_stops_the_run(tmp_path, small, monkeypatch,
                                                                capsys):
    small_photos(tmp_path / "in", small)
    backend = KERNEL_BACKEND_SPECS[0].split("/")[0]
    args = ["generate", "--input", str(tmp_path / "in"), "--backend", backend, "--quiet",
            "--verify", "1", "--tile", "24", "32"]
    assert main([*args, "--output", str(tmp_path / "clean")]) == 0
    monkeypatch.setenv(TEST_FAULT, "to_raw@3,3")
    assert main([*args, "--output", str(tmp_path / "bad")]) == 1
    lines = [json.loads(x) for x in (tmp_path / "bad" / "manifest.jsonl").read_text().splitlines()]
    assert [x["status"] for x in lines] == ["failed", "failed"]
    assert all(x["error"].startswith(SPOT_CHECK_FAILED) for x in lines)
    capsys.readouterr()
    assert main([*args, "--output", str(tmp_path / "strict"), "--strict"]) == 2
    assert "--strict" in capsys.readouterr().err
    lines = (tmp_path / "strict" / "manifest.jsonl").read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["status"] == "failed"
    assert main(["generate", "--output", str(tmp_path / "o"), "--strict", "--quiet"]) == 2
    assert "give --verify FRACTION too" in capsys.readouterr().err


# -- discovery -----------------------------------------------------------------------------

def write_frames(folder, names, size=(12, 16), seed=0):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for name in names:
        cv2.imwrite(str(folder / name), rng.integers(0, 256, (*size, 3), np.uint8))


def rsblur_tree(root):
    """RSBlur_sharps-style samples with RSBlur's other folders beside the frames."""
    for session, sample in (("0001", "000001"), ("0001", "000002"), ("0003", "000007")):
        folder = root / session / sample
        write_frames(folder, [f"{i}.png" for i in range(9)])
        write_frames(folder / "avg65_img", ["avg_blur.png"])
        write_frames(folder / "avg65_mask_100", ["avg_blur.png"])
        write_frames(folder / "gt", ["gt_sharp.png"])
        write_frames(folder / "real_blur", ["real_blur.png"])


def test_rsblur_style_sample_folders_are_sequences(tmp_path):
    rsblur_tree(tmp_path / "RSBlur_sharps")
    write_frames(tmp_path / "GoPro" / "GOPR0372_07_00" / "sharp",
                 [f"{i:06d}.png" for i in range(9)])
    write_frames(tmp_path / "GoPro" / "GOPR0372_07_00" / "blur", ["000000.png"])
    write_frames(tmp_path / "notes" / "misc", ["a.png"])  # not a <session>/<id> folder
    specs = find_samples(tmp_path, "average", 9).take()
    assert [s.name for s in specs] == ["GoPro/GOPR0372_07_00/000000",
                                       "RSBlur_sharps/0001/000001/0",
                                       "RSBlur_sharps/0001/000002/0",
                                       "RSBlur_sharps/0003/000007/0"]
    for spec in specs[1:]:
        assert [p.name for p in spec.inputs] == [f"{i}.png" for i in range(9)]
        assert all(p.parent.parent.parent.name == "RSBlur_sharps" for p in spec.inputs)
    # a session folder, or one sample folder, as --input
    session = find_samples(tmp_path / "RSBlur_sharps" / "0001", "average", 9).take()
    assert [s.name for s in session] == ["000001/0", "000002/0"]
    sample = find_samples(tmp_path / "RSBlur_sharps" / "0003" / "000007", "average", 9).take()
    assert [s.name for s in sample] == ["000007/0"]


def test_generate_reads_an_rsblur_tree(tmp_path):
    rsblur_tree(tmp_path / "in")
    (tmp_path / "s.toml").write_text('[blur]\nmode = "average"\nframes = 9\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out), "--scene",
                 str(tmp_path / "s.toml"), "--quiet"]) == 0
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert [x["name"] for x in lines] == ["0001/000001/0", "0001/000002/0", "0003/000007/0"]
    assert all(len(x["inputs"]) == 9 and x["status"] == "ok" for x in lines)


@pytest.mark.parametrize("per_sequence, starts", [
    (None, [0, 3]),  # default: consecutive, non-overlapping
    (1, [0]),
    (2, [0, 4]),  # strided, first and last window
    (3, [0, 2, 4]),  # overlapping
    (6, [0, 1, 2, 2, 3, 4]),  # more windows than starts: a window again, with its own draws
])
def test_samples_per_sequence_spreads_windows_evenly(tmp_path, per_sequence, starts):
    write_frames(tmp_path / "seq" / "sharp", [f"{i:06d}.png" for i in range(7)])
    specs = find_samples(tmp_path, "average", 3, samples_per_sequence=per_sequence).take()
    assert [int(s.inputs[0].stem) for s in specs] == starts
    assert all(len(s.inputs) == 3 for s in specs)
    assert len({s.name for s in specs}) == len(specs)  # repeats are named apart
    assert [s.index for s in specs] == list(range(len(specs)))


def test_samples_per_sequence_on_the_command_line_and_resume(tmp_path, capsys):
    write_frames(tmp_path / "in" / "0002" / "000004", [f"{i}.png" for i in range(9)])
    (tmp_path / "s.toml").write_text('[blur]\nmode = "average"\nframes = 9\n')
    args = ["generate", "--input", str(tmp_path / "in"), "--output", str(tmp_path / "out"),
            "--scene", str(tmp_path / "s.toml"), "--quiet"]
    assert main([*args, "--samples-per-sequence", "3"]) == 0
    lines = [json.loads(x) for x in (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()]
    assert [x["name"] for x in lines] == ["0002/000004/0", "0002/000004/0_1", "0002/000004/0_2"]
    assert len({json.dumps(x["params"]) for x in lines}) == 3  # own draws each
    assert main([*args, "--samples-per-sequence", "2", "--resume"]) == 2
    assert "--samples-per-sequence" in capsys.readouterr().err


# -- where the time goes ---------------------------------------------------------------------

def test_synthesis_reports_its_time_by_category(small):
    result = gpu_blur.synthesize([small], scene_from_dict({}), seed=SEED, sample_index=SAMPLE,
                                 tile=(24, 32), verify=0.5)
    t = result.timings
    assert set(t) == {*CATEGORIES, "other", "total"}
    assert all(v >= 0 for v in t.values())
    assert t["kernels"] > 0 and t["writing"] == 0
    assert sum(t[k] for k in (*CATEGORIES, "other")) == pytest.approx(t["total"], rel=1e-6)


def test_generate_says_where_the_time_went(tmp_path, small, capsys):
    small_photos(tmp_path / "in", small, count=3)
    backend = KERNEL_BACKEND_SPECS[0].split("/")[0] if KERNEL_BACKEND_SPECS else "numpy"
    # one thread does every step, so each category is its own work (with I/O threads,
    # reading and writing are its waits for them: tests/synthesis/test_generate_pipeline.py)
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(tmp_path / "o"),
                 "--backend", backend, "--verify", "0.5", "--quiet", "--io-threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "wrote 3 samples (0 failed)" in out and "samples/s" in out
    total = float(re.search(r"where the time went \(([\d.]+) s\):", out)[1])
    wall = float(re.search(r"in ([\d.]+) s \(", out)[1])
    assert total == pytest.approx(wall, abs=0.051)
    seconds = {}
    for category in (*CATEGORIES, "other"):
        m = re.search(rf"^  {category} +([\d.]+) s +([\d.]+) %", out, re.MULTILINE)
        assert m, f"no {category} line in:\n{out}"
        seconds[category] = float(m[1])
    assert all(v >= 0 for v in seconds.values())
    assert seconds["reading"] > 0 and seconds["kernels"] > 0 and seconds["writing"] > 0
    assert sum(seconds.values()) == pytest.approx(total, abs=0.01)
