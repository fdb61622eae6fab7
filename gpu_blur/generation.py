"""A whole data set from Python: :func:`generate_set`, the driver ``gpu-blur generate`` runs.

It checks the options and the scene before any sample, opens the output folder
(:class:`~gpu_blur.dataset.DatasetWriter`: new, ``overwrite`` or ``resume``), has an executor
make the samples (this thread with I/O threads, ``devices`` or ``ray``; see
:mod:`gpu_blur.generate` and :mod:`gpu_blur.distributed`), writes them in order and returns a
:class:`SetReport`. Nothing is printed unless asked (``progress=True``: the progress bar);
what stops the run is raised: ValueError, OSError or RuntimeError for what no sample could
get past (bad options, scene, input or output folder, a full disk), :class:`StrictStop` for a
spot-check mismatch under ``strict``, :class:`SetInterrupted` for Ctrl-C (the samples made
so far are written first). Options and messages are the command's: a keyword is the option's
name with ``_`` for ``-`` (``max_device_memory="2G"`` is ``--max-device-memory 2G``).

Example::

    report = gpu_blur.generate_set("out", limit=8, seed=1)
    print(report.made, report.manifest)
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import hashlib
import os
import time
import types
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from gpu_blur import testhooks

__all__ = ["InputFound", "Progress", "ResumeState", "SetInterrupted", "SetReport", "StrictStop",
           "blur_in_words", "check_setup", "extras", "generate_set", "scene_files"]

#: ``progress``: True (a progress bar on standard error), or ``progress(done, total)`` called
#: as each sample comes back (made or failed); False or None: nothing.
Progress = bool | Callable[[int, int], None] | None


@dataclasses.dataclass(frozen=True)
class ResumeState:
    """What a ``resume`` found in the output folder, before any sample is made.

    Attributes:
        done: samples an earlier run finished (kept untouched).
        samples: samples of the set (after ``limit``).
        to_make: samples this run makes (the missing and the failed ones).
        failed_before: of those, the ones that failed before (tried again).
        torn: manifest lines ignored (torn by a kill, or not valid).
    """

    done: int
    samples: int
    to_make: int
    failed_before: int
    torn: int


@dataclasses.dataclass(frozen=True)
class InputFound:
    """What the input holds and how it is blurred, known before any sample (``on_input``).

    Attributes:
        input: the input folder, or None for the built-in photo.
        layout: its layout in words (photos; GOPRO_Large_all (GOPRxxxx_yy_zz/*.png); ...).
        sequences: frame sequences in it (averaged in mode average, else taken as photos).
        images: the frames averaged, the photos or the blurred images found.
        samples: the samples the input gives.
        taking: the samples this run's set holds (``limit`` taken into account).
        mode: ``blur.mode``.
        blur: the blur mode in words, with the frames per blur in mode average.
    """

    input: Path | None
    layout: str
    sequences: int
    images: int
    samples: int
    taking: int
    mode: str
    blur: str

    def lines(self) -> tuple[str, str]:
        """``gpu-blur generate``'s two lines: ``input: ...`` and ``blur: ...``."""
        def count(n: int, what: str) -> str:
            return f"{n} {what}{'' if n == 1 else 's'}"

        what = {"average": "frame", "none": "image"}.get(self.mode, "photo")
        held = count(self.images, what)
        if self.sequences:
            held = f"{count(self.sequences, 'sequence')}, {held}"
        limit = f", taking {self.taking} (--limit)" if self.taking < self.samples else ""
        found = (f"{self.input}: {self.layout}; {held}" if self.input is not None
                 else self.layout)
        return (f"input: {found} -> {count(self.samples, 'sample')}{limit}",
                f"blur: {self.blur}")


def blur_in_words(scene, found) -> str:
    """The scene's blur mode as ``generate`` prints it (``found``: the input's Samples)."""
    from gpu_blur.discovery import GOPRO_NAME
    from gpu_blur.scene import FROM_NAME, PER_SEQUENCE

    b = scene.blur
    if b.mode == "average":
        if b.frames == FROM_NAME:
            counts = sorted({int(m[2]) for f in found.sequences
                             if (m := GOPRO_NAME.fullmatch(f.folder.name))})
            here = (f"{counts[0]}" if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"
                    ) if counts else "none"
            frames = (f"yy consecutive frames per sample, yy from each sequence's name "
                      f"GOPRxxxx_yy_zz (blur.frames = '{FROM_NAME}'; here {here})")
        else:
            frames = f"{b.frames} consecutive frames per sample"
        raised = ("" if b.interpolation == 1 else ", the frame rate raised 1, 2, 4 or 8x per "
                  "gap by interpolation (blur.interpolation = 'auto')"
                  if isinstance(b.interpolation, str) else
                  f", the frame rate raised {b.interpolation}x by interpolation")
        apart = f", windows {b.stride} frames apart (blur.stride)" if b.stride else ""
        shared = (f", camera settings drawn once per sequence (blur.draws = '{PER_SEQUENCE}')"
                  if b.draws == PER_SEQUENCE else "")
        return f"average of {frames}{raised}{apart}{shared}"
    if b.mode == "kernel":
        with_what = f"the kernel {b.kernel}" if b.kernel else "a random motion kernel per sample"
        return f"kernel: each photo convolved with {with_what}"
    if b.mode == "trajectory":
        return "trajectory: camera shake over each photo"
    return "none: the input images are blurred already (saturation, noise and ISP only)"


@dataclasses.dataclass(frozen=True)
class SetReport:
    """What a finished :func:`generate_set` made, and where its time went.

    Attributes:
        output: the set's folder.
        manifest: its ``manifest.jsonl``.
        device: the device the samples ran on (as ``gpu-blur generate`` names it).
        made: samples made and written by this run.
        failed: the manifest lines of the samples that failed (``index``, ``name``,
            ``error``, ...); fix their inputs and run again with ``resume=True``.
        skipped: samples an earlier run had finished (``resume``), left untouched.
        to_make: samples this run set out to make (``made + len(failed)`` when it finished).
        seconds: the wall time of making and writing them.
        timings: seconds per category summed over the run (:data:`gpu_blur.timings.CATEGORIES`).
        bound: which stage bounded the run, as a line (None with ``ray``, and with
            ``devices`` and ``io_threads=1``).
        summary: the lines ``gpu-blur generate`` prints at the end (samples, samples/s, where
            the time went, the I/O threads, the bound).
    """

    output: Path
    manifest: Path
    device: str
    made: int
    failed: tuple[dict, ...]
    skipped: int
    to_make: int
    seconds: float
    timings: dict[str, float]
    bound: str | None
    summary: tuple[str, ...]


class StrictStop(RuntimeError):
    """``strict``: a spot check failed, and the run stopped there (samples made are kept)."""

    def __init__(self, index: int, name: str, error: str):
        super().__init__(f"--strict: sample {index} ({name}): {error}; the run stopped "
                         "(samples made so far are kept; --resume goes on)")
        self.index, self.name, self.error = index, name, error


class SetInterrupted(KeyboardInterrupt):
    """Ctrl-C (or a stop signal) ended the run; the samples made so far were written first.

    Attributes:
        made: new samples written by this run.
        cause: the KeyboardInterrupt that stopped it (``gpu_blur.cli``'s ``Terminated`` for
            SIGTERM and SIGHUP).
    """

    def __init__(self, made: int, cause: KeyboardInterrupt):
        super().__init__(made)
        self.made, self.cause = made, cause


def extras(save: str | Iterable[str]) -> tuple[str, ...]:
    """``save``'s outputs (a comma list or names), checked, in ``dataset.EXTRAS`` order."""
    from gpu_blur.dataset import EXTRAS

    text = save if isinstance(save, str) else ",".join(save)
    given = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in given if name not in EXTRAS]
    if unknown:
        raise ValueError(f"--save {text}: {unknown[0]!r} is not an output; allowed: a comma "
                         f"list of {', '.join(EXTRAS)}")
    return tuple(name for name in EXTRAS if name in given)


def scene_files(scene) -> dict[str, Path]:
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


def frame_cache_bytes(value: str | int | None) -> int | None:
    """``--frame-cache``'s bytes: None for the default, 0 for none, else a memory size."""
    from gpu_blur.scheduler import parse_bytes

    if value is None or str(value).strip() == "0":
        return None if value is None else 0
    try:
        return parse_bytes(value)
    except ValueError as e:
        raise ValueError(f"--frame-cache: {e}; 0 keeps no frames") from None


def _check_jpeg_decoder(o) -> None:
    """Refuse a ``--jpeg-decoder`` this run cannot use, before the backend is asked.

    The GPU decoder feeds the one-device pipeline of :func:`gpu_blur.generate.run_pipelined`;
    what it needs of the backend and libraries :func:`gpu_blur.gpu_jpeg.for_backend` checks.
    """
    from gpu_blur.generate import default_io_threads
    from gpu_blur.gpu_jpeg import JPEG_DECODERS

    decoder = getattr(o, "jpeg_decoder", "cpu")
    if decoder not in JPEG_DECODERS:
        raise ValueError(f"--jpeg-decoder {decoder}: not a decoder; give one of "
                         f"{', '.join(JPEG_DECODERS)}")
    if decoder != "gpu":
        return
    if o.devices is not None or o.ray is not None:
        raise ValueError(f"--jpeg-decoder gpu decodes in a run on one device, not with "
                         f"--{'devices' if o.devices is not None else 'ray'}: leave one out")
    if (o.io_threads or default_io_threads()) == 1:
        raise ValueError("--jpeg-decoder gpu decodes in the pipeline of I/O threads, and this "
                         "run has one thread (--io-threads 1, or a host of one core): give "
                         "--io-threads 2 or more, or leave --jpeg-decoder at cpu")


def early_workers(o, job):
    """The ``--devices`` workers, started before the run's set-up where the names are known.

    They import gpu_blur and open their devices (a second each on a GPU: Warp's import and
    start-up, a CUDA context) while the driver opens its own, reads the input and the output
    folder. A list names them; ``--devices all`` as counted cheaply
    (:func:`gpu_blur.distributed.counted_devices`: numpy, and Warp's CUDA devices), else
    they start later, once the devices are known (an OpenCL backend, Warp without CUDA); so
    does a run without ``--devices`` or with ``--ray`` (None). The names are checked
    afterwards (:func:`gpu_blur.distributed.parse_devices`): a bad one stops them, and
    workers started for another list than ``all`` stands for are stopped
    (:meth:`_Run._set_up`).
    """
    from gpu_blur.distributed import DeviceWorkers, counted_devices

    if o.devices is None or o.ray is not None:
        return None
    if o.devices.strip() == "all":
        names = counted_devices(o.backend)
        if names is None:
            return None
    else:
        names = [name.strip() for name in o.devices.split(",")]
    if not all(names):
        return None  # refused by parse_devices, naming the empty name
    return DeviceWorkers(job, names, o.io_threads)


def check_setup(o, scene) -> None:
    """Fail before any sample for what every sample would fail on (``o``: the options)."""
    from gpu_blur.cameras import scene_camera
    from gpu_blur.kernel_files import read_kernel
    from gpu_blur.planning import raw_round_trip
    from gpu_blur.scheduler import check_tile
    from gpu_blur.set_formats import check_format

    check_format(getattr(o, "format", "png"), getattr(o, "shard_size", None), scene.output.bits)
    if not 0 <= o.seed < 2**64:
        raise ValueError(f"--seed {o.seed}: must lie in [0, 2**64)")
    if o.tile:
        check_tile(o.tile, "--tile")
    if (o.samples_per_photo is not None and o.samples_per_photo < 1) or (
            o.limit is not None and o.limit < 1):
        raise ValueError("--samples-per-photo and --limit must be >= 1")
    if o.samples_per_sequence is not None and o.samples_per_sequence < 1:
        raise ValueError(f"--samples-per-sequence {o.samples_per_sequence}: must be >= 1")
    if o.input is not None and o.input.resolve().is_relative_to(o.output.resolve()):
        raise ValueError(f"--input {o.input} is --output {o.output} or lies inside it, "
                         "where generate writes and removes the set's files; give an --output "
                         "outside the input (one inside it is fine: it is left out of the "
                         "input)")
    if o.io_threads is not None and o.io_threads < 1:
        raise ValueError(f"--io-threads {o.io_threads}: must be >= 1 (1: no I/O threads)")
    frame_cache_bytes(getattr(o, "frame_cache", None))
    _check_jpeg_decoder(o)
    if not 0.0 <= o.verify <= 1.0:
        raise ValueError(f"--verify {o.verify}: the fraction of tiles to check, 0 to 1")
    if "raw" in extras(o.save) and not raw_round_trip(scene):
        where = f"scene file {scene.path}" if scene.path else "the scene"
        raise ValueError(f"--save raw: {where} has no RAW round trip (noise.model = "
                         f"{scene.noise.model!r}, isp.round_trip = {scene.isp.round_trip!r}); "
                         "set noise.model = 'poisson-gaussian' or isp.round_trip = 'always', "
                         "or leave raw out of --save")
    if o.strict and not o.verify:
        raise ValueError("--strict stops the run at the first spot-check mismatch; give "
                         "--verify FRACTION too")
    if o.max_device_memory is not None:
        from gpu_blur.planning import plan
        from gpu_blur.scheduler import check_budget

        numpy = o.backend.split(":")[0] == "numpy"
        check_budget(o.max_device_memory, plan(scene),
                     "float64" if numpy else scene.output.precision)
    # an unknown camera name, a bad camera file, a response float32 kernels cannot evaluate
    scene_camera(scene, o.backend.split(":")[0])
    kernel = scene_files(scene).get("blur.kernel")
    if kernel is not None:
        try:
            read_kernel(kernel)
        except ValueError as e:
            raise ValueError(f"scene file {scene.path}: {e}" if scene.path else str(e)) from None


def _cannot_write(output: Path, spec, error: OSError) -> OSError:
    """The error that stops a run which cannot write a sample: the sample and the way out."""
    return OSError(f"--output {output}: cannot write sample {spec.index} ({spec.name}): "
                   f"{error}; the samples finished so far are kept: free space or fix the "
                   "folder, then run the same command with --resume")


def generate_set(
    output: str | os.PathLike, *, input: str | os.PathLike | None = None,
    scene: str | os.PathLike | dict | None = None, seed: int = 0, backend: str = "numpy",
    devices: str | None = None, ray: str | None = None, gpus_per_task: float | None = None,
    retries: int | None = None, ray_batch: int | None = None, io_threads: int | None = None,
    tile: Sequence[int] | None = None, max_device_memory: str | int | None = None,
    frame_cache: str | int | None = None, jpeg_decoder: str = "cpu", verify: float = 0.0,
    strict: bool = False, samples_per_photo: int | None = None,
    samples_per_sequence: int | None = None, limit: int | None = None,
    save: str | Iterable[str] = "", format: str = "png", shard_size: int | None = None,
    overwrite: bool = False, resume: bool = False, average_gopro_large_sharp: bool = False,
    frames_as_photos: bool = False,
    progress: Progress = False, on_device: Callable[[str], None] | None = None,
    on_resume: Callable[[ResumeState], None] | None = None,
    on_input: Callable[[InputFound], None] | None = None,
) -> SetReport:
    """Make a data set of blurred/sharp pairs and its manifest, as ``gpu-blur generate`` does.

    Every keyword but the last four is the command's option of that name (``gpu-blur
    generate --help`` says more); the files are the command's, byte for byte.

    Args:
        output: the set's folder (blur/, sharp/, params/, manifest.jsonl, run.json).
        input: a folder of sequences, photos or blurred images; None: the built-in photo.
        scene: a scene TOML, a built-in scene's name or a dict of sections; None: default.
        seed: the set's seed, in [0, 2**64).
        backend: numpy, opencl, opencl:P:D, warp, warp:cpu, warp:cuda:N.
        devices: one worker process per device of this host ("all" or a comma list).
        ray: a Ray cluster's address ("auto"); with gpus_per_task, retries, ray_batch.
        gpus_per_task: GPUs each Ray task asks for.
        retries: times a failed Ray task runs again (default 3).
        ray_batch: samples per Ray task.
        io_threads: threads that decode and write beside synthesis (1: none).
        tile: (rows, cols): run each image in tiles of at most that size.
        max_device_memory: device memory one tile's passes may hold ("2G", bytes).
        frame_cache: host memory for decoded frames that several samples read ("2G", bytes;
            0: none; default 1/8 of physical memory, at most 1 GiB), used where they do.
        jpeg_decoder: ``"cpu"`` (OpenCV) or ``"gpu"`` (nvJPEG through torchvision, a Warp
            CUDA backend; pixels may differ by a few codes): :mod:`gpu_blur.gpu_jpeg`.
        verify: fraction of tiles recomputed by the numpy reference and compared.
        strict: stop at the first spot-check mismatch (raises :class:`StrictStop`).
        samples_per_photo: samples drawn from each photo (default 1; 4 for the built-in one).
        samples_per_sequence: blur.mode average: windows per sequence.
        limit: make at most this many samples.
        save: further outputs, ``"mask,raw"`` or ``["mask", "raw"]``.
        format: how the samples are stored: ``"png"`` (files), ``"lmdb"`` (BasicSR's
            paired LMDB) or ``"webdataset"`` (tar shards); :mod:`gpu_blur.set_formats`.
        shard_size: with ``format="webdataset"``, samples per shard (default 100).
        overwrite: replace an existing set in ``output``.
        resume: finish the set in ``output`` that a run with the same settings started.
        average_gopro_large_sharp: blur.mode average over GOPRO_Large's ``<seq>/sharp/``
            frames (beside ``<seq>/blur/``), refused without it: they are one ground-truth
            frame per blurred image, with gaps between them (use GOPRO_Large_all).
        frames_as_photos: a photo mode (trajectory, kernel) over an input of frame sequences,
            each frame taken as a photo; refused without it.
        progress: True: a progress bar on standard error; a callable: ``progress(done,
            total)`` as each sample comes back; default: nothing.
        on_device: called with the device's description once the backend is open, before
            the options are checked.
        on_resume: with ``resume``, called with a :class:`ResumeState` before the first sample.
        on_input: called with an :class:`InputFound` once the input is read, before its
            layout is checked and the output folder opened.

    Returns:
        a :class:`SetReport`; samples that failed are in ``report.failed`` (and the manifest).

    Raises:
        ValueError, OSError, RuntimeError: nothing could start (options, scene, input or
            output folder), or the run could not go on (a sample's files cannot be written).
        StrictStop: ``strict`` and a spot check failed.
        SetInterrupted: KeyboardInterrupt while samples were made (those made are written).
    """
    if devices is not None and ray is not None:
        raise ValueError("--devices and --ray exclude each other: give one")
    if overwrite and resume:
        raise ValueError("--overwrite and --resume exclude each other: give one")
    o = types.SimpleNamespace(
        output=Path(output), input=None if input is None else Path(input), scene=scene,
        seed=seed, backend=backend, devices=devices, ray=ray, gpus_per_task=gpus_per_task,
        retries=retries, ray_batch=ray_batch, io_threads=io_threads,
        tile=None if tile is None else list(tile), max_device_memory=max_device_memory,
        frame_cache=frame_cache, jpeg_decoder=jpeg_decoder, verify=verify, strict=strict,
        samples_per_photo=samples_per_photo,
        samples_per_sequence=samples_per_sequence, limit=limit, save=save, format=format,
        shard_size=shard_size, overwrite=overwrite, resume=resume,
        average_gopro_large_sharp=average_gopro_large_sharp, frames_as_photos=frames_as_photos)
    return _Run(o, progress, on_device, on_resume, on_input).run()


class _Run:
    """One :func:`generate_set` call: set up, make the samples, sum up."""

    def __init__(self, o, progress: Progress, on_device, on_resume, on_input=None):
        from gpu_blur.generate import Job
        from gpu_blur.scene import load_scene
        from gpu_blur.scheduler import Schedule

        self.o, self.progress = o, progress
        scene = self.scene = load_scene(o.scene)
        check_setup(o, scene)
        # the Schedule rides in Job.tile (tile, memory budget, spot checks; see pipeline)
        self.schedule = Schedule(tuple(o.tile) if o.tile else None, o.max_device_memory,
                                 o.verify)
        self.extras = extras(o.save)
        self.job = Job(scene, o.seed, o.backend, self.schedule, "raw" in self.extras,
                       bits=scene.output.bits, with_mask="mask" in self.extras)
        self.workers = early_workers(o, self.job)
        try:
            self._set_up(on_device, on_resume, on_input)
        except BaseException:  # the workers started for nothing
            if self.workers is not None:
                self.workers.stop()
            raise

    def _set_up(self, on_device, on_resume, on_input) -> None:
        from gpu_blur.backends import get_backend
        from gpu_blur.discovery import BUILT_IN_INPUT, check_layout, find_samples
        from gpu_blur.distributed import pick_executor
        from gpu_blur.gpu_jpeg import for_backend
        from gpu_blur.png_codecs import encoder_name
        from gpu_blur.run_record import library_versions
        from gpu_blur.set_formats import format_record, writer

        o, scene = self.o, self.scene
        self.backend = get_backend(o.backend, scene.output.precision)  # fails before any work
        if on_device is not None:
            on_device(self.backend.device)
        self.jpeg = (for_backend(self.backend, scene.blur.mode == "average")
                     if o.jpeg_decoder == "gpu" else None)
        self.executor = pick_executor(o, scene.output.precision)  # serial, devices or ray
        #: --devices' workers' devices (the executor is run_devices), else None
        self.devices = getattr(self.executor, "keywords", {}).get("devices")
        if self.workers is not None and self.workers.devices != self.devices:
            self.workers.stop()  # --devices all stands for others than counted: started anew
            self.workers = None
        per_photo = o.samples_per_photo or (1 if o.input else 4)
        where = (f"scene file {scene.path}" if scene.path
                 else "the default scene" if o.scene is None else "the scene")
        found = find_samples(o.input, scene.blur.mode, scene.blur.frames, per_photo,
                             o.samples_per_sequence, exclude=o.output,
                             masks=scene.saturation.mode != "off", where=where,
                             stride=scene.blur.stride)
        if on_input is not None:
            on_input(InputFound(o.input, found.layout, len(found.sequences), found.images,
                                found.total, min(found.total, o.limit or found.total),
                                scene.blur.mode, blur_in_words(scene, found)))
        check_layout(found, o.input, scene.blur.mode, where,
                     average_gopro_large_sharp=o.average_gopro_large_sharp,
                     frames_as_photos=o.frames_as_photos)
        specs = found.take(o.limit)
        # how samples run and are stored, never what they give: recorded, not checked by
        # resume (which keeps the first run's record); the PNG encoder says whose bytes the
        # files are (output.png = "fastest"'s may vary, fast's never)
        how = {"tile": list(self.schedule.tile) if self.schedule.tile else None,
               "max_device_memory": self.schedule.max_device_memory,
               "verify": self.schedule.verify,
               "png_encoder": encoder_name(scene.output.png) if scene.output.bits else None}
        scene_file = (str(o.scene) if o.scene is not None and not isinstance(o.scene, dict)
                      else None)
        run = {"seed": o.seed, "backend": o.backend, "device": self.backend.device,
               "input": str(o.input) if o.input else BUILT_IN_INPUT, **how,
               "samples_per_photo": per_photo, "samples_per_sequence": o.samples_per_sequence,
               "scene_file": scene_file, "scene": scene.to_dict(),
               "files": {key: hashlib.sha256(path.read_bytes()).hexdigest()
                         for key, path in scene_files(scene).items()},
               "libraries": library_versions(o.backend)}
        if self.jpeg:  # absent for the CPU's decoder, as sets made before the option record it
            run["jpeg_decoder"] = o.jpeg_decoder
            run["libraries"].update(self.jpeg.libraries)
        if self.extras:  # absent without save, as sets made before it record it
            run["save"] = list(self.extras)
        run.update(format_record(o.format, o.shard_size))  # absent for PNG, as sets before
        self.writer = writer(o.format, o.shard_size)(
            o.output, scene.output.bits, run, overwrite=o.overwrite, resume=o.resume,
            specs=specs, total=found.total, extras=self.extras, png=scene.output.png)
        self.todo = [s for s in specs if s.index not in self.writer.done]
        self.done = len(specs) - len(self.todo)
        if o.resume and on_resume is not None:
            on_resume(ResumeState(self.done, len(specs), len(self.todo), self.writer.retry,
                                  self.writer.torn))
        self.record = {"seed": o.seed, "backend": o.backend, "device": self.backend.device,
                       **how}
        self.failed: list[dict] = []
        self.made = 0

    def save(self, spec, result) -> dict:
        """A made sample's files (in an I/O thread if there are), its manifest line back.

        A ``--devices`` worker that wrote them itself sent the line (:class:`Saved`).
        """
        from gpu_blur.dataset import sample_record
        from gpu_blur.generate import Saved

        try:
            if isinstance(result, Saved):
                if result.error is not None:
                    raise result.error
                return result.line
            return self.writer.save(spec, result, sample_record(self.record, result) | (
                self.jpeg.record(spec) if self.jpeg else {}))
        except OSError as e:
            raise _cannot_write(self.o.output, spec, e) from None

    def finish(self, spec, error, line) -> None:
        """Each sample once written, in order: into the manifest, made or failed."""
        from gpu_blur.scheduler import SPOT_CHECK_FAILED

        try:
            if error is not None:  # this sample's input: record it, go on
                checked = {"spot_check": "failed"} if error.startswith(
                    SPOT_CHECK_FAILED) else {}
                self.failed.append(self.writer.fail(spec, error, self.record | checked))
            else:
                self.writer.add(line)
                self.made += 1
        except OSError as e:  # a full disk, a folder gone
            raise _cannot_write(self.o.output, spec, e) from None
        testhooks.sleep_after(spec.index)

    def _watched(self, samples):
        """The executor's samples, through the progress bar or callback if asked."""
        if self.progress is True:
            from tqdm import tqdm

            yield from tqdm(samples, total=len(self.todo), desc="samples", unit="sample")
            return
        for count, sample in enumerate(samples, 1):
            yield sample
            if callable(self.progress):
                self.progress(count, len(self.todo))

    def run(self) -> SetReport:
        """Make the samples to do, write them, and sum up."""
        from gpu_blur.generate import (
            QUEUE_PER_THREAD,
            WriteBehind,
            default_io_threads,
            pinned_staging,
            run_pipelined,
            run_serial,
        )
        from gpu_blur.scheduler import SPOT_CHECK_FAILED
        from gpu_blur.timings import PoolTimes, RunTotals, current, timer

        o, writer = self.o, self.writer
        totals, writing = RunTotals(), current().seconds["writing"]
        devices = self.devices is not None
        # --devices into a set of files: the workers write them, in their threads
        writes = writer.folder_writes(self.record) if devices else None
        threads = o.io_threads or default_io_threads()
        if writes is not None:  # the workers' threads are counted as they report them
            io, pool = PoolTimes(0), None
        else:
            io = PoolTimes(threads) if threads > 1 else None  # else one thread does every step
            pool = ThreadPoolExecutor(threads, thread_name_prefix="gpu-blur-io") if io else None
        behind = WriteBehind(self.save, pool, QUEUE_PER_THREAD * threads, io)
        stop: StrictStop | SetInterrupted | None = None
        samples = watched = None
        ended = False
        start = time.perf_counter()
        job = self.job
        try:
            # one device: the pool also decodes ahead; devices and ray workers decode their
            # own inputs (device workers through shares of the frame cache), and the pool
            # encodes and writes what they make, unless device workers write it themselves
            cache = self.frame_cache() if self.executor is run_serial or devices else None
            samples = (run_pipelined(job, self.todo, pool, io, QUEUE_PER_THREAD * threads, cache,
                                     pinned_staging(job), jpeg=self.jpeg)
                       if io and self.executor is run_serial else
                       run_serial(job, self.todo, cache) if self.executor is run_serial else
                       self.executor(job, self.todo, frame_cache=cache, pool_times=io,
                                     writes=writes, io_threads=o.io_threads,
                                     workers=self.workers)
                       if devices else
                       self.executor(job, self.todo))
            # kept in a name: after a strict stop the progress bar closes once the stop is
            # dropped (its message is then on the screen above it)
            watched = self._watched(samples)
            for spec, result, error in watched:
                if error is None:
                    totals.add(result.timings)
                with timer("writing"):
                    for written in behind.put(spec, result, error):
                        self.finish(*written)
                if o.strict and error is not None and error.startswith(SPOT_CHECK_FAILED):
                    with timer("writing"):
                        for written in behind.drain():
                            self.finish(*written)
                    stop = StrictStop(spec.index, spec.name, error)
                    break
            else:
                with timer("writing"):
                    for written in behind.drain():
                        self.finish(*written)
            ended = True
        except KeyboardInterrupt as e:
            if watched is not None:  # the progress bar ends before the samples are written
                watched.close()
            # the samples made so far are written first; a second Ctrl-C or a failing write
            # stops that (resume makes them again)
            with contextlib.suppress(KeyboardInterrupt, OSError):
                for written in behind.drain():
                    self.finish(*written)
            # those whose lines wait for an earlier sample's are dropped: made again on resume
            stop, ended = SetInterrupted(self.made - writer.held_back, e), True
        finally:
            # no thread or worker may write once the folder's lock is released
            if samples is not None:  # an executor's workers stop (device workers write)
                samples.close()
            if self.workers is not None:  # started, though never handed the samples
                self.workers.stop()
            if pool is not None:
                pool.shutdown(cancel_futures=True)
            if not ended:  # the error that stopped the run is the one to report, not a flush
                with contextlib.suppress(OSError):
                    writer.close()
        self._close(stop)
        if stop is not None:
            raise stop from getattr(stop, "cause", None)
        took = time.perf_counter() - start
        totals.add({"writing": current().seconds["writing"] - writing
                    + (io.waited_for_writes if io else 0.0),
                    "reading": io.waited_for_inputs if io else 0.0})
        return self._report(took, totals, io, run_serial, cache)

    def frame_cache(self):
        """A frame cache where samples share input files, else None.

        Samples share files where windows of a sequence overlap or a photo is drawn several
        times (:class:`~gpu_blur.frame_cache.FrameCache`).
        """
        from gpu_blur.frame_cache import FrameCache, default_budget

        budget = frame_cache_bytes(self.o.frame_cache)
        uses = collections.Counter(path for spec in self.todo for path in spec.inputs)
        if budget == 0 or not any(count > 1 for count in uses.values()):
            return None
        return FrameCache(default_budget() if budget is None else budget)

    def _close(self, stop) -> None:
        """Close the writer; a failing close after a stop names the stop as its cause."""
        try:
            self.writer.close()
        except OSError as e:
            if stop is None:
                raise
            raise e from stop

    def _report(self, took: float, totals, io, run_serial, cache=None) -> SetReport:
        o, writer = self.o, self.writer
        if io is not None and not io.threads:  # device workers of one thread each, in turn
            io = None
        before = f", {self.done} were done before" if self.done else ""
        lines = [f"wrote {self.made} samples ({len(self.failed)} failed) to {o.output} in "
                 f"{took:.1f} s ({self.made / max(took, 1e-9):.2f} samples/s){before}; "
                 f"manifest: {writer.manifest_path}"]
        lines += totals.summary(took, on_host=self.backend.name == "numpy")
        if io is not None:
            lines.append(io.summary(took))
            handoff = io.handoff_summary()
            if handoff:
                lines.append(handoff)
        if cache is not None:
            lines.append(cache.counts().summary())
        if self.jpeg:
            lines.append(self.jpeg.summary())
        # the waits for inputs are this thread's, or (--devices) the workers' in io; Ray's
        # tasks send none back
        devices = getattr(self.executor, "keywords", {}).get("devices")
        bound = (totals.bound(took, io) if self.executor is run_serial else
                 totals.bound(took, io, len(devices)) if devices and io else None)
        if bound is not None:
            lines.append(bound)
            output = self.scene.output
            if (bound.startswith("bound by: encode/write") and output.bits in (8, 16)
                    and output.png != "stored"):
                if output.png == "fast":
                    lines.append('  output.png = "fastest" compresses with ISA-L, faster, but '
                                 "a file's bytes may differ from run to run (its pixels never)")
                lines.append(f'  output.png = "stored" (now "{output.png}") writes these PNGs '
                             "uncompressed: several times less CPU a file, up to 1.7 times the "
                             "bytes; faster only where memory and disk keep up, so measure "
                             "(docs: performance, PNG codecs)")
        return SetReport(output=o.output, manifest=Path(writer.manifest_path),
                         device=self.backend.device, made=self.made, failed=tuple(self.failed),
                         skipped=self.done, to_make=len(self.todo), seconds=took,
                         timings=dict(totals.seconds), bound=bound, summary=tuple(lines))
