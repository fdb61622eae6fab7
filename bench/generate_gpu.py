"""``gpu-blur generate`` from PNG files against the host's decode-plus-encode bound.

Writes a GoPro-style sequence (``seq/sharp/000000.png ...``, 36 frames of 1920 x 1200, the
built-in photo panned 2 px per frame), then runs ``gpu-blur generate --scene rsblur`` over
``--samples`` overlapping windows of it (``--samples-per-sequence``) with one I/O thread and
with one per core. Each run's rate leaves out the process's fixed start (imports, device,
kernels from the cache): ``(N - 1) / (t(N) - t(1))`` from a run of N samples and one of 1,
after an uncounted 1-sample run that warms the caches. The bound: a sample decodes 9 PNG
frames and encodes 2 PNG outputs, so with every core busy the host makes at most
``cores / (9 t_decode + 2 t_encode)`` samples per second (single-core times measured here on
the same images, codecs assumed to scale linearly with cores).

    PYTHONPATH=$PWD python3 bench/generate_gpu.py --backend warp --samples 32 --json out.json

``--workers 1,2,4`` adds runs of ``--devices`` with that many worker processes sharing
``--backend``'s device, and checks that every set holds the same bytes. ``--png stored`` (or
``small``) writes the outputs that way (the rsblur scene with ``output.png`` set), and
measures this tree's encode time and bound with it.

``--windows overlapping,distinct`` runs both kinds of windows: ``overlapping`` (the default:
``--samples`` windows of one 36-frame sequence, each frame read by up to 16 samples, where a
frame cache helps) and ``distinct`` (a sequence of ``9 x --samples`` frames, each frame read by
one sample: only faster codecs and the pipeline help). ``--against TREE`` runs each case with
another checkout's ``gpu_blur`` too (e.g. ``git archive 1d3f510 gpu_blur kernels | tar -x -C
old``), one I/O thread per core, and compares the sets by their decoded pixels (a digest of
every output image's pixels: PNG bytes differ between encoders).

With ``--windows``, t(1) and t(N) of each tree are measured ``--repeats`` times (default 3),
the trees taking turns (before's pair, now's, before's, ...) so that drift hits both alike.
A run's ``samples_per_s`` is ``(N - 1) / (median t(N) - median t(1))``, ``seconds`` and
``start_seconds`` those medians, ``in_run_samples_per_s`` the median of ``generate``'s own
rates (its ``wrote`` line) and ``summary`` the lines of the N-sample run whose t(N) is the
median (the lower middle one for an even count); ``seconds_each``, ``start_seconds_each``,
``in_run_each`` and ``samples_per_s_each`` (each repeat's own pair) keep every repeat. The
speed-up is the ratio of the two median-based rates. Over 64 samples t(N) - t(1) is about as
long as the spread of the process's start, so that rate moves with it; ``written_samples_per_s``
(median; ``written_each``) counts from the first blurred output's file time to the last's,
``(N - 1)`` samples, a rate without the start however short the run.

``bound_now_measured`` sits beside the single-core bounds (``bound_before``, ``bound_now``):
this checkout's codecs alone (``read_image``; ``encode_image(image, 8)``) through a pool of one
thread per core, as many as the runs' I/O threads. It decodes each input frame as often as
this tree does (overlapping: each frame of the sequence once, the frame cache serving the rest;
distinct: 9 a sample) and encodes as many images as the run did (each blurred output and
each distinct sharp one: windows that share their centre frame share a sharp reference, which
gpu_blur encodes once; ``bound_now``'s ``encodes_per_sample`` too): the "now" run's own outputs
read back (blurred and sharp PNGs in turn, noisier than the inputs; up to 32, cycled). Its
``samples_per_s`` is the samples over the median wall seconds of the pool's job (decode-only
and encode-only seconds beside). It is the ceiling these codecs reach through these threads on
this host; not the run's: synthesis, host-device copies, the main thread's work and the writes
to disk are left out. ``ratio_to_measured_bound_now``: now's rate over it.

``--device-png``: the "now" tree deflates ``output.png = "fast"``'s files on the GPU
(gpu_blur.png_device, Warp on CUDA), so its I/O threads only put each file together from a
stream (checksum, join); its bounds count that instead of an encode (the streams made
beforehand, the same bytes).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from gpu_blur.discovery import default_photo

H, W, FRAMES = 1200, 1920, 9
ENCODED = 32  # output images read back for the measured bound, at most


def panned_frames(count: int) -> list[np.ndarray]:
    """``count`` H x W x 3 uint8 BGR frames: the built-in photo, resized, panned 2 px a frame."""
    photo = cv2.resize(cv2.imread(str(default_photo())), (W + 2 * count, H))
    return [photo[:, 2 * i:2 * i + W] for i in range(count)]


def write_sequence(folder: Path, count: int) -> list[Path]:
    """:func:`panned_frames` as PNG files ``seq/sharp/000000.png ...`` under ``folder``.

    Written by OpenCV with its default settings, as a user's frames most often are.
    """
    sharp = folder / "seq" / "sharp"
    sharp.mkdir(parents=True)
    paths = [sharp / f"{i:06d}.png" for i in range(count)]
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        list(pool.map(lambda pf: cv2.imwrite(str(pf[0]), pf[1]),
                      zip(paths, panned_frames(count), strict=True)))
    return paths


def single_core_seconds(paths: list[Path]) -> dict:
    """Median seconds to decode one frame and to encode one 8-bit output, on one core."""
    cv2.setNumThreads(1)
    decode = []
    for path in paths[:5]:
        start = time.perf_counter()
        cv2.imread(str(path))
        decode.append(time.perf_counter() - start)
    image = cv2.imread(str(paths[0]))[4:-4, 4:-4]
    encode = []
    for _ in range(5):
        start = time.perf_counter()
        cv2.imencode(".png", image)
        encode.append(time.perf_counter() - start)
    return {"decode": statistics.median(decode), "encode": statistics.median(encode)}


def encoder(png: str, device_png: bool):
    """``encode(image)``: an output's file as this checkout's I/O threads make it.

    With ``device_png`` the stream was deflated on the GPU (gpu_blur.png_device): the threads
    only put the file together, so the stream is made here beforehand (the same bytes).
    """
    from gpu_blur.file_writing import encode_image
    from gpu_blur.png_codecs import filtered_rows, huffman_zlib

    if not device_png:
        return partial(encode_image, bits=8, png=png)
    streams = {}

    def encode(image):
        stream = streams.setdefault(id(image), (huffman_zlib(filtered_rows(image)),))
        return encode_image(image, 8, png=png, stream=stream)

    return encode


def gpu_blur_codec_seconds(paths: list[Path], png: str = "fast",
                           device_png: bool = False) -> dict:
    """:func:`single_core_seconds` for this checkout's own read and write paths.

    ``read_image`` (ISA-L and numpy for the Sub-filtered files OpenCV writes by default) and
    :func:`encoder`'s with ``output.png = png``; one thread, OpenCV on one core.
    """
    from gpu_blur.image_reading import read_image

    cv2.setNumThreads(1)
    decode = []
    for path in paths[:5]:
        start = time.perf_counter()
        read_image(path)
        decode.append(time.perf_counter() - start)
    image = read_image(paths[0])[4:-4, 4:-4]
    encode_one = encoder(png, device_png)
    encode_one(image)  # a device stream made beforehand
    encode = []
    for _ in range(5):
        start = time.perf_counter()
        encode_one(image)
        encode.append(time.perf_counter() - start)
    return {"decode": statistics.median(decode), "encode": statistics.median(encode)}


def decode_encode_bound(per: dict, cores: int, decodes: float = FRAMES,
                        encodes: float = 2) -> float:
    """Samples per second the host can decode and encode, every core busy.

    A sample decodes ``decodes`` frames (9; fewer where a frame cache serves overlapping
    windows) and encodes ``encodes`` images (2; fewer where windows share a sharp
    reference, encoded once: :func:`encodes_made`) (``per``: :func:`single_core_seconds`).
    """
    return cores / (decodes * per["decode"] + encodes * per["encode"])


def encodes_made(out: Path) -> int:
    """Images a run encoded for the set ``out``: each blurred one, each distinct sharp one.

    gpu_blur encodes a sharp reference its run wrote before once
    (``gpu_blur.file_writing.EncodedImages``); a tree before it encoded every one, so this
    counts what the newer code does.
    """
    blurred = sum(1 for _ in (out / "blur").glob("*.png"))
    return blurred + len({path.read_bytes() for path in (out / "sharp").glob("*.png")})


def measured_codec_bound(paths: list[Path], decodes: int, out: Path, samples: int,
                         threads: int, repeats: int, png: str = "fast",
                         device_png: bool = False) -> dict:
    """Samples per second this checkout's codecs alone reach through ``threads`` threads.

    ``decodes`` reads of ``paths`` (in turn) with ``read_image`` and :func:`encoder`'s
    encodes of images of the output set ``out`` read back, as many as the run encoded
    (:func:`encodes_made`), mixed as the samples run; the pool's wall seconds, the median of
    ``repeats`` (each job also decode-only and encode-only).
    """
    from gpu_blur.image_reading import read_image

    # the blurred and sharp images of each sample in turn
    outputs = sorted(out.rglob("*.png"), key=lambda path: (path.name, path.parent.name))
    images = [read_image(path) for path in outputs[:ENCODED]]
    decode = [partial(read_image, paths[i % len(paths)]) for i in range(decodes)]
    encode_one = encoder(png, device_png)
    for image in images:
        encode_one(image)  # device streams made beforehand
    encode = [partial(encode_one, images[i % len(images)]) for i in range(encodes_made(out))]
    order = sorted([(i / len(decode), 0, i) for i in range(len(decode))]
                   + [(i / len(encode), 1, i) for i in range(len(encode))])
    both = [(decode, encode)[kind][i] for _, kind, i in order]

    def call(task) -> None:  # drops each result as it comes
        task()

    with ThreadPoolExecutor(threads) as pool:
        def wall(tasks) -> float:
            start = time.perf_counter()
            for _ in pool.map(call, tasks):
                pass
            return time.perf_counter() - start

        wall(both[:2 * threads])  # threads started, first allocations made
        each = {"seconds_each": [], "decode_seconds_each": [], "encode_seconds_each": []}
        for _ in range(repeats):
            for key, tasks in zip(each, (both, decode, encode), strict=True):
                each[key].append(wall(tasks))
    seconds = {key.removesuffix("_each"): statistics.median(v) for key, v in each.items()}
    return {"threads": threads, "decodes": len(decode), "encodes": len(encode),
            "images_encoded": len(images), **seconds, **each,
            "samples_per_s": samples / seconds["seconds"]}


def scene_file(folder: str | Path, png: str) -> str:
    """The built-in rsblur scene with ``output.png = png``: its name where png is its own."""
    if png == "fast":
        return "rsblur"
    from gpu_blur.scene import load_scene

    text = Path(load_scene("rsblur").path).read_text()  # the built-in scene's file
    if "\n[output]\n" not in text:
        raise SystemExit("--png: the rsblur scene's file has no [output] table to set it in")
    path = Path(folder) / f"rsblur_png_{png}.toml"
    path.write_text(text.replace("\n[output]\n", f'\n[output]\npng = "{png}"\n', 1))
    if load_scene(str(path)).output.png != png:
        raise SystemExit(f"--png {png}: the scene written does not say it")
    return str(path)


def pixel_digest(out: Path) -> str:
    """sha256 over the decoded pixels of every image of a set (names and codes).

    Sets whose PNG files differ only in how they are compressed give the same digest.
    """
    digest = hashlib.sha256()
    for path in sorted(out.rglob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        digest.update(path.relative_to(out).as_posix().encode() + image.tobytes())
    return digest.hexdigest()


def compare(args, cores: int, save=None) -> dict:
    """``--windows`` and ``--against``: each kind of windows with both checkouts, side by side.

    Each case is printed, and the results so far passed to ``save``, as soon as it is done:
    a run stopped by a time limit keeps the cases it finished.
    """
    cases = {}
    result = {"backend": args.backend, "cores": cores, "image": [W, H], "frames": FRAMES,
              "repeats": args.repeats, "against": args.against and Path(args.against).name,
              "png": args.png, "device_png": args.device_png, "cases": cases}
    for windows in args.windows.split(","):
        if windows not in ("overlapping", "distinct"):
            raise SystemExit(f"--windows {windows}: overlapping or distinct")
        frames = 4 * FRAMES if windows == "overlapping" else FRAMES * args.samples
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "in"
            paths = write_sequence(root, frames)
            # the new tree reads each frame once where a cache holds it; the old reads 9
            new_decodes = min(FRAMES, frames / args.samples)
            old_per = single_core_seconds(paths)
            new_per = gpu_blur_codec_seconds(paths, args.png, args.device_png)
            case = {"frames_in_sequence": frames, "samples": args.samples,
                    "bound_before": {"single_core_seconds": old_per, "decodes_per_sample":
                                     FRAMES, "samples_per_s":
                                     decode_encode_bound(old_per, cores)},
                    "runs": {}, "pixel_digests": {}}
            trees = ([("before", args.against)] if args.against else []) + [("now", None)]
            outs = {name: (Path(tmp) / f"out_{name}", tree) for name, tree in trees}
            case["runs"] = generate_each(outs, root, args.backend, args.samples, cores,
                                         repeats=args.repeats, scene=scene_file(tmp, args.png))
            new_encodes = encodes_made(outs["now"][0]) / args.samples
            case["bound_now"] = {"single_core_seconds": new_per,
                                 "decodes_per_sample": new_decodes,
                                 "encodes_per_sample": new_encodes, "samples_per_s":
                                 decode_encode_bound(new_per, cores, new_decodes, new_encodes)}
            case["pixel_digests"] = {name: pixel_digest(out) for name, (out, _) in outs.items()}
            case["same_pixels"] = len(set(case["pixel_digests"].values())) == 1
            case["bound_now_measured"] = measured_codec_bound(
                paths, round(new_decodes * args.samples), outs["now"][0], args.samples, cores,
                args.repeats, args.png, args.device_png)
            now = case["runs"]["now"]["samples_per_s"]
            case["ratio_to_bound_now"] = now / case["bound_now"]["samples_per_s"]
            case["ratio_to_measured_bound_now"] = (
                now / case["bound_now_measured"]["samples_per_s"])
            if args.against:
                case["speedup"] = now / case["runs"]["before"]["samples_per_s"]
        cases[windows] = case
        _print_case(windows, case, args.samples, cores)
        if save is not None:
            save(result)
    return result


def _print_case(windows: str, case: dict, samples: int, cores: int) -> None:
    """One ``--windows`` case's rates, bounds and its median "now" run's summary."""
    runs = ", ".join(f"{name} {run['samples_per_s']:.2f} (in the run "
                     f"{_num(run['in_run_samples_per_s'], '.3g')})"
                     for name, run in case["runs"].items())
    speed = f" ({case['speedup']:.2f}x)" if "speedup" in case else ""
    measured = case["bound_now_measured"]
    print(f"{windows}: samples/s {runs}{speed}; bound now "
          f"{case['bound_now']['samples_per_s']:.1f}/s "
          f"({100 * case['ratio_to_bound_now']:.0f} % of it), before "
          f"{case['bound_before']['samples_per_s']:.1f}/s; same pixels: "
          f"{case['same_pixels']}")
    for name, run in case["runs"].items():
        print(f"  {name}, {run['repeats']} repeats: samples/s "
              f"{_spread(run['samples_per_s_each'], '.2f')}, t(1) "
              f"{_spread(run['start_seconds_each'], '.2f')} s, t({samples}) "
              f"{_spread(run['seconds_each'], '.2f')} s, in the run "
              f"{_spread(run['in_run_each'], '')}, first to last written "
              f"{_spread(run['written_each'], '.1f')}")
    print(f"  measured bound now: {measured['samples_per_s']:.1f} samples/s "
          f"({100 * case['ratio_to_measured_bound_now']:.0f} % of it; {cores} threads, "
          f"{measured['decodes']} decodes and {measured['encodes']} encodes in "
          f"{measured['seconds']:.2f} s, decode-only {measured['decode_seconds']:.2f} s, "
          f"encode-only {measured['encode_seconds']:.2f} s)")
    print("\n".join(case["runs"]["now"]["summary"]), flush=True)


def _write_json(path: Path, result: dict) -> None:
    """``result`` in ``path``, replaced whole (a reader never sees half a file)."""
    part = path.with_name(path.name + ".part")
    part.write_text(json.dumps(result, indent=1))
    part.replace(path)


def _num(value: float | None, spec: str) -> str:
    """``value`` formatted, ``?`` where a run printed none."""
    return "?" if value is None else f"{value:{spec}}"


def _spread(values: list, spec: str) -> str:
    """``lowest-highest`` of the repeats' figures."""
    known = [v for v in values if v is not None]
    return f"{min(known):{spec}}-{max(known):{spec}}" if known else "?"


def _run(root: Path, out: Path, backend: str, samples: int, threads: int,
         extra: tuple[str, ...] = (), tree: str | None = None, scene: str = "rsblur",
         launcher: tuple[str, ...] = ("-m", "gpu_blur.cli"), environ: dict | None = None):
    """Wall seconds of one ``gpu-blur generate`` into a new ``out``, and its summary lines.

    ``launcher``: Python's arguments that run the CLI with the rest (``-c CODE`` runs
    ``CODE`` instead, with the CLI's arguments in ``sys.argv[1:]``). ``environ``: the run's
    environment (default this process's).
    """
    # another checkout takes the built-in scene: one older than output.png rejects the key
    command = [sys.executable, *launcher, "generate", "--input", str(root),
               "--output", str(out), "--scene", "rsblur" if tree else scene, "--backend", backend,
               "--samples-per-sequence", str(samples), "--io-threads", str(threads),
               "--quiet", "--overwrite", *extra]
    env = dict(os.environ if environ is None else environ)
    if tree is not None:  # that checkout's gpu_blur first on the path
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [tree, env.get("PYTHONPATH")]))
    shutil.rmtree(out, ignore_errors=True)  # not timed: no run removes an earlier one's files
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    wall = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(done.stderr[-2000:])
    # the run's temporary folders named as such: no path of this machine in the results
    lines = (done.stdout + done.stderr).replace(str(root.parent), "<tmp>").strip().splitlines()
    return wall, lines[next((i for i, line in enumerate(lines) if line.startswith("wrote ")),
                            max(len(lines) - 12, 0)):]


def generate_each(outs: dict[str, tuple[Path, str | None]], root: Path, backend: str,
                  samples: int, threads: int, extra: tuple[str, ...] = (),
                  repeats: int = 1, scene: str = "rsblur") -> dict[str, dict]:
    """:func:`generate` for several checkouts, ``name: (output folder, tree)``, in turn.

    Each tree's uncounted 1-sample run first, then ``repeats`` rounds of each tree's t(1) and
    t(N) in the order given; rates from the medians (the module's docstring has the keys).
    """
    for out, tree in outs.values():
        _run(root, out, backend, 1, threads, extra, tree, scene)
    each = {name: {"start": [], "wall": [], "summary": [], "written": []} for name in outs}
    for repeat in range(repeats):
        for name, (out, tree) in outs.items():
            each[name]["start"].append(
                _run(root, out, backend, 1, threads, extra, tree, scene)[0])
            wall, summary = _run(root, out, backend, samples, threads, extra, tree, scene)
            each[name]["wall"].append(wall)
            each[name]["summary"].append(summary)
            each[name]["written"].append(written_rate(out, samples))
            print(f"  {name}, repeat {repeat + 1} of {repeats}: t(1) "
                  f"{each[name]['start'][-1]:.2f} s, t({samples}) {wall:.2f} s",
                  file=sys.stderr, flush=True)
    runs = {}
    for name, got in each.items():
        starts, walls = got["start"], got["wall"]
        wrote = [re.search(r"\(([\d.]+) samples/s\)", lines[0]) if lines else None
                 for lines in got["summary"]]
        in_run = [float(m[1]) if m else None for m in wrote]
        start, wall = statistics.median(starts), statistics.median(walls)
        middle = sorted(range(repeats), key=walls.__getitem__)[(repeats - 1) // 2]
        runs[name] = {
            "threads": threads, "options": list(extra), "repeats": repeats, "seconds": wall,
            "start_seconds": start, "samples_per_s": (samples - 1) / (wall - start),
            "in_run_samples_per_s": (statistics.median(in_run) if None not in in_run
                                     else None),
            "summary": got["summary"][middle], "seconds_each": walls,
            "start_seconds_each": starts, "in_run_each": in_run,
            "samples_per_s_each": [(samples - 1) / (w - t) for w, t in zip(walls, starts,
                                                                           strict=True)],
            "written_samples_per_s": statistics.median(got["written"]),
            "written_each": got["written"]}
    return runs


def written_rate(out: Path, samples: int) -> float:
    """Samples a second between the first and the last blurred output written (file times).

    Leaves out everything before the first sample is out (process start, first decodes,
    page-locked slots, first kernels), so a short run's rate does not move with its start;
    it still holds the run's later waits and the writes' drain.
    """
    times = sorted(path.stat().st_mtime_ns for path in (out / "blur").rglob("*")
                   if path.is_file())
    if len(times) != samples or times[-1] == times[0]:
        raise RuntimeError(f"{out}: {len(times)} blurred outputs for {samples} samples, "
                           "or all written at once: no rate between the first and the last")
    return (samples - 1) / ((times[-1] - times[0]) / 1e9)


def generate(root: Path, out: Path, backend: str, samples: int, threads: int,
             extra: tuple[str, ...] = (), tree: str | None = None,
             scene: str = "rsblur") -> dict:
    """Samples per second of ``gpu-blur generate`` without its fixed start, and its summary.

    A first 1-sample run warms the file cache and the kernel caches and is not counted: a
    cold start can take longer than the whole run that follows. ``tree``: a checkout whose
    ``gpu_blur`` runs instead of this one. One t(1) and one t(N).
    """
    return generate_each({"": (out, tree)}, root, backend, samples, threads, extra,
                         scene=scene)[""]


def set_digest(out: Path) -> str:
    """sha256 over every file of a set (names and bytes); run.json and the lock file aside.

    The manifest's input paths are left out (the input lies in a temporary folder of its own
    in each run of this script), so runs of different commits compare.
    """
    digest = hashlib.sha256()
    for path in sorted(p for p in out.rglob("*") if p.is_file()
                       and p.name not in ("run.json", ".gpu_blur.lock")):
        data = path.read_bytes()
        if path.name == "manifest.jsonl":
            lines = [json.loads(line) for line in data.decode().splitlines()]
            data = "\n".join(json.dumps({k: v for k, v in line.items() if k != "inputs"})
                             for line in lines).encode()
        digest.update(path.relative_to(out).as_posix().encode() + data)
    return digest.hexdigest()


def main(argv=None) -> int:
    # the --windows paragraphs (repeats, the measured bound) as the help's epilog
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[-2:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--backend", default="warp", help="backend (default warp)")
    p.add_argument("--samples", type=int, default=64, help="samples per run (default 64)")
    p.add_argument("--threads", default="1,all", help="--io-threads of the one-process runs, "
                   "comma-separated; all: one per core (default 1,all)")
    p.add_argument("--workers", default="", help="also run --devices with each of these "
                   "numbers of workers on --backend's device, comma-separated (e.g. 1,2,4), "
                   "and compare the sets' bytes")
    p.add_argument("--windows", help="overlapping,distinct: compare kinds of windows "
                   "(one I/O thread per core) instead of the --threads runs, with the "
                   "codecs' bound measured through as many threads beside the single-core one")
    p.add_argument("--against", metavar="TREE", help="with --windows: also run another "
                   "checkout's gpu_blur (a folder holding gpu_blur/ and kernels/), the trees "
                   "taking turns")
    p.add_argument("--repeats", type=int, default=3, help="with --windows: times each tree's "
                   "t(1) and t(N), and the measured bound, are measured; rates from the "
                   "medians (default 3)")
    p.add_argument("--png", default="fast", help="the outputs' output.png (fast, small, "
                   "stored): the rsblur scene with it (default fast, the scene's own; a tree "
                   "older than output.png takes fast only)")
    p.add_argument("--device-png", action="store_true",
                   help="this checkout deflates output.png fast's files on the GPU (Warp on "
                        "CUDA): its bounds count the I/O threads' part, putting each file "
                        "together from its stream")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args(argv)
    cores = len(os.sched_getaffinity(0))
    if args.repeats < 1:
        raise SystemExit("--repeats: 1 or more")
    if args.windows:
        compare(args, cores, args.json and partial(_write_json, Path(args.json)))
        return 0
    devices = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "in"
        paths = write_sequence(root, 4 * FRAMES)
        per = single_core_seconds(paths)
        bound = decode_encode_bound(per, cores)
        threads = [cores if t == "all" else int(t) for t in args.threads.split(",")]
        scene = scene_file(tmp, args.png)
        runs = [generate(root, Path(tmp) / f"out{t}", args.backend, args.samples, t,
                         scene=scene) for t in threads]
        digests = {"serial": set_digest(Path(tmp) / f"out{threads[-1]}")}
        for n in [int(v) for v in args.workers.split(",") if v]:
            out = Path(tmp) / f"workers{n}"
            devices[n] = generate(root, out, args.backend, args.samples, cores,
                                  ("--devices", ",".join([args.backend] * n)), scene=scene)
            digests[f"{n} workers"] = set_digest(out)
    result = {"backend": args.backend, "cores": cores, "image": [W, H], "frames": FRAMES,
              "png": args.png, "single_core_seconds": per, "bound_samples_per_s": bound,
              "runs": runs,
              "ratio_to_bound": runs[-1]["samples_per_s"] / bound,
              "devices_workers": devices, "set_digests": digests,
              "same_bytes": len(set(digests.values())) == 1}
    for run in runs:
        print(f"io-threads {run['threads']:>2}: {run['samples_per_s']:.2f} samples/s")
    for n, run in devices.items():
        print(f"--devices, {n} worker(s): {run['samples_per_s']:.2f} samples/s")
    print("every set the same bytes" if result["same_bytes"] else f"SETS DIFFER: {digests}")
    print(f"bound: {bound:.2f} samples/s ({cores} cores; decode {1e3 * per['decode']:.1f} ms, "
          f"encode {1e3 * per['encode']:.1f} ms per image on one core); "
          f"{100 * result['ratio_to_bound']:.0f} % of it")
    print("\n".join(runs[-1]["summary"]))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
