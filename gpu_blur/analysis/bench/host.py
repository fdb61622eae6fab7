"""The machine and the code that run: CPU name, source commit and digest, backends present."""

from __future__ import annotations

import os
import platform
import re
from collections.abc import Sequence
from pathlib import Path

__all__ = ["ROOT", "available_backends", "choose_backends", "cpu_name", "device_tag",
           "load_average", "source_commit", "source_digest"]

#: The repository root (or the installed package's parent folder): gpu_blur/analysis/bench/..
ROOT = Path(__file__).resolve().parents[3]


def cpu_name() -> str:
    """The host CPU's model name (``/proc/cpuinfo``), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def source_commit() -> str | None:
    """The git commit of the gpu_blur source that runs (``+modified`` when files differ).

    None when the package does not sit in a git checkout (an installed wheel).
    """
    import subprocess

    root = ROOT

    def git(*args):
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD")
        modified = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+modified" if modified else "")


def source_digest() -> str:
    """SHA-256 of the code that runs: every file under gpu_blur/ and kernels/, by path.

    A commit names the code only where the checkout's git metadata is its own (a copy of the
    tree on another machine may carry stale metadata); the digest of the files themselves can
    be checked against any commit (``git worktree add``, then this function there).
    """
    import hashlib

    root = ROOT
    digest = hashlib.sha256()
    for folder in ("gpu_blur", "kernels"):
        for path in sorted((root / folder).rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                digest.update(path.relative_to(root).as_posix().encode() + b"\0")
                digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


def available_backends() -> dict[str, dict]:
    """Every backend of this host that can run: spec -> {device, kind, fp64}.

    numpy, every OpenCL device that builds kernels, every Warp device; a backend whose Python
    package is missing is left out.
    """
    found = {"numpy": {"device": f"numpy float64 on {cpu_name()}", "kind": "CPU",
                       "fp64": True}}
    try:
        from gpu_blur.backends.opencl import opencl_devices
    except ImportError:
        pass
    else:
        for d in opencl_devices():
            if d.usable:
                found[d.spec] = {"device": f"{d.kind} {d.name} ({d.platform})", "kind": d.kind,
                                 "fp64": d.fp64}
    try:
        from gpu_blur.backends.warp import warp_devices
    except ImportError:
        pass
    else:
        for d in warp_devices():
            name = cpu_name() if d["kind"] == "CPU" else d["name"]  # Warp names its CPU "CPU"
            found[d["spec"]] = {"device": f"{d['kind']} {name} (Warp)", "kind": d["kind"],
                                "fp64": d["fp64"]}
    return found


def choose_backends(wanted: Sequence[str] | None) -> dict[str, dict]:
    """The backends to run: ``wanted`` (numpy always first: it is the reference), or all.

    Raises:
        ValueError: naming a wanted backend that is not present and the ones that are.
    """
    present = available_backends()
    if not wanted:
        return present
    unknown = [w for w in wanted if w not in present]
    if unknown:
        raise ValueError(f"--backends: {', '.join(unknown)} not present (or cannot build "
                         f"kernels); present: {', '.join(present)} (see gpu-blur devices)")
    return {s: present[s] for s in ["numpy", *[w for w in wanted if w != "numpy"]]}


def device_tag(backends: dict[str, dict]) -> str:
    """Output file tag: ``cpu`` when no GPU runs, else the first GPU's name as a slug."""
    gpus = [b["device"] for b in backends.values() if b["kind"] == "GPU"]
    if not gpus:
        return "cpu"
    name = gpus[0].split("(")[0].removeprefix("GPU ")  # "GPU NVIDIA H200 (NVIDIA CUDA)"
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def load_average() -> float | None:
    """The host's 1-minute load average (None where the OS does not say)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None
