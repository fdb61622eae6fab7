"""Making the samples of a set: one job description, and executors that run it.

The driver (``gpu-blur generate``) owns the output folder and the manifest; executors only
make samples and hand them back as ``(spec, result, error)``, in any order. A sample's output
depends only on (seed, sample index, scene), so any executor, worker or device gives the same
files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator

from gpu_blur.dataset import SampleSpec
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
    """One sample: ``(spec, result, None)``, or ``(spec, None, reason)`` for bad input."""
    try:
        if spec.problem:
            raise ValueError(spec.problem)
        result = synthesize(list(spec.inputs), job.scene, seed=job.seed,
                            sample_index=spec.index, backend=job.backend, tile=job.schedule)
    except (ValueError, OSError) as e:  # this sample's input: reported, the run goes on
        return spec, None, str(e)
    return spec, result, None


def run_serial(job: Job, specs: Iterable[SampleSpec]) -> Iterator[tuple]:
    """Make the samples one after another in this process."""
    for spec in specs:
        yield make_sample(job, spec)
