"""Each sample's plan and drawn values, the same on the resident and the host path."""

from __future__ import annotations

from collections.abc import Mapping

from gpu_blur.backends.flows import with_factors
from gpu_blur.cameras import Camera
from gpu_blur.params import draw_params
from gpu_blur.planning import Plan, StageName, plan
from gpu_blur.reference.flow import RegionFactors
from gpu_blur.scene import Scene
from gpu_blur.synthesis.inputs import Inputs

__all__ = ["Draws"]


class Draws:
    """A scene's plans (made once per clip test, size and interpolation) and samples' draws.

    Args:
        scene: the scene.
        camera: its camera (:func:`gpu_blur.cameras.scene_camera`).
        seed: dataset seed.
        overrides: drawn parameters fixed for every sample (already checked).
    """

    def __init__(self, scene: Scene, camera: Camera, seed: int, overrides: Mapping | None):
        self.scene, self.camera, self.seed, self.overrides = scene, camera, seed, overrides
        self._plans: dict = {}

    def plan(self, saturated: bool, h: int, w: int, factors) -> Plan:
        """The plan of a sample of this size, clip test and interpolation (made once)."""
        key = (saturated, h, w, factors)
        if key not in self._plans:  # a plan depends on the scene, the clip test and the size
            self._plans[key] = plan(self.scene, saturated=saturated, size=(h, w),
                                    interpolation_factors=factors)
        return self._plans[key]

    def drawn(self, item: Inputs, sample_index: int, h: int, w: int,
              measured: RegionFactors | None, uniforms: dict | None = None, *,
              saturated: bool | None = None, sequence_index: int | None = None):
        """A sample's plan and drawn values: (plan, params).

        ``measured``: the gaps' factors under interpolation auto
        (:func:`~gpu_blur.backends.flows.scene_factors`).
        ``uniforms``: the sample's row of :func:`gpu_blur.params.batch_uniforms`, else drawn.
        ``saturated``: the clip test's answer to plan by, for the input's own.
        ``sequence_index``: its frame sequence's, which keys the draws under
        ``blur.draws = "per-sequence"`` (:func:`gpu_blur.params.draw_keys`).
        """
        scene = self.scene
        frames = item.frames
        sample_plan = self.plan(item.saturated if saturated is None else saturated, h, w,
                                measured.gaps if measured else None)
        # Every draw has a fixed index (gpu_blur.params), so a stage the sample skips (auto
        # saturation) never shifts another draw.
        overrides = self.overrides
        if scene.saturation.mode == "auto" and not sample_plan.kept(StageName.SATURATE):
            # nothing to saturate in this sample: a fixed alpha has nothing to act on
            overrides = {k: v for k, v in (overrides or {}).items() if k != "alpha"}
        params = draw_params(scene, sample_plan, self.camera, seed=self.seed,
                             sample_index=sample_index, image_shape=(h, w), overrides=overrides,
                             uniforms=uniforms, sequence_index=sequence_index)
        if measured is not None:  # the plan's factors, recorded in the manifest
            params = with_factors(sample_plan, params, frames, measured)
        return sample_plan, params
