"""PNG frames decoded by a pool of threads, with glibc's malloc as it comes and keeping memory.

Writes ``--frames`` frames of 1920 x 1200 (``generate_gpu.write_sequence``: the built-in
photo panned 2 px a frame, saved with OpenCV's defaults, as a user's frames most often are),
then ``--rounds`` times, each setting of :data:`SETTINGS` in turn (``glibc``: glibc's own;
``keep``: glibc's variables below, which keep freed memory in the process for the next frame
where glibc would give it back to the kernel), a fresh process that decodes every frame
through ``--threads`` threads (``read_image``, as ``generate``'s I/O threads do) after
decoding ``2 x threads`` of them uncounted. Each run: the pool's wall seconds, frames a second,
the milliseconds a frame took a thread (threads x seconds / frames) and the process's peak
resident memory (MiB).

``--generate N --backend warp`` adds ``gpu-blur generate`` over N distinct windows of the
first ``9 N`` frames (each frame read by one sample, as ``generate_gpu.py --windows
distinct``) with each setting in turn, ``--rounds`` times, after one such run uncounted (the
first run on a host builds or loads the kernels and meets cold caches: at 74843aa on an H200
host it ran at less than half the later runs' rate): its own rate (its ``wrote`` line), its
I/O threads' decoding line, and its peak resident memory.

``--parts`` adds, in a process of each setting per round, where one frame's decode spends
its time on one thread (``parts``, milliseconds, the median of ``--part-runs`` calls each):
``read_image`` whole, ``decode_png`` on the file's bytes, and its steps alone on the same
bytes: the walk over the chunks, the join of the IDAT data, the inflate, the unfiltering
(Sub rows: numpy's running sum). The steps reuse one frame's buffers call after call; the
whole decode makes new ones each time, so the difference between the whole and its steps is
mostly the new memory's cost, which the settings change.

At 74843aa ``gpu-blur generate`` set ``keep`` itself (through ``mallopt``); it gained too
little in the run for the memory it cost and was taken out (docs/performance.md, "Freed
memory kept"). The variables set the same from the process's start.

    PYTHONPATH=$PWD python3 bench/decode_threads.py --frames 2304 --generate 256 \\
        --backend warp --json bench/results/decode_threads_h200.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import generate_gpu  # noqa: E402  (this folder's benches: the frames, the runs, the host)
import png_codecs  # noqa: E402

#: glibc's malloc variables of each setting (mallopt(3)): ``keep`` serves blocks up to 32 MiB
#: from the heaps (a frame of 16-bit 1920 x 1200 RGB is 13.8 MB), returns a heap's memory to
#: the kernel only past 1 GiB free at its top, and grows a heap 64 MiB more than it needs.
SETTINGS = {
    "glibc": {},
    "keep": {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 30),
             "MALLOC_TOP_PAD_": str(64 << 20)},
}

#: The decoding process (its setting in its environment): the pool, timed.
_DECODE = """
import sys, time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from gpu_blur.image_reading import read_image
paths, threads = sorted(Path(sys.argv[1]).rglob("*.png")), int(sys.argv[2])
with ThreadPoolExecutor(threads) as pool:
    list(pool.map(lambda p: read_image(p).shape, paths[:2 * threads]))
    start = time.perf_counter()
    list(pool.map(lambda p: read_image(p).shape, paths))
    print(time.perf_counter() - start, len(paths), peak_kb(), sep="\\t")
"""
#: One frame's decode and its steps on one thread (``--parts``): their median ms, as JSON.
_PARTS = """
import json, statistics, sys, time
from pathlib import Path
import numpy as np
from gpu_blur import png_codecs
from gpu_blur.image_reading import read_image
path, runs = Path(sys.argv[1]), int(sys.argv[2])
data = path.read_bytes()
width, height, depth, channels, idat = png_codecs._idat(data)
step = channels * depth // 8
stride = 1 + width * step
joined = b"".join(idat)
inflater = png_codecs._inflater()
if inflater is None:
    sys.exit("--parts: gpu_blur's decoder needs the deflate (or isal) package")
name, inflate = inflater
rows = np.frombuffer(inflate(joined, height * stride), np.uint8).reshape(height, stride)
steps = {"read_image": lambda: read_image(path),
         "decode_png": lambda: png_codecs.decode_png(data),
         "chunks": lambda: png_codecs._idat(data), "join": lambda: b"".join(idat),
         "inflate": lambda: inflate(joined, height * stride),
         "unfilter": lambda: png_codecs._unfilter(rows[:, 0], rows[:, 1:], step)}
times = {key: [] for key in steps}
for _ in range(runs + 1):  # the first round uncounted
    for key, call in steps.items():
        start = time.perf_counter()
        call()
        times[key].append(1e3 * (time.perf_counter() - start))
print(json.dumps({"inflater": name, "idat_chunks": len(idat),
                  "ms": {key: statistics.median(t[1:]) for key, t in times.items()}}))
"""
#: The process's peak resident memory (Linux: KiB), for both children.
_PEAK = """
import resource
def peak_kb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
"""
#: ``gpu-blur generate`` that says its peak memory after its summary.
_GENERATE = """
import sys
from gpu_blur.cli import main
status = main(sys.argv[1:])
print(f"peak memory {peak_kb()} KiB", file=sys.stderr)  # last of its output
sys.exit(status)
"""


def _environment(setting: str) -> dict[str, str]:
    """This process's environment without glibc's malloc variables, plus ``setting``'s."""
    return {**{k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")},
            **SETTINGS[setting]}


def decode_run(root: Path, threads: int, setting: str) -> dict:
    """One decoding process with ``setting``: seconds, frames/s, ms a frame a thread."""
    env = _environment(setting)
    done = subprocess.run([sys.executable, "-c", _PEAK + _DECODE, str(root), str(threads)],
                          env=env, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    seconds, frames, peak = done.stdout.strip().split("\t")
    seconds, frames = float(seconds), int(frames)
    return {"seconds": seconds, "frames_per_s": frames / seconds,
            "ms_a_frame_a_thread": 1e3 * threads * seconds / frames,
            "peak_memory_mib": int(peak) / 1024}


def parts_run(frame: Path, runs: int, setting: str) -> dict:
    """One process with ``setting`` timing a frame's decode and its steps (:data:`_PARTS`)."""
    done = subprocess.run([sys.executable, "-c", _PARTS, str(frame), str(runs)],
                          env=_environment(setting), capture_output=True, text=True,
                          check=False)
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    return json.loads(done.stdout)


def generate_run(root: Path, out: Path, backend: str, samples: int, threads: int,
                 setting: str) -> dict:
    """``gpu-blur generate`` over ``samples`` windows with ``setting``: its rate and lines."""
    wall, lines = generate_gpu._run(root, out, backend, samples, threads,
                                    launcher=("-c", _PEAK + _GENERATE),
                                    environ=_environment(setting))
    rate = re.search(r"\(([\d.]+) samples/s\)", lines[0])
    decoding = next((line for line in lines if line.startswith("I/O threads")), "")
    each = re.search(r"([\d.]+) ms each", decoding)
    peak = re.search(r"^peak memory (\d+) KiB$", lines[-1])
    return {"seconds": wall, "in_run_samples_per_s": float(rate.group(1)) if rate else None,
            "decode_ms_each": float(each.group(1)) if each else None,
            "peak_memory_mib": int(peak.group(1)) / 1024 if peak else None,
            "summary": lines[:-1] if peak else lines}


def _medians(runs: dict[str, list[dict]], key: str) -> dict[str, float]:
    return {setting: statistics.median(run[key] for run in each)
            for setting, each in runs.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=2304, help="frames to write and decode "
                   "(default 2304: 256 samples of 9)")
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)),
                   help="decoding threads (default: the cores this process may run on)")
    p.add_argument("--rounds", type=int, default=2, help="times each setting runs, in turn")
    p.add_argument("--generate", type=int, metavar="N", default=0,
                   help="also gpu-blur generate over N distinct windows with each setting")
    p.add_argument("--backend", default="warp", help="--generate's backend (default warp)")
    p.add_argument("--parts", action="store_true",
                   help="also time one frame's decode and its steps on one thread")
    p.add_argument("--part-runs", type=int, default=20,
                   help="--parts: calls of each step, the median kept (default 20)")
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    frames = max(args.frames, 9 * args.generate)
    root = Path(tempfile.mkdtemp(prefix="gpu_blur_decode_")) / "in"
    generate_gpu.write_sequence(root, frames)
    if args.generate:  # uncounted: kernels, caches
        generate_run(root, root.parent / "out", args.backend, args.generate, args.threads,
                     "keep")
    decodes: dict[str, list[dict]] = {s: [] for s in SETTINGS}
    runs: dict[str, list[dict]] = {s: [] for s in SETTINGS}
    parts: dict[str, list[dict]] = {s: [] for s in SETTINGS}
    frame = min(root.rglob("*.png"))
    for round_ in range(args.rounds):
        for setting in SETTINGS:
            if args.parts:
                parts[setting].append(found := parts_run(frame, args.part_runs, setting))
                print(f"round {round_ + 1}, {setting}: one frame on one thread, ms: "
                      + ", ".join(f"{k} {v:.1f}" for k, v in found["ms"].items()), flush=True)
            decodes[setting].append(run := decode_run(root, args.threads, setting))
            print(f"round {round_ + 1}, {setting}: {frames} frames through {args.threads} "
                  f"threads in {run['seconds']:.2f} s, {run['ms_a_frame_a_thread']:.1f} ms "
                  f"a frame a thread, peak memory {run['peak_memory_mib']:.0f} MiB", flush=True)
            if args.generate:
                runs[setting].append(made := generate_run(
                    root, root.parent / "out", args.backend, args.generate, args.threads,
                    setting))
                print(f"  generate: {made['in_run_samples_per_s']} samples/s in the run, "
                      f"decoding {made['decode_ms_each']} ms a file, peak memory "
                      f"{made['peak_memory_mib']:.0f} MiB", flush=True)
    result = {
        "what": f"bench/decode_threads.py --frames {frames} --threads {args.threads} "
                f"--rounds {args.rounds}"
                + (f" --generate {args.generate} --backend {args.backend}"
                   if args.generate else ""),
        "machine": png_codecs.machine(),
        "image": [generate_gpu.W, generate_gpu.H], "frames": frames, "threads": args.threads,
        "decode": {"runs": decodes,
                   "median_ms_a_frame_a_thread": _medians(decodes, "ms_a_frame_a_thread"),
                   "median_frames_per_s": _medians(decodes, "frames_per_s")},
    }
    if args.parts:
        result["parts"] = {"runs": parts, "part_runs": args.part_runs, "frame": frame.name,
                           "median_ms": {setting: {key: statistics.median(
                               run["ms"][key] for run in each) for key in each[0]["ms"]}
                               for setting, each in parts.items()}}
        result["what"] += f" --parts --part-runs {args.part_runs}"
    if args.generate:
        result["generate"] = {"samples": args.generate, "backend": args.backend, "runs": runs,
                              "median_in_run_samples_per_s":
                                  _medians(runs, "in_run_samples_per_s")}
    print(json.dumps({k: v for k, v in result["decode"].items() if k != "runs"}))
    if args.parts:
        print(json.dumps(result["parts"]["median_ms"]))
    if args.generate:
        print(json.dumps(result["generate"]["median_in_run_samples_per_s"]))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
