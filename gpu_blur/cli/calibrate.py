"""``gpu-blur calibrate``: fit a camera file to a photo of a colour chart."""

from __future__ import annotations

import argparse
from pathlib import Path

from gpu_blur.cli.common import refuse_writing_over_inputs

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """The subcommand and its options."""
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


def run(args) -> int:
    """Run the subcommand; returns its exit status."""
    from gpu_blur.analysis.calibrate import calibrate, write_camera_file

    inputs = [("--chart", args.chart), ("--boxes", args.boxes), ("--reference", args.reference),
              ("--align-to", args.align_to)] + [("--crf-linear", p) for p in args.crf_linear] + [
              ("--crf-rendered", p) for p in args.crf_rendered]
    refuse_writing_over_inputs(f"--output {args.output}", [args.output],
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

