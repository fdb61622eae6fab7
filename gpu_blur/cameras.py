"""Cameras as data: colour matrices, white-balance gain distributions and noise levels.

Presets (values and sources in ``gpu_blur/data/rsblur.json``):

* ``a7r3``: Sony A7R3, the RealBlur camera. XYZ -> camera matrix from LibRaw as normalised by
  the RSBlur authors; WB red ~ U(1.9, 2.4), blue ~ U(1.5, 1.9) (their PyTorch pipeline); noise
  K = 8.8915e-5, sigma_r = 2.9430e-5 (their RealBlur estimates).
* ``a7r3-wb-list``: the same camera with (red, blue) gains drawn from the RealBlur training
  list (6 distinct pairs, weighted by their row counts), as the authors' TF pipeline does.
* ``rsblur-0001`` ... ``rsblur-0019``: one per RSBlur capture session: the session's XYZ-space
  colour correction matrix (ccm cell 1) under D65/D50 adaptation and its fixed WB gains; noise
  K = 1e-4, sigma_r = 9.1504e-4 (RSBlur estimates).
* ``srgb``: identity colour (camera RGB is linear sRGB), unit gains, RSBlur noise levels.

A custom camera is a TOML or JSON file; see :func:`load_camera` for its keys. Only a camera
file carries a fitted response (``[response]``, from ``gpu-blur calibrate``), which
``output.crf = "camera"`` re-tones with; presets have none.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from pathlib import Path

import numpy as np

from gpu_blur import limits
from gpu_blur.constants import rsblur_data
from gpu_blur.files import read_settings
from gpu_blur.reference.color import camera_to_linear_matrix, checked_inverse
from gpu_blur.scene import FIELDS, Scene

__all__ = ["CAMERA_FILE_KEYS", "Camera", "FLOAT32_RESPONSE_MAX_ABS_SUM", "WhiteBalance",
           "check_float32_response", "get_camera", "load_camera", "preset_names",
           "read_camera_spec", "response_polynomial", "scene_camera"]


@dataclasses.dataclass(frozen=True)
class WhiteBalance:
    """How a sample's white-balance gains are drawn (green is always 1).

    Exactly one form is used: ``pairs`` (a weighted list of (red, blue) gains), else
    ``red_range`` / ``blue_range`` (independent uniforms; equal bounds fix a gain).
    """

    red_range: tuple[float, float] = (1.0, 1.0)
    blue_range: tuple[float, float] = (1.0, 1.0)
    pairs: tuple[tuple[float, float, float], ...] = ()

    def draw(self, u_red: float, u_blue: float) -> tuple[float, float]:
        """Gains from two uniforms in (0, 1): ``u_red`` picks the pair when ``pairs`` is set."""
        if self.pairs:
            weights = np.array([w for _, _, w in self.pairs], dtype=np.float64)
            edges = np.cumsum(weights) / weights.sum()
            i = min(int(np.searchsorted(edges, u_red, side="right")), len(self.pairs) - 1)
            return float(self.pairs[i][0]), float(self.pairs[i][1])
        (r0, r1), (b0, b1) = self.red_range, self.blue_range
        return r0 + (r1 - r0) * u_red, b0 + (b1 - b0) * u_blue


@dataclasses.dataclass(frozen=True)
class Camera:
    """A camera the pipeline simulates.

    Attributes:
        name: preset name or file name.
        source: where the numbers come from.
        camera_to_linear: (3, 3) float64, camera RGB -> linear sRGB (the ISP's Cam2Lin).
        linear_to_camera: (3, 3) float64, its float64 inverse (Lin2Cam, supplementary Eq. 7/8).
        white_balance: the per-sample gain distribution.
        shot_noise_k: Poisson gain K in units of the [0, 1] RAW signal (RSBlur's beta1).
        read_noise_std: read-noise standard deviation, same units (RSBlur's beta2, a std).
        response: (K + 1,) float64, read-only: the fitted camera response c_0 ... c_K in
            ascending powers (supplementary Eq. 6, ``[response] polynomial`` of a camera file
            that ``gpu-blur calibrate`` wrote), or None (presets, files without one).
    """

    name: str
    source: str
    camera_to_linear: np.ndarray
    linear_to_camera: np.ndarray
    white_balance: WhiteBalance
    shot_noise_k: float
    read_noise_std: float
    response: np.ndarray | None = None

    def fitted_response(self) -> np.ndarray:
        """:attr:`response`, which ``output.crf = "camera"`` re-tones with.

        Raises:
            ValueError: naming the camera and the fix, when it has no fitted response.
        """
        if self.response is None:
            others = ", ".join(c for c in FIELDS["output"]["crf"].choices if c != "camera")
            raise ValueError(
                f"camera {self.name!r} has no fitted response for output.crf = 'camera': run "
                "gpu-blur calibrate with --crf-linear and --crf-rendered (it writes the "
                "response into the camera file's [response] table) and name that file in "
                f"camera.name, or pick another output.crf ({others})")
        return self.response


#: Largest sum of |c_k| of a fitted response that float32 kernels may evaluate. Horner's
#: rounding error in float32 grows about as 2^-24 sum |c_k| (measured 0.3 to 0.45 of it on
#: OpenCL and Warp CPU: the A7R3 polynomial, sum 1,178, within 2.4e-5; an order-7 sRGB fit,
#: sum 764, 1.5e-5; order 9, sum 13,628, 3.6e-4; order 12, sum 1.25e6, 0.043), and the
#: kernels are checked to 3e-5 (TOLERANCES row finish_crf_polynomial): above this sum the
#: float32 result would leave that row.
FLOAT32_RESPONSE_MAX_ABS_SUM = 1500.0


def check_float32_response(camera: Camera) -> None:
    """Refuse a fitted response too large for float32 kernels (see the constant above).

    Raises:
        ValueError: naming the camera, the sum, the expected error and the two fixes.
    """
    total = float(np.abs(camera.fitted_response()).sum())
    if total > FLOAT32_RESPONSE_MAX_ABS_SUM:
        raise ValueError(
            f"camera {camera.name!r}: its fitted response's coefficients sum to {total:.4g} in "
            f"magnitude (at most {FLOAT32_RESPONSE_MAX_ABS_SUM:g} in float32): float32 kernels "
            f"would evaluate it with errors near {0.45 * total * 2**-24:.2g}; set "
            "output.precision = 'float64', or refit with a lower --crf-order (7, the default)")


def _camera(name, source, cam_to_lin, wb, shot, read, response=None) -> Camera:
    """A checked :class:`Camera` (noise levels and matrix entries within :mod:`gpu_blur.limits`).

    Raises:
        ValueError: naming the camera, the value and what is allowed.
    """
    cam_to_lin = np.asarray(cam_to_lin, dtype=np.float64)
    lin_to_cam = checked_inverse(cam_to_lin, f"camera {name!r} camera_to_linear")
    for what, m, limit in (("Cam2Lin", cam_to_lin, limits.CAM2LIN_LARGEST),
                           ("Lin2Cam", lin_to_cam, limits.LIN2CAM_LARGEST)):
        m.setflags(write=False)
        # the largest |m @ x| for x in [0, 1]^3
        largest = float(max(np.clip(m, 0, None).sum(axis=1).max(),
                            np.clip(-m, 0, None).sum(axis=1).max()))
        problem = limit.problem(largest)
        if problem:
            raise ValueError(f"camera {name!r}: its {what} maps a [0, 1] colour to "
                             f"{largest:.4g}; allowed: {problem}")
    for key, value, limit in (("noise.shot_noise_k", shot, limits.SHOT_NOISE_K),
                              ("noise.read_noise_std", read, limits.READ_NOISE_STD)):
        problem = limit.problem(value)
        if problem:
            raise ValueError(f"camera {name!r}: {key} = {value!r} is invalid; allowed: {problem}")
    return Camera(name, source, cam_to_lin, lin_to_cam, wb, float(shot), float(read), response)


def _a7r3(name: str, wb: WhiteBalance, wb_source: str) -> Camera:
    d = rsblur_data()["a7r3"]
    return _camera(
        name,
        f"colour: {d['xyz_to_camera_source']}; WB: {wb_source}; noise: {d['noise_source']}",
        camera_to_linear_matrix(xyz_to_cam=d["xyz_to_camera"]),
        wb,
        d["shot_noise_k"],
        d["read_noise_std"],
    )


def _rsblur_session(session: str) -> Camera:
    d = rsblur_data()["rsblur"]
    s = d["sessions"][session]
    red, _, blue = s["wb_rgb"]
    # The session CCM C is in row convention (ref_row = cam_row @ C): T = C.T in column form.
    cam_to_lin = camera_to_linear_matrix(ccm=np.array(s["ccm_row"]).T, adapt_d50=True)
    return _camera(
        f"rsblur-{session}",
        f"colour and WB: {d['session_source']}; noise: {d['noise_source']}",
        cam_to_lin,
        WhiteBalance((red, red), (blue, blue)),
        d["shot_noise_k"],
        d["read_noise_std"],
    )


def preset_names() -> list[str]:
    """Names of the built-in cameras."""
    sessions = sorted(rsblur_data()["rsblur"]["sessions"])
    return ["a7r3", "a7r3-wb-list", *[f"rsblur-{s}" for s in sessions], "srgb"]


def get_camera(name_or_path: str | Path, base_dir: Path | None = None) -> Camera:
    """A preset by name, or a camera file (TOML or JSON) by path.

    Args:
        name_or_path: a name from :func:`preset_names` or a path ending in .toml or .json.
        base_dir: folder that relative paths are resolved against (the scene's folder).
    """
    name = str(name_or_path)
    if name in preset_names():
        return _preset(name)
    path = Path(name)
    if path.suffix.lower() in (".toml", ".json"):
        if base_dir is not None and not path.is_absolute():
            path = base_dir / path
        return load_camera(path)
    raise ValueError(
        f"unknown camera {name!r}: use one of {', '.join(preset_names())} "
        "or the path of a .toml/.json camera file"
    )


def scene_camera(scene: Scene, backend: str = "numpy") -> Camera:
    """The scene's camera (a preset or a camera file next to the scene).

    Args:
        scene: the scene.
        backend: the backend's name (``numpy``, ``opencl``, ``warp``): float32 kernels refuse a
            fitted response they cannot evaluate within tolerance
            (:func:`check_float32_response`).

    Raises:
        ValueError: naming the scene's ``camera.name`` and the cameras there are; or, for
            ``output.crf = "camera"``, naming the camera when it has no fitted response or
            one too large for float32 kernels.
    """
    where = f"scene file {scene.path}" if scene.path else "scene"
    try:
        camera = get_camera(scene.camera.name, scene.base_dir)
    except ValueError as e:
        raise ValueError(f"{where}: camera.name = {scene.camera.name!r}: {e}") from None
    if scene.output.crf == "camera":
        try:
            camera.fitted_response()
            if backend != "numpy" and scene.output.precision == "float32":
                check_float32_response(camera)
        except ValueError as e:
            raise ValueError(f"{where}: camera.name = {scene.camera.name!r}: {e}") from None
    return camera


@functools.cache
def _preset(name: str) -> Camera:
    """A built-in camera, made once (a Camera is frozen, its matrices read-only)."""
    data = rsblur_data()
    if name == "a7r3":
        return _a7r3(name, WhiteBalance((1.9, 2.4), (1.5, 1.9)),
                     "RSBlur PyTorch pipeline, dataset_RealisticDeblur.py")
    if name == "a7r3-wb-list":
        pairs = tuple((r, b, n) for r, b, n in data["a7r3"]["realblur_wb_pairs"])
        return _a7r3(name, WhiteBalance(pairs=pairs), data["a7r3"]["realblur_wb_source"])
    if name.startswith("rsblur-"):
        return _rsblur_session(name[7:])
    return _camera("srgb", "identity colour; RSBlur noise levels", np.eye(3), WhiteBalance(),
                   data["rsblur"]["shot_noise_k"], data["rsblur"]["read_noise_std"])


#: The keys a camera file may hold, per table ("" is the top level); :func:`load_camera`
#: refuses any other, as a scene file does. ``[calibration]`` is ``gpu-blur calibrate``'s
#: record of the fit, not read here: any keys (None).
CAMERA_FILE_KEYS: dict[str, tuple[str, ...] | None] = {
    "": ("name", "source", "color", "white_balance", "noise", "response", "calibration"),
    "color": ("xyz_to_camera", "ccm_xyz", "adapt_d50", "camera_to_linear"),
    "white_balance": ("red", "blue", "pairs"),
    "noise": ("shot_noise_k", "read_noise_std"),
    "response": ("polynomial", "inverse_linear", "source", "residual_rms", "condition_number"),
    "calibration": None,
}


def load_camera(path: str | Path) -> Camera:
    """Load a camera file.

    Keys (TOML shown; JSON has the same structure)::

        name = "my-camera"              # optional, defaults to the file name
        source = "where the numbers come from"
        [color]                         # exactly one of the three matrices
        xyz_to_camera = [[...], [...], [...]]   # camera matrix (Eq. 8), column convention
        ccm_xyz = [[...], [...], [...]]         # XYZ-space correction T (Eq. 3), column conv.
        adapt_d50 = false                       # with ccm_xyz: wrap T in D65 <-> D50
        camera_to_linear = [[...], [...], [...]]  # the composed Cam2Lin itself
        [white_balance]                 # either ranges or pairs
        red = [1.9, 2.4]                        # a gain or a range [low, high]
        blue = [1.5, 1.9]
        pairs = [[2.66, 1.46, 1380], ...]       # (red, blue, weight)
        [noise]
        shot_noise_k = 8.8915e-5
        read_noise_std = 2.9430e-5
        [response]                      # optional: a fitted camera response (Eq. 6)
        polynomial = [c_0, c_1, ..., c_K]       # ascending powers, >= 2 finite numbers

    Numbers must be finite and within :mod:`gpu_blur.limits` (gains ``WB_GAIN``, weights
    ``WB_WEIGHT``, noise ``SHOT_NOISE_K`` and ``READ_NOISE_STD``, the same as scene keys and
    overrides; Cam2Lin and its inverse ``CAM2LIN_LARGEST`` and ``LIN2CAM_LARGEST``); keys
    other than those in :data:`CAMERA_FILE_KEYS` are refused.

    ``gpu-blur calibrate`` writes ``[response]`` when given ``--crf-linear`` and
    ``--crf-rendered``; a scene with ``output.crf = "camera"`` then re-tones its output and
    sharp reference with that polynomial (:attr:`Camera.response`). The table's other keys
    (``inverse_linear``, residuals) and ``[calibration]`` (the chart fit) are not read here
    (see :mod:`gpu_blur.analysis.calibrate`).

    Raises:
        ValueError: naming the file, the key, the value and what is allowed.
    """
    path = Path(path)
    spec = read_camera_spec(path)

    def fail(key, value, allowed):
        raise ValueError(f"camera file {path}: {key} = {value!r} is invalid; expected {allowed}")

    def number(key, value, limit):
        problem = limit.problem(value)
        if problem:
            raise ValueError(f"camera file {path}: {key} = {value!r} is invalid; allowed: "
                             f"{problem}")
        return float(value)

    _check_camera_keys(spec, path)
    for key in ("name", "source"):
        if key in spec and not isinstance(spec[key], str):
            fail(key, spec[key], "a string")
    color = spec.get("color", {})
    given = [k for k in ("xyz_to_camera", "ccm_xyz", "camera_to_linear") if k in color]
    if len(given) != 1:
        fail("[color]", sorted(color), "exactly one of xyz_to_camera, ccm_xyz, camera_to_linear")
    key = given[0]
    rows = color[key]
    if not (isinstance(rows, list) and len(rows) == 3 and all(
            isinstance(r, list) and len(r) == 3 and all(_is_finite_number(v) for v in r)
            for r in rows)):
        fail(f"color.{key}", rows, "a 3 x 3 list of numbers, each finite")
    adapt = color.get("adapt_d50", False)
    if not isinstance(adapt, bool):
        fail("color.adapt_d50", adapt, "true or false")
    matrix = np.array(rows, dtype=np.float64)
    try:
        if key == "xyz_to_camera":
            cam_to_lin = camera_to_linear_matrix(xyz_to_cam=matrix)
        elif key == "ccm_xyz":
            cam_to_lin = camera_to_linear_matrix(ccm=matrix, adapt_d50=adapt)
        else:
            cam_to_lin = matrix
    except ValueError as e:
        raise ValueError(f"camera file {path}: color.{key}: {e}") from None

    wb_spec = spec.get("white_balance", {})
    if "pairs" in wb_spec:
        pairs = wb_spec["pairs"]
        if "red" in wb_spec or "blue" in wb_spec:
            fail("[white_balance]", sorted(wb_spec), "either pairs, or red and blue")
        if not (isinstance(pairs, list) and pairs and all(
                isinstance(p, list) and len(p) == 3 for p in pairs)):
            fail("white_balance.pairs", pairs, "a list of [red_gain, blue_gain, weight]")
        wb = WhiteBalance(pairs=tuple(
            (number(f"white_balance.pairs[{i}][0] (red gain)", p[0], limits.WB_GAIN),
             number(f"white_balance.pairs[{i}][1] (blue gain)", p[1], limits.WB_GAIN),
             number(f"white_balance.pairs[{i}][2] (weight)", p[2], limits.WB_WEIGHT))
            for i, p in enumerate(pairs)))
    else:
        ranges = []
        for channel in ("red", "blue"):
            r = wb_spec.get(channel, [1.0, 1.0])
            r = r if isinstance(r, list) else [r, r]
            if len(r) != 2:
                fail(f"white_balance.{channel}", r, "a gain or a range [low, high]")
            low, high = (number(f"white_balance.{channel}", v, limits.WB_GAIN) for v in r)
            if low > high:
                fail(f"white_balance.{channel}", r, "a range [low, high] with low <= high")
            ranges.append((low, high))
        wb = WhiteBalance(*ranges)

    response = response_polynomial(spec, path) if "response" in spec else None
    noise = spec.get("noise", {})
    shot = number("noise.shot_noise_k", noise.get("shot_noise_k", 1e-4), limits.SHOT_NOISE_K)
    read = number("noise.read_noise_std", noise.get("read_noise_std", 9.1504e-4),
                  limits.READ_NOISE_STD)
    try:
        return _camera(spec.get("name", path.stem), spec.get("source", str(path.name)),
                       cam_to_lin, wb, shot, read, response)
    except ValueError as e:
        raise ValueError(f"camera file {path}: color.{key}: {e}") from None


def _is_finite_number(value) -> bool:
    """A real number (not a bool) that float64 holds as a finite value."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond float64 (TOML and JSON allow any)
        return False


def _check_camera_keys(spec: dict, path: Path) -> None:
    """Refuse keys a camera file does not have, and tables that are not tables.

    Raises:
        ValueError: naming the file and the key (:data:`CAMERA_FILE_KEYS` lists the keys).
    """
    for table, keys in CAMERA_FILE_KEYS.items():
        if table and table not in spec:
            continue
        given = spec[table] if table else spec
        if not isinstance(given, dict):
            raise ValueError(f"camera file {path}: [{table}] = {given!r} is invalid; expected a "
                             f"table of keys ({', '.join(keys or ())})")
        unknown = sorted(set(given) - set(keys)) if keys is not None else []
        if unknown:
            where = f"{table}.{unknown[0]}" if table else unknown[0]
            raise ValueError(f"camera file {path}: unknown key {where}; "
                             f"{f'[{table}]' if table else 'top-level'} keys are "
                             f"{', '.join(keys)}")


def read_camera_spec(path: Path) -> dict:
    """A camera file's tables, parsed as TOML, or JSON for a name ending in .json.

    Raises:
        ValueError: naming the file when it cannot be read (also: no regular file, not
            UTF-8), is not valid TOML/JSON, or is not a table of keys.
    """
    spec = read_settings(path, f"camera file {path}")
    if not isinstance(spec, dict):
        raise ValueError(f"camera file {path}: expected a table of keys ([color], [noise], ...), "
                         f"got {type(spec).__name__}")
    return spec


def response_polynomial(spec: dict, path: Path) -> np.ndarray:
    """The ``[response] polynomial`` of a parsed camera file, checked.

    Args:
        spec: the file's tables (:func:`read_camera_spec`).
        path: the file, for messages.

    Returns:
        (K + 1,) read-only float64 coefficients c_0 ... c_K in ascending powers.

    Raises:
        ValueError: naming the file, the key and the value when the table or the polynomial
            is missing or not >= 2 finite numbers, with the fix.
    """
    fix = ("rerun gpu-blur calibrate with --crf-linear and --crf-rendered, or remove the "
           "[response] table")
    response = spec.get("response")
    if not isinstance(response, dict):
        raise ValueError(f"camera file {path}: [response] = {response!r} is invalid; expected "
                         f"a table with polynomial = [c_0, ..., c_K]: {fix}")
    value = response.get("polynomial")
    c = None
    if isinstance(value, list) and len(value) >= 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        try:
            c = np.array(value, dtype=np.float64)
        except OverflowError:  # an integer beyond float64
            c = None
    if c is None or not np.all(np.isfinite(c)):
        raise ValueError(
            f"camera file {path}: response.polynomial = {value!r} is invalid; expected a list "
            f"of >= 2 finite numbers c_0 ... c_K (ascending powers, supplementary Eq. 6): {fix}")
    c.setflags(write=False)
    return c
