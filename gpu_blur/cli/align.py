"""``gpu-blur align``: ECC homography from REAL to SYNTH, frames warped onto REAL's grid."""

from __future__ import annotations

import argparse
from pathlib import Path

from gpu_blur.cli.common import read_unit, refuse_writing_over_inputs, same_size

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """The subcommand and its options."""
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


def run(args) -> int:
    """``gpu-blur align``: ECC homography from REAL to SYNTH, frames warped onto REAL."""
    import json

    import numpy as np

    from gpu_blur.analysis.align import align_ecc, inside_mask, warp_to_reference
    from gpu_blur.file_writing import write_image, write_text
    from gpu_blur.image_arrays import to_unit
    from gpu_blur.image_reading import read_image

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
        refuse_writing_over_inputs(f"--output {args.output}", outputs, inputs,
                                    "give --output a folder that holds none of the inputs")
        there = [str(p) for p in outputs if p.exists() or p.is_symlink()]
        if there and not args.overwrite:
            more = f" and {len(there) - 3} more" if len(there) > 3 else ""
            raise ValueError(f"--output {args.output} holds {', '.join(there[:3])}{more} "
                             "already; pass --overwrite to replace them, or choose another "
                             "--output")
    real = read_unit(args.real, "REAL")
    synth = read_unit(args.synth, "SYNTH")
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
        same_size(synth, f"SYNTH {args.synth}", codes, f"FRAME {path}", "the frames must be in "
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

