"""``gpu-blur generate`` from PNG files against the host's decode-plus-encode bound.

Writes a GoPro-style sequence (``seq/sharp/000000.png ...``, 36 frames of 1920 x 1200, the
built-in photo panned 2 px per frame), then runs ``gpu-blur generate --scene rsblur`` over
``--samples`` overlapping windows of it (``--samples-per-sequence``) with one I/O thread and
with one per core. Each run's rate leaves out the process's fixed start (imports, device,
kernels from the cache): ``(N - 1) / (t(N) - t(1))`` from a run of N samples and one of 1. The
bound: a sample decodes 9 PNG frames and encodes 2 PNG outputs, so with every core busy the
host makes at most ``cores / (9 t_decode + 2 t_encode)`` samples per second (single-core times
measured here on the same images).

    PYTHONPATH=$PWD python3 bench/generate_gpu.py --backend warp --samples 32 --json out.json

``--workers 1,2,4`` adds runs of ``--devices`` with that many worker processes sharing
``--backend``'s device, and checks that every set holds the same bytes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from gpu_blur.discovery import default_photo

H, W, FRAMES = 1200, 1920, 9


def panned_frames(count: int) -> list[np.ndarray]:
    """``count`` H x W x 3 uint8 BGR frames: the built-in photo, resized, panned 2 px a frame."""
    photo = cv2.resize(cv2.imread(str(default_photo())), (W + 2 * count, H))
    return [photo[:, 2 * i:2 * i + W] for i in range(count)]


def write_sequence(folder: Path, count: int) -> list[Path]:
    """:func:`panned_frames` as PNG files ``seq/sharp/000000.png ...`` under ``folder``."""
    sharp = folder / "seq" / "sharp"
    sharp.mkdir(parents=True)
    paths = []
    for i, frame in enumerate(panned_frames(count)):
        path = sharp / f"{i:06d}.png"
        cv2.imwrite(str(path), frame)
        paths.append(path)
    return paths


def single_core_seconds(paths: list[Path]) -> dict:
    """Median seconds to decode one frame and to encode one 8-bit output, on one core."""
    cv2.setNumThreads(1)
    decode = []
    for path in paths[:5]:
        start = time.perf_counter()
        cv2.imread(str(path))
        decode.append(time.perf_counter() - start)
    image = cv2.imread(str(paths[0]))[4:-4, 4:-4]
    encode = []
    for _ in range(5):
        start = time.perf_counter()
        cv2.imencode(".png", image)
        encode.append(time.perf_counter() - start)
    return {"decode": statistics.median(decode), "encode": statistics.median(encode)}


def decode_encode_bound(per: dict, cores: int) -> float:
    """Samples per second the host can decode and encode, every core busy.

    A sample decodes 9 frames and encodes 2 images (``per``: :func:`single_core_seconds`).
    """
    return cores / (FRAMES * per["decode"] + 2 * per["encode"])


def _run(root: Path, out: Path, backend: str, samples: int, threads: int,
         extra: tuple[str, ...] = ()):
    command = [sys.executable, "-m", "gpu_blur.cli", "generate", "--input", str(root),
               "--output", str(out), "--scene", "rsblur", "--backend", backend,
               "--samples-per-sequence", str(samples), "--io-threads", str(threads),
               "--quiet", "--overwrite", *extra]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    return wall, (done.stdout + done.stderr).strip().splitlines()[-9:]


def generate(root: Path, out: Path, backend: str, samples: int, threads: int,
             extra: tuple[str, ...] = ()) -> dict:
    """Samples per second of ``gpu-blur generate`` without its fixed start, and its summary.

    A first 1-sample run warms the file cache and the kernel caches and is not counted: a
    cold start can take longer than the whole run that follows.
    """
    _run(root, out, backend, 1, threads, extra)
    start, _ = _run(root, out, backend, 1, threads, extra)
    wall, summary = _run(root, out, backend, samples, threads, extra)
    return {"threads": threads, "options": list(extra), "seconds": wall,
            "start_seconds": start, "samples_per_s": (samples - 1) / (wall - start),
            "summary": summary}


def set_digest(out: Path) -> str:
    """sha256 over every file of a set (names and bytes); run.json and the lock file aside.

    The manifest's input paths are left out (the input lies in a temporary folder of its own
    in each run of this script), so runs of different commits compare.
    """
    digest = hashlib.sha256()
    for path in sorted(p for p in out.rglob("*") if p.is_file()
                       and p.name not in ("run.json", ".gpu_blur.lock")):
        data = path.read_bytes()
        if path.name == "manifest.jsonl":
            lines = [json.loads(line) for line in data.decode().splitlines()]
            data = "\n".join(json.dumps({k: v for k, v in line.items() if k != "inputs"})
                             for line in lines).encode()
        digest.update(path.relative_to(out).as_posix().encode() + data)
    return digest.hexdigest()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", default="warp", help="backend (default warp)")
    p.add_argument("--samples", type=int, default=64, help="samples per run (default 64)")
    p.add_argument("--threads", default="1,all", help="--io-threads of the one-process runs, "
                   "comma-separated; all: one per core (default 1,all)")
    p.add_argument("--workers", default="", help="also run --devices with each of these "
                   "numbers of workers on --backend's device, comma-separated (e.g. 1,2,4), "
                   "and compare the sets' bytes")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    cores = len(os.sched_getaffinity(0))
    devices = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "in"
        paths = write_sequence(root, 4 * FRAMES)
        per = single_core_seconds(paths)
        bound = decode_encode_bound(per, cores)
        threads = [cores if t == "all" else int(t) for t in args.threads.split(",")]
        runs = [generate(root, Path(tmp) / f"out{t}", args.backend, args.samples, t)
                for t in threads]
        digests = {"serial": set_digest(Path(tmp) / f"out{threads[-1]}")}
        for n in [int(v) for v in args.workers.split(",") if v]:
            out = Path(tmp) / f"workers{n}"
            devices[n] = generate(root, out, args.backend, args.samples, cores,
                                  ("--devices", ",".join([args.backend] * n)))
            digests[f"{n} workers"] = set_digest(out)
    result = {"backend": args.backend, "cores": cores, "image": [W, H], "frames": FRAMES,
              "single_core_seconds": per, "bound_samples_per_s": bound, "runs": runs,
              "ratio_to_bound": runs[-1]["samples_per_s"] / bound,
              "devices_workers": devices, "set_digests": digests,
              "same_bytes": len(set(digests.values())) == 1}
    for run in runs:
        print(f"io-threads {run['threads']:>2}: {run['samples_per_s']:.2f} samples/s")
    for n, run in devices.items():
        print(f"--devices, {n} worker(s): {run['samples_per_s']:.2f} samples/s")
    print("every set the same bytes" if result["same_bytes"] else f"SETS DIFFER: {digests}")
    print(f"bound: {bound:.2f} samples/s ({cores} cores; decode {1e3 * per['decode']:.1f} ms, "
          f"encode {1e3 * per['encode']:.1f} ms per image on one core); "
          f"{100 * result['ratio_to_bound']:.0f} % of it")
    print("\n".join(runs[-1]["summary"]))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
