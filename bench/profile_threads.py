"""Where each thread of a run spends its time: a command sampled by py-spy, summed by thread.

Runs ``py-spy record --subprocesses --threads --idle`` on the command after ``--`` (by default
``python -m gpu_blur.cli`` with the arguments given), so every thread of the driver and of
each ``--devices`` worker is sampled, waiting or not, without changing the code. The samples
are summed per process and per thread group (a pool's threads, ``gpu-blur-io_0`` ...
``gpu-blur-io_31``, are one group ``gpu-blur-io``), and for each group print:

- ``seconds``: the samples over the rate, summed over the group's threads (a pool of 32
  threads busy for a second counts 32 s);
- ``where``: the group's time by the deepest frame of the package (``gpu_blur/...``) in each
  sample, which stage of ours it was in, beside ``outside`` (no package frame);
- ``leaf``: the group's time by the innermost frame (what it was doing: a lock's wait, a
  memcpy in numpy, a pipe read).

py-spy samples the Python stacks only (``--native`` would add C frames, slower): time in a C
call shows as the Python frame that made it. Needs py-spy (``pip install py-spy``) and the
right to read the child processes' memory (a container may need ``--cap-add SYS_PTRACE``).

    python bench/profile_threads.py --json threads.json -- generate --output /tmp/out \\
        --devices warp:cuda:0,warp:cuda:1 --samples-per-sequence 256 --input FRAMES --quiet
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

PROCESS = re.compile(r'process (\d+):"(.*)"$')
THREAD = re.compile(r"thread \((\w+)\)(?:: (.*))?$")
FRAME = re.compile(r"^(.*) \((.+?)(?::\d+)?\)$")


def group_of(name: str | None) -> str:
    """A thread's group: its name without a pool's ``_N`` (``unnamed`` for none)."""
    return re.sub(r"_\d+$", "", name) if name else "unnamed"


def role_of(command: str) -> str:
    """What a sampled process is, from its command line."""
    if "resource_tracker" in command:
        return "resource tracker"
    if "multiprocessing.spawn" in command:
        return "worker"
    return "driver"


def ours(frame: str) -> str | None:
    """``function (gpu_blur/module.py)`` for a frame of the package, else None."""
    m = FRAME.match(frame)
    if not m or "gpu_blur/" not in m[2]:
        return None
    return f"{m[1]} ({m[2][m[2].index('gpu_blur/'):]})"


def leaf_of(frame: str) -> str:
    """A frame without its line number: ``function (file)``."""
    m = FRAME.match(frame)
    return f"{m[1]} ({m[2]})" if m else frame


def summarize(lines, rate: float, top: int = 8) -> list[dict]:
    """py-spy's raw lines (``frame;frame;... count``) summed per process and thread group.

    Returns one row per (process, group), the most sampled first: ``process`` (its pid and
    role), ``group``, ``threads``, ``seconds``, and ``where`` and ``leaf`` (the ``top``
    frames' seconds, as the module docstring says).
    """
    seconds = Counter()
    threads = defaultdict(set)
    where, leaf = defaultdict(Counter), defaultdict(Counter)
    for line in lines:
        stack, _, count = line.rstrip("\n").rpartition(" ")
        if not stack or not count.isdigit():
            continue
        parts = stack.split(";")
        process, thread, frames, i = None, None, [], 0
        while i < len(parts):
            part = parts[i]
            if part.startswith("process "):  # its command line may hold a ';'
                while not part.endswith('"') and i + 1 < len(parts):
                    i += 1
                    part += ";" + parts[i]
                if (m := PROCESS.match(part)) is not None:
                    process = f"{m[1]} ({role_of(m[2])})"
            elif (m := THREAD.match(part)) is not None:
                thread, frames = m, parts[i + 1:]
                break
            i += 1
        if process is None or thread is None or "(resource tracker)" in process:
            continue
        key = (process, group_of(thread[2]))
        s = int(count) / rate
        seconds[key] += s
        threads[key].add(thread[1])
        mine = [f for f in map(ours, frames) if f is not None]
        where[key][mine[-1] if mine else "outside"] += s
        leaf[key][leaf_of(frames[-1]) if frames else "idle"] += s
    return [{"process": process, "group": group, "threads": len(threads[key]),
             "seconds": seconds[key],
             "where": dict(where[key].most_common(top)),
             "leaf": dict(leaf[key].most_common(top))}
            for key, _ in seconds.most_common() for process, group in [key]]


def render(rows: list[dict]) -> str:
    """The rows as text, a block per process and thread group."""
    out = []
    for row in rows:
        out.append(f"{row['process']}, {row['group']} ({row['threads']} thread"
                   f"{'s' if row['threads'] > 1 else ''}): {row['seconds']:.2f} s")
        for label in ("where", "leaf"):
            for frame, s in row[label].items():
                out.append(f"  {label:5}  {s:7.2f} s  {100 * s / row['seconds']:5.1f} %  {frame}")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rate", type=float, default=200, help="samples a second (default 200)")
    p.add_argument("--top", type=int, default=8, help="frames shown per group (default 8)")
    p.add_argument("--json", help="write the rows here")
    p.add_argument("--raw", help="summarize this py-spy raw file instead of running anything")
    p.add_argument("command", nargs=argparse.REMAINDER,
                   help="after --: gpu-blur's arguments, or a whole command (starting with "
                        "python or a path)")
    args = p.parse_args(argv)
    command = given = args.command[1:] if args.command[:1] == ["--"] else args.command
    returncode = 0
    if args.raw:
        raw = Path(args.raw).read_text().splitlines()
    else:
        if not command:
            p.error("give the command after --, or --raw FILE")
        spy = shutil.which("py-spy")
        if spy is None:
            raise SystemExit("py-spy is not on PATH: pip install py-spy")
        if not (command[0].startswith(("python", "/", ".")) or shutil.which(command[0])):
            command = [sys.executable, "-m", "gpu_blur.cli", *command]
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "raw.txt"
            done = subprocess.run([spy, "record", "--subprocesses", "--threads", "--idle",
                                   "--nonblocking", "-r", str(args.rate), "-f", "raw",
                                   "-o", str(out), "--", *command], check=False)
            if not out.exists():
                raise SystemExit(f"py-spy wrote nothing (exit {done.returncode})")
            raw = out.read_text().splitlines()
            returncode = done.returncode  # py-spy's own: it does not pass on the command's
    rows = summarize(raw, args.rate, args.top)
    print(render(rows))
    if args.json:
        Path(args.json).write_text(json.dumps({"command": given, "rate": args.rate,
                                               "returncode": returncode, "rows": rows},
                                              indent=1) + "\n")
    return returncode


if __name__ == "__main__":
    raise SystemExit(main())
