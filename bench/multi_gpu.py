"""Samples per second on 1, 2, ... GPUs of one host, from frames in memory and from PNG files.

Memory: one process per GPU, each a ``gpu_blur.Synthesizer`` (RSBlur scene) on its own
device, fed batches of 9 uint8 frames of 1920 x 1200 already decoded (the built-in photo
panned 2 px per frame), in pageable numpy arrays or in that GPU's pinned memory
(``Synthesizer.pinned``, the results too, through ``out=``); batch k goes to GPU ``k % n``
and holds samples ``k * batch ...``.
Every process warms up on a batch that is not counted, then all start together; the rate is
the samples made over the time from the first start to the last finish (the hashing of the
checked batches left out).

Disk: ``gpu-blur generate --devices`` with one worker per GPU over PNG frames on disk
(bench/generate_gpu.py's sequence, rate without the process start and from the first file
written to the last), and one process without ``--devices`` (``disk_one_process``), the rows
taking turns ``--repeats`` times (each row the run of the median rate, every run's rates
beside it), its summary saying what bounds it and what handing the samples to the
driver cost, and the host's decode-plus-encode bound: from one core's codec times with 9
decodes a sample (``disk_bound_samples_per_s``), and measured (``disk_bound_measured``: this
checkout's codecs alone through one thread per core, each frame decoded once as a frame cache
does, each sample's two images encoded). ``shared_memory_bytes``: the size of /dev/shm, where
the workers' result blocks live (a small one sends samples through the pipes, which the
summary's hand-off line counts).

Copy bound (Warp): one process per GPU copying pinned host memory to and from its GPU at
once; the host's aggregate rate bounds the memory runs (a sample moves 62 MB in and 55 MB out).

Both check that every GPU count makes the same bytes (sha256 over the outputs: every file
of the set from disk; the first ``CHECKED`` batches from memory).

    PYTHONPATH=$PWD python3 bench/multi_gpu.py --gpus 1,2 --json out.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import generate_gpu
import numpy as np

from gpu_blur.backends import get_backend

H, W, FRAMES = generate_gpu.H, generate_gpu.W, generate_gpu.FRAMES  # the same sequence
#: Memory: the first batches, whichever GPU made them, are hashed to compare GPU counts (the
#: hashing, 0.9 GB of float32 a batch, is left out of the time; hashing every batch would
#: cost more than making it).
CHECKED = 4


def device_spec(backend: str, index: int) -> str:
    """The ``index``-th GPU of ``backend`` (Warp's CUDA devices, OpenCL's first platform), or
    ``backend`` itself when it names one device (``warp:cpu``: every "GPU" is that device, to
    try this script on a CPU)."""
    if ":" in backend:
        return backend
    return f"warp:cuda:{index}" if backend == "warp" else f"opencl:0:{index}"


def frames(batch: int) -> np.ndarray:
    """batch x 9 x H x W x 3 uint8 RGB: the built-in photo panned 2 px per frame."""
    stack = np.stack(generate_gpu.panned_frames(FRAMES))[..., ::-1]  # BGR -> RGB
    return np.ascontiguousarray(np.broadcast_to(stack, (batch, *stack.shape)))


def _memory_worker(spec: str, gpu: int, gpus: int, batches: int, batch: int, pinned: bool,
                   barrier, results) -> None:
    import gpu_blur
    synth = gpu_blur.Synthesizer("rsblur", backend=spec, seed=1)
    given = frames(batch)
    if pinned:  # the frames and the out= arrays in this GPU's pinned memory
        held = synth.pinned(given.shape, given.dtype)
        held[...] = given
        given = held
    first = synth(given, first_index=10 ** 9)  # warm-up: kernel builds, buffers, staging
    into = ([synth.pinned(first.blurred.shape), synth.pinned(first.sharp.shape)] if pinned
            else None)
    barrier.wait()
    start, digests, hashing = time.perf_counter(), {}, 0.0
    for k in range(gpu, batches, gpus):
        out = synth(given, first_index=k * batch, out=into)
        if k < CHECKED:
            begin = time.perf_counter()
            digests[k] = hashlib.sha256(out.blurred.tobytes() + out.sharp.tobytes()).hexdigest()
            hashing += time.perf_counter() - begin
    results.put((gpu, start, time.perf_counter() - hashing, digests))


def _together(target, args: list[tuple]) -> list:
    """What each process put on ``results``: ``target(*a, barrier, results)`` for each ``a``.

    One spawned process per entry of ``args``, started together (they meet at the barrier).
    """
    spawn = multiprocessing.get_context("spawn")
    barrier, results = spawn.Barrier(len(args)), spawn.Queue()
    workers = [spawn.Process(target=target, args=(*a, barrier, results)) for a in args]
    for worker in workers:
        worker.start()
    done = [results.get(timeout=600) for _ in workers]
    for worker in workers:
        worker.join()
        if worker.exitcode:
            raise RuntimeError(f"a {target.__name__} process exited with status "
                               f"{worker.exitcode}")
    return done


def from_memory(backend: str, gpus: int, batches: int, batch: int, pinned: bool) -> dict:
    """Samples per second of ``gpus`` processes, one per GPU, and the set's digest."""
    done = _together(_memory_worker, [(device_spec(backend, g), g, gpus, batches, batch,
                                       pinned) for g in range(gpus)])
    digests = {k: d for *_, part in done for k, d in part.items()}
    seconds = max(end for _, _, end, _ in done) - min(start for _, start, _, _ in done)
    whole = hashlib.sha256("".join(digests[k] for k in sorted(digests)).encode())
    return {"gpus": gpus, "pinned": pinned, "samples": batches * batch, "seconds": seconds,
            "samples_per_s": batches * batch / seconds,
            "per_gpu_seconds": {g: end - start for g, start, end, _ in done},
            "digest": whole.hexdigest()}


#: Bytes of one copy of the copy-bound measure, each way.
COPY_BYTES = 1 << 28


def _copy_worker(gpu: int, reps: int, barrier, results) -> None:
    import warp as wp

    device = f"cuda:{gpu}"
    pairs = [(wp.empty(COPY_BYTES, dtype=wp.uint8, device="cpu", pinned=True),
              wp.empty(COPY_BYTES, dtype=wp.uint8, device=device)) for _ in range(2)]
    up, down = wp.Stream(device), wp.Stream(device)
    wp.copy(pairs[0][1], pairs[0][0], stream=up)  # warm-up
    wp.synchronize_device(device)
    barrier.wait()
    start = time.perf_counter()
    for _ in range(reps):  # both directions at once, as a streamed batch moves its bytes
        wp.copy(pairs[0][1], pairs[0][0], stream=up)
        wp.copy(pairs[1][0], pairs[1][1], stream=down)
    wp.synchronize_device(device)
    results.put((start, time.perf_counter()))


def copy_bound(gpus: int, reps: int = 16) -> dict:
    """The host's pinned copy rate with ``gpus`` Warp CUDA GPUs copying at once, both ways.

    One process per GPU copies 256 MB up and 256 MB down at the same time, ``reps`` times;
    the rate is all the bytes of one direction over the time from the first start to the
    last end. It bounds any run that moves its frames in and its results out through host
    memory.
    """
    done = _together(_copy_worker, [(g, reps) for g in range(gpus)])
    seconds = max(end for _, end in done) - min(start for start, _ in done)
    return {"gpus": gpus, "gb_s_each_way": gpus * reps * COPY_BYTES / seconds / 1e9}


def from_disk(backend: str, gpus: int | None, root: Path, out: Path, samples: int, cores: int,
              scene: str = "rsblur") -> dict:
    """A disk run: ``generate --devices`` with a worker per GPU, or one process (``gpus``
    None, no ``--devices``)."""
    extra = () if gpus is None else (
        "--devices", ",".join(device_spec(backend, g) for g in range(gpus)))
    run = generate_gpu.generate(root, out, backend, samples, cores, extra, scene=scene)
    return {"gpus": gpus, **run, "digest": generate_gpu.set_digest(out)}


def shared_memory_bytes() -> int | None:
    """The size of /dev/shm, where --devices' result blocks live (Linux), or None.

    A small one (a container's 64 MB) sends the samples through the workers' pipes.
    """
    try:
        return shutil.disk_usage("/dev/shm").total
    except OSError:
        return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", default="warp", help="warp or opencl: one process per GPU "
                   "of that family; a device name (warp:cpu) runs every process on it "
                   "(default warp)")
    p.add_argument("--gpus", default="1,2", help="GPU counts, comma-separated (default 1,2)")
    p.add_argument("--batches", type=int, default=64,
                   help="memory: batches per run (default 64)")
    p.add_argument("--batch", type=int, default=16, help="memory: samples per batch (default 16)")
    p.add_argument("--samples", type=int, default=64, help="disk: samples per run (default 64)")
    p.add_argument("--repeats", type=int, default=1, help="disk: runs of each row, one process's "
                   "first, taking turns; each row the run of the median rate (default 1)")
    p.add_argument("--memory", default="pageable,pinned",
                   help="memory: the frames and outputs in pageable numpy arrays, in each "
                   "GPU's pinned memory (Synthesizer.pinned), or both (default both)")
    p.add_argument("--skip", default="", help="leave out 'memory' or 'disk'")
    p.add_argument("--png", default="fast", help="disk: the outputs' output.png (fast, small, "
                   "stored), in the rsblur scene and the measured bound (default fast)")
    p.add_argument("--device-png", action="store_true",
                   help="disk: the checkout deflates output.png fast's files on the GPU "
                        "(bench/generate_gpu.py --device-png): the measured bound counts that")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    counts = [int(v) for v in args.gpus.split(",")]
    cores = len(os.sched_getaffinity(0))
    result = {"what": __doc__.split("\n\n")[0], "backend": args.backend, "cores": cores,
              "cpu": platform.processor() or platform.machine(), "image": [W, H],
              "frames": FRAMES, "png": args.png, "device_png": args.device_png,
              "memory": [], "disk": [],
              "shared_memory_bytes": shared_memory_bytes()}
    if result["shared_memory_bytes"] is not None:
        print(f"/dev/shm: {result['shared_memory_bytes'] / 1e9:.2f} GB", flush=True)
    result["devices"] = [get_backend(device_spec(args.backend, g)).device
                         for g in range(max(counts))]
    kinds = [k for k in ("pageable", "pinned") if k in args.memory.split(",")]
    # what a sample moves: 9 uint8 frames in, blurred and sharp float32 (cropped 4 px) out
    moved_in, moved_out = FRAMES * H * W * 3, 2 * (H - 8) * (W - 8) * 3 * 4
    if args.backend == "warp" and "memory" not in args.skip:
        result["copy_bound"] = []
        for n in counts:
            row = copy_bound(n)
            row["samples_per_s"] = row["gb_s_each_way"] * 1e9 / max(moved_in, moved_out)
            result["copy_bound"].append(row)
            print(f"copy bound, {n} GPU(s): {row['gb_s_each_way']:.1f} GB/s each way at once, "
                  f"{row['samples_per_s']:.0f} samples/s", flush=True)
    if "memory" not in args.skip:
        for kind in kinds:
            for n in counts:
                row = from_memory(args.backend, n, args.batches, args.batch, kind == "pinned")
                result["memory"].append(row)
                print(f"memory ({kind}), {n} GPU(s): {row['samples_per_s']:.1f} samples/s",
                      flush=True)
    if "disk" not in args.skip:
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "in"
            paths = generate_gpu.write_sequence(root, 4 * FRAMES)
            per = generate_gpu.single_core_seconds(paths)
            result["disk_bound_samples_per_s"] = generate_gpu.decode_encode_bound(per, cores)
            result["single_core_seconds"] = per
            scene = generate_gpu.scene_file(tmp, args.png)
            rows = {n: [] for n in [None, *counts]}  # None: one process, no --devices
            for _ in range(args.repeats):
                for n, made in rows.items():
                    made.append(from_disk(args.backend, n, root, Path(tmp) / f"out{n}",
                                          args.samples, cores, scene))
            for n, made in rows.items():
                row = sorted(made, key=lambda r: r["samples_per_s"])[(len(made) - 1) // 2]
                row = {**row, "samples_per_s_each": [r["samples_per_s"] for r in made],
                       "in_run_each": [r["in_run_samples_per_s"] for r in made],
                       "written_each": [r["written_samples_per_s"] for r in made]}
                if n is None:
                    result["disk_one_process"] = row
                else:
                    result["disk"].append(row)
                print(f"disk, {'one process' if n is None else f'{n} GPU(s)'}: "
                      f"{row['samples_per_s']:.1f} samples/s (in the run, workers' start "
                      f"included: {row.get('in_run_samples_per_s')}; first to last written "
                      f"{row['written_samples_per_s']:.1f}; each run: "
                      + ", ".join(f"{v:.1f}" for v in row["samples_per_s_each"]) + ")",
                      flush=True)
            # the codecs alone through one thread per core, each frame decoded once (a frame
            # cache's run) and each image encoded as the run did: the host's own ceiling
            result["disk_bound_measured"] = generate_gpu.measured_codec_bound(
                paths, len(paths), Path(tmp) / f"out{counts[-1]}", args.samples, cores,
                repeats=3, png=args.png, device_png=args.device_png)
    sources = {"disk": result["disk"]}
    for kind in kinds:
        sources["memory" if kind == "pageable" else "memory_pinned"] = [
            r for r in result["memory"] if r["pinned"] == (kind == "pinned")]
    for source, rows in sources.items():
        if rows:
            one = rows[0]["samples_per_s"]
            result[f"{source}_speedup"] = {r["gpus"]: r["samples_per_s"] / one for r in rows}
            print(f"{source}: speed-up " + ", ".join(
                f"{g} GPUs {s:.2f}x" for g, s in result[f"{source}_speedup"].items()))
    for source in ("memory", "disk"):  # pinned or not, every GPU count: one set of bytes
        if result[source]:
            rows = result[source] + ([result["disk_one_process"]] if source == "disk" else [])
            same = len({r["digest"] for r in rows}) == 1
            result[f"{source}_same_bytes"] = same
            print(f"{source}: " + ("every run the same bytes" if same else "SETS DIFFER"))
    if result["disk"]:
        print(f"disk bound: {result['disk_bound_samples_per_s']:.1f} samples/s ({cores} cores, "
              f"9 decodes a sample); measured, each frame decoded once: "
              f"{result['disk_bound_measured']['samples_per_s']:.1f} samples/s")
        print("\n".join(result["disk"][-1]["summary"]))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
