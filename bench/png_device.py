"""``output.png = "fast"`` streams deflated on the device against the host's encoder.

Images: noisy 1920 x 1200 RGB 8-bit codes like a synthesized output's (the built-in photo
resized, plus Gaussian noise of ``--noise`` codes), ``--batch`` different ones. Per batch size:

* ``device_ms``: gpu_blur.png_device.DeviceDeflate on the codes already on the device, the
  six kernels and the download of the streams and their sizes, the device synchronized
  (median of ``--runs`` after a warm-up), per image; ``kernels_ms``: the kernels alone;
* ``host_ms``: gpu_blur.png_codecs.huffman_zlib of numpy's Sub-filtered rows on one thread
  (what an I/O thread spends per image without it), per image;
* ``same_bytes``: every image's device stream equal to the host's.

``--kernels``: also each kernel's time in a batch of the largest size (``kernel_ms``, per
image; the device synchronized around every launch, so their sum exceeds ``kernels_ms``).

``--generate N``: also ``gpu-blur generate --scene rsblur`` over N overlapping windows of a
36-frame sequence (bench/generate_gpu.py's) on ``--device``, then every PNG file of the set
read back and encoded again on the host (``encode_png(..., "fast")``): ``set``'s
``same_bytes`` says whether every file the device deflated is the host's file, byte for byte.

    PYTHONPATH=$PWD python3 bench/png_device.py --device cuda:0 \
        --json bench/results/png_device_<gpu>.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from gpu_blur.analysis.bench.host import cpu_name, source_commit
from gpu_blur.analysis.bench.measure import median_time
from gpu_blur.discovery import default_photo
from gpu_blur.png_codecs import filtered_rows, huffman_zlib

H, W = 1200, 1920


def noisy_images(count: int, noise: float) -> np.ndarray:
    """``count`` x H x W x 3 uint8: the built-in photo resized, with Gaussian noise."""
    photo = cv2.resize(cv2.imread(str(default_photo())), (W, H), interpolation=cv2.INTER_CUBIC)
    rng = np.random.default_rng(0)
    return np.stack([np.clip(photo + rng.normal(0, noise, photo.shape), 0, 255).astype(np.uint8)
                     for _ in range(count)])


def median_ms(work, runs: int) -> float:
    """Median ms of ``runs`` calls of ``work`` after a warm-up call (kernel builds, scratch)."""
    return 1e3 * statistics.median(median_time(work, runs)[0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda:0", help="Warp device (default cuda:0)")
    p.add_argument("--batches", default="1,4,16", help="images a call (default 1,4,16)")
    p.add_argument("--noise", type=float, default=3.0, help="noise in codes (default 3)")
    p.add_argument("--runs", type=int, default=5, help="timed runs (default 5)")
    p.add_argument("--kernels", action="store_true", help="also time each kernel")
    p.add_argument("--generate", type=int, default=0, metavar="N",
                   help="also check a generated set of N samples file by file (default 0)")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    wp.init()
    from gpu_blur.png_device import DeviceDeflate

    batches = [int(b) for b in args.batches.split(",")]
    images = noisy_images(max(batches), args.noise)
    host = [huffman_zlib(filtered_rows(image)) for image in images]
    host_ms = median_ms(lambda: huffman_zlib(filtered_rows(images[0])), args.runs)
    encoder = DeviceDeflate(args.device)
    device = wp.get_device(args.device)
    rows = []
    for batch in batches:
        codes = wp.array(images[:batch].reshape(-1), dtype=wp.uint8, device=device)
        made = encoder.streams(codes, batch, H, W, 3)
        same = all(a == b for a, b in zip(made, host[:batch], strict=True))

        def kernels():
            encoder.deflate(codes, batch, H, W, 3)  # noqa: B023
            wp.synchronize_device(device)

        rows.append({
            "batch": batch,
            "device_ms": median_ms(lambda: encoder.streams(codes, batch, H, W, 3),  # noqa: B023
                                   args.runs) / batch,
            "kernels_ms": median_ms(kernels, args.runs) / batch,
            "same_bytes": same,
        })
        print(rows[-1], flush=True)
    result = {
        "what": "output.png fast streams: gpu_blur.png_device on the device against "
                "huffman_zlib on one host thread, 1920 x 1200 RGB noisy photos",
        "device": wp.get_device(args.device).name, "cpu": cpu_name(),
        "platform": platform.platform(), "commit": source_commit(), "noise": args.noise,
        "stream_mb": statistics.mean(len(s) for s in host) / 1e6,
        "host_ms": host_ms, "rows": rows,
    }
    if args.kernels:
        result["kernel_ms"] = kernel_times(encoder, images, device, args.runs)
        print(result["kernel_ms"], flush=True)
    if args.generate:
        result["set"] = generated_set(args.device, args.generate)
        print(result["set"], flush=True)
    print(json.dumps(result, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0 if all(r["same_bytes"] for r in rows) and result.get("set", {}).get(
        "same_bytes", True) else 1


class _TimedWarp:
    """Warp with each ``launch`` synchronized and timed by kernel name (``times``, seconds)."""

    def __init__(self, wp, device):
        self._wp, self._device, self.times = wp, device, {}

    def __getattr__(self, name):
        return getattr(self._wp, name)

    def launch(self, kernel, *args, **kwargs):
        self._wp.synchronize_device(self._device)
        start = time.perf_counter()
        self._wp.launch(kernel, *args, **kwargs)
        self._wp.synchronize_device(self._device)
        self.times.setdefault(kernel.key, []).append(time.perf_counter() - start)


def kernel_times(encoder, images: np.ndarray, device, runs: int) -> dict:
    """Median ms per image of each deflate kernel, a batch of all ``images``."""
    import warp as wp

    codes = wp.array(images.reshape(-1), dtype=wp.uint8, device=device)
    timed = _TimedWarp(wp, device)
    encoder.wp = timed
    try:
        for _ in range(runs + 1):
            encoder.deflate(codes, len(images), H, W, 3)
    finally:
        encoder.wp = wp
    return {name: 1e3 * statistics.median(times[1:]) / len(images)
            for name, times in timed.times.items()}


def generated_set(device: str, samples: int) -> dict:
    """A ``gpu-blur generate`` set's PNG files against the host's encoder, file by file."""
    import subprocess
    import sys
    import tempfile

    from generate_gpu import write_sequence

    from gpu_blur.image_reading import read_image
    from gpu_blur.png_codecs import encode_png

    with tempfile.TemporaryDirectory() as tmp:
        root, out = Path(tmp) / "in", Path(tmp) / "out"
        write_sequence(root, 36)
        done = subprocess.run([sys.executable, "-m", "gpu_blur.cli", "generate", "--input",
                               str(root), "--output", str(out), "--scene", "rsblur",
                               "--backend", f"warp:{device}", "--samples-per-sequence",
                               str(samples), "--quiet"], capture_output=True, text=True,
                              check=False)
        if done.returncode:
            raise SystemExit(done.stderr[-2000:])
        files = sorted(out.glob("*/*.png"))
        differ = [f.relative_to(out).as_posix() for f in files
                  if f.read_bytes() != encode_png(read_image(f), "fast")]
    return {"samples": samples, "files": len(files), "differ": differ[:10],
            "same_bytes": not differ}


if __name__ == "__main__":
    raise SystemExit(main())
