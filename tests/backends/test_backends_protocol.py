"""The kernel backends against :class:`gpu_blur.backends.ResidentBackend`, by name only.

Two directions, no device opened:

- every member the Protocol declares (its own and :class:`~gpu_blur.backends.Backend`'s) is
  one that each subclass of ``KernelBackend`` (which leaves ``name``, ``device`` and the like
  to them) provides: a method with the Protocol's parameters, or an attribute set on the class
  or assigned to ``self`` in its source or its bases';
- every attribute the synthesis layer reads on its backend (``runner.<name>``,
  ``self.runner.<name>``, ``backend.<name>`` in gpu_blur/synthesis/*.py, read with ``ast``)
  is one the Protocol declares, so that code needs nothing a concrete backend adds.
"""

from __future__ import annotations

import ast
import inspect
import textwrap

import pytest
from conftest import ROOT

from gpu_blur.backends import Backend, ResidentBackend, is_resident
from gpu_blur.backends.kernel import KernelBackend
from gpu_blur.backends.numpy import NumpyBackend

SYNTHESIS = ROOT / "gpu_blur" / "synthesis"

#: The names the synthesis layer gives its backend object.
RUNNER_NAMES = ("runner", "backend")


def members(protocol) -> dict[str, object]:
    """Name -> the Protocol's function (a method) or None (an attribute), its bases' included."""
    found: dict[str, object] = {}
    for cls in reversed(protocol.__mro__):
        if cls.__module__ != protocol.__module__:  # Protocol, Generic, object
            continue
        found.update(dict.fromkeys(vars(cls).get("__annotations__", {})))
        found.update({name: value for name, value in vars(cls).items()
                      if not name.startswith("_") and inspect.isfunction(value)})
    return found


def assigned_to_self(cls) -> set[str]:
    """Attribute names any method of ``cls`` or its bases of ours assigns on ``self``."""
    found = set()
    for klass in cls.__mro__:
        if not klass.__module__.startswith("gpu_blur."):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        found.update(node.attr for node in ast.walk(tree)
                     if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
                     and isinstance(node.value, ast.Name) and node.value.id == "self")
    return found


def parameters(function) -> list[str]:
    """A function's parameter names without ``self`` (a static method has none)."""
    names = list(inspect.signature(function).parameters)
    return names[1:] if names[:1] == ["self"] else names


def kernel_backends() -> list[type]:
    """Every subclass of KernelBackend whose module imports here (pyopencl, warp)."""
    for module in ("gpu_blur.backends.opencl", "gpu_blur.backends.warp"):
        try:
            __import__(module)
        except ImportError:  # that family's library is missing: its class is not checked
            pass
    found, queue = [], [KernelBackend]
    while queue:
        subclasses = [c for c in queue.pop(0).__subclasses__()
                      if c.__module__.startswith("gpu_blur.")]
        found += subclasses
        queue += subclasses
    return found


def runner_reads() -> dict[str, set[str]]:
    """Attribute name -> the synthesis modules that read it on their backend object."""

    def is_runner(node) -> bool:
        if isinstance(node, ast.Name):
            return node.id in RUNNER_NAMES
        return (isinstance(node, ast.Attribute) and node.attr in RUNNER_NAMES
                and isinstance(node.value, ast.Name) and node.value.id == "self")

    found: dict[str, set[str]] = {}
    for path in sorted(SYNTHESIS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Attribute) and is_runner(node.value):
                found.setdefault(node.attr, set()).add(path.name)
    return found


def test_the_protocol_extends_backend_and_declares_the_resident_path():
    declared = members(ResidentBackend)
    assert set(members(Backend)) <= set(declared)
    assert {"put", "slots", "stacked", "sync_passes", "wp_device", "hand_to"} <= set(declared)
    assert declared["sync_passes"] is None and inspect.isfunction(declared["put"])


@pytest.mark.parametrize("cls", kernel_backends(), ids=lambda c: c.__name__)
def test_each_kernel_backend_provides_every_member(cls):
    attributes = assigned_to_self(cls)
    missing, differ = [], []
    for name, protocol_function in members(ResidentBackend).items():
        if protocol_function is None:
            if not (hasattr(cls, name) or name in attributes):
                missing.append(name)
            continue
        function = getattr(cls, name, None)
        if not callable(function):
            missing.append(name)
        elif parameters(function) != parameters(protocol_function):
            differ.append(f"{name}{inspect.signature(function)} against the Protocol's "
                          f"{name}{inspect.signature(protocol_function)}")
    assert not missing, f"{cls.__name__} lacks {missing}"
    assert not differ, "\n".join(differ)


def test_both_kernel_languages_are_checked():
    names = {cls.__name__ for cls in kernel_backends()}
    pytest.importorskip("pyopencl")
    pytest.importorskip("warp")
    assert {"OpenCLBackend", "WarpBackend"} <= names


def test_synthesis_reads_only_what_the_protocol_declares():
    reads = runner_reads()
    # the scan sees the reads it is meant to (so it cannot pass on nothing)
    assert {"put", "sync_passes", "hand_to", "wp_device", "slots"} <= set(reads)
    undeclared = {name: sorted(where) for name, where in reads.items()
                  if name not in members(ResidentBackend)}
    assert not undeclared, f"declare these in ResidentBackend: {undeclared}"


def test_only_kernel_backends_are_resident():
    assert not is_resident(NumpyBackend())
    assert all(issubclass(cls, KernelBackend) for cls in kernel_backends())
