"""Every code block of README.md and docs/**/*.md runs as written, or says why it cannot.

The convention (tests/docs/README.md has it at more length):

* ```python blocks run; the blocks of one page run in order in one fresh process, in one
  temporary working folder, so a block may use what an earlier block of its page made. A
  block of ``>>>`` lines runs as a doctest (its shown output is checked).
* ```console / ```bash / ```sh / ```shell blocks run their ``gpu-blur`` commands with the
  installed command, in that folder. With ``$ `` prompts, the lines after a command are the
  output it must print (``...`` stands for any text); without prompts every line is a command
  and only its exit status is checked. A command other than ``gpu-blur`` cannot run here.
* ```toml and ```json blocks are parsed; a TOML block of scene sections is loaded as a scene.
* A block that cannot run here (installs packages, needs a GPU, a data set or minutes) has
  the line ``<!-- excerpt: why -->`` right before its fence; it is only checked for syntax.
* Other languages (``text``, ``bibtex``, ...) are shown, not run; a fence without a language
  fails: give it one (``text`` for output and diagrams).

Each block is one test, named by its page and the line of its fence (``README.md:57``).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RUNNER = Path(__file__).with_name("page_runner.py")

PYTHON = {"python", "py", "pycon"}
SHELL = {"console", "bash", "sh", "shell", "shell-session"}
PARSED = {"toml", "json"}
#: Most seconds the blocks of one page may take together.
PAGE_TIMEOUT = 600

FENCE = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`]*)$")
MARKER = re.compile(r"^\s*<!--\s*excerpt\s*:(?P<reason>.*?)-->\s*$")
MARKER_LIKE = re.compile(r"<!--\s*excerpt\b")
#: pymdownx.snippets' include line inside a block (mkdocs.yml: base_path is the repository).
SNIPPET = re.compile(r'^\s*-+8<-+\s+"(?P<file>[^":]+)(?::(?P<start>\d*)(?::(?P<end>\d*))?)?"\s*$')


@dataclasses.dataclass(frozen=True)
class Block:
    """One fenced block of a page."""

    path: str  # relative to the repository root, with /
    line: int  # of the opening fence, 1-based
    lang: str
    code: str
    excerpt: str | None  # the marker's reason; None: no marker

    @property
    def id(self) -> str:
        """``page:line``, the test's name."""
        return f"{self.path}:{self.line}"

    @property
    def kind(self) -> str:
        """What is done with it: python, doctest, shell, parsed, shown or unlabeled."""
        if self.lang in PYTHON:
            doctest_lines = self.lang == "pycon" or self.code.lstrip().startswith(">>>")
            return "doctest" if doctest_lines else "python"
        if self.lang in SHELL:
            return "shell"
        if self.lang in PARSED:
            return "parsed"
        return "shown" if self.lang else "unlabeled"


def pages() -> list[Path]:
    """README.md and every Markdown page under docs/ (as many as there are now)."""
    found = [ROOT / "README.md"] if (ROOT / "README.md").exists() else []
    return found + sorted(p for p in (ROOT / "docs").rglob("*.md") if p.is_file())


def read_blocks(path: Path) -> tuple[list[Block], list[str]]:
    """The fenced blocks of a page, and the problems of its excerpt markers."""
    rel = path.relative_to(ROOT).as_posix()
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, problems, i = [], [], 0
    pending = None  # (line, reason) of a marker not yet followed by its fence
    while i < len(lines):
        text = lines[i]
        marker = MARKER.match(text)
        if marker:
            if pending is not None:
                problems.append(f"{rel}:{pending[0]}: an excerpt marker with no fence after it")
            pending = (i + 1, marker["reason"].strip())
            i += 1
            continue
        if MARKER_LIKE.search(text):
            problems.append(f"{rel}:{i + 1}: write the marker as <!-- excerpt: reason --> on a "
                            "line of its own")
        fence = FENCE.match(text)
        if not fence:
            if text.strip() and pending is not None:
                problems.append(f"{rel}:{pending[0]}: an excerpt marker must be the line right "
                                "before its fence")
                pending = None
            i += 1
            continue
        indent, mark = len(fence["indent"]), fence["fence"]
        lang = fence["info"].strip().split()[0].lstrip(".").lower() if fence["info"].strip() \
            else ""
        close = re.compile(rf"^ *{re.escape(mark[0])}{{{len(mark)},}}\s*$")
        body, j = [], i + 1
        while j < len(lines) and not close.match(lines[j]):
            line = lines[j]
            body.extend(included(line) or [line[indent:] if line[:indent].strip() == ""
                                           else line.lstrip()])
            j += 1
        excerpt = pending[1] if pending is not None else None
        blocks.append(Block(rel, i + 1, lang, "\n".join(body) + "\n", excerpt))
        pending = None
        i = j + 1
    if pending is not None:
        problems.append(f"{rel}:{pending[0]}: an excerpt marker with no fence after it")
    return blocks, problems


def included(line: str) -> list[str] | None:
    """The lines a snippet include line stands for (as the site shows them), or None."""
    snippet = SNIPPET.match(line)
    if not snippet:
        return None
    lines = (ROOT / snippet["file"]).read_text(encoding="utf-8").splitlines()
    start, end = int(snippet["start"] or 1), int(snippet["end"] or len(lines))
    return lines[start - 1:end]  # lines start to end, 1-based, either side left out: the end


def shell_commands(block: Block) -> list[tuple[str, str | None]]:
    """(command, output it must print or None) for each command of a shell block.

    With ``$ `` prompts, lines after a command up to the next prompt are its output; a line
    ending in a backslash continues the command. Without prompts every line that is not blank
    or a ``#`` comment is a command.
    """
    lines = block.code.splitlines()
    prompted = any(line.startswith("$ ") or line == "$" for line in lines)
    commands: list[list] = []
    continued = False
    for line in lines:
        if continued:
            commands[-1][0] += "\n" + line
            continued = line.endswith("\\")
        elif prompted and line.startswith("$"):
            commands.append([line[1:].strip(), []])
            continued = line.endswith("\\")
        elif prompted:
            if commands:
                commands[-1][1].append(line)
        elif line.strip() and not line.lstrip().startswith("#"):
            commands.append([line.strip(), None])
            continued = line.endswith("\\")
    return [(c, "\n".join(out) if prompted else None) for c, out in commands]


def runnable(block: Block) -> bool:
    """Whether the block runs in its page's process."""
    return block.excerpt is None and block.kind in ("python", "doctest", "shell")


ALL = {path: read_blocks(path) for path in pages()}
BLOCKS = [b for blocks, _ in ALL.values() for b in blocks if b.kind != "shown"]


#: Pages run at the same time, each in its own process and folder (its blocks in order there):
#: a page's run is mostly one process on one core, and the tests only wait for it.
PARALLEL_PAGES = max(1, min(4, os.cpu_count() or 1))


def uses_its_page(block: Block) -> bool:
    """Whether ``test_block`` asks for the block's page run (it runs, as written, here)."""
    return block.excerpt is None and runnable(block) and unrunnable(block) is None


@pytest.fixture(scope="session")
def page_results(request, tmp_path_factory):
    """page -> (its blocks' results, the runner's output).

    Every page that a selected test asks for starts on first use, in the tests' order,
    PARALLEL_PAGES at a time; a test waits for its own page only.
    """
    pages = []
    for item in request.session.items:
        block = getattr(item, "callspec", None) and item.callspec.params.get("block")
        if isinstance(block, Block) and uses_its_page(block) and block.path not in pages:
            pages.append(block.path)
    running: dict[str, subprocess.Popen] = {}
    closing = threading.Event()

    def run(path: str, folder: Path) -> tuple[dict, str]:
        blocks = [b for b in ALL[ROOT / path][0] if runnable(b) and not unrunnable(b)]
        spec, out = folder / ".blocks.json", folder / ".results.json"
        spec.write_text(json.dumps([{
            "id": b.id, "path": b.path, "line": b.line, "kind": b.kind, "code": b.code,
            "commands": shell_commands(b) if b.kind == "shell" else []} for b in blocks]))
        env = dict(os.environ, MPLBACKEND="Agg", PYTHONUNBUFFERED="1",
                   PATH=os.pathsep.join([str(Path(sys.executable).parent),
                                         os.environ.get("PATH", "")]))
        if closing.is_set():
            return {}, "not run: the session ended first"
        process = subprocess.Popen([sys.executable, str(RUNNER), str(spec), str(out)],
                                   cwd=folder, env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, text=True)
        running[path] = process
        try:
            printed, _ = process.communicate(timeout=PAGE_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            printed = f"the page took more than {PAGE_TIMEOUT} s\n{process.communicate()[0]}"
        finally:
            running.pop(path, None)
        found = json.loads(out.read_text()) if out.exists() else {}
        return found, printed

    pool = concurrent.futures.ThreadPoolExecutor(PARALLEL_PAGES, "docs-page")
    started: dict[str, concurrent.futures.Future] = {}

    def results(path: str) -> tuple[dict, str]:
        for page in [*pages, path]:  # the first use starts them all, in the tests' order
            if page not in started:
                folder = tmp_path_factory.mktemp(re.sub(r"\W", "_", page))
                started[page] = pool.submit(run, page, folder)
        return started[path].result()

    yield results
    closing.set()
    for process in list(running.values()):
        process.kill()
    pool.shutdown(wait=True, cancel_futures=True)


def unrunnable(block: Block) -> str | None:
    """Why an unmarked block cannot run here, or None."""
    if block.kind == "unlabeled":
        return ("a fence without a language: give it one (python, console, toml, text for "
                "output and diagrams)")
    if block.kind == "shell":
        commands = shell_commands(block)
        if not commands:
            return "a shell block without a command"
        for command, _ in commands:
            if command != "gpu-blur" and not command.startswith("gpu-blur "):
                return (f"runs {command.split()[0]!r}: only gpu-blur commands run here; mark the "
                        "block <!-- excerpt: why --> on the line before its fence")
    return None


def check_syntax(block: Block) -> None:
    """An excerpt's syntax: python compiles, shell commands parse, TOML and JSON load."""
    if block.kind in ("python", "doctest"):
        if block.kind == "doctest":
            import doctest

            source = "".join(e.source for e in doctest.DocTestParser().get_examples(block.code))
        else:
            source = block.code
        compile("\n" * block.line + source, block.path, "exec")
    elif block.kind == "shell":
        for command, _ in shell_commands(block):
            done = subprocess.run(["bash", "-n", "-c", command], stderr=subprocess.PIPE,
                                  text=True)
            assert done.returncode == 0, f"{block.id}: {command!r} does not parse:\n{done.stderr}"
    elif block.kind == "parsed":
        parse(block)


def parse(block: Block):
    """A TOML or JSON block's data; a TOML block of scene sections loads as a scene."""
    if block.lang == "json":
        return json.loads(block.code)
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib
    data = tomllib.loads(block.code)
    from gpu_blur.scene import FIELDS, load_scene

    if block.excerpt is None and data and set(data) <= set(FIELDS):
        load_scene(data)
    return data


@pytest.mark.parametrize("path", [p.relative_to(ROOT).as_posix() for p in ALL])
def test_excerpt_markers_say_why_and_stand_before_their_fence(path):
    blocks, problems = ALL[ROOT / path]
    problems = problems + [f"{b.id}: <!-- excerpt: --> without a reason: say why it cannot run"
                           for b in blocks if b.excerpt == ""]
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_block(block, page_results):
    if block.excerpt is not None:
        assert block.excerpt, f"{block.id}: <!-- excerpt: --> needs a reason"
        check_syntax(block)
        return
    why = unrunnable(block)
    assert why is None, f"{block.id}: {why}"
    if block.kind == "parsed":
        parse(block)
        return
    results, printed = page_results(block.path)
    result = results.get(block.id)
    assert result is not None, f"{block.id}: the page's run ended before it:\n{printed[-6000:]}"
    assert result["status"] == "passed", f"{block.id}: {result['status']}:\n{result['why']}"
