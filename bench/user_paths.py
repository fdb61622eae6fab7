"""What a user waits for, path by path, beside what the device computes.

For each example scene (RealBlur-J: a float32 blurred image and its mask at 1920 x 1200;
RSBlur: 9 uint8 frames at 1920 x 1200; the training benchmark's random-kernel scene on
256 x 256 crops) and each way in: ``synthesize`` one sample per call from numpy,
``Synthesizer`` batches from numpy, the same batches and their ``out=`` arrays in the
Synthesizer's pinned memory (``Synthesizer.pinned``), and (with torch and CUDA) batches of
torch CUDA tensors. Each path warms up once; reported: the median over ``--runs`` of
milliseconds per sample, end to end (arguments in, results out, the device synchronized), and
for Warp on CUDA the device's own kernel time per sample in one batch (Warp's CUDA activity
timer), torch batches also back to back (32 calls, one synchronization: what a loop feeding
the device waits) and the pinned copy bound of the bytes a sample moves (:func:`copy_bound_ms`).
Scenes with 8/16-bit output also time the pinned batch with ``codes=True`` (the codes made on
the device, into pinned uint8/uint16 ``out=`` arrays) beside the bound of the bytes it moves.

``--paths dtypes`` times the same torch batches as uint8 codes and as float32 values (codes /
255: only the dtype differs, so a float batch pays its value checks and float-input passes):
one call synchronized and back to back, per sample, side by side with their ratio; on CUDA also
each kernel's device time per sample (Warp's CUDA activity; name by name, so the checks'
``inspect`` of older commits shows), the device time of the reductions torch batches' float
checks run (``torch.aminmax`` over each input, CUDA events), and float32 back to back again with
the Warp memory pool keeping what it frees (its release threshold raised for the run: whether
returning memory at each synchronization costs). Tensors lie on the backend's device (CUDA, or
the host for ``warp:cpu``). The RealBlur-J float-input figure::

    PYTHONPATH=$PWD python3 bench/user_paths.py --backend warp:cuda:0 --paths dtypes \
        --scenes realblur_j --json $OUT/float_inputs.json

With an older gpu_blur on ``PYTHONPATH`` (no ``Synthesizer``) only ``synthesize`` is timed,
so one script compares commits. On the GPU machine, from the repository root::

    PYTHONPATH=$PWD python3 bench/user_paths.py --backend warp:cuda:0 --json $OUT/paths.json
"""

from __future__ import annotations

import argparse
import inspect
import json
import platform
import re
import statistics
import sys

import numpy as np

import gpu_blur
from gpu_blur.analysis.bench.measure import median_time
from gpu_blur.backends import get_backend
from gpu_blur.scene import scene_from_dict

#: (name, scene, (height, width)): the training benchmark's scene is bench/train_on_the_fly's.
SCENES = (
    ("realblur_j", "realblur_j", (1200, 1920)),
    ("rsblur", "rsblur", (1200, 1920)),
    ("kernel_256", {"blur": {"mode": "kernel"}, "output": {"bits": 0, "crop": 0}}, (256, 256)),
)


def inputs(scene, batch: int, h: int, w: int) -> dict:
    """Random sRGB inputs of the scene's blur mode, numpy, a batch of them."""
    rng = np.random.default_rng(0)
    if scene.blur.mode == "average":
        return {"batch": rng.integers(0, 256, (batch, scene.blur.frames, h, w, 3), np.uint8)}
    if scene.blur.mode == "none":
        images = rng.random((batch, h, w, 3), dtype=np.float32)
        return {"batch": images, "mask": (images > 0.97).astype(np.float32)}
    return {"batch": rng.integers(0, 256, (batch, h, w, 3), np.uint8)}


def as_dtype(given: dict, dtype: str) -> dict:
    """The inputs as uint8 codes or as float32 values (codes / 255): the same image either way.

    Float inputs are quantized to codes first (masks of 0 and 1 become 0 and 255).
    """
    out = {}
    for key, x in given.items():
        codes = x if x.dtype == np.uint8 else np.round(x * 255).astype(np.uint8)
        out[key] = codes if dtype == "uint8" else (codes / np.float32(255)).astype(np.float32)
    return out


def kernel_ms(synth, tensors: dict, samples: int) -> dict:
    """Each Warp kernel's device time per sample of one batch (CUDA activity), by name."""
    import warp as wp

    with wp.ScopedTimer("batch", cuda_filter=wp.TIMING_KERNEL, print=False,
                        synchronize=True) as timer:
        synth(tensors["batch"], mask=tensors.get("mask"))
    spent: dict = {}
    for result in timer.timing_results:
        # CUDA names <kernel>_<hash>_cuda_kernel_forward: the kernel's own name kept
        name = re.sub(r"(_[0-9a-f]{6,})*_cuda_kernel_forward$", "", result.name)
        spent[name] = spent.get(name, 0.0) + result.elapsed / samples
    return spent


def reduction_ms(tensors: dict, samples: int, runs: int) -> float:
    """Device ms per sample of ``torch.aminmax`` over each sample of each float input (the
    reductions a torch CUDA float batch's checks run), best of ``runs`` (CUDA events)."""
    import torch

    floats = [x.reshape(x.shape[0], -1) for x in tensors.values() if x.is_floating_point()]
    best = float("inf")
    for _ in range(runs + 1):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for x in floats:
            torch.aminmax(x, dim=1)
        end.record()
        end.synchronize()
        best = min(best, start.elapsed_time(end) / samples)
    return best


def wp_pools(device: str) -> bool:
    """Whether Warp allocates on ``device`` from a CUDA memory pool (stream-ordered)."""
    import warp as wp

    return wp.get_device(device).is_mempool_supported and wp.is_mempool_enabled(device)


def pool_kept(device: str):
    """A context in which the Warp memory pool of ``device`` keeps what it frees.

    Its release threshold (bytes held before synchronizations return memory to the driver;
    Warp's default 0) raised to the whole device's memory, and put back after.
    """
    import contextlib

    import warp as wp

    @contextlib.contextmanager
    def kept():
        before = wp.get_mempool_release_threshold(device)
        wp.set_mempool_release_threshold(device, wp.get_device(device).total_memory)
        try:
            yield
        finally:
            wp.set_mempool_release_threshold(device, before)

    return kept()


def dtype_rows(synth, given: dict, batch: int, runs: int, backend, cuda: bool) -> dict:
    """The ``dtypes`` path: one scene's torch batches as uint8 and as float32, ms a sample."""
    import torch

    device = "cuda" if cuda else "cpu"
    sync = torch.cuda.synchronize if cuda else backend.wait
    row = {}
    for dtype in ("uint8", "float32"):
        tensors = {k: torch.from_numpy(v).to(device) for k, v in as_dtype(given, dtype).items()}

        def call(s=synth, t=tensors):
            return s(t["batch"], mask=t.get("mask"))

        row[f"{dtype}_ms"] = median_ms(call, batch, runs, sync)
        row[f"{dtype}_back_to_back_ms"] = back_to_back_ms(call, batch, runs, sync)
        if cuda:
            row[f"{dtype}_kernels_ms"] = kernel_ms(synth, tensors, batch)
            if dtype == "float32":
                row["float32_reductions_ms"] = reduction_ms(tensors, batch, runs)
            if wp_pools(backend.wp_device):
                with pool_kept(backend.wp_device):
                    row[f"{dtype}_back_to_back_pool_kept_ms"] = back_to_back_ms(
                        call, batch, runs, sync)
    for kind in ("", "back_to_back_", "back_to_back_pool_kept_"):
        if f"uint8_{kind}ms" in row:
            row[f"float32_over_uint8_{kind}ratio"] = (row[f"float32_{kind}ms"]
                                                      / row[f"uint8_{kind}ms"])
    return row


#: The dtypes path's columns: result key -> heading.
DTYPE_COLUMNS = {"uint8_ms": "uint8", "float32_ms": "float32", "float32_over_uint8_ratio": "ratio",
                 "uint8_back_to_back_ms": "uint8 b2b", "float32_back_to_back_ms": "float32 b2b",
                 "float32_over_uint8_back_to_back_ratio": "b2b ratio",
                 "uint8_back_to_back_pool_kept_ms": "u8 b2b pool kept",
                 "float32_back_to_back_pool_kept_ms": "f32 b2b pool kept",
                 "float32_over_uint8_back_to_back_pool_kept_ratio": "pool kept ratio",
                 "float32_reductions_ms": "f32 reductions"}


def print_dtypes(device: str, rows: list) -> None:
    """The ``dtypes`` rows side by side, and each kernel's device time on CUDA."""
    print(f"\n{device}: torch batches as uint8 and float32, ms per sample (b2b: 32 calls back "
          "to back; ratio: float32 / uint8)")
    print(f"{'scene':<12}{'size':>10}" + "".join(f"{h:>19}" for h in DTYPE_COLUMNS.values()))
    for row in rows:
        if "uint8_ms" in row:
            print(f"{row['scene']:<12}{row['size']:>10}" + "".join(
                f"{row[k]:>19.3f}" if row.get(k) is not None else f"{'-':>19}"
                for k in DTYPE_COLUMNS))
    for row in rows:
        if "uint8_kernels_ms" in row:
            names = sorted(set(row["uint8_kernels_ms"]) | set(row["float32_kernels_ms"]))
            print(f"\n{row['scene']}: each kernel's device ms per sample{'uint8':>16}"
                  f"{'float32':>12}")
            for name in names:
                u, f = (row[f"{d}_kernels_ms"].get(name) for d in ("uint8", "float32"))
                print(f"  {name:<58}" + "".join(f"{v:>12.4f}" if v is not None else f"{'-':>12}"
                                                 for v in (u, f)))


def one_sample(given: dict, b: int):
    """Sample b as ``synthesize`` takes it."""
    if "mask" in given:
        return {"blurred": given["batch"][b], "mask": given["mask"][b]}
    if given["batch"].ndim == 5:
        return list(given["batch"][b])
    return given["batch"][b]


def median_ms(run, samples: int, runs: int, sync) -> float:
    """Median milliseconds per sample of ``run()``, the device synchronized (one warm-up first)."""
    times, _ = median_time(lambda: (run(), sync()), runs)
    return statistics.median(times) / samples * 1e3


def back_to_back_ms(run, samples: int, runs: int, sync, calls: int = 32) -> float:
    """Median milliseconds per sample of ``calls`` calls of ``run()`` in a row, then one
    synchronization.

    A loop feeding the device (a training loop: each result used, then dropped), where a
    call that returns before its passes end lets the next call's host work overlap them.
    """
    def loop():
        for _ in range(calls):
            run()
        sync()

    times, _ = median_time(loop, runs)
    return statistics.median(times) / (calls * samples) * 1e3


def device_ms(synth, given: dict, samples: int) -> float | None:
    """Kernel time per sample of one batch on a Warp CUDA device (CUDA activity), else None."""
    import warp as wp

    with wp.ScopedTimer("batch", cuda_filter=wp.TIMING_KERNEL, print=False,
                        synchronize=True) as timer:
        synth(given["batch"], mask=given.get("mask"))
    return sum(r.elapsed for r in timer.timing_results) / samples


def copy_bound_ms(backend, bytes_in: int, bytes_out: int) -> dict:
    """A sample's pinned host-device copy bound on a Warp CUDA device, in ms.

    Rates: 256 MB copied each way between pinned host memory and the device (best of 5).
    ``serial``: uploads then downloads; ``duplex``: both directions at once (the copy engines
    overlap them), the least a sample that moves these bytes can take.
    """
    import time

    import warp as wp

    n = 1 << 28
    host = wp.empty(n, dtype=wp.uint8, device="cpu", pinned=True)
    dev = wp.empty(n, dtype=wp.uint8, device=backend.wp_device)
    rates = []
    for dst, src in ((dev, host), (host, dev)):
        best = float("inf")
        for _ in range(5):
            wp.synchronize()
            start = time.perf_counter()
            wp.copy(dst, src)
            wp.synchronize()
            best = min(best, time.perf_counter() - start)
        rates.append(n / best)
    up, down = bytes_in / rates[0] * 1e3, bytes_out / rates[1] * 1e3
    return {"h2d_gb_s": rates[0] / 1e9, "d2h_gb_s": rates[1] / 1e9,
            "bound_serial_ms": up + down, "bound_duplex_ms": max(up, down)}


def commit() -> str | None:
    """The gpu_blur commit measured (``git rev-parse HEAD`` beside the package), if known."""
    import subprocess
    from pathlib import Path

    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True, cwd=Path(gpu_blur.__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backend", default="warp", help="backend (default warp)")
    p.add_argument("--batch", type=int, default=16, help="samples per batch (default 16)")
    p.add_argument("--runs", type=int, default=5, help="timed repeats (default 5)")
    p.add_argument("--scenes", default=",".join(s[0] for s in SCENES),
                   help="comma list of " + ", ".join(s[0] for s in SCENES))
    p.add_argument("--scale", type=float, default=1.0, help="size factor (CPU: e.g. 0.25)")
    p.add_argument("--paths", default="synthesize,numpy,pinned,torch",
                   help="which of synthesize, numpy, pinned (the batch and out= in "
                   "Synthesizer.pinned memory), torch, dtypes (torch batches as uint8 and "
                   "float32, side by side) to time (default all but dtypes)")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    backend = get_backend(args.backend)
    cuda = backend.name == "warp" and getattr(backend, "uses_cuda", False)
    try:
        import torch
    except ImportError:
        torch = None
    sync = backend.wait if hasattr(backend, "wait") else (lambda: None)
    batched = hasattr(gpu_blur, "Synthesizer")
    rows = []
    for name, spec, (h, w) in SCENES:
        if name not in args.scenes.split(","):
            continue
        h, w = int(h * args.scale) // 2 * 2, int(w * args.scale) // 2 * 2
        scene = (scene_from_dict(spec) if isinstance(spec, dict)
                 else gpu_blur.scene.load_scene(spec))
        given = inputs(scene, args.batch, h, w)
        row = {"scene": name, "size": f"{w}x{h}", "batch": args.batch}

        def calls(scene=scene, given=given):
            for b in range(args.batch):
                gpu_blur.synthesize(one_sample(given, b), scene, seed=1, sample_index=b,
                                    backend=backend)

        paths = args.paths.split(",")
        if "synthesize" in paths:
            row["synthesize_ms"] = median_ms(calls, args.batch, args.runs, sync)
        if batched:
            synth = gpu_blur.Synthesizer(scene, backend=backend, seed=1)
            if "numpy" in paths:
                row["batch_numpy_ms"] = median_ms(
                    lambda s=synth, g=given: s(g["batch"], mask=g.get("mask")), args.batch,
                    args.runs, sync)
            if "pinned" in paths:  # the batch and out= in the Synthesizer's pinned memory
                held = {k: synth.pinned(v.shape, v.dtype) for k, v in given.items()}
                for k, v in given.items():
                    held[k][...] = v
                first = synth(held["batch"], mask=held.get("mask"))
                out = [synth.pinned(first.blurred.shape), synth.pinned(first.sharp.shape)]
                row["batch_pinned_ms"] = median_ms(
                    lambda s=synth, g=held, o=out: s(g["batch"], mask=g.get("mask"), out=o),
                    args.batch, args.runs, sync)
                if cuda:
                    moved = (sum(v[0].nbytes for v in given.values()),
                             first.blurred[0].nbytes + first.sharp[0].nbytes)
                    row["bytes_in_out"] = moved
                    row.update(copy_bound_ms(backend, *moved))
                if scene.output.bits and "codes" in inspect.signature(synth).parameters:
                    code = np.uint8 if scene.output.bits == 8 else np.uint16
                    out = [synth.pinned(first.blurred.shape, code) for _ in range(2)]
                    row["batch_pinned_codes_ms"] = median_ms(
                        lambda s=synth, g=held, o=out: s(g["batch"], mask=g.get("mask"), out=o,
                                                         codes=True),
                        args.batch, args.runs, sync)
                    if cuda:  # the same rates, a quarter (a half) of the bytes out
                        up = row["bytes_in_out"][0] / row["h2d_gb_s"] / 1e6
                        down = 2 * out[0][0].nbytes / row["d2h_gb_s"] / 1e6
                        row["bound_serial_codes_ms"] = up + down
                        row["bound_duplex_codes_ms"] = max(up, down)
            if "torch" in paths and cuda and torch is not None and torch.cuda.is_available():
                on_gpu = {k: torch.from_numpy(v).cuda() for k, v in given.items()}
                row["batch_torch_cuda_ms"] = median_ms(
                    lambda s=synth, g=on_gpu: s(g["batch"], mask=g.get("mask")), args.batch,
                    args.runs, torch.cuda.synchronize)
                row["batch_torch_cuda_back_to_back_ms"] = back_to_back_ms(
                    lambda s=synth, g=on_gpu: s(g["batch"], mask=g.get("mask")), args.batch,
                    args.runs, torch.cuda.synchronize)
                row["kernels_ms"] = device_ms(synth, on_gpu, args.batch)
            if "dtypes" in paths and torch is not None and (
                    not cuda or torch.cuda.is_available()):
                row.update(dtype_rows(synth, given, args.batch, args.runs, backend, cuda))
        rows.append(row)
        print(json.dumps(row), flush=True)
    keys = ("synthesize_ms", "batch_numpy_ms", "batch_pinned_ms", "bound_serial_ms",
            "bound_duplex_ms", "batch_pinned_codes_ms", "bound_serial_codes_ms",
            "bound_duplex_codes_ms", "batch_torch_cuda_ms", "batch_torch_cuda_back_to_back_ms",
            "kernels_ms")
    if any("uint8_ms" in row for row in rows):
        print_dtypes(backend.device, rows)
    if any(k in row for row in rows for k in keys):
        print(f"\n{backend.device} (ms per sample, end to end; kernels: device time)")
        print(f"{'scene':<12}{'size':>10}" + "".join(f"{k[:-3]:>31}" for k in keys))
    for row in rows:
        if not any(k in row for k in keys):
            continue
        cells = "".join(f"{row[k]:>31.3f}" if row.get(k) is not None else f"{'-':>31}"
                        for k in keys)
        print(f"{row['scene']:<12}{row['size']:>10}{cells}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": backend.device, "host": platform.node(),
                       "processor": platform.processor(), "runs": args.runs,
                       "bench": "bench/user_paths.py " + " ".join(sys.argv[1:] if argv is None
                                                                  else argv),
                       "commit": commit(), "results": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
