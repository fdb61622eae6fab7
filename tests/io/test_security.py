"""Compiler caches and import paths are private to the user whatever the environment (issue 35).

Each finding of the hostile-input run is a test: PoCL's cache without ``HOME``, Warp's cache
with ``XDG_CACHE_HOME=''`` and no ``HOME``, a ``multiprocessing`` package planted in the
folder ``--devices`` workers start from, and cache folders others can write.
"""

import json
import os
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ROOT

from gpu_blur import caches

PYTHON = sys.executable


def _pwd_home() -> str:
    import pwd

    return pwd.getpwuid(os.getuid()).pw_dir


def _bare_env(**extra) -> dict:
    """This environment without HOME, XDG_CACHE_HOME, GPU_BLUR_CACHE_DIR and cache variables."""
    env = {k: v for k, v in os.environ.items() if k not in (
        "HOME", "XDG_CACHE_HOME", caches.ENV, "POCL_CACHE_DIR", "CUDA_CACHE_PATH",
        "WARP_CACHE_PATH", "PYTHONSAFEPATH")}
    env.update(extra)
    return env


def _run(code: str, env: dict, cwd: Path) -> dict:
    """Run ``code`` in a fresh Python in ``cwd``; it prints one JSON line, returned."""
    done = subprocess.run([PYTHON, "-c", textwrap.dedent(code)], env=env, cwd=cwd,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def _assert_private(path: str) -> None:
    assert os.path.isabs(path), path
    st = os.lstat(path)
    assert stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid(), path
    assert stat.S_IMODE(st.st_mode) & 0o077 == 0, oct(st.st_mode)


@pytest.fixture
def home_cache():
    """The default cache root without HOME: the password database's home (skip if unusable)."""
    root = Path(_pwd_home()) / ".cache" / "gpu_blur"
    try:
        caches.private(root, "test")
    except caches.CacheError as e:
        pytest.skip(f"this user's home from the password database is no use here: {e}")
    return root


def test_without_home_pocl_caches_in_a_private_folder_of_the_user(tmp_path, home_cache):
    pytest.importorskip("pyopencl")
    got = _run("""
        import json, os
        import gpu_blur.backends.opencl
        print(json.dumps({"pocl": os.environ.get("POCL_CACHE_DIR")}))
    """, _bare_env(), tmp_path)
    assert got["pocl"] == str(home_cache / "pocl")  # not /tmp/pocl/kcache
    _assert_private(got["pocl"])


def test_opencl_runtimes_write_their_caches_under_the_private_folder(tmp_path):
    """PoCL's kernel cache and pyopencl's (binary, invoker) caches land in the cache folder."""
    pytest.importorskip("pyopencl")
    root = tmp_path / "cache"
    got = _run("""
        import json, os
        import pyopencl.invoker
        from gpu_blur.backends import opencl
        platforms = sorted({d.platform for d in opencl.opencl_devices()})
        print(json.dumps({"platforms": platforms,
                          "invoker": pyopencl.invoker.invoker_cache.container_dir}))
    """, _bare_env(XDG_CACHE_HOME="relative", GPU_BLUR_CACHE_DIR=str(root)), tmp_path)
    assert got["invoker"] == str(root / "pytools")
    if "Portable Computing Language" in got["platforms"]:
        assert any((root / "pocl").iterdir())
    if any(p.startswith("Intel(R) OpenCL") for p in got["platforms"]):
        assert any((root / "pyopencl").iterdir())  # Intel's runtime keeps no cache itself
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache"]  # nothing in the cwd
    _assert_private(str(root))


def test_warp_s_kernel_cache_is_absolute_and_private_without_home_or_xdg(tmp_path, home_cache):
    pytest.importorskip("warp")
    got = _run("""
        import json
        import warp as wp
        from gpu_blur.backends import warp
        warp._init()
        print(json.dumps({"cache": wp.config.kernel_cache_dir}))
    """, _bare_env(XDG_CACHE_HOME=""), tmp_path)
    cache = Path(got["cache"])
    assert cache.is_absolute() and cache.parent == home_cache / "warp", cache
    _assert_private(str(cache.parent))
    assert list(tmp_path.iterdir()) == []  # nothing cached relative to the current folder


def test_warp_refuses_a_kernel_cache_others_can_write(tmp_path):
    pytest.importorskip("warp")
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    done = subprocess.run([PYTHON, "-c", "import gpu_blur.backends.warp"], cwd=tmp_path,
                          env=_bare_env(WARP_CACHE_PATH=str(shared)), capture_output=True,
                          text=True, timeout=120)
    assert done.returncode != 0
    assert f"refusing WARP_CACHE_PATH {shared}: it is writable by others" in done.stderr


@pytest.mark.parametrize("flags", [[], ["-E"]], ids=["safe-path", "start-elsewhere"])
def test_device_workers_do_not_import_a_package_planted_in_the_current_folder(tmp_path, flags):
    """A ``multiprocessing`` package in the run's folder is not what workers import.

    ``-E`` (which the workers repeat, so ``PYTHONSAFEPATH`` cannot reach them) takes the way
    Python 3.10 takes: the workers start in the cache folder and go back to the driver's.
    """
    work, marker = tmp_path / "work", tmp_path / "imported"
    (work / "multiprocessing").mkdir(parents=True)
    (work / "multiprocessing" / "__init__.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nraise SystemExit('planted package ran')\n")
    cv2.imwrite(str(work / "a.png"), np.full((16, 24, 3), 128, np.uint8))
    driver = tmp_path / "driver.py"  # a script elsewhere, as the gpu-blur entry point is
    driver.write_text(textwrap.dedent("""
        import json
        import sys
        from pathlib import Path
        sys.path.insert(0, ROOT)  # gpu_blur from this tree: -E drops PYTHONPATH
        from gpu_blur.discovery import find_samples
        from gpu_blur.distributed import run_devices
        from gpu_blur.generate import Job
        from gpu_blur.scene import load_scene

        if __name__ == "__main__":
            job = Job(load_scene({"blur": {"steps": 2}}), 0, "numpy")
            specs = find_samples(Path("."), "trajectory", 1, 1).take()
            made = list(run_devices(job, specs, ["numpy"]))
            print(json.dumps({"made": len(made), "errors": [str(e) for _, _, e in made if e]}))
    """).replace("ROOT", repr(str(ROOT))))
    done = subprocess.run([PYTHON, *flags, str(driver)], cwd=work, capture_output=True,
                          text=True, env=_bare_env(HOME=str(tmp_path)), timeout=120)
    assert not marker.exists(), done.stderr
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1]) == {"made": 1, "errors": []}


def test_the_cache_root_is_made_private(tmp_path, monkeypatch):
    monkeypatch.setenv(caches.ENV, str(tmp_path / "mine"))
    assert caches.folder("pocl") == tmp_path / "mine" / "pocl"
    _assert_private(str(tmp_path / "mine"))
    _assert_private(str(tmp_path / "mine" / "pocl"))


def test_the_cache_root_follows_xdg_then_home_then_the_password_database(tmp_path,
                                                                         monkeypatch):
    monkeypatch.delenv(caches.ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert caches.base() == tmp_path / "xdg" / "gpu_blur"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert caches.base() == tmp_path / ".cache" / "gpu_blur"
    monkeypatch.setenv("HOME", ".")
    assert caches.base() == Path(_pwd_home()) / ".cache" / "gpu_blur"
    monkeypatch.setattr(caches, "_home", lambda: "")
    with pytest.raises(caches.CacheError, match="set GPU_BLUR_CACHE_DIR to an absolute path"):
        caches.base()
    monkeypatch.setenv(caches.ENV, "relative")
    with pytest.raises(caches.CacheError, match="GPU_BLUR_CACHE_DIR='relative' is not an"):
        caches.base()


def test_a_cache_folder_others_can_write_is_refused(tmp_path, monkeypatch):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)  # made before gpu_blur by someone, open to all
    monkeypatch.setenv(caches.ENV, str(shared))
    with pytest.raises(caches.CacheError, match=f"refusing gpu_blur's cache folder {shared}: "
                       "it is writable by others .mode 777."):
        caches.root()
    monkeypatch.setenv(caches.ENV, str(tmp_path / "mine"))
    monkeypatch.setenv("POCL_CACHE_DIR", str(shared))
    with pytest.raises(caches.CacheError, match="point POCL_CACHE_DIR at a folder of yours"):
        caches.set_opencl_caches()


def test_a_symlinked_or_foreign_cache_folder_is_refused(tmp_path, monkeypatch):
    real = tmp_path / "real"
    real.mkdir(mode=0o700)
    (tmp_path / "link").symlink_to(real)
    monkeypatch.setenv(caches.ENV, str(tmp_path / "link"))
    with pytest.raises(caches.CacheError, match="it is a symbolic link"):
        caches.root()
    if os.getuid() != 0:
        return  # only root can make a folder another user owns
    os.chown(real, 12345, -1)
    monkeypatch.setenv(caches.ENV, str(real))
    with pytest.raises(caches.CacheError, match=r"owned by user id 12345, not by you \(0\)"):
        caches.root()


def test_a_relative_runtime_cache_variable_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv(caches.ENV, str(tmp_path / "mine"))
    monkeypatch.setenv("POCL_CACHE_DIR", "kcache")
    with pytest.raises(caches.CacheError, match="POCL_CACHE_DIR kcache is not an absolute"):
        caches.set_opencl_caches()
