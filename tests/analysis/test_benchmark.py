"""gpu-blur bench (gpu_blur.analysis.bench): the report's structure, errors, availability, plot."""

from __future__ import annotations

import json
import math
import os
import sys

import cv2
import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS

from gpu_blur.analysis import bench as benchmark
from gpu_blur.cli import main
from gpu_blur.testing import tolerance

#: The kernel backend the quick run uses: the first one present (OpenCL, else Warp), float32.
KERNEL_BACKEND = KERNEL_BACKEND_SPECS[0].split("/")[0]
FAMILY = KERNEL_BACKEND.split(":")[0]
SIZE = (64, 48)
#: The base scene re-tones with the A7R3 polynomial: the whole float32 pipeline, noise off,
#: is within that row (its float32 Horner dominates).
PIPELINE_ATOL = tolerance("finish_crf_polynomial", FAMILY, "float32")[1]


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    """``gpu-blur bench --quick`` at 64 x 48 on numpy and one kernel backend: (report, files).

    numpy runs once per setting (``--reference-runs 1``, as on a GPU machine).
    """
    out = tmp_path_factory.mktemp("bench")
    status = main(["bench", "--size", f"{SIZE[0]}x{SIZE[1]}", "--quick", "--backends",
                   f"numpy,{KERNEL_BACKEND}", "--reference-runs", "1", "--output", str(out),
                   "--tag", "test"])
    assert status == 0
    report = json.loads((out / "accuracy_vs_time_test.json").read_text())
    return report, out


@pytest.mark.slow
def test_quick_run_writes_json_markdown_and_plot(quick_report):
    report, out = quick_report
    assert report["size"] == list(SIZE)
    assert list(report["devices"]) == ["numpy", KERNEL_BACKEND]
    markdown = (out / "accuracy_vs_time_test.md").read_text()
    assert "| knob | setting | backend |" in markdown
    summary = [line for line in markdown.splitlines() if line.startswith("| demosaic | bilinear |")
               and "`numpy`" not in line]
    assert len(summary) == 1 + 2  # the summary line, then one row per backend
    plot = cv2.imread(str(out / "accuracy_vs_time_test.png"))
    assert plot is not None and plot.std() > 0


@pytest.mark.slow
def test_quick_run_has_two_settings_of_every_knob_on_both_backends(quick_report):
    report, _ = quick_report
    expected = benchmark.quick_knobs()
    for setting in expected:
        backends = {r["backend"] for r in report["rows"]
                    if (r["knob"], r["setting"]) == (setting.knob, setting.label)}
        if setting.kernel_only and not setting.reference:
            assert backends in ({KERNEL_BACKEND}, {"-"}), setting
        else:
            assert backends in ({"numpy", KERNEL_BACKEND}, {"-"}), setting


@pytest.mark.slow
def test_report_names_the_code_that_ran_by_commit_and_file_digest(quick_report):
    report, out = quick_report
    assert report["source_digest"] == benchmark.source_digest()
    assert len(report["source_digest"]) == 64 and int(report["source_digest"], 16) >= 0
    assert report["source_digest"][:16] in (out / "accuracy_vs_time_test.md").read_text()


@pytest.mark.slow
def test_reference_runs_time_numpy_alone_and_the_table_says_so(quick_report):
    report, out = quick_report
    runs = {r["backend"]: len(r["runs_s"]) for r in report["rows"] if r["runs_s"]}
    assert runs == {"numpy": 1, KERNEL_BACKEND: benchmark.MIN_RUNS}
    assert report["reference_runs"] == 1 and report["runs"] == benchmark.MIN_RUNS
    assert "numpy: 1 run, no warm-up" in (out / "accuracy_vs_time_test.md").read_text()


@pytest.mark.slow
def test_quick_run_errors_are_finite_and_zero_for_the_reference(quick_report):
    report, _ = quick_report
    available = [r for r in report["rows"] if r["available"]]
    assert available
    for r in available:
        assert r["ms_per_megapixel"] > 0 and r["runs_s"], r
        assert math.isfinite(r["max_abs_error"]) and r["max_abs_error"] >= 0, r
        assert math.isfinite(r["residual_kl"]) and r["residual_kl"] >= 0, r
        if r["backend"] == "numpy" and r["reference"]:
            assert r["max_abs_error"] == 0 and r["residual_kl"] == 0 and r["psnr_db"] is None
    pipeline = {r["backend"]: r for r in report["side_by_side"]["pipeline"]}
    assert pipeline["numpy"]["max_abs_error"] == 0 and pipeline["numpy"]["residual_kl"] == 0
    assert pipeline[KERNEL_BACKEND]["max_abs_error"] <= PIPELINE_ATOL


@pytest.mark.slow
def test_a_setting_that_changes_the_output_shows_an_error(quick_report):
    report, _ = quick_report
    bilinear = [r for r in report["rows"] if r["setting"] == "bilinear"]
    # the knob's change is far beyond float32 rounding, on the reference and the kernels
    assert bilinear and all(r["max_abs_error"] > PIPELINE_ATOL for r in bilinear)
    normal = [r for r in report["rows"] if r["knob"] == "Poisson" and not r["reference"]]
    assert normal and all(r["residual_kl"] > 0 for r in normal)


@pytest.mark.slow
def test_side_by_side_rows_agree_with_the_reference_where_the_maths_is_the_same(quick_report):
    report, _ = quick_report
    demosaic = {r["method"]: r for r in report["side_by_side"]["demosaic"]}
    assert demosaic["gpu_blur numpy Malvar 2004 (float64)"]["max_abs_error"] == 0
    # colour-demosaicing's Malvar is the same filter (tests/reference/test_demosaic.py checks it)
    assert (demosaic["colour-demosaicing Malvar 2004 (float64)"]["max_abs_error"]
            <= tolerance("demosaic_malvar2004", "independent", "float64")[1])
    assert (demosaic[f"gpu_blur {KERNEL_BACKEND} Malvar 2004 (float32)"]["max_abs_error"]
            <= tolerance("demosaic_malvar2004", FAMILY, "float32")[1])
    blur = {r["method"]: r for r in report["side_by_side"]["kernel_blur"]}
    assert (blur["OpenCV filter2D (float64)"]["max_abs_error"]
            <= tolerance("blur_convolve", "independent", "float64")[1])
    assert (blur[f"gpu_blur {KERNEL_BACKEND} kernel blur (float32)"]["max_abs_error"]
            <= tolerance("accumulate", FAMILY, "float32")[1])


def test_a_knob_the_scene_does_not_know_is_reported_not_available():
    knobs = [benchmark.Setting("future", "accurate", reference=True),
             benchmark.Setting("future", "unknown key", {"noise": {"no_such_key": 1}})]
    report = benchmark.run_benchmark(SIZE, ["numpy"], knobs=knobs, log=lambda line: None)
    missing = [r for r in report["rows"] if r["setting"] == "unknown key"]
    assert len(missing) == 1 and not missing[0]["available"]
    assert "not available" in missing[0]["note"] and "noise.no_such_key" in missing[0]["note"]
    assert missing[0]["ms_per_megapixel"] is None and missing[0]["max_abs_error"] is None


def test_knobs_are_chosen_by_name_in_any_case():
    chosen = benchmark.select_knobs(["Motion", "tile"])
    assert {s.knob for s in chosen} == {"motion", "tile"}
    assert chosen == [s for s in benchmark.KNOBS if s.knob in ("motion", "tile")]


def test_pareto_front_keeps_the_points_no_other_beats_in_time_and_error():
    points = [(1.0, 5.0), (2.0, 3.0), (2.5, 4.0), (3.0, 1.0), (0.5, 9.0), (3.0, 1.0)]
    assert benchmark.pareto_front(points) == [4, 0, 1, 3]


@pytest.mark.slow
def test_plot_is_drawn_with_opencv_without_matplotlib(quick_report, tmp_path, monkeypatch):
    report, _ = quick_report
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib fails
    path = tmp_path / "plot.png"
    assert benchmark.write_plot(report["rows"], path, "title") == "cv2"
    image = cv2.imread(str(path))
    assert image is not None and np.count_nonzero(image < 128) > 1000


@pytest.mark.parametrize("argv, message", [
    (["--size", "63x48"], "63 x 48"),
    (["--size", "64x48", "--runs", "3"], "runs = 3"),
    (["--size", "64x48", "--reference-runs", "0"], "reference runs = 0"),
    (["--size", "64x48", "--knobs", "precision,colour"], "--knobs: colour; known: precision"),
    (["--size", "64x48", "--backends", "numpy,opencl:9:9"], "opencl:9:9"),
])
def test_bad_options_are_refused_naming_the_value(argv, message, capsys, tmp_path):
    assert main(["bench", *argv, "--output", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err


def test_output_files_are_tagged_cpu_or_by_the_first_gpu():
    cpu = {"numpy": {"device": "numpy float64 on x", "kind": "CPU"},
           "warp:cpu": {"device": "CPU x (Warp)", "kind": "CPU"}}
    assert benchmark.device_tag(cpu) == "cpu"
    gpu = cpu | {"opencl:0:0": {"device": "GPU NVIDIA H200 (NVIDIA CUDA)", "kind": "GPU"}}
    assert benchmark.device_tag(gpu) == "nvidia-h200"


@pytest.mark.slow
def test_each_row_times_its_setting_and_the_accurate_one_equally_often(quick_report):
    report, out = quick_report
    for r in report["rows"]:
        if not r["available"]:
            continue
        assert len(r["accurate_runs_s"]) == len(r["runs_s"]), r
        median = sorted(r["runs_s"])[len(r["runs_s"]) // 2]
        accurate = sorted(r["accurate_runs_s"])[len(r["runs_s"]) // 2]
        assert r["time_vs_accurate"] == pytest.approx(median / accurate, rel=1e-3), r
        if r["reference"]:
            assert r["accurate_runs_s"] == r["runs_s"] and r["time_vs_accurate"] == 1
    assert "| time / accurate |" in (out / "accuracy_vs_time_test.md").read_text()


def test_a_setting_and_its_accurate_one_run_in_turn(monkeypatch):
    from gpu_blur.analysis.bench import measure

    calls = []

    def fake(spec, frames, setting, *extra):
        calls.append((setting.label, bool(extra)))
        return np.zeros((2, 2, 3), np.float32)

    monkeypatch.setattr(measure, "synthesize_setting", fake)
    knobs = [s for s in benchmark.KNOBS if s.knob == "demosaic"]
    runner = measure.Runner([np.zeros((48, 64, 3), np.uint8)], {"numpy": {}}, knobs, runs=5,
                            log=lambda line: None)
    runner.row(knobs[0], "numpy")
    calls.clear()
    runner.row(knobs[1], "numpy")
    timed = [label for label, clean in calls if not clean]
    # the warm-up of the new setting, then five rounds of (setting, accurate)
    assert timed == ["bilinear"] + ["bilinear", "Malvar 2004"] * 5


def bench_args(out, *extra):
    return ["bench", "--size", "64x48", "--backends", "numpy", "--knobs", "demosaic",
            "--reference-runs", "1", "--output", str(out), "--tag", "t", *extra]


def test_an_interrupted_bench_keeps_its_rows_and_the_same_command_goes_on(tmp_path,
                                                                          monkeypatch, capsys):
    from gpu_blur.analysis.bench.measure import Runner

    measured, real_row = [], Runner.row

    def row(self, setting, spec):
        if len(measured) == 1:
            raise KeyboardInterrupt  # Ctrl-C during the second row
        measured.append(setting.label)
        return real_row(self, setting, spec)

    monkeypatch.setattr(Runner, "row", row)
    path = tmp_path / "accuracy_vs_time_t.json"
    assert main(bench_args(tmp_path)) == 130
    assert "run the same command to go on" in capsys.readouterr().err
    partial = json.loads(path.read_text())
    assert partial["complete"] is False and [r["setting"] for r in partial["rows"]] == [
        "Malvar 2004"]

    measured.clear()
    monkeypatch.setattr(Runner, "row", lambda self, setting, spec: measured.append(
        setting.label) or real_row(self, setting, spec))
    assert main(bench_args(tmp_path)) == 0
    assert measured == ["bilinear"]  # the finished row is kept, not measured again
    report = json.loads(path.read_text())
    assert report["complete"] is True and report["rows"][0] == partial["rows"][0]
    assert [r["setting"] for r in report["rows"]] == ["Malvar 2004", "bilinear"]
    captured = capsys.readouterr()
    assert f"resuming {path}: 1 of 5 steps done" in captured.out
    # the progress bar: steps done of all, elapsed and remaining time
    assert "bench: 5/5 steps 100%" in captured.err
    assert "00:00 left]" in captured.err


@pytest.mark.parametrize("extra, message", [
    (["--runs", "6"], "another --runs: runs = 5 (this run: 6)"),
    (["--knobs", "tile"], "another --knobs: settings = "),
])
def test_a_rerun_with_other_options_is_refused_naming_the_option(tmp_path, extra, message,
                                                                 capsys):
    path = tmp_path / "accuracy_vs_time_t.json"
    assert main(bench_args(tmp_path)) == 0
    before = path.read_text()
    argv = bench_args(tmp_path)
    if extra[0] == "--knobs":
        argv[argv.index("--knobs") + 1] = extra[1]
    else:
        argv += extra
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{path} holds a bench run with {message}" in err and "another --output" in err
    assert path.read_text() == before


def test_quick_runs_small_frames_unless_a_size_is_given(monkeypatch, capsys, tmp_path):
    from gpu_blur.analysis.bench import run

    def stop(width, height):
        raise ValueError(f"frames of {width} x {height}")

    monkeypatch.setattr(run, "make_frames", stop)
    for size, expected in ([], benchmark.QUICK_SIZE), (["--size", "96x64"], (96, 64)):
        assert main(["bench", "--quick", "--backends", "numpy", *size, "--output",
                     str(tmp_path)]) == 2
        assert f"frames of {expected[0]} x {expected[1]}" in capsys.readouterr().err


def test_the_time_left_weighs_rows_by_their_frame_interpolation():
    from gpu_blur.analysis.bench.measure import Runner

    # 8x (accurate), 4x, 2x, 1x, auto
    motion = [s for s in benchmark.KNOBS if s.knob == "motion"]
    runner = Runner([np.zeros((48, 64, 3), np.uint8)], {"numpy": {}}, motion, runs=5)
    # a row runs its setting and the accurate one; k-fold interpolation costs about 3 k, auto
    # as much as its largest factor (8)
    assert [runner.cost(s, "numpy") for s in motion] == [24, 12 + 24, 6 + 24, 1 + 24, 24 + 24]


def test_a_second_bench_on_the_same_report_is_refused_while_the_first_runs(tmp_path, capsys):
    from gpu_blur.locking import take_lock

    path = tmp_path / "accuracy_vs_time_t.json"
    holder = take_lock(path.with_name(f".{path.name}.lock"), "test", "")  # a first run's lock
    try:
        assert main(bench_args(tmp_path)) == 2
    finally:
        os.close(holder)
    err = capsys.readouterr().err
    assert f"bench report {path}: another gpu-blur run is writing it" in err
    assert f"pid {os.getpid()}" in err and not path.exists()
    assert main(bench_args(tmp_path)) == 0  # the lock ends with its holder


POCL = "CPU pthread-skylake-avx512-AMD EPYC (Portable Computing Language)"  # 66 characters


def crowded_rows() -> list[dict]:
    """Rows whose Pareto front is five points within 10 % in time and error, on a device with
    a long name, beside a slow numpy reference."""
    def row(backend, device, knob, setting, ms, error):
        return {"knob": knob, "setting": setting, "backend": backend, "device": device,
                "available": True, "ms_per_megapixel": ms, "max_abs_error": error,
                "residual_kl": error / 10}

    rows = [row("opencl:1:0", POCL, "CRF table", f"{n} nodes", 20 + 0.5 * i, 3e-9 - 1e-10 * i)
            for i, n in enumerate((256, 512, 1024, 2048, 4096))]
    rows += [row("opencl:1:0", POCL, "precision", "float64", 40.0, 0.0),
             row("numpy", "numpy float64 on AMD EPYC", "precision", "float64", 2000.0, 0.0),
             row("numpy", "numpy float64 on AMD EPYC", "demosaic", "bilinear", 1900.0, 0.3)]
    return rows


def overlapping(boxes) -> list[tuple[int, int]]:
    """Pairs of (x0, y0, x1, y1) boxes that share area."""
    return [(i, j) for i, a in enumerate(boxes) for j, b in enumerate(boxes[:i])
            if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]]


def test_plot_labels_every_front_point_apart_and_keeps_the_legend_off_the_panels():
    pytest.importorskip("matplotlib")
    from matplotlib.text import Text

    from gpu_blur.analysis.bench import plot

    fig = plot.figure(crowded_rows(), "title")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        labels = [t for t in ax.texts if t.get_text()]
        assert sorted(t.get_text() for t in labels) == sorted(
            [f"opencl:1:0 CRF table: {n} nodes" for n in (256, 512, 1024, 2048, 4096)]
            + ["opencl:1:0 precision: float64"])
        # the text itself (an annotation's own extent takes in its leader line)
        boxes = [tuple(Text.get_window_extent(t, renderer).extents) for t in labels]
        assert overlapping(boxes) == []
    legend_text = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert f"opencl:1:0: {POCL}" in legend_text and "CRF table" in legend_text
    panels = [tuple(ax.get_window_extent(renderer).extents) for ax in fig.axes]
    legends = [tuple(legend.get_window_extent(renderer).extents) for legend in fig.legends]
    assert overlapping(panels + legends) == []


def test_opencv_plot_writes_every_name_in_full_and_every_label_apart_inside_the_image(
        tmp_path, monkeypatch):
    from gpu_blur.analysis.bench import plot

    written, put_text = [], cv2.putText

    def record(img, text, org, font, scale, colour, thickness=1, *rest):
        (w, h), base = cv2.getTextSize(text, font, scale, thickness)
        written.append((text, (org[0], org[1] - h, org[0] + w, org[1] + base)))
        return put_text(img, text, org, font, scale, colour, thickness, *rest)

    monkeypatch.setattr(cv2, "putText", record)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    path = tmp_path / "plot.png"
    assert plot.write_plot(crowded_rows(), path, "title") == "cv2"
    height, width = cv2.imread(str(path)).shape[:2]
    texts = [t for t, _ in written]
    assert f"opencl:1:0: {POCL}" in texts and "numpy: numpy float64 on AMD EPYC" in texts
    labels = [box for t, box in written if t.startswith("opencl:1:0 ")]
    assert len(labels) == 2 * 6  # both panels label their six front points
    assert overlapping(labels[:6]) == [] and overlapping(labels[6:]) == []
    for text, (x0, y0, x1, y1) in written:
        assert 0 <= x0 and x1 <= width and 0 <= y0 and y1 <= height, text
