"""gpu_blur: realistic motion-blur synthesis (RSBlur, Rim et al. ECCV 2022) on CPUs and GPUs.

Start with :func:`synthesize` (one sample), :func:`load_scene` (settings) and :func:`plan`
(which stages a scene runs); the float64 reference of every stage is :mod:`gpu_blur.reference`.
"""

__version__ = "0.1.0"

from gpu_blur.pipeline import Synthesis, synthesize  # noqa: E402
from gpu_blur.plan import Plan, Stage, plan  # noqa: E402
from gpu_blur.scene import Scene, SceneError, load_scene  # noqa: E402

__all__ = ["Plan", "Scene", "SceneError", "Stage", "Synthesis", "load_scene", "plan",
           "synthesize", "__version__"]
