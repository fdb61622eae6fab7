"""``gpu-blur generate``: a data set, by :func:`gpu_blur.generate_set`, with its messages.

The set is :func:`~gpu_blur.generation.generate_set`'s; this module adds the options, the
progress bar, the lines printed before and after, the exit status (0 all samples made, 1 some
failed, 2 nothing could start or a --strict stop, 130 Ctrl-C, 128 + the signal for SIGTERM and
SIGHUP) and the stop signals.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from pathlib import Path

from gpu_blur.cli.common import verbosity, verbosity_arguments

__all__ = ["SHOW_FAILED", "STOP_SIGNALS", "Terminated", "add_parser", "run"]

#: Failed samples listed one by one in the summary (all are in the manifest).
SHOW_FAILED = 20


def add_parser(sub) -> None:
    """The subcommand and its options (:func:`gpu_blur.generate_set`'s keywords)."""
    g = sub.add_parser(
        "generate", help="make a training set of blurred/sharp pairs",
        description="Synthesize realistic blurred/sharp PNG pairs and a JSONL manifest. "
        "With no --input, blurs the built-in photograph along camera-shake paths.")
    g.add_argument("--input", type=Path, help="folder of frame sequences for blur.mode = "
                   "average (GOPRO_Large_all's GOPRxxxx_yy_zz/*.png, every frame; "
                   "<seq>/sharp/*.png; RSBlur's <session>/<id>/*.png), of photos (kernel, "
                   "trajectory), or of already-blurred images with saturation masks (none: "
                   "GoPro_INTER_ABME avg_inter_img/, RSBlur avg65_img/, GoPro_U "
                   "centroid_blurred_img/). generate prints the layout it found and the blur "
                   "mode before it starts")
    g.add_argument("--output", type=Path, required=True, help="folder for blur/, sharp/, "
                   "params/ (or the --format's containers), manifest.jsonl and run.json")
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
                        "per CPU core it may use) or a comma list of --backend's devices, "
                        "repeatable (opencl:0:0,opencl:0:1; numpy,numpy); same files as one "
                        "process")
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
    g.add_argument("--frame-cache", metavar="BYTES", help="host memory for decoded input "
                   "frames that several samples read (overlapping windows, a photo drawn "
                   "several times), each decoded once while it fits (e.g. 512M, 2G; 0: none; "
                   "default 1/8 of the host's memory, at most 1G; with --devices split among "
                   "the workers); the output does not change")
    g.add_argument("--jpeg-decoder", choices=("cpu", "gpu"), default="cpu",
                   help="what decodes JPEG inputs: cpu (OpenCV's libjpeg-turbo, the default) or "
                   "gpu (NVIDIA's nvJPEG through torchvision, a group of samples' files at a "
                   "time, into the memory of a --backend warp:cuda:N; needs torch and "
                   "torchvision built for CUDA). Decoded pixels may differ from the CPU's by a "
                   "few codes (docs/cli/generate.md gives the measured tolerance), so the set "
                   "records the decoder and --resume keeps it; files nvJPEG is not given "
                   "(progressive, greyscale, damaged) are decoded on the CPU")
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
    g.add_argument("--average-gopro-large-sharp", action="store_true", help="blur.mode = "
                   "average over GOPRO_Large (<seq>/sharp/ beside <seq>/blur/) all the same; "
                   "refused without it: those sharp frames are one ground-truth frame per "
                   "blurred image, with gaps between them, and average into ghosted blur "
                   "(average GOPRO_Large_all's frames with blur.frames = \"from-name\" instead)")
    g.add_argument("--frames-as-photos", action="store_true", help="blur.mode = trajectory or "
                   "kernel over an input of frame sequences all the same, each frame a photo "
                   "of its own; refused without it (blur.mode = average averages them)")
    g.add_argument("--save", default="", metavar="LIST", help="also write, per pair, a comma "
                   "list of: mask (the blurred saturation mask, 16-bit PNG in mask/), raw (the "
                   "noisy Bayer mosaic before demosaicing, 16-bit DNG in raw/, its CFA pattern, "
                   "levels, gains and matrix also in the manifest's raw_info; needs the RAW "
                   "round trip); default: the pair only")
    g.add_argument("--format", default="png", metavar="FORMAT", help="how the pairs are "
                   "stored: png (files in blur/, sharp/, params/), lmdb (BasicSR's paired "
                   "LMDB: blur.lmdb and sharp.lmdb with meta_info.txt, for dataroot_lq and "
                   "dataroot_gt; pip install 'gpu_blur[lmdb]'), webdataset (tar shards "
                   "shard-NNNNNN.tar, per sample <key>.blur.png, <key>.sharp.png, "
                   "<key>.json); the same image bytes in each (default png)")
    g.add_argument("--shard-size", type=int, metavar="N", help="with --format webdataset: "
                   "samples per shard (default 100); a shard is renamed into place when "
                   "complete, and --resume makes the samples of unfinished shards again")
    again = g.add_mutually_exclusive_group()
    again.add_argument("--overwrite", action="store_true",
                       help="replace an existing set in --output")
    again.add_argument("--resume", action="store_true",
                       help="finish the set in --output that a run with the same settings "
                       "started (killed, or with failed samples): keeps finished samples "
                       "untouched, makes the missing ones and retries the failed ones")
    verbosity_arguments(g)


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


def run(args) -> int:
    """``generate``, stopped by SIGTERM or SIGHUP as by Ctrl-C, exiting with 128 + the signal."""
    from gpu_blur import notices

    received: list[int] = []
    with notices.verbosity_set(verbosity(args)):
        try:
            with _stop_on_signals(received):
                status = _generate(args)
        except Terminated as e:  # outside generate's own handling (setting up, summing up)
            print(f"gpu-blur: stopped by {signal.Signals(e.signum).name}; run the same command "
                  "with --resume to finish the set", file=sys.stderr)
            return 128 + e.signum
    return 128 + received[0] if received else status


def _say_device(device: str) -> None:
    print(f"device: {device}", file=sys.stderr)


def _say_input(found) -> None:
    """What the input holds and the blur mode (:class:`gpu_blur.generation.InputFound`)."""
    for line in found.lines():
        print(line, file=sys.stderr)


def _generate(args) -> int:
    """Make the set; print what it did, or what stopped it; return the exit status."""
    from gpu_blur.generation import SetInterrupted, StrictStop, generate_set

    def say_resume(state) -> None:
        print(f"resuming {args.output}: {state.done} of {state.samples} samples done, "
              f"{state.to_make} to make ({state.failed_before} failed before, to retry; "
              f"{state.torn} torn or invalid manifest line(s) ignored)")

    try:
        report = generate_set(
            args.output, input=args.input, scene=args.scene, seed=args.seed,
            backend=args.backend, devices=args.devices, ray=args.ray,
            gpus_per_task=args.gpus_per_task, retries=args.retries, ray_batch=args.ray_batch,
            io_threads=args.io_threads, tile=args.tile, max_device_memory=args.max_device_memory,
            frame_cache=args.frame_cache, jpeg_decoder=args.jpeg_decoder,
            verify=args.verify, strict=args.strict, samples_per_photo=args.samples_per_photo,
            samples_per_sequence=args.samples_per_sequence, limit=args.limit, save=args.save,
            format=args.format, shard_size=args.shard_size,
            overwrite=args.overwrite, resume=args.resume,
            average_gopro_large_sharp=args.average_gopro_large_sharp,
            frames_as_photos=args.frames_as_photos, progress=not args.quiet,
            on_device=_say_device, on_resume=say_resume, on_input=_say_input)
    except StrictStop as e:
        print(f"gpu-blur: error: {e}", file=sys.stderr)
        return 2
    except SetInterrupted as e:
        _say_interrupted(e.made)
        return 130
    except OSError as e:  # closing the set failed after a stop: say the stop first
        if isinstance(e.__cause__, StrictStop):
            print(f"gpu-blur: error: {e.__cause__}", file=sys.stderr)
        elif isinstance(e.__cause__, SetInterrupted):
            _say_interrupted(e.__cause__.made)
        raise
    print("\n".join(report.summary))
    failed = report.failed
    if not failed:
        return 0
    print(f"gpu-blur: {len(failed)} of {report.to_make} samples failed; each is in the manifest "
          'with "status": "failed" and its "error":', file=sys.stderr)
    for line in failed[:SHOW_FAILED]:
        print(f"  sample {line['index']} ({line['name']}): {line['error']}", file=sys.stderr)
    if len(failed) > SHOW_FAILED:
        print(f"  ... and {len(failed) - SHOW_FAILED} more", file=sys.stderr)
    print("fix those inputs and run the same command with --resume to make only them",
          file=sys.stderr)
    return 1


def _say_interrupted(made: int) -> None:
    print(f"gpu-blur: interrupted after {made} new samples; run the same command with "
          "--resume to finish the set", file=sys.stderr)
