"""Writing a camera file (TOML or JSON) that :func:`gpu_blur.cameras.load_camera` reads."""

from __future__ import annotations

import json
from pathlib import Path

from gpu_blur.imageio import write_text


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value) if isinstance(value, int) else repr(float(value))
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def camera_file_text(camera: dict, suffix: str = ".toml") -> str:
    """A camera dict (top-level scalars, then tables of values) as TOML or JSON text."""
    if suffix.lower() == ".json":
        return json.dumps(camera, indent=2) + "\n"
    lines = [f"{k} = {_toml_value(v)}" for k, v in camera.items() if not isinstance(v, dict)]
    for table, values in camera.items():
        if isinstance(values, dict):
            lines += ["", f"[{table}]"]
            lines += [f"{k} = {_toml_value(v)}" for k, v in values.items()]
    return "\n".join(lines) + "\n"


def write_camera_file(path: str | Path, camera: dict) -> None:
    """Write a camera file atomically and check that ``load_camera`` reads it.

    The text goes to a temporary file next to ``path``, is loaded back with
    :func:`gpu_blur.cameras.load_camera`, and is renamed onto ``path``
    (:func:`gpu_blur.imageio.write_text`), so ``path`` is never half-written or invalid.

    Raises:
        ValueError: for a name not ending in .toml or .json, or a camera the loader refuses.
        OSError: naming the file when it cannot be written.
    """
    from gpu_blur.cameras import load_camera

    path = Path(path)
    if path.suffix.lower() not in (".toml", ".json"):
        raise ValueError(f"{path}: a camera file's name must end in .toml or .json")

    def check(tmp: Path) -> None:
        try:
            load_camera(tmp)
        except ValueError as e:
            raise ValueError(str(e).replace(str(tmp), str(path))) from None

    try:
        write_text(path, camera_file_text(camera, path.suffix), check)
    except OSError as e:
        raise OSError(f"{path}: cannot write the camera file ({e.strerror})") from None
