"""Every stage has its row in gpu_blur.stages.STAGES, and every row its parts.

A row's parts: a :class:`~gpu_blur.stages.Pass`, reference functions that exist, a cost switch
for a stage of the to_raw or finish pass (a stage without one would never be costed by
``gpu-blur plan --cost``), values read from scene keys that exist. :func:`problems` lists what
is missing; the tests run it on the registry and on registries broken on purpose.
"""

from __future__ import annotations

import dataclasses
import importlib

import pytest

from gpu_blur.analysis.stage_cost import NEEDS, SWITCHES
from gpu_blur.planning import plan
from gpu_blur.scene import FIELDS, builtin_scenes, load_scene
from gpu_blur.stages import SIZE, STAGES, Pass, StageName, StageSpec, stage_values

#: Passes whose stages are timed on their own, through a cost switch.
SWITCHED_PASSES = (Pass.TO_RAW, Pass.FINISH)


def resolves(dotted: str) -> bool:
    """Whether ``dotted`` (``package.module.name``) names a callable that can be imported."""
    module, _, name = dotted.rpartition(".")
    try:
        return callable(getattr(importlib.import_module(module), name, None))
    except ImportError:
        return False


def problems(specs: tuple[StageSpec, ...], switches=SWITCHES) -> list[str]:
    """What ``specs`` lacks, in words (empty when every stage has every part)."""
    found = []
    names = [s.name for s in specs]
    if names != list(StageName):
        found.append(f"rows {names} are not one per StageName in its order {list(StageName)}")
    for s in specs:
        if not isinstance(s.pass_, Pass):
            found.append(f"{s.name}: pass {s.pass_!r} is not a Pass")
        if not s.reference:
            found.append(f"{s.name}: no reference function")
        found += [f"{s.name}: reference {r!r} does not exist" for r in s.reference
                  if not resolves(r)]
        if s.pass_ in SWITCHED_PASSES and s.switch not in switches:
            found.append(f"{s.name}: a {s.pass_} stage with no cost switch ({s.switch!r} is "
                         f"not one of {list(switches)})")
        if s.pass_ not in SWITCHED_PASSES and s.switch is not None:
            found.append(f"{s.name}: a {s.pass_} stage is not timed alone, yet has switch "
                         f"{s.switch!r}")
        found += [f"{s.name}: value {key!r} is neither a scene key nor SIZE" for key in s.values
                  if key != SIZE and key.partition(".")[2] not in FIELDS.get(
                      key.partition(".")[0], {})]
    return found


def test_every_stage_has_every_part():
    assert problems(STAGES) == []


def _without(name: StageName) -> tuple[StageSpec, ...]:
    return tuple(s for s in STAGES if s.name != name)


def _changed(name: StageName, **changes) -> tuple[StageSpec, ...]:
    return tuple(dataclasses.replace(s, **changes) if s.name == name else s for s in STAGES)


@pytest.mark.parametrize("broken, expected", [
    (_without(StageName.TONE), "not one per StageName"),
    (STAGES[::-1], "not one per StageName"),
    (_changed(StageName.TONE, pass_="finish"), "is not a Pass"),
    (_changed(StageName.TONE, reference=()), "no reference function"),
    (_changed(StageName.TONE, reference=("gpu_blur.reference.transfer.no_such",)),
     "does not exist"),
    (_changed(StageName.TONE, reference=("gpu_blur.reference.no_such.linear_to_srgb",)),
     "does not exist"),
    (_changed(StageName.TONE, switch=None), "no cost switch"),
    (_changed(StageName.TONE, switch="no such switch"), "no cost switch"),
    (_changed(StageName.CROP, switch="tone"), "not timed alone"),
    (_changed(StageName.VIGNETTING, values=("optics.no_such", SIZE)), "neither a scene key"),
], ids=["missing", "out of order", "pass", "no reference", "no function", "no module",
        "no switch", "unknown switch", "host switch", "unknown value"])
def test_a_missing_part_is_found(broken, expected):
    assert any(expected in p for p in problems(broken)), problems(broken)


def test_a_stage_whose_switch_is_not_costed_is_found():
    switches = {k: v for k, v in SWITCHES.items() if k != "tone"}
    assert any("tone: a finish stage with no cost switch" in p
               for p in problems(STAGES, switches))


def test_switches_are_the_rows_switches():
    assert set(SWITCHES) == {s.switch for s in STAGES if s.switch is not None}
    for name, (stages, needs) in SWITCHES.items():
        assert stages == tuple(s.name for s in STAGES if s.switch == name)
        assert set(needs) <= set(SWITCHES)
    assert set(NEEDS) <= set(SWITCHES)


@pytest.mark.parametrize("scene", sorted(builtin_scenes()))
def test_a_plan_follows_the_rows(scene):
    settings, size = load_scene(scene), (48, 64)
    p = plan(settings, size=size)
    assert [s.name for s in p.stages] == [s.name for s in STAGES]
    for stage, spec in zip(p.stages, STAGES, strict=True):
        assert stage.pass_ is spec.pass_
        assert stage.values == stage_values(spec, settings, size)
    assert p[StageName.VIGNETTING].values == (float(settings.optics.vignetting), 48.0, 64.0)
