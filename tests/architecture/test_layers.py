"""The package's layers, read from its import statements with ast (nothing is imported).

Layers (ARCHITECTURE.md, "Layers"), lowest first:

- ``gpu_blur.reference``: the float64 maths; imports nothing of ours but ``gpu_blur.constants``
  (and itself);
- ``gpu_blur.backends``: devices and passes; never the synthesis layer;
- the synthesis layer (``gpu_blur.synthesis``, ``gpu_blur.generate``, ``gpu_blur.generation``,
  ``gpu_blur.dataset``, ``gpu_blur.set_formats``, ``gpu_blur.discovery``): samples and data
  sets from the backends;
- ``gpu_blur.cli``: the command, which nothing else imports.

The synthesis layer reaches a backend only through ``gpu_blur.backends`` itself (its Protocols,
``get_backend`` and helpers): no synthesis module imports a concrete backend or a device
library directly (that package imports them, so the rule is on direct imports only).

``gpu_blur.testing`` is the tests' helpers: no module of the package imports it (the tolerance
rows the spot checks and ``gpu-blur validate`` use are ``gpu_blur.tolerances``).

The graph has an edge for every ``import`` and ``from ... import`` anywhere in a module (inside
functions too), to the module it names (``from gpu_blur.x import name`` is ``gpu_blur.x``;
``from gpu_blur import x`` is ``gpu_blur.x`` where that is a module, else ``gpu_blur``). The
parent packages Python runs first are not edges: ``gpu_blur/__init__.py`` imports the public
API of every layer, so ``import gpu_blur.reference.rng`` would otherwise reach everything. The
rules hold over the transitive closure: a backend that imports a module that imports the
synthesis layer breaks them too. Names are matched by prefix, so the rules hold for a module
and for a package of the same name (``gpu_blur/cli.py`` or ``gpu_blur/cli/``).
"""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest
from conftest import ROOT

PACKAGE = ROOT / "gpu_blur"

REFERENCE = ("gpu_blur.reference",)
#: What the reference may import besides itself. Known exceptions, none today: a module named
#: here is one the reference imported when this test was written, to be taken out.
REFERENCE_MAY_IMPORT = ("gpu_blur.constants",)
KNOWN_REFERENCE_EXCEPTIONS: tuple[str, ...] = ()
BACKENDS = ("gpu_blur.backends",)
SYNTHESIS = ("gpu_blur.synthesis", "gpu_blur.generate", "gpu_blur.generation",
             "gpu_blur.dataset", "gpu_blur.set_formats", "gpu_blur.discovery",
             "gpu_blur.blurred_inputs", "gpu_blur.input_folders", "gpu_blur.run_record")
CLI = ("gpu_blur.cli",)
TESTING = ("gpu_blur.testing",)
#: Concrete backends and device libraries, which the synthesis layer never imports directly: it
#: is typed against ``gpu_blur.backends.ResidentBackend`` and ``Backend`` instead.
CONCRETE_BACKENDS = ("gpu_blur.backends.kernel", "gpu_blur.backends.opencl",
                     "gpu_blur.backends.warp", "gpu_blur.backends.numpy", "warp", "pyopencl")
#: Allowed all the same: the host path renders the numpy backend's sharp reference with its
#: float64 re-toning (``gpu_blur.backends.numpy.retone``, a host function with no device).
SYNTHESIS_MAY_IMPORT = ("gpu_blur.backends.numpy",)
#: Known exceptions, module -> what it imports: ``gpu_blur.run_record`` records the device
#: libraries' versions in a set's run.json (``library_versions``), to be taken behind
#: gpu_blur.backends.
KNOWN_SYNTHESIS_EXCEPTIONS = {"gpu_blur.run_record": ("warp", "pyopencl")}


def within(name: str, prefixes: tuple[str, ...]) -> bool:
    """Whether ``name`` is one of ``prefixes`` or inside one (``a.b`` is in ``a``, ``ab`` not)."""
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def modules(package: Path) -> dict[str, list[Path]]:
    """Module name -> its files, for every module of ``package`` (a folder).

    Two files while a module becomes a package of the same name (``x.py`` and ``x/``).
    """
    found: dict[str, list[Path]] = {}
    for path in sorted(package.rglob("*.py")):
        if "__pycache__" not in path.parts:
            parts = path.relative_to(package.parent).with_suffix("").parts
            found.setdefault(".".join(parts[:-1] if parts[-1] == "__init__" else parts),
                             []).append(path)
    return found


def named(path: Path, name: str) -> set[str]:
    """Every name of ours that ``path`` (module ``name``) imports, resolved to absolute names."""
    return {n for n in imported(path, name) if within(n, ("gpu_blur",))}


def imported(path: Path, name: str) -> set[str]:
    """Every name ``path`` (module ``name``) imports, ours or not, resolved to absolute names."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the package, one level up per dot past the first
                parts = package[:len(package) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module
            found.update(base if alias.name == "*" else f"{base}.{alias.name}"
                         for alias in node.names)
    return found


def graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """Module -> the modules of ours it imports (each name to its longest module prefix)."""
    known = modules(package)

    def to_module(name: str) -> str:
        while name not in known:
            name = name.rpartition(".")[0]
        return name

    edges = {}
    for name, paths in known.items():
        edges[name] = {to_module(n) for path in paths for n in named(path, name)} - {name}
    return edges


def reached(edges: dict[str, set[str]], start: str) -> dict[str, list[str]]:
    """Every module ``start`` reaches, with a shortest import chain to it."""
    chains = {start: [start]}
    queue = [start]
    while queue:
        current = queue.pop(0)
        for target in sorted(edges.get(current, ())):
            if target not in chains:
                chains[target] = chains[current] + [target]
                queue.append(target)
    del chains[start]
    return chains


def direct_imports(package: Path, sources, forbidden, allowed=()) -> list[str]:
    """``module -> name`` for each name a module in ``sources`` imports itself from ``forbidden``.

    Not through other modules, unlike :func:`violations`: ``allowed`` names are left out.
    """
    found = []
    for name, paths in sorted(modules(package).items()):
        if within(name, sources):
            found += [f"{name} -> {n}" for n in sorted(set().union(
                *(imported(path, name) for path in paths)))
                if within(n, forbidden) and not within(n, allowed)]
    return found


def violations(edges, sources, forbidden) -> list[str]:
    """Import chains from a module for which ``sources(name)`` holds to a forbidden module."""
    found = []
    for name in sorted(edges):
        if not sources(name):
            continue
        for target, chain in sorted(reached(edges, name).items()):
            if forbidden(name, target):
                found.append(" -> ".join(chain))
    return found


@pytest.fixture(scope="module")
def edges():
    return graph()


def test_the_graph_sees_the_layers_it_checks(edges):
    assert any(within(n, REFERENCE) for n in edges) and any(within(n, BACKENDS) for n in edges)
    assert any(within(n, CLI) for n in edges) and any(within(n, SYNTHESIS) for n in edges)
    # relative imports resolve (reference/demosaic.py: "from .bayer import ...")
    assert "gpu_blur.reference.bayer" in edges["gpu_blur.reference.demosaic"]
    assert "gpu_blur.tolerances" in edges["gpu_blur.scheduler"]


def test_the_reference_imports_nothing_of_ours_but_constants(edges):
    allowed = REFERENCE + REFERENCE_MAY_IMPORT + KNOWN_REFERENCE_EXCEPTIONS
    found = violations(edges, lambda n: within(n, REFERENCE),
                       lambda _, target: not within(target, allowed))
    assert not found, "\n".join(found)


def test_backends_never_import_the_synthesis_layer_or_the_command(edges):
    found = violations(edges, lambda n: within(n, BACKENDS),
                       lambda _, target: within(target, SYNTHESIS + CLI))
    assert not found, "\n".join(found)


def test_synthesis_imports_no_concrete_backend_or_device_library():
    known = [f"{module} -> {n}" for module, names in KNOWN_SYNTHESIS_EXCEPTIONS.items()
             for n in names]
    found = direct_imports(PACKAGE, SYNTHESIS, CONCRETE_BACKENDS, SYNTHESIS_MAY_IMPORT)
    assert not set(found) - set(known), "\n".join(sorted(set(found) - set(known)))
    # each known exception still holds, so it is taken off this list once fixed
    assert set(known) <= set(found), sorted(set(known) - set(found))


def test_nothing_imports_the_command_but_itself(edges):
    found = violations(edges, lambda n: not within(n, CLI),
                       lambda _, target: within(target, CLI))
    assert not found, "\n".join(found)


def test_no_module_of_the_package_imports_the_tests_helpers(edges):
    found = violations(edges, lambda n: not within(n, TESTING),
                       lambda _, target: within(target, TESTING))
    assert not found, "\n".join(found)


def test_a_violating_import_is_caught(tmp_path):
    """The checks on a small package that breaks each rule, directly and through others."""
    package = tmp_path / "gpu_blur"
    files = {
        "__init__.py": "",
        "constants.py": "",
        "plan.py": "",
        "testing.py": "",
        "scheduler.py": "from gpu_blur import testing\n",
        "reference/__init__.py": "",
        "reference/rng.py": "from gpu_blur.constants import X\nfrom . import fixedmath\n",
        "reference/fixedmath.py": "import gpu_blur.plan\n",
        "backends/__init__.py": "",
        "backends/warp.py": "def f():\n    from gpu_blur.scheduler import g\n",
        "backends/opencl.py": "from ..synthesis.batches import Batch\n",
        "synthesis/__init__.py": "",
        "synthesis/batches.py": "from gpu_blur.backends import warp\n",
        "cli/__init__.py": "from gpu_blur.cli import main\n",
        "cli/main.py": "",
        "dataset.py": "from gpu_blur.cli.main import run\n",
    }
    for name, text in files.items():
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(text)
    small = graph(package)
    assert violations(small, lambda n: within(n, REFERENCE),
                      lambda _, t: not within(t, REFERENCE + REFERENCE_MAY_IMPORT)) == [
        "gpu_blur.reference.fixedmath -> gpu_blur.plan",
        "gpu_blur.reference.rng -> gpu_blur.reference.fixedmath -> gpu_blur.plan"]
    assert violations(small, lambda n: within(n, BACKENDS),
                      lambda _, t: within(t, SYNTHESIS + CLI)) == [
        "gpu_blur.backends.opencl -> gpu_blur.synthesis.batches"]
    assert violations(small, lambda n: not within(n, CLI), lambda _, t: within(t, CLI)) == [
        "gpu_blur.dataset -> gpu_blur.cli.main"]
    assert violations(small, lambda n: not within(n, TESTING),
                      lambda _, t: within(t, TESTING)) == [
        "gpu_blur.backends.opencl -> gpu_blur.synthesis.batches -> gpu_blur.backends.warp"
        " -> gpu_blur.scheduler -> gpu_blur.testing",
        "gpu_blur.backends.warp -> gpu_blur.scheduler -> gpu_blur.testing",
        "gpu_blur.scheduler -> gpu_blur.testing",
        "gpu_blur.synthesis.batches -> gpu_blur.backends.warp -> gpu_blur.scheduler"
        " -> gpu_blur.testing"]
    # direct imports of a concrete backend or a device library, also inside a function
    (package / "dataset.py").write_text("def f():\n    import warp\n")
    assert direct_imports(package, SYNTHESIS, CONCRETE_BACKENDS, SYNTHESIS_MAY_IMPORT) == [
        "gpu_blur.dataset -> warp", "gpu_blur.synthesis.batches -> gpu_blur.backends.warp"]


def call_trace_layers():
    """``bench/call_trace.py``'s ``layer_of``, which counts one sample's calls by layer."""
    spec = importlib.util.spec_from_file_location("call_trace", ROOT / "bench" / "call_trace.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return lambda name: module.layer_of(name.removeprefix("gpu_blur."))


def test_call_trace_layers_follow_the_import_graph():
    """No module of a layer the call trace counts reaches a module of a higher layer by imports.

    So a call up in the trace is a callback, never a module calling what it imports.
    """
    layer_of, edges = call_trace_layers(), graph()
    up = []
    for name in sorted(edges):
        low = layer_of(name)
        if low is None:
            continue
        for target, chain in reached(edges, name).items():
            high = layer_of(target)
            if high is not None and high < low:
                up.append(" -> ".join(f"{n} ({layer_of(n)})" for n in chain))
    assert up == []
