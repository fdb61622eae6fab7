"""What the benchmark runs: the input frames, the base scene and every knob setting."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

__all__ = ["BASE", "BASE_SCENE", "DEFAULT_SIZE", "FRAMES", "KERNEL_ONLY_KEYS", "KNOBS", "MIN_RUNS",
           "MIN_SIDE", "NOISE_FREE", "PAN_PX", "QUICK_SIZE", "Setting", "make_frames", "merge",
           "quick_knobs", "select_knobs", "setting_scene"]

#: The input's size, width x height, and frame count (blur.mode = "average").
DEFAULT_SIZE = (1920, 1200)
#: ``--quick``'s size: a few minutes for every backend of a 2-core CPU (README, bench).
QUICK_SIZE = (320, 200)
FRAMES = 9
#: Pixels the camera pans right per frame: each frame is a window of the upscaled photo.
PAN_PX = 2
#: Every run draws the same values: the errors compare like with like.
SEED, SAMPLE_INDEX = 1, 0
#: Timed runs per measurement, after one warm-up (issue 7: at least 5).
MIN_RUNS = 5
#: The smallest --size side: the side-by-side border, the 29-tap kernel and the 8 x 8 optical
#: flow patches need some room.
MIN_SIDE = 32

#: The base scene, close to RSBlur's synthesis: 9 frames averaged, saturation on, the A7R3
#: camera's Poisson-Gaussian noise on the RAW mosaic, Malvar 2004, re-toned with the A7R3
#: response; float output so errors below one 8-bit code show.
BASE_SCENE = {
    "blur": {"mode": "average", "frames": FRAMES},
    "saturation": {"mode": "on"},
    "camera": {"name": "a7r3"},
    "noise": {"model": "poisson-gaussian"},
    "isp": {"demosaic": "malvar2004"},
    "output": {"crf": "a7r3", "bits": 0},
}
#: Added for the error runs: no noise, but the RAW round trip (mosaic, demosaic) still runs.
NOISE_FREE = {"noise": {"model": "none"}, "isp": {"round_trip": "always"}}
#: Scene keys the numpy reference ignores (it always runs float64 with precise maths).
KERNEL_ONLY_KEYS = (("output", "precision"), ("output", "fast_math"))


@dataclasses.dataclass(frozen=True)
class Setting:
    """One setting of one accuracy knob.

    Attributes:
        knob: the knob's name (rows of one knob compare against one reference).
        label: the setting, in words.
        scene: scene overrides over :data:`BASE_SCENE`, ``{section: {key: value}}``.
        tile: run in tiles of at most (rows, columns) pixels, or None for the whole image.
        reference: the knob's accurate setting: its numpy float64 run is the reference.
    """

    knob: str
    label: str
    scene: dict = dataclasses.field(default_factory=dict)
    tile: tuple[int, int] | None = None
    reference: bool = False

    @property
    def kernel_only(self) -> bool:
        """Whether only kernel backends see this setting (numpy ignores it)."""
        keys = [(s, k) for s, keys in self.scene.items() for k in keys]
        return self.tile is not None or bool(keys) and all(k in KERNEL_ONLY_KEYS for k in keys)


#: The base scene itself (the side-by-side pipeline rows).
BASE = Setting("base", "base scene")


def _lut(nodes: int) -> dict:
    return {"output": {"crf": "a7r3-lut", "crf_table_size": nodes}}


def _normal_above(rate: float) -> dict:
    return {"noise": {"poisson": "normal", "normal_above": rate}}


#: Every knob setting, each knob's accurate (reference) setting first. ``--quick`` keeps the
#: first two settings of each knob.
KNOBS: tuple[Setting, ...] = (
    Setting("precision", "float64", {"output": {"precision": "float64"}}, reference=True),
    Setting("precision", "float32", {"output": {"precision": "float32"}}),
    Setting("precision", "float16 storage", {"output": {"precision": "float16"}}),
    Setting("demosaic", "Malvar 2004", {"isp": {"demosaic": "malvar2004"}}, reference=True),
    Setting("demosaic", "bilinear", {"isp": {"demosaic": "bilinear"}}),
    # The authors' table is another curve than their polynomial (up to 0.0071 apart,
    # gpu_blur.reference.transfer.a7r3_lookup_table), so the tables' resolution is a knob of
    # its own, against the authors' table.
    Setting("CRF", "polynomial", {"output": {"crf": "a7r3"}}, reference=True),
    Setting("CRF", "authors' table", _lut(0)),
    Setting("CRF table", "2,551 nodes (authors')", _lut(0), reference=True),
    Setting("CRF table", "4,096 nodes", _lut(4096)),
    Setting("CRF table", "1,024 nodes", _lut(1024)),
    Setting("CRF table", "256 nodes", _lut(256)),
    Setting("maths", "precise", {"output": {"fast_math": False}}, reference=True),
    Setting("maths", "fast", {"output": {"fast_math": True}}),
    Setting("Poisson", "exact", {"noise": {"poisson": "exact"}}, reference=True),
    Setting("Poisson", "normal above 1000", _normal_above(1000.0)),
    Setting("Poisson", "normal above 100", _normal_above(100.0)),
    Setting("Poisson", "normal above 10", _normal_above(10.0)),
    Setting("motion", "interpolation 8x", {"blur": {"interpolation": 8}}, reference=True),
    Setting("motion", "interpolation 4x", {"blur": {"interpolation": 4}}),
    Setting("motion", "interpolation 2x", {"blur": {"interpolation": 2}}),
    Setting("motion", "interpolation 1x", {"blur": {"interpolation": 1}}),
    Setting("motion", "interpolation auto (1 px)", {"blur": {"interpolation": "auto"}}),
    Setting("tile", "whole image", reference=True),
    Setting("tile", "1024 x 1024", tile=(1024, 1024)),
    Setting("tile", "512 x 512", tile=(512, 512)),
    Setting("tile", "256 x 256", tile=(256, 256)),
)


def quick_knobs(knobs: Sequence[Setting] = KNOBS) -> list[Setting]:
    """The first two settings of every knob (its reference and one other)."""
    seen: dict[str, int] = {}
    kept = []
    for s in knobs:
        seen[s.knob] = seen.get(s.knob, 0) + 1
        if seen[s.knob] <= 2:
            kept.append(s)
    return kept


def select_knobs(names: Sequence[str], knobs: Sequence[Setting] = KNOBS) -> list[Setting]:
    """The settings of the named knobs (names as in the table, any case).

    Raises:
        ValueError: naming an unknown knob and the known ones.
    """
    known = {s.knob.lower(): s.knob for s in knobs}
    unknown = [n for n in names if n.lower() not in known]
    if unknown or not names:
        raise ValueError(f"--knobs: {', '.join(unknown) or 'none given'}; known: "
                         f"{', '.join(dict.fromkeys(known.values()))}")
    wanted = {known[n.lower()] for n in names}
    return [s for s in knobs if s.knob in wanted]


def merge(*layers: dict) -> dict:
    """Scene dicts merged section by section, later layers winning."""
    out: dict = {}
    for layer in layers:
        for section, values in layer.items():
            out.setdefault(section, {}).update(values)
    return out


def setting_scene(setting: Setting, *extra: dict):
    """The validated scene of a setting (a :class:`~gpu_blur.scene.SceneError` if refused)."""
    from gpu_blur.scene import scene_from_dict

    return scene_from_dict(merge(BASE_SCENE, setting.scene, *extra),
                           where=f"knob {setting.knob}: {setting.label}")


def make_frames(width: int, height: int, frames: int = FRAMES) -> list[np.ndarray]:
    """The benchmark's input: windows of the upscaled built-in photo, panning right.

    The photo (600 x 400, :func:`gpu_blur.discovery.default_photo`) is upscaled with bicubic
    interpolation until a ``width x height`` window fits ``(frames - 1) * PAN_PX`` times
    side by side; frame ``i`` starts ``i * PAN_PX`` pixels right of frame 0.

    Returns:
        ``frames`` arrays of ``height x width x 3`` uint8 sRGB codes (R, G, B).
    """
    import cv2

    from gpu_blur.discovery import default_photo
    from gpu_blur.image_reading import read_image

    photo = read_image(default_photo())
    pan = (frames - 1) * PAN_PX
    scale = max((width + pan) / photo.shape[1], height / photo.shape[0])
    size = (math.ceil(photo.shape[1] * scale), math.ceil(photo.shape[0] * scale))
    big = cv2.resize(photo, size, interpolation=cv2.INTER_CUBIC)
    y0 = (big.shape[0] - height) // 2
    return [np.ascontiguousarray(big[y0:y0 + height, i * PAN_PX:i * PAN_PX + width])
            for i in range(frames)]
