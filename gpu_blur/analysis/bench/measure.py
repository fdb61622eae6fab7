"""Measuring a setting on a backend: median times, errors against the reference, the rows."""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
import time
from collections.abc import Callable, Sequence

import numpy as np

from gpu_blur.analysis.bench.workload import (
    BASE,
    KERNEL_ONLY_KEYS,
    MIN_RUNS,
    NOISE_FREE,
    SAMPLE_INDEX,
    SEED,
    Setting,
    setting_scene,
)
from gpu_blur.reference.flow import INTERPOLATION_AUTO, INTERPOLATION_FACTORS

__all__ = ["KL_BINS", "Measurement", "NOT_OFFERED", "Runner", "errors", "finite_or_none",
           "measurement_key", "median_time", "scene_refusal", "synthesize_setting"]

#: Residual histograms: bins per unit of value, one per 8-bit code (gpu_blur.analysis.metrics).
KL_BINS = 255


@dataclasses.dataclass
class Measurement:
    """One setting on one backend: its final images with and without noise.

    Attributes:
        noisy: the final image, H x W x 3 float32 (None once released).
        clean: the same run without noise, H x W x 3 float32.
        problem: why it could not run (then the images are None).
    """

    noisy: np.ndarray | None = None
    clean: np.ndarray | None = None
    problem: str = ""


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


def synthesize_setting(spec: str, frames: Sequence[np.ndarray], setting: Setting,
                       *extra: dict) -> np.ndarray:
    """The final image of a setting on a backend (host memory, so the device is done).

    ``extra``: scene layers over the setting's (:data:`NOISE_FREE` for the clean image).
    """
    import gpu_blur

    return gpu_blur.synthesize(frames, setting_scene(setting, *extra), seed=SEED,
                               sample_index=SAMPLE_INDEX, backend=spec,
                               tile=setting.tile).blurred


#: What a run that a backend does not offer raises (the row says so and the bench goes on).
NOT_OFFERED = (ValueError, RuntimeError, NotImplementedError)


def _problem(e: Exception) -> str:
    return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def scene_refusal(setting: Setting) -> str:
    """Why the scene refuses the setting ("" when it accepts it)."""
    from gpu_blur.scene import SceneError

    try:
        setting_scene(setting)
    except SceneError as e:
        return str(e)
    return ""


def finite_or_none(value: float) -> float | None:
    """A JSON-safe number: None for inf (identical images have no PSNR)."""
    return value if math.isfinite(value) else None


def errors(run: Measurement, reference: Measurement) -> dict:
    """Max abs error and PSNR of the noise-free image, and the residual KL divergence.

    Returns:
        ``max_abs_error`` (values in [0, 1]), ``psnr_db`` (None when identical) and
        ``residual_kl`` (nats, D(reference residuals || this run's residuals)).
    """
    from gpu_blur.analysis.metrics import histogram_kl, psnr

    clean = run.clean.astype(np.float64)
    expected = reference.clean.astype(np.float64)
    residuals = [m.noisy.astype(np.float64) - m.clean for m in (reference, run)]
    return {"max_abs_error": float(np.max(np.abs(clean - expected))),
            "psnr_db": finite_or_none(psnr(expected, clean)),
            "residual_kl": histogram_kl(*residuals, bins=KL_BINS)}


class Runner:
    """Measures the rows of the knob table, one at a time.

    Each row times its setting and its knob's accurate setting on the same backend, the same
    number of times and alternately (setting, accurate, setting, ...), so both medians see
    the same load on the host; the first run of each (setting, backend) in this process is
    an untimed warm-up that builds the kernels. Images (for the errors) are kept for the
    runs some knob compares against, and dropped for the others once their row is done.

    Args:
        frames: the input frames.
        backends: spec -> device description (:func:`choose_backends`).
        knobs: the settings to run.
        runs: timed runs per measurement (>= :data:`MIN_RUNS`).
        log: called with one line per row as it is measured.
        reference_runs: timed runs on numpy (default ``runs``); fewer than :data:`MIN_RUNS`
            skip its warm-up (see :func:`run_benchmark`).
    """

    def __init__(self, frames, backends: dict[str, dict], knobs: Sequence[Setting],
                 runs: int, log: Callable[[str], None] = print,
                 reference_runs: int | None = None):
        self.frames, self.backends, self.knobs, self.runs = frames, backends, knobs, runs
        self.reference_runs = runs if reference_runs is None else reference_runs
        self.log = log
        self.megapixels = frames[0].shape[0] * frames[0].shape[1] / 1e6
        self._images: dict[str, Measurement] = {}
        self._warm: set[str] = set()
        # runs that some knob compares against: their images stay in memory
        self._keep = {measurement_key(spec, s) for spec in backends
                      for s in [*[s for s in knobs if s.reference and not scene_refusal(s)], BASE]}

    def tasks(self) -> list[tuple[Setting, str]]:
        """Every row to measure, in order, as (setting, backend).

        The backend is "-" when the scene refuses the setting; numpy leaves out the
        kernel-only settings but the accurate one.
        """
        out = []
        for setting in self.knobs:
            if scene_refusal(setting):
                out.append((setting, "-"))
                continue
            out += [(setting, spec) for spec in self.backends
                    if not (spec == "numpy" and setting.kernel_only and not setting.reference)]
        return out

    def reference_of(self, setting: Setting) -> Setting | None:
        """The accurate setting of ``setting``'s knob (None when the knob has none)."""
        return next((s for s in self.knobs if s.knob == setting.knob and s.reference), None)

    def cost(self, setting: Setting, spec: str) -> float:
        """A row's run time relative to a plain row's, for the progress bar's time left.

        Interpolating frames k times costs about 3 k plain averages (numpy and OpenCL on a
        CPU, 320 x 200 to 1920 x 1200; "auto" counted as its largest factor); a row also runs
        its knob's accurate setting.
        """
        def runs_cost(s: Setting | None) -> float:
            k = s.scene.get("blur", {}).get("interpolation", 1) if s is not None else 1
            k = INTERPOLATION_FACTORS[-1] if k == INTERPOLATION_AUTO else k
            return 3.0 * k if k > 1 else 1.0

        if spec == "-":
            return 0.0
        ref = self.reference_of(setting)
        return runs_cost(setting) + (runs_cost(ref) if ref not in (None, setting) else 0.0)

    def _runs(self, spec: str) -> int:
        return self.reference_runs if spec == "numpy" else self.runs

    def _run(self, spec: str, setting: Setting) -> np.ndarray:
        """One run, its image kept as the setting's noisy image (a problem propagates)."""
        image = synthesize_setting(spec, self.frames, setting)
        key = measurement_key(spec, setting)
        self._images.setdefault(key, Measurement()).noisy = image
        self._warm.add(key)
        return image

    def images(self, spec: str, setting: Setting) -> Measurement:
        """The setting's final images on ``spec`` with and without noise (made if needed)."""
        try:
            key = measurement_key(spec, setting)
        except NOT_OFFERED as e:  # the scene refuses the setting (a SceneError)
            return Measurement(problem=_problem(e))
        held = self._images.get(key)
        if held is not None and (held.problem or held.clean is not None):
            return held
        try:
            if held is None or held.noisy is None:
                self._run(spec, setting)
            held = self._images[key]
            held.clean = synthesize_setting(spec, self.frames, setting, NOISE_FREE)
        except NOT_OFFERED as e:
            held = self._images[key] = Measurement(problem=_problem(e))
        return held

    def time_together(self, spec: str, settings: Sequence[Setting]) -> list[list[float]]:
        """Seconds of each setting's timed runs on ``spec``, taken in turn.

        Each setting first gets a warm-up run (unless it ran in this process already, or
        numpy runs fewer than :data:`MIN_RUNS` times). A run that fails raises.
        """
        runs = self._runs(spec)
        for s in settings:
            if runs >= MIN_RUNS and measurement_key(spec, s) not in self._warm:
                self._run(spec, s)
        times: list[list[float]] = [[] for _ in settings]
        for _ in range(runs):
            for i, s in enumerate(settings):
                start = time.perf_counter()
                self._run(spec, s)
                times[i].append(time.perf_counter() - start)
        return times

    def release(self) -> None:
        """Drop the images of runs no knob compares against."""
        for key in [k for k in self._images if k not in self._keep]:
            del self._images[key]

    def row(self, setting: Setting, spec: str) -> dict:
        """Measure one row (a task of :meth:`tasks`) and log it."""
        if spec == "-":
            refused = scene_refusal(setting)
            self.log(f"{setting.knob:<10} {setting.label:<22} not available: {refused}")
            return self._row(setting, spec, note=f"not available: {refused}")
        ref_setting = self.reference_of(setting)
        try:
            row = self._measured_row(setting, spec, ref_setting)
        finally:
            self.release()
        return row

    def _measured_row(self, setting: Setting, spec: str, ref_setting: Setting | None) -> dict:
        reference = None if ref_setting is None else self.images("numpy", ref_setting)
        own_ref = None if ref_setting is None else self.images(spec, ref_setting)
        paired = (own_ref is not None and not own_ref.problem
                  and measurement_key(spec, ref_setting) != measurement_key(spec, setting))
        m = self.images(spec, setting)
        problem = m.problem
        if not problem:
            try:
                times = self.time_together(spec, [setting, ref_setting] if paired else [setting])
            except NOT_OFFERED as e:
                problem = _problem(e)
        if problem:
            self.log(f"{setting.knob:<10} {setting.label:<22} {spec:<12} not available: "
                     f"{problem}")
            return self._row(setting, spec, note=f"not available: {problem}")
        notes = []
        if reference is None or reference.problem:
            notes.append("no reference: the knob's accurate setting did not run on numpy")
            scores = None
        else:
            scores = errors(m, reference)
        if own_ref is not None and own_ref.problem:
            notes.append(f"accurate setting not timed on this backend: {own_ref.problem}")
        elif (paired and np.array_equal(own_ref.clean, m.clean)
              and np.array_equal(own_ref.noisy, m.noisy)):
            notes.append(f"output identical to {ref_setting.label} on this backend")
        if paired:
            ref_times = times[1]
        else:  # the accurate setting itself, or no accurate setting to time
            ref_times = times[0] if own_ref is not None and not own_ref.problem else None
        row = self._row(setting, spec, times[0], ref_times, scores, "; ".join(notes))
        ratio = row["time_vs_accurate"]
        self.log(f"{setting.knob:<10} {setting.label:<22} {spec:<12} "
                 f"{row['ms_per_megapixel']:9.2f} ms/MP"
                 + (f" ({ratio:.2f} x accurate)" if ratio is not None else "")
                 + "  max err " + (f"{row['max_abs_error']:.3g}  KL {row['residual_kl']:.3g}"
                                   if scores else "-") + (f"  ({row['note']})" if row["note"]
                                                          else ""))
        return row

    def _row(self, setting: Setting, spec: str, times: list[float] | None = None,
             ref_times: list[float] | None = None, scores: dict | None = None,
             note: str = "") -> dict:
        row = {"knob": setting.knob, "setting": setting.label, "scene": setting.scene,
               "tile": list(setting.tile) if setting.tile else None,
               "reference": setting.reference, "backend": spec,
               "device": self.backends.get(spec, {}).get("device", ""),
               "available": times is not None, "note": note,
               "median_s": None, "ms_per_megapixel": None, "runs_s": None,
               "accurate_median_s": None, "accurate_runs_s": None, "time_vs_accurate": None,
               "max_abs_error": None, "psnr_db": None, "residual_kl": None}
        if times is not None:
            median = statistics.median(times)
            row |= {"median_s": round(median, 6),
                    "ms_per_megapixel": round(median * 1e3 / self.megapixels, 4),
                    "runs_s": [round(t, 6) for t in times]}
        if ref_times is not None:
            ref_median = statistics.median(ref_times)
            row |= {"accurate_median_s": round(ref_median, 6),
                    "accurate_runs_s": [round(t, 6) for t in ref_times],
                    "time_vs_accurate": round(statistics.median(times) / ref_median, 4)}
        if scores is not None:
            row |= scores
        return row

    def pipeline(self) -> list[dict]:
        """The base scene on every backend against the numpy reference (speed-up, errors).

        The backends are timed in turn, round by round, so each speed-up compares runs taken
        under the same load (numpy runs only its ``reference_runs`` rounds).
        """
        reference = self.images("numpy", BASE)
        measured = {spec: self.images(spec, BASE) for spec in self.backends}
        ready = [spec for spec, m in measured.items() if not m.problem]
        for spec in ready:
            if self._runs(spec) >= MIN_RUNS and measurement_key(spec, BASE) not in self._warm:
                self._run(spec, BASE)
        times: dict[str, list[float]] = {spec: [] for spec in ready}
        for round_ in range(max(self._runs(spec) for spec in ready)):
            for spec in ready:
                if round_ < self._runs(spec):
                    start = time.perf_counter()
                    self._run(spec, BASE)
                    times[spec].append(time.perf_counter() - start)
        ref_median = statistics.median(times["numpy"])
        rows = []
        for spec, m in measured.items():
            if m.problem:
                rows.append({"backend": spec, "device": self.backends[spec]["device"],
                             "available": False, "note": m.problem})
                continue
            median = statistics.median(times[spec])
            rows.append({"backend": spec, "device": self.backends[spec]["device"],
                         "available": True, "median_s": round(median, 6),
                         "ms_per_megapixel": round(median * 1e3 / self.megapixels, 4),
                         "speedup_over_numpy": round(ref_median / median, 3),
                         **errors(m, reference)})
        return rows
