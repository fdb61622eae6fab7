"""Writing a camera file (TOML or JSON) that :func:`gpu_blur.cameras.load_camera` reads."""

from __future__ import annotations

import json
from pathlib import Path

from gpu_blur.file_writing import write_text

__all__ = ["camera_file_text", "write_camera_file"]


def _toml_string(text: str) -> str:
    """``text`` as a TOML basic string, its characters as they are but quotes and controls.

    The quotation mark, the backslash and the control characters TOML forbids are escaped
    (``json.dumps`` would split a character beyond U+FFFF, an emoji, into a surrogate pair
    of escapes, which TOML refuses).
    """
    out = []
    for c in text:
        if c in '"\\':
            out.append("\\" + c)
        elif c < " " or c == "\x7f":
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value) if isinstance(value, int) else repr(float(value))
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _check_text(camera: dict, path: Path, key: str = "") -> None:
    """Refuse a string of ``camera`` that UTF-8 cannot hold (a lone surrogate).

    Python gives bytes of a command-line argument that are not UTF-8 as lone surrogates.

    Raises:
        ValueError: naming the file, the key and the value.
    """
    for k, value in camera.items():
        where = f"{key}.{k}" if key else k
        if isinstance(value, dict):
            _check_text(value, path, where)
        elif isinstance(value, str) and any("\ud800" <= c <= "\udfff" for c in value):
            raise ValueError(f"{path}: {where} = {value!r} is invalid; expected text (it holds "
                             "bytes that are not UTF-8): give it in UTF-8")


def camera_file_text(camera: dict, suffix: str = ".toml") -> str:
    """A camera dict (top-level scalars, then tables of values) as TOML or JSON text."""
    if suffix.lower() == ".json":
        return json.dumps(camera, indent=2, ensure_ascii=False) + "\n"
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
    (:func:`gpu_blur.file_writing.write_text`), so ``path`` is never half-written or invalid.

    Raises:
        ValueError: for a name not ending in .toml or .json, or a camera the loader refuses.
        OSError: naming the file when it cannot be written.
    """
    from gpu_blur.cameras import load_camera

    path = Path(path)
    if path.suffix.lower() not in (".toml", ".json"):
        raise ValueError(f"{path}: a camera file's name must end in .toml or .json")
    _check_text(camera, path)

    def check(tmp: Path) -> None:
        try:
            load_camera(tmp)
        except ValueError as e:
            raise ValueError(str(e).replace(str(tmp), str(path))) from None

    try:
        write_text(path, camera_file_text(camera, path.suffix), check)
    except OSError as e:
        raise OSError(f"{path}: cannot write the camera file ({e.strerror})") from None
