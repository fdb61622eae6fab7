"""Running the benchmark: :func:`run_benchmark`, and ``gpu-blur bench``'s options."""

from __future__ import annotations

import argparse
import json
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
from gpu_blur.analysis.bench.report import report_paths, write_report
from gpu_blur.analysis.bench.workload import (
    BASE_SCENE,
    DEFAULT_SIZE,
    FRAMES,
    KNOBS,
    MIN_RUNS,
    MIN_SIDE,
    NOISE_FREE,
    PAN_PX,
    QUICK_SIZE,
    SAMPLE_INDEX,
    SEED,
    Setting,
    make_frames,
    quick_knobs,
    select_knobs,
)
from gpu_blur.file_writing import write_text
from gpu_blur.locking import release_lock, take_lock

__all__ = ["RESUME_KEYS", "SIDE_BY_SIDE", "add_arguments", "main", "run_benchmark", "run_from_args"]

#: The report keys a resumed run must share with the JSON it finishes, and what sets each.
RESUME_KEYS = {"size": "--size", "devices": "--backends (their devices)", "runs": "--runs",
               "reference_runs": "--reference-runs", "quick": "--quick",
               "settings": "--knobs", "source_digest": "gpu_blur source (files' SHA-256)"}
#: Side-by-side steps after the rows (each one progress step, saved when done).
SIDE_BY_SIDE = ("pipeline", "demosaic", "kernel_blur")


def _shown(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _finished_part(path: Path | None, options: dict) -> dict | None:
    """The report a run with the same options left in ``path`` (None if there is none).

    Raises:
        ValueError: naming the file and the first option that differs (or why it cannot be
            read), and the ways out.
    """
    if path is None or not path.exists():
        return None
    way_out = ("rerun with that run's options to finish it, or give another --output or "
               "--tag, or delete the file to start again")
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: cannot read it as a bench report ({e}); {way_out}") from None
    if not isinstance(old, dict) or not isinstance(old.get("rows"), list):
        raise ValueError(f"{path}: not a bench report (no list of rows); {way_out}")
    for key, option in RESUME_KEYS.items():
        if old.get(key) != options[key]:
            raise ValueError(f"{path} holds a bench run with another {option}: {key} = "
                             f"{_shown(old.get(key))} (this run: {_shown(options[key])}); "
                             f"{way_out}")
    return old


def run_benchmark(size: tuple[int, int] | None = None, backends: Sequence[str] | None = None,
                  quick: bool = False, runs: int = MIN_RUNS,
                  knobs: Sequence[Setting] | None = None,
                  log: Callable[[str], None] = print,
                  reference_runs: int | None = None, save_to: Path | None = None,
                  progress: bool = False) -> dict:
    """Run the benchmark and return its report (what the JSON file holds).

    Args:
        size: (width, height) of the frames, even, each >= :data:`MIN_SIDE` (default
            :data:`DEFAULT_SIZE`, with ``quick`` :data:`QUICK_SIZE`).
        backends: backend specs to run (numpy always runs: it is the reference); None: all.
        quick: the first two settings of each knob only (:func:`quick_knobs`).
        runs: timed runs per measurement, >= :data:`MIN_RUNS`.
        knobs: the settings (default :data:`KNOBS`).
        log: called with a line per measured row.
        reference_runs: timed runs on numpy, >= 1 (default ``runs``). Fewer than
            :data:`MIN_RUNS` (no warm-up) serve a GPU machine's run, where numpy is only
            the source of the reference images: its times there are single runs, and its
            medians come from a CPU run.
        save_to: the report's JSON file, rewritten after every row and side-by-side step
            (``"complete": false`` until the end). A report there from a run with the same
            options (:data:`RESUME_KEYS`) is finished: its rows are kept, not measured again.
        progress: show a progress bar (steps done, elapsed, remaining) on stderr.

    Raises:
        ValueError: bad size, runs or backend names, or a report in ``save_to`` from a run
            with other options (naming the first that differs).
    """
    from tqdm import tqdm  # here: gpu-blur --help builds this command's options from this module

    import gpu_blur

    width, height = size or (QUICK_SIZE if quick else DEFAULT_SIZE)
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
    options = {"size": [width, height], "devices": {spec: b["device"] for spec, b in
                                                    chosen.items()},
               "runs": runs, "reference_runs": reference_runs, "quick": quick,
               "settings": [[s.knob, s.label] for s in settings],
               "source_digest": source_digest()}
    before = _finished_part(save_to, options) or {}
    frames = make_frames(width, height)
    report = {
        "what": "accuracy against time per knob setting: gpu_blur.synthesize, frames in host "
                "memory, median of the timed runs after a warm-up, each setting timed in turn "
                "with its knob's accurate setting; errors of the noise-free "
                "final image and residual KL against the numpy float64 reference "
                "(gpu_blur/analysis/bench)",
        "complete": False,
        "host": platform.node(), "cpu": cpu_name(), "python": platform.python_version(),
        "gpu_blur": gpu_blur.__version__, "source": source_commit(), **options,
        "frames": FRAMES, "pan_px_per_frame": PAN_PX,
        "megapixels": width * height / 1e6, "seed": SEED,
        "sample_index": SAMPLE_INDEX, "base_scene": BASE_SCENE, "noise_free": NOISE_FREE,
        "knobs": list(dict.fromkeys(s.knob for s in settings)),
        # other work on the host slows the runs: its 1-minute load average, start and end
        "load_average": [load_average(), None],
        "rows": [], "side_by_side": {},
    }

    def save():
        if save_to is not None:
            save_to.parent.mkdir(parents=True, exist_ok=True)
            write_text(save_to, json.dumps(report, indent=1, allow_nan=False) + "\n")

    def say(line: str) -> None:
        with tqdm.external_write_mode(file=sys.stderr):  # the bar steps aside for the line
            log(line)

    runner = Runner(frames, chosen, settings, runs, say, reference_runs)
    tasks = runner.tasks()
    kept = {(r["knob"], r["setting"], r["backend"]): r for r in before.get("rows", [])}
    steps = len(tasks) + len(SIDE_BY_SIDE)
    done = [(s.knob, s.label, spec) in kept for s, spec in tasks] + [
        k in before.get("side_by_side", {}) for k in SIDE_BY_SIDE]
    if before:
        log(f"resuming {save_to}: {sum(done)} of {steps} steps done (delete it to measure "
            "again)")
    middle = frames[len(frames) // 2]
    side = {"pipeline": runner.pipeline,
            "demosaic": lambda: demosaic_side_by_side(middle, chosen, runs),
            "kernel_blur": lambda: kernel_blur_side_by_side(middle, chosen, runs)}
    # the bar counts steps weighted by their expected cost, so its time left holds when the
    # slow rows (frame interpolation) come late; its text counts the steps themselves
    weights = [runner.cost(s, spec) for s, spec in tasks] + [1.0] * len(SIDE_BY_SIDE)
    with tqdm(total=sum(weights), initial=sum(w for w, d in zip(weights, done, strict=True) if d),
              disable=not progress, file=sys.stderr, dynamic_ncols=True,
              bar_format="{desc} {percentage:3.0f}%|{bar}| "
                         "[{elapsed} taken, {remaining} left]") as bar:
        def finished(step: int) -> None:
            save()
            if not done[step]:
                done[step] = True
                bar.set_description_str(f"bench: {sum(done)}/{steps} steps", refresh=False)
                bar.update(weights[step])

        bar.set_description_str(f"bench: {sum(done)}/{steps} steps")
        for i, (setting, spec) in enumerate(tasks):
            row = kept.get((setting.knob, setting.label, spec)) or runner.row(setting, spec)
            report["rows"].append(row)
            finished(i)
        for i, key in enumerate(SIDE_BY_SIDE, len(tasks)):
            held = before.get("side_by_side", {}).get(key)
            report["side_by_side"][key] = held if held is not None else side[key]()
            finished(i)
    report["load_average"][1] = load_average()
    report["complete"] = True
    save()
    return report


def _size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTHxHEIGHT, e.g. 480x300")
    return int(match[1]), int(match[2])


def add_arguments(p: argparse.ArgumentParser, default_output: Path = Path(".")) -> None:
    """The options of ``gpu-blur bench`` and ``bench/accuracy_vs_time.py``."""
    p.add_argument("--size", type=_size, metavar="WxH", help="frame size, even sides "
                   "(default 1920x1200; with --quick 320x200)")
    p.add_argument("--backends", metavar="LIST", type=lambda s: [x.strip() for x in
                   s.split(",") if x.strip()], help="comma list of backends (numpy always runs, "
                   "as the reference), e.g. numpy,opencl:0:0,warp:cpu (default: every usable "
                   "device; see gpu-blur devices)")
    p.add_argument("--quick", action="store_true", help="two settings per knob (its accurate "
                   "one and one other) at 320x200: 2 to 4 minutes on a 2-core CPU for numpy, "
                   "two or three OpenCL runtimes and Warp's CPU device (fewer --backends, less)")
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
                   f"{default_output}); the JSON is written as rows finish, and a run with the "
                   "same options finishes it instead of starting again")
    p.add_argument("--tag", help="file name tag (default: cpu, or the first GPU's name)")


def run_from_args(args: argparse.Namespace, progress: bool = True) -> int:
    """Run ``gpu-blur bench`` with parsed options; returns the exit status.

    ``progress``: show the progress bar on stderr.
    """
    knobs = select_knobs(args.knobs) if args.knobs is not None else None
    tag = args.tag or device_tag(choose_backends(args.backends))
    saved = report_paths(args.output, tag)[0]
    saved.parent.mkdir(parents=True, exist_ok=True)
    # one run per report: a second one would interleave its rows with this one's; the lock
    # file goes when the run ends (gpu_blur.locking.release_lock)
    lock_file = saved.with_name(f".{saved.name}.lock")
    lock = take_lock(lock_file, f"bench report {saved}",
                     "wait for that run to end, or give another --output or --tag")
    print(f"bench: writing {saved} as each row finishes (stopped, the same command goes on "
          "from there)", flush=True)
    try:
        try:
            report = run_benchmark(args.size and tuple(args.size), args.backends, args.quick,
                                   args.runs, knobs=knobs,
                                   log=lambda line: print(line, flush=True),
                                   reference_runs=args.reference_runs, save_to=saved,
                                   progress=progress)
        except KeyboardInterrupt:
            print(f"bench: interrupted; the rows measured so far are in {saved}: run the same "
                  "command to go on", file=sys.stderr)
            return 130
        for path in write_report(report, args.output, tag):
            print(f"wrote {path}")
        return 0
    finally:
        release_lock(lock, lock_file)


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
