"""A set's run.json: what a resumed run must share with the set it finishes.

:data:`RESUME_KEYS` are the settings that decide a sample's inputs, draws or pixels;
:func:`check_run` refuses a resume whose settings differ, naming the first difference;
:func:`library_versions` records the libraries the pixels depend on.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from gpu_blur import files
from gpu_blur.input_folders import RUN
from gpu_blur.reference.flow import INTERPOLATION_AUTO
from gpu_blur.version import __version__

__all__ = ["RESUME_KEYS", "check_run", "jsonable", "library_versions", "plain", "set_keys"]

#: run.json keys a resumed run must share with the set it finishes, with what sets each:
#: everything that decides a sample's inputs, draws or pixels (not --tile or --limit). "files"
#: holds the sha256 of each file the scene names (camera.name, blur.kernel), "device" the
#: backend's device (OpenCL platform numbers change when a runtime is installed),
#: "libraries" the versions of the libraries that compute the pixels (library_versions),
#: "save" the extra outputs of --save (absent without it), "jpeg_decoder" --jpeg-decoder
#: (absent for the default, cpu; before "libraries", to which it adds torchvision's).
RESUME_KEYS = {"seed": "--seed", "scene": "--scene", "backend": "--backend",
               "device": "device behind --backend", "jpeg_decoder": "--jpeg-decoder",
               "input": "--input",
               "samples_per_photo": "--samples-per-photo",
               "samples_per_sequence": "--samples-per-sequence",
               "files": "camera or kernel file contents", "libraries": "library version",
               "save": "--save", "format": "--format", "shard_size": "--shard-size"}


def jsonable(value):
    """``value`` as JSON holds it: a numpy scalar as its Python number, else as it is."""
    if isinstance(value, np.generic):
        return value.item()
    return value


def plain(value):
    """``value`` as it reads back from JSON (tuples become lists, numpy scalars numbers)."""
    return json.loads(json.dumps(value, default=jsonable))


def library_versions(backend: str) -> dict[str, str]:
    """The versions of the libraries a sample's pixels depend on with ``backend``.

    gpu_blur, numpy and OpenCV (image decoding and encoding, resampling) always; pyopencl or
    Warp with their backends. ``--jpeg-decoder gpu`` adds its own
    (:attr:`gpu_blur.gpu_jpeg.JpegBatches.libraries`).
    """
    import cv2

    versions = {"gpu_blur": __version__, "numpy": np.__version__, "opencv": cv2.__version__}
    family = backend.split(":", 1)[0]
    if family == "opencl":
        import pyopencl

        versions["pyopencl"] = pyopencl.VERSION_TEXT
    elif family == "warp":
        import warp

        versions["warp"] = warp.config.version
    return versions


#: Scene keys of [blur] added since sets were made, with the value those sets had.
_BEFORE_THEM = {"draws": "per-sample", "stride": 0}


def set_keys(scene):
    """A recorded scene without its None-valued keys, as resume compares it.

    A key added to the scene format since a set was made is absent from its run.json, and
    None means the same (a stage off, or the camera's level); so do ``blur.draws =
    "per-sample"`` and ``blur.stride = 0``, what sets made before them did.
    ``blur.interpolation_region`` counts only under ``blur.interpolation = "auto"``, where a
    set made before it had one factor per gap: 0. ``output.png`` changes no pixel, only how
    the files are compressed, so a set resumes under either mode.
    """
    if not isinstance(scene, dict):
        return scene
    scene = {section: ({k: v for k, v in keys.items() if v is not None}
                       if isinstance(keys, dict) else keys) for section, keys in scene.items()}
    blur = scene.get("blur")
    if isinstance(blur, dict):
        scene["blur"] = ({"interpolation_region": 0, **blur}
                         if blur.get("interpolation") == INTERPOLATION_AUTO
                         else {k: v for k, v in blur.items() if k != "interpolation_region"})
        scene["blur"] = {k: v for k, v in scene["blur"].items()
                         if k not in _BEFORE_THEM or v != _BEFORE_THEM[k]}
    if isinstance(scene.get("output"), dict):
        scene["output"] = {k: v for k, v in scene["output"].items() if k != "png"}
    return scene


def _difference(name: str, old, new) -> str:
    """Where two JSON values first differ, as ``name.key = old (this run: new)``."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            if old.get(key) != new.get(key):
                return _difference(f"{name}.{key}", old.get(key), new.get(key))
    shown = [repr(v) if len(repr(v)) <= 80 else repr(v)[:77] + "..." for v in (old, new)]
    return f"{name} = {shown[0]} (this run: {shown[1]})"


def check_run(out: Path, run: dict) -> None:
    """Refuse to resume the set in ``out`` unless ``run`` matches its run.json (RESUME_KEYS)."""
    path = out / RUN
    try:
        if not os.path.lexists(path):
            raise FileNotFoundError(path)
        old = json.loads(files.read_text(path, str(path)))  # a regular file: no FIFO wait
    except FileNotFoundError:
        raise ValueError(f"--resume: {path} is missing, so the settings the set in "
                         f"{out} was made with are unknown; start it again with "
                         "--overwrite, or use another --output") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"--resume: cannot read {path} ({e}); start the set again with "
                         "--overwrite, or use another --output") from None
    if not isinstance(old, dict):
        raise ValueError(f"--resume: {path} holds a JSON {type(old).__name__}, not the "
                         "object gpu-blur writes; start the set again with --overwrite, or "
                         "use another --output")
    for key, option in RESUME_KEYS.items():
        was, now = plain(old.get(key)), plain(run.get(key))
        if key == "scene":  # a key added since (output.jpeg_quality) is absent there
            was, now = set_keys(was), set_keys(now)
        if was != now:
            raise ValueError(
                f"--resume: the set in {out} was made with another {option}: "
                f"{_difference(key, was, now)}; resume with what {path} records (options, "
                "device, library versions, camera and kernel files), or start a new set "
                "with --overwrite or another --output")
