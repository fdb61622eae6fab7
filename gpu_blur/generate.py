"""Making the samples of a set: one job description, and executors that run it.

The driver (``gpu-blur generate``) owns the output folder and the manifest; executors only
make samples and hand them back as ``(spec, result, error)``, in any order. A sample's output
depends only on (seed, sample index, scene), so any executor, worker or device gives the same
files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator

import cv2

from gpu_blur.dataset import SampleSpec
from gpu_blur.imageio import opencv_reason
from gpu_blur.pipeline import Synthesis, synthesize
from gpu_blur.scene import Scene
from gpu_blur.scheduler import Schedule


@dataclasses.dataclass(frozen=True)
class Job:
    """Everything a worker needs to make any sample of a set (picklable)."""

    scene: Scene
    seed: int
    backend: str
    schedule: Schedule | None = None  # tiles, memory budget, spot checks


def make_sample(job: Job, spec: SampleSpec) -> tuple[SampleSpec, Synthesis | None, str | None]:
    """One sample: ``(spec, result, None)``, or ``(spec, None, reason)`` for bad input.

    What fails only this sample (the reason goes to the manifest and the run goes on) is what
    this sample's inputs and size cause: ValueError (a check refused an input or a value),
    OSError (a file could not be read), cv2.error (OpenCV refused the sample's data, e.g. its
    size) and MemoryError (the sample needs more host memory than there is). Anything else
    is a fault of gpu_blur or of the device and would fail every sample alike, so it stops
    the run with its traceback (TypeError, AttributeError, a backend's RuntimeError), as do
    KeyboardInterrupt and SystemExit.
    """
    try:
        if spec.problem:
            raise ValueError(spec.problem)
        result = synthesize(list(spec.inputs), job.scene, seed=job.seed,
                            sample_index=spec.index, backend=job.backend, tile=job.schedule)
    except (ValueError, OSError) as e:
        return spec, None, str(e)
    except cv2.error as e:
        return spec, None, f"OpenCV refused this sample's data: {opencv_reason(e)}"
    except MemoryError as e:
        detail = str(e) or "no detail"
        return spec, None, (f"out of memory ({detail}): this sample needs more host memory "
                            "than there is; make it smaller (frames, blur.steps, "
                            "blur.interpolation) or free memory")
    return spec, result, None


def run_serial(job: Job, specs: Iterable[SampleSpec]) -> Iterator[tuple]:
    """Make the samples one after another in this process."""
    for spec in specs:
        yield make_sample(job, spec)
