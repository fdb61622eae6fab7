"""``gpu-blur bench``: accuracy against time of every accuracy knob on every backend."""

from __future__ import annotations

from gpu_blur.cli.common import verbosity, verbosity_arguments

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """The subcommand; its options are :mod:`gpu_blur.analysis.bench.run`'s."""
    from gpu_blur.analysis.bench.run import add_arguments as bench_arguments

    b = sub.add_parser(
        "bench", help="accuracy against time of every accuracy knob on every backend",
        description="Time every accuracy knob's settings on numpy and every OpenCL and Warp "
        "device, with the error against the numpy float64 reference; writes "
        "accuracy_vs_time_<tag>.json, .md (tables) and .png (Pareto plot). See "
        "gpu_blur/analysis/bench/.")
    bench_arguments(b)
    verbosity_arguments(b)


def run(args) -> int:
    """Run the benchmark at the verbosity asked for."""
    from gpu_blur import notices
    from gpu_blur.analysis.bench.run import run_from_args

    with notices.verbosity_set(verbosity(args)):
        return run_from_args(args, progress=not args.quiet)
