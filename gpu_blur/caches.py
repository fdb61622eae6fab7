"""Where the kernel compilers gpu_blur drives keep their caches: folders private to this user.

PoCL, pyopencl (compiled binaries, and pytools' store of generated Python code), Warp and
NVIDIA's driver read back what they compiled earlier from a disk cache: whoever can write that
folder can have their code run in this process. Each of them is pointed at a folder under
:func:`root`, one absolute folder of this user's (mode 0700, checked before use), whatever the
environment holds (``HOME`` unset, ``XDG_CACHE_HOME=''``, a relative path):

- ``GPU_BLUR_CACHE_DIR`` when set (an absolute path; used as it is);
- else ``$XDG_CACHE_HOME/gpu_blur`` when that is an absolute path;
- else ``$HOME/.cache/gpu_blur`` when ``HOME`` is an absolute path;
- else ``<home from the password database>/.cache/gpu_blur`` (Windows: ``%LOCALAPPDATA%``);
- else :class:`CacheError`.

A cache folder a user chose for a runtime (``POCL_CACHE_DIR``, ``WARP_CACHE_PATH``,
``warp.config.kernel_cache_dir``, ``CUDA_CACHE_PATH``) is kept, after the same checks.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["CacheError", "ENV", "FIX", "base", "check", "env_folder", "folder", "private",
           "pyopencl_cache", "root", "set_cuda_cache", "set_opencl_caches", "set_warp_cache"]

#: The environment variable that names the cache root (an absolute path).
ENV = "GPU_BLUR_CACHE_DIR"
FIX = f"set {ENV} to an absolute path of a folder of yours (created if missing)"


class CacheError(RuntimeError):
    """No private cache folder: none can be found or made, or one is open to others."""


def _home() -> str:
    """The current user's home folder from the password database ('' when there is none)."""
    try:
        import pwd

        return pwd.getpwuid(os.getuid()).pw_dir
    except (ImportError, KeyError, AttributeError):  # Windows; a uid without an entry
        return ""


def base() -> Path:
    """The cache root's path, not yet made or checked (see the module's docstring)."""
    chosen = os.environ.get(ENV)
    if chosen:
        if not os.path.isabs(chosen):
            raise CacheError(f"{ENV}={chosen!r} is not an absolute path; {FIX}")
        return Path(chosen)
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    if os.path.isabs(xdg):
        return Path(xdg) / "gpu_blur"
    for home in (os.environ.get("HOME", ""), _home()):
        if os.path.isabs(home):
            return Path(home) / ".cache" / "gpu_blur"
    local = os.environ.get("LOCALAPPDATA", "")
    if os.name == "nt" and os.path.isabs(local):
        return Path(local) / "gpu_blur"
    raise CacheError("no per-user folder for gpu_blur's compiler caches: XDG_CACHE_HOME and "
                     "HOME are not absolute paths and the password database gives no home "
                     f"folder; {FIX}")


def check(path: Path, what: str, fix: str = FIX) -> Path:
    """``path`` if it is a real folder (no symlink) owned by this user, writable by no one else.

    The owner and mode checks are skipped where there are no user ids (Windows).

    Raises:
        CacheError: naming ``what``, the path, what is wrong and ``fix``.
    """
    try:
        st = os.lstat(path)
    except OSError as e:
        raise CacheError(f"{what} {path}: {e.strerror}; {fix}") from None
    problem = ""
    if stat.S_ISLNK(st.st_mode):
        problem = "is a symbolic link"
    elif not stat.S_ISDIR(st.st_mode):
        problem = "is not a folder"
    elif hasattr(os, "getuid") and st.st_uid != os.getuid():
        problem = f"is owned by user id {st.st_uid}, not by you ({os.getuid()})"
    elif hasattr(os, "getuid") and st.st_mode & 0o022:
        problem = f"is writable by others (mode {stat.S_IMODE(st.st_mode):o})"
    if problem:
        raise CacheError(f"refusing {what} {path}: it {problem}, so another user could put "
                         f"compiled code there that gpu_blur would run; remove it (gpu_blur "
                         f"then makes it again, private), or {fix}")
    return path


def private(path: Path, what: str, fix: str = FIX) -> Path:
    """``path`` made (mode 0700, parents as the umask says) if missing, then :func:`check`-ed.

    Raises:
        CacheError: a relative path, a folder that cannot be made, or one :func:`check` refuses.
    """
    if not path.is_absolute():
        raise CacheError(f"{what} {path} is not an absolute path; {fix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    except OSError as e:
        raise CacheError(f"cannot make {what} {path}: {e.strerror}; {fix}") from None
    return check(path, what, fix)


def root() -> Path:
    """The cache root, made if missing and checked (see the module's docstring)."""
    return private(base(), "gpu_blur's cache folder")


def folder(name: str) -> Path:
    """The private folder ``name`` under :func:`root` (one per cache), made if missing."""
    return private(root() / name, f"gpu_blur's cache folder for {name}")


def env_folder(variable: str, name: str, export: bool = True) -> Path:
    """The folder an environment variable names for a runtime's cache, checked.

    When ``variable`` is unset or empty, :func:`folder` ``(name)``, and with ``export`` written
    into the environment (for this process's runtimes and its child processes).
    """
    chosen = os.environ.get(variable)
    if chosen:
        return private(Path(chosen), variable, f"point {variable} at a folder of yours "
                       "(an absolute path), or unset it")
    path = folder(name)
    if export:
        os.environ[variable] = str(path)
    return path


def set_cuda_cache() -> None:
    """Keep NVIDIA's JIT cache (``CUDA_CACHE_PATH``) private; before the driver starts.

    A path the user set is checked. Unset, the driver uses ``$HOME/.nv/ComputeCache``, left
    so where ``HOME`` is an absolute path, else replaced by a folder under :func:`root`.
    """
    home = os.environ.get("HOME", "")
    if os.environ.get("CUDA_CACHE_PATH") or (os.name != "nt" and not os.path.isabs(home)):
        env_folder("CUDA_CACHE_PATH", "nv")


def set_opencl_caches() -> None:
    """``POCL_CACHE_DIR`` and ``CUDA_CACHE_PATH``; must run before OpenCL's first platform query.

    PoCL, unconfigured, caches under ``$XDG_CACHE_HOME`` or ``$HOME`` even when they are
    relative, and in ``/tmp/pocl/kcache`` without ``HOME``. Intel's CPU runtime keeps no cache
    of its own (pyopencl caches its binaries: :func:`pyopencl_cache`).
    """
    env_folder("POCL_CACHE_DIR", "pocl")
    set_cuda_cache()


def pyopencl_cache(version: str) -> str:
    """The folder for pyopencl's binary cache (``Program.build(cache_dir=...)``)."""
    return str(folder("pyopencl") / version)


def set_warp_cache() -> None:
    """Point Warp's kernel cache at a private folder; must run before ``wp.init()``.

    ``warp.config.kernel_cache_dir`` or ``WARP_CACHE_PATH`` when the user set one (checked),
    else ``<root>/warp``. Warp then keeps its files in a subfolder named by its version.
    After ``wp.init()`` the folder Warp chose is checked.

    Raises:
        CacheError: the folder Warp uses or would use is not private.
    """
    import warp as wp

    chosen = wp.config.kernel_cache_dir
    if chosen is None:
        set_cuda_cache()
        wp.config.kernel_cache_dir = str(env_folder("WARP_CACHE_PATH", "warp", export=False))
        return
    path = Path(chosen)
    if path.name == wp.config.version:  # after wp.init(): the version folder in the chosen one
        path = path.parent
    private(path, "Warp's kernel cache (warp.config.kernel_cache_dir)",
            "set warp.config.kernel_cache_dir to an absolute path of a folder of yours "
            "before wp.init(), or leave it unset")
