"""Pass configuration and kernel arguments: the plan carried into the kernels.

* :func:`pass_config`: (plan, pass) -> the settings a pass's kernels are built with
  (:class:`PassConfig`; :func:`sharp_config` for the sharp reference);
* the ``*_args`` functions: the ordered arguments of each kernel, as :class:`Arg` values that
  name their type, so each language renders them (``np.int64`` for an OpenCL ``long``, a
  Python ``int`` for Warp). Arguments marked ``extent`` are sizes only OpenCL takes (Warp reads
  them from the launch grid or the array).

What differs per sample of a batched launch (:class:`Drawn`) reaches the kernels as two small
tables (:func:`sample_tables`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from gpu_blur.backends import Drawn, cfa_bits
from gpu_blur.cameras import Camera
from gpu_blur.kernel_constants import SAMPLE_REALS, SAMPLE_WORDS
from gpu_blur.planning import Pass, Plan, StageName
from gpu_blur.reference.rng import key_from_seed
from gpu_blur.reference.transfer import a7r3_lookup_table
from gpu_blur.tiling import Region

__all__ = ["Arg", "PassConfig", "S", "average_args", "finish_args", "pass_config", "retone_curves",
           "sample_tables", "sharp_config", "source_dtype", "stage_values", "to_raw_args"]

S = StageName


@dataclasses.dataclass(frozen=True)
class PassConfig:
    """What one pass's kernels are built with (hashable: a cache key).

    Attributes:
        pass_: the pass.
        stages: the pass's kept stages, in plan order.
        fast_math: fast float transcendentals (scene ``output.fast_math``).
        poisson_normal: to_raw: Poisson counts above the plan's rate by a rounded normal.
        clip_camera: to_raw: clip after Lin2Cam.
        demosaic: finish: the demosaic method, ``""`` without a RAW round trip.
        zero_border: finish: the demosaic reads zeros beyond the image (else reflects).
        clip_demosaic: finish: clip after demosaicing.
        retone: finish: the plan's ``retone_curve`` (``"polynomial"``, ``"lookup"``, ``""``).
        bits: finish: quantization bits, 0 for none.
    """

    pass_: Pass
    stages: tuple[StageName, ...]
    fast_math: bool = False
    poisson_normal: bool = False
    clip_camera: bool = False
    demosaic: str = ""
    zero_border: bool = False
    clip_demosaic: bool = False
    retone: str = ""
    bits: int = 0

    def kept(self, stage: StageName) -> bool:
        """Whether ``stage`` is compiled in."""
        return stage in self.stages


def pass_config(plan: Plan, pass_: Pass) -> PassConfig:
    """The settings of pass ``pass_``'s kernels under ``plan``.

    The one translation of a plan into kernel builds: OpenCL renders it as ``-D`` defines,
    Warp as its kernel factories' static flags.
    """
    stages = tuple(StageName(s.name) for s in plan.stages if s.kept and s.pass_ == pass_)
    config = PassConfig(Pass(pass_), stages, plan.fast_math)
    if pass_ == Pass.TO_RAW:
        noise = plan[S.POISSON_GAUSSIAN_NOISE]
        return dataclasses.replace(
            config,
            poisson_normal=noise.kept and noise.options["sampler"] == "normal",
            clip_camera=plan.kept(S.LINEAR_TO_CAMERA)
            and plan[S.LINEAR_TO_CAMERA].options["clip"])
    if pass_ == Pass.FINISH:
        demosaic = plan[S.DEMOSAIC]
        options = demosaic.options if demosaic.kept else {}
        return dataclasses.replace(
            config, demosaic=options.get("method", ""),
            zero_border=options.get("border") == "zero", clip_demosaic=bool(options.get("clip")),
            retone=plan.retone_curve,
            bits=plan[S.QUANTIZE].options["bits"] if plan.kept(S.QUANTIZE) else 0)
    return config


def sharp_config(plan: Plan) -> PassConfig:
    """The finish pass's configuration cut to what acts on the sharp reference.

    Its tone, retone and quantize stages, the re-toning curve, the bits and fast maths: one
    build of :meth:`KernelBackend.render_sharp` serves every demosaic and noise setting.
    """
    finish = pass_config(plan, Pass.FINISH)
    stages = tuple(s for s in finish.stages if s in (S.TONE, S.RETONE, S.QUANTIZE))
    return PassConfig(Pass.FINISH, stages, finish.fast_math, retone=finish.retone,
                      bits=finish.bits)


def retone_curves(plan: Plan, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(polynomial coefficients, lookup table / 255) of the plan's re-toning, for the kernels.

    Both curves go to the kernels; the one the plan does not use is a placeholder never read.
    """
    polynomial = plan.retone_polynomial(camera)
    polynomial = np.zeros(1) if polynomial is None else polynomial
    table = a7r3_lookup_table(plan[S.RETONE].options["table_size"]) / 255.0
    return polynomial, table


class Arg(NamedTuple):
    """One scalar kernel argument with its type, rendered by each backend.

    Attributes:
        kind: ``"index"`` (OpenCL ``long``), ``"int"`` (``int``), ``"uint"`` (``uint``),
            ``"real"`` (the compute type) or ``"position"`` (float64 where the device has it).
        value: the value.
        extent: a size only OpenCL takes; Warp leaves it out.
    """

    kind: str
    value: object
    extent: bool = False


def _index(*values) -> tuple[Arg, ...]:
    return tuple(Arg("index", int(v)) for v in values)


def _random_key(seed: int) -> tuple[Arg, ...]:
    key = key_from_seed(seed)
    return Arg("uint", int(key[0])), Arg("uint", int(key[1]))


def _out_geometry(region: Region) -> tuple[Arg, ...]:
    """Where a 2-D launch writes: the region's origin, width and (OpenCL) height."""
    return (*_index(region.x0, region.y0, region.w), Arg("index", int(region.h), extent=True))


def _view_geometry(view: Region) -> tuple[Arg, ...]:
    """A source view: its origin and width, and the whole image's width and height."""
    return _index(view.x0, view.y0, view.w, view.full_w, view.full_h)


def stage_values(plan: Plan, pass_: Pass) -> tuple[Arg, ...]:
    """The pass's stages' :attr:`~gpu_blur.planning.Stage.values`, in plan order, as reals.

    They close the to_raw and finish kernels' argument lists.
    """
    stages = [s for s in plan.stages if s.pass_ == pass_ and s.values]
    for s in stages:
        if s.kept and None in s.values:
            raise ValueError(f"the {s.name} stage's numbers are not all known (the plan was "
                             "built without the sample's size): build it with "
                             "plan(scene, size=(height, width)), as synthesize does")
    return tuple(Arg("real", 0.0 if v is None else v) for s in stages for v in s.values)


def sample_tables(samples: Sequence[Drawn]) -> tuple[np.ndarray, np.ndarray]:
    """A batched launch's per-sample tables: (reals, words), one row per sample.

    reals: float64 rows of :data:`~gpu_blur.kernel_constants.SAMPLE_REALS` (a backend rounds
    them to its compute type, as it rounds a scalar argument); words: uint32 rows of
    :data:`~gpu_blur.kernel_constants.SAMPLE_WORDS`. The to_raw and finish passes of the same
    samples read the same tables.
    """
    values = np.array([[float(d.params.get(name, default)) for name, default in SAMPLE_REALS]
                       for d in samples], dtype=np.float64).reshape(len(samples),
                                                                    len(SAMPLE_REALS))
    words = np.array([(cfa_bits(d.params.get("pattern")), d.sample_index, d.slot)
                      for d in samples], dtype=np.uint32).reshape(len(samples),
                                                                  len(SAMPLE_WORDS))
    return values, words


def to_raw_args(plan: Plan, tables, origin: tuple[int, int], h: int, w: int, inputs, matrix,
                outputs, *, seed: int) -> tuple:
    """The to_raw kernel's arguments, in order.

    ``tables``: the batch's (reals, words) on the device (:func:`sample_tables`); ``inputs``
    (linear, mask) and ``outputs`` (saturated, raw): each a (buffer, stride) pair.
    """
    (linear, mask), (saturated, raw) = inputs, outputs
    return (*linear, *mask, *_index(origin[1], origin[0], w), Arg("index", h, extent=True),
            *tables, matrix, Arg("real", plan[S.POISSON_GAUSSIAN_NOISE].options["normal_above"]),
            *_random_key(seed), *saturated, *raw, *stage_values(plan, Pass.TO_RAW))


def finish_args(plan: Plan, tables, view: Region, out: Region, inputs, matrix, polynomial,
                table, result, *, seed: int) -> tuple:
    """The finish kernel's arguments, in order.

    ``inputs`` (raw, saturated) and ``result``: (buffer, stride) pairs; ``polynomial``,
    ``table``: (buffer, size).
    """
    raw, saturated = inputs
    return (*raw, *saturated, *_view_geometry(view), *_out_geometry(out), *tables, matrix,
            *_random_key(seed), polynomial[0], Arg("int", polynomial[1], extent=True),
            table[0], Arg("int", table[1], extent=True), *result,
            *stage_values(plan, Pass.FINISH))


def average_args(stack, count: int, n: int, sums, first: bool, mean_of: int, linear, sat_mask,
                 table) -> tuple:
    """The average's summing kernel's arguments, in order.

    ``count`` frames of ``n`` values each from ``stack`` join ``sums``; ``mean_of`` > 0 writes
    the means instead.
    """
    return (stack, Arg("uint", count), Arg("index", n), *sums, Arg("int", int(first)),
            Arg("uint", mean_of), linear, sat_mask, table)


def source_dtype(frame, real) -> np.dtype:
    """The dtype a frame travels to the device in: its 8/16-bit codes, else the compute type."""
    dtype = np.dtype(frame.dtype)
    return dtype if dtype in (np.dtype(np.uint8), np.dtype(np.uint16)) else np.dtype(real)
