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

#: Residual histograms: bins per unit of value, one per 8-bit code (gpu_blur.analysis.metrics).
KL_BINS = 255


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


def scene_accepts(setting: Setting) -> bool:
    """Whether the scene accepts the setting."""
    from gpu_blur.scene import SceneError

    try:
        setting_scene(setting)
    except SceneError:
        return False
    return True


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
                      for s in [*[s for s in knobs if s.reference and scene_accepts(s)], BASE]}

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
