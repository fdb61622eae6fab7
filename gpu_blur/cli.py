"""The ``gpu-blur`` command."""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path

from gpu_blur import __version__, testhooks

EPILOG = """examples:
  gpu-blur generate --output out/                      # built-in photo, camera shake
  gpu-blur generate --input GOPRO/train --output out/ --scene average.toml
  gpu-blur plan realblur_j.toml                        # which stages a scene runs, and why
  gpu-blur calibrate --chart patches.csv --output my_camera.toml   # a camera from a chart
  gpu-blur scene                                       # every scene key with its default
  gpu-blur compare real.png synth.png --interp interp.png --json scores.json
  gpu-blur align real.png avg.png seq/*.png --output aligned/   # ECC, then warp the frames

exit status of generate: 0 all samples made; 1 some samples failed (each is in the manifest
with "status": "failed" and why; fix them and rerun with --resume); 2 nothing could start
(bad option, scene, input folder or output folder)
"""

#: Failed samples listed one by one in the summary (all are in the manifest).
SHOW_FAILED = 20


def _verbosity_arguments(p: argparse.ArgumentParser) -> None:
    """--quiet / --verbose: how much the command says on stderr besides errors."""
    said = p.add_mutually_exclusive_group()
    said.add_argument("--quiet", action="store_true", help="no progress bar and no notices "
                      "(the device line, errors and the summary remain)")
    said.add_argument("--verbose", action="store_true", help="also each kernel build's time "
                      "(by default one line per device says when kernels compile on first "
                      "use)")


def _verbosity(args) -> int:
    """The notice level (:mod:`gpu_blur.notices`) that --quiet / --verbose ask for."""
    from gpu_blur import notices

    return (notices.QUIET if args.quiet else notices.VERBOSE if args.verbose
            else notices.NORMAL)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="gpu-blur", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Realistic motion-blur synthesis (RSBlur, Rim et al. ECCV 2022).")
    p.add_argument("--version", action="version", version=f"gpu_blur {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser(
        "generate", help="make a training set of blurred/sharp pairs",
        description="Synthesize realistic blurred/sharp PNG pairs and a JSONL manifest. "
        "With no --input, blurs the built-in photograph along camera-shake paths.")
    g.add_argument("--input", type=Path, help="folder of GoPro-style sequences "
                   "(<seq>/sharp/*.png, blur.mode = average), of photos (kernel, trajectory), "
                   "or of already-blurred images with saturation masks (none: "
                   "GoPro_INTER_ABME avg_inter_img/, RSBlur avg65_img/, GoPro_U "
                   "centroid_blurred_img/)")
    g.add_argument("--output", type=Path, required=True, help="folder for blur/, sharp/, "
                   "params/, manifest.jsonl and run.json")
    g.add_argument("--scene", type=Path, help="scene TOML, or a built-in scene's name "
                   "(realblur_j, rsblur, minimal; a file of that name wins); default: the "
                   "default scene (`gpu-blur scene` prints it as TOML to start from)")
    g.add_argument("--seed", type=int, default=0, help="dataset seed; with a sample's index it "
                   "fixes all of that sample's random draws (default 0)")
    g.add_argument("--backend", default="numpy", help="numpy (float64 reference), opencl "
                   "(a GPU, else the fastest CPU runtime), opencl:<platform>:<device>, warp "
                   "(CUDA if present, else CPU), warp:cpu or warp:cuda:<n>; see `gpu-blur "
                   "devices`")
    spread = g.add_mutually_exclusive_group()
    spread.add_argument("--devices", metavar="LIST", help="one worker process per device of "
                        "this host: 'all' (every usable device of --backend: OpenCL GPUs, "
                        "else OpenCL devices; Warp's CUDA devices, else its CPU; numpy: one "
                        "per CPU core) or a comma list of --backend's devices, repeatable "
                        "(opencl:0:0,opencl:0:1; numpy,numpy); same files as one process")
    spread.add_argument("--ray", metavar="ADDRESS", help="tasks on a Ray cluster: 'auto' (the "
                        "running cluster: RAY_ADDRESS or `ray start`'s, else a new local one) "
                        "or an address for ray.init (host:6379, ray://host:10001); inputs and "
                        "gpu_blur at the same paths on every node; pip install 'gpu_blur[ray]'")
    g.add_argument("--gpus-per-task", type=float, metavar="G", help="with --ray: GPUs each "
                   "task asks for (default 1 when --backend runs on an NVIDIA GPU, else 0)")
    g.add_argument("--retries", type=int, metavar="N", help="with --ray: times a failed task "
                   "(lost worker or node) is run again before the run stops (default 3)")
    g.add_argument("--ray-batch", type=int, metavar="K", help="with --ray: samples per task "
                   "(default 1; 32 on GPUs, where each task starts a fresh process)")
    g.add_argument("--io-threads", type=int, metavar="N", help="threads that decode the next "
                   "samples' inputs and encode and write finished ones while the device "
                   "synthesizes (default: the host's cores, at most 32; 1: one thread does "
                   "each step in turn); memory: at most 2 x N samples wait decoded and 2 x N "
                   "wait to be written; same files either way. With --devices or --ray they "
                   "encode and write only (a --devices worker decodes in its own threads)")
    g.add_argument("--tile", type=int, nargs=2, metavar=("ROWS", "COLS"),
                   help="run each image in tiles of at most ROWS x COLS (bounds device memory; "
                   "the output does not change)")
    g.add_argument("--max-device-memory", metavar="BYTES", help="device memory one tile's "
                   "passes may hold (e.g. 512M, 2G; K/M/G binary): images that need more run "
                   "in the largest tiles that fit, halos included (--tile wins); the output "
                   "does not change")
    g.add_argument("--verify", type=float, default=0.0, metavar="FRACTION",
                   help="recompute this fraction of tiles (0 to 1, chosen from seed and sample "
                   "index) with the numpy reference and compare under the tolerance table; a "
                   "mismatch fails that sample (default 0: off)")
    g.add_argument("--strict", action="store_true", help="with --verify: stop the run at the "
                   "first spot-check mismatch (exit status 2)")
    g.add_argument("--samples-per-photo", type=int, default=None, metavar="K",
                   help="samples drawn from each photo, or each blurred image in blur.mode = none "
                   "(default 1; 4 for the built-in photo)")
    g.add_argument("--samples-per-sequence", type=int, default=None, metavar="K",
                   help="blur.mode = average: K windows per sequence, spread evenly from first "
                   "to last (overlapping when needed; default: every non-overlapping window)")
    g.add_argument("--limit", type=int, default=None, metavar="N", help="make at most N samples")
    g.add_argument("--save", default="", metavar="LIST", help="also write, per pair, a comma "
                   "list of: mask (the blurred saturation mask, 16-bit PNG in mask/), raw (the "
                   "noisy Bayer mosaic before demosaicing, 16-bit DNG in raw/, its CFA pattern, "
                   "levels, gains and matrix also in the manifest's raw_info; needs the RAW "
                   "round trip); default: the pair only")
    again = g.add_mutually_exclusive_group()
    again.add_argument("--overwrite", action="store_true",
                       help="replace an existing set in --output")
    again.add_argument("--resume", action="store_true",
                       help="finish the set in --output that a run with the same settings "
                       "started (killed, or with failed samples): keeps finished samples "
                       "untouched, makes the missing ones and retries the failed ones")
    _verbosity_arguments(g)

    pl = sub.add_parser("plan", help="print the stages a scene runs, kept or skipped, with why")
    pl.add_argument("scene", type=Path, nargs="?", help="scene TOML, or a built-in scene's "
                    "name (realblur_j, rsblur, minimal; default: the default scene)")
    pl.add_argument("--cost", action="store_true", help="also time what each kept stage costs "
                    "and what each skipped one would cost, on the built-in photo (a few "
                    "seconds)")
    pl.add_argument("--backend", default="numpy", help="with --cost: the backend timed "
                    "(numpy, opencl:P:D, warp:cpu, warp:cuda:0; default numpy: present "
                    "everywhere, no kernel builds)")
    pl.add_argument("--size", default="480x320", help="with --cost: the input's WxH in "
                    "pixels, even sides (default 480x320)")

    sub.add_parser("devices", help="list every backend and device, with fp64 support and memory")
    sub.add_parser("scene", help="print the default scene as TOML: every key with its default, "
                   "meaning and range (gpu-blur scene > my.toml, then --scene my.toml)")
    sub.add_parser("cameras", help="list the built-in cameras")
    from gpu_blur.analysis.bench.run import add_arguments as bench_arguments

    b = sub.add_parser(
        "bench", help="accuracy against time of every accuracy knob on every backend",
        description="Time every accuracy knob's settings on numpy and every OpenCL and Warp "
        "device, with the error against the numpy float64 reference; writes "
        "accuracy_vs_time_<tag>.json, .md (tables) and .png (Pareto plot). See "
        "gpu_blur/analysis/bench/.")
    bench_arguments(b)
    _verbosity_arguments(b)

    c = sub.add_parser(
        "compare", help="score a synthesized blurred image against a real one (PSNR, SSIM, "
        "noise levels, residual KL)", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Compare a synthesized blurred image with the real blurred image of the "
        "same scene,\nas RSBlur's supplementary Sec. 13 does: PSNR and SSIM (Gaussian window, "
        "sigma 1.5) of\nSYNTH against REAL, the noise level sigma of each (Chen et al., ICCV "
        "2015; also\nprinted in 8-bit codes), and, given a noise-free reference, the KL\n"
        "divergence D(real || synth) in nats between the residuals REAL - "
        "reference and\nSYNTH - reference (one bin per 8-bit code, add-one smoothing; "
        "gpu_blur.analysis.metrics).",
        epilog="examples:\n"
        "  gpu-blur compare real.png synth.png\n"
        "  gpu-blur compare real.png synth.png --interp interp.png --json scores.json\n"
        "  gpu-blur compare real.png synth.png --sharp sharp.png --align\n\n"
        "The images are read as sRGB values in [0, 1] (8- or 16-bit PNG, JPEG, float TIFF).\n"
        "Without --align, every image must have REAL's size. With --align, SYNTH may differ:\n"
        "PSNR, SSIM and REAL's residuals are taken over REAL's pixels that the homography\n"
        "maps inside SYNTH; noise levels and SYNTH's residuals use the files as they are\n"
        "(warping would smooth their noise).\n\n"
        "exit status: 0 scored; 2 missing or unreadable file, size mismatch, failed alignment")
    c.add_argument("real", type=Path, help="the real blurred image (REAL)")
    c.add_argument("synth", type=Path, help="the synthesized blurred image (SYNTH)")
    reference = c.add_mutually_exclusive_group()
    reference.add_argument("--interp", type=Path, metavar="B", help="noise-free reference "
                           "in SYNTH's geometry: the average of frame-interpolated sharp "
                           "frames (RSBlur's B_interp); enables the residual KL")
    reference.add_argument("--sharp", type=Path, metavar="S", help="a sharp frame (or plain "
                           "average of sharp frames) as a rougher noise-free reference, when no "
                           "interpolated average exists; enables the residual KL")
    c.add_argument("--align", action="store_true", help="first estimate a homography from "
                   "REAL to SYNTH by ECC (OpenCV findTransformECC, 3-level pyramid) and warp "
                   "SYNTH and the reference onto REAL's grid")
    c.add_argument("--json", type=Path, metavar="OUT", help="also write the scores to this "
                   "JSON file")

    a = sub.add_parser(
        "align", help="align sharp frames to a real blurred image (ECC homography)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Estimate the homography between a real blurred image (REAL) and one "
        "synthesized from\nits sharp frames (SYNTH) by ECC (OpenCV findTransformECC, "
        "MOTION_HOMOGRAPHY, on\ngrayscale, coarse to fine over a Gaussian pyramid), and warp "
        "the sharp frames onto\nREAL's pixel grid, as RSBlur's supplementary Sec. 6 does. "
        "Prints the iterations per\nlevel, the final correlation and whether ECC converged.",
        epilog="examples:\n"
        "  gpu-blur align real.png avg.png                          # the homography only\n"
        "  gpu-blur align real.png avg.png seq/*.png --output aligned/\n\n"
        "Warped frames keep their names and bit depth (PNG; float TIFF for float input).\n"
        "Positions outside a frame read its mirror image about the edge (BORDER_REFLECT);\n"
        "alignment.json holds the homography (REAL pixel -> SYNTH pixel), the convergence\n"
        "record and the fraction of REAL's pixels that map inside the frames.\n\n"
        "exit status: 0 converged; 1 ECC stopped at --max-iterations (frames are still\n"
        "written, check them); 2 missing or unreadable file, ECC failed")
    a.add_argument("real", type=Path, help="the real blurred image (REAL): the reference grid")
    a.add_argument("synth", type=Path, help="a blurred image synthesized from the frames "
                   "(SYNTH), e.g. their average")
    a.add_argument("frames", type=Path, nargs="*", metavar="FRAME", help="sharp frames in "
                   "SYNTH's geometry to warp onto REAL's grid (needs --output)")
    a.add_argument("--output", type=Path, metavar="DIR", help="folder for the warped frames "
                   "and alignment.json")
    a.add_argument("--overwrite", action="store_true", help="replace warped frames and "
                   "alignment.json already in --output (refused otherwise)")
    a.add_argument("--levels", type=int, default=3, help="Gaussian pyramid levels (1: full "
                   "resolution only; default 3)")
    a.add_argument("--max-iterations", type=int, default=100, metavar="N",
                   help="ECC iterations per level (default 100)")
    a.add_argument("--interpolation", choices=("linear", "cubic"), default="linear",
                   help="resampling of the frames (default linear: no overshoot)")
    _calibrate_parser(sub)
    _validate_parser(sub)
    return p


def _precisions(text: str) -> list[str]:
    """--precision's comma list, each float32 or float64."""
    names = [x.strip() for x in text.split(",") if x.strip()]
    wrong = [x for x in names if x not in ("float32", "float64")]
    if wrong or not names:
        raise argparse.ArgumentTypeError(f"{text!r}: give float32, float64 or both "
                                         "(float32,float64)")
    return list(dict.fromkeys(names))


def _validate_parser(sub) -> None:
    v = sub.add_parser(
        "validate", help="conformance suite: is gpu_blur correct on this device, stage by stage",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run every stage of every pass on the conformance cases (crafted hard "
        "cases and the\nbuilt-in photograph) against the numpy float64 reference under the "
        "tolerance table\nthe test suite uses; random draws bit for bit; tiled against "
        "untiled; the whole\npipeline of each example scene. Prints a table per device.",
        epilog="examples:\n"
        "  gpu-blur validate --quick                     # every kernel device, a few checks\n"
        "  gpu-blur validate --backend opencl:0:0 --precision float32 --json cl.json\n"
        "  gpu-blur validate --backend opencl:0:0 --against warp:cuda:0\n\n"
        "exit status: 0 every check passed; 1 a check failed (the table and the FAIL lines\n"
        "name it); 2 bad option or unknown device")
    v.add_argument("--backend", action="append", metavar="B", help="a device to validate, "
                   "repeatable: numpy, opencl:<platform>:<device>, warp:cpu, warp:cuda:<n> "
                   "(default: every kernel device `gpu-blur devices` lists as ready)")
    v.add_argument("--precision", type=_precisions, default=["float32", "float64"],
                   metavar="LIST", help="float32, float64 or float32,float64 (default both; "
                   "numpy runs float64 only, a device without fp64 float32 only)")
    v.add_argument("--against", metavar="B2", help="compare each --backend with this device "
                   "directly (the cross-backend rows: both kernel devices) instead of with "
                   "the reference")
    v.add_argument("--quick", action="store_true", help="a few checks per pass (under a "
                   "minute per device on a 2-core CPU)")
    v.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON "
                   "(written whole or not at all)")


def _validate(args) -> int:
    import json

    from gpu_blur.conformance import validate
    from gpu_blur.imageio import write_text

    names = args.backend or validate.kernel_devices()
    if not names:
        raise ValueError("no kernel device here (see gpu-blur devices); validate the reference "
                         "itself with --backend numpy")
    report = validate.run(names, args.precision, quick=args.quick, against=args.against)
    print(validate.render(report))
    if args.json:
        write_text(args.json, json.dumps(report, indent=1) + "\n")
    return 0 if report["passed"] else 1


def _calibrate_parser(sub) -> None:
    from gpu_blur.analysis.calibrate import DEFAULT_CRF_ORDER, help_text

    c = sub.add_parser(
        "calibrate", help="fit a camera file (WB gains, colour matrix, response) to a chart",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Fit a camera file from a photo of a 24-patch colour chart, as RSBlur's "
        "supplementary\nSec. 4-7 does: white-balance gains from the grey patches (Eq. 1), the "
        "brightness alpha,\nthen the XYZ colour correction T by least squares (Eq. 2); "
        "optionally the alignment to\nanother camera (Eq. 4) and a polynomial response "
        "that increases on [0, 1] (Eq. 6).\nPrints gains, alpha, T, residuals and condition "
        "numbers; a scene uses the file with\n[camera] name = \"my_camera.toml\".",
        epilog="examples:\n"
        "  gpu-blur calibrate --chart patches.csv --output my_camera.toml\n"
        "  gpu-blur calibrate --chart chart_raw.tiff --boxes boxes.csv --output my_camera.toml "
        "\\\n      --crf-linear lin_a.tiff --crf-rendered jpeg_a.jpg \\\n"
        "      --crf-linear lin_b.tiff --crf-rendered jpeg_b.jpg\n"
        "  then: scene.toml with [camera] name = \"my_camera.toml\" (and, to re-tone with "
        "the fitted\n        response, [output] crf = \"camera\"), and\n"
        "        gpu-blur generate --scene scene.toml --output out\n\n"
        + help_text() + "\nexit status: 0 written; 2 bad input (the message names the file "
        "and line)")
    c.add_argument("--chart", type=Path, required=True, metavar="FILE", help="the chart's "
                   "camera RGB per patch before white balance: CSV/JSON, or a linear image "
                   "with --boxes")
    c.add_argument("--boxes", type=Path, metavar="FILE", help="x,y,w,h of each patch (CSV/"
                   "JSON), for image inputs")
    c.add_argument("--output", type=Path, required=True, metavar="FILE", help="camera file "
                   "to write (.toml or .json)")
    c.add_argument("--overwrite", action="store_true", help="replace an existing --output")
    c.add_argument("--name", help="camera name written in the file (default: its file name)")
    c.add_argument("--reference", type=Path, metavar="JSON", help="chart reference colours "
                   "(default: the built-in ColorChecker 24, X-Rite values after Nov. 2014)")
    c.add_argument("--align-to", type=Path, metavar="FILE", help="the same chart from the "
                   "camera to match (its RAW patches): T becomes T_p @ T (Eq. 4)")
    c.add_argument("--crf-linear", type=Path, action="append", default=[], metavar="FILE",
                   help="linear sRGB patch values or image of one exposure (repeatable)")
    c.add_argument("--crf-rendered", type=Path, action="append", default=[], metavar="FILE",
                   help="the camera's rendered (JPEG) values of the same exposure (repeatable, "
                   "in the same order)")
    c.add_argument("--crf-order", type=int, default=DEFAULT_CRF_ORDER, metavar="K",
                   help=f"response polynomial order (default {DEFAULT_CRF_ORDER})")
    c.add_argument("--shot-noise-k", type=float, metavar="K", help="Poisson gain for [noise] "
                   "(default: RSBlur's estimate; calibrate does not measure noise)")
    c.add_argument("--read-noise-std", type=float, metavar="S", help="read-noise std for "
                   "[noise] (default: RSBlur's estimate)")


def _calibrate(args) -> int:
    from gpu_blur.analysis.calibrate import calibrate, write_camera_file

    inputs = [("--chart", args.chart), ("--boxes", args.boxes), ("--reference", args.reference),
              ("--align-to", args.align_to)] + [("--crf-linear", p) for p in args.crf_linear] + [
              ("--crf-rendered", p) for p in args.crf_rendered]
    _refuse_writing_over_inputs(f"--output {args.output}", [args.output],
                                [(role, p) for role, p in inputs if p is not None],
                                "give --output a new camera file name")
    if args.output.exists() and not args.overwrite:
        raise ValueError(f"--output {args.output} exists; pass --overwrite to replace it")
    result = calibrate(args.chart, boxes=args.boxes, reference=args.reference,
                       name=args.name, crf_linear=args.crf_linear,
                       crf_rendered=args.crf_rendered, crf_order=args.crf_order,
                       align_to=args.align_to, shot_noise_k=args.shot_noise_k,
                       read_noise_std=args.read_noise_std)
    write_camera_file(args.output, result.camera)
    print(result.report())
    print(f"wrote {args.output}; a scene in the same folder uses it with [camera] name = "
          f'"{args.output.name}"'
          + ('; add [output] crf = "camera" to re-tone with its fitted response'
             if result.response is not None else ""))
    return 0


def _cost_size(text: str) -> tuple[int, int]:
    """``plan --size WxH`` as (height, width), within the pixel budget of an input image.

    Raises:
        ValueError: naming the option and its value, for text that is not WxH or a size above
            :func:`gpu_blur.limits.max_pixels` (the timed images are made in memory).
    """
    from gpu_blur import limits

    match = re.fullmatch(r"(\d{1,9})x(\d{1,9})", text.lower(), re.ASCII)
    if not match:
        raise ValueError(f"--size {text!r} is invalid; allowed: WxH in pixels, e.g. 480x320")
    width, height = int(match[1]), int(match[2])
    most = limits.max_pixels()
    if width * height > most:
        raise ValueError(f"--size {text!r} is invalid; allowed: at most {most:,} pixels (the "
                         f"pixel budget of an input image; {width * height:,} would be made in "
                         f"memory): give a smaller size, or raise the budget with the "
                         f"environment variable {limits.MAX_PIXELS_VARIABLE}")
    return height, width


def _check_setup(args, scene) -> None:
    """Fail before any sample for what every sample would fail on (exit status 2)."""
    from gpu_blur.cameras import scene_camera
    from gpu_blur.imageio import read_kernel
    from gpu_blur.plan import raw_round_trip
    from gpu_blur.scheduler import check_tile

    if not 0 <= args.seed < 2**64:
        raise ValueError(f"--seed {args.seed}: must lie in [0, 2**64)")
    if args.tile:
        check_tile(args.tile, "--tile")
    if (args.samples_per_photo is not None and args.samples_per_photo < 1) or (
            args.limit is not None and args.limit < 1):
        raise ValueError("--samples-per-photo and --limit must be >= 1")
    if args.samples_per_sequence is not None and args.samples_per_sequence < 1:
        raise ValueError(f"--samples-per-sequence {args.samples_per_sequence}: must be >= 1")
    if args.input is not None and args.input.resolve().is_relative_to(args.output.resolve()):
        raise ValueError(f"--input {args.input} is --output {args.output} or lies inside it, "
                         "where generate writes and removes the set's files; give an --output "
                         "outside the input (one inside it is fine: it is left out of the "
                         "input)")
    if args.io_threads is not None and args.io_threads < 1:
        raise ValueError(f"--io-threads {args.io_threads}: must be >= 1 (1: no I/O threads)")
    if not 0.0 <= args.verify <= 1.0:
        raise ValueError(f"--verify {args.verify}: the fraction of tiles to check, 0 to 1")
    extras = _extras(args.save)
    if "raw" in extras and not raw_round_trip(scene):
        where = f"scene file {scene.path}" if scene.path else "the scene"
        raise ValueError(f"--save raw: {where} has no RAW round trip (noise.model = "
                         f"{scene.noise.model!r}, isp.round_trip = {scene.isp.round_trip!r}); "
                         "set noise.model = 'poisson-gaussian' or isp.round_trip = 'always', "
                         "or leave raw out of --save")
    if args.strict and not args.verify:
        raise ValueError("--strict stops the run at the first spot-check mismatch; give "
                         "--verify FRACTION too")
    if args.max_device_memory is not None:
        from gpu_blur.plan import plan
        from gpu_blur.scheduler import check_budget

        numpy = args.backend.split(":")[0] == "numpy"
        check_budget(args.max_device_memory, plan(scene),
                     "float64" if numpy else scene.output.precision)
    # an unknown camera name, a bad camera file, a response float32 kernels cannot evaluate
    scene_camera(scene, args.backend.split(":")[0])
    kernel = _scene_files(scene).get("blur.kernel")
    if kernel is not None:
        try:
            read_kernel(kernel)
        except ValueError as e:
            raise ValueError(f"scene file {scene.path}: {e}" if scene.path else str(e)) from None


def _extras(save: str) -> tuple[str, ...]:
    """--save's comma list, checked, in :data:`gpu_blur.dataset.EXTRAS` order."""
    from gpu_blur.dataset import EXTRAS

    given = [name.strip() for name in save.split(",") if name.strip()]
    unknown = [name for name in given if name not in EXTRAS]
    if unknown:
        raise ValueError(f"--save {save}: {unknown[0]!r} is not an output; allowed: a comma "
                         f"list of {', '.join(EXTRAS)}")
    return tuple(name for name in EXTRAS if name in given)


def _scene_files(scene) -> dict[str, Path]:
    """The files a scene reads, by scene key.

    A camera file (``camera.name`` ending in .toml or .json) and ``blur.kernel`` (mode
    "kernel"); a relative path is taken from the scene file's folder.
    """
    named = {}
    if Path(scene.camera.name).suffix.lower() in (".toml", ".json"):
        named["camera.name"] = Path(scene.camera.name)
    if scene.blur.mode == "kernel" and scene.blur.kernel:
        named["blur.kernel"] = Path(scene.blur.kernel)
    return {key: path if path.is_absolute() or scene.base_dir is None else scene.base_dir / path
            for key, path in named.items()}


def _cannot_write(output: Path, spec, error: OSError) -> OSError:
    """The error that stops a run which cannot write a sample: the sample and the way out."""
    return OSError(f"--output {output}: cannot write sample {spec.index} ({spec.name}): "
                   f"{error}; the samples finished so far are kept: free space or fix the "
                   "folder, then run the same command with --resume")


def _generate(args) -> int:
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from gpu_blur.backends import get_backend
    from gpu_blur.dataset import BUILT_IN_INPUT, DatasetWriter, find_samples, library_versions
    from gpu_blur.distributed import pick_executor
    from gpu_blur.generate import (
        QUEUE_PER_THREAD,
        Job,
        WriteBehind,
        default_io_threads,
        run_pipelined,
        run_serial,
    )
    from gpu_blur.scene import load_scene
    from gpu_blur.scheduler import SPOT_CHECK_FAILED, Schedule
    from gpu_blur.timings import PoolTimes, RunTotals, current, timer

    scene = load_scene(args.scene)
    backend = get_backend(args.backend, scene.output.precision)  # fails before any work
    print(f"device: {backend.device}", file=sys.stderr)
    _check_setup(args, scene)
    executor = pick_executor(args, scene.output.precision)  # serial, --devices or --ray
    per_photo = args.samples_per_photo or (1 if args.input else 4)
    found = find_samples(args.input, scene.blur.mode, scene.blur.frames, per_photo,
                         args.samples_per_sequence, exclude=args.output,
                         masks=scene.saturation.mode != "off")
    specs = found.take(args.limit)
    # the Schedule rides in Job.tile (tile, memory budget, spot checks; see pipeline)
    schedule = Schedule(tuple(args.tile) if args.tile else None, args.max_device_memory,
                        args.verify)
    # how samples run, never what they give: recorded, not checked by --resume
    how = {"tile": list(schedule.tile) if schedule.tile else None,
           "max_device_memory": schedule.max_device_memory, "verify": schedule.verify}
    run = {"seed": args.seed, "backend": args.backend, "device": backend.device,
           "input": str(args.input) if args.input else BUILT_IN_INPUT, **how,
           "samples_per_photo": per_photo, "samples_per_sequence": args.samples_per_sequence,
           "scene_file": str(args.scene) if args.scene else None, "scene": scene.to_dict(),
           "files": {key: hashlib.sha256(path.read_bytes()).hexdigest()
                     for key, path in _scene_files(scene).items()},
           "libraries": library_versions(args.backend)}
    extras = _extras(args.save)
    if extras:  # absent without --save, as sets made before it record it
        run["save"] = list(extras)
    writer = DatasetWriter(args.output, scene.output.bits, run, overwrite=args.overwrite,
                           resume=args.resume, specs=specs, total=found.total, extras=extras)
    todo = [s for s in specs if s.index not in writer.done]
    done = len(specs) - len(todo)
    if args.resume:
        print(f"resuming {args.output}: {done} of {len(specs)} samples done, {len(todo)} to "
              f"make ({writer.retry} failed before, to retry; {writer.torn} torn or invalid "
              "manifest line(s) ignored)")
    record = {"seed": args.seed, "backend": args.backend, "device": backend.device, **how}
    failed, made = [], 0
    totals, writing = RunTotals(), current().seconds["writing"]
    threads = args.io_threads or default_io_threads()
    io = PoolTimes(threads) if threads > 1 else None  # else one thread does every step

    def save(spec, result) -> dict:  # a made sample's files, in an I/O thread if there are
        try:  # the model of device that made it
            return writer.save(spec, result, {**record,
                                              "device": result.device or record["device"]})
        except OSError as e:
            raise _cannot_write(args.output, spec, e) from None

    def finish(spec, error, line) -> None:  # each sample once written, in order
        nonlocal made
        try:
            if error is not None:  # this sample's input: record it, go on
                checked = {"spot_check": "failed"} if error.startswith(
                    SPOT_CHECK_FAILED) else {}
                failed.append(writer.fail(spec, error, record | checked))
            else:
                writer.add(line)
                made += 1
        except OSError as e:  # a full disk, a folder gone
            raise _cannot_write(args.output, spec, e) from None
        testhooks.sleep_after(spec.index)

    pool = ThreadPoolExecutor(threads, thread_name_prefix="gpu-blur-io") if io else None
    behind = WriteBehind(save, pool, QUEUE_PER_THREAD * threads, io)
    start = time.perf_counter()
    try:
        job = Job(scene, args.seed, args.backend, schedule, "raw" in extras,
                  bits=scene.output.bits, with_mask="mask" in extras)
        # one device: the pool also decodes ahead; --devices and --ray workers decode their
        # own inputs, and the pool encodes and writes what they make
        samples = (run_pipelined(job, todo, pool, io, QUEUE_PER_THREAD * threads)
                   if io and executor is run_serial else executor(job, todo))
        for spec, result, error in tqdm(samples, total=len(todo), desc="samples",
                                        unit="sample", disable=args.quiet):
            if error is None:
                totals.add(result.timings)
            with timer("writing"):
                for written in behind.put(spec, result, error):
                    finish(*written)
            if args.strict and error is not None and error.startswith(SPOT_CHECK_FAILED):
                with timer("writing"):
                    for written in behind.drain():
                        finish(*written)
                print(f"gpu-blur: error: --strict: sample {spec.index} ({spec.name}): "
                      f"{error}; the run stopped (samples made so far are kept; --resume "
                      "goes on)", file=sys.stderr)
                return 2
        with timer("writing"):
            for written in behind.drain():
                finish(*written)
    except KeyboardInterrupt:
        # the samples made so far are written first; a second Ctrl-C or a failing write
        # stops that (--resume makes them again)
        with contextlib.suppress(KeyboardInterrupt, OSError):
            for written in behind.drain():
                finish(*written)
        print(f"gpu-blur: interrupted after {made} new samples; run the same command with "
              "--resume to finish the set", file=sys.stderr)
        return 130
    finally:
        if pool is not None:  # no thread may write once the folder's lock is released
            pool.shutdown(cancel_futures=True)
        if sys.exc_info()[1] is None:
            writer.close()
        else:  # the error that stopped the run is the one to report, not a failing flush
            with contextlib.suppress(OSError):
                writer.close()
    took = time.perf_counter() - start
    before = f", {done} were done before" if done else ""
    print(f"wrote {made} samples ({len(failed)} failed) to {args.output} in {took:.1f} s "
          f"({made / max(took, 1e-9):.2f} samples/s){before}; manifest: {writer.manifest_path}")
    totals.add({"writing": current().seconds["writing"] - writing,
                "reading": io.waited_for_inputs if io else 0.0})
    print("\n".join(totals.summary(took, on_host=backend.name == "numpy")))
    if io is not None:
        print(io.summary(took))
    if executor is run_serial:  # the device's time is this thread's
        print(totals.bound(took, io))
    if not failed:
        return 0
    print(f"gpu-blur: {len(failed)} of {len(todo)} samples failed; each is in the manifest with "
          '"status": "failed" and its "error":', file=sys.stderr)
    for line in failed[:SHOW_FAILED]:
        print(f"  sample {line['index']} ({line['name']}): {line['error']}", file=sys.stderr)
    if len(failed) > SHOW_FAILED:
        print(f"  ... and {len(failed) - SHOW_FAILED} more", file=sys.stderr)
    print("fix those inputs and run the same command with --resume to make only them",
          file=sys.stderr)
    return 1


def _devices() -> None:
    from gpu_blur.backends.numpy import NumpyBackend

    print(f"{'numpy':<16} {NumpyBackend.device}")
    try:
        from gpu_blur.backends.opencl import NO_PLATFORM_HELP, opencl_devices
    except ImportError:
        print("opencl           not installed (pip install 'gpu_blur[opencl]')")
        devices = []
    else:
        devices = opencl_devices()
        if not devices:
            print(f"opencl           {NO_PLATFORM_HELP}")
    for d in devices:
        state = "ready" if d.usable else f"cannot build kernels: {d.problem}"
        print(f"{d.spec:<16} {d.kind} {d.name} ({d.platform}); fp64 {'yes' if d.fp64 else 'no'}"
              f"; {d.memory_bytes / 2**30:.1f} GiB; {state}")
    try:
        from gpu_blur.backends.warp import warp_devices
    except ImportError:
        print("warp             not installed (pip install 'gpu_blur[warp]')")
        return
    for d in warp_devices():
        memory = f"; {d['memory_bytes'] / 2**30:.1f} GiB" if d["memory_bytes"] else ""
        print(f"{d['spec']:<16} {d['kind']} {d['name']} (NVIDIA Warp); fp64 yes{memory}; ready")


def _refuse_writing_over_inputs(option: str, outputs, inputs, fix: str) -> None:
    """Refuse a command whose output file is one of its inputs, before any work.

    Args:
        option: the option that places the outputs (``--json``, ``--output DIR``).
        outputs: the paths the command may write.
        inputs: ``(role, path)`` of the files it reads (``("REAL", Path("real.png"))``).
        fix: what to do instead.

    The same file is found by device and inode (:func:`os.path.samefile`), so a symbolic or
    hard link to an input counts; an output that does not exist yet is no input.

    Raises:
        ValueError: naming the option, the output, the input and ``fix``.
    """
    files = {}
    for role, path in inputs:
        with contextlib.suppress(OSError):  # a missing input is refused when it is read
            st = os.stat(path)
            files.setdefault((st.st_dev, st.st_ino), (role, path))
    for out in outputs:
        try:
            st = os.stat(out)
        except OSError:
            continue
        if (st.st_dev, st.st_ino) in files:
            role, path = files[st.st_dev, st.st_ino]
            raise ValueError(f"{option}: it would write {out}, which is {role} {path} (the same "
                             f"file): the command would destroy its own input; {fix}")


def _cameras() -> None:
    """``gpu-blur cameras``: each built-in camera with the numbers one chooses by."""
    from gpu_blur.cameras import get_camera, preset_names

    print(f"{'camera':<14} {'K':>10} {'read std':>10}  {'WB red':<12} {'WB blue':<12} source")
    for name in preset_names():
        c = get_camera(name)
        wb = c.white_balance
        if wb.pairs:
            red, blue = (f"{len(wb.pairs)} pairs", f"{min(p[1] for p in wb.pairs):.2f}-"
                         f"{max(p[1] for p in wb.pairs):.2f}")
            red += f" {min(p[0] for p in wb.pairs):.2f}-{max(p[0] for p in wb.pairs):.2f}"
        else:
            red, blue = ("-".join(f"{g:.2f}" for g in dict.fromkeys(r))
                         for r in (wb.red_range, wb.blue_range))
        print(f"{name:<14} {c.shot_noise_k:>10.4g} {c.read_noise_std:>10.4g}  {red:<12} "
              f"{blue:<12} {c.source}")


def _read_unit(path: Path, role: str):
    """An image file as float64 sRGB values in [0, 1], H x W x 3; errors name the role."""
    from gpu_blur.imageio import read_image, to_unit

    try:
        return to_unit(read_image(path), str(path))
    except ValueError as e:
        raise ValueError(f"{role} {e}") from None


def _same_size(a, a_name: str, b, b_name: str, fix: str) -> None:
    """Refuse two images of different sizes, naming both sizes and the way out."""
    if a.shape[:2] != b.shape[:2]:
        raise ValueError(f"{a_name} is {a.shape[0]} x {a.shape[1]} (H x W) but {b_name} is "
                         f"{b.shape[0]} x {b.shape[1]}; {fix}")


def _compare(args) -> int:
    """``gpu-blur compare``: print (and optionally write) the scores of SYNTH against REAL."""
    import json
    import math

    from gpu_blur.analysis import metrics
    from gpu_blur.imageio import write_text

    ref_path = args.interp or args.sharp
    ref_kind = "interp" if args.interp else "sharp"
    if args.json:
        inputs = [("REAL", args.real), ("SYNTH", args.synth)]
        _refuse_writing_over_inputs(f"--json {args.json}", [args.json],
                                    inputs + ([(f"--{ref_kind}", ref_path)] if ref_path else []),
                                    "give --json a new file name")
    real = _read_unit(args.real, "REAL")
    synth = _read_unit(args.synth, "SYNTH")
    ref = _read_unit(ref_path, f"--{ref_kind}") if ref_path else None
    names = f"REAL {args.real}", f"SYNTH {args.synth}"
    if ref is not None:
        _same_size(synth, names[1], ref, f"--{ref_kind} {ref_path}", "the reference must be "
                   "in SYNTH's geometry: make both from the same sharp frames and crop")
    alignment, mask = None, None
    if args.align:
        from gpu_blur.analysis.align import align_ecc, warp_to_reference

        alignment = align_ecc(real, synth)
        scored, mask = warp_to_reference(synth, alignment.homography, real.shape)
        ref_on_real = (warp_to_reference(ref, alignment.homography, real.shape)[0]
                       if ref is not None else None)
    else:
        _same_size(real, names[0], synth, names[1], "crop or resize one to the other's size "
                   "(e.g. both to the common region), or pass --align to warp SYNTH onto "
                   "REAL's grid")
        scored, ref_on_real = synth, ref
    kl = None
    if ref is not None:
        real_residuals = real - ref_on_real
        kl = metrics.histogram_kl(real_residuals if mask is None else real_residuals[mask],
                                  synth - ref)
    scores = {
        "real": str(args.real), "synth": str(args.synth),
        "size": list(real.shape[:2]),
        "psnr_db": metrics.psnr(real, scored, mask=mask),
        "ssim": metrics.ssim(real, scored, mask=mask),
        "noise_level": {"real": metrics.noise_level(real), "synth": metrics.noise_level(synth)},
        "reference": {"kind": ref_kind, "path": str(ref_path)} if ref is not None else None,
        "residual_kl": kl,
        "alignment": alignment.to_dict() if alignment else None,
        "scored_fraction": float(mask.mean()) if mask is not None else 1.0,
    }
    psnr_text = f"{scores['psnr_db']:.2f} dB" if math.isfinite(scores["psnr_db"]) else "inf"
    print(f"REAL   {args.real}  ({real.shape[0]} x {real.shape[1]})")
    print(f"SYNTH  {args.synth}  ({synth.shape[0]} x {synth.shape[1]})")
    if alignment:
        state = "converged" if alignment.converged else "NOT converged (check the images)"
        print(f"align  ECC homography: {'+'.join(map(str, alignment.iterations))} iterations "
              f"({alignment.levels} levels), correlation {alignment.correlation:.4f}, {state}; "
              f"{100 * scores['scored_fraction']:.1f} % of REAL's pixels scored")
    print(f"PSNR   {psnr_text}")
    print(f"SSIM   {scores['ssim']:.4f}")
    for role in ("real", "synth"):
        sigma = scores["noise_level"][role]
        print(f"noise  {role:<5} sigma {sigma:.5f} ({255 * sigma:.3f} of 255)")
    if kl is not None:
        print(f"KL     D(real || synth) of residuals against --{ref_kind}: {kl:.4f} nats")
    else:
        print("KL     (give --interp or --sharp for the residual KL divergence)")
    if args.json:
        if not math.isfinite(scores["psnr_db"]):
            scores["psnr_db"] = None  # identical images; JSON has no infinity
        try:
            write_text(args.json, json.dumps(scores, indent=2) + "\n")
        except OSError as e:
            raise OSError(f"--json {args.json}: cannot write it ({e.strerror})") from None
    return 0


def _align(args) -> int:
    """``gpu-blur align``: ECC homography from REAL to SYNTH, frames warped onto REAL."""
    import json

    import numpy as np

    from gpu_blur.analysis.align import align_ecc, inside_mask, warp_to_reference
    from gpu_blur.imageio import read_image, to_unit, write_image, write_text

    if args.frames and not args.output:
        raise ValueError("gpu-blur align: give --output DIR for the warped frames")
    stems = [f.stem for f in args.frames]
    if len(set(stems)) != len(stems):
        raise ValueError("gpu-blur align: two frames share a file name (without its suffix); "
                         "the warped frames keep their names in --output: align each sequence "
                         "separately")
    if args.output:  # a warped frame is <stem>.png, or <stem>.tiff for float data
        outputs = [args.output / f"{stem}{suffix}" for stem in stems
                   for suffix in (".png", ".tiff")] + [args.output / "alignment.json"]
        inputs = [("REAL", args.real), ("SYNTH", args.synth)] + [("FRAME", f)
                                                                 for f in args.frames]
        _refuse_writing_over_inputs(f"--output {args.output}", outputs, inputs,
                                    "give --output a folder that holds none of the inputs")
        there = [str(p) for p in outputs if p.exists() or p.is_symlink()]
        if there and not args.overwrite:
            more = f" and {len(there) - 3} more" if len(there) > 3 else ""
            raise ValueError(f"--output {args.output} holds {', '.join(there[:3])}{more} "
                             "already; pass --overwrite to replace them, or choose another "
                             "--output")
    real = _read_unit(args.real, "REAL")
    synth = _read_unit(args.synth, "SYNTH")
    result = align_ecc(real, synth, levels=args.levels, max_iterations=args.max_iterations)
    state = "converged" if result.converged else (
        f"NOT converged within {args.max_iterations} iterations: check the frames, or raise "
        "--max-iterations")
    print(f"ECC homography (REAL pixel -> SYNTH pixel), {'+'.join(map(str, result.iterations))}"
          f" iterations over {result.levels} levels, correlation {result.correlation:.5f}, "
          f"{state}")
    with np.printoptions(precision=6, suppress=True):
        print(result.homography)
    inside = inside_mask(result.homography, real.shape, synth.shape)
    record = {"real": str(args.real), "synth": str(args.synth), **result.to_dict(),
              "inside_fraction": float(inside.mean()), "interpolation": args.interpolation,
              "frames": []}
    if args.output:
        args.output.mkdir(parents=True, exist_ok=True)
    for path in args.frames:
        try:
            codes = read_image(path)
        except ValueError as e:
            raise ValueError(f"FRAME {e}") from None
        _same_size(synth, f"SYNTH {args.synth}", codes, f"FRAME {path}", "the frames must be in "
                   "SYNTH's geometry (the frames SYNTH was made from)")
        bits = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(codes.dtype, 0)
        warped, _ = warp_to_reference(to_unit(codes, str(path)), result.homography,
                                      real.shape, interpolation=args.interpolation)
        out = args.output / (path.stem + (".png" if bits else ".tiff"))
        write_image(out, np.clip(warped, 0.0, 1.0), bits)
        record["frames"].append({"input": str(path), "output": str(out)})
    if args.output:
        write_text(args.output / "alignment.json", json.dumps(record, indent=2) + "\n")
        print(f"wrote {len(args.frames)} warped frame(s) and alignment.json to {args.output}")
    return 0 if result.converged else 1


class Terminated(KeyboardInterrupt):
    """A termination signal (SIGTERM, SIGHUP) received by ``generate``: it stops as on Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


#: Signals that stop ``generate`` as Ctrl-C does: finished samples kept, workers ended.
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP")
                     if hasattr(signal, name))


@contextlib.contextmanager
def _stop_on_signals(received: list[int]):
    """Within the block, a stop signal raises :class:`Terminated` and is appended to ``received``.

    Only the first: the handlers are then reset, so a second signal ends the process at once.
    Outside the main thread (where Python cannot set handlers) nothing changes.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        received.append(signum)
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_DFL)
        raise Terminated(signum)

    before = {s: signal.signal(s, stop) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


def _generate_until_stopped(args) -> int:
    """``generate``, stopped by SIGTERM or SIGHUP as by Ctrl-C, exiting with 128 + the signal."""
    received: list[int] = []
    try:
        with _stop_on_signals(received):
            status = _generate(args)
    except Terminated as e:  # outside generate's own handling (setting up, summing up)
        print(f"gpu-blur: stopped by {signal.Signals(e.signum).name}; run the same command "
              "with --resume to finish the set", file=sys.stderr)
        return 128 + e.signum
    return 128 + received[0] if received else status


def _open_standard_streams() -> None:
    """Make closed standard streams (``gpu-blur ... >&- 2>&-``) ``/dev/null``.

    A closed descriptor 0, 1 or 2 would be taken by the next file opened (a sample, the
    manifest), which messages and worker processes would then write into; and Python sets
    ``sys.stdout`` or ``sys.stderr`` to None, on which the progress bar fails.
    """
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:  # closed: the lowest free descriptor, this one, becomes /dev/null
            os.open(os.devnull, os.O_RDWR)
    if sys.stdout is None:
        sys.stdout = open(os.devnull, "w")  # for the process's life
    if sys.stderr is None:
        sys.stderr = open(os.devnull, "w")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpu-blur``; returns the exit status."""
    from gpu_blur import notices

    _open_standard_streams()
    args = _parser().parse_args(argv)
    try:
        if args.command == "generate":
            with notices.verbosity_set(_verbosity(args)):
                return _generate_until_stopped(args)
        if args.command == "calibrate":
            return _calibrate(args)
        if args.command == "validate":
            return _validate(args)
        if args.command == "bench":
            from gpu_blur.analysis.bench.run import run_from_args

            with notices.verbosity_set(_verbosity(args)):
                return run_from_args(args, progress=not args.quiet)
        if args.command == "plan":
            from gpu_blur.cameras import scene_camera
            from gpu_blur.plan import plan
            from gpu_blur.scene import load_scene

            scene = load_scene(args.scene)
            scene_camera(scene)  # an unknown camera or a bad camera file, as generate says
            print(plan(scene))
            if args.cost:
                from gpu_blur.analysis.stage_cost import format_costs, stage_costs

                costs = stage_costs(scene, args.backend, _cost_size(args.size))
                print(format_costs(costs, plan(scene)))
        elif args.command == "devices":
            _devices()
        elif args.command == "scene":
            from gpu_blur.scene import describe_fields

            print(describe_fields())
        elif args.command == "compare":
            return _compare(args)
        elif args.command == "align":
            return _align(args)
        elif args.command == "cameras":
            _cameras()
        return 0
    except BrokenPipeError:  # the reader left (gpu-blur cameras | head -1): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except (ValueError, OSError, RuntimeError) as e:
        print(f"gpu-blur: error: {e}", file=sys.stderr)
        return 2
    except MemoryError as e:  # inputs too large for this machine, outside any one sample
        print(f"gpu-blur: error: out of memory ({str(e) or 'no detail'}): use smaller inputs "
              "or free memory", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
