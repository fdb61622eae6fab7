"""Every module of the package names its public surface in ``__all__`` (read with ast).

A name in ``__all__`` must be bound at the module's top level (defined there, or imported: a
package's ``__init__`` re-exports); ``__main__`` modules are scripts and have none.
"""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import ROOT

PACKAGE = ROOT / "gpu_blur"


def package_modules() -> list[Path]:
    return [p for p in sorted(PACKAGE.rglob("*.py"))
            if "__pycache__" not in p.parts and p.name != "__main__.py"]


def top_level_bindings(tree: ast.Module) -> set[str]:
    """The names a module's top-level statements bind (in if/try blocks too)."""
    bound: set[str] = set()
    statements = list(tree.body)
    while statements:
        node = statements.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            bound.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            bound.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
        elif isinstance(node, (ast.If, ast.Try)):
            statements += node.body + node.orelse + getattr(node, "finalbody", [])
            statements += [s for h in getattr(node, "handlers", []) for s in h.body]
    return bound


def declared(tree: ast.Module) -> list[str] | None:
    """The module's ``__all__`` (a literal list or tuple of strings), None without one."""
    for node in tree.body:
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, ast.AnnAssign) else [])
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            return list(ast.literal_eval(node.value))
    return None


def test_every_module_declares_all_and_each_name_is_bound():
    problems = []
    for path in package_modules():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        names = declared(tree)
        where = path.relative_to(ROOT).as_posix()
        if names is None:
            problems.append(f"{where}: no __all__")
            continue
        unbound = sorted(set(names) - top_level_bindings(tree))
        if unbound:
            problems.append(f"{where}: __all__ names unbound {unbound}")
        if len(set(names)) != len(names):
            problems.append(f"{where}: __all__ repeats a name")
    assert problems == []


def test_the_checks_see_a_missing_all_and_an_unbound_name():
    tree = ast.parse('import os\n\n__all__ = ["os", "f", "g"]\n\n\ndef f():\n    pass\n')
    assert declared(tree) == ["os", "f", "g"]
    assert set(declared(tree)) - top_level_bindings(tree) == {"g"}
    assert declared(ast.parse("x = 1\n")) is None
