"""Run the runnable code blocks of one Markdown page, in order, in one fresh process.

``python page_runner.py SPEC.json RESULTS.json``, in the page's working folder. SPEC is a list
of blocks, each ``{"id": "README.md:57", "path": "README.md", "line": 57, "kind": "python" or
"doctest" or "shell", "code": ..., "commands": [[command, expected output or null], ...]}``.
Python blocks run with ``exec`` in one namespace, so a block may use what an earlier one of its
page defined; shell commands run with bash in the working folder. After a block fails, the
rest of the page is not run. RESULTS (rewritten after every block, so a timeout leaves what
ran): id -> {"status": "passed" | "failed" | "not run", "seconds": ..., "why": ...}.

Used by ``test_examples.py``; it imports nothing from the tests.
"""

from __future__ import annotations

import contextlib
import doctest
import io
import json
import os
import re
import subprocess
import sys
import time
import traceback

#: Most seconds one shell command may take.
COMMAND_TIMEOUT = 300


def output_matches(expected: str, actual: str) -> bool:
    """Whether ``actual`` is the shown output, ``...`` standing for any text (doctest's rule).

    Trailing spaces and blank lines at either end do not count.
    """
    def tidy(text: str) -> str:
        return "\n".join(line.rstrip() for line in text.strip("\n").splitlines())

    pattern = ".*?".join(re.escape(part) for part in tidy(expected).split("..."))
    return re.fullmatch(pattern, tidy(actual), re.DOTALL) is not None


def run_shell(block: dict) -> str:
    """Run a block's commands; the log of what they printed. Raises on the first failure."""
    log = []
    for command, expected in block["commands"]:
        try:
            done = subprocess.run(["bash", "-c", command], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, timeout=COMMAND_TIMEOUT)
        except subprocess.TimeoutExpired as e:
            raise AssertionError(f"$ {command}\ntook more than {COMMAND_TIMEOUT} s") from e
        log.append(f"$ {command}\n{done.stdout}")
        if expected is not None and not output_matches(expected, done.stdout):
            raise AssertionError(f"$ {command}\nprinted:\n{done.stdout}\nbut the page shows:\n"
                                 f"{expected}\n(exit status {done.returncode})")
        if done.returncode and expected is None:
            raise AssertionError(f"$ {command}\nexit status {done.returncode}:\n{done.stdout}")
    return "".join(log)


def run_python(block: dict, namespace: dict) -> str:
    """Execute a block in the page's namespace; what it printed."""
    # line numbers in tracebacks are the page's own: the code starts after its fence line
    code = compile("\n" * block["line"] + block["code"], block["path"], "exec")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(code, namespace)
    return printed.getvalue()


def run_doctest(block: dict, namespace: dict) -> str:
    """Run a ``>>>`` block in the page's namespace, ``...`` and spacing as doctest allows."""
    test = doctest.DocTestParser().get_doctest(block["code"], namespace, block["id"],
                                               block["path"], block["line"])
    report = io.StringIO()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test, out=report.write, clear_globs=False)
    if runner.failures:
        raise AssertionError(report.getvalue())
    return ""


def main(spec_path: str, results_path: str) -> int:
    """Run every block of the spec; 0 when all passed."""
    with open(spec_path) as f:
        blocks = json.load(f)
    namespace = {"__name__": "__main__"}
    results, failed = {}, None
    for block in blocks:
        if failed is not None:
            results[block["id"]] = {"status": "not run",
                                    "why": f"{failed} failed first (blocks of a page run in order)"}
            continue
        start = time.perf_counter()
        try:
            if block["kind"] == "shell":
                printed = run_shell(block)
            elif block["kind"] == "doctest":
                printed = run_doctest(block, namespace)
            else:
                printed = run_python(block, namespace)
            results[block["id"]] = {"status": "passed", "printed": printed[-4000:]}
        except BaseException:  # noqa: B036 (a block's SystemExit is its failure too)
            results[block["id"]] = {"status": "failed", "why": traceback.format_exc(limit=-8)}
            failed = block["id"]
        results[block["id"]]["seconds"] = round(time.perf_counter() - start, 2)
        with open(results_path + ".part", "w") as f:
            json.dump(results, f)
        os.replace(results_path + ".part", results_path)
    with open(results_path, "w") as f:
        json.dump(results, f)
    return 0 if failed is None else 1


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
