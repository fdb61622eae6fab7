"""What each stage of a plan costs on one backend, and what the skipped ones would cost.

Kernel backends fuse a pass's stages into one kernel, so a stage is never timed alone: a
stage's cost is the time of its passes (to_raw and finish) with it, less their time without it;
a skipped stage's cost is their time with it forced on, less the plan's. Stages that only run
together switch together (:data:`SWITCHES`: the RAW round trip's six stages, saturation and its
restore); a switch is timed alone, the switches that need it off (Poisson-Gaussian noise, for
the RAW round trip) and those it needs on. The accumulate pass (linearize and blur, one kernel)
is timed whole. Every time is a median of ``repeats`` runs after one warm-up run (kernel
builds), the device synchronized before the clock stops; a difference is the median of
differences of runs taken in turns, with a distribution-free interval for that median
(:func:`median_interval`): a difference whose interval holds 0 is within the timing noise and
is printed as such, never as a negative cost. ``gpu-blur plan SCENE --cost`` prints
:func:`format_costs`;
``bench/plan_cost.py`` compares the plan with every stage forced on, per example scene.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import textwrap
import time

import numpy as np

from gpu_blur.planning import Plan, Stage, StageName, plan
from gpu_blur.stages import STAGES

__all__ = ["CONFIDENCE", "FORCED_OPTIONS", "NEEDS", "S", "SWITCHES", "StageCosts", "bench_inputs",
           "cost_text", "every_stage_on", "format_costs", "median_interval", "stage_costs",
           "switch_kept", "switch_off", "switch_on"]

S = StageName

#: Switches that need others on: Poisson-Gaussian noise acts on the RAW mosaic.
NEEDS: dict[str, tuple[str, ...]] = {"poisson_gaussian_noise": ("raw round trip",)}
#: Switches: stages that run only together, switched on or off as one, each with the switches
#: it needs on (:data:`NEEDS`). Read from the stages' rows (:data:`gpu_blur.stages.STAGES`,
#: :attr:`~gpu_blur.stages.StageSpec.switch`), in the order of their first stage.
SWITCHES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    switch: (tuple(s.name for s in STAGES if s.switch == switch), NEEDS.get(switch, ()))
    for switch in dict.fromkeys(s.switch for s in STAGES if s.switch is not None)
}
#: What a stage skipped by the scene runs with when forced on (its options then say nothing
#: runnable): the A7R3 polynomial re-toning, 8-bit quantization.
FORCED_OPTIONS = {S.RETONE: {"crf": "a7r3"}, S.QUANTIZE: {"bits": 8}}
#: The least coverage of the interval a cost difference is judged by (5 runs give their range,
#: 94 %).
CONFIDENCE = 0.9


def switch_on(p: Plan, name: str) -> Plan:
    """``p`` with switch ``name`` (and the switches it needs) on."""
    stages, needs = SWITCHES[name]
    for need in needs:
        p = switch_on(p, need)

    def on(s: Stage) -> Stage:
        if s.name not in stages or s.kept:
            return s
        return dataclasses.replace(s, kept=True, reason="forced on to time it",
                                   options={**s.options, **FORCED_OPTIONS.get(s.name, {})})
    return dataclasses.replace(p, stages=tuple(on(s) for s in p.stages))


def switch_off(p: Plan, name: str) -> Plan:
    """``p`` with switch ``name`` (and the switches that need it) off."""
    for other, (_, needs) in SWITCHES.items():
        if name in needs:
            p = switch_off(p, other)
    stages = SWITCHES[name][0]
    return dataclasses.replace(p, stages=tuple(
        dataclasses.replace(s, kept=False) if s.name in stages else s for s in p.stages))


def switch_kept(p: Plan, name: str) -> bool:
    """Whether the plan runs switch ``name`` (its first stage)."""
    return p.kept(SWITCHES[name][0][0])


def every_stage_on(p: Plan) -> Plan:
    """``p`` with every switch on: what the bench compares the plan with."""
    for name in SWITCHES:
        p = switch_on(p, name)
    return p


@dataclasses.dataclass
class StageCosts:
    """Seconds per sample on one backend.

    Attributes:
        backend: the backend spec; device: its device in words; size: (height, width).
        accumulate: the accumulate pass (linearize and blur) with the plan.
        passes: the to_raw and finish passes with the plan.
        forced: the to_raw and finish passes with every stage on.
        switches: switch name -> (kept by the plan, seconds it adds: with less without, the
            median of the runs' differences).
        params: the sample's parameters (``interpolation_factors`` under interpolation auto).
        intervals: switch name -> (low, high) seconds, the interval of its median difference
            (:func:`median_interval`); ``"every stage"``: that of ``forced - passes``.
    """

    backend: str
    device: str
    size: tuple[int, int]
    accumulate: float
    passes: float
    forced: float
    switches: dict[str, tuple[bool, float]]
    params: dict
    intervals: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)

    @property
    def with_plan(self) -> float:
        """The three passes with the plan."""
        return self.accumulate + self.passes

    @property
    def every_stage(self) -> float:
        """The three passes with every stage forced on."""
        return self.accumulate + self.forced


def bench_inputs(scene, width: int, height: int):
    """``(frames, mask)``: the benchmark's input for ``scene``.

    The built-in photo panned 2 px a frame (:func:`gpu_blur.analysis.bench.workload.make_frames`),
    one frame for a one-photo scene; under ``blur.frames = "from-name"`` (a count per input
    sequence), the default count of the scene format.
    """
    from gpu_blur.analysis.bench.workload import make_frames
    from gpu_blur.scene import FIELDS, FROM_NAME

    count = scene.blur.frames if scene.blur.mode == "average" else 1
    if count == FROM_NAME:
        count = FIELDS["blur"]["frames"].default
    return make_frames(width, height, count), None


def _seconds(run) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def _median_time(run, repeats: int) -> float:
    run()  # warm-up: kernel builds, first allocations
    return statistics.median(_seconds(run) for _ in range(repeats))


def median_interval(values, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """A distribution-free interval for the median of ``values``: (low, high).

    The order statistics x_(k) and x_(n+1-k) with k the largest whose coverage, 1 - 2 P(B <
    k) for B ~ Binomial(n, 1/2), is at least ``confidence``; the whole range when no k reaches
    it (5 values: their range, 94 %). No assumption on the noise's distribution: timings on a
    loaded machine have long tails.
    """
    ordered = sorted(values)
    n, k = len(ordered), 1
    for j in range(2, n // 2 + 1):
        if 1 - 2 * sum(math.comb(n, i) for i in range(j)) / 2**n < confidence:
            break
        k = j
    return ordered[k - 1], ordered[n - k]


def _median_difference(run_with, run_without,
                       repeats: int) -> tuple[float, tuple[float, float]]:
    """Median of ``time(run_with) - time(run_without)`` and its :func:`median_interval`.

    Runs taken in turns: a drifting load on a shared machine then shifts both alike.
    """
    run_with()  # warm-up: kernel builds, first allocations
    run_without()
    differences = [_seconds(run_with) - _seconds(run_without) for _ in range(repeats)]
    return statistics.median(differences), median_interval(differences)


def stage_costs(scene, backend: str = "numpy", size: tuple[int, int] = (320, 480), *,
                repeats: int = 5) -> StageCosts:
    """Time the plan of ``scene`` and each switch on or off, on one backend.

    Args:
        scene: a :class:`~gpu_blur.scene.Scene` or what :func:`gpu_blur.scene.load_scene` takes.
        backend: a backend spec (``numpy``, ``opencl:P:D``, ``warp:cpu``, ``warp:cuda:0``).
        size: (height, width) of the input (even sides: the RAW round trip's Bayer cells).
        repeats: timed runs per figure (their median is taken).
    """
    from gpu_blur.backends import get_backend
    from gpu_blur.backends.flows import with_flows
    from gpu_blur.cameras import scene_camera
    from gpu_blur.params import draw_params
    from gpu_blur.scene import load_scene
    from gpu_blur.synthesis.inputs import reaches_clip_level
    from gpu_blur.tiling import Region

    if not hasattr(scene, "blur"):
        scene = load_scene(scene)
    h, w = size
    if h % 2 or w % 2 or min(h, w) < 16:
        raise ValueError(f"--size {w}x{h}: both sides must be even and at least 16 (the RAW "
                         "round trip's 2 x 2 Bayer cells, the optical flow's smallest frame)")
    runner = get_backend(backend, scene.output.precision)
    camera = scene_camera(scene, runner.name)
    frames, mask = bench_inputs(scene, w, h)
    p = plan(scene, saturated=reaches_clip_level(frames, mask), size=(h, w))
    region = Region.whole(h, w)
    # every switch's values are drawn, so a plan with any of them on finds its parameters
    params = draw_params(scene, every_stage_on(p), camera, seed=0, sample_index=0,
                         image_shape=(h, w))
    wait = getattr(runner, "wait", lambda: None)

    def accumulate():
        out = runner.accumulate(p, params, frames, mask, region)
        wait()
        return out

    t_accumulate = _median_time(accumulate, repeats)  # flows included: the pass's host part
    params = with_flows(p, params, frames)
    linear, sat_mask = accumulate()

    def passes(variant: Plan):
        def run():
            image, saturated = runner.to_raw(variant, params, camera, linear, sat_mask,
                                             seed=0, sample_index=0)
            runner.finish(variant, params, camera, image, saturated, region, region, seed=0,
                          sample_index=0)
            wait()
        return run

    switches, intervals = {}, {}
    for name in SWITCHES:
        # the switch alone: with the switches that need it off, and those it needs on
        kept, base = switch_kept(p, name), p
        if kept:
            for other, (_, needs) in SWITCHES.items():
                if name in needs:
                    base = switch_off(base, other)
            pair = base, switch_off(base, name)
        else:
            for need in SWITCHES[name][1]:
                base = switch_on(base, need)
            pair = switch_on(base, name), base
        seconds, intervals[name] = _median_difference(*map(passes, pair), repeats)
        switches[name] = (kept, seconds)
    t_plan = _median_time(passes(p), repeats)
    added, intervals["every stage"] = _median_difference(passes(every_stage_on(p)), passes(p),
                                                         repeats)
    t_forced = t_plan + added
    shown = {k: v for k, v in params.items() if k != "flows" and not isinstance(v, np.ndarray)}
    return StageCosts(backend, runner.device, (h, w), t_accumulate, t_plan, t_forced, switches,
                      shown, intervals)


def cost_text(seconds: float, interval: tuple[float, float] | None) -> str:
    """A measured difference in words, never a negative cost.

    ``12.3 ms`` when its interval lies above 0; ``within noise (< 2.1 ms)`` when it holds 0
    (the interval's top, the most it may cost; ``< 0.1 ms`` below that); ``none (3.0 ms
    faster with it)`` when it lies below 0.
    """
    low, high = interval if interval is not None else (seconds, seconds)
    ms = 1e3
    if low > 0:
        return f"{seconds * ms:.1f} ms"
    if high < 0:
        return f"none ({-seconds * ms:.1f} ms faster with it)"
    return f"within noise (< {max(high * ms, 0.1):.1f} ms)"


def format_costs(costs: StageCosts, p: Plan) -> str:
    """The cost report under ``gpu-blur plan --cost``."""
    ms = 1e3
    h, w = costs.size
    blur = p[S.BLUR]
    lines = [f"cost on {costs.backend} ({costs.device}), {w} x {h} px, medians of timed runs "
             "after a warm-up:",
             f"  accumulate pass (linearize + blur{f' [{blur.variant}]' if blur.kept else ''}, "
             f"one pass): {costs.accumulate * ms:.1f} ms"]
    factors = costs.params.get("interpolation_factors")
    if factors is not None:
        lines.append(f"  interpolation auto: factors per gap {factors} on the bench input "
                     "(the photo panned 2 px a frame)")
    lines.append(f"  to_raw + finish passes: {costs.passes * ms:.1f} ms with the plan")
    width = max(len(n) for n in SWITCHES)
    texts = {name: cost_text(seconds, costs.intervals.get(name))
             for name, (_, seconds) in costs.switches.items()}
    text_width = max(len(t) for t in texts.values())
    for name, (kept, _) in costs.switches.items():
        stages = ", ".join(SWITCHES[name][0])
        what = "costs     " if kept else "would cost"
        lines.append(f"    {'run ' if kept else 'skip'} {name:<{width}}  {what} "
                     f"{texts[name]:>{text_width}}  ({stages})")
    forced = costs.intervals.get("every stage")
    if costs.every_stage > costs.with_plan and (forced is None or forced[0] > 0):
        saved = f"the plan saves {1 - costs.with_plan / costs.every_stage:.0%}"
    else:
        saved = "the plan saves nothing measurable here"
    note = ("Stages of one fused pass cannot be timed alone: each figure is the median of the "
            "to_raw + finish time with the stages on less the time with them off, runs taken "
            "in turns; 'within noise' where that median's interval (order statistics, at least "
            f"{CONFIDENCE:.0%} coverage) holds 0, with the most it may cost. numpy runs the "
            "stages one by one and is timed the same way.")
    lines += [f"  all passes: {costs.with_plan * ms:.1f} ms with the plan, "
              f"{costs.every_stage * ms:.1f} ms with every stage forced on ({saved})",
              textwrap.fill(note, 100)]
    return "\n".join(lines)
