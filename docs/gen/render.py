"""What the documentation site generates instead of typing: Markdown made from the code and data.

A page asks for a piece with a marker line, ``<!-- gen: KIND ARGUMENTS -->``; the mkdocs hook
(``hooks.py`` beside this file) replaces each marker with :func:`expand`'s text when the site is
built, so the help texts, the scene key reference, the camera table and every benchmark figure
come from the package and from ``bench/results/*.json`` as they are at that commit. The kinds:

    cli-help [SUBCOMMAND]     ``gpu-blur [SUBCOMMAND] --help``, 100 columns wide
    cli-commands              the subcommands with their one-line help, linked to their pages
    scene-keys                every scene key: default, allowed values, meaning (scene.FIELDS)
    cameras                   the built-in cameras and where their numbers come from
    tolerances                the tolerance rows of whole passes and pipelines, per backend
    bench NAME                a table from bench/results, with its device and commit (BENCH)
    accuracy FILE             ``gpu-blur bench``'s summary table of one results file
    image PATH ALT            an image of the repository (copied into the site by the hook)
    file PATH LANGUAGE        a file of the repository as a fenced block (an example scene)

Nothing here imports mkdocs, so ``tests/docs/test_site.py`` calls it directly. Figures name
the device from the results file and the commit the file itself names (``at commit ...``,
``source``); where it names none, the commit that last wrote the file (``git log``).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
import subprocess
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "bench" / "results"
MARKER = re.compile(r"^(?P<indent> *)<!-- gen: (?P<kind>[a-z-]+)(?P<args>(?: [^>]*?)?) -->$",
                    re.M)
HELP_COLUMNS = 100


class GenError(ValueError):
    """A marker that names nothing known, or results that lack what a table reads."""


# -- the command line ------------------------------------------------------------------------

def cli_help(subcommand: str | None = None) -> str:
    """``gpu-blur [subcommand] --help`` as the command prints it at 100 columns."""
    from gpu_blur.cli import COMMANDS, main

    if subcommand is not None and subcommand not in COMMANDS:
        raise GenError(f"cli-help: no subcommand {subcommand!r}; gpu-blur has "
                       f"{', '.join(COMMANDS)}")
    argv = [subcommand, "--help"] if subcommand else ["--help"]
    out = io.StringIO()
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(HELP_COLUMNS)  # argparse wraps at the terminal's width
    try:
        with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
            main(argv)
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old
    return "```text\n$ gpu-blur " + " ".join(argv) + "\n" + out.getvalue().rstrip() + "\n```"


def cli_commands() -> str:
    """A table of the subcommands, each linked to its page, with its one-line help."""
    import argparse

    from gpu_blur.cli import COMMANDS, _command

    parser = argparse.ArgumentParser(prog="gpu-blur")
    sub = parser.add_subparsers()
    for name in COMMANDS:
        _command(name).add_parser(sub)
    helps = {a.dest: a.help for a in sub._choices_actions}
    lines = ["| command | what it does |", "| --- | --- |"]
    lines += [f"| [`gpu-blur {n}`]({n}.md) | {_cell(helps.get(n) or '')} |" for n in COMMANDS]
    return "\n".join(lines)


# -- scenes and cameras ------------------------------------------------------------------------

def _toml(value) -> str:
    return json.dumps(value) if value is not None else "(the camera's)"


def _allowed(field) -> str:
    if field.choices:
        return " \\| ".join(f"`{json.dumps(c)}`" for c in field.choices)
    if field.limit is not None:
        kind = "integers" if field.limit.integer else "numbers"
        text = f"{kind} {field.limit.describe()}"
        text = f"`[low, high]`, {text}" if field.pair else text
        words = getattr(field, "words", ())  # strings a number key also takes
        return text + "".join(f", or `{json.dumps(w)}`" for w in words)
    return {str: "text", bool: "`true` \\| `false`"}.get(field.kind, str(field.kind))


def scene_keys() -> str:
    """One table per scene section, a row per key, from :data:`gpu_blur.scene.FIELDS`."""
    from gpu_blur.scene import FIELDS

    parts = []
    for section, fields in FIELDS.items():
        parts.append(f"### `[{section}]`\n")
        parts.append("| key | default | allowed | meaning |")
        parts.append("| --- | --- | --- | --- |")
        for key, field in fields.items():
            default = ("(off)" if field.default is None and field.pair
                       else _toml(field.default))
            parts.append(f"| `{section}.{key}` | `{default}` | {_allowed(field)} | "
                         f"{_cell(field.help)} |")
        parts.append("")
    return "\n".join(parts).rstrip()


def cameras() -> str:
    """The built-in cameras: noise levels, white-balance draws, and each one's source."""
    from gpu_blur.cameras import get_camera, preset_names

    lines = ["| camera | shot noise K | read noise std | WB red | WB blue |",
             "| --- | ---: | ---: | --- | --- |"]
    sources: dict[str, list[str]] = {}
    for name in preset_names():
        c = get_camera(name)
        wb = c.white_balance
        if wb.pairs:
            red = f"{len(wb.pairs)} measured pairs, {min(p[0] for p in wb.pairs):.2f} to " \
                  f"{max(p[0] for p in wb.pairs):.2f}"
            blue = f"with them, {min(p[1] for p in wb.pairs):.2f} to " \
                   f"{max(p[1] for p in wb.pairs):.2f}"
        else:
            red, blue = (" to ".join(f"{g:.2f}" for g in dict.fromkeys(r))
                         for r in (wb.red_range, wb.blue_range))
        lines.append(f"| `{name}` | {c.shot_noise_k:.5g} | {c.read_noise_std:.5g} | {red} | "
                     f"{blue} |")
        sources.setdefault(c.source, []).append(name)
    lines.append("")
    lines.append("Where the numbers come from:\n")
    for source, names in sources.items():
        shown = (f"`{names[0]}`" if len(names) == 1
                 else f"`{names[0]}` to `{names[-1]}`" if len(names) > 3
                 else ", ".join(f"`{n}`" for n in names))
        lines.append(f"- {shown}: {_cell(source)}")
    return "\n".join(lines)


#: The tolerance rows the docs show, with what each compares.
TOLERANCE_ROWS = {
    "pipeline": "whole pipeline, noise off",
    "pipeline_noisy": "whole pipeline, noise on",
    "pipeline_noisy_outliers": "noise on: share of values that may miss that row",
    "pipeline_fast_math": "whole pipeline, output.fast_math",
    "accumulate": "accumulate pass",
    "to_raw": "to_raw pass, noise off",
    "finish": "finish pass",
    "cross_backend": "OpenCL against Warp, whole pipeline",
}


def tolerances() -> str:
    """The rows of gpu_blur/tolerances.py that say how close a device comes to the reference."""
    from gpu_blur.tolerances import TOLERANCES

    columns = [("opencl", "float32"), ("opencl", "float64"), ("warp", "float32"),
               ("warp", "float64")]
    rows = []
    for stage, what in TOLERANCE_ROWS.items():
        cells = []
        for backend, dtype in columns:
            row = TOLERANCES.get((stage, backend, dtype)) or TOLERANCES.get(
                (stage, "kernels", dtype))
            if row is None:
                cells.append("")
                continue
            rtol, atol = row
            text = f"{atol:.2g}" if atol else "exact"
            cells.append(text + (f", relative {rtol:.2g}" if rtol else ""))
        rows.append([f"{what} (`{stage}`)"] + cells)
    return _table(["comparison (row)"] + [f"{b} {d}" for b, d in columns], rows)


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


# -- benchmark results -----------------------------------------------------------------------

@cache
def _git_commit(path: Path) -> str:
    """``abc1234 (2026-11-27)``: the commit that last wrote ``path``, with its date."""
    rel = path.relative_to(ROOT).as_posix()
    try:
        done = subprocess.run(["git", "log", "-1", "--format=%h (%ad)", "--date=short", "--",
                               rel], cwd=ROOT, capture_output=True, text=True, timeout=30)
        changed = subprocess.run(["git", "status", "--porcelain", "--", rel], cwd=ROOT,
                                 capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "not known here (no git history)"
    text = done.stdout.strip() or "not yet committed"
    return text + (", changed since" if changed and done.stdout.strip() else "")


def _named_commit(*texts) -> str | None:
    """The commit a results file names for its code (``at commit abc1234``, a bare hash)."""
    for text in texts:
        if not isinstance(text, str):
            continue
        m = re.search(r"\bat (?:commit )?([0-9a-f]{7,40})\b", text) or \
            re.fullmatch(r"([0-9a-f]{7,40})(\+modified)?(?: .*)?", text, re.S)
        if m:
            return m.group(1)[:7] + ("+modified" if "+modified" in text[:60] else "")
    return None


def _named(data: dict) -> str | None:
    """The commit a results file names in its ``what``, ``bench`` or ``source`` field."""
    return _named_commit(data.get("what"), data.get("bench"), data.get("source"))


def load(name: str) -> tuple[dict, Path]:
    """A results file of ``bench/results`` by name (``.json`` added)."""
    path = RESULTS / (name if name.endswith(".json") else name + ".json")
    if not path.is_file():
        raise GenError(f"no results file {path.relative_to(ROOT).as_posix()}")
    return json.loads(path.read_text()), path


def provenance(path: Path, device: str, named: str | None) -> str:
    """The line under a table: device, commit, file."""
    rel = path.relative_to(ROOT).as_posix()
    code = (f"code at {named}, recorded in {_git_commit(path)}" if named
            else f"recorded in commit {_git_commit(path)}")
    return f"*{device}; {code}; `{rel}`.*"


def _table(header: list[str], rows: list[list], right_from: int = 1) -> str:
    aligns = ["---" if i < right_from else "---:" for i in range(len(header))]
    out = ["| " + " | ".join(header) + " |", "| " + " | ".join(aligns) + " |"]
    out += ["| " + " | ".join(_fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        if value == 0:
            return "0"
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        return f"{value:.3g}"
    return _cell(value)


SCENES = {"realblur_j": "RealBlur-J, 1920 x 1200", "rsblur": "RSBlur, 9 x 1920 x 1200 uint8",
          "kernel_256": "random kernels, 256 x 256"}


def _scene(name: str) -> str:
    return SCENES.get(name, name)


def bench_per_sample() -> str:
    """Whole pipeline per sample on each device, float32 and float64 (the accuracy runs)."""
    parts = []
    for name in ("accuracy_vs_time_cpu", "accuracy_vs_time_h200"):
        data, path = load(name)
        rows = []
        for backend, device in data["devices"].items():
            times = {r["setting"]: r["median_s"] for r in data["rows"]
                     if r["knob"] == "precision" and r["backend"] in (backend, "-")
                     and r.get("available", True) and r.get("median_s") is not None}
            rows.append([f"`{backend}`", device, times.get("float32"), times.get("float64")])
        size = data["size"]
        parts.append(_table(["backend", "device", "float32 s", "float64 s"], rows, 2))
        parts.append(provenance(path, f"{data['cpu']} host; {data['frames']} frames of "
                                f"{size[0]} x {size[1]}, medians of {data['runs']}",
                                _named_commit(data.get("source"))))
    return "\n\n".join(parts)


def bench_batches() -> str:
    """Batches of 16 on one H200: numpy, pinned and torch CUDA paths against the copy bound."""
    data, path = load("user_paths_pinned_h200")
    after = data["medians"]["after"]
    rows = [[_scene(s), m.get("batch_numpy_ms"), m.get("batch_pinned_ms"),
             m.get("batch_torch_cuda_ms"), m.get("kernels_ms"), m.get("bound_serial_ms"),
             m.get("bound_duplex_ms")] for s, m in after.items()]
    table = _table(["scene", "numpy in and out", "pinned numpy", "torch CUDA",
                    "device kernels", "copy bound, serial", "copy bound, duplex"], rows)
    return table + "\n\n" + provenance(path, data["device"] + "; " + data["machine"]
                                       + "; ms a sample, medians of three rounds", _named(data))


def bench_pinned_h100() -> str:
    """The same paths on one H100, each round's figure."""
    data, path = load("user_paths_pinned_h100")
    by_scene: dict[str, list[dict]] = {}
    for run in data["rounds"]:
        for r in run:
            by_scene.setdefault(r["scene"], []).append(r)
    keys = ["batch_numpy_ms", "batch_pinned_ms", "batch_torch_cuda_ms", "kernels_ms"]
    rows = [[_scene(s)] + [" / ".join(_fmt(r[k]) for r in rs) for k in keys]
            for s, rs in by_scene.items()]
    table = _table(["scene", "numpy in and out", "pinned numpy", "torch CUDA",
                    "device kernels"], rows)
    return table + "\n\n" + provenance(path, data["device"] + "; ms a sample, one figure "
                                       "per round", _named(data))


def bench_back_to_back() -> str:
    """One synchronized call against calls back to back (a training loop's pace)."""
    data, path = load("user_paths_back_to_back_h200")
    rows = [[_scene(r["scene"]), r["batch_torch_cuda_ms"], r["batch_torch_cuda_back_to_back_ms"],
             r["kernels_ms"]] for r in data["results"]]
    table = _table(["scene (torch CUDA in and out)", "one call, synchronized",
                    "32 calls back to back", "device kernels"], rows)
    return table + "\n\n" + provenance(path, data["device"] + "; ms a sample, batches of 16",
                                       _named_commit(data.get("what")))


def bench_codes() -> str:
    """Float results against 8-bit codes made on the device, from pinned memory."""
    data, path = load("user_paths_codes_h200")
    rows = []
    for run in data["runs"]:
        for r in run["results"]:
            rows.append([run["device"], r["batch_pinned_ms"], r["batch_pinned_codes_ms"],
                         r.get("bound_serial_codes_ms")])
    table = _table(["device (RSBlur, pinned, batches of 16)", "float32 results",
                    "uint8 codes", "codes' copy bound"], rows)
    return table + "\n\n" + provenance(path, "one H200 on a 16-core host; ms a sample",
                                       _named(data))


def bench_synthesize_vs_batch() -> str:
    """``synthesize`` one sample a call against ``Synthesizer`` batches from numpy."""
    rows, notes = [], []
    for name in ("batch_vs_synthesize_h100", "batch_vs_synthesize_opencl_h100",
                 "batch_vs_synthesize_cpu"):
        data, path = load(name)
        per = data.get("ms_per_sample") or data.get("after")
        for scene, m in per.items():
            rows.append([_scene(scene).split(",")[0], data["device"], m.get("synthesize"),
                         m.get("batch"), m.get("batch, out=")])
        notes.append(provenance(path, f"{data['device']}, batches of {data['batch']}",
                                _named_commit(data.get("what"))))
    table = _table(["scene", "device", "synthesize", "batch", "batch, out= arrays"], rows, 2)
    return table + "\n\n" + "\n".join(f"- {n}" for n in notes)


def bench_generate_threads() -> str:
    """``gpu-blur generate`` from PNG files with one I/O thread and with the host's cores."""
    data, path = load("generate_gpu_h100")
    rows = [[r["threads"], r["samples_per_s"]] for r in data["runs"]]
    rows.append(["decode-plus-encode bound of the host", data["bound_samples_per_s"]])
    table = _table(["I/O threads", "samples/s"], rows)
    return table + "\n\n" + provenance(
        path, f"one H100, {data['cores']}-core host, `{data['backend']}`; RSBlur samples of "
        f"{data['frames']} PNG frames of {data['image'][0]} x {data['image'][1]}", _named(data))


def bench_generate_codes() -> str:
    """``generate`` writing codes made on the device against float results converted."""
    data, path = load("generate_codes_h200x4")
    rows = []
    for key, label in (("codes_on_host", "float32 results, converted by the writers"),
                       ("codes_on_device", "8-bit codes made on the device")):
        part = data[key]
        at = re.search(rf"'{key}' at ([0-9a-f]{{7,40}})", data.get("what", ""))
        rows.append([label, part["runs"][0]["samples_per_s"], part["bound_samples_per_s"],
                     part["ratio_to_bound"], f"`{at.group(1)}`" if at else "not recorded"])
    table = _table(["results", "samples/s", "host's decode-plus-encode bound",
                    "share of the bound", "code at"], rows)
    return table + "\n\n" + provenance(path, data["machine"] + "; one process, one GPU, "
                                       "the two runs back to back", None)


def bench_generate_devices() -> str:
    """``generate --devices`` with 1, 2 and 4 workers sharing one GPU."""
    data, path = load("generate_devices_h100")
    rows = [[w, r["samples_per_s"]] for w, r in data["devices_workers"].items()]
    rows.append(["decode-plus-encode bound of the host", data["bound_samples_per_s"]])
    table = _table(["workers on warp:cuda:0", "samples/s"], rows)
    same = "every set the same bytes" if data.get("same_bytes") else "sets differ"
    return table + "\n\n" + provenance(path, f"{data['device']}; {same}", _named(data))


def bench_generate_windows(name: str = "generate_windows_h200") -> str:
    """``generate`` over distinct and overlapping windows, a commit before and this one.

    Files of ``--repeats`` runs add each rate's range over the repeats and the measured bound
    (the codecs alone through one thread per core), newer ones the rate from the first
    output written to the last; older files render as they did.
    """
    data, path = load(name)
    cases = data["cases"].values()
    measured = any("bound_now_measured" in case for case in cases)
    spread = any("samples_per_s_each" in run for case in cases for run in case["runs"].values())
    written = all("written_samples_per_s" in run for case in cases
                  for run in case["runs"].values())

    def rate(run: dict | None):
        if run is None or "samples_per_s_each" not in run:
            return run and run["samples_per_s"]
        each = run["samples_per_s_each"]
        return f"{_fmt(run['samples_per_s'])} ({_fmt(min(each))}-{_fmt(max(each))})"

    rows = []
    for windows, case in data["cases"].items():
        before, now = case["runs"].get("before"), case["runs"]["now"]
        bound = case["bound_now"]
        rows.append([windows, case["frames_in_sequence"], case["samples"],
                     rate(before), before and before["in_run_samples_per_s"]]
                    + ([before and before["written_samples_per_s"]] if written else [])
                    + [rate(now), now["in_run_samples_per_s"]]
                    + ([now["written_samples_per_s"]] if written else [])
                    + [case.get("speedup"),
                     bound["samples_per_s"], bound["decodes_per_sample"],
                     case["ratio_to_bound_now"]]
                    + ([case.get("bound_now_measured", {}).get("samples_per_s"),
                        case.get("ratio_to_measured_bound_now")] if measured else [])
                    + [case["same_pixels"]])
    table = _table(["windows", "frames", "samples", "before", "before, in the run"]
                   + (["before, first to last written"] if written else [])
                   + ["now", "now, in the run"]
                   + (["now, first to last written"] if written else [])
                   + ["speed-up", "bound now", "decodes a sample", "share of the bound"]
                   + (["measured bound now", "share of the measured bound"] if measured else [])
                   + ["same pixels"], rows)
    device = data["machine"]
    if spread:
        device += (f"; each rate from the medians of {data.get('repeats', 'several')} runs a "
                   "tree, the trees taking turns, with the range of the single runs' rates")
    if measured:
        device += ("; measured bound: this code's decodes and encodes alone through one "
                   "thread per core")
    if data.get("device_png"):
        device += ("; \"now\" deflates its PNGs on the GPU, so its bounds count an encode as "
                   "the I/O thread's part, the file put together from its stream")
    return table + "\n\n" + provenance(path, device, _named(data))


def bench_devices_host(name: str = "generate_devices_h200x2") -> str:
    """``generate`` on a host of several GPUs: one process against ``--devices`` workers."""
    data, path = load(name)
    one = data["one_process"]["runs"][-1]
    rows = [[f"one process, {one['threads']} I/O threads, one GPU", one["samples_per_s"],
             one.get("written_samples_per_s"), one["in_run_samples_per_s"]]]
    rows += [[f"`--devices`, {r['gpus']} GPU{'s' if r['gpus'] > 1 else ''}", r["samples_per_s"],
              r.get("written_samples_per_s"), r["in_run_samples_per_s"]]
             for r in data["devices"]["disk"]]
    rows.append(["bound with 1d3f510's codecs and no cache (9 OpenCV decodes, 2 encodes a sample)",
                 data["devices"]["disk_bound_samples_per_s"], None, None])
    measured = data["devices"].get("disk_bound_measured")  # absent from older results
    if measured:
        rows.append([f"bound measured: the codecs alone through {measured['threads']} threads, "
                     "each frame decoded once", measured["samples_per_s"], None, None])
    table = _table(["run", "samples/s without the start", "first to last written",
                    "in the run"], rows)
    same = "every set the same bytes" if data["same_bytes_everywhere"] else "sets differ"
    return table + "\n\n" + provenance(path, f"{data['machine']}; {same}", _named(data))


def bench_device_frames(name: str = "generate_device_frames_h200x2_bf299bf") -> str:
    """Overlapping windows made from frames kept on the device, against the tree before."""
    data, path = load(name)
    rows = [[r["tree"], r["run"], r["round"], r["in_run_samples_per_s"], r["wall_s"],
             r["copies_s"], r["reading_s"], r["decode_ms_a_file"]] for r in data["runs"]]
    runs = _table(["tree", "run", "round", "samples/s in the run", "wall s", "copies s",
                   "waiting for inputs s", "decode ms a file"], rows, 2)
    same = "every set the same bytes" if data["same_bytes_everywhere"] else "sets differ"
    return (runs + "\n\n" + _devices_table(data["devices"]) + "\n\n"
            + provenance(path, f"{data['machine']}; {same}", _named(data)))


def _devices_table(devices: dict) -> str:
    """bench/multi_gpu.py's disk rows by tree, each against its measured codec bound."""
    rows = []
    for tree, found in devices.items():
        bound = found["disk_bound_measured"]["samples_per_s"]
        rows += [[tree, r["gpus"], r["samples_per_s"], r.get("written_samples_per_s"),
                  r["in_run_samples_per_s"], bound, 100 * r["samples_per_s"] / bound]
                 for r in found["disk"]]
    return _table(["tree", "`--devices` GPUs", "samples/s without the start",
                   "first to last written", "in the run", "measured codec bound",
                   "% of the bound"], rows, 1)


def bench_sharp_once(name: str = "generate_sharp_once_h200x2") -> str:
    """Sharp references encoded once, in turn against the tree before; fast against fastest."""
    data, path = load(name)
    rows = [[r["tree"], r["png"], r["run"], r["round"], r["in_run_samples_per_s"],
             r["io_busy_percent"]] for r in data["runs"]]
    runs = _table(["tree", "output.png", "run", "round", "samples/s in the run",
                   "I/O threads busy %"], rows, 3)
    stress = data["stress"]
    seen = (f"{data['same_bytes']}; {stress['tree']}'s {stress['png']}: "
            f"{stress['files_differing']} of {stress['files_compared']:,} files in "
            f"{stress['runs_compared']} runs other bytes than the first run's")
    return (runs + "\n\n" + _devices_table(data["devices"]) + "\n\n"
            + provenance(path, f"{data['machine']}; {seen}", _named(data)))


def bench_png_bytes(name: str = "png_fast_libdeflate_h200x2") -> str:
    """ISA-L's deflate against libdeflate's: whether a file's bytes repeat, and what each costs."""
    data, path = load(name)
    stress = data["stress"]
    rows = [[encoder, c["one_thread_ms"], c["images_per_s_16_threads"], c["bytes"],
             c["differing_under_churn"]] for encoder, c in data["codec"].items()]
    codecs = _table(["deflate of one noisy 1920 x 1200 image", "ms, one thread",
                     "images/s, 16 threads", "bytes", "other bytes, repeated under churn"],
                    rows, 1)
    rows = [[r["encoder"], r["run"], r["round"], r["in_run_samples_per_s"],
             r["io_busy_percent"]] for r in data["generate"]]
    runs = _table(["encoder", "run", "round", "samples/s in the run", "I/O threads busy %"],
                  rows, 2)
    seen = (f"generate with ISA-L: {stress['files_differing']} of {stress['files_compared']:,} "
            f"files in {stress['runs_compared']} runs came out as other bytes "
            f"({stress['differing']})")
    return (codecs + "\n\n" + runs + "\n\n"
            + provenance(path, f"{data['machine']}; {seen}; {data['generate_same']}",
                         _named(data)))


def bench_png_huffman(name: str = "png_fast_huffman_intel-xeon") -> str:
    """Deflates of Sub-filtered rows on one core: ms, MB, and which write zlib's own bytes."""
    data, path = load(name)
    rows = [[r["image"], r["encoder"], r["ms"], r["mb"], r.get("same_as_zlib")]
            for r in data["rows"]]
    table = _table(["rows of", "deflate", "ms", "MB", "same as zlib"], rows, 2)
    return table + "\n\n" + provenance(path, data["machine"], _named(data))


def bench_png_device(name: str = "png_device_h200") -> str:
    """``output.png = "fast"`` streams deflated on the device against one host core."""
    data, path = load(name)
    rows = [[f"on the device, {r['batch']} image{'s' if r['batch'] > 1 else ''} a call",
             r["device_ms"], r["kernels_ms"], r["same_bytes"]] for r in data["rows"]]
    rows.append(["on one core of the host (`huffman_zlib`)", data["host_ms"], None, True])
    table = _table(["deflate", "ms an image, streams fetched into pageable memory",
                    "ms an image, kernels alone", "zlib's bytes"], rows)
    machine = f"{data['device']} with its host's {data['cpu']}; noisy 1920 x 1200 RGB photos"
    made = data.get("set")
    if made:  # --generate: a set's files against the host's encoder
        machine += (f"; a `gpu-blur generate` set of {made['samples']} samples: "
                    + (f"all {made['files']} PNG files the host encoder's bytes"
                       if made["same_bytes"] else f"files differ: {', '.join(made['differ'])}"))
    return table + "\n\n" + provenance(path, machine, _named_commit(data.get("commit")))


def bench_devices_handoff() -> str:
    """``--devices`` results to the driver: through the pipe against shared memory."""
    data, path = load("devices_handoff_h200x2")
    rows = [[r["mode"], r["workers"], r["samples_per_s"], r["gb_per_s"],
             r["driver_ms_per_sample"], r["mb_per_sample"]] for r in data["rows"]]
    table = _table(["hand-off", "workers", "samples/s", "GB/s", "driver ms a sample",
                    "MB a sample"], rows, 2)
    return table + "\n\n" + provenance(path, f"{data['cpus']}-core host of two H200s",
                                       _named(data))


def _kernels_ratio(row: dict) -> float | None:
    """float32's kernels' device time a sample over uint8's (bench/user_paths.py on CUDA)."""
    if "uint8_kernels_ms" not in row:
        return None
    return sum(row["float32_kernels_ms"].values()) / sum(row["uint8_kernels_ms"].values())


#: bench_device_path_beside's rows: (label, path through a gpu_targets file, scale).
_BESIDE_ROWS = (
    ("frames on the device, wall ms a sample (synchronized after each pass)",
     ("warp_frames_on_device", "wall_seconds_synchronized_per_pass"), 1e3),
    ("frames on the device, wall ms a sample (one synchronize)",
     ("warp_frames_on_device", "wall_seconds_one_synchronize"), 1e3),
    ("pinned frames one at a time, samples/s",
     ("warp_frames_in_pinned_memory", "one_at_a_time", "samples_per_s"), 1),
    ("pinned frames pipelined, samples/s",
     ("warp_frames_in_pinned_memory", "pipelined", "samples_per_s"), 1),
    ("Warp synthesize from numpy, serial copies, samples/s",
     ("warp_synthesize_numpy_frames", "serial", "samples_per_s"), 1),
    ("Warp synthesize from numpy, overlapped copies, samples/s",
     ("warp_synthesize_numpy_frames", "overlapped", "samples_per_s"), 1),
    ("OpenCL synthesize from numpy, serial copies, samples/s",
     ("opencl_synthesize_numpy_frames", "serial", "samples_per_s"), 1),
    ("OpenCL synthesize from numpy, overlapped copies, samples/s",
     ("opencl_synthesize_numpy_frames", "overlapped", "samples_per_s"), 1),
    ("Warp batches of torch CUDA frames, samples/s",
     ("warp_batches_torch_cuda_frames", "samples_per_s"), 1),
)


def bench_device_path_beside() -> str:
    """The device path at 1d3f510 and now, bench/gpu_targets.py interleaved, and host time."""
    data, path = load("device_path_beside_h200")
    names = list(data["gpu_targets"])

    def value(run: dict, keys: tuple):
        for key in keys:
            run = run.get(key, {}) if isinstance(run, dict) else {}
        return run if isinstance(run, (int, float)) else None

    rows = [[label, *((v * scale if (v := value(data["gpu_targets"][n], keys)) is not None
                       else None) for n in names)] for label, keys, scale in _BESIDE_ROWS]
    heads = [f"{'1d3f510' if n.startswith('old') else 'now'}, run {n[-1]}" for n in names]
    table = _table(["bench/gpu_targets.py", *heads], rows)
    host = data["host_overhead"]
    host_rows = [[o["input"], o["batch_ms"], n["batch_ms"]]
                 for o, n in zip(host["old"]["rows"], host["new"]["rows"], strict=True)]
    table += "\n\n" + _table(["bench/host_overhead.py, host ms a batch of 16", "1d3f510", "now"],
                               host_rows)
    return table + "\n\n" + provenance(path, data["machine"], _named(data))


def bench_float_inputs(name: str = "float_inputs_h200") -> str:
    """Torch batches as uint8 codes against float32 values, ms a sample (and a tree before)."""
    data, path = load(name)
    beside = "before" in data
    trees = ([(data["before"]["commit"], data["before"]["results"])] if beside
             else []) + [(data.get("commit"), data["results"])]
    rows = [([commit] if beside else []) + [
        r["scene"], r["size"], r["batch"], r["uint8_ms"], r["float32_ms"],
        r["float32_over_uint8_ratio"], r["uint8_back_to_back_ms"], r["float32_back_to_back_ms"],
        r["float32_over_uint8_back_to_back_ratio"],
        r.get("float32_over_uint8_back_to_back_pool_kept_ratio"), _kernels_ratio(r),
        r["float32_reductions_ms"]] for commit, results in trees for r in results]
    heads = (["commit"] if beside else []) + [
        "scene", "size", "batch", "uint8", "float32", "ratio", "uint8 back to back",
        "float32 back to back", "ratio back to back", "ratio back to back, Warp's pool kept",
        "kernels' ratio", "float32 checks' reductions"]
    return (_table(heads, rows, 2 + beside) + "\n\n"
            + provenance(path, data["device"], _named(data)))


def bench_decode_threads(name: str = "decode_threads_h200") -> str:
    """PNG frames through a pool of threads with glibc's malloc as it comes and keeping memory."""
    data, path = load(name)
    decode, made = data["decode"], data.get("generate")
    peaks = "peak_memory_mib" in decode["runs"]["keep"][0]

    def each(runs: list[dict], key: str) -> str:
        return " / ".join(_fmt(run[key]) for run in runs)

    rows = []
    for setting in ("glibc", "keep"):
        runs = decode["runs"][setting]
        rows.append([setting, decode["median_ms_a_frame_a_thread"][setting],
                     each(runs, "ms_a_frame_a_thread"), decode["median_frames_per_s"][setting]]
                    + ([each(runs, "peak_memory_mib")] if peaks else [])
                    + ([each(made["runs"][setting], "in_run_samples_per_s"),
                        each(made["runs"][setting], "decode_ms_each")] if made else [])
                    + ([each(made["runs"][setting], "peak_memory_mib")]
                       if made and peaks else []))
    heads = (["glibc malloc", "ms a frame a thread (median)", "each round",
              "frames a second (median)"]
             + (["peak memory, MiB, each round"] if peaks else [])
             + ([f"generate, {made['samples']} distinct windows: samples/s in the run, each "
                 "round", "its ms a frame decoded"] if made else [])
             + (["its peak memory, MiB"] if made and peaks else []))
    host = data["machine"]
    device = (f"{host.get('host', host.get('cpu'))}; {data['frames']} frames of "
              f"{data['image'][0]} x {data['image'][1]} through {data['threads']} threads")
    table = _table(heads, rows)
    if "parts" in data:  # one frame's decode and its steps on one thread
        parts = data["parts"]["median_ms"]
        steps = {"read_image": "read_image (file to pixels)",
                 "decode_png": "decode_png (bytes to pixels)", "chunks": "walk the chunks",
                 "join": "join the IDAT data", "inflate": "inflate",
                 "unfilter": "unfilter (Sub: numpy's running sum)"}
        table += "\n\n" + _table(
            ["one frame on one thread, ms (median of each round's median)", *parts],
            [[label, *(parts[setting][key] for setting in parts)]
             for key, label in steps.items() if key in parts["glibc"]])
    return table + "\n\n" + provenance(path, device, _named(data))


def bench_multi_gpu(name: str) -> str:
    """Samples per second on 1, 2, 4 GPUs of one host, by source."""
    data, path = load(name)
    runs = [data] if "memory" in data else [data[k] for k in ("warp", "opencl") if k in data]
    rows = []
    gpus = sorted({m["gpus"] for run in runs for m in run["memory"] + run["disk"]})
    for run in runs:
        backend = run["backend"]
        for pinned in (False, True):
            ms = {m["gpus"]: m["samples_per_s"] for m in run["memory"]
                  if bool(m.get("pinned")) == pinned}
            if ms:
                source = ("frames in each GPU's pinned memory" if pinned
                          else "numpy frames in memory")
                rows.append([f"{source}, batches of 16, {backend}"] + [ms.get(g) for g in gpus])
        ds = {m["gpus"]: m["samples_per_s"] for m in run["disk"]}
        if ds:
            rows.append([f"PNG files, `gpu-blur generate --devices`, {backend}"]
                        + [ds.get(g) for g in gpus])
        one = run.get("disk_one_process")
        if one:  # one process drives one GPU
            rows.append([f"PNG files, `gpu-blur generate`, one process, {backend}"]
                        + [one["samples_per_s"] if g == 1 else None for g in gpus])
        if one and run.get("disk_bound_measured"):  # the host's, whatever the GPUs
            rows.append(["PNG files, the codecs alone through one thread per core (measured "
                         "bound)"] + [run["disk_bound_measured"]["samples_per_s"]] * len(gpus))
    bound = data.get("copy_bound")
    if bound:
        rb = {b["gpus"]: b["gb_s_each_way"] for b in bound}
        rows.append(["host's pinned copy rate, GB/s each way"] + [rb.get(g) for g in gpus])
    table = _table(["samples/s, source"] + [f"{g} GPU{'s' if g > 1 else ''}" for g in gpus],
                   rows)
    machine = data.get("machine") or f"{len(data.get('devices', []))} GPUs of one host"
    return table + "\n\n" + provenance(path, f"{machine}; RSBlur, 9 uint8 frames of 1920 x "
                                       "1200", _named_commit(data.get("what")))


def bench_training() -> str:
    """Training on the fly against presynthesized batches and CPU workers."""
    parts = []
    for name in ("train_on_the_fly_h200", "train_on_the_fly_unet_h200_second_run"):
        data, path = load(name)
        rows = []
        for net, m in data["nets"].items():
            rows.append([f"{net}, {m['parameters']:,} parameters",
                         m["on_the_fly"]["step_ms"], m["presynthesized"]["step_ms"],
                         m["cpu_workers"]["samples_per_s"], m["on_the_fly"]["samples_per_s"],
                         f"{m['synthesis_share']:.1%}",
                         f"{m['synchronized']['transform_share']:.1%}"])
        parts.append(_table(["network", "step ms, on the fly", "step ms, presynthesized",
                             "CPU workers (numpy), samples/s", "on the fly, samples/s",
                             "synthesis share", "synchronized share"], rows))
        parts.append(provenance(path, f"{data['device']}, `{data['backend']}`; batches of "
                                f"{data['batch']}, crops of {data['crop']}, "
                                f"{data['workers']} DataLoader workers, {data['input']}",
                                _named(data)))
    return "\n\n".join(parts)


def bench_side_by_side() -> str:
    """gpu_blur's RealBlur-J chain against a plain PyTorch port of the authors' chain."""
    data, path = load("realblur_j_side_by_side_h100")
    rows = [["gpu_blur `Synthesizer`", data["ours"]["device_ms_per_sample"],
             data["ours"]["host_to_host_ms_per_sample"]],
            ["PyTorch port of the authors' chain", data["torch"]["device_ms_per_sample"],
             data["torch"]["host_to_host_ms_per_sample"]],
            ["pinned-copy bound", None, data["pinned_copy"]["copy_bound_ms_per_sample"]]]
    table = _table(["RealBlur-J, batches of 16", "torch CUDA in and out, ms",
                    "numpy in and out, ms"], rows)
    return table + "\n\n" + provenance(path, f"{data['device']}, torch "
                                       f"{data['versions']['torch']}",
                                       _named_commit(data["versions"].get("gpu_blur_commit")))


def bench_gpu_targets() -> str:
    """Device-side figures of one sample: the passes as a CUDA graph, pinned frames."""
    data, path = load("gpu_targets_h200")
    dev, pinned = data["warp_frames_on_device"], data["warp_frames_in_pinned_memory"]
    per = data["warp_per_pass"]
    rj = data.get("warp_realblur_j_on_device")
    ms = {k: f"{v['seconds'] * 1e3:.3f}" for k, v in per.items()}
    rows = [["frames on the device, three passes as a CUDA graph",
             f"{dev['graph_seconds'] * 1e3:.3f} ms (accumulate {ms['accumulate']}, to_raw "
             f"{ms['to_raw']}, finish {ms['finish']})"],
            ["the same from Python, one synchronize / one per pass",
             f"{dev['wall_seconds_one_synchronize'] * 1e3:.2f} ms / "
             f"{dev['wall_seconds_synchronized_per_pass'] * 1e3:.2f} ms"],
            ["minimal bytes over graph time, share of a device copy",
             f"{dev['ratio_to_d2d_copy']:.1%}"]]
    if rj:
        rows.append(["RealBlur-J scene on the device, as a graph",
                     f"{rj['graph_seconds'] * 1e3:.3f} ms, {rj['ratio_to_d2d_copy']:.1%} of the "
                     "copy rate"])
    for key, label in (("one_at_a_time", "pinned frames, one sample at a time"),
                       ("pipelined", "pinned frames, the next sample's prefetched"),
                       ("pipelined_no_host_sync", "pinned frames, the host never waiting")):
        p = pinned[key]
        rows.append([label, f"{p['samples_per_s']:.0f} samples/s, {p['ratio_to_bound']:.0%} "
                     f"of the {pinned['bound_samples_per_s']:.0f}/s upload bound"])
    for key, label in (("warp_synthesize_numpy_frames", "`synthesize` from numpy, Warp"),
                       ("opencl_synthesize_numpy_frames", "`synthesize` from numpy, OpenCL")):
        if key in data:
            s = data[key]
            rows.append([f"{label}, overlapped / serial copies",
                         f"{s['overlapped']['samples_per_s']:.1f} / "
                         f"{s['serial']['samples_per_s']:.1f} samples/s"])
    table = _table(["measure", "value"], rows, 2)
    return table + "\n\n" + provenance(path, f"{data['gpu']}, Warp {data['warp']}; "
                                       f"{data['frames']} frames of {data['image'][1]} x "
                                       f"{data['image'][0]}, RSBlur-like plan, float32",
                                       _named_commit(data.get("source")))


def bench_reference() -> str:
    """The numpy float64 reference, stage by stage at 1920 x 1200."""
    data, path = load("reference_cpu")
    rows = [[k.replace("_", " "), v] for k, v in data["seconds"].items()]
    table = _table(["numpy float64, one call at 1920 x 1200", "seconds"], rows)
    return table + "\n\n" + provenance(path, f"{data['device']}, numpy {data['numpy']}",
                                       _named(data))


def bench_plan_cost(name: str) -> str:
    """Time a sample with its plan against every stage switched on."""
    data, path = load(name)
    rows = [[r["scene"], r["device"], r["with_plan_ms"], r["every_stage_on_ms"],
             f"{r['saved_fraction']:.1%}"] for r in data["rows"]]
    table = _table(["scene", "device", "with its plan, ms", "every stage on, ms", "saved"],
                   rows, 2)
    size = data["size_wxh"]
    return table + "\n\n" + provenance(path, f"{data['host']} host; {size[0]} x {size[1]}, "
                                       f"{data['input']}", _named(data))


def bench_interpolation(name: str) -> str:
    """Each interpolation setting over every test sequence: worst error and time against 8x."""
    data, path = load(name)
    settings: dict[str, list[dict]] = {}
    for r in data["rows"]:
        settings.setdefault(r["setting"], []).append(r)
    eight = sum(r["ms"] for r in settings["8x"])
    rows = []
    for setting, rs in settings.items():
        psnr = [r["psnr_db"] for r in rs if r["psnr_db"] is not None]
        rows.append([setting, max(r["max_codes"] for r in rs),
                     min(psnr) if psnr else "identical", sum(r["ms"] for r in rs) / eight])
    table = _table(["setting", "worst 8-bit codes from 8x", "worst PSNR dB", "time / 8x's"],
                   rows)
    size = data["size_wxh"]
    seqs = sorted({r["sequence"] for r in data["rows"]})
    return table + "\n\n" + provenance(path, f"{data['device']}; {size[0]} x {size[1]}, "
                                       f"{data['frames']} frames; sequences: "
                                       f"{', '.join(seqs)}", _named(data))


METRICS = {"batch_numpy_ms": "numpy in and out", "batch_pinned_ms": "pinned numpy",
           "batch_torch_cuda_ms": "torch CUDA in and out", "kernels_ms": "device kernels"}


def bench_history(name: str) -> str:
    """A results file's medians before and after the change it measured, per scene and path."""
    data, path = load(name)
    before = _named_commit(data["before"]) or data["before"].split()[0]
    after = f"{_git_commit(path).split()[0]}"
    rows = []
    for scene, new in data["medians"]["after"].items():
        old = data["medians"]["before"].get(scene, {})
        for key, label in METRICS.items():
            if key in new and key in old:
                rows.append([_scene(scene), label, old[key], new[key]])
    table = _table(["scene", "path", f"before (`{before}`)", f"after (`{after}`)"], rows, 2)
    what = data["after"].split(":", 1)[-1].strip() if ":" in data["after"] else data["after"]
    return (table + "\n\nThe change: " + _cell(what).rstrip(".") + ".\n\n"
            + provenance(path, data["device"] + "; ms a sample, medians of the rounds", None))


PNG_IMAGES = {"noisy": "noisy 1920 x 1200", "smooth": "smooth 1920 x 1200",
              "coffee": "coffee.png, 600 x 400"}


def _png_cells(rows: list[dict], image: str, pick) -> list:
    """The ms and MB (ms alone for decoders) at 8 and 16 bits of the row ``pick`` selects."""
    cells = []
    for bits in (8, 16):
        row = next((r for r in rows if r["image"] == image and r["bits"] == bits and pick(r)
                    and r.get("ms") is not None), None)
        cells += [row and row["ms"]] + ([row and row["mb"]] if rows and "mb" in rows[0] else [])
    return cells


def bench_png_codecs(name: str = "png_codecs_intel-xeon", part: str = "picks",
                     image: str = "noisy") -> str:
    """PNG codecs (bench/png_codecs.py): ``part`` picks, encode, decode (one core) or threads.

    encode and decode show ``image``; picks every image; threads reads a ``--threads`` file.
    """
    data, path = load(name)
    if part == "threads":
        return _png_threads(data, path)
    enc, dec = data["encode"], data["decode"]
    default = "opencv: no parameters"
    if part == "picks":
        from gpu_blur.png_codecs import PNG_MODES

        # gpu_blur's modes in this file (older files have no stored mode)
        modes = [m for m in PNG_MODES
                 if any(r["encoder"].endswith(f"output.png = {m}") for r in enc)]
        rows = []
        for image in data["images"]:
            for label, pick in ((f"write `output.png = \"{m}\"`",
                                 lambda r, m=m: r["encoder"].endswith(f"output.png = {m}"))
                                for m in modes):
                rows.append([PNG_IMAGES.get(image, image), label, *_png_cells(enc, image, pick)])
            rows.append([PNG_IMAGES.get(image, image), "write: OpenCV's default (before)",
                         *_png_cells(enc, image, lambda r: r["encoder"].startswith(default))])
            files = {"read: ": default} | ({"read a `\"stored\"` file: ": "output.png = stored"}
                                           if "stored" in modes else {})
            reads = [(f"{what}{reader}", decoder, file) for what, file in files.items()
                     for reader, decoder in (("`read_image`", "read_image"),
                                             ("OpenCV `imdecode`", "opencv"))]
            for label, decoder, file in reads:
                cells = _png_cells(dec, image, lambda r, d=decoder, f=file: d in r["decoder"]
                                   and f in r["file"])
                rows.append([PNG_IMAGES.get(image, image), label, cells[0], None, cells[1],
                             None])
        header = ["image", "what", "8-bit ms", "8-bit MB", "16-bit ms", "16-bit MB"]
        table = _table(header, rows, 2)
    elif part == "encode":
        names = list(dict.fromkeys(r["encoder"] for r in enc if "ms" in r))
        rows = []
        for encoder in names:
            mine = [r for r in enc if r["encoder"] == encoder]
            first = mine[0]
            rows.append([first["codec"] + _apart(encoder), first["setting"],
                         *_png_cells(enc, image, lambda r, e=encoder: r["encoder"] == e),
                         all(r.get("same") for r in mine if "ms" in r)])
        table = _table([f"encoder ({PNG_IMAGES.get(image, image)})", "setting", "8-bit ms",
                        "8-bit MB", "16-bit ms",
                        "16-bit MB", "same pixels, every image"], rows, 2)
    elif part == "decode":
        rows = []
        for decoder in dict.fromkeys(r["decoder"] for r in dec):
            mine = [r for r in dec if r["decoder"] == decoder and "same" in r]
            cells = []
            for file in (default, "opencv: level 6,"):
                cells += _png_cells(dec, image, lambda r, d=decoder, f=file:
                                    r["decoder"] == d and r["file"].startswith(f))
            same = {bits: all(r["same"] for r in mine if r["bits"] == bits)
                    for bits in (8, 16) if any(r["bits"] == bits for r in mine)}
            said = ", ".join(f"{b}-bit: {'yes' if ok else 'no'}" for b, ok in same.items())
            rows.append([decoder + _apart(decoder), *cells, said])
        table = _table([f"decoder ({PNG_IMAGES.get(image, image)})",
                        "OpenCV-default file, 8-bit ms", "16-bit ms",
                        "libpng level-6 file, 8-bit ms", "16-bit ms",
                        "same pixels, every file"], rows)
    else:
        raise GenError(f"bench png-codecs: part picks, encode, decode or threads; got "
                       f"{part!r}")
    machine = data["machine"]
    libraries = ", ".join(f"{k} {v}" for k, v in data["libraries"].items())
    return table + "\n\n" + provenance(
        path, f"{machine['cpu']} (family {machine.get('family')}, model {machine.get('model')})"
        f", {machine['cores']} cores, one of them pinned, OpenCV on one thread; medians of "
        f"{_runs(data)} rounds; {libraries}", _named_commit(data.get("commit")))


def _png_threads(data: dict, path: Path) -> str:
    """Images a second through pools of threads (bench/png_codecs.py --threads)."""
    counts = sorted({r["threads"] for r in data["rows"]})
    images = list(dict.fromkeys(r.get("image", "noisy") for r in data["rows"]))
    rows = []
    for image in images:
        for bits in (8, 16):
            for codec in dict.fromkeys(r["codec"] for r in data["rows"]):
                rate = {r["threads"]: r["images_per_s"] for r in data["rows"]
                        if r.get("image", "noisy") == image and r["bits"] == bits
                        and r["codec"] == codec}
                if rate:
                    rows.append([f"{image}, {bits}-bit", codec, *(rate.get(n) for n in counts)])
    table = _table(["", "codec, images a second", *(f"{n} threads" if n > 1 else "1 thread"
                                                     for n in counts)], rows, 2)
    machine, libraries = data["machine"], data["libraries"]
    versions = ", ".join(f"{name} {libraries[name]}" for name in
                         ("deflate", "isal", "opencv-python-headless") if name in libraries)
    return table + "\n\n" + provenance(
        path, f"{machine['cpu']} (family {machine.get('family')}, model "
        f"{machine.get('model')}), {machine['cores']} cores, the host of an H200; the "
        f"{' and '.join(images)} 1920 x 1200 image{'s' if len(images) > 1 else ''}; best of 3 "
        f"pool runs; {versions}", _named_commit(data.get("commit")))


def _apart(name: str) -> str:
    """pyspng-seunglab runs in a child process (its module clashes with pyspng's)."""
    return " (timed in a process of its own)" if "seunglab" in name else ""


def _runs(data: dict) -> str:
    match = re.search(r"median of (\d+)", data["what"])
    return match.group(1) if match else "several"


#: ``bench NAME [ARG]``: the tables a page may ask for.
BENCH = {
    "per-sample": bench_per_sample,
    "batches": bench_batches,
    "pinned-h100": bench_pinned_h100,
    "back-to-back": bench_back_to_back,
    "codes": bench_codes,
    "synthesize-vs-batch": bench_synthesize_vs_batch,
    "generate-threads": bench_generate_threads,
    "generate-codes": bench_generate_codes,
    "generate-devices": bench_generate_devices,
    "generate-windows": bench_generate_windows,
    "decode-threads": bench_decode_threads,
    "device-path-beside": bench_device_path_beside,
    "devices-host": bench_devices_host,
    "device-frames": bench_device_frames,
    "png-bytes": bench_png_bytes,
    "png-huffman": bench_png_huffman,
    "png-device": bench_png_device,
    "sharp-once": bench_sharp_once,
    "devices-handoff": bench_devices_handoff,
    "float-inputs": bench_float_inputs,
    "multi-gpu": bench_multi_gpu,
    "training": bench_training,
    "side-by-side": bench_side_by_side,
    "gpu-targets": bench_gpu_targets,
    "reference": bench_reference,
    "plan-cost": bench_plan_cost,
    "interpolation": bench_interpolation,
    "history": bench_history,
    "png-codecs": bench_png_codecs,
}


def accuracy(name: str) -> str:
    """``gpu-blur bench``'s summary of one results file, with its host, devices and commit."""
    from gpu_blur.analysis.bench.report import summary_table

    data, path = load(name)
    devices = "; ".join(f"`{k}` {v}" for k, v in data["devices"].items())
    size = data["size"]
    note = (f"{data['cpu']} host, load average {data['load_average'][0]} to "
            f"{data['load_average'][1]}; {data['frames']} frames of {size[0]} x {size[1]}; "
            f"devices: {devices}")
    return "\n".join(summary_table(data)) + "\n\n" + provenance(
        path, note, _named_commit(data.get("source")))


# -- markers -----------------------------------------------------------------------------------

def expand(kind: str, args: list[str]) -> str:
    """The Markdown a marker stands for."""
    if kind == "cli-help":
        return cli_help(*args[:1])
    if kind == "cli-commands":
        return cli_commands()
    if kind == "scene-keys":
        return scene_keys()
    if kind == "cameras":
        return cameras()
    if kind == "tolerances":
        return tolerances()
    if kind == "bench":
        if not args or args[0] not in BENCH:
            raise GenError(f"bench: name one of {', '.join(BENCH)}; got {args}")
        return BENCH[args[0]](*args[1:])
    if kind == "accuracy":
        return accuracy(*args)
    if kind == "file":
        path = ROOT / args[0]
        if not path.is_file():
            raise GenError(f"file: no file {args[0]}")
        lang = args[1] if len(args) > 1 else "text"
        return f"```{lang}\n" + path.read_text(encoding="utf-8").rstrip() + "\n```"
    if kind == "image":
        from_root, alt = args[0], " ".join(args[1:])
        if not (ROOT / from_root).is_file():
            raise GenError(f"image: no file {from_root}")
        return f"![{alt}]({image_uri(from_root)})"
    raise GenError(f"unknown marker kind {kind!r}")


def image_uri(from_root: str) -> str:
    """Where the hook puts a repository file in the site (``assets/<path>``)."""
    return "assets/" + from_root


def images(markdown: str) -> list[str]:
    """The repository files a page's ``image`` markers name."""
    return [shlex.split(m["args"])[0] for m in MARKER.finditer(markdown)
            if m["kind"] == "image"]


def render_page(markdown: str, depth: int = 0) -> str:
    """``markdown`` with every marker replaced; ``depth``: folders below docs/ (for links)."""
    def one(m: re.Match) -> str:
        text = expand(m["kind"], shlex.split(m["args"]))
        text = text.replace("](assets/", "](" + "../" * depth + "assets/")
        return "\n".join(m["indent"] + line if line else line for line in text.split("\n"))
    return MARKER.sub(one, markdown)
