"""How fast ``--devices`` workers' results reach the driver: through the pipe, or shared memory.

Each of N spawned workers sends the same made sample (a ``Synthesis`` of H x W x 3 blurred and
sharp codes, 8 or 16 bit, with ``--mask`` an H x W x 3 float32 mask too) S times, as fast as
it can; the driver receives them in one thread, as ``gpu_blur.distributed`` does:

* ``pipe``: the whole result pickled through the worker's pipe (gpu_blur before
  gpu_blur.shared_results);
* ``shared``: the arrays written into a shared-memory block (``Outbox.pack``), the rest through
  the pipe, the driver copying them out (``Blocks.receive``) and handing the block back.

The rate counts from the moment every worker is ready (imports and array set-up left out) to
the last sample received; ``driver ms`` is the receiving thread's CPU time per sample, which
bounds its rate at any number of workers. Synthesis, decoding and writing files are left out:
this is the hand-off alone. Since 543c36e only LMDB and WebDataset sets hand their samples
over this way; the workers of a PNG set write its files themselves and send only the lines.

    PYTHONPATH=$PWD python3 bench/devices_handoff.py --workers 1,2,4 --json handoff.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import time
from multiprocessing.connection import wait

import numpy as np

from gpu_blur.shared_results import ASK, Blocks, Outbox
from gpu_blur.synthesis import Synthesis


def made_sample(height: int, width: int, bits: int, mask: bool) -> Synthesis:
    """A stand-in result: random codes, a mask if asked, small params as a real one has."""
    rng = np.random.default_rng(0)
    dtype = np.uint8 if bits == 8 else np.uint16
    blurred = rng.integers(0, np.iinfo(dtype).max + 1, (height, width, 3), dtype)
    return Synthesis(blurred=blurred, sharp=blurred.copy(),
                     _mask=rng.random((height, width, 3), np.float32) if mask else None,
                     params={"homographies": rng.random((9, 3, 3)), "iso": 800.0},
                     plan=None, timings={"total": 0.1})


def worker(conn, mode: str, samples: int, shape: tuple[int, int], bits: int,
           mask: bool) -> None:
    """Send ``samples`` copies of the made sample once the driver says go."""
    result = made_sample(*shape, bits, mask)
    outbox = Outbox(conn, lambda message: None) if mode == "shared" else None
    conn.send("ready")
    conn.recv()  # go
    for index in range(samples):
        shell, layout = outbox.pack(result) if outbox else (result, None)
        conn.send(("sample", (index, shell, None, layout, None)))
    try:
        while True:  # until the driver closes its end
            conn.recv()
    except EOFError:
        pass
    if outbox is not None:
        outbox.close()


def run(mode: str, workers: int, samples: int, shape, bits: int, mask: bool) -> dict:
    """One mode and worker count: samples/s, GB/s, the driver's CPU ms per sample."""
    context = multiprocessing.get_context("spawn")
    conns, processes = [], []
    for _ in range(workers):
        conn, child = context.Pipe()
        process = context.Process(target=worker, daemon=True,
                                  args=(child, mode, samples, shape, bits, mask))
        process.start()
        child.close()
        conns.append(conn)
        processes.append(process)
    blocks = Blocks()
    try:
        for conn in conns:
            assert conn.recv() == "ready"
        start, cpu = time.perf_counter(), time.thread_time()
        for conn in conns:
            conn.send("go")
        left, got, nbytes = {id(c): samples for c in conns}, 0, 0
        while any(left.values()):
            for conn in wait([c for c in conns if left[id(c)]]):
                kind, value = conn.recv()
                if kind == ASK:
                    blocks.answer(conn, *value)
                    continue
                _, result, _, layout, _ = value
                if layout is not None:
                    result = blocks.receive(conn, result, layout)
                nbytes += result.blurred.nbytes + result.sharp.nbytes + (
                    result.mask.nbytes if result.mask is not None else 0)
                left[id(conn)] -= 1
                got += 1
        seconds, cpu = time.perf_counter() - start, time.thread_time() - cpu
    finally:
        for conn in conns:
            conn.close()
        for process in processes:
            process.join(30)
        blocks.close()
    return {"mode": mode, "workers": workers, "samples": got, "seconds": seconds,
            "samples_per_s": got / seconds, "gb_per_s": nbytes / seconds / 1e9,
            "driver_ms_per_sample": 1e3 * cpu / got, "mb_per_sample": nbytes / got / 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", default="1,2", help="worker counts, comma list")
    parser.add_argument("--samples", type=int, default=60, help="samples per worker")
    parser.add_argument("--size", default="1200x1920", help="H x W of a sample")
    parser.add_argument("--bits", type=int, choices=(8, 16), default=8)
    parser.add_argument("--mask", action="store_true", help="a float32 mask with each sample")
    parser.add_argument("--modes", default="pipe,shared")
    parser.add_argument("--json", help="write the rows here")
    args = parser.parse_args()
    shape = tuple(int(v) for v in args.size.lower().split("x"))
    rows = [run(mode, workers, args.samples, shape, args.bits, args.mask)
            for workers in (int(w) for w in args.workers.split(","))
            for mode in args.modes.split(",")]
    print(f"{'mode':7} {'workers':>7} {'samples/s':>10} {'GB/s':>6} {'driver ms':>10} "
          f"{'MB each':>8}")
    for r in rows:
        print(f"{r['mode']:7} {r['workers']:7d} {r['samples_per_s']:10.1f} "
              f"{r['gb_per_s']:6.2f} {r['driver_ms_per_sample']:10.2f} "
              f"{r['mb_per_sample']:8.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"host": platform.node(), "cpus": os.cpu_count(),
                       "python": platform.python_version(), "size": shape, "bits": args.bits,
                       "mask": args.mask, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
