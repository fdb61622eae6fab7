"""The benchmark's report files: JSON (every number), Markdown (the tables), PNG (the plot)."""

from __future__ import annotations

import json
from pathlib import Path

from gpu_blur.analysis.bench.peers import BORDER_PX, KERNEL_SIZE
from gpu_blur.analysis.bench.plot import write_plot
from gpu_blur.analysis.bench.workload import MIN_RUNS
from gpu_blur.file_writing import write_text

__all__ = ["markdown", "report_paths", "summary_table", "write_report"]


def _number(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if value == 0:
        return "0"
    return f"{value:.{digits}g}"


def summary_table(report: dict) -> list[str]:
    """One line per knob setting: ms per megapixel on each backend, the largest errors.

    Errors are the largest over the backends that ran the setting (the numpy row shows the
    setting's own effect; kernel rows add their float32 rounding).
    """
    specs = list(report["devices"])
    lines = ["| knob | setting | " + " | ".join(f"`{s}` ms/MP" for s in specs)
             + " | max abs error | residual KL |",
             "|---|---|" + "---:|" * (len(specs) + 2)]
    settings = dict.fromkeys((r["knob"], r["setting"], r["reference"]) for r in report["rows"])
    for knob, label, reference in settings:
        rows = [r for r in report["rows"] if (r["knob"], r["setting"]) == (knob, label)]
        cells = []
        for spec in specs:
            row = next((r for r in rows if r["backend"] in (spec, "-")), None)
            cells.append("" if row is None and spec == "numpy"
                         else "n/a" if row is None or not row["available"]
                         else _number(row["ms_per_megapixel"], 4))
        worst = {key: max((r[key] for r in rows if r[key] is not None), default=None)
                 for key in ("max_abs_error", "residual_kl")}
        star = " *" if reference else ""
        lines.append(f"| {knob} | {label}{star} | " + " | ".join(cells)
                     + f" | {_number(worst['max_abs_error'])} | "
                     f"{_number(worst['residual_kl'])} |")
    return lines


def markdown(report: dict) -> str:
    """The report's tables in Markdown."""
    size = report["size"]
    lines = [
        f"# Accuracy against time: {report['frames']} frames of {size[0]} x {size[1]}",
        "",
        f"Host: {report['cpu']}, 1-minute load average {report['load_average'][0]} at the "
        f"start and {report['load_average'][1]} at the end (other work slows the runs). "
        f"Source: {report['source']} (files' SHA-256 "
        f"{str(report.get('source_digest'))[:16]}...). Devices: "
        + "; ".join(f"`{k}` {v}" for k, v in report["devices"].items()) + ".",
        "",
        "Base scene (RSBlur-like): " + json.dumps(report["base_scene"]) + ". Times: median of "
        f"{report['runs']} runs after a warm-up, each setting timed in turn with its knob's "
        "accurate setting (time / accurate: the ratio of the two medians)"
        + (f" (numpy: {report['reference_runs']} run, no warm-up: here it only makes the "
           "reference images; its medians are in the CPU run)"
           if report.get("reference_runs", report["runs"]) < MIN_RUNS else "")
        + ", frames in host memory, result back on the "
        "host, per megapixel of output. Errors: the final image without noise (RAW round "
        "trip kept, float output) against the numpy float64 run of the knob's accurate "
        "setting (*); residual KL: D(reference || run) of the noise residuals (final with "
        "noise minus final without), one bin per 8-bit code, add-one smoothing. "
        "PSNR \"-\" means identical.",
        "",
        "Summary (empty: numpy ignores the setting, it always runs float64 with precise "
        "maths on whole images; n/a: not offered, by the scene or by that backend (the note "
        "below says which); errors: the largest over the backends):",
        "",
        *summary_table(report),
        "",
        "Every row:",
        "",
        "| knob | setting | backend | ms/MP | time / accurate | max abs error | PSNR (dB) | "
        "residual KL | note |",
        "|---|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in report["rows"]:
        star = " *" if r["reference"] else ""
        lines.append(
            f"| {r['knob']} | {r['setting']}{star} | {r['backend']} | "
            f"{_number(r['ms_per_megapixel'], 4)} | {_number(r.get('time_vs_accurate'))} | "
            f"{_number(r['max_abs_error'])} | "
            f"{_number(r['psnr_db'], 4)} | {_number(r['residual_kl'])} | "
            f"{r['note'].replace('|', '/')} |")
    side = report["side_by_side"]
    lines += ["", "## Side by side: what a user would pick instead", "",
              "Whole pipeline, base scene, against the numpy reference:", "",
              "| backend | device | ms/MP | speed-up over numpy | max abs error | residual KL |",
              "|---|---|---:|---:|---:|---:|"]
    for r in side["pipeline"]:
        if r["available"]:
            lines.append(f"| {r['backend']} | {r['device']} | "
                         f"{_number(r['ms_per_megapixel'], 4)} | "
                         f"{_number(r['speedup_over_numpy'])} | "
                         f"{_number(r['max_abs_error'])} | {_number(r['residual_kl'])} |")
        else:
            lines.append(f"| {r['backend']} | {r['device']} | - | - | - | {r['note']} |")
    for key, title in (("demosaic", "Demosaicing one RGGB mosaic of the linear middle frame, "
                        f"against our float64 Malvar 2004, outputs clipped to [0, 1], "
                        f"{BORDER_PX} px border left out:"),
                       ("kernel_blur", f"Kernel blur, a {KERNEL_SIZE} x {KERNEL_SIZE} random "
                        "motion kernel on the linear middle frame, against our float64 FFT "
                        "convolution (both reflect-101):")):
        lines += ["", title, "", "| method | time covers | ms/MP | max abs error | PSNR (dB) |",
                  "|---|---|---:|---:|---:|"]
        for r in side[key]:
            if "note" in r:
                lines.append(f"| {r['method']} | {r['note']} | - | - | - |")
                continue
            lines.append(f"| {r['method']} | {r['covers']} | "
                         f"{_number(r['ms_per_megapixel'], 4)} | "
                         f"{_number(r['max_abs_error'])} | {_number(r['psnr_db'], 4)} |")
    return "\n".join(lines) + "\n"


def report_paths(folder: Path, tag: str) -> list[Path]:
    """The report's JSON, Markdown and PNG files."""
    stem = folder / f"accuracy_vs_time_{tag}"
    return [stem.with_suffix(".json"), stem.with_suffix(".md"), stem.with_suffix(".png")]


def write_report(report: dict, folder: Path, tag: str) -> list[Path]:
    """Write the JSON, Markdown and PNG files of a report; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = report_paths(folder, tag)
    write_text(paths[0], json.dumps(report, indent=1, allow_nan=False) + "\n")
    write_text(paths[1], markdown(report))
    size = report["size"]
    write_plot(report["rows"], paths[2], f"gpu_blur accuracy against time, {report['frames']} "
               f"frames of {size[0]} x {size[1]}, {report['cpu']}; "
               + ", ".join(report["devices"]))
    return paths
