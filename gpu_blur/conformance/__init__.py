"""The conformance cases: crafted inputs and real photos that every backend must get right.

One source for ``gpu-blur validate`` (:mod:`gpu_blur.conformance.checks` and the checks'
topic modules, imported at the end of this one) and the test suite
(tests/backends/test_hard_cases.py imports these inputs and helpers), so that a green CI and a
green ``validate`` mean the same thing.

The helpers take any backend (``gpu_blur.backends.get_backend``); pass outputs come back to the
host as float64 arrays. Kernel backends round their inputs to their compute type; where a check
is about the kernels' arithmetic, the reference is fed the same rounded values
(:func:`on_device`).
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Sequence
from importlib import resources

import numpy as np

from gpu_blur.backends import to_host
from gpu_blur.cameras import get_camera
from gpu_blur.params import draw_params
from gpu_blur.planning import plan
from gpu_blur.reference import transfer
from gpu_blur.scene import scene_from_dict
from gpu_blur.tiling import Region

__all__ = ["A7R3_DIP_POINTS", "A7R3_POLYNOMIAL_POINTS", "BIG", "BigFrame", "DESATURATING",
           "NEAR_SINGULAR", "NO_RAW_FINISH", "OUT_OF_GAMUT", "POSES_LEAVING_THE_IMAGE", "PRIMARIES",
           "RATES", "StreamedFrames", "big_pattern", "coffee", "coffee_crop", "decode_on",
           "finish_on", "in_a_row", "on_device", "prepare", "scene_for", "seam_image", "shift",
           "tall_thin_linear", "transfer_points"]

#: The seed and sample index every case draws its parameters and noise with.
SEED, SAMPLE = 23, 5


# -- real photos -------------------------------------------------------------------------------

@functools.cache
def coffee() -> np.ndarray:
    """The built-in photograph (gpu_blur/data/coffee.png), float64 sRGB in [0, 1], R, G, B.

    scikit-image's CC0 "coffee", 400 x 600 x 3. Read-only, so no caller can change it for
    the others.

    Its spoon and cup rim clip (saturated highlights); crops used by the cases:
    ``[220:316, 300:428]`` (the spoon) and ``[150:310, 250:450]`` (cup, rim and table).
    """
    import cv2

    path = resources.files("gpu_blur").joinpath("data/coffee.png")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise OSError(f"cannot read {path}: reinstall gpu_blur (the file ships with it)")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0
    rgb.setflags(write=False)
    return rgb


def coffee_crop(rows=slice(220, 316), cols=slice(300, 428)) -> np.ndarray:
    """A crop of the coffee photograph (default: the spoon's clipped highlights)."""
    return np.ascontiguousarray(coffee()[rows, cols])


# -- running one pass on a backend ---------------------------------------------------------------

def on_device(precision: str, values) -> np.ndarray:
    """``values`` as kernels of ``precision`` hold them (float32 rounds), as float64."""
    real = np.float32 if precision == "float32" else np.float64
    return np.asarray(values, dtype=real).astype(np.float64)


def scene_for(precision: str, settings: dict):
    """A scene from sections of settings, computing in ``precision``."""
    data = {section: dict(values) for section, values in settings.items()}
    data.setdefault("output", {})["precision"] = precision
    return scene_from_dict(data)


def prepare(precision: str, settings: dict, shape, camera: str = "a7r3", overrides=None):
    """(plan, camera, params) of sample :data:`SEED` / :data:`SAMPLE` for ``shape`` (rows, cols).

    The parameters are drawn as the pipeline draws them.
    """
    scene = scene_for(precision, settings)
    cam = get_camera(camera)
    params = draw_params(scene, plan(scene), cam, seed=SEED, sample_index=SAMPLE,
                         image_shape=shape, overrides=overrides)
    return plan(scene), cam, params


def in_a_row(values) -> np.ndarray:
    """Values as a 1-row RGB image, in order along the row (padded with 1.0 to whole pixels)."""
    values = np.asarray(values, dtype=np.float64)
    padded = np.concatenate([values, np.ones(-values.size % 3)])
    return padded.reshape(1, -1, 3)


def decode_on(backend, srgb: np.ndarray) -> np.ndarray:
    """The sRGB EOTF through ``backend``'s accumulate pass (blur mode none linearizes only)."""
    image = in_a_row(srgb)
    p, _, params = prepare(backend.precision, {"blur": {"mode": "none"}}, image.shape[:2])
    linear, _ = backend.accumulate(p, params, [image], None, Region.whole(*image.shape[:2]))
    return to_host(linear).reshape(-1)[:srgb.size]


#: Settings of a finish pass without a RAW round trip: clip(OETF(x)), then the re-tone.
NO_RAW_FINISH = {"blur": {"mode": "none"}, "noise": {"model": "none"},
                 "saturation": {"mode": "off"}, "output": {"bits": 0}}


def finish_on(backend, linear: np.ndarray, crf: str = "srgb") -> np.ndarray:
    """The finish pass of ``backend`` without a RAW round trip: clip(OETF(x)), then ``crf``."""
    image = in_a_row(linear)
    settings = {**NO_RAW_FINISH, "output": {"bits": 0, "crf": crf}}
    p, cam, params = prepare(backend.precision, settings, image.shape[:2])
    whole = Region.whole(*image.shape[:2])
    out = backend.finish(p, params, cam, image, image, whole, whole, seed=SEED,
                         sample_index=SAMPLE)
    return to_host(out).reshape(-1)[:linear.size]


# -- transfer functions ------------------------------------------------------------------------

def transfer_points() -> np.ndarray:
    """0, 1, the sRGB knees and their float64 and float32 neighbours, denormals, tiny values."""
    points = [0.0, 5e-324, 1e-310, 2.0**-149, 1e-40, 2.0**-126, 1e-30, 1e-12, 1e-7, 0.5,
              1 - 2.0**-24, 1 - 2.0**-53, 1.0]
    for knee in (transfer.SRGB_ENCODE_KNEE, transfer.SRGB_DECODE_KNEE):
        f = np.float32(knee)
        points += [knee, np.nextafter(knee, 0), np.nextafter(knee, 1), float(f),
                   float(np.nextafter(f, np.float32(0))), float(np.nextafter(f, np.float32(1)))]
    dense = [np.linspace(0, 1, 1025), np.linspace(0.0030, 0.0032, 129),
             np.linspace(0.0400, 0.0410, 129)]
    return np.unique(np.concatenate([points, *dense]))


#: Linear values for the A7R3 polynomial: both sides of [0, 1] (it must clip to exactly 0 and
#: 1) and a dense sweep where its degree-7 Horner sum cancels.
A7R3_POLYNOMIAL_POINTS = np.concatenate([[-7.0, -1.0, -1e-3, -0.0, 0.0, 1e-6],
                                         np.linspace(0, 1, 4097), [1 + 1e-6, 1.5, 7.0]])

#: Linear values near 0.86, where the fitted A7R3 polynomial dips and its table does not.
A7R3_DIP_POINTS = np.linspace(0.85, 0.875, 2001)


# -- frames ------------------------------------------------------------------------------------

class StreamedFrames(Sequence):
    """``n`` sRGB frames made on demand from their index, never all held at once.

    Half the values stay the same in every frame (a plain running sum of equal terms drifts
    the most), the others oscillate; bright pixels saturate on every third frame. Records how
    many earlier frames are still alive whenever a frame is made (``max_alive``).
    """

    def __init__(self, n: int, shape=(12, 16)):
        self.n, self.shape = n, (*shape, 3)
        gen = np.random.default_rng(7)
        self.base = gen.uniform(0.45, 1.0, self.shape)
        self.amplitude = np.where(gen.uniform(size=self.shape) < 0.5, 0.0, 0.03)
        self.phase = gen.uniform(0, 2 * np.pi, self.shape)
        self.bright = self.base > 0.96
        self._made: list[weakref.ref] = []
        self.max_alive = 0

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):
        if not isinstance(i, (int, np.integer)):
            raise TypeError("frames are streamed by index")
        if not -self.n <= i < self.n:
            raise IndexError(i)
        i %= self.n
        alive = sum(ref() is not None for ref in self._made)
        self.max_alive = max(self.max_alive, alive)
        frame = np.clip(self.base + self.amplitude * np.sin(0.7 * i + self.phase), 0, 1)
        if i % 3 == 0:
            frame[self.bright] = 1.0
        self._made.append(weakref.ref(frame))
        return frame


def shift(tx: float, ty: float) -> np.ndarray:
    """The homography of a translation: content moves by (tx, ty) pixels."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


#: Camera poses that move the content past every edge, by whole and fractional pixels, two of
#: them so far right that the first 4 columns of a 32-column image see no image.
POSES_LEAVING_THE_IMAGE = np.stack([shift(4.5, -2.25), shift(6.0, 3.0), shift(4.25, 0.5)])


def seam_image(case: str, tile: int, h: int = 40, w: int = 48) -> np.ndarray:
    """A grey image with saturated pixels where tiles of ``tile`` meet.

    At the first corner (``case = "corner"``) or along every seam (``"seams"``).
    """
    image = np.full((h, w, 3), 0.35)
    image[..., 1] = 0.5
    if case == "corner":
        image[tile, tile] = 1.0  # the first pixel of the second row and column of tiles
    else:
        for t in range(tile, h, tile):
            image[t - 1:t + 1, ::3] = 1.0
        for t in range(tile, w, tile):
            image[::3, t - 1:t + 1] = 1.0
    return image


# -- noise -------------------------------------------------------------------------------------

#: Poisson rates across the samplers' branches: 0, tiny, inversion (< 10), both sides of the
#: switch to PTRS at 10, and large rates.
RATES = [0.0, 1e-12, 1.0, 9.99, 10.01, 1e4, 1e7]


# -- colour ------------------------------------------------------------------------------------

#: Linear colours outside the sRGB gamut (negative components): the preset cameras' Lin2Cam
#: matrices have positive entries only, so in-gamut colours never give negative camera values.
OUT_OF_GAMUT = np.array([[1.0, -0.15, -0.1], [-0.12, 0.9, -0.05], [-0.05, -0.1, 0.95],
                         [0.6, -0.2, 0.7], [-0.1, 0.5, 0.0], [0.3, 0.3, -0.25]])
#: A camera file's Cam2Lin that desaturates, so its Lin2Cam has negative entries: saturated
#: in-gamut colours then give negative camera values.
DESATURATING = [[0.7, 0.2, 0.1], [0.15, 0.7, 0.15], [0.1, 0.2, 0.7]]
#: Saturated in-gamut colours for :data:`DESATURATING`.
PRIMARIES = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.8],
                      [0.9, 0.0, 0.9], [0.05, 0.9, 0.0]])
#: A colour matrix with condition number 1e7: camera files holding it are refused.
NEAR_SINGULAR = np.diag([1.0, 1.0, 1e-7]).tolist()


# -- index arithmetic at large coordinates -----------------------------------------------------

#: Sides of a full image of 32,774 x 32,774 pixels (never allocated): y * full_w * 3 exceeds
#: 2^31 in its last rows, and its global coordinates feed the Bayer phase, the random counters
#: and reflect-101. Kernels index their buffers relative to a view; cases run the passes on
#: its bottom-right corner and compare with the reference on just those pixels.
BIG = 2**15 + 6


def big_pattern(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The sRGB value of the big image at global (y, x): smooth, with saturated dots."""
    v = 0.5 + 0.45 * np.sin(0.37 * x + 0.11 * y)
    image = np.stack([v, 0.8 * v, 1 - 0.6 * v], axis=-1)
    image[(7 * x + 13 * y) % 17 == 0] = 1.0
    return image


class BigFrame:
    """A full-size frame too large to hold, made for the slices the backends ask for."""

    dtype = np.dtype(np.float64)  # values in [0, 1], as gpu_blur.image_arrays.check_image gives

    def __init__(self, h: int, w: int):
        self.shape = (h, w, 3)

    def __getitem__(self, key):
        rows, cols = key
        y = np.arange(*rows.indices(self.shape[0]))[:, None]
        x = np.arange(*cols.indices(self.shape[1]))[None, :]
        return big_pattern(y, x)


def tall_thin_linear(height: int) -> np.ndarray:
    """A height x 2 x 3 float32 linear image: a 997-row pattern repeated (no float64 copy)."""
    period = (np.arange(997 * 6, dtype=np.float32).reshape(997, 2, 3) % 251) / 251
    return np.resize(period, (height, 2, 3))


# -- the checks ----------------------------------------------------------------------------------

# Each topic module registers its checks in gpu_blur.conformance.checks.CHECKS as it is
# imported: this order is the order ``gpu-blur validate`` runs and lists them. They import the
# cases above, so they come last.
# isort: off
from gpu_blur.conformance import transfer_checks  # noqa: E402, F401
from gpu_blur.conformance import accumulate_checks  # noqa: E402, F401
from gpu_blur.conformance import raw_checks  # noqa: E402, F401
from gpu_blur.conformance import random_checks  # noqa: E402, F401
from gpu_blur.conformance import pipeline_checks  # noqa: E402, F401
# isort: on
