"""Accuracy against time: what each accuracy knob of the pipeline costs, on every backend.

``gpu-blur bench`` (and ``bench/accuracy_vs_time.py``) runs one fixed input, 9 frames made
from the built-in photograph (upscaled, the camera panning :data:`PAN_PX` pixels per frame),
through :func:`gpu_blur.synthesize` for every setting of every knob in :data:`KNOBS`, on numpy
(the float64 reference) and on every OpenCL and Warp device present, and reports for each:

* **time**: milliseconds per megapixel of output, the median of at least :data:`MIN_RUNS` runs
  after one warm-up run (which builds the kernels). Frames start in host memory and the result
  ends there, so every device is synchronized before the clock stops;
* **error of the final image without noise** (``noise.model = "none"`` with the RAW round trip
  kept, ``isp.round_trip = "always"``): max abs error and PSNR against the numpy float64 run of
  the knob's accurate setting (its ``reference``), float output (``output.bits = 0``) so that
  errors below one 8-bit code show;
* **noise**: the KL divergence between the residuals (final image with noise minus the same
  run without noise, same seed and sample index) of the reference and of this run, RSBlur's
  measure of noise realism (supplementary Sec. 13; :func:`gpu_blur.metrics.histogram_kl`,
  one bin per 8-bit code).

A knob whose scene key or value is not offered (the scene refuses it) is reported as not
available, as is a run that fails on one backend (with its error). Side by side, from the
same run: our demosaicing against OpenCV's and colour-demosaicing's, our kernel blur against
``cv2.filter2D``, and every backend's whole pipeline against the numpy reference.

Outputs: ``accuracy_vs_time_<tag>.json`` (every number and the devices),
``accuracy_vs_time_<tag>.md`` (the tables) and ``accuracy_vs_time_<tag>.png`` (error against
time, one series per backend and device, the Pareto front marked).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import re
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

#: The input's size, width x height, and frame count (blur.mode = "average").
DEFAULT_SIZE = (1920, 1200)
FRAMES = 9
#: Pixels the camera pans right per frame: each frame is a window of the upscaled photo.
PAN_PX = 2
#: Every run draws the same values: the errors compare like with like.
SEED, SAMPLE_INDEX = 1, 0
#: Timed runs per measurement, after one warm-up (issue 7: at least 5).
MIN_RUNS = 5
#: The smallest --size side: the side-by-side border, the 29-tap kernel and the 8 x 8 optical
#: flow patches need some room.
MIN_SIDE = 32

#: The base scene, close to RSBlur's synthesis: 9 frames averaged, saturation on, the A7R3
#: camera's Poisson-Gaussian noise on the RAW mosaic, Malvar 2004, re-toned with the A7R3
#: response; float output so errors below one 8-bit code show.
BASE_SCENE = {
    "blur": {"mode": "average", "frames": FRAMES},
    "saturation": {"mode": "on"},
    "camera": {"name": "a7r3"},
    "noise": {"model": "poisson-gaussian"},
    "isp": {"demosaic": "malvar2004"},
    "output": {"crf": "a7r3", "bits": 0},
}
#: Added for the error runs: no noise, but the RAW round trip (mosaic, demosaic) still runs.
NOISE_FREE = {"noise": {"model": "none"}, "isp": {"round_trip": "always"}}
#: Scene keys the numpy reference ignores (it always runs float64 with precise maths).
KERNEL_ONLY_KEYS = (("output", "precision"), ("output", "fast_math"))
#: Residual histograms: bins per unit of value, one per 8-bit code (gpu_blur.metrics).
KL_BINS = 255
#: Side-by-side demosaic errors leave out this many pixels at every edge: border rules differ
#: (OpenCV's own border handling; ours mirrors the mosaic keeping the Bayer phase).
BORDER_PX = 8
#: Side-by-side kernel blur: a random motion kernel of this size (the largest GoPro_U size,
#: scene key blur.kernel_size).
KERNEL_SIZE = 29
#: The side-by-side mosaic's Bayer order.
PATTERN = "RGGB"


@dataclasses.dataclass(frozen=True)
class Setting:
    """One setting of one accuracy knob.

    Attributes:
        knob: the knob's name (rows of one knob compare against one reference).
        label: the setting, in words.
        scene: scene overrides over :data:`BASE_SCENE`, ``{section: {key: value}}``.
        tile: run in tiles of at most (rows, columns) pixels, or None for the whole image.
        reference: the knob's accurate setting: its numpy float64 run is the reference.
    """

    knob: str
    label: str
    scene: dict = dataclasses.field(default_factory=dict)
    tile: tuple[int, int] | None = None
    reference: bool = False

    @property
    def kernel_only(self) -> bool:
        """Whether only kernel backends see this setting (numpy ignores it)."""
        keys = [(s, k) for s, keys in self.scene.items() for k in keys]
        return self.tile is not None or bool(keys) and all(k in KERNEL_ONLY_KEYS for k in keys)


#: The base scene itself (the side-by-side pipeline rows).
BASE = Setting("base", "base scene")


def _lut(nodes: int) -> dict:
    return {"output": {"crf": "a7r3-lut", "crf_table_size": nodes}}


def _normal_above(rate: float) -> dict:
    return {"noise": {"poisson": "normal", "normal_above": rate}}


#: Every knob setting, each knob's accurate (reference) setting first. ``--quick`` keeps the
#: first two settings of each knob.
KNOBS: tuple[Setting, ...] = (
    Setting("precision", "float64", {"output": {"precision": "float64"}}, reference=True),
    Setting("precision", "float32", {"output": {"precision": "float32"}}),
    Setting("precision", "float16 storage", {"output": {"precision": "float16"}}),
    Setting("demosaic", "Malvar 2004", {"isp": {"demosaic": "malvar2004"}}, reference=True),
    Setting("demosaic", "bilinear", {"isp": {"demosaic": "bilinear"}}),
    # The authors' table is another curve than their polynomial (up to 0.0071 apart,
    # gpu_blur.reference.transfer.a7r3_lookup_table), so the tables' resolution is a knob of
    # its own, against the authors' table.
    Setting("CRF", "polynomial", {"output": {"crf": "a7r3"}}, reference=True),
    Setting("CRF", "authors' table", _lut(0)),
    Setting("CRF table", "2,551 nodes (authors')", _lut(0), reference=True),
    Setting("CRF table", "4,096 nodes", _lut(4096)),
    Setting("CRF table", "1,024 nodes", _lut(1024)),
    Setting("CRF table", "256 nodes", _lut(256)),
    Setting("maths", "precise", {"output": {"fast_math": False}}, reference=True),
    Setting("maths", "fast", {"output": {"fast_math": True}}),
    Setting("Poisson", "exact", {"noise": {"poisson": "exact"}}, reference=True),
    Setting("Poisson", "normal above 1000", _normal_above(1000.0)),
    Setting("Poisson", "normal above 100", _normal_above(100.0)),
    Setting("Poisson", "normal above 10", _normal_above(10.0)),
    Setting("motion", "interpolation 8x", {"blur": {"interpolation": 8}}, reference=True),
    Setting("motion", "interpolation 4x", {"blur": {"interpolation": 4}}),
    Setting("motion", "interpolation 2x", {"blur": {"interpolation": 2}}),
    Setting("motion", "interpolation 1x", {"blur": {"interpolation": 1}}),
    Setting("tile", "whole image", reference=True),
    Setting("tile", "1024 x 1024", tile=(1024, 1024)),
    Setting("tile", "512 x 512", tile=(512, 512)),
    Setting("tile", "256 x 256", tile=(256, 256)),
)


def quick_knobs(knobs: Sequence[Setting] = KNOBS) -> list[Setting]:
    """The first two settings of every knob (its reference and one other)."""
    seen: dict[str, int] = {}
    kept = []
    for s in knobs:
        seen[s.knob] = seen.get(s.knob, 0) + 1
        if seen[s.knob] <= 2:
            kept.append(s)
    return kept


def select_knobs(names: Sequence[str], knobs: Sequence[Setting] = KNOBS) -> list[Setting]:
    """The settings of the named knobs (names as in the table, any case).

    Raises:
        ValueError: naming an unknown knob and the known ones.
    """
    known = {s.knob.lower(): s.knob for s in knobs}
    unknown = [n for n in names if n.lower() not in known]
    if unknown or not names:
        raise ValueError(f"--knobs: {', '.join(unknown) or 'none given'}; known: "
                         f"{', '.join(dict.fromkeys(known.values()))}")
    wanted = {known[n.lower()] for n in names}
    return [s for s in knobs if s.knob in wanted]


def merge(*layers: dict) -> dict:
    """Scene dicts merged section by section, later layers winning."""
    out: dict = {}
    for layer in layers:
        for section, values in layer.items():
            out.setdefault(section, {}).update(values)
    return out


# -- input ------------------------------------------------------------------------------------

def make_frames(width: int, height: int, frames: int = FRAMES) -> list[np.ndarray]:
    """The benchmark's input: windows of the upscaled built-in photo, panning right.

    The photo (600 x 400, :func:`gpu_blur.dataset.default_photo`) is upscaled with bicubic
    interpolation until a ``width x height`` window fits ``(frames - 1) * PAN_PX`` times
    side by side; frame ``i`` starts ``i * PAN_PX`` pixels right of frame 0.

    Returns:
        ``frames`` arrays of ``height x width x 3`` uint8 sRGB codes (R, G, B).
    """
    import cv2

    from gpu_blur.dataset import default_photo
    from gpu_blur.imageio import read_image

    photo = read_image(default_photo())
    pan = (frames - 1) * PAN_PX
    scale = max((width + pan) / photo.shape[1], height / photo.shape[0])
    size = (math.ceil(photo.shape[1] * scale), math.ceil(photo.shape[0] * scale))
    big = cv2.resize(photo, size, interpolation=cv2.INTER_CUBIC)
    y0 = (big.shape[0] - height) // 2
    return [np.ascontiguousarray(big[y0:y0 + height, i * PAN_PX:i * PAN_PX + width])
            for i in range(frames)]


# -- backends -----------------------------------------------------------------------------------

def cpu_name() -> str:
    """The host CPU's model name (``/proc/cpuinfo``), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def source_commit() -> str | None:
    """The git commit of the gpu_blur source that runs (``+modified`` when files differ).

    None when the package does not sit in a git checkout (an installed wheel).
    """
    import subprocess

    root = Path(__file__).resolve().parents[1]

    def git(*args):
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD")
        modified = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+modified" if modified else "")


def source_digest() -> str:
    """SHA-256 of the code that runs: every file under gpu_blur/ and kernels/, by path.

    A commit names the code only where the checkout's git metadata is its own (a copy of the
    tree on another machine may carry stale metadata); the digest of the files themselves can
    be checked against any commit (``git worktree add``, then this function there).
    """
    import hashlib

    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for folder in ("gpu_blur", "kernels"):
        for path in sorted((root / folder).rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                digest.update(path.relative_to(root).as_posix().encode() + b"\0")
                digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


def available_backends() -> dict[str, dict]:
    """Every backend of this host that can run: spec -> {device, kind, fp64}.

    numpy, every OpenCL device that builds kernels, every Warp device; a backend whose Python
    package is missing is left out.
    """
    found = {"numpy": {"device": f"numpy float64 on {cpu_name()}", "kind": "CPU",
                       "fp64": True}}
    try:
        from gpu_blur.backends.opencl import opencl_devices
    except ImportError:
        pass
    else:
        for d in opencl_devices():
            if d.usable:
                found[d.spec] = {"device": f"{d.kind} {d.name} ({d.platform})", "kind": d.kind,
                                 "fp64": d.fp64}
    try:
        from gpu_blur.backends.warp import warp_devices
    except ImportError:
        pass
    else:
        for d in warp_devices():
            name = cpu_name() if d["kind"] == "CPU" else d["name"]  # Warp names its CPU "CPU"
            found[d["spec"]] = {"device": f"{d['kind']} {name} (Warp)", "kind": d["kind"],
                                "fp64": d["fp64"]}
    return found


def choose_backends(wanted: Sequence[str] | None) -> dict[str, dict]:
    """The backends to run: ``wanted`` (numpy always first: it is the reference), or all.

    Raises:
        ValueError: naming a wanted backend that is not present and the ones that are.
    """
    present = available_backends()
    if not wanted:
        return present
    unknown = [w for w in wanted if w not in present]
    if unknown:
        raise ValueError(f"--backends: {', '.join(unknown)} not present (or cannot build "
                         f"kernels); present: {', '.join(present)} (see gpu-blur devices)")
    return {s: present[s] for s in ["numpy", *[w for w in wanted if w != "numpy"]]}


def device_tag(backends: dict[str, dict]) -> str:
    """Output file tag: ``cpu`` when no GPU runs, else the first GPU's name as a slug."""
    gpus = [b["device"] for b in backends.values() if b["kind"] == "GPU"]
    if not gpus:
        return "cpu"
    name = gpus[0].split("(")[0].removeprefix("GPU ")  # "GPU NVIDIA H200 (NVIDIA CUDA)"
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


# -- measurements ---------------------------------------------------------------------------

@dataclasses.dataclass
class Measurement:
    """One setting on one backend: run times and the final images with and without noise.

    Attributes:
        times_s: seconds of each timed run.
        noisy: the final image of the last timed run, H x W x 3 float32.
        clean: the same run without noise, H x W x 3 float32.
        problem: why it could not run (then the others are empty).
    """

    times_s: list[float]
    noisy: np.ndarray | None = None
    clean: np.ndarray | None = None
    problem: str = ""


def setting_scene(setting: Setting, *extra: dict):
    """The validated scene of a setting (a :class:`~gpu_blur.scene.SceneError` if refused)."""
    from gpu_blur.scene import scene_from_dict

    return scene_from_dict(merge(BASE_SCENE, setting.scene, *extra),
                           where=f"knob {setting.knob}: {setting.label}")


def measurement_key(spec: str, setting: Setting) -> str:
    """What makes two measurements the same run: backend, every scene value, tile.

    Settings that spell out a default share a run with the base scene; numpy ignores the
    kernel-only keys and tiles.

    Raises:
        gpu_blur.scene.SceneError: the setting's scene is refused.
    """
    scene = setting_scene(setting).to_dict()
    tile = setting.tile
    if spec == "numpy":
        for section, key in KERNEL_ONLY_KEYS:
            scene[section].pop(key)
        tile = None
    return json.dumps([spec, scene, tile], sort_keys=True, default=str)


def median_time(run: Callable[[], object], runs: int,
                warm_up: bool = True) -> tuple[list[float], object]:
    """Seconds of ``runs`` calls of ``run`` (after one warm-up call), and the last result.

    ``run`` must return only once its device work is done (host results).
    """
    times, result = [], run() if warm_up else None
    for _ in range(runs):
        start = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - start)
    return times, result


def measure(spec: str, frames: Sequence[np.ndarray], setting: Setting,
            runs: int, warm_up: bool = True) -> Measurement:
    """Time a setting on a backend and keep its final images with and without noise.

    A scene the setting makes is validated first (a SceneError propagates); a failure of the
    run itself (a backend that does not offer the setting) becomes ``problem``.
    """
    import gpu_blur

    scene, quiet = setting_scene(setting), setting_scene(setting, NOISE_FREE)

    def run(which):
        return gpu_blur.synthesize(frames, which, seed=SEED, sample_index=SAMPLE_INDEX,
                                   backend=spec, tile=setting.tile).blurred

    try:
        times, noisy = median_time(lambda: run(scene), runs, warm_up)
        clean = run(quiet)
    except (ValueError, RuntimeError, NotImplementedError) as e:
        return Measurement([], problem=f"{type(e).__name__}: {str(e).splitlines()[0]}")
    return Measurement(times, noisy, clean)


def _valid(setting: Setting) -> bool:
    """Whether the scene accepts the setting."""
    from gpu_blur.scene import SceneError

    try:
        setting_scene(setting)
    except SceneError:
        return False
    return True


def _finite(value: float) -> float | None:
    """A JSON-safe number: None for inf (identical images have no PSNR)."""
    return value if math.isfinite(value) else None


def errors(run: Measurement, reference: Measurement) -> dict:
    """Max abs error and PSNR of the noise-free image, and the residual KL divergence.

    Returns:
        ``max_abs_error`` (values in [0, 1]), ``psnr_db`` (None when identical) and
        ``residual_kl`` (nats, D(reference residuals || this run's residuals)).
    """
    from gpu_blur.metrics import histogram_kl, psnr

    clean = run.clean.astype(np.float64)
    expected = reference.clean.astype(np.float64)
    residuals = [m.noisy.astype(np.float64) - m.clean for m in (reference, run)]
    return {"max_abs_error": float(np.max(np.abs(clean - expected))),
            "psnr_db": _finite(psnr(expected, clean)),
            "residual_kl": histogram_kl(*residuals, bins=KL_BINS)}


class Runner:
    """Runs the knob table on the backends, measuring each distinct run once.

    Args:
        frames: the input frames.
        backends: spec -> device description (:func:`choose_backends`).
        knobs: the settings to run.
        runs: timed runs per measurement (>= :data:`MIN_RUNS`).
        log: called with one line per row as it is measured.
        reference_runs: timed runs of numpy (default ``runs``); fewer than
            :data:`MIN_RUNS` skip its warm-up (see :func:`run_benchmark`).
    """

    def __init__(self, frames, backends: dict[str, dict], knobs: Sequence[Setting],
                 runs: int, log: Callable[[str], None] = print,
                 reference_runs: int | None = None):
        self.frames, self.backends, self.knobs, self.runs = frames, backends, knobs, runs
        self.reference_runs = runs if reference_runs is None else reference_runs
        self.log = log
        self.megapixels = frames[0].shape[0] * frames[0].shape[1] / 1e6
        self._cache: dict[str, Measurement] = {}
        # runs that some knob compares against: their images stay in memory
        self._keep = {measurement_key(spec, s) for spec in backends
                      for s in [*[s for s in knobs if s.reference and _valid(s)], BASE]}

    def get(self, spec: str, setting: Setting) -> Measurement:
        """The measurement of ``setting`` on ``spec`` (measured now unless already held)."""
        key = measurement_key(spec, setting)
        held = self._cache.get(key)
        if held is None or (held.clean is None and not held.problem):
            runs = self.reference_runs if spec == "numpy" else self.runs
            held = measure(spec, self.frames, setting, runs, warm_up=runs >= MIN_RUNS)
            self._cache[key] = held
        return held

    def _release(self) -> None:
        """Drop the images of runs no knob compares against (times stay)."""
        for key, m in self._cache.items():
            if key not in self._keep:
                m.noisy = m.clean = None

    def rows(self) -> list[dict]:
        """One row per (setting, backend): time, errors, availability."""
        from gpu_blur.scene import SceneError

        out = []
        for knob in dict.fromkeys(s.knob for s in self.knobs):
            settings = [s for s in self.knobs if s.knob == knob]
            ref_setting = next((s for s in settings if s.reference), None)
            reference = None
            if ref_setting is not None:
                try:
                    reference = self.get("numpy", ref_setting)
                except SceneError:
                    reference = None
                if reference is not None and reference.problem:
                    reference = None
            for setting in settings:
                try:
                    setting_scene(setting)
                except SceneError as e:
                    out.append(self._row(setting, "-", None, None, None,
                                         f"not available: {e}"))
                    self.log(f"{knob:<10} {setting.label:<22} not available: {e}")
                    continue
                for spec in self.backends:
                    if spec == "numpy" and setting.kernel_only and not setting.reference:
                        continue
                    out.append(self._measured_row(spec, setting, ref_setting, reference))
            self._release()
        return out

    def _measured_row(self, spec: str, setting: Setting, ref_setting: Setting | None,
                      reference: Measurement | None) -> dict:
        m = self.get(spec, setting)
        if m.problem:
            self.log(f"{setting.knob:<10} {setting.label:<22} {spec:<12} not available: "
                     f"{m.problem}")
            return self._row(setting, spec, None, None, None, f"not available: {m.problem}")
        note = ""
        if reference is None:
            note = "no reference: the knob's accurate setting did not run"
            scores = None
        else:
            scores = errors(m, reference)
            own = self.get(spec, ref_setting)
            if (setting is not ref_setting and own.clean is not None
                    and np.array_equal(own.clean, m.clean)
                    and np.array_equal(own.noisy, m.noisy)):
                note = f"output identical to {ref_setting.label} on this backend"
        row = self._row(setting, spec, m, scores, reference, note)
        self.log(f"{setting.knob:<10} {setting.label:<22} {spec:<12} "
                 f"{row['ms_per_megapixel']:9.2f} ms/MP  max err "
                 + (f"{row['max_abs_error']:.3g}  KL {row['residual_kl']:.3g}"
                    if scores else "-") + (f"  ({note})" if note else ""))
        return row

    def _row(self, setting: Setting, spec: str, m: Measurement | None, scores: dict | None,
             reference: Measurement | None, note: str) -> dict:
        row = {"knob": setting.knob, "setting": setting.label, "scene": setting.scene,
               "tile": list(setting.tile) if setting.tile else None,
               "reference": setting.reference, "backend": spec,
               "device": self.backends.get(spec, {}).get("device", ""),
               "available": m is not None, "note": note,
               "median_s": None, "ms_per_megapixel": None, "runs_s": None,
               "max_abs_error": None, "psnr_db": None, "residual_kl": None}
        if m is not None:
            median = statistics.median(m.times_s)
            row |= {"median_s": round(median, 6),
                    "ms_per_megapixel": round(median * 1e3 / self.megapixels, 4),
                    "runs_s": [round(t, 6) for t in m.times_s]}
        if scores is not None:
            row |= scores
        return row

    def pipeline(self) -> list[dict]:
        """The base scene on every backend against the numpy reference (speed-up, errors)."""
        reference = self.get("numpy", BASE)
        ref_median = statistics.median(reference.times_s)
        rows = []
        for spec in self.backends:
            m = self.get(spec, BASE)
            if m.problem:
                rows.append({"backend": spec, "device": self.backends[spec]["device"],
                             "available": False, "note": m.problem})
                continue
            median = statistics.median(m.times_s)
            rows.append({"backend": spec, "device": self.backends[spec]["device"],
                         "available": True, "median_s": round(median, 6),
                         "ms_per_megapixel": round(median * 1e3 / self.megapixels, 4),
                         "speedup_over_numpy": round(ref_median / median, 3),
                         **errors(m, reference)})
        return rows


# -- side by side: what a user would pick instead -----------------------------------------------

def _compare(name: str, covers: str, times: list[float], output: np.ndarray,
             expected: np.ndarray, megapixels: float, border: int = 0) -> dict:
    """A side-by-side row: median time and errors against ``expected`` (values clipped)."""
    from gpu_blur.metrics import psnr

    inner = (slice(border, expected.shape[0] - border), slice(border, expected.shape[1] - border))
    got = np.asarray(output, np.float64)[inner]
    want = expected[inner]
    median = statistics.median(times)
    # PSNR takes values in [0, 1]: float32 sums of values <= 1 may end a rounding above
    return {"method": name, "covers": covers, "median_s": round(median, 6),
            "ms_per_megapixel": round(median * 1e3 / megapixels, 4),
            "max_abs_error": float(np.max(np.abs(got - want))),
            "psnr_db": _finite(psnr(np.clip(want, 0, 1), np.clip(got, 0, 1)))}


def _bayer_code(cv2, suffix: str = "") -> int:
    """OpenCV's code for an RGGB mosaic to RGB.

    OpenCV names its Bayer codes after the second row's second and third pixels, so RGGB is
    ``COLOR_BayerBG2RGB``; OpenCV 4.5+ also offers the top-left name ``COLOR_BayerRGGB2RGB``.
    """
    return getattr(cv2, f"COLOR_BayerRGGB2RGB{suffix}", None) or getattr(
        cv2, f"COLOR_BayerBG2RGB{suffix}")


def demosaic_side_by_side(frame: np.ndarray, backends: dict[str, dict], runs: int) -> list[dict]:
    """Demosaicing methods on one mosaic, against our float64 Malvar 2004.

    The mosaic is the linear middle frame sampled through an RGGB filter array (values in
    [0, 1]). Every output is clipped to [0, 1] (what an image keeps); errors leave out
    :data:`BORDER_PX` pixels at every edge, where the methods' border rules differ.
    """
    import cv2

    from gpu_blur.backends import get_backend, to_host
    from gpu_blur.cameras import get_camera
    from gpu_blur.imageio import unit_values
    from gpu_blur.plan import plan
    from gpu_blur.reference import bayer, demosaic, transfer
    from gpu_blur.scene import scene_from_dict
    from gpu_blur.tiling import Region

    raw = bayer.mosaic(transfer.srgb_to_linear(unit_values(frame)), PATTERN)
    h, w = raw.shape
    mp = h * w / 1e6
    expected = np.clip(demosaic.demosaic_malvar2004(raw, PATTERN), 0.0, 1.0)
    rows = []

    def add(name, covers, run, scale=1.0):
        times, out = median_time(run, runs)
        rows.append(_compare(name, covers, times, np.clip(np.asarray(out) * scale, 0, 1),
                             expected, mp, BORDER_PX))

    add("gpu_blur numpy Malvar 2004 (float64)", "demosaic",
        lambda: demosaic.demosaic_malvar2004(raw, PATTERN))
    add("gpu_blur numpy bilinear (float64)", "demosaic",
        lambda: demosaic.demosaic_bilinear(raw, PATTERN))
    # The finish pass alone, with nothing after the demosaic but an identity Cam2Lin and the
    # clip to [0, 1]: camera "srgb", no tone curve, no saturation, float output.
    only = plan(scene_from_dict({"blur": {"mode": "none"}, "saturation": {"mode": "off"},
                                 "camera": {"name": "srgb"}, "noise": {"model": "none"},
                                 "isp": {"round_trip": "always"},
                                 "output": {"crf": "none", "bits": 0}}))
    camera, whole, blank = get_camera("srgb"), Region.whole(h, w), np.zeros((h, w, 3))
    for spec in backends:
        if spec == "numpy":
            continue
        runner = get_backend(spec, "float32")
        add(f"gpu_blur {spec} Malvar 2004 (float32)", "upload, demosaic, download",
            lambda runner=runner: to_host(runner.finish(
                only, {"pattern": PATTERN}, camera, raw, blank, whole, whole, seed=SEED,
                sample_index=SAMPLE_INDEX)))
    codes = np.round(raw * 65535).astype(np.uint16)
    add("OpenCV demosaicing, bilinear (uint16)", "demosaic",
        lambda: cv2.demosaicing(codes, _bayer_code(cv2)), 1 / 65535)
    add("OpenCV demosaicing, edge-aware (uint16)", "demosaic",
        lambda: cv2.demosaicing(codes, _bayer_code(cv2, "_EA")), 1 / 65535)
    try:
        from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004
    except ImportError:
        rows.append({"method": "colour-demosaicing Malvar 2004", "covers": "",
                     "note": "not installed (pip install colour-demosaicing)"})
    else:
        add("colour-demosaicing Malvar 2004 (float64)", "demosaic",
            lambda: demosaicing_CFA_Bayer_Malvar2004(raw, PATTERN))
    return rows


def kernel_blur_side_by_side(frame: np.ndarray, backends: dict[str, dict],
                             runs: int) -> list[dict]:
    """Our kernel blur against ``cv2.filter2D`` (BORDER_REFLECT_101), one motion kernel.

    The kernel is a random motion kernel of :data:`KERNEL_SIZE` (the scene's own draw for the
    benchmark's seed and sample index); the image is the linear middle frame. Errors against
    our float64 FFT convolution (:func:`gpu_blur.reference.blur.convolve_kernel`), same border
    rule, whole image.
    """
    import cv2

    from gpu_blur.backends import get_backend, to_host
    from gpu_blur.imageio import unit_values
    from gpu_blur.plan import plan
    from gpu_blur.reference import blur, rng, transfer
    from gpu_blur.scene import scene_from_dict
    from gpu_blur.tiling import Region

    linear = transfer.srgb_to_linear(unit_values(frame))
    h, w = linear.shape[:2]
    mp = h * w / 1e6
    uniforms = rng.image_uniforms(SEED, SAMPLE_INDEX, rng.Stream.KERNEL, blur.KERNEL_UNIFORMS)
    kernel = blur.random_motion_kernel(uniforms, KERNEL_SIZE)
    expected = blur.convolve_kernel(linear, kernel)
    rows = []

    def add(name, covers, run):
        times, out = median_time(run, runs)
        rows.append(_compare(name, covers, times, out, expected, mp))

    add("gpu_blur numpy FFT convolution (float64)", "blur", lambda: blur.convolve_kernel(
        linear, kernel))
    kernel_plan = plan(scene_from_dict({"blur": {"mode": "kernel"}}))
    whole = Region.whole(h, w)
    for spec in backends:
        if spec == "numpy":
            continue
        runner = get_backend(spec, "float32")
        add(f"gpu_blur {spec} kernel blur (float32)",
            "upload uint8, linearize, blur image and saturation mask, download image",
            lambda runner=runner: to_host(runner.accumulate(
                kernel_plan, {"kernel": kernel}, [frame], None, whole)[0]))
    # filter2D correlates: flip the kernel for a convolution
    flipped = np.ascontiguousarray(kernel[::-1, ::-1] / kernel.sum())
    for dtype in (np.float32, np.float64):
        image, taps = linear.astype(dtype), flipped.astype(dtype)
        add(f"OpenCV filter2D ({np.dtype(dtype).name})", "blur", lambda image=image, taps=taps:
            cv2.filter2D(image, -1, taps, borderType=cv2.BORDER_REFLECT_101))
    return rows


# -- Pareto front and plot --------------------------------------------------------------------

def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and error (lower is better).

    Args:
        points: (time, error) pairs.

    Returns:
        The front's indices, fastest first; of equal points, the first.
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1], i))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


#: The plot's panels: (row key, axis label).
PANELS = (("max_abs_error", "max abs error, no noise (vs float64 reference)"),
          ("residual_kl", "residual KL divergence, nats (noise)"))


def _floor(values: list[float]) -> float:
    """Where a log axis shows 0: a decade below the smallest positive value."""
    positive = [v for v in values if v > 0]
    return 10.0 ** (math.floor(math.log10(min(positive))) - 1) if positive else 1e-9


def _series(rows: list[dict], key: str):
    """(series label -> [(ms/MP, error, label)]), the floor that stands for 0."""
    usable = [r for r in rows if r["available"] and r[key] is not None]
    floor = _floor([r[key] for r in usable])
    series: dict[str, list] = {}
    for r in usable:
        name = f"{r['backend']}: {r['device']}"
        point = (r["ms_per_megapixel"], max(r[key], floor),
                 f"{r['backend']} {r['knob']}: {r['setting']}")
        points = series.setdefault(name, [])
        if not any(p[:2] == point[:2] for p in points):  # one run shared by several knobs
            points.append(point)
    return series, floor


def write_plot(rows: list[dict], path: Path, title: str) -> str:
    """Error against time, log scales, one series per backend and device, front marked.

    Uses matplotlib when installed, else draws with OpenCV. Returns which one drew it.
    """
    try:
        import matplotlib
    except ImportError:
        _plot_cv2(rows, path, title)
        return "cv2"
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(14, 6))
    for ax, (key, label) in zip(axes, PANELS, strict=True):
        series, floor = _series(rows, key)
        everything = [p for points in series.values() for p in points]
        for name, points in series.items():
            ax.scatter([p[0] for p in points], [p[1] for p in points], label=name, s=22)
        front = [everything[i] for i in pareto_front([p[:2] for p in everything])]
        if front:
            ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="k",
                    lw=1, label="Pareto front")
            ax.scatter([p[0] for p in front], [p[1] for p in front], s=90,
                       facecolors="none", edgecolors="k")
            for x, y, text in front:
                ax.annotate(text, (x, y), textcoords="offset points", xytext=(4, 4),
                            fontsize=7)
        ax.axhline(floor, color="0.7", lw=0.8, ls=":")
        ax.set(xscale="log", yscale="log", xlabel="ms per megapixel",
               ylabel=f"{label}; {floor:.0e} = 0")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return "matplotlib"


#: cv2 drawing: BGR colours of the series, in order.
_COLOURS = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
            (75, 86, 140), (194, 119, 227), (127, 127, 127))


def _plot_cv2(rows: list[dict], path: Path, title: str) -> None:
    """The plot of :func:`write_plot` drawn with OpenCV (no matplotlib)."""
    import cv2

    panel_w, h, margin = 700, 620, 80
    canvas = np.full((h, panel_w * len(PANELS), 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, title[:150], (10, 20), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for n, (key, label) in enumerate(PANELS):
        series, floor = _series(rows, key)
        everything = [p for points in series.values() for p in points]
        if not everything:
            continue
        x0, x1 = margin + n * panel_w, (n + 1) * panel_w - 20
        y0, y1 = h - margin, 50
        lx = [math.log10(p[0]) for p in everything]
        ly = [math.log10(p[1]) for p in everything]
        xs = (math.floor(min(lx)), math.ceil(max(lx)) + (min(lx) == max(lx)))
        ys = (math.floor(min(ly)), math.ceil(max(ly)) + (min(ly) == max(ly)))

        def at(p, xs=xs, ys=ys, x0=x0, x1=x1, y0=y0, y1=y1):
            fx = (math.log10(p[0]) - xs[0]) / (xs[1] - xs[0])
            fy = (math.log10(p[1]) - ys[0]) / (ys[1] - ys[0])
            return int(x0 + fx * (x1 - x0)), int(y0 + fy * (y1 - y0))

        for d in range(xs[0], xs[1] + 1):
            x, _ = at((10.0 ** d, 10.0 ** ys[0]))
            cv2.line(canvas, (x, y0), (x, y1), (225, 225, 225), 1)
            cv2.putText(canvas, f"1e{d}", (x - 12, y0 + 18), font, 0.4, (0, 0, 0), 1)
        for d in range(ys[0], ys[1] + 1):
            _, y = at((10.0 ** xs[0], 10.0 ** d))
            cv2.line(canvas, (x0, y), (x1, y), (225, 225, 225), 1)
            cv2.putText(canvas, f"1e{d}", (x0 - 45, y + 4), font, 0.4, (0, 0, 0), 1)
        cv2.rectangle(canvas, (x0, y1), (x1, y0), (0, 0, 0), 1)
        cv2.putText(canvas, "ms per megapixel", (x0 + 200, y0 + 40), font, 0.45, (0, 0, 0), 1)
        cv2.putText(canvas, f"{label}; {floor:.0e} = 0"[:80], (x0, y1 - 10), font, 0.4,
                    (0, 0, 0), 1)
        for (name, points), colour in zip(series.items(), _COLOURS * 4, strict=False):
            for p in points:
                cv2.circle(canvas, at(p), 4, colour, -1, cv2.LINE_AA)
            if n == 0:
                k = list(series).index(name)
                cv2.circle(canvas, (x0 + 10, y1 + 15 + 16 * k), 4, colour, -1)
                cv2.putText(canvas, name[:70], (x0 + 20, y1 + 19 + 16 * k), font, 0.38,
                            (0, 0, 0), 1)
        front = [at(everything[i]) for i in pareto_front([p[:2] for p in everything])]
        for a, b in zip(front, front[1:], strict=False):
            cv2.line(canvas, a, (b[0], a[1]), (0, 0, 0), 1, cv2.LINE_AA)
            cv2.line(canvas, (b[0], a[1]), b, (0, 0, 0), 1, cv2.LINE_AA)
        for p in front:
            cv2.circle(canvas, p, 8, (0, 0, 0), 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), canvas):
        raise OSError(f"cannot write {path}")


# -- report -------------------------------------------------------------------------------------

def _number(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if value == 0:
        return "0"
    return f"{value:.{digits}g}"


def summary_table(report: dict) -> list[str]:
    """One line per knob setting: ms per megapixel on each backend, the largest errors.

    Errors are the largest over the backends that ran the setting (the numpy row shows the
    setting's own effect; kernel rows add their float32 rounding).
    """
    specs = list(report["devices"])
    lines = ["| knob | setting | " + " | ".join(f"`{s}` ms/MP" for s in specs)
             + " | max abs error | residual KL |",
             "|---|---|" + "---:|" * (len(specs) + 2)]
    settings = dict.fromkeys((r["knob"], r["setting"], r["reference"]) for r in report["rows"])
    for knob, label, reference in settings:
        rows = [r for r in report["rows"] if (r["knob"], r["setting"]) == (knob, label)]
        cells = []
        for spec in specs:
            row = next((r for r in rows if r["backend"] in (spec, "-")), None)
            cells.append("" if row is None and spec == "numpy"
                         else "n/a" if row is None or not row["available"]
                         else _number(row["ms_per_megapixel"], 4))
        worst = {key: max((r[key] for r in rows if r[key] is not None), default=None)
                 for key in ("max_abs_error", "residual_kl")}
        star = " *" if reference else ""
        lines.append(f"| {knob} | {label}{star} | " + " | ".join(cells)
                     + f" | {_number(worst['max_abs_error'])} | "
                     f"{_number(worst['residual_kl'])} |")
    return lines


def markdown(report: dict) -> str:
    """The report's tables in Markdown."""
    size = report["size"]
    lines = [
        f"# Accuracy against time: {report['frames']} frames of {size[0]} x {size[1]}",
        "",
        f"Host: {report['cpu']}, 1-minute load average {report['load_average'][0]} at the "
        f"start and {report['load_average'][1]} at the end (other work slows the runs). "
        f"Source: {report['source']} (files' SHA-256 "
        f"{str(report.get('source_digest'))[:16]}...). Devices: "
        + "; ".join(f"`{k}` {v}" for k, v in report["devices"].items()) + ".",
        "",
        "Base scene (RSBlur-like): " + json.dumps(report["base_scene"]) + ". Times: median of "
        f"{report['runs']} runs after a warm-up"
        + (f" (numpy: {report['reference_runs']} run, no warm-up: here it only makes the "
           "reference images; its medians are in the CPU run)"
           if report.get("reference_runs", report["runs"]) < MIN_RUNS else "")
        + ", frames in host memory, result back on the "
        "host, per megapixel of output. Errors: the final image without noise (RAW round "
        "trip kept, float output) against the numpy float64 run of the knob's accurate "
        "setting (*); residual KL: D(reference || run) of the noise residuals (final with "
        "noise minus final without), one bin per 8-bit code, add-one smoothing. "
        "PSNR \"-\" means identical.",
        "",
        "Summary (empty: numpy ignores the setting, it always runs float64 with precise "
        "maths on whole images; n/a: not offered, by the scene or by that backend (the note "
        "below says which); errors: the largest over the backends):",
        "",
        *summary_table(report),
        "",
        "Every row:",
        "",
        "| knob | setting | backend | ms/MP | max abs error | PSNR (dB) | residual KL | note |",
        "|---|---|---|---:|---:|---:|---:|---|",
    ]
    for r in report["rows"]:
        star = " *" if r["reference"] else ""
        lines.append(
            f"| {r['knob']} | {r['setting']}{star} | {r['backend']} | "
            f"{_number(r['ms_per_megapixel'], 4)} | {_number(r['max_abs_error'])} | "
            f"{_number(r['psnr_db'], 4)} | {_number(r['residual_kl'])} | "
            f"{r['note'].replace('|', '/')} |")
    side = report["side_by_side"]
    lines += ["", "## Side by side: what a user would pick instead", "",
              "Whole pipeline, base scene, against the numpy reference:", "",
              "| backend | device | ms/MP | speed-up over numpy | max abs error | residual KL |",
              "|---|---|---:|---:|---:|---:|"]
    for r in side["pipeline"]:
        if r["available"]:
            lines.append(f"| {r['backend']} | {r['device']} | "
                         f"{_number(r['ms_per_megapixel'], 4)} | "
                         f"{_number(r['speedup_over_numpy'])} | "
                         f"{_number(r['max_abs_error'])} | {_number(r['residual_kl'])} |")
        else:
            lines.append(f"| {r['backend']} | {r['device']} | - | - | - | {r['note']} |")
    for key, title in (("demosaic", "Demosaicing one RGGB mosaic of the linear middle frame, "
                        f"against our float64 Malvar 2004, outputs clipped to [0, 1], "
                        f"{BORDER_PX} px border left out:"),
                       ("kernel_blur", f"Kernel blur, a {KERNEL_SIZE} x {KERNEL_SIZE} random "
                        "motion kernel on the linear middle frame, against our float64 FFT "
                        "convolution (both reflect-101):")):
        lines += ["", title, "", "| method | time covers | ms/MP | max abs error | PSNR (dB) |",
                  "|---|---|---:|---:|---:|"]
        for r in side[key]:
            if "note" in r:
                lines.append(f"| {r['method']} | {r['note']} | - | - | - |")
                continue
            lines.append(f"| {r['method']} | {r['covers']} | "
                         f"{_number(r['ms_per_megapixel'], 4)} | "
                         f"{_number(r['max_abs_error'])} | {_number(r['psnr_db'], 4)} |")
    return "\n".join(lines) + "\n"


def run_benchmark(size: tuple[int, int] = DEFAULT_SIZE, backends: Sequence[str] | None = None,
                  quick: bool = False, runs: int = MIN_RUNS,
                  knobs: Sequence[Setting] | None = None,
                  log: Callable[[str], None] = print,
                  reference_runs: int | None = None) -> dict:
    """Run the benchmark and return its report (what the JSON file holds).

    Args:
        size: (width, height) of the frames, even, each >= :data:`MIN_SIDE`.
        backends: backend specs to run (numpy always runs: it is the reference); None: all.
        quick: the first two settings of each knob only (:func:`quick_knobs`).
        runs: timed runs per measurement, >= :data:`MIN_RUNS`.
        knobs: the settings (default :data:`KNOBS`).
        log: called with a line per measured row.
        reference_runs: timed runs of the numpy reference, >= 1 (default ``runs``). Fewer
            than :data:`MIN_RUNS` (no warm-up) serve a GPU machine's run, where numpy is only
            the source of the reference images: its times there are single runs, and its
            medians come from a CPU run.

    Raises:
        ValueError: bad size, runs or backend names.
    """
    import gpu_blur

    width, height = size
    if width < MIN_SIDE or height < MIN_SIDE or width % 2 or height % 2:
        raise ValueError(f"size {width} x {height}: give even sides of at least {MIN_SIDE} "
                         "(e.g. --size 480x300)")
    if runs < MIN_RUNS:
        raise ValueError(f"runs = {runs}: the medians need at least {MIN_RUNS} timed runs")
    reference_runs = runs if reference_runs is None else reference_runs
    if reference_runs < 1:
        raise ValueError(f"reference runs = {reference_runs}: numpy needs at least one run")
    chosen = choose_backends(backends)
    settings = list(KNOBS if knobs is None else knobs)
    if quick:
        settings = quick_knobs(settings)
    frames = make_frames(width, height)
    load_before = _load_average()
    runner = Runner(frames, chosen, settings, runs, log, reference_runs)
    rows = runner.rows()
    middle = frames[len(frames) // 2]
    side_by_side = {
        "pipeline": runner.pipeline(),
        "demosaic": demosaic_side_by_side(middle, chosen, runs),
        "kernel_blur": kernel_blur_side_by_side(middle, chosen, runs),
    }
    return {
        "what": "accuracy against time per knob setting: gpu_blur.synthesize, frames in host "
                "memory, median of the timed runs after a warm-up; errors of the noise-free "
                "final image and residual KL against the numpy float64 reference "
                "(gpu_blur/benchmark.py)",
        "host": platform.node(), "cpu": cpu_name(), "python": platform.python_version(),
        "gpu_blur": gpu_blur.__version__, "source": source_commit(),
        "source_digest": source_digest(),
        "devices": {spec: b["device"] for spec, b in chosen.items()},
        "size": [width, height], "frames": FRAMES, "pan_px_per_frame": PAN_PX,
        "megapixels": runner.megapixels, "runs": runs, "reference_runs": reference_runs,
        "seed": SEED,
        "sample_index": SAMPLE_INDEX, "base_scene": BASE_SCENE, "noise_free": NOISE_FREE,
        "quick": quick, "knobs": list(dict.fromkeys(s.knob for s in settings)),
        # other work on the host slows the runs: its 1-minute load average, start and end
        "load_average": [load_before, _load_average()],
        "rows": rows, "side_by_side": side_by_side,
    }


def _load_average() -> float | None:
    """The host's 1-minute load average (None where the OS does not say)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def write_report(report: dict, folder: Path, tag: str) -> list[Path]:
    """Write the JSON, Markdown and PNG files of a report; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"accuracy_vs_time_{tag}"
    paths = [stem.with_suffix(".json"), stem.with_suffix(".md"), stem.with_suffix(".png")]
    paths[0].write_text(json.dumps(report, indent=1, allow_nan=False) + "\n")
    paths[1].write_text(markdown(report))
    size = report["size"]
    write_plot(report["rows"], paths[2], f"gpu_blur accuracy against time, {report['frames']} "
               f"frames of {size[0]} x {size[1]}, {report['cpu']}; "
               + ", ".join(report["devices"]))
    return paths


def _size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTHxHEIGHT, e.g. 480x300")
    return int(match[1]), int(match[2])


def add_arguments(p: argparse.ArgumentParser, default_output: Path = Path(".")) -> None:
    """The options of ``gpu-blur bench`` and ``bench/accuracy_vs_time.py``."""
    p.add_argument("--size", type=_size, default=DEFAULT_SIZE, metavar="WxH",
                   help="frame size, even sides (default 1920x1200; 480x300 for a quick look)")
    p.add_argument("--backends", metavar="LIST", type=lambda s: [x.strip() for x in
                   s.split(",") if x.strip()], help="comma list of backends (numpy always runs, "
                   "as the reference), e.g. numpy,opencl:0:0,warp:cpu (default: every usable "
                   "device; see gpu-blur devices)")
    p.add_argument("--quick", action="store_true", help="two settings per knob (its accurate "
                   "one and one other)")
    p.add_argument("--knobs", metavar="LIST", type=lambda s: [x.strip() for x in s.split(",")
                   if x.strip()], help="comma list of the knobs to run, e.g. motion or "
                   "\"precision,CRF table\" (default: all; names as in the table)")
    p.add_argument("--runs", type=int, default=MIN_RUNS, help=f"timed runs per measurement "
                   f"after a warm-up, >= {MIN_RUNS} (default {MIN_RUNS})")
    p.add_argument("--reference-runs", type=int, metavar="N", help="timed runs of the numpy "
                   "reference (default: --runs); 1 on a GPU machine, where numpy only makes the "
                   "reference images and its medians come from a CPU run")
    p.add_argument("--output", type=Path, default=default_output, metavar="DIR",
                   help=f"folder for accuracy_vs_time_<tag>.json/.md/.png (default "
                   f"{default_output})")
    p.add_argument("--tag", help="file name tag (default: cpu, or the first GPU's name)")


def run_from_args(args: argparse.Namespace) -> int:
    """Run ``gpu-blur bench`` with parsed options; returns the exit status."""
    knobs = select_knobs(args.knobs) if args.knobs is not None else None
    report = run_benchmark(tuple(args.size), args.backends, args.quick, args.runs, knobs=knobs,
                           log=lambda line: print(line, flush=True),
                           reference_runs=args.reference_runs)
    tag = args.tag or device_tag(choose_backends(list(report["devices"])))
    for path in write_report(report, args.output, tag):
        print(f"wrote {path}")
    return 0


def main(argv: Sequence[str] | None = None, default_output: Path = Path(".")) -> int:
    """``python -m gpu_blur.benchmark`` / ``bench/accuracy_vs_time.py``: parse and run."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(p, default_output)
    try:
        return run_from_args(p.parse_args(argv))
    except (ValueError, OSError, RuntimeError) as e:
        print(f"accuracy_vs_time: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
