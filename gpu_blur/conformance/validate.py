"""``gpu-blur validate``: run the conformance checks on devices and report them.

:func:`run` gives a report (a JSON-ready dict: per device and precision, each check's outcomes,
with the device's name, driver and library versions); :func:`render` makes it the tables the
command prints.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time

from gpu_blur import backends
from gpu_blur.conformance import checks
from gpu_blur.conformance.checks import Outcome, Target

__all__ = ["PRECISIONS", "UsageError", "device_info", "kernel_devices", "open_target", "render",
           "run"]

PRECISIONS = ("float32", "float64")


class UsageError(ValueError):
    """A backend, precision or pairing that cannot be validated as asked (exit status 2)."""


def kernel_devices() -> list[str]:
    """Every usable kernel device here: each OpenCL device that builds kernels, each Warp one."""
    found = []
    for kind in ("opencl", "warp"):
        with contextlib.suppress(ImportError):  # the family's library is not installed
            found += backends.usable_devices(kind, "float32")[0]
    return found


def device_info(backend) -> dict:
    """The device's name, its driver and the versions of the libraries its results depend on."""
    from gpu_blur.run_record import library_versions

    if backend.name == "opencl":
        dev = backend.cl_device
        driver = f"driver {dev.driver_version}; platform {dev.platform.version.strip()}"
    elif backend.name == "warp":
        import warp as wp

        if backend.wp_device.startswith("cuda"):
            driver = (f"CUDA driver {wp.get_cuda_driver_version()}, toolkit "
                      f"{wp.get_cuda_toolkit_version()}")
        else:
            driver = "Warp's CPU code generator (LLVM, built into Warp)"
    else:
        driver = "host CPU (numpy)"
    name = backend.device.rpartition(",")[0] or backend.device  # without the precision
    return {"device": name, "driver": driver, "libraries": library_versions(backend.name)}


def open_target(name: str, precision: str) -> Target | str:
    """The device ``name`` at ``precision``, or why that precision cannot run there.

    Raises:
        UsageError: the name is no backend or device here.
    """
    if checks.family(name) == "numpy" and precision != "float64":
        return "numpy is float64 only"
    try:
        backend = backends.get_backend(name, precision)
    except Exception as e:  # OpenCLError, ValueError, RuntimeError (missing library)
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        if "fp64" in message:
            return message
        raise UsageError(f"--backend {name}: {message}") from None
    return Target(backend, checks.family(name), precision)


def _outcome_dict(o: Outcome) -> dict:
    d = dataclasses.asdict(o)
    d["measured"] = checks.finite_or_none(o.measured)
    d["claim"] = checks.row_sources().get(tuple(o.row.split("/")), (0, ""))[1] if o.row else ""
    return d


def run(names: list[str], precisions: list[str], *, quick: bool = False,
        against: str | None = None, progress: bool = True) -> dict:
    """Validate each device of ``names`` at each precision; a report ready for JSON.

    Args:
        names: backend names (``numpy``, ``opencl:1:0``, ``warp:cpu``).
        precisions: ``float32`` and/or ``float64``.
        quick: only the checks marked quick.
        against: a second device: compare each of ``names`` with it directly (the
            cross-backend rows) instead of with the reference.
        progress: a line per check on stderr.

    Raises:
        UsageError: an unknown backend or an impossible pairing.
    """
    start = time.perf_counter()
    def say(text: str) -> None:
        if progress:
            print(text, file=sys.stderr, flush=True)

    items = checks.selected(quick) if against is None else checks.AGAINST
    devices = []
    plan = []
    for name in names:
        for precision in precisions:
            target = open_target(name, precision)
            other = open_target(against, precision) if against and not isinstance(target, str) \
                else None
            plan.append((name, precision, target, other))
    if against:
        for name, *_ in plan:
            if "numpy" in (checks.family(name), checks.family(against)):
                raise UsageError("--against compares two kernel devices; numpy is the reference "
                                 "every check already compares with (drop --against)")
    total = sum(len(items) for *_, t, o in plan if not isinstance(t, str)
                and not isinstance(o, str))
    done = 0
    for name, precision, target, other in plan:
        entry = next((d for d in devices if d["backend"] == name), None)
        if entry is None:
            entry = {"backend": name, "rows": []}
            devices.append(entry)
        why = target if isinstance(target, str) else other if isinstance(other, str) else None
        if why:
            entry["rows"].append(_outcome_dict(Outcome("all checks", "-", None, "", None, "",
                                                       None, why)) | {"precision": precision})
            say(f"{name} {precision}: skipped ({why})")
            continue
        entry.update(device_info(target.backend))
        if other is not None:
            entry["against"] = {"backend": against, **device_info(other.backend)}
        for item in items:
            done += 1
            t0 = time.perf_counter()
            outcomes = checks.run_check(item, target, other)
            seconds = time.perf_counter() - t0
            verdict = ("FAIL" if not checks.passed(outcomes) else
                       "skip" if all(o.passed is None for o in outcomes) else "ok")
            say(f"[{done}/{total}] {name} {precision} {item.name}: {verdict} ({seconds:.1f} s)")
            entry["rows"] += [_outcome_dict(o) | {"precision": precision, "seconds": seconds}
                              for o in outcomes]
    rows = [r for d in devices for r in d["rows"]]
    return {"passed": all(r["passed"] is not False for r in rows), "quick": quick,
            "against": against, "seconds": round(time.perf_counter() - start, 1),
            "checks": len({r["check"] for r in rows}), "failed": sum(r["passed"] is False
                                                                    for r in rows),
            "devices": devices}


def _number(x: float | None) -> str:
    return "-" if x is None else "0" if x == 0 else f"{x:.2g}"


def _tolerance(text: str) -> str:
    """``rtol 0, atol 1e-06`` as ``atol 1e-06``: the table's short form."""
    if not text.startswith("rtol"):
        return text
    row, _, outliers = text.partition("; ")
    parts = [p for p in row.split(", ") if not p.endswith(" 0")]
    short = ", ".join(parts) or "exact"
    return f"{short}; {outliers.replace(' of values may miss', ' may miss')}" if outliers \
        else short


def _cell(rows: list[dict]) -> str:
    """One precision's measured error, tolerance and verdict for a check's stage."""
    if not rows:
        return ""
    if all(r["passed"] is None for r in rows):
        return f"{'-':<9}{'':<29}skip"
    measured = [r["measured"] for r in rows if r["measured"] is not None]
    verdict = "pass" if all(r["passed"] is not False for r in rows) else "FAIL"
    return (f"{_number(max(measured) if measured else None):<9}"
            f"{_tolerance(rows[0]['tolerance']):<29}{verdict}")


def _sources(rows: list[dict]) -> str:
    """Where the rows' claims come from: lines of gpu_blur/tolerances.py, or why exact."""
    lines = [r["source"].partition(":")[2] for r in rows if r["row"]]
    if lines:
        return "tolerances.py:" + " / ".join(dict.fromkeys(lines))
    texts = [r["source"] or r["detail"] for r in rows]
    return texts[0] if texts else ""


def render(report: dict) -> str:
    """The report as text: a table per device, then each failure with its first mismatch.

    A table row is a check's stage; per precision, the largest error of its comparisons (or
    the fraction of values out of tolerance, for rows that allow some), the tolerance and the
    verdict; last, the row's line in gpu_blur/tolerances.py or why the claim is exact.
    """
    out = []
    for d in report["devices"]:
        device = d.get("device", "").removeprefix(d["backend"] + " ")
        out.append(f"== {d['backend']}: {device}")
        if "driver" in d:
            libs = ", ".join(f"{k} {v}" for k, v in d["libraries"].items())
            out.append(f"   {d['driver']}; {libs}")
        if "against" in d:
            a = d["against"]
            device = a["device"].removeprefix(a["backend"] + " ")
            out.append(f"   against {a['backend']}: {device}; {a['driver']}")
        ran = [r for r in d["rows"] if r["check"] != "all checks"]
        for r in d["rows"]:
            if r["check"] == "all checks":
                out.append(f"   {r['precision']}: skipped ({r['detail']})")
        precisions = list(dict.fromkeys(r["precision"] for r in ran))
        groups: dict = {}
        for r in ran:
            groups.setdefault((r["check"], r["stage"]), []).append(r)
        if not groups:
            out.append("")
            continue
        head = "".join(f"{p:<9}{'tolerance':<29}{'':<4}  " for p in precisions)
        out.append(f"{'check':<56}{'stage':<30}{head}source")
        for (check, stage), rows in groups.items():
            cells = "".join(f"{_cell([r for r in rows if r['precision'] == p]):<42}  "
                            for p in precisions)
            out.append(f"{check[:55]:<56}{stage[:29]:<30}{cells}{_sources(rows)}".rstrip())
        out.append("")
    failures = [(d["backend"], r) for d in report["devices"] for r in d["rows"]
                if r["passed"] is False]
    for backend, r in failures:
        out.append(f"FAIL {backend} {r['precision']} {r['check']} [{r['stage']}]: {r['detail']}")
    words = "quick run" if report["quick"] else "full run"
    verdict = "every check passed" if report["passed"] else f"{report['failed']} comparisons failed"
    out.append(f"validate ({words}, {report['checks']} checks): {verdict} in "
               f"{report['seconds']:.1f} s")
    return "\n".join(out)
