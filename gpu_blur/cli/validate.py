"""``gpu-blur validate``: the conformance suite, stage by stage, on this host's devices."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_parser", "run"]


def _precisions(text: str) -> list[str]:
    """--precision's comma list, each float32 or float64."""
    names = [x.strip() for x in text.split(",") if x.strip()]
    wrong = [x for x in names if x not in ("float32", "float64")]
    if wrong or not names:
        raise argparse.ArgumentTypeError(f"{text!r}: give float32, float64 or both "
                                         "(float32,float64)")
    return list(dict.fromkeys(names))


def add_parser(sub) -> None:
    """The subcommand and its options."""
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


def run(args) -> int:
    """Run the subcommand; returns its exit status."""
    import json

    from gpu_blur.conformance import validate
    from gpu_blur.file_writing import write_text

    names = args.backend or validate.kernel_devices()
    if not names:
        raise ValueError("no kernel device here (see gpu-blur devices); validate the reference "
                         "itself with --backend numpy")
    report = validate.run(names, args.precision, quick=args.quick, against=args.against)
    print(validate.render(report))
    if args.json:
        write_text(args.json, json.dumps(report, indent=1) + "\n")
    return 0 if report["passed"] else 1
