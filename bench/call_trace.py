"""One generated sample's call path through the package's layers, from a call trace.

Makes one sample the way ``gpu-blur generate`` does (the built-in photo, the default scene,
seed 0, no tiles, no spot checks) through the lowest entry that every tree since 1d3f510 has,
``gpu_blur.generate.make_sample(Job(...), spec)``, with ``sys.setprofile`` (and
``threading.setprofile``, for threads started while it runs) watching every Python call whose
code lies in the ``gpu_blur`` package that is imported. It reports:

- ``modules``: the distinct modules of the package entered;
- ``calls``: the calls of package functions (generator resumptions included);
- ``transitions``: the calls from one module into another module;
- ``returns_up``: the returns that go back up a layer, from a module of a lower layer (a
  higher number below) to its caller in a higher one; every call down a layer makes one, so
  this counts the path's trips down and back;
- ``calls_up``: calls from a lower layer into a higher one (callbacks; the path should have
  none);
- ``entered``: how many times each group is entered from outside it (``synthesis`` is
  ``gpu_blur/synthesis/`` or the older ``gpu_blur/pipeline.py``).

Layers, by module path (first match, :data:`LAYERS`): 0 the command; 1 the sets (``generation``,
``generate``, ``dataset``, ``discovery`` and their helpers); 2 ``synthesis``; 3 ``scheduler``,
``params``; 4 ``backends``, ``warp_kernels``; 5 ``planning`` (``plan`` in older trees), ``stages``;
6 ``reference``. Every other module (``arrays``, ``imageio``, ``scene``, ``timings``, ``tiling``,
...) is *shared*: a helper any layer may call, in no layer, so its calls and returns are no layer
crossing; they are counted as ``shared_calls``, and ``returns_up_with_shared`` counts the returns up
with the shared modules as a layer 7 below all others.

The traced sample is the second of the set (index 1) after the first was made untraced, as a
set's samples after its first run (kernels built, caches filled); ``--cold`` traces the
first sample of a fresh process instead.

Run from the repository root, on any tree (``PYTHONPATH=<tree>`` picks an older checkout)::

    python bench/call_trace.py [--backend numpy|opencl:0:0|warp:cpu] [--cold]
        [--json bench/results/call_trace.json]

``--json`` adds this run to the file (keyed by commit, backend, warm or cold, and layering),
keeping the runs already there.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

#: (layer, module path prefixes), first match wins; a prefix matches a module or a package.
#: They follow the package's import graph (tests/architecture/test_layers.py checks that
#: no module imports one of a higher layer): the backends import the plan (``planning``,
#: ``stages``), which the scheduler and the draws (``params``) read, so the plan lies below the
#: backends; the Warp kernels are the Warp backend's.
#: Before 2026-11-27 the plan was put with the scheduler above the backends, which counted a
#: backend reading its plan as a call up (docs/architecture-trace.md gives both).
LAYERS = (
    (0, ("cli",)),
    (1, ("generation", "generate", "dataset", "datasets", "discovery", "blurred_inputs",
         "input_folders", "distributed", "set_formats", "run_record")),
    (2, ("synthesis", "pipeline")),
    (3, ("scheduler", "params")),
    (4, ("backends", "warp_kernels")),
    (5, ("plan", "planning", "stages")),
    (6, ("reference",)),
)
#: The name runs record their layering under (runs before it have none: "plan above backends").
LAYERS_NAME = "import graph"
#: The layer the shared modules take in ``returns_up_with_shared``.
SHARED_LAYER = 7
#: The groups whose entries are counted: name -> module path prefixes.
GROUPS = {
    "synthesis": ("synthesis", "pipeline"),
    "backends": ("backends",),
    "reference": ("reference",),
    "warp_kernels": ("warp_kernels",),
    "scheduler/plan/params": ("scheduler", "plan", "planning", "params"),
}
#: Module pairs shown per list (those with the most calls).
TOP_PAIRS = 8


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def layer_of(module: str) -> int | None:
    """The layer of a module (a dotted path inside the package), None for a shared one."""
    for layer, prefixes in LAYERS:
        if _within(module, prefixes):
            return layer
    return None


class CallTrace:
    """The package's calls seen by a profile function, a stack of modules per thread."""

    def __init__(self, package: Path):
        self.root = str(package.resolve()) + "/"
        self.names: dict[str, str | None] = {}  # file -> module, None outside the package
        self.stacks: dict[int, list[str]] = collections.defaultdict(list)
        self.calls = collections.Counter()  # module -> calls into it
        self.pairs = collections.Counter()  # (caller, callee) -> calls, caller "" for none
        self.threads: set[int] = set()

    def _module(self, filename: str) -> str | None:
        name = self.names.get(filename, "")
        if name == "":
            name = None
            if filename.startswith(self.root) and filename.endswith(".py"):
                parts = filename[len(self.root):-3].split("/")
                if parts[-1] == "__init__":
                    parts = parts[:-1]
                name = ".".join(parts) or "__init__"
            self.names[filename] = name
        return name

    def profile(self, frame, event, arg) -> None:
        if event == "call":
            module = self._module(frame.f_code.co_filename)
            if module is None:
                return
            thread = threading.get_ident()
            stack = self.stacks[thread]
            self.threads.add(thread)
            self.calls[module] += 1
            self.pairs[stack[-1] if stack else "", module] += 1
            stack.append(module)
        elif event == "return":
            if self._module(frame.f_code.co_filename) is None:
                return
            stack = self.stacks[threading.get_ident()]
            if stack:
                stack.pop()

    def run(self, function, *args):
        threading.setprofile(self.profile)
        sys.setprofile(self.profile)
        try:
            return function(*args)
        finally:
            sys.setprofile(None)
            threading.setprofile(None)


def summarize(trace: CallTrace) -> dict:
    """The counts the module docstring names, from a finished trace."""
    returns_up = calls_up = transitions = with_shared = shared = 0
    up_pairs, back_pairs, all_pairs = (collections.Counter() for _ in range(3))
    entered = {group: 0 for group in GROUPS}
    for (caller, callee), n in trace.pairs.items():
        if caller == callee:
            continue
        for group, prefixes in GROUPS.items():
            if _within(callee, prefixes) and not (caller and _within(caller, prefixes)):
                entered[group] += n
        if not caller:
            continue
        transitions += n
        all_pairs[f"{caller} -> {callee}"] += n
        high, low = layer_of(caller), layer_of(callee)
        shared += n if low is None else 0
        # every call returns once (a generator's each resumption too), to the caller
        if high is not None and low is not None:
            if low > high:
                returns_up += n
                up_pairs[f"{caller} -> {callee}"] += n
            elif low < high:
                calls_up += n
                back_pairs[f"{caller} -> {callee}"] += n
        high = SHARED_LAYER if high is None else high
        low = SHARED_LAYER if low is None else low
        with_shared += n if low > high else 0
    layers = collections.Counter()
    for module, n in trace.calls.items():
        layer = layer_of(module)
        layers["shared" if layer is None else str(layer)] += n
    return {
        "modules": len(trace.calls),
        "calls": sum(trace.calls.values()),
        "transitions": transitions,
        "returns_up": returns_up,
        "calls_up": calls_up,
        "returns_up_with_shared": with_shared,
        "shared_calls": shared,
        "entered": entered,
        "calls_per_layer": dict(sorted(layers.items())),
        "threads": len(trace.threads),
        "top_transitions": dict(all_pairs.most_common(TOP_PAIRS)),
        "top_returns_up": dict(up_pairs.most_common(TOP_PAIRS)),
        "top_calls_up": dict(back_pairs.most_common(TOP_PAIRS)),
        "modules_entered": sorted(trace.calls),
    }


def _commit(package: Path) -> tuple[str, bool]:
    """The commit of the package's checkout and whether its package files differ from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=package, capture_output=True, text=True,
                              check=False).stdout.strip()
    return git("rev-parse", "HEAD") or "unknown", bool(git("status", "--porcelain", "--", "."))


def _first(name: str, *modules: str):
    """``name`` from the first of ``modules`` that has it (a name may move), else None."""
    for module in modules:
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):
            continue
    return None


def sample_maker(backend: str):
    """``(entry, make(index))``: one sample of the built-in photo, the default scene, seed 0.

    ``gpu_blur.generate.make_sample`` where the tree has it (1d3f510 and later), else the
    synthesis function of whatever tree this is, named in ``entry``.
    """
    from gpu_blur.scene import load_scene

    scene = load_scene(None)
    try:
        from gpu_blur.generate import Job, make_sample
        from gpu_blur.scheduler import Schedule
    except ImportError:
        make_sample = None
    find_samples = _first("find_samples", "gpu_blur.dataset", "gpu_blur.discovery")
    if make_sample is not None and find_samples is not None:
        # as gpu-blur generate: 4 samples per built-in photo, no --save extras, the set's bits
        specs = find_samples(None, scene.blur.mode, scene.blur.frames, 4, None,
                             masks=scene.saturation.mode != "off").take(None)
        job = Job(scene, 0, backend, Schedule(None, None, 0.0), False, bits=scene.output.bits,
                  with_mask=False)

        def make(index):
            spec, result, error = make_sample(job, specs[index])
            if error is not None:
                raise RuntimeError(f"sample {index}: {error}")
            return result
        return "gpu_blur.generate.make_sample", make
    try:
        from gpu_blur.synthesis import synthesize
        entry = "gpu_blur.synthesis.synthesize"
    except ImportError:
        from gpu_blur.pipeline import synthesize
        entry = "gpu_blur.pipeline.synthesize"
    default_photo = _first("default_photo", "gpu_blur.dataset", "gpu_blur.discovery")

    def make(index):
        return synthesize([default_photo()], scene, seed=0, sample_index=index,
                          backend=backend, codes=bool(scene.output.bits))
    return entry, make


def table(run: dict) -> str:
    """The counts of one run as a few lines of text."""
    c = run["counts"]
    lines = [f"{run['commit'][:7]}{' (modified)' if run['modified'] else ''} {run['backend']} "
             f"({run['sample']}, {run['entry']})",
             f"  modules entered              {c['modules']:>8}",
             f"  calls                        {c['calls']:>8}",
             f"  module transitions           {c['transitions']:>8}",
             f"  returns up a layer           {c['returns_up']:>8}"
             f"   (shared modules as layer 7: {c['returns_up_with_shared']})",
             f"  calls up a layer             {c['calls_up']:>8}"]
    lines += [f"  {group + ' entered':<28} {n:>8}" for group, n in c["entered"].items()]
    for key, label in (("top_transitions", "most transitions"),
                       ("top_returns_up", "most returns up"), ("top_calls_up", "calls up")):
        lines.append(f"  {label}: " + (", ".join(
            f"{pair} {n}" for pair, n in c[key].items()) or "none"))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="numpy")
    parser.add_argument("--cold", action="store_true",
                        help="trace the first sample of this process (no untraced one before)")
    parser.add_argument("--json", type=Path, help="add this run to a JSON file")
    args = parser.parse_args()

    import gpu_blur

    package = Path(gpu_blur.__file__).parent
    commit, modified = _commit(package)
    entry, make = sample_maker(args.backend)
    if not args.cold:
        make(0)
    trace = CallTrace(package)
    start = time.perf_counter()
    trace.run(make, 0 if args.cold else 1)
    took = time.perf_counter() - start
    run = {"commit": commit, "modified": modified, "backend": args.backend,
           "sample": "cold, sample 0" if args.cold else "warm, sample 1 after sample 0",
           "entry": entry, "python": sys.version.split()[0], "traced_seconds": round(took, 2),
           "layers": LAYERS_NAME, "counts": summarize(trace)}
    print(table(run))
    if args.json:
        runs = []
        if args.json.exists():
            runs = json.loads(args.json.read_text(encoding="utf-8"))["runs"]
        def key(r: dict) -> tuple:
            return r["commit"], r["backend"], r["sample"], r.get("layers", "plan above backends")
        runs = [r for r in runs if key(r) != key(run)] + [run]
        out = {"what": "bench/call_trace.py: one generated sample's calls in gpu_blur, "
                       "counted by module and layer (see the script's docstring)",
               "runs": runs}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
