"""How long the I/O threads' work keeps the making thread waiting for the GIL.

``gpu-blur generate`` makes samples on one thread while I/O threads decode and encode. The
making thread calls into Warp or OpenCL dozens of times a sample, and each call releases the
GIL and takes it back: whatever an I/O thread does while holding the GIL (Python code, a copy
of a bytes object) delays the making thread there.

Here one thread runs an operation in a loop while this thread makes GIL-releasing calls (a
ctypes call into the C library) back to back and times each. A call slower than ``STALL_US``
counts as a stall (it waited for the GIL, or for a core: run on an otherwise idle machine
with a core for each thread). Per operation: its rate, the stalled milliseconds a second and
per operation, and the longest stall. Operations: the PNG encode of a noisy 1920 x 1200 8-bit
image in each ``output.png`` mode, the decode of an OpenCV-written frame, and as references a
join and an addition of two bytes objects of 4 MB (a join that large releases the GIL; an
addition holds it while copying). glibc's ``MALLOC_*`` variables, if set, are recorded
(``malloc_settings``): freeing and mapping memory of several MB happens with the GIL held.

    PYTHONPATH=$PWD python3 bench/gil_holds.py --json gil_holds.json
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import generate_gpu
import numpy as np

from gpu_blur.analysis.bench.host import cpu_name, load_average, source_commit
from gpu_blur.file_writing import encode_image
from gpu_blur.image_reading import read_image
from gpu_blur.png_codecs import PNG_MODES

#: A GIL-releasing call slower than this (microseconds) counts as a stall.
STALL_US = 20.0


def noisy_output() -> np.ndarray:
    """A synthesized output's like: the bench's photo frame with noise, H x W x 3 uint8 RGB."""
    frame = generate_gpu.panned_frames(1)[0][..., ::-1]
    noise = np.random.default_rng(0).normal(0, 4, frame.shape).round()
    return np.clip(frame + noise, 0, 255).astype(np.uint8)


def operations(folder: Path) -> dict:
    """Name: a callable, each an I/O thread's step or a reference."""
    image = noisy_output()
    frame = folder / "frame.png"
    cv2.imwrite(str(frame), generate_gpu.panned_frames(1)[0])  # OpenCV's defaults, as users'
    blob = bytes(4 << 20)
    ops = {f"encode png {mode}": (lambda mode=mode: encode_image(image, 8, "bench", mode))
           for mode in PNG_MODES}
    ops["decode an OpenCV-written frame"] = lambda: read_image(frame)
    ops["join two bytes of 4 MB (reference)"] = lambda: b"".join((blob, b"x"))
    ops["add two bytes of 4 MB (reference)"] = lambda: blob + b"x"
    return ops


def stalls(operation, seconds: float) -> dict:
    """This thread's GIL-releasing calls timed while another thread loops ``operation``."""
    libc = ctypes.CDLL(None)
    stop, done = threading.Event(), [0]

    def loop():
        while not stop.is_set():
            operation()
            done[0] += 1

    worker = threading.Thread(target=loop)
    worker.start()
    time.sleep(0.2)  # past the first call's set-up
    calls, stalled, longest, first = 0, 0.0, 0.0, done[0]
    start = time.perf_counter()
    end = start + seconds
    while (before := time.perf_counter()) < end:
        libc.getpid()
        took = time.perf_counter() - before
        calls += 1
        if took > STALL_US * 1e-6:
            stalled += took
            longest = max(longest, took)
    wall = time.perf_counter() - start
    ops = done[0] - first
    stop.set()
    worker.join()
    return {"operations_per_s": ops / wall, "calls": calls,
            "stalled_ms_a_second": 1e3 * stalled / wall,
            "stalled_ms_per_operation": 1e3 * stalled / max(ops, 1),
            "longest_stall_ms": 1e3 * longest}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=3.0, help="seconds per operation "
                   "(default 3)")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    result = {"what": __doc__.split("\n\n")[0], "cpu": cpu_name(), "cores": os.cpu_count(),
              "load_average": load_average(), "python": sys.version.split()[0],
              "commit": source_commit(), "stall_us": STALL_US, "seconds": args.seconds,
              "switch_interval_ms": 1e3 * sys.getswitchinterval(),
              "malloc_settings": {k: v for k, v in os.environ.items() if k.startswith("MALLOC_")},
              "operations": {}}
    print(f"{'operation':40s} {'ops/s':>8s} {'stalled ms/s':>13s} {'ms/op':>8s} "
          f"{'longest ms':>11s}")
    with tempfile.TemporaryDirectory() as tmp:
        # the first row: the other thread only sleeps, so a stall there is the machine's own
        for name, operation in {"a thread sleeping (baseline)": lambda: time.sleep(0.001),
                                **operations(Path(tmp))}.items():
            row = stalls(operation, args.seconds)
            result["operations"][name] = row
            print(f"{name:40s} {row['operations_per_s']:8.1f} {row['stalled_ms_a_second']:13.1f} "
                  f"{row['stalled_ms_per_operation']:8.2f} {row['longest_stall_ms']:11.2f}",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
