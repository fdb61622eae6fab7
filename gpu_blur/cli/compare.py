"""``gpu-blur compare``: score a synthesized blurred image against a real one."""

from __future__ import annotations

import argparse
from pathlib import Path

from gpu_blur.cli.common import read_unit, refuse_writing_over_inputs, same_size

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """The subcommand and its options."""
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



def run(args) -> int:
    """``gpu-blur compare``: print (and optionally write) the scores of SYNTH against REAL."""
    import json
    import math

    from gpu_blur.analysis import metrics
    from gpu_blur.file_writing import write_text

    ref_path = args.interp or args.sharp
    ref_kind = "interp" if args.interp else "sharp"
    if args.json:
        inputs = [("REAL", args.real), ("SYNTH", args.synth)]
        refuse_writing_over_inputs(f"--json {args.json}", [args.json],
                                    inputs + ([(f"--{ref_kind}", ref_path)] if ref_path else []),
                                    "give --json a new file name")
    real = read_unit(args.real, "REAL")
    synth = read_unit(args.synth, "SYNTH")
    ref = read_unit(ref_path, f"--{ref_kind}") if ref_path else None
    names = f"REAL {args.real}", f"SYNTH {args.synth}"
    if ref is not None:
        same_size(synth, names[1], ref, f"--{ref_kind} {ref_path}", "the reference must be "
                   "in SYNTH's geometry: make both from the same sharp frames and crop")
    alignment, mask = None, None
    if args.align:
        from gpu_blur.analysis.align import align_ecc, warp_to_reference

        alignment = align_ecc(real, synth)
        scored, mask = warp_to_reference(synth, alignment.homography, real.shape)
        ref_on_real = (warp_to_reference(ref, alignment.homography, real.shape)[0]
                       if ref is not None else None)
    else:
        same_size(real, names[0], synth, names[1], "crop or resize one to the other's size "
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

