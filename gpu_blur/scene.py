"""The scene: what is simulated, as validated settings loaded from a TOML file.

Every field has a default, so an empty file is a valid scene (camera-shake blur of one photo
through the Sony A7R3 model). A bad file gets an error naming the file, the key, the bad value
and what is allowed. See ``gpu_blur/data/scenes/`` for examples and :data:`FIELDS` for the
full list (``gpu-blur plan --help`` prints it).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from importlib import resources
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from gpu_blur import limits
from gpu_blur.constants import GAUSSIAN_SRGB_NOISE_STD
from gpu_blur.files import parse_settings, read_text
from gpu_blur.limits import Limit
from gpu_blur.png_codecs import PNG_MODES
from gpu_blur.reference.flow import (
    FLOW_METHODS,
    INTERPOLATION_AUTO,
    INTERPOLATION_FACTORS,
    REGION_STEP,
)

__all__ = ["Blur", "CameraSettings", "FIELDS", "FROM_NAME", "Field", "Isp", "Noise", "Optics",
           "Output", "PATTERNS", "PER_SAMPLE", "PER_SEQUENCE", "Saturation", "Scene",
           "SceneError", "builtin_scenes",
           "check_scene", "describe_fields", "load_scene", "scene_from_dict", "scene_path",
           "toml_loads"]

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
#: ``blur.frames`` taking each sequence's frames per blur from its folder's name, ``yy`` of
#: ``GOPRxxxx_yy_zz`` (:func:`gpu_blur.discovery.frames_from_name`).
FROM_NAME = "from-name"
#: ``blur.draws``: a sample's per-image values drawn from its own index (every set before
#: them), or from its frame sequence's, shared by the sequence's windows
#: (:class:`gpu_blur.reference.rng.Keyed`).
PER_SAMPLE, PER_SEQUENCE = "per-sample", "per-sequence"


@dataclasses.dataclass(frozen=True)
class Field:
    """One scene key: its default, what is allowed, and what it means.

    A key takes one of ``choices``, a value of type ``kind`` (str, bool), or a number within
    ``limit`` (:mod:`gpu_blur.limits`: finite, in range, with the reason); ``pair`` makes it a
    ``[low, high]`` range of two such numbers; ``words``: strings a number key also takes.
    """

    default: Any
    help: str
    choices: tuple = ()
    kind: type | None = None
    limit: Limit | None = None
    pair: bool = False
    words: tuple = ()


#: section -> key -> Field. The single definition of the scene format.
FIELDS: dict[str, dict[str, Field]] = {
    "blur": {
        "mode": Field("trajectory", "how the blur is made: 'average' consecutive frames, "
                      "'kernel' (convolve one photo), 'trajectory' (camera shake over one photo), "
                      "'none' (input is already blurred sRGB)",
                      choices=("average", "kernel", "trajectory", "none")),
        "frames": Field(9, "frames averaged per sample in mode 'average' (RSBlur: 9), or "
                        f"'{FROM_NAME}': yy of each sequence folder named GOPRxxxx_yy_zz "
                        "(GOPRO_Large_all: yy frames make one blur)",
                        limit=limits.FRAMES, words=(FROM_NAME,)),
        "stride": Field(0, "mode 'average': frames from one window's first frame to the next "
                        "one's in a sequence; 0 = blur.frames (consecutive windows side by "
                        "side); fewer than blur.frames makes overlapping windows",
                        limit=limits.STRIDE),
        "draws": Field(PER_SAMPLE, f"mode 'average': '{PER_SAMPLE}' draws each sample's "
                       "camera settings (white-balance gains, noise levels, saturation alpha, "
                       f"Bayer pattern, JPEG quality) on its own; '{PER_SEQUENCE}' draws them "
                       "once per frame sequence, shared by all of its windows (video "
                       "deblurring); the noise's pixels differ per window either way",
                       choices=(PER_SAMPLE, PER_SEQUENCE)),
        "interpolation": Field(1, "mode 'average': raise the frame rate by this factor before "
                               "averaging, (frames - 1) * factor + 1 frames in all (RSBlur: 8, "
                               "9 -> 65); 1 averages the frames as they are; 'auto' picks 1, "
                               "2, 4 or 8 per gap from the frames' measured motion",
                               choices=(*INTERPOLATION_FACTORS, INTERPOLATION_AUTO)),
        "interpolation_tolerance": Field(
            1.0, "blur.interpolation = 'auto': the largest step, pixels, between consecutive "
            "averaged frames; each gap gets the fewest inserted frames that keep its motion "
            "(99th percentile) under it", limit=limits.INTERPOLATION_TOLERANCE),
        "interpolation_region": Field(
            64, "blur.interpolation = 'auto': side, pixels (a multiple of 16), of the squares "
            "that each get their own factor per gap, so a still part of a moving sequence "
            "inserts no frames; 0 = one factor per gap for the whole frame",
            limit=limits.INTERPOLATION_REGION),
        "flow": Field("dis", "optical flow for blur.interpolation other than 1, computed on "
                      "the host with OpenCV: 'dis' (DIS, preset medium) or 'farneback'",
                      choices=FLOW_METHODS),
        "steps": Field(0, "poses along the camera path in mode 'trajectory'; 0 = auto: about "
                       "one per pixel of the longest pixel path, so blur is a streak, not copies",
                       limit=limits.STEPS),
        "extent": Field([4.0, 24.0], "range of the shake path's extent at the image centre, "
                        "pixels (drawn per sample)", limit=limits.EXTENT, pair=True),
        "roll": Field(0.5, "largest camera roll during the exposure, degrees",
                      limit=limits.ROLL),
        "kernel": Field("", "mode 'kernel': path of a kernel (.npy or grayscale .png); "
                        "empty draws a random motion kernel per sample", kind=str),
        "kernel_size": Field([5, 29], "mode 'kernel', random kernels: range of odd sizes "
                             "(GoPro_U used 5..29)", limit=limits.KERNEL_SIZE, pair=True),
    },
    "saturation": {
        "mode": Field("auto", "saturation synthesis: 'on', 'off', or 'auto' (only for samples "
                      "with pixels at the clip level)", choices=("auto", "on", "off")),
        "alpha": Field([0.25, 1.75], "range of the highlight boost alpha (RSBlur: U(0.25, "
                       "1.75))", limit=limits.ALPHA, pair=True),
    },
    "camera": {
        "name": Field("a7r3", "camera preset (a7r3, a7r3-wb-list, rsblur-0001..0019, srgb) or "
                      "path of a camera .toml/.json", kind=str),
    },
    "noise": {
        "model": Field("poisson-gaussian", "'poisson-gaussian' on the RAW mosaic, 'gaussian' "
                       "in sRGB, or 'none'", choices=("poisson-gaussian", "gaussian", "none")),
        "shot_noise_k": Field(None, "Poisson gain K (RSBlur beta1); default: the camera's",
                              limit=limits.SHOT_NOISE_K),
        "read_noise_std": Field(None, "read-noise std (RSBlur beta2); default: the camera's",
                                limit=limits.READ_NOISE_STD),
        "spread": Field(0.5, "K and the std are drawn in level * (1 +- spread) (RSBlur: 0.5)",
                        limit=limits.SPREAD),
        "gaussian_std": Field(GAUSSIAN_SRGB_NOISE_STD, "sRGB Gaussian noise std before the "
                              "+- spread draw (RSBlur TF)", limit=limits.GAUSSIAN_STD),
        "poisson": Field("exact", "shot-noise sampler: 'exact' (inversion below rate 10, PTRS "
                         "above) or 'normal' (accuracy knob: max(0, round(rate + sqrt(rate) z)) "
                         "for rates above noise.normal_above)", choices=("exact", "normal")),
        "normal_above": Field(1000.0, "noise.poisson = 'normal': the Poisson rate (photon "
                              "counts per photosite) above which counts are a rounded normal",
                              limit=limits.NORMAL_ABOVE),
    },
    "isp": {
        "round_trip": Field("auto", "RAW round trip: 'auto' (only with poisson-gaussian noise) "
                            "or 'always' (demosaic artefacts even without noise)",
                            choices=("auto", "always")),
        "demosaic": Field("malvar2004", "demosaicing method", choices=("malvar2004", "bilinear")),
        "pattern": Field("random", "Bayer pattern, or 'random' per sample",
                         choices=("random", *PATTERNS)),
        "border": Field("reflect", "demosaic border: 'reflect' keeps the Bayer phase; 'zero' "
                        "as the authors' PyTorch code", choices=("reflect", "zero")),
        "clip_camera": Field(False, "clip camera RGB to [0, 1] before mosaicing (RSBlur TF)",
                             kind=bool),
        "clip_demosaic": Field(False, "clip the demosaiced image to [0, 1] (RSBlur TF)",
                               kind=bool),
    },
    "optics": {
        "vignetting": Field(0.0, "lens vignetting strength s: linear irradiance times "
                            "1 - s (r / r_corner)^2, r the distance from the image centre "
                            "(0: none)", limit=limits.VIGNETTING),
    },
    "output": {
        "crf": Field("srgb", "final tone: 'srgb' (the ISP's sRGB curve), 'a7r3' (re-tone with "
                     "the A7R3 polynomial), 'a7r3-lut' (its lookup table), 'camera' (re-tone "
                     "with the camera file's fitted response, its [response] polynomial from "
                     "gpu-blur calibrate --crf-linear/--crf-rendered), 'none' (linear)",
                     choices=("srgb", "a7r3", "a7r3-lut", "camera", "none")),
        "bits": Field(8, "quantize to 8 or 16 bits (round half up), or 0 to keep float",
                      choices=(0, 8, 16)),
        "crop": Field(0, "pixels cropped from every side of both outputs (RSBlur: 4)",
                      limit=limits.CROP),
        "precision": Field("float32", "compute precision of kernel backends",
                           choices=("float32", "float64")),
        "crf_table_size": Field(0, "output.crf = 'a7r3-lut': nodes of the re-toning table; 0 = "
                                "the authors' 2,551, another size (>= 2, e.g. 256, 1024, 4096) "
                                "resamples it (accuracy knob)",
                                limit=limits.CRF_TABLE_SIZE),
        "fast_math": Field(False, "kernel backends, float32 only: fast transcendentals (OpenCL "
                           "native_ functions, Warp's CUDA fast math) for the sRGB curves and "
                           "the Gaussian normals; Poisson counts stay exact (accuracy knob)",
                           kind=bool),
        "png": Field("fast", "how PNG outputs are compressed, the same pixels either way: "
                     "'fast' (numpy's Sub filter, Huffman-coded deflate), 'fastest' (ISA-L's "
                     "deflate instead: faster, but a file's bytes may differ between runs, "
                     "never its pixels), 'small' (the "
                     "smallest of OpenCV's libpng files and the fast one: slower, a few % "
                     "smaller), 'stored' (no compression: the largest files, the least CPU "
                     "to write and read); the performance page gives ms and MB an image",
                     choices=tuple(PNG_MODES)),
        "jpeg_quality": Field(None, "[low, high]: a JPEG round trip of the blurred output as "
                              "the last stage (OpenCV, 4:2:0 chroma), at a quality drawn per "
                              "sample in the range; needs output.bits = 8; absent: no JPEG",
                              limit=limits.JPEG_QUALITY, pair=True),
    },
}


def _section_class(section: str, name: str):
    """A frozen dataclass for one section, named ``name`` in this module (so it pickles)."""
    fields = [(k, object, dataclasses.field(default=None)) for k in FIELDS[section]]
    cls = dataclasses.make_dataclass(name, fields, frozen=True)
    cls.__module__ = __name__  # make_dataclass leaves "types": pickle could not find it
    return cls


Blur = _section_class("blur", "Blur")
Saturation = _section_class("saturation", "Saturation")
CameraSettings = _section_class("camera", "CameraSettings")
Noise = _section_class("noise", "Noise")
Isp = _section_class("isp", "Isp")
Optics = _section_class("optics", "Optics")
Output = _section_class("output", "Output")
_SECTIONS = {"blur": Blur, "saturation": Saturation, "camera": CameraSettings, "noise": Noise,
             "isp": Isp, "optics": Optics,
             "output": Output}


@dataclasses.dataclass(frozen=True)
class Scene:
    """Validated scene settings, one frozen dataclass per TOML section (see :data:`FIELDS`)."""

    blur: Any
    saturation: Any
    camera: Any
    noise: Any
    isp: Any
    optics: Any
    output: Any
    path: Path | None = None  # the file it came from (relative camera/kernel paths use it)

    def __post_init__(self):
        check_scene(self, f"scene file {self.path}" if self.path else "scene")

    @property
    def base_dir(self) -> Path | None:
        """Folder that relative paths inside the scene are resolved against."""
        return self.path.parent if self.path else None

    def to_dict(self) -> dict:
        """Plain nested dict of every setting (for manifests and ``gpu-blur plan``)."""
        return {s: dataclasses.asdict(getattr(self, s)) for s in _SECTIONS}


class SceneError(ValueError):
    """A scene file or dict that does not validate."""


def toml_loads(text: str) -> dict:
    """Parse TOML text (stdlib tomllib on 3.11+, tomli before); errors are ValueError."""
    return tomllib.loads(text)


def _check(where: str, key: str, field: Field, value):
    """``value`` of one key, checked (pairs as lists, numbers as Python int or float).

    Raises:
        SceneError: naming ``where``, the key, the value and what is allowed.
    """
    def fail(allowed: str):
        raise SceneError(f"{where}: {key} = {value!r} is invalid; allowed: {allowed}")

    def number(v):
        problem = field.limit.problem(v)
        if problem and field.words:
            problem += "".join(f", or {w!r}" for w in field.words)
        if problem:
            fail(f"[low, high], each {problem}" if field.pair else problem)
        if type(v) not in (int, float):  # numpy scalars from the Python API
            v = int(v) if field.limit.integer else float(v)
        return v

    if value is None and field.default is None:
        return None  # the camera's level
    if field.choices:
        if value not in field.choices or isinstance(value, bool) != isinstance(
                field.choices[0], bool):
            fail(" | ".join(repr(c) for c in field.choices))
        return value
    if isinstance(value, str) and value in field.words:
        return value
    if field.pair:
        if not (isinstance(value, (list, tuple)) and len(value) == 2):
            fail(f"a [low, high] pair of {field.limit.kind} {field.limit.describe()}")
        low, high = (number(v) for v in value)
        if low > high:
            fail("low <= high")
        return [low, high]
    if field.limit is not None:
        return number(value)
    if not isinstance(value, field.kind) or (field.kind is not bool and isinstance(value, bool)):
        fail(field.kind.__name__)
    return value


def check_scene(scene: Scene, where: str) -> None:
    """Check every setting of a scene, and how they combine, as :func:`scene_from_dict` does.

    :class:`Scene` runs it on construction, so a scene made in Python (or changed with
    ``dataclasses.replace``) meets the checks of a scene file.

    Raises:
        SceneError: naming ``where``, the key, the bad value and what is allowed.
    """
    sections = {name: getattr(scene, name) for name in FIELDS}
    for section, fields in FIELDS.items():
        for key, field in fields.items():
            _check(where, f"{section}.{key}", field, getattr(sections[section], key))
    _check_consistency(sections, where)


def scene_from_dict(data: dict, where: str = "scene", path: Path | None = None) -> Scene:
    """Validate a nested dict (as parsed from TOML) into a :class:`Scene`.

    Raises:
        SceneError: naming ``where``, the key, the bad value and what is allowed.
    """
    if not isinstance(data, dict):
        raise SceneError(f"{where}: expected a table of sections, got {type(data).__name__}")
    unknown = sorted(set(data) - set(FIELDS))
    if unknown:
        raise SceneError(f"{where}: unknown section [{unknown[0]}]; sections are "
                         f"{', '.join('[' + s + ']' for s in FIELDS)}")
    sections = {}
    for section, fields in FIELDS.items():
        given = data.get(section, {})
        if not isinstance(given, dict):
            raise SceneError(f"{where}: {section} must be a [{section}] table, got {given!r}")
        extra = sorted(set(given) - set(fields))
        if extra:
            raise SceneError(f"{where}: unknown key {section}.{extra[0]}; [{section}] keys are "
                             f"{', '.join(fields)}")
        values = {}
        for key, field in fields.items():
            if key in given:
                values[key] = _check(where, f"{section}.{key}", field, given[key])
            else:
                values[key] = (list(field.default) if field.pair and field.default is not None
                               else field.default)
        sections[section] = _SECTIONS[section](**values)
    _check_consistency(sections, where)
    return Scene(**sections, path=path)


def _check_consistency(sections: dict, where: str) -> None:
    blur, output = sections["blur"], sections["output"]
    if blur.interpolation != 1 and blur.mode != "average":
        raise SceneError(f"{where}: blur.interpolation = {blur.interpolation!r} needs "
                         f"blur.mode = 'average' (it is {blur.mode!r}); allowed: 1 for "
                         "this mode, or set blur.mode = 'average'")
    if blur.frames == FROM_NAME and blur.mode != "average":
        raise SceneError(f"{where}: blur.frames = '{FROM_NAME}' needs blur.mode = 'average' "
                         f"(it is {blur.mode!r}): it counts the frames averaged per blur; "
                         "allowed for this mode: a number, or set blur.mode = 'average'")
    for key, value, plain in (("draws", blur.draws, PER_SAMPLE), ("stride", blur.stride, 0)):
        if value != plain and blur.mode != "average":
            raise SceneError(f"{where}: blur.{key} = {value!r} needs blur.mode = 'average' (it "
                             f"is {blur.mode!r}): it concerns the windows of frame sequences; "
                             f"allowed for this mode: {plain!r}, or set blur.mode = 'average'")
    if blur.interpolation_region % REGION_STEP:
        raise SceneError(f"{where}: blur.interpolation_region = {blur.interpolation_region!r} "
                         f"is invalid; allowed: 0 or a multiple of {REGION_STEP} (e.g. 64)")
    lo, hi = blur.kernel_size
    if blur.mode == "kernel" and not blur.kernel and lo % 2 == 0 and lo == hi:
        raise SceneError(f"{where}: blur.kernel_size = {blur.kernel_size!r} holds no odd "
                         "size; allowed: a range containing an odd size")
    size, crf = output.crf_table_size, output.crf
    if size == 1:
        raise SceneError(f"{where}: output.crf_table_size = 1 is invalid; allowed: 0 (the "
                         "authors' table) or a size >= 2")
    if size and crf != "a7r3-lut":
        raise SceneError(f"{where}: output.crf_table_size = {size!r} needs output.crf = "
                         f"'a7r3-lut' (it is {crf!r}); allowed with another crf: 0")
    if output.jpeg_quality is not None and output.bits != 8:
        raise SceneError(f"{where}: output.jpeg_quality = {list(output.jpeg_quality)!r} needs "
                         f"output.bits = 8 (it is {output.bits!r}): JPEG holds 8-bit codes; "
                         "set output.bits = 8, or leave output.jpeg_quality out")
    if output.fast_math and output.precision != "float32":
        raise SceneError(f"{where}: output.fast_math = true needs output.precision = "
                         "'float32' (fast functions exist for float only); allowed with "
                         "'float64': false")


def builtin_scenes() -> dict[str, Path]:
    """The example scenes shipped in ``gpu_blur/data/scenes/``, by name (file name, no suffix)."""
    folder = Path(str(resources.files("gpu_blur").joinpath("data/scenes")))
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}


def scene_path(name: str | Path) -> Path:
    """The file a scene name stands for: an existing file, else a built-in scene's.

    ``realblur_j`` and ``realblur_j.toml`` name the built-in scene unless a file of that name
    exists (a file of one's own always wins).

    Raises:
        SceneError: naming the file and the built-in scenes, when it is neither.
    """
    path = Path(name)
    if path.exists():
        return path
    builtin = builtin_scenes()
    stem = path.name[:-5] if path.name.endswith(".toml") else path.name
    if path.parent == Path(".") and stem in builtin:
        return builtin[stem]
    raise SceneError(f"scene file {path} does not exist; built-in scenes (by name): "
                     f"{', '.join(builtin)}")


def load_scene(path: str | Path | dict | None = None) -> Scene:
    """Load and validate a scene: a TOML file, a built-in scene's name, or a dict of sections.

    ``None`` gives the default scene; names are resolved by :func:`scene_path`.
    """
    if path is None:
        return scene_from_dict({})
    if isinstance(path, dict):
        return scene_from_dict(path)
    path = scene_path(path)
    where = f"scene file {path}"
    try:
        data = parse_settings(read_text(path, where), "TOML", where)
    except ValueError as e:
        raise SceneError(str(e)) from None
    return scene_from_dict(data, where=where, path=path)


def describe_fields() -> str:
    """Every scene key with its default, meaning and range: a TOML file of the default scene.

    ``gpu-blur scene > my.toml`` is a scene ``--scene`` takes as it is; a key whose default
    comes from the camera, or a stage off unless given, is commented out (TOML has no null).
    """
    lines = []
    for section, fields in FIELDS.items():
        lines.append(f"[{section}]")
        for key, f in fields.items():
            allowed = f" [{f.limit.describe()}]" if f.limit is not None else ""
            if f.choices:
                allowed = f" [one of {', '.join(json.dumps(c) for c in f.choices)}]"
            if f.default is None:
                lines.append(f"# {key} = ...  # {f.help}{allowed}")
                continue
            default = json.dumps(f.default)  # TOML's strings, numbers, booleans and arrays
            lines.append(f"{key} = {default}  # {f.help}{allowed}")
        lines.append("")
    return "\n".join(lines)
