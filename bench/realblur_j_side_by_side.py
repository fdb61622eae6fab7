"""The RealBlur-J scene side by side: gpu_blur's batch API against a plain PyTorch port of the
authors' chain (``bench/torch_chain.py``), in one run on one device (issue 15, item 4).

Both get the same batch: B blurred sRGB images, their saturation masks and sharp images,
float32 in [0, 1] (the built-in photo at the chosen size, box-blurred along rows, its mask the
same blur of its clipped pixels, each sample shifted). Each side is timed two ways, per sample:

* **device**: torch tensors on the device in, torch tensors on the device out (ours with
  ``channels_first=True``, the torch chain's own B x 3 x H x W);
* **host to host**: B x H x W x 3 numpy arrays in, numpy out (the torch chain: the plain
  ``torch.from_numpy(x).to(device)`` and ``.cpu().numpy()`` a user writes, no pinned memory).

Each time is the median over ``--runs`` batches after one warm-up batch, with the device
synchronized (``torch.cuda.synchronize``, which waits for every stream, Warp's included)
before the clock starts and before it stops. On CUDA the run also measures pinned
host-to-device and device-to-host copy rates and states the copy bound of the host-to-host
case: the inputs' and outputs' bytes at those rates. Without CUDA it runs on the CPU and says
so.

Run from the repository root: ``PYTHONPATH=$PWD python bench/realblur_j_side_by_side.py``
(``--help`` for the options); prints a table and the ratios, writes
``bench/results/realblur_j_side_by_side_<device>.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from gpu_targets import median_seconds  # bench/ is the script's folder: on sys.path
from torch_chain import BORDER, random_parameters, realblur_j_chain

import gpu_blur
from gpu_blur.analysis.bench.host import cpu_name, source_commit
from gpu_blur.analysis.bench.run import _size
from gpu_blur.discovery import default_photo

SCENE = "realblur_j"
RESULTS = Path(__file__).resolve().parent / "results"


def make_inputs(batch: int, width: int, height: int) -> dict[str, np.ndarray]:
    """B x H x W x 3 float32 ``blurred``, ``mask`` and ``sharp`` in [0, 1] (see the module)."""
    photo = cv2.cvtColor(cv2.imread(str(default_photo())), cv2.COLOR_BGR2RGB)
    sharp = cv2.resize(photo, (width, height), interpolation=cv2.INTER_CUBIC)
    sharp = sharp.astype(np.float32) / 255
    linear = np.where(sharp <= 0.04045, sharp / 12.92, ((sharp + 0.055) / 1.055) ** 2.4)
    # a 15 px horizontal streak (ksize is width, height) in linear light, and the same blur of
    # the clipped pixels as the mask: the authors' kernel variant (RSBLUR_PIPELINE.md 2B)
    blurred_lin = cv2.blur(linear, (15, 1), borderType=cv2.BORDER_REFLECT)
    mask = cv2.blur((sharp >= 1).astype(np.float32), (15, 1), borderType=cv2.BORDER_REFLECT)
    blurred = np.where(blurred_lin <= 0.0031308, 12.92 * blurred_lin,
                       1.055 * blurred_lin ** (1 / 2.4) - 0.055).clip(0, 1)
    images = {"blurred": blurred, "mask": mask, "sharp": sharp}
    return {k: np.stack([np.roll(v, 7 * b, axis=1) for b in range(batch)]).astype(np.float32)
            for k, v in images.items()}


def device_tag(device: torch.device) -> str:
    """``cpu``, or a short slug of the GPU's name (``h100`` for "NVIDIA H100 80GB HBM3")."""
    if device.type != "cuda":
        return "cpu"
    name = torch.cuda.get_device_name(device)
    model = re.search(r"\b([A-Z]{1,2}\d{2,4}[A-Z]?)\b", name)
    return model[1].lower() if model else re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def pinned_copy_rates(nbytes: int, device: torch.device, runs: int) -> dict:
    """Pinned host-to-device and device-to-host bytes per second for ``nbytes`` at once."""
    host = torch.empty(nbytes, dtype=torch.uint8, pin_memory=True)
    dev = torch.empty(nbytes, dtype=torch.uint8, device=device)
    sync = torch.cuda.synchronize
    h2d = median_seconds(lambda: dev.copy_(host, non_blocking=True), sync, runs)
    d2h = median_seconds(lambda: host.copy_(dev, non_blocking=True), sync, runs)
    return {"bytes": nbytes, "h2d_bytes_per_s": nbytes / h2d, "d2h_bytes_per_s": nbytes / d2h}


def per_sample(seconds: float, batch: int) -> float:
    return 1e3 * seconds / batch


def time_torch_chain(host: dict, device: torch.device, runs: int, sync) -> dict:
    batch = host["blurred"].shape[0]
    on_device = {k: torch.from_numpy(v).to(device).permute(0, 3, 1, 2).contiguous()
                 for k, v in host.items()}
    params_generator = torch.Generator().manual_seed(0)
    noise_generator = torch.Generator(device).manual_seed(0)

    def chain(blurred, mask, sharp):
        params = random_parameters(batch, params_generator)
        return realblur_j_chain(blurred, mask, sharp, **params, generator=noise_generator)

    def device_run():
        return chain(on_device["blurred"], on_device["mask"], on_device["sharp"])

    def host_run():
        inputs = [torch.from_numpy(host[k]).to(device).permute(0, 3, 1, 2)
                  for k in ("blurred", "mask", "sharp")]
        return [t.permute(0, 2, 3, 1).contiguous().cpu().numpy() for t in chain(*inputs)]

    out = {"device_ms_per_sample": per_sample(median_seconds(device_run, sync, runs), batch),
           "host_to_host_ms_per_sample": per_sample(median_seconds(host_run, sync, runs),
                                                    batch)}
    out["output_mean"] = float(host_run()[0].mean())
    return out


def time_ours(host: dict, device: torch.device, backend: str, runs: int, sync) -> dict:
    batch = host["blurred"].shape[0]
    on_device = {k: torch.from_numpy(v).to(device).permute(0, 3, 1, 2).contiguous()
                 for k, v in host.items()}
    synth_tensors = gpu_blur.Synthesizer(SCENE, backend=backend, seed=0, channels_first=True)
    synth_numpy = gpu_blur.Synthesizer(SCENE, backend=backend, seed=0)
    last = {}

    def device_run():
        last["device"] = synth_tensors(on_device["blurred"], mask=on_device["mask"],
                                       sharp=on_device["sharp"])

    def host_run():
        last["host"] = synth_numpy(host["blurred"], mask=host["mask"], sharp=host["sharp"])

    out = {"device_ms_per_sample": per_sample(median_seconds(device_run, sync, runs), batch),
           "host_to_host_ms_per_sample": per_sample(median_seconds(host_run, sync, runs),
                                                    batch)}
    result = last["device"].blurred
    if not (isinstance(result, torch.Tensor) and result.device == device):
        out["problem"] = f"torch tensors on {device} in, {type(result).__name__} out"
    out["device_last_batch_timings_s"] = last["device"].timings
    out["host_last_batch_timings_s"] = last["host"].timings
    out["output_mean"] = float(np.asarray(last["host"].blurred).mean())
    out["device_name"] = synth_numpy.runner.device
    return out


def versions(ours: bool) -> dict:
    v = {"python": platform.python_version(), "torch": torch.__version__,
         "torch_cuda": torch.version.cuda, "numpy": np.__version__,
         "gpu_blur": gpu_blur.__version__, "gpu_blur_commit": source_commit()}
    if ours:
        try:
            import warp
            v["warp"] = warp.__version__
        except ImportError:
            v["warp"] = None
    return v


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=_size, default=(1920, 1200), metavar="WxH",
                   help="image size, even sides (default 1920x1200)")
    p.add_argument("--batch", type=int, default=16, help="samples per batch (default 16)")
    p.add_argument("--runs", type=int, default=10, help="timed batches per measurement, "
                   "after one warm-up (default 10)")
    p.add_argument("--backend", default="warp", help="gpu_blur backend (default warp: CUDA "
                   "when present)")
    only = p.add_mutually_exclusive_group()
    only.add_argument("--ours-only", action="store_true", help="time only gpu_blur")
    only.add_argument("--torch-only", action="store_true", help="time only the torch chain")
    p.add_argument("--output", type=Path, help="JSON path (default bench/results/"
                   "realblur_j_side_by_side_<device>.json)")
    args = p.parse_args(argv)
    (width, height), batch = args.size, args.batch
    if width % 2 or height % 2 or min(width, height) <= 2 * BORDER or batch < 1:
        p.error(f"--size {width}x{height} --batch {batch}: need even sides above "
                f"{2 * BORDER} and a batch of at least 1")

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    cuda = device.type == "cuda"
    name = torch.cuda.get_device_name(device) if cuda else f"CPU {cpu_name()} (no CUDA)"
    print(f"device: {name}" + ("" if cuda else ": timings are the CPU's"), flush=True)
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    host = make_inputs(batch, width, height)
    bytes_in = sum(v.nbytes for v in host.values())
    bytes_out = 2 * batch * (height - 2 * BORDER) * (width - 2 * BORDER) * 3 * 4
    report = {
        "what": "RealBlur-J scene (blur mode none; saturation, A7R3 RAW round trip with "
                "Poisson-Gaussian noise, Malvar 2004, A7R3 re-toning, 4 px crop; float32 "
                "out): gpu_blur.Synthesizer against a plain PyTorch port of the authors' "
                "chain; ms per sample, median over batches after a warm-up, device "
                "synchronized before each clock reading",
        "device": name, "host": platform.node(), "cpu": cpu_name(), "versions":
            versions(not args.torch_only),
        "size": [width, height], "batch": batch, "runs": args.runs, "backend": args.backend,
        "bytes_per_sample": {"in": bytes_in // batch, "out": bytes_out // batch},
    }
    if cuda:
        rates = pinned_copy_rates(bytes_in // 3, device, args.runs)
        rates["copy_bound_ms_per_sample"] = 1e3 * (
            bytes_in / rates["h2d_bytes_per_s"] + bytes_out / rates["d2h_bytes_per_s"]) / batch
        rates["copy_bound_overlapped_ms_per_sample"] = 1e3 * max(
            bytes_in / rates["h2d_bytes_per_s"], bytes_out / rates["d2h_bytes_per_s"]) / batch
        report["pinned_copy"] = rates
    if not args.torch_only:
        report["ours"] = time_ours(host, device, args.backend, args.runs, sync)
    if not args.ours_only:
        report["torch"] = time_torch_chain(host, device, args.runs, sync)
    if "ours" in report and "torch" in report:
        report["torch_over_ours"] = {
            k: report["torch"][k] / report["ours"][k]
            for k in ("device_ms_per_sample", "host_to_host_ms_per_sample")}

    out = args.output or RESULTS / f"realblur_j_side_by_side_{device_tag(device)}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=float) + "\n")
    print(f"{width} x {height}, batch {batch}, median of {args.runs} batches; ms per sample")
    print(f"  {'':12s} {'device':>10s} {'host to host':>14s}")
    for side in ("ours", "torch"):
        if side in report:
            r = report[side]
            print(f"  {side:12s} {r['device_ms_per_sample']:10.3f} "
                  f"{r['host_to_host_ms_per_sample']:14.3f}")
    if "pinned_copy" in report:
        c = report["pinned_copy"]
        print(f"  pinned copies: H2D {c['h2d_bytes_per_s'] / 1e9:.1f} GB/s, D2H "
              f"{c['d2h_bytes_per_s'] / 1e9:.1f} GB/s; host-to-host bound "
              f"{c['copy_bound_ms_per_sample']:.3f} ms per sample "
              f"({c['copy_bound_overlapped_ms_per_sample']:.3f} with both directions at once)")
    if "torch_over_ours" in report:
        ratio = report["torch_over_ours"]
        print(f"  torch / ours: {ratio['device_ms_per_sample']:.1f}x on the device, "
              f"{ratio['host_to_host_ms_per_sample']:.1f}x host to host")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
