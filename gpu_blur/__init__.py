"""gpu_blur: realistic motion-blur synthesis (RSBlur, Rim et al. ECCV 2022) on CPUs and GPUs.

Start with :func:`synthesize` (one sample), :class:`Synthesizer` (batches: numpy, torch, CuPy
or Warp arrays in and out), :func:`generate_set` (a whole data set, as ``gpu-blur generate``),
:func:`load_scene` (settings) and :func:`plan` (which stages a scene runs); the float64
reference of every stage is :mod:`gpu_blur.reference`.

One sample, module by module:

    scene.py        the scene: validated settings (limits.py: every number's range)
    planning.py     scene -> the ordered stages it calls for, each kept or skipped
    params.py       the sample's random draws (rng: reference/rng.py), or given values
    synthesis/      Synthesizer (synthesize(): a batch of one): the three passes on a
                    backend, resident on its device or from the host, where scheduler.py runs
                    them in tiles (tiling.py) within a memory budget, with spot checks;
                    arrays.py: the array types batches come in; torch.py: RealisticBlur, the
                    batch API as a training transform
    backends/       numpy (reference/), OpenCL (kernels/opencl/), Warp (warp_kernels/)
    discovery.py    inputs: sequences, photos and already-blurred images, as samples
                    (blurred_inputs.py, input_folders.py)
    dataset.py      outputs: blurred and sharp images, parameters, the manifest
                    (generation.py: generate_set, a whole set; generate.py and
                    distributed.py make its samples; png_codecs.py writes and reads PNG
                    files on the host, png_device.py deflates them on a Warp GPU)

Apart from synthesis: :mod:`gpu_blur.analysis` (calibration, alignment, metrics, the
benchmark), which measures and never synthesizes. Test hooks: :mod:`gpu_blur.testhooks`;
the tolerance table: :mod:`gpu_blur.tolerances` (the tests' helpers: :mod:`gpu_blur.testing`).
"""

from gpu_blur.generation import SetReport, generate_set
from gpu_blur.planning import Plan, Stage, plan
from gpu_blur.scene import Scene, SceneError, load_scene
from gpu_blur.synthesis import Batch, Synthesis, Synthesizer, synthesize
from gpu_blur.version import __version__

__all__ = ["Batch", "Plan", "Scene", "SceneError", "SetReport", "Stage", "Synthesis",
           "Synthesizer", "generate_set", "load_scene", "plan", "synthesize", "__version__"]
