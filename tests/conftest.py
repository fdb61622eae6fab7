"""Fixtures and helpers shared by the tests.

The test modules sit in folders that mirror the package (tests/reference/ for
gpu_blur/reference/, tests/backends/ for gpu_blur/backends/, and so on), without __init__.py.
Under pytest's default "prepend" import mode each module's folder and this one go on sys.path,
so the modules import ``conftest``, ``golden`` and ``device_functions`` by name, and a test
module's file name must be unique across all folders (pytest stops at collection with "import
file mismatch" otherwise).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

#: This folder (tests/), its data folder and the repository root. The test modules sit one folder
#: down (tests/<part>/, mirroring gpu_blur/), so they take these paths from here rather than
#: counting parents of their own __file__.
TESTS = Path(__file__).resolve().parent
TEST_DATA = TESTS / "data"
ROOT = TESTS.parent
DATA = ROOT / "gpu_blur" / "data"


@pytest.fixture(scope="session")
def coffee_rgb() -> np.ndarray:
    """scikit-image's CC0 "coffee" photograph: 400 x 600 x 3 float64 sRGB in [0, 1], R, G, B.

    Read-only, so a test cannot change it for the others.
    """
    import cv2

    bgr = cv2.imread(str(DATA / "coffee.png"), cv2.IMREAD_COLOR)
    assert bgr is not None, f"cannot read {DATA / 'coffee.png'}"
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0
    rgb.setflags(write=False)
    return rgb


@pytest.fixture(scope="session")
def rocket_rgb() -> np.ndarray:
    """SpaceX's public-domain DSCOVR launch photo: 427 x 640 x 3 float64 sRGB, R, G, B.

    Cropped to 426 x 640 so the Bayer steps get even sizes. Read-only.
    """
    import cv2

    path = TEST_DATA / "rocket.jpg"
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, f"cannot read {path}"
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)[:426].astype(np.float64) / 255.0
    rgb.setflags(write=False)
    return rgb


# -- Philox known answers: one table for the reference and the kernels -----------------------------

# Random123 tests/kat_vectors (github.com/DEShawResearch/random123), the philox4x32 lines:
# rounds, counter (4 words), key (2 words), expected output (4 words). The same lines appear in
# several independent ports; test_philox_matches_pyopencl_random123_on_opencl re-derives them
# on the OpenCL device from pyopencl's bundled philox.cl. tests/reference/test_rng.py checks
# the reference against them, tests/backends/test_device_random.py the kernels.
KNOWN_ANSWERS = [
    (10, (0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    (
        10,
        (0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF),
        (0xFFFFFFFF, 0xFFFFFFFF),
        (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD),
    ),
    (
        10,
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xA4093822, 0x299F31D0),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1),
    ),
    (7, (0, 0, 0, 0), (0, 0), (0x5F6FB709, 0x0D893F64, 0x4F121F81, 0x4F730A48)),
    (
        7,
        (0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF),
        (0xFFFFFFFF, 0xFFFFFFFF),
        (0x5207DDC2, 0x45165E59, 0x4D8EE751, 0x8C52F662),
    ),
    (
        7,
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xA4093822, 0x299F31D0),
        (0x4DFCCABA, 0x190A87F0, 0xC47362BA, 0xB6B5242A),
    ),
]


# -- backends: one test body runs on every backend present -----------------------------------

def one_cpu_device_per_runtime(devices):
    """``devices`` with only the first CPU device of each platform name: two PoCLs (Debian's
    and PyPI's) would run every OpenCL test twice on the same cores, for no new coverage
    (measured here: 160 s each). Not applied when GPU_BLUR_BACKENDS names the devices."""
    seen, kept = set(), []
    for d in devices:
        if d.kind == "CPU" and d.platform in seen:
            continue
        seen.add(d.platform)
        kept.append(d)
    return kept


def _backend_specs() -> list[str]:
    """numpy, every usable OpenCL device in float32 and (with fp64) float64, every Warp device.

    Narrow with GPU_BLUR_BACKENDS, e.g. ``GPU_BLUR_BACKENDS=numpy,opencl:0:0,warp:cpu``.
    """
    specs = ["numpy"]
    try:
        from gpu_blur.backends.opencl import opencl_devices
    except ImportError:
        devices = []
    else:
        devices = [d for d in opencl_devices() if d.usable]
        if not os.environ.get("GPU_BLUR_BACKENDS"):
            devices = one_cpu_device_per_runtime(devices)
    for d in devices:
        specs.append(f"{d.spec}/float32")
        if d.fp64:
            specs.append(f"{d.spec}/float64")
    try:
        from gpu_blur.backends.warp import warp_devices
    except ImportError:
        pass
    else:
        for d in warp_devices():
            specs += [f"{d['spec']}/float32", f"{d['spec']}/float64"]
    wanted = os.environ.get("GPU_BLUR_BACKENDS")
    if wanted:
        names = wanted.split(",")
        specs = [s for s in specs if s.split("/")[0] in names or s in names]
    return specs


BACKEND_SPECS = _backend_specs()
KERNEL_BACKEND_SPECS = [s for s in BACKEND_SPECS if s != "numpy"]

#: GPU_BLUR_REQUIRE's names: the OpenCL platform each stands for (.ci/run sets "pocl,intel").
REQUIRABLE = {"pocl": "Portable Computing Language", "intel": "Intel(R) OpenCL"}


def missing_required(required: str, devices, specs) -> list[str]:
    """Why each runtime named in ``required`` (GPU_BLUR_REQUIRE, e.g. ``pocl,intel``) has no
    OpenCL device in ``devices`` whose float32 and float64 runs are among ``specs``."""
    problems = []
    for name in filter(None, (x.strip() for x in required.split(","))):
        if name not in REQUIRABLE:
            problems.append(f"unknown name {name!r} (known: {', '.join(REQUIRABLE)})")
            continue
        platform = REQUIRABLE[name]
        found = [d for d in devices if platform in d.platform]
        runs = [d for d in found if d.usable and d.fp64
                and {f"{d.spec}/float32", f"{d.spec}/float64"} <= set(specs)]
        if not runs:
            seen = "; ".join(f"{d.spec}: {d.problem or 'not in GPU_BLUR_BACKENDS or no fp64'}"
                             for d in found) or "none installed"
            problems.append(f"{name} ({platform}): no device the tests run on ({seen})")
    return problems


def pytest_sessionstart(session):
    """Under GPU_BLUR_REQUIRE (CI), a required OpenCL runtime that is missing fails the run
    instead of leaving its tests out: a green run proves the kernels ran on it."""
    required = os.environ.get("GPU_BLUR_REQUIRE", "")
    if not required:
        return
    try:
        from gpu_blur.backends.opencl import opencl_devices
    except ImportError:
        devices = []
    else:
        devices = opencl_devices()
    problems = missing_required(required, devices, BACKEND_SPECS)
    if problems:
        raise pytest.UsageError(
            f"GPU_BLUR_REQUIRE={required}: " + "; ".join(problems) + ". Install the runtime "
            "(README.md, Backends and devices: PoCL on Debian/Ubuntu is apt-get install "
            "pocl-opencl-icd) or set GPU_BLUR_REQUIRE= to run without it")


def make_backend(spec: str):
    """A backend for 'numpy' or 'opencl:P:D/<precision>' (one per session), whose passes
    return host float64 arrays, as tests compare them (:class:`HostOutputs`)."""
    from gpu_blur.backends import get_backend

    name, _, precision = spec.partition("/")
    return HostOutputs(get_backend(name, precision or "float64"))


class HostOutputs:
    """A backend whose pass outputs come back to the host as float64 (gpu_blur.backends.to_host).

    Kernel backends leave outputs on the device; tests compare values. Everything else is the
    wrapped backend's (``.backend``).
    """

    def __init__(self, backend):
        self.backend = backend

    def __getattr__(self, name):
        return getattr(self.backend, name)

    def accumulate(self, *args, **kwargs):
        from gpu_blur.backends import to_host

        return tuple(to_host(x) for x in self.backend.accumulate(*args, **kwargs))

    def to_raw(self, *args, **kwargs):
        from gpu_blur.backends import to_host

        return tuple(to_host(x) for x in self.backend.to_raw(*args, **kwargs))

    def finish(self, *args, **kwargs):
        from gpu_blur.backends import to_host

        return to_host(self.backend.finish(*args, **kwargs))


def spec_dtype(spec: str) -> str:
    """The tolerance table's dtype column for a backend spec."""
    return spec.partition("/")[2] or "float64"


def spec_backend(spec: str) -> str:
    """The tolerance table's backend column for a backend spec."""
    return spec.split(":")[0].split("/")[0]


@pytest.fixture(scope="session")
def opencl_queue():
    """(pyopencl, context, queue) on the device ``backend="opencl"`` would use.

    Skips only when no OpenCL device can build kernels here (the message says why). The
    context is returned and must be kept: Intel's CPU runtime invalidates a context whose
    Python object is gone even while a queue refers to it.
    """
    try:
        from gpu_blur.backends.opencl import OpenCLError, cl, select_device
    except ImportError:
        pytest.skip("pyopencl is not installed")
    try:
        device, _ = select_device("opencl")
    except OpenCLError as e:
        pytest.skip(str(e))
    context = cl.Context([device])
    return cl, context, cl.CommandQueue(context)


# -- measured numbers --------------------------------------------------------------------------

def report(record_property, name: str, value) -> None:
    """A measured number: into the test report (``record_property``) and, with ``-s``, stdout."""
    record_property(name, value)
    print(f"{name} = {value}")


# -- generated sets: what a run wrote, for comparing runs ------------------------------------

#: The folders of a generated set that hold per-sample files.
SETS = ("blur", "sharp", "params")


def manifest_lines(out):
    """Every manifest line of the set in ``out`` parsed (a torn line fails here), by index."""
    lines = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    return sorted(lines, key=lambda x: x["index"])


def files(out):
    """{relative path: bytes} of every per-sample file of the set in ``out``."""
    return {p.relative_to(out).as_posix(): p.read_bytes()
            for sub in SETS for p in sorted((out / sub).iterdir())}


#: A scene of the full default chain with 3 camera poses: the built-in photo (400 x 600) in
#: about 1 s a sample on numpy instead of 6 (the default scene's poses follow the shake's
#: length). For runs whose subject is not the default path's length.
QUICK_SCENE = "[blur]\nsteps = 3\n"


@pytest.fixture
def quick_scene(tmp_path):
    """The :data:`QUICK_SCENE` file (``quick.toml``)."""
    scene = tmp_path / "quick.toml"
    scene.write_text(QUICK_SCENE)
    return scene


def write_photos(root):
    """Two small photos (in/a.png, in/b.png, 24 x 32) and a fast scene (s.toml, 3 camera poses)
    under ``root``: (input folder, scene file). The same bytes every time."""
    import cv2

    folder = root / "in"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(0, 256, (24, 32, 3), np.uint8))
    scene = root / "s.toml"
    scene.write_text(QUICK_SCENE)  # the full default chain, 3 camera poses
    return folder, scene


@pytest.fixture
def photos(tmp_path):
    """Two small photos (in/a.png, in/b.png, 24 x 32) and a fast scene (3 camera poses).

    Returns (input folder, scene file): the full default chain in a few ms per sample.
    """
    return write_photos(tmp_path)


@pytest.fixture(scope="module")
def shared_photos(tmp_path_factory):
    """:func:`photos` once for a module, for tests that only read them: sets made from the same
    folder have the same manifest (it names the input files), so tests can share them."""
    return write_photos(tmp_path_factory.mktemp("photos"))
