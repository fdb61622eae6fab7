"""``gpu-blur plan --cost``: switching stages on and off, and the cost report."""

from __future__ import annotations

import pytest

from gpu_blur.analysis.stage_cost import (
    SWITCHES,
    every_stage_on,
    stage_costs,
    switch_off,
    switch_on,
)
from gpu_blur.backends.kernel import pass_config
from gpu_blur.cli import main
from gpu_blur.planning import PASSES, StageName, plan


def test_every_stage_on_keeps_every_switch_with_runnable_options():
    p = every_stage_on(plan("minimal", size=(32, 48)))
    for stages, _ in SWITCHES.values():
        assert all(p.kept(s) for s in stages)
    assert p.retone_curve == "polynomial"  # minimal's output.crf = srgb has no retone curve
    assert pass_config(p, PASSES[2]).bits == 8
    assert plan("minimal").kept(StageName.BLUR) == p.kept(StageName.BLUR)  # blur stays


def test_switching_the_raw_round_trip_off_switches_its_noise_off_and_on_again():
    p = plan("rsblur", size=(32, 48))
    off = switch_off(p, "raw round trip")
    assert not off.raw_round_trip and not off.kept(StageName.POISSON_GAUSSIAN_NOISE)
    on = switch_on(off, "poisson_gaussian_noise")
    assert on.raw_round_trip and on.kept(StageName.POISSON_GAUSSIAN_NOISE)


def test_stage_costs_time_every_switch_and_the_plan_against_every_stage_on():
    costs = stage_costs("rsblur", "numpy", (32, 48), repeats=1)
    assert set(costs.switches) == set(SWITCHES)
    assert costs.switches["raw round trip"][0] and not costs.switches["gaussian_noise"][0]
    # times, not their signs: a difference of two timings under load may be negative
    assert all(isinstance(t, float) and t == t for t in (costs.with_plan, costs.every_stage))


def test_plan_cost_prints_each_switch_and_the_saving(capsys):
    assert main(["plan", "minimal", "--cost", "--size", "48x32"]) == 0
    out = capsys.readouterr().out
    assert "cost on numpy" in out and "48 x 32 px" in out
    for name in SWITCHES:
        assert name in out
    assert "with every stage forced on" in out
    assert "cannot be timed alone" in out


@pytest.mark.parametrize("size", ["48x31", "48by32"])
def test_plan_cost_refuses_a_bad_size(size, capsys):
    assert main(["plan", "minimal", "--cost", "--size", size]) == 2
    assert "--size" in capsys.readouterr().err
