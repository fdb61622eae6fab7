"""Running the benchmark: :func:`run_benchmark`, and ``gpu-blur bench``'s options."""

from __future__ import annotations

import argparse
import platform
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from gpu_blur.analysis.bench.host import (
    choose_backends,
    cpu_name,
    device_tag,
    load_average,
    source_commit,
    source_digest,
)
from gpu_blur.analysis.bench.measure import Runner
from gpu_blur.analysis.bench.peers import demosaic_side_by_side, kernel_blur_side_by_side
from gpu_blur.analysis.bench.report import write_report
from gpu_blur.analysis.bench.workload import (
    BASE_SCENE,
    DEFAULT_SIZE,
    FRAMES,
    KNOBS,
    MIN_RUNS,
    MIN_SIDE,
    NOISE_FREE,
    PAN_PX,
    SAMPLE_INDEX,
    SEED,
    Setting,
    make_frames,
    quick_knobs,
    select_knobs,
)


def run_benchmark(size: tuple[int, int] = DEFAULT_SIZE, backends: Sequence[str] | None = None,
                  quick: bool = False, runs: int = MIN_RUNS,
                  knobs: Sequence[Setting] | None = None,
                  log: Callable[[str], None] = print,
                  reference_runs: int | None = None) -> dict:
    """Run the benchmark and return its report (what the JSON file holds).

    Args:
        size: (width, height) of the frames, even, each >= :data:`MIN_SIDE`.
        backends: backend specs to run (numpy always runs: it is the reference); None: all.
        quick: the first two settings of each knob only (:func:`quick_knobs`).
        runs: timed runs per measurement, >= :data:`MIN_RUNS`.
        knobs: the settings (default :data:`KNOBS`).
        log: called with a line per measured row.
        reference_runs: timed runs of the numpy reference, >= 1 (default ``runs``). Fewer
            than :data:`MIN_RUNS` (no warm-up) serve a GPU machine's run, where numpy is only
            the source of the reference images: its times there are single runs, and its
            medians come from a CPU run.

    Raises:
        ValueError: bad size, runs or backend names.
    """
    import gpu_blur

    width, height = size
    if width < MIN_SIDE or height < MIN_SIDE or width % 2 or height % 2:
        raise ValueError(f"size {width} x {height}: give even sides of at least {MIN_SIDE} "
                         "(e.g. --size 480x300)")
    if runs < MIN_RUNS:
        raise ValueError(f"runs = {runs}: the medians need at least {MIN_RUNS} timed runs")
    reference_runs = runs if reference_runs is None else reference_runs
    if reference_runs < 1:
        raise ValueError(f"reference runs = {reference_runs}: numpy needs at least one run")
    chosen = choose_backends(backends)
    settings = list(KNOBS if knobs is None else knobs)
    if quick:
        settings = quick_knobs(settings)
    frames = make_frames(width, height)
    load_before = load_average()
    runner = Runner(frames, chosen, settings, runs, log, reference_runs)
    rows = runner.rows()
    middle = frames[len(frames) // 2]
    side_by_side = {
        "pipeline": runner.pipeline(),
        "demosaic": demosaic_side_by_side(middle, chosen, runs),
        "kernel_blur": kernel_blur_side_by_side(middle, chosen, runs),
    }
    return {
        "what": "accuracy against time per knob setting: gpu_blur.synthesize, frames in host "
                "memory, median of the timed runs after a warm-up; errors of the noise-free "
                "final image and residual KL against the numpy float64 reference "
                "(gpu_blur/analysis/bench)",
        "host": platform.node(), "cpu": cpu_name(), "python": platform.python_version(),
        "gpu_blur": gpu_blur.__version__, "source": source_commit(),
        "source_digest": source_digest(),
        "devices": {spec: b["device"] for spec, b in chosen.items()},
        "size": [width, height], "frames": FRAMES, "pan_px_per_frame": PAN_PX,
        "megapixels": runner.megapixels, "runs": runs, "reference_runs": reference_runs,
        "seed": SEED,
        "sample_index": SAMPLE_INDEX, "base_scene": BASE_SCENE, "noise_free": NOISE_FREE,
        "quick": quick, "knobs": list(dict.fromkeys(s.knob for s in settings)),
        # other work on the host slows the runs: its 1-minute load average, start and end
        "load_average": [load_before, load_average()],
        "rows": rows, "side_by_side": side_by_side,
    }


def _size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTHxHEIGHT, e.g. 480x300")
    return int(match[1]), int(match[2])


def add_arguments(p: argparse.ArgumentParser, default_output: Path = Path(".")) -> None:
    """The options of ``gpu-blur bench`` and ``bench/accuracy_vs_time.py``."""
    p.add_argument("--size", type=_size, default=DEFAULT_SIZE, metavar="WxH",
                   help="frame size, even sides (default 1920x1200; 480x300 for a quick look)")
    p.add_argument("--backends", metavar="LIST", type=lambda s: [x.strip() for x in
                   s.split(",") if x.strip()], help="comma list of backends (numpy always runs, "
                   "as the reference), e.g. numpy,opencl:0:0,warp:cpu (default: every usable "
                   "device; see gpu-blur devices)")
    p.add_argument("--quick", action="store_true", help="two settings per knob (its accurate "
                   "one and one other)")
    p.add_argument("--knobs", metavar="LIST", type=lambda s: [x.strip() for x in s.split(",")
                   if x.strip()], help="comma list of the knobs to run, e.g. motion or "
                   "\"precision,CRF table\" (default: all; names as in the table)")
    p.add_argument("--runs", type=int, default=MIN_RUNS, help=f"timed runs per measurement "
                   f"after a warm-up, >= {MIN_RUNS} (default {MIN_RUNS})")
    p.add_argument("--reference-runs", type=int, metavar="N", help="timed runs of the numpy "
                   "reference (default: --runs); 1 on a GPU machine, where numpy only makes the "
                   "reference images and its medians come from a CPU run")
    p.add_argument("--output", type=Path, default=default_output, metavar="DIR",
                   help=f"folder for accuracy_vs_time_<tag>.json/.md/.png (default "
                   f"{default_output})")
    p.add_argument("--tag", help="file name tag (default: cpu, or the first GPU's name)")


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``gpu-blur bench`` with parsed options; returns the exit status."""
    knobs = select_knobs(args.knobs) if args.knobs is not None else None
    report = run_benchmark(tuple(args.size), args.backends, args.quick, args.runs, knobs=knobs,
                           log=lambda line: print(line, flush=True),
                           reference_runs=args.reference_runs)
    tag = args.tag or device_tag(choose_backends(list(report["devices"])))
    for path in write_report(report, args.output, tag):
        print(f"wrote {path}")
    return 0


def main(argv: Sequence[str] | None = None, default_output: Path = Path(".")) -> int:
    """``python -m gpu_blur.analysis.bench`` / ``bench/accuracy_vs_time.py``: parse and run."""
    from gpu_blur.analysis import bench  # its docstring says what the benchmark measures

    p = argparse.ArgumentParser(description=bench.__doc__.split("\n\n")[0])
    add_arguments(p, default_output)
    try:
        return run_from_args(p.parse_args(argv))
    except (ValueError, OSError, RuntimeError) as e:
        print(f"accuracy_vs_time: error: {e}", file=sys.stderr)
        return 2
