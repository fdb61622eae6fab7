"""The documentation site cannot drift from the code: what it generates, and what it names.

The site (mkdocs.yml, docs/) fills its ``<!-- gen: ... -->`` markers when it is built
(docs/gen/render.py, through the hook docs/gen/hooks.py): the ``--help`` of every subcommand,
the scene key reference from ``gpu_blur.scene.FIELDS``, the built-in cameras, the tolerance
rows and every benchmark table from ``bench/results``. These tests run the same generator
without mkdocs, so a renamed subcommand, scene key, results file or results field fails here
as well as in ``mkdocs build --strict`` (.ci/run). They also check that every page names
files and Python objects that exist.
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from pathlib import Path

import pytest

from gpu_blur.cli import COMMANDS
from gpu_blur.scene import FIELDS

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.rglob("*.md"))


def _render():
    spec = importlib.util.spec_from_file_location("gpu_blur_docs_render",
                                                  DOCS / "gen" / "render.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


render = _render()


def _page(rel: str) -> str:
    return (DOCS / rel).read_text(encoding="utf-8")


def _rel(page: Path) -> str:
    return page.relative_to(DOCS).as_posix()


def test_every_subcommand_has_a_page_in_the_nav_showing_its_help():
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    pages = {p.stem for p in (DOCS / "cli").glob("*.md")} - {"index"}
    assert pages == set(COMMANDS), "docs/cli/ should have one page per subcommand"
    for name in COMMANDS:
        assert f"<!-- gen: cli-help {name} -->" in _page(f"cli/{name}.md"), name
        assert f"cli/{name}.md" in nav, f"mkdocs.yml's nav lacks cli/{name}.md"


@pytest.mark.parametrize("name", COMMANDS)
def test_the_help_shown_is_the_commands_own(name, capsys):
    from gpu_blur.cli import main

    shown = render.cli_help(name).splitlines()
    assert shown[0] == "```text" and shown[1] == f"$ gpu-blur {name} --help"
    with pytest.raises(SystemExit):
        main([name, "--help"])
    printed = capsys.readouterr().out
    # the same text, whatever width this terminal wraps it at (argparse breaks at hyphens too)
    assert "".join("".join(shown[2:-1]).split()) == "".join(printed.split())


def test_the_scene_page_lists_every_key_with_its_default():
    assert "<!-- gen: scene-keys -->" in _page("scenes.md")
    text = render.scene_keys()
    for section, fields in FIELDS.items():
        assert f"### `[{section}]`" in text
        for key, field in fields.items():
            row = next((line for line in text.splitlines()
                        if line.startswith(f"| `{section}.{key}` |")), None)
            assert row is not None, f"{section}.{key} is missing from the scene reference"
            if field.default is not None:
                assert render._toml(field.default) in row, f"{section}.{key}'s default"
    keys = sum(len(f) for f in FIELDS.values())
    assert text.count("\n| `") == keys, "a row for a key the scene does not have"


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_every_marker_of_a_page_renders(page):
    """A marker naming a gone subcommand, results file or results field fails here."""
    text = page.read_text(encoding="utf-8")
    out = render.render_page(text, _rel(page).count("/"))
    assert "<!-- gen:" not in out
    for m in render.MARKER.finditer(text):
        assert m["kind"] in ("cli-help", "cli-commands", "scene-keys", "cameras",
                             "tolerances", "bench", "accuracy", "image", "file")


@pytest.mark.parametrize("name", sorted(render.BENCH))
def test_every_benchmark_table_names_its_device_and_commit(name):
    args = {"multi-gpu": ["multi_gpu_h200x4"], "plan-cost": ["plan_cost_cpu"],
            "interpolation": ["interpolation_auto_cpu"],
            "history": ["user_paths_h200"]}.get(name, [])
    text = render.BENCH[name](*args)
    provenance = [line for line in text.splitlines() if "`bench/results/" in line]
    assert provenance, f"{name}: no line naming its results file"
    for line in provenance:
        assert "recorded in" in line, line
        assert re.search(r"\b[0-9a-f]{7}\b|no git history|not yet committed", line), line


def test_the_performance_page_types_no_figure_of_its_own_above_the_recorded_notes():
    """Figures above the notes on commits come from the results files, not from the page."""
    text = _page("performance.md")
    generated = text.split("## Why the code is so")[0]
    prose = "\n".join(line for line in generated.splitlines()
                      if not line.startswith("<!-- gen:"))
    assert not re.search(r"\d+(\.\d+)? ?(ms|s|samples/s|GB/s|%)\b", prose), \
        "a measured figure typed into docs/performance.md: generate it from bench/results"


PATH = re.compile(r"`((?:gpu_blur|tests|bench|kernels|docs|\.ci)/[\w./*-]*)`")


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_files_a_page_names_exist(page):
    missing = []
    for m in PATH.finditer(page.read_text(encoding="utf-8")):
        name = m.group(1).rstrip(".")
        if not any(ROOT.glob(name)) and not (ROOT / name).exists():
            missing.append(name)
    assert not missing, f"docs/{_rel(page)} names files that do not exist: {missing}"


OBJECT = re.compile(r"^::: ([\w.]+)\s*$", re.M)


@pytest.mark.parametrize("page", [p for p in PAGES if OBJECT.search(p.read_text())], ids=_rel)
def test_api_blocks_name_importable_objects(page):
    for name in OBJECT.findall(page.read_text(encoding="utf-8")):
        module, _, attr = name.rpartition(".")
        try:
            target = importlib.import_module(name)
        except ImportError:
            target = getattr(importlib.import_module(module), attr, None)
        assert target is not None, f"docs/{_rel(page)}: ::: {name} names nothing"
        assert getattr(target, "__doc__", None), f"docs/{_rel(page)}: {name} has no docstring"
