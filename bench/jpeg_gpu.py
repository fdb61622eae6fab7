"""JPEG decoding on the CPU (OpenCV) against the GPU (nvJPEG through torchvision): ms an
image, how far the pixels lie apart, and the same for a whole ``gpu-blur generate`` set.

Frames: the built-in photo resized (cubic) to 1920 x 1200 and panned 1 px a frame, written by
OpenCV at quality 95 and 90, chroma 4:2:0 and 4:4:4 (``--frames`` each). Per case:

* ``cpu_ms``: OpenCV's decode of one file's bytes on one thread (``cv2.imdecode``, as
  gpu_blur.image_reading decodes), and ``read_image_ms``: gpu_blur's whole read (the damage
  and size checks included); ``checks_ms``: those checks alone
  (gpu_blur.image_reading.read_checked), which the I/O threads still run for the GPU path;
* ``gpu_ms``: nvJPEG on the CUDA device in batches of 16 files (gpu_blur.gpu_jpeg's
  nvjpeg_decode), the device synchronized before the clock stops;
* ``difference``: nvJPEG's pixels against OpenCV's over every frame: the largest absolute
  difference of a channel (8-bit codes), the mean, and the fraction of pixels with a channel
  that differs.

Times: one warm-up pass, then ``--runs`` passes; medians. ``set``: ``gpu-blur generate --scene
rsblur --backend warp:cuda:0`` over ``--samples`` distinct 9-frame windows of a quality-95
4:2:0 sequence, once with ``--jpeg-decoder cpu`` and once with ``gpu`` (after a 1-sample
warm-up run): samples/s of each and the difference of their output pixels (blurred and
sharp). ``tolerance`` holds gpu_blur.gpu_jpeg's NVJPEG_MAX_DIFFERENCE and
NVJPEG_MEAN_DIFFERENCE and whether every case lies within them.

    PYTHONPATH=$PWD python3 bench/jpeg_gpu.py --json bench/results/jpeg_gpu_<gpu>.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from gpu_blur.analysis.bench.host import cpu_name, source_commit
from gpu_blur.analysis.bench.measure import median_time
from gpu_blur.discovery import default_photo
from gpu_blur.gpu_jpeg import NVJPEG_MAX_DIFFERENCE, NVJPEG_MEAN_DIFFERENCE, nvjpeg_decode
from gpu_blur.image_reading import read_checked, read_image

H, W = 1200, 1920
#: (quality, chroma subsampling) of the decoded files.
CASES = [(q, s) for q in (95, 90) for s in ("420", "444")]
SAMPLING = {"420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
            "444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444}
#: Files nvJPEG decodes in one call.
GPU_BATCH = 16
#: Frames averaged per sample by the rsblur scene.
FRAMES = 9


def panned_frames(count: int) -> list[np.ndarray]:
    """``count`` H x W x 3 uint8 BGR frames: the built-in photo, resized, panned 1 px a frame."""
    photo = cv2.resize(cv2.imread(str(default_photo())), (W + count, H),
                       interpolation=cv2.INTER_CUBIC)
    return [photo[:, i:i + W] for i in range(count)]


def write_jpegs(folder: Path, frames: list[np.ndarray], quality: int, sampling: str
                ) -> list[Path]:
    """``frames`` as JPEG files ``000000.jpg ...`` in ``folder``, written by OpenCV."""
    folder.mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
              SAMPLING[sampling]]
    paths = [folder / f"{i:06d}.jpg" for i in range(len(frames))]
    for path, frame in zip(paths, frames, strict=True):
        assert cv2.imwrite(str(path), frame, params)
    return paths


def median_ms(work, count: int, runs: int) -> float:
    """Median over ``runs`` passes of ``work()`` (after one warm-up), in ms per image."""
    times, _ = median_time(work, runs)
    return 1e3 * statistics.median(times) / count


def cpu_times(paths: list[Path], runs: int) -> dict:
    """OpenCV's decode, gpu_blur's read_image and its checks alone: ms an image, one thread."""
    cv2.setNumThreads(1)
    data = [np.frombuffer(p.read_bytes(), np.uint8) for p in paths]
    return {"cpu_ms": median_ms(lambda: [cv2.imdecode(d, cv2.IMREAD_UNCHANGED) for d in data],
                                len(paths), runs),
            "read_image_ms": median_ms(lambda: [read_image(p) for p in paths], len(paths), runs),
            "checks_ms": median_ms(lambda: [read_checked(p, str(p), "") for p in paths],
                                   len(paths), runs)}


def difference(a: np.ndarray, b: np.ndarray) -> dict:
    """How far two H x W x C images lie apart, in codes, and the fraction of pixels that do."""
    d = np.abs(a.astype(np.int32) - b.astype(np.int32))
    return {"max_abs": int(d.max()), "mean_abs": float(d.mean()),
            "pixels_differing": float(np.count_nonzero(d.max(axis=-1)) / d[..., 0].size)}


def merged(parts: list[dict]) -> dict:
    """:func:`difference` of several images (equal sizes) as one."""
    return {"max_abs": max(p["max_abs"] for p in parts),
            "mean_abs": statistics.fmean(p["mean_abs"] for p in parts),
            "pixels_differing": statistics.fmean(p["pixels_differing"] for p in parts)}


def gpu_case(paths: list[Path], device: str, runs: int) -> dict:
    """nvJPEG's ms an image in batches of :data:`GPU_BATCH`, and its pixels against OpenCV's."""
    import torch

    data = [np.frombuffer(p.read_bytes(), np.uint8) for p in paths]
    batches = [data[i:i + GPU_BATCH] for i in range(0, len(data), GPU_BATCH)]

    def decode_all():
        out = [image for batch in batches for image in nvjpeg_decode(batch, device)]
        torch.cuda.synchronize(device)
        return out

    ms = median_ms(decode_all, len(paths), runs)
    decoded = decode_all()
    parts = [difference(image.permute(1, 2, 0).cpu().numpy(), read_image(path))
             for image, path in zip(decoded, paths, strict=True)]
    return {"gpu_ms": ms, "difference": merged(parts)}


def set_pixels(out: Path) -> dict[str, np.ndarray]:
    """Every output image of a set (blur/, sharp/), decoded, by relative path."""
    return {p.relative_to(out).as_posix(): cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            for sub in ("blur", "sharp") for p in sorted((out / sub).glob("*.png"))}


def set_case(root: Path, samples: int, device: str) -> dict:
    """``generate`` with each decoder over ``samples`` windows: samples/s, pixel differences."""
    from gpu_blur import generate_set

    threads = len(os.sched_getaffinity(0))
    frames = write_jpegs(root / "in" / "seq" / "sharp", panned_frames(FRAMES * samples), 95,
                         "420")
    common = {"input": root / "in", "scene": "rsblur", "backend": f"warp:{device}",
              "io_threads": max(2, threads), "overwrite": True}
    generate_set(root / "warm", limit=1, **common)  # kernels built, files in the page cache
    runs, sets = {}, {}
    for decoder in ("cpu", "gpu"):
        out = root / decoder
        start = time.perf_counter()
        report = generate_set(out, jpeg_decoder=decoder, **common)
        seconds = time.perf_counter() - start
        runs[decoder] = {"samples": report.made, "seconds": seconds,
                         "samples_per_s": report.made / seconds,
                         "summary": [line.replace(str(root), "<tmp>")
                                     for line in report.summary]}
        sets[decoder] = set_pixels(out)
    assert sets["cpu"].keys() == sets["gpu"].keys()
    kinds = {kind: merged([difference(sets["gpu"][k], sets["cpu"][k]) for k in sets["cpu"]
                           if k.startswith(kind)]) for kind in ("blur", "sharp")}
    return {"frames": len(frames), "quality": 95, "sampling": "420", "io_threads":
            common["io_threads"], "runs": runs, "output_difference": kinds}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=32, help="JPEG files per case (default 32)")
    p.add_argument("--runs", type=int, default=5, help="timed passes (default 5)")
    p.add_argument("--samples", type=int, default=8, help="samples of the generate runs "
                   "(distinct windows of 9 frames; default 8; 0: none)")
    p.add_argument("--device", default="cuda:0", help="CUDA device (default cuda:0)")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    result = {"host": cpu_name(), "python": platform.python_version(),
              "commit": source_commit(), "image": [W, H], "gpu_batch": GPU_BATCH,
              "opencv": cv2.__version__, "cases": []}
    with tempfile.TemporaryDirectory() as tmp:
        frames = panned_frames(args.frames)
        paths = {case: write_jpegs(Path(tmp) / f"q{case[0]}_{case[1]}", frames, *case)
                 for case in CASES}
        for (quality, sampling), files in paths.items():
            result["cases"].append({"quality": quality, "sampling": sampling,
                                    "megabytes_an_image": sum(f.stat().st_size for f in files)
                                    / len(files) / 1e6, **cpu_times(files, args.runs)})
            print(f"q{quality} {sampling}: OpenCV {result['cases'][-1]['cpu_ms']:.2f} ms an "
                  f"image, checks {result['cases'][-1]['checks_ms']:.2f} ms")
        import torch

        if not torch.cuda.is_available():
            print(f"CUDA is missing: torch {torch.__version__} sees no CUDA device; nvJPEG "
                  "needs torch and torchvision built for CUDA on a host with an NVIDIA GPU",
                  file=sys.stderr)
            return 1
        import torchvision

        result.update(device=torch.cuda.get_device_name(args.device), torch=torch.__version__,
                      torchvision=torchvision.__version__, cuda=torch.version.cuda)
        for case, files in zip(result["cases"], paths.values(), strict=True):
            case.update(gpu_case(files, args.device, args.runs))
            d = case["difference"]
            print(f"q{case['quality']} {case['sampling']}: nvJPEG {case['gpu_ms']:.3f} ms an "
                  f"image; pixels: max {d['max_abs']}, mean {d['mean_abs']:.3f}, "
                  f"{100 * d['pixels_differing']:.1f} % differ")
        if args.samples:
            result["set"] = set_case(Path(tmp) / "set", args.samples, args.device)
            s = result["set"]
            print(", ".join(f"{k}: {r['samples_per_s']:.2f} samples/s"
                            for k, r in s["runs"].items())
                  + "; outputs: " + ", ".join(f"{k} max {d['max_abs']}, "
                                              f"{100 * d['pixels_differing']:.1f} % differ"
                                              for k, d in s["output_difference"].items()))
    result["tolerance"] = {
        "max_abs": NVJPEG_MAX_DIFFERENCE, "mean_abs": NVJPEG_MEAN_DIFFERENCE,
        "within": all(c["difference"]["max_abs"] <= NVJPEG_MAX_DIFFERENCE
                      and c["difference"]["mean_abs"] <= NVJPEG_MEAN_DIFFERENCE
                      for c in result["cases"])}
    print(f"within gpu_blur.gpu_jpeg's tolerance: {result['tolerance']['within']}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
