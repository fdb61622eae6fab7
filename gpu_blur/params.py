"""Per-sample random parameters, drawn from the counter-based generator and overridable.

Every scalar comes from a fixed index of stream ``PARAMS`` keyed by (seed, sample index), so
fixing one with ``overrides`` never shifts another, and a sample's draws never depend on which
worker, tile or backend makes it. Only the parameters of kept stages are drawn and reported.
Under ``blur.draws = "per-sequence"`` the same streams are keyed by (seed, sequence index)
instead (:class:`gpu_blur.reference.rng.Keyed`), so every window of a frame sequence draws the
same values; the noise's pixels stay keyed by the sample index (the kernels' counters).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from gpu_blur import limits
from gpu_blur.cameras import Camera
from gpu_blur.kernel_files import check_kernel, kernel_weights, read_kernel
from gpu_blur.planning import Plan
from gpu_blur.reference import motion_kernel, rng, shake
from gpu_blur.reference.bayer import BayerPattern
from gpu_blur.reference.noise import draw_noise_levels
from gpu_blur.scene import PATTERNS, PER_SEQUENCE, Scene

__all__ = ["ARRAY_PARAMS", "DRAW_INDEX", "KERNEL_WALK", "OVERRIDE_LIMITS", "batch_uniforms",
           "check_overrides", "draw_keys", "draw_params", "image_streams"]

#: Index of each scalar draw in stream PARAMS (a contract: changing one changes every dataset).
DRAW_INDEX = {
    "alpha": 0,
    "pattern": 1,
    "red_gain": 2,
    "blue_gain": 3,
    "shot_noise_k": 4,
    "read_noise_std": 5,
    "gaussian_std": 6,
    "kernel_size": 7,
    "extent_px": 8,
    "jpeg_quality": 9,
}
#: Array-valued parameters (recorded beside the scalars, overridable too).
ARRAY_PARAMS = ("kernel", "homographies")
#: The range an override of each number must lie in: the same as the scene key or camera
#: value it stands for (:mod:`gpu_blur.limits`). Drawn values come from checked settings.
OVERRIDE_LIMITS = {
    "alpha": limits.ALPHA,
    "red_gain": limits.WB_GAIN,
    "blue_gain": limits.WB_GAIN,
    "shot_noise_k": limits.SHOT_NOISE_K,
    "read_noise_std": limits.READ_NOISE_STD,
    "gaussian_std": limits.GAUSSIAN_STD,
    "kernel_size": limits.KERNEL_SIZE,
    "extent_px": limits.EXTENT,
    "jpeg_quality": limits.JPEG_QUALITY,
}


def check_overrides(overrides) -> None:
    """Refuse an override of unknown name, type or range, whether or not its stage will run.

    Raises:
        TypeError: ``overrides`` is not a mapping.
        ValueError: naming the override, its value and what is allowed.
    """
    if overrides is None:
        return
    if not isinstance(overrides, Mapping):
        raise TypeError(f"overrides: a mapping of parameter names to values (e.g. "
                        f"{{'alpha': 1.0}}); got a {type(overrides).__name__}")
    known = set(DRAW_INDEX) | set(ARRAY_PARAMS)
    for name, value in overrides.items():
        if name not in known:
            raise ValueError(f"unknown override {name!r}; parameters are {sorted(known)}")
        problem = OVERRIDE_LIMITS[name].problem(value) if name in OVERRIDE_LIMITS else None
        if problem:
            raise ValueError(f"overrides[{name!r}] = {value!r} is invalid; allowed: {problem}")
        if name == "pattern" and (not isinstance(value, str) or not _is_pattern(value)):
            raise ValueError(f"overrides['pattern'] = {value!r} is not a Bayer pattern; "
                             f"allowed: {' | '.join(PATTERNS)} (any case)")
        if name == "kernel":
            check_kernel(kernel_weights(value, "overrides['kernel']"), "overrides['kernel']")
        if name == "homographies":
            h = _numbers(value)
            most = limits.STEPS.high
            if (h is None or h.ndim != 3 or h.shape[1:] != (3, 3) or not 1 <= len(h) <= most
                    or not np.isfinite(h).all()):
                raise ValueError(f"overrides['homographies'] must be a finite n x 3 x 3 array "
                                 f"(1 <= n <= {most:g}, as blur.steps) of camera poses; got "
                                 f"{_what(h)}")


def _numbers(value) -> np.ndarray | None:
    """``value`` as a float64 array when it holds integers or floats, else None."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested lists
        return None
    return array.astype(np.float64) if array.dtype.kind in "iuf" else None


def _what(array: np.ndarray | None) -> str:
    return "values that are not real numbers" if array is None else f"shape {array.shape}"


def _is_pattern(text: str) -> bool:
    try:
        BayerPattern.parse(text)
    except ValueError:
        return False
    return True


def _uniform_range(u: float, lo: float, hi: float) -> float:
    return lo + (hi - lo) * u


#: The key of a :func:`batch_uniforms` row's random-kernel walk values
#: (:func:`gpu_blur.reference.motion_kernel.kernel_walk_values` of its kernel uniforms).
KERNEL_WALK = "kernel_walk"


def image_streams(scene: Scene) -> dict:
    """The per-image random streams :func:`draw_params` reads for ``scene``: {stream: count}."""
    streams = {rng.Stream.PARAMS: len(DRAW_INDEX)}
    if scene.blur.mode == "kernel" and not scene.blur.kernel:
        streams[rng.Stream.KERNEL] = motion_kernel.KERNEL_UNIFORMS
    if scene.blur.mode == "trajectory":
        streams[rng.Stream.TRAJECTORY] = shake.SHAKE_UNIFORMS
    return streams


def draw_keys(scene: Scene, sample_indices, sequence_indices=None
              ) -> tuple[list[int], rng.Keyed]:
    """The indices the per-image draws of these samples are keyed by, and what they number.

    The samples' own (:attr:`~gpu_blur.reference.rng.Keyed.SAMPLE`), or under
    ``blur.draws = "per-sequence"`` their frame sequences' (``sequence_indices``, one per
    sample; :attr:`~gpu_blur.reference.rng.Keyed.SEQUENCE`), which then must be given.

    Raises:
        ValueError: a per-sequence scene without sequence indices, or not one per sample.
    """
    if scene.blur.draws != PER_SEQUENCE:
        return list(sample_indices), rng.Keyed.SAMPLE
    if sequence_indices is None or any(i is None for i in sequence_indices):
        raise ValueError(
            f"blur.draws = '{PER_SEQUENCE}' draws each sample's camera settings from its frame "
            "sequence: give each sample's sequence index (synthesize's sequence_index, a "
            "Synthesizer batch's sequences), as gpu-blur generate does for each window")
    if len(sequence_indices) != len(sample_indices):
        raise ValueError(f"sequences: {len(sequence_indices)} sequence indices for "
                         f"{len(sample_indices)} samples; give one per sample")
    return list(sequence_indices), rng.Keyed.SEQUENCE


def batch_uniforms(scene: Scene, *, seed: int, sample_indices,
                   sequence_indices=None) -> list[dict]:
    """Each sample's uniforms of :func:`image_streams`, drawn for the samples at once.

    Row b is what :func:`draw_params` draws for ``sample_indices[b]`` (its ``uniforms``
    argument; keyed by ``sequence_indices[b]`` under per-sequence draws, :func:`draw_keys`):
    the same values (:func:`gpu_blur.reference.rng.image_uniforms_batch`), in one Philox
    evaluation per stream instead of one per sample; random kernels' walk values
    (:data:`KERNEL_WALK`) likewise.
    """
    keys, keyed = draw_keys(scene, sample_indices, sequence_indices)
    drawn = {stream: rng.image_uniforms_batch(seed, keys, stream, count, keyed)
             for stream, count in image_streams(scene).items()}
    if rng.Stream.KERNEL in drawn:  # one fixedmath call for every kernel's walk
        drawn[KERNEL_WALK] = motion_kernel.kernel_walk_values(drawn[rng.Stream.KERNEL])
    return [{stream: u[b] for stream, u in drawn.items()} for b in range(len(keys))]


def draw_params(scene: Scene, plan: Plan, camera: Camera, *, seed: int, sample_index: int,
                image_shape: tuple[int, int], overrides: dict | None = None,
                uniforms: dict | None = None, sequence_index: int | None = None) -> dict:
    """Draw every random value the plan needs for one sample.

    Args:
        scene: the settings (ranges, levels).
        plan: the sample's plan; parameters of skipped stages are not drawn.
        camera: white-balance distribution and noise levels.
        seed: dataset seed, 0 <= seed < 2**64.
        sample_index: the sample's index, 0 <= index < 2**32.
        image_shape: (height, width) of the sample, for the camera path.
        overrides: values to use instead of drawing (same names as the result); numbers
            must lie within :data:`OVERRIDE_LIMITS`.
        uniforms: the sample's row of :func:`batch_uniforms` (drawn for a batch at once);
            None: drawn here.
        sequence_index: the index of the frame sequence the sample is a window of; under
            ``blur.draws = "per-sequence"`` the draws are keyed by it (:func:`draw_keys`),
            else it is not used.

    Returns:
        A dict of plain Python scalars and, for ``kernel`` / ``homographies``, float64 arrays.

    Raises:
        ValueError: an unknown or unused override, or one outside its range (naming it, the
            value and what is allowed); a per-sequence scene without ``sequence_index``.
    """
    check_overrides(overrides)
    overrides = dict(overrides or {})
    streams = image_streams(scene)
    given = uniforms or {}
    (key,), keyed = draw_keys(scene, [sample_index], [sequence_index])

    def stream_uniforms(stream):
        if stream in given:
            return given[stream]
        return rng.image_uniforms(seed, key, stream, streams[stream], keyed)

    u = stream_uniforms(rng.Stream.PARAMS)
    draw = {name: float(u[i]) for name, i in DRAW_INDEX.items()}
    p: dict = {}

    def put(name, value):  # an override instead of the drawn value (check_overrides: valid)
        p[name] = overrides.pop(name) if name in overrides else value

    b = scene.blur
    if plan.kept("blur") and b.mode == "kernel" and b.kernel:
        path = Path(b.kernel)
        put("kernel", read_kernel(path if path.is_absolute() or scene.base_dir is None
                                  else scene.base_dir / path))
    elif plan.kept("blur") and b.mode == "kernel":
        lo, hi = b.kernel_size
        sizes = [s for s in range(lo, hi + 1) if s % 2 == 1]
        put("kernel_size", sizes[min(int(draw["kernel_size"] * len(sizes)), len(sizes) - 1)])
        ku = stream_uniforms(rng.Stream.KERNEL)
        put("kernel", motion_kernel.random_motion_kernel(ku, int(p["kernel_size"]),
                                                         given.get(KERNEL_WALK)))
    if plan.kept("blur") and b.mode == "trajectory":
        put("extent_px", _uniform_range(draw["extent_px"], *b.extent))
        su = stream_uniforms(rng.Stream.TRAJECTORY)
        frame = (su, image_shape[0], image_shape[1])
        steps = b.steps or shake.auto_shake_steps(*frame, float(p["extent_px"]), float(b.roll))
        put("homographies", shake.camera_shake_homographies(
            *frame, steps, float(p["extent_px"]), float(b.roll)))
    if plan.kept("saturate"):
        put("alpha", _uniform_range(draw["alpha"], *scene.saturation.alpha))
    if plan.raw_round_trip:
        fixed = scene.isp.pattern
        put("pattern", fixed if fixed != "random"
            else PATTERNS[min(int(draw["pattern"] * 4), 3)])
        p["pattern"] = BayerPattern.parse(str(p["pattern"])).value
        red, blue = camera.white_balance.draw(draw["red_gain"], draw["blue_gain"])
        put("red_gain", red)
        put("blue_gain", blue)
    if plan.kept("poisson_gaussian_noise"):
        n = scene.noise
        shot = camera.shot_noise_k if n.shot_noise_k is None else n.shot_noise_k
        read = camera.read_noise_std if n.read_noise_std is None else n.read_noise_std
        k, std = draw_noise_levels(draw["shot_noise_k"], draw["read_noise_std"], shot, read,
                                   n.spread)
        put("shot_noise_k", k)
        put("read_noise_std", std)
    if plan.kept("gaussian_noise"):
        n = scene.noise
        put("gaussian_std", n.gaussian_std * (1 + n.spread * (2 * draw["gaussian_std"] - 1)))
    if plan.kept("jpeg"):
        lo, hi = scene.output.jpeg_quality
        put("jpeg_quality", lo + min(int(draw["jpeg_quality"] * (hi - lo + 1)), hi - lo))
    if overrides:
        raise ValueError(
            f"override {sorted(overrides)[0]!r} is not used by this scene's plan; used here: "
            f"{sorted(p)}")
    for name, limit in OVERRIDE_LIMITS.items():
        if name in p:  # plain Python numbers, for the manifest
            p[name] = int(p[name]) if limit.integer else float(p[name])
    for name in ARRAY_PARAMS:
        if name in p:
            p[name] = np.asarray(p[name], dtype=np.float64)
    return p
