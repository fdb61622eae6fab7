"""The kernel backend written once: the plan's passes as launches, for any kernel language.

:class:`KernelBackend` holds the host logic of the three passes (which kernels run, in what
order, on which buffers, with which arguments); :mod:`gpu_blur.backends.opencl` and
:mod:`gpu_blur.backends.warp` subclass it and keep only what differs: devices, buffers,
queues or streams, launching, and rendering a :class:`PassConfig` into ``-D`` defines or Warp
static flags.

Two functions carry the plan into the kernels:

* :func:`pass_config`: (plan, pass) -> the settings a pass's kernels are built with;
* the ``*_args`` functions: the ordered arguments of each kernel, as :class:`Arg` values that
  name their type, so each language renders them (``np.int64`` for an OpenCL ``long``, a
  Python ``int`` for Warp). Arguments marked ``extent`` are sizes only OpenCL takes (Warp reads
  them from the launch grid or the array).
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from gpu_blur.backends import (
    FRAMES_PER_LAUNCH,
    OnDevice,
    PinnedHost,
    cfa_bits,
    copy_values,
    pinned_owner,
)
from gpu_blur.backends.flows import gap_regions, interpolation_factor, with_flows
from gpu_blur.cameras import Camera
from gpu_blur.kernel_constants import (
    EXACT_COUNT_SHIFT,
    EXACT_FRAMES_MAX,
    EXACT_UNIT,
    KERNEL_WORDS,
    SAMPLE_REALS,
    SAMPLE_WORDS,
    SATURATION_LEVEL,
)
from gpu_blur.plan import Pass, Plan, StageName
from gpu_blur.reference import blur, fixedmath
from gpu_blur.reference.interpolate import (
    CONSISTENCY_ABSOLUTE_PX2,
    CONSISTENCY_RELATIVE,
    gap_weights,
)
from gpu_blur.reference.output import code_dtype
from gpu_blur.reference.rng import key_from_seed
from gpu_blur.reference.transfer import a7r3_lookup_table
from gpu_blur.testhooks import fault_planted, planted_fault
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

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
    """The pass's stages' :attr:`~gpu_blur.plan.Stage.values`, in plan order, as reals.

    They close the to_raw and finish kernels' argument lists.
    """
    stages = [s for s in plan.stages if s.pass_ == pass_ and s.values]
    for s in stages:
        if s.kept and None in s.values:
            raise ValueError(f"the {s.name} stage's numbers are not all known (the plan was "
                             "built without the sample's size): build it with "
                             "plan(scene, size=(height, width)), as synthesize does")
    return tuple(Arg("real", 0.0 if v is None else v) for s in stages for v in s.values)


class Drawn(NamedTuple):
    """One sample of a batched to_raw or finish launch.

    Attributes:
        params: its drawn values (:func:`gpu_blur.params.draw_params`).
        sample_index: its index (with the seed, its random stream).
        slot: its row in the batch's buffers.
    """

    params: dict
    sample_index: int
    slot: int


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


class Slots(NamedTuple):
    """A batch's device buffer: ``count`` slots ``stride`` values apart, one per sample.

    Made by :meth:`KernelBackend.slots`; sample b's values start at ``b * stride``
    (:meth:`KernelBackend.slot_image`).
    """

    buffer: object
    count: int
    stride: int


def _check_slots(samples: Sequence[Drawn], buffers) -> None:
    """Refuse a batched launch whose slots could not hold what its kernel reads or writes.

    ``buffers``: (name, :class:`Slots`, values a slot must hold) each. The kernels index by
    slot and stride without bounds checks, so this is what keeps them inside the buffers.
    """
    used = [d.slot for d in samples]
    top = max(used, default=-1)
    for name, slots, needed in buffers:
        if slots.stride < needed or top >= slots.count or min(used, default=0) < 0:
            raise ValueError(f"batched launch: {name} has {slots.count} slot(s) of "
                             f"{slots.stride} values; its samples need slots 0..{top} of "
                             f"{needed} values (a gpu_blur bug: please report it)")


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


def source_dtype(frame, real) -> np.dtype:
    """The dtype a frame travels to the device in: its 8/16-bit codes, else the compute type."""
    dtype = np.dtype(frame.dtype)
    return dtype if dtype in (np.dtype(np.uint8), np.dtype(np.uint16)) else np.dtype(real)


class KernelBackend:
    """The passes of a plan as kernel launches (see :mod:`gpu_blur.backends`).

    A subclass sets ``name``, ``precision``, ``device``, ``np_real`` (the compute type as a
    numpy dtype) and ``position_dtype`` (float64 where the device has it), and supplies the
    primitives below: buffers (``_upload``, ``_empty``, ``_zeros``, ``_write``, ``_fetch``),
    kernels (``_pass_kernels``, ``_launch``, ``_timed``) and ``_frame_stacks``.
    """

    name: str
    precision: str
    device: str
    device_arrays = False
    #: Whether each pass waits for its launches (its "kernels" time is then device time).
    #: False queues every launch back to back (a batch: :class:`gpu_blur.Synthesizer`, or a
    #: CUDA graph capture: bench/gpu_targets.py); timings then hold launch times only.
    sync_passes = True

    def __init__(self):
        self._constants: dict = {}  # (bytes, dtype) -> device copy of a small constant
        self._code_tables: dict = {}  # (config, source dtype) -> the 8-bit linear table
        self._sharp_tables: dict = {}  # (config, curves, source dtype) -> every code rendered
        self._derived: dict = {}  # id(plan), id(camera) -> (plan, camera, what they give)
        self._put_turn = 0  # which of the two pinned input buffers a staged put fills next
        self._last_tables = None  # (their bytes, device tables) of the last batched launch
        self._counts_host = None  # pinned host words that inspect counts come back in
        self._counts_reader = None  # weak reference: the read still to come of those words
        self._kept_codes: dict = {}  # (count, bits) -> device codes buffer (codes_buffer)

    # -- primitives a language supplies ----------------------------------------------------
    @property
    def uses_cuda(self) -> bool:
        """Whether the device is an NVIDIA GPU run through CUDA's driver."""
        raise NotImplementedError

    def wait(self) -> None:
        """Wait for every launch and copy queued so far."""
        raise NotImplementedError

    def _upload(self, values, dtype=None):
        """``values`` on the device, flat: an :class:`OnDevice` as it is, host data copied."""
        raise NotImplementedError

    def _empty(self, count: int, dtype=None):
        """An uninitialized flat device buffer of ``count`` values (compute type by default)."""
        raise NotImplementedError

    def _zeros(self, count: int, dtype=None):
        """A zeroed flat device buffer."""
        raise NotImplementedError

    def _write(self, buffer, values: np.ndarray) -> None:
        """Copy host ``values`` into the device buffer ``buffer`` (after earlier launches)."""
        raise NotImplementedError

    def _fetch(self, values: OnDevice, dtype) -> np.ndarray:
        """An output's host copy (timed as ``copies``)."""
        raise NotImplementedError

    def _fetch_queued(self, buffer, into: np.ndarray) -> Callable[[], None]:
        """Queue a copy of ``buffer``'s first ``into.size`` values into host ``into``.

        ``into``: this backend's :meth:`pinned` memory, of the buffer's dtype. The function
        returned waits for that copy alone, not for what is queued after it.
        """
        raise NotImplementedError

    def _pass_kernels(self, config: PassConfig, source=None, interpolate: bool = False):
        """The kernels built for ``config``, by name.

        ``source``: the frames' dtype (accumulate only); ``interpolate``: the
        interpolated-averaging kernels instead.
        """
        raise NotImplementedError

    def _launch(self, kernels, name: str, grid, *args):
        """Launch kernel ``name`` over ``grid`` (``n`` values, or ``(rows, columns)``)."""
        raise NotImplementedError

    def _timed(self, sync: bool = True):
        """A timer of launches as ``kernels``; ``sync`` waits for them at its end."""
        raise NotImplementedError

    def _frame_stacks(self, frames: Sequence[np.ndarray], region: Region):
        """Yield (stack, count): device stacks of up to FRAMES_PER_LAUNCH frames of ``region``.

        The caller launches the stack's sum before asking for the next one.
        """
        raise NotImplementedError

    def device_array(self, values: OnDevice):
        """A result's flat device buffer, as the backend holds it."""
        return values.data

    # -- shared helpers --------------------------------------------------------------------
    def _of_plan(self, plan: Plan, camera: Camera | None = None) -> dict:
        """What a plan (and camera) give the kernels, worked out once per plan object.

        Its passes' :func:`pass_config`, :func:`sharp_config` and, with a camera,
        :func:`retone_curves`: a batch runs the same plan object for many samples
        (``gpu_blur.Synthesizer`` caches plans), and these cost about 0.1 ms a sample.
        """
        key = (id(plan), id(camera))
        entry = self._derived.get(key)
        if entry is None or entry[0] is not plan or entry[1] is not camera:
            if len(self._derived) >= 64:
                self._derived.clear()
            derived = {p: pass_config(plan, p) for p in (Pass.ACCUMULATE, Pass.TO_RAW,
                                                         Pass.FINISH)}
            derived["sharp"] = sharp_config(plan)
            if camera is not None:
                derived["curves"] = retone_curves(plan, camera)
            entry = self._derived[key] = (plan, camera, derived)
        return entry[2]

    def _stacks_for(self, frames: Sequence[np.ndarray], region: Region, dtype):
        """How :meth:`_frame_stacks` splits ``frames`` into device stacks.

        Returns:
            (frames per stack, values per frame, each stack's frame indices, the two device
            stacks that take turns).
        """
        per = min(FRAMES_PER_LAUNCH, len(frames))
        values = region.h * region.w * 3
        groups = [range(i, min(i + per, len(frames))) for i in range(0, len(frames), per)]
        stacks = [self._empty(per * values, dtype) for _ in range(min(2, len(groups)))]
        return per, values, groups, stacks

    def _constant(self, values, dtype=None):
        """A small constant (matrix, polynomial, table) on the device, uploaded once."""
        data = np.ascontiguousarray(np.ravel(values), dtype=dtype or self.np_real)
        key = (data.tobytes(), data.dtype.str)
        if key not in self._constants:
            self._constants[key] = self._upload(data, data.dtype)
        return self._constants[key]

    def _out(self, buffer, shape, pass_: Pass, origin) -> OnDevice:
        """A pass's output, with the :data:`~gpu_blur.testhooks.TEST_FAULT` hook applied."""
        result = OnDevice(buffer, shape, self._fetch)
        if fault_planted(pass_):
            host = planted_fault(pass_, result.numpy(), origin)
            self._write(buffer, np.ascontiguousarray(host.ravel(), dtype=self.np_real))
        return result

    def _linear_out(self, linear, sat_mask, shape, region: Region):
        """The accumulate pass's (linear, mask), left on the device."""
        return (self._out(linear, shape, Pass.ACCUMULATE, region.origin),
                OnDevice(sat_mask, shape, self._fetch))

    def _code_table(self, config: PassConfig, source):
        """The linear value of every 8-bit code, from these kernels' own linearize.

        The average's sum gathers from it instead of evaluating the EOTF per value: the same
        function of the same 256 codes, so the same bits. Made once per build; a one-value
        placeholder when the frames are not 8-bit codes (the kernel does not read it).
        """
        key = (config, np.dtype(source).str)
        if key not in self._code_tables:
            count = 256 if np.dtype(source) == np.uint8 else 1
            table, indicator = self._empty(count), self._empty(count)
            if count == 256:
                codes = self._upload(np.arange(256), np.uint8)
                with self._timed():
                    self._launch(self._pass_kernels(config, source), "linearize", count, codes,
                                 table, indicator)
            self._code_tables[key] = table
        return self._code_tables[key]

    def _exact_units(self, config: PassConfig, source):
        """Each 8-bit code's entry for the exact one-launch average, or None where it is not used.

        ``gb_blur_average_exact`` sums these (kernel_constants.EXACT_UNIT): the code table's
        value as a whole number of units, plus ``1 << EXACT_COUNT_SHIFT`` where it is saturated.
        None unless the frames are 8-bit codes in a float32 build whose table values are whole
        units in [0, 1] (the condition of gb_sum.h's proof, checked here on the values).
        """
        if np.dtype(source) != np.uint8 or np.dtype(self.np_real) != np.float32:
            return None
        key = ("exact", config)
        if key not in self._code_tables:
            table = OnDevice(self._code_table(config, source), (256,), self._fetch)
            values = table.numpy(np.float64)
            units = values / EXACT_UNIT
            whole = bool(np.all(units == np.floor(units)) and np.all((values >= 0)
                                                                     & (values <= 1)))
            saturated = values >= float(np.float32(SATURATION_LEVEL))
            entries = (units.astype(np.uint64)
                       + (saturated.astype(np.uint64) << np.uint64(EXACT_COUNT_SHIFT)))
            self._code_tables[key] = self._upload(entries, np.uint64) if whole else None
        return self._code_tables[key]

    def _sum_frames(self, k, config: PassConfig, source, stack, count: int, n: int, sums,
                    first: bool, mean_of: int, linear, sat_mask) -> None:
        """Launch the average's sum of ``count`` frames of ``n`` values each from ``stack``.

        Exactly in integers (``blur_average_exact``) when these are all the frames (``first``,
        ``mean_of == count``), at most EXACT_FRAMES_MAX 8-bit ones in a float32 build read four
        codes at a time (:meth:`_quads`); else the compensated sum (``blur_average_add``,
        :func:`average_args`). The same bits either way.
        """
        units = (self._exact_units(config, source)
                 if first and mean_of == count and count <= EXACT_FRAMES_MAX else None)
        quads = self._quads((stack, linear, sat_mask), n) if units is not None else None
        if quads is not None:
            self._launch(k, "blur_average_exact", (1, n // 4), quads[0], Arg("uint", count),
                         *_index(n // 4, 0), units, *quads[1:], *_index(0))
            return
        self._launch(k, "blur_average_add", n, *average_args(
            stack, count, n, sums, first, mean_of, linear, sat_mask,
            self._code_table(config, source)))

    def _quads(self, buffers, n: int):
        """Buffers of ``n`` values each as kernels taking four values a work item read them.

        8-bit codes as 4-byte words, reals as 4-vectors; None where they cannot: ``n`` must be
        a multiple of 4. The buffers themselves here (the OpenCL kernels declare
        ``uchar4`` and ``float4``); word and 4-vector views in Warp.
        """
        return tuple(buffers) if n % 4 == 0 else None

    # -- pass 1: accumulate ----------------------------------------------------------------
    def accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region: Region) -> tuple[OnDevice, OnDevice]:
        """Linearize and blur on the device; (linear, mask) over ``region``, on the device.

        ``frames``: host frames as stored (streamed a few at a time, any region), or inputs
        already on the device (:meth:`put`, whole images only): an ``n x H x W x 3`` stack
        for mode average, one ``H x W x 3`` image otherwise; ``mask`` likewise.
        """
        if isinstance(frames, OnDevice):
            return self._accumulate_put(plan, params, frames, mask, region)
        config = self._of_plan(plan)[Pass.ACCUMULATE]
        source = source_dtype(frames[0], self.np_real)
        k = self._pass_kernels(config, source)
        mode = plan.variant(S.BLUR) or "none"
        n = region.h * region.w * 3
        shape = (region.h, region.w, 3)
        linear = self._empty(n)
        sat_mask = None if mode == "none" else self._empty(n)  # mode none is given its mask
        if mode == "average" and interpolation_factor(plan) > 1:
            self._interpolated_average(plan, config, params, frames, region, linear, sat_mask)
        elif mode == "average":
            self._average(config, frames, region, linear, sat_mask)
        elif mode == "none":
            image = self._upload(region.of(frames[0]), source)
            with self._timed():
                self._linearize_unblurred(config, source, image, n, linear)
            del image
            given = np.zeros(shape) if mask is None else region.of(mask)
            return (self._out(linear, shape, Pass.ACCUMULATE, region.origin),
                    OnDevice(self._upload(given), shape, self._fetch))
        else:
            self._blur_photo(k, mode, params, frames[0], source, region, linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _accumulate_put(self, plan: Plan, params: dict, frames: OnDevice,
                        mask: OnDevice | None, region: Region,
                        into: tuple | None = None) -> tuple[OnDevice, OnDevice]:
        """:meth:`accumulate` of inputs on the device, over the whole image.

        ``into``: (linear, mask) device buffers of ``3 h w`` values to write (a batch's slots,
        :meth:`accumulate_into`), else new ones.
        """
        mode = plan.variant(S.BLUR) or "none"
        h, w = frames.shape[-3:-1]
        if (region.h, region.w) != (h, w) or region.origin != (0, 0):
            raise ValueError(f"inputs on the device run whole images; got the region {region} "
                             f"of a {h} x {w} image")
        if (frames.ndim == 4) != (mode == "average"):
            wanted = "an n x H x W x 3 stack of frames" if mode == "average" else "one image"
            raise ValueError(f"blur.mode = {mode} takes {wanted} on the device, got shape "
                             f"{frames.shape}")
        if mode == "average" and interpolation_factor(plan) > 1:
            raise ValueError("blur.interpolation > 1 needs the frames in host memory (its "
                             "optical flows are computed there)")
        config = self._of_plan(plan)[Pass.ACCUMULATE]
        source = frames.dtype or np.dtype(self.np_real)
        k = self._pass_kernels(config, source)
        n = h * w * 3
        shape = (h, w, 3)
        # mode none is given its mask (into a batch's slot, or as it is: _mask_values)
        linear, sat_mask = into or (self._empty(n), None if mode == "none" else self._empty(n))
        if mode == "average":  # one launch sums every frame of the stack
            count = frames.shape[0]
            spare = self._empty(1, np.uint32)
            with self._timed():
                self._sum_frames(k, config, source, frames.data, count, n,
                                 (linear, sat_mask, spare), True, count, linear, sat_mask)
        elif mode == "none":
            with self._timed(sync=False):
                self._linearize_unblurred(config, source, frames.data, n, linear)
            if into is None:
                return (self._out(linear, shape, Pass.ACCUMULATE, region.origin),
                        self._mask_values(mask, n, shape))
            self._mask_into(mask, n, sat_mask)
        else:
            self._blur_photo(k, mode, params, frames, source, region, linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _linearize_unblurred(self, config: PassConfig, source, image, count: int,
                             linear) -> None:
        """Blur mode none's linearize: ``count`` values of ``image`` into ``linear``.

        No clip indicator: mode none's given mask replaces it. 8-bit codes where they come in
        fours go four a work item through the code table (``linearize_codes``, the same bits);
        else ``linearize``, its indicator into a spare buffer.
        """
        k = self._pass_kernels(config, source)
        quads = self._quads((image, linear), count) if np.dtype(source) == np.uint8 else None
        if quads is None:
            self._launch(k, "linearize", count, image, linear, self._empty(count))
        else:
            self._launch(k, "linearize_codes", count // 4, quads[0],
                         self._code_table(config, source), quads[1])

    def _unit_values(self, stored: OnDevice, count: int, into) -> None:
        """``count`` stored values (a mask in its stored dtype) as reals in [0, 1] into ``into``.

        8-bit codes where they come in fours go four a work item (``unit_values_codes``, the
        same bits).
        """
        source = self._stored_dtype(stored)
        k = self._input_kernels(None, source)
        quads = self._quads((stored.data, into), count) if source == np.uint8 else None
        with self._timed(sync=False):
            if quads is None:
                self._launch(k, "unit_values", count, stored.data, into)
            else:
                self._launch(k, "unit_values_codes", count // 4, *quads)

    def _mask_into(self, mask: OnDevice | None, n: int, into) -> None:
        """Mode none's given mask as compute-type values in the device buffer ``into``."""
        if mask is None:
            self._fill_zeros(into, n)
        elif self._stored_dtype(mask) == np.dtype(self.np_real):
            self._copy(into, mask.data, n)
        else:
            self._unit_values(mask, n, into)

    def accumulate_into(self, plan: Plan, params: dict, frames: OnDevice,
                        mask: OnDevice | None, linear: Slots, sat_mask: Slots, b: int) -> None:
        """:meth:`accumulate` of whole inputs put on the device, into slot ``b`` of batch buffers.

        ``linear``, ``sat_mask``: slots of ``3 h w`` values (:meth:`slots`), as the batched
        to_raw pass reads them.
        """
        h, w = frames.shape[-3:-1]
        self._into_slots((linear, sat_mask), b, h * w * 3, lambda into: self._accumulate_put(
            plan, params, frames, mask, Region.whole(h, w), into))

    def accumulate_batch(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                         inputs: Sequence[tuple[OnDevice, OnDevice | None]], linear: Slots,
                         sat_mask: Slots) -> Slots:
        """:meth:`accumulate_into` for every sample of a batch, each into its slot.

        Returns the slots that hold the saturation masks: ``sat_mask``, or in blur mode none
        the given masks' own device buffer where they lie back to back in the compute type
        (:meth:`_linearize_batch`: nothing copied; the later passes only read it).

        Blur mode kernel takes two launches a sample fewer: each photo is linearized into its
        slot of two batch buffers made for the call (``3 h w`` values a sample each), then one
        launch convolves every sample with its own kernel (:meth:`_blur_kernels`). The other
        modes run sample by sample.

        Args:
            plans: each sample's plan.
            samples: each sample's draws, index and slot.
            inputs: each sample's (frames, mask) put on the device (:meth:`put`).
            linear: the batch's slots of ``3 h w`` values for the linear images.
            sat_mask: the same for the saturation masks.
        """
        masks = self._linearize_batch(plans, samples, inputs, linear, sat_mask)
        if masks is not None:
            return masks
        if self._averaged_at_once(plans, samples, [frames for frames, _ in inputs], linear,
                                  sat_mask):
            return sat_mask
        kernel_mode = [i for i, p in enumerate(plans) if p.variant(S.BLUR) == "kernel"]
        for p, drawn, (frames, mask) in zip(plans, samples, inputs, strict=True):
            if p.variant(S.BLUR) != "kernel":
                self.accumulate_into(p, drawn.params, frames, mask, linear, sat_mask, drawn.slot)
        if not kernel_mode:
            return sat_mask
        h, w = inputs[kernel_mode[0]][0].shape[-3:-1]
        n = h * w * 3
        src, ind = self.slots(linear.count, n), self.slots(linear.count, n)
        at_once = len(kernel_mode) == len(plans) and self._linearized_at_once(
            plans, samples, [photo for photo, _ in inputs], (src, ind))
        groups: dict = {}  # the samples of each accumulate configuration and source dtype
        for i in kernel_mode:
            photo = inputs[i][0]
            if photo.ndim != 3 or tuple(photo.shape[:2]) != (h, w):
                raise ValueError(f"blur.mode = kernel takes one {h} x {w} x 3 image per sample "
                                 f"on the device; got shape {photo.shape}")
            source = photo.dtype or np.dtype(self.np_real)
            config = self._of_plan(plans[i])[Pass.ACCUMULATE]
            k = self._pass_kernels(config, source)
            slot = samples[i].slot
            if not at_once:
                with self._timed(sync=False):
                    self._into_slots((src, ind), slot, n, lambda into, k=k, photo=photo:
                                     self._launch(k, "linearize", n, photo.data, *into))
            groups.setdefault((config, source.str), (k, []))[1].append(samples[i])
        whole = Region.whole(h, w)
        for k, drawn in groups.values():
            with self._timed():
                self._blur_kernels(k, drawn, src, ind, whole, whole, linear, sat_mask)
        return sat_mask

    def _linearize_batch(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                         inputs: Sequence[tuple[OnDevice, OnDevice | None]], linear: Slots,
                         sat_mask: Slots) -> Slots | None:
        """Blur mode none for a whole batch at once, where it can; else None.

        It can where :meth:`_linearized_at_once` can, and every mask, if any is given, lies
        back to back in one device buffer too: then its masks follow in one conversion
        (8/16-bit codes) or none at all (values of the compute type: their own buffer is
        returned), as :meth:`_accumulate_put` does it sample by sample. Returns the masks'
        slots.
        """
        if any((p.variant(S.BLUR) or "none") != "none" for p in plans):
            return None
        given = [m for _, m in inputs if m is not None]
        mask = self.consecutive(given) if given else None
        if given and (len(given) != len(inputs) or mask is None):
            return None
        if not self._linearized_at_once(plans, samples, [f for f, _ in inputs],
                                        (linear, sat_mask), indicator=False):
            return None
        n = linear.stride
        if mask is not None and self._stored_dtype(mask) == np.dtype(self.np_real):
            return Slots(mask.data, len(samples), n)
        self._mask_into(mask, len(samples) * n, sat_mask.buffer)
        return sat_mask

    def _averaged_at_once(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                          stacks: Sequence[OnDevice], linear: Slots, sat_mask: Slots) -> bool:
        """Blur mode average of every sample in one launch, where it can; whether it ran.

        It can where :meth:`_at_once` can and the frames sum exactly (``blur_average_exact``:
        8-bit codes, :meth:`_exact_units`, :meth:`_quads`).
        """
        if any(p.variant(S.BLUR) != "average" for p in plans):
            return False
        batch = self._at_once(plans, samples, stacks, (linear, sat_mask), frames=True)
        if batch is None:
            return False
        whole, config, n = batch
        count = whole.shape[1]
        units = self._exact_units(config, whole.dtype) if count <= EXACT_FRAMES_MAX else None
        quads = (self._quads((whole.data, linear.buffer, sat_mask.buffer), n)
                 if units is not None else None)
        if quads is None:
            return False
        k = self._pass_kernels(config, whole.dtype)
        with self._timed(sync=False):
            self._launch(k, "blur_average_exact", (len(samples), n // 4), quads[0],
                         Arg("uint", count), *_index(n // 4, count * n // 4), units,
                         *quads[1:], *_index(n // 4))
        return True

    def _linearized_at_once(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                            photos: Sequence[OnDevice], into: tuple[Slots, Slots], *,
                            indicator: bool = True) -> bool:
        """Every sample's photo linearized in one launch, where it can; whether it ran.

        Into its slots of ``into`` (linear values, clip indicators), where :meth:`_at_once`
        can; without ``indicator`` (blur mode none) the indicators' slots are left as they are.
        """
        batch = self._at_once(plans, samples, photos, into, frames=False)
        if batch is None:
            return False
        whole, config, n = batch
        source = whole.dtype or np.dtype(self.np_real)
        with self._timed(sync=False):
            if indicator:
                self._launch(self._pass_kernels(config, source), "linearize",
                             len(samples) * n, whole.data, into[0].buffer, into[1].buffer)
            else:
                self._linearize_unblurred(config, source, whole.data, len(samples) * n,
                                          into[0].buffer)
        return True

    def _at_once(self, plans: Sequence[Plan], samples: Sequence[Drawn],
                 inputs: Sequence[OnDevice], slots: Sequence[Slots], *, frames: bool
                 ) -> tuple[OnDevice, PassConfig, int] | None:
        """(inputs as one, accumulate configuration, values a slot) for a one-launch batch.

        None where one accumulate launch cannot take the whole batch. It can when the inputs
        (frame stacks with ``frames``, else images) lie back to back in one device buffer
        (:meth:`consecutive`), fewer than 2^31 values (the kernels' indices), in slot order;
        each of ``slots`` holds exactly one image a slot; and the samples share one
        accumulate configuration.
        """
        whole = self.consecutive(inputs)
        configs = {self._of_plan(p)[Pass.ACCUMULATE] for p in plans}
        if (whole is None or whole.ndim != (5 if frames else 4) or len(configs) != 1
                or int(np.prod(whole.shape)) >= 2**31
                or [d.slot for d in samples] != list(range(len(samples)))):
            return None
        n = int(np.prod(whole.shape[2 if frames else 1:]))
        if any(s.stride != n or s.count < len(samples) for s in slots):
            return None
        return whole, configs.pop(), n

    def _into_slots(self, slots: Sequence[Slots], b: int, count: int, fill) -> None:
        """``fill(buffers)`` writes the first ``count`` values of slot ``b`` of each of ``slots``.

        In place where the language has views of a buffer (Warp); else into new buffers, then
        copied into the slots (OpenCL: NVIDIA's sub-buffers cost several times the copy).
        """
        into = tuple(self._in_slot(s, b, count) for s in slots)
        if None not in into:
            fill(into)
            return
        into = tuple(self._empty(count) for _ in slots)
        fill(into)
        for s, values in zip(slots, into, strict=True):
            self._copy(s.buffer, values, count, b * s.stride)

    def _blur_kernels(self, k, samples: Sequence[Drawn], src: Slots, ind: Slots, view: Region,
                      region: Region, linear: Slots, sat_mask: Slots) -> None:
        """Blur mode kernel of samples in one launch, each sample in its slot.

        Each sample's linear image and saturation indicator (its slots of ``src`` and ``ind``,
        over ``view``) convolved with its ``params["kernel"]`` into its slots of ``linear`` and
        ``sat_mask`` (over ``region``).
        """
        kernels = [blur.normalize_kernel(d.params["kernel"]) for d in samples]
        need = region.expand(max(max(kern.shape) // 2 for kern in kernels))
        if not (view.y0 <= need.y0 and view.x0 <= need.x0 and need.y0 + need.h <= view.y0
                + view.h and need.x0 + need.w <= view.x0 + view.w):
            raise ValueError(f"blur kernels: the view {view} does not hold {need}, the region "
                             "and the largest kernel's radius (a gpu_blur bug: please report it)")
        _check_slots(samples, (("src", src, view.h * view.w * 3),
                               ("ind", ind, view.h * view.w * 3),
                               ("linear", linear, region.h * region.w * 3),
                               ("sat_mask", sat_mask, region.h * region.w * 3)))
        first = np.cumsum([0] + [kern.size for kern in kernels[:-1]])
        words = np.array([(f, *kern.shape, d.slot)
                          for f, kern, d in zip(first, kernels, samples, strict=True)],
                         dtype=np.uint32).reshape(len(samples), len(KERNEL_WORDS))
        taps = np.concatenate([kern.ravel() for kern in kernels]).astype(self.np_real)
        self._launch(k, "blur_kernel", (len(samples), region.h, region.w), *self._slots(src),
                     *self._slots(ind), *_view_geometry(view), self._rows(taps),
                     self._rows(words), *self._slots(linear), *self._slots(sat_mask),
                     *_out_geometry(region))

    #: Whether :meth:`_view` gives views of a buffer (else slots are read and written by copies).
    slot_views = False

    def _view(self, buffer, start: int, count: int):
        """Values ``start .. start + count`` of a device buffer, as a buffer sharing its memory."""
        raise NotImplementedError

    def _in_slot(self, slots: Slots, b: int, count: int):
        """The first ``count`` values of slot ``b`` as a buffer sharing its memory, or None.

        A view where the language has them; slot 0 is the buffer itself (its first values).
        """
        if self.slot_views:
            return self._view(slots.buffer, b * slots.stride, count)
        return slots.buffer if b == 0 else None

    def slot_image(self, slots: Slots, b: int, shape) -> OnDevice:
        """Slot ``b`` of a batch buffer as an ``OnDevice`` image of ``shape``.

        A view where the language has them (and for slot 0), else a device copy.
        """
        size = int(np.prod(shape))
        data = self._in_slot(slots, b, size)
        if data is None:
            data = self._part(slots.buffer, b * slots.stride, size, None)
        return OnDevice(data, shape, self._fetch)

    def stacked(self, slots: Slots, shape) -> OnDevice:
        """Every slot of a batch buffer as one ``count x shape`` ``OnDevice`` stack."""
        return OnDevice(slots.buffer, (slots.count, *shape), self._fetch)

    def _copy(self, into, values, count: int, offset: int = 0) -> None:
        """Copy ``count`` values of ``values`` into ``into`` from value ``offset`` on.

        Both device buffers; queued after the launches before it.
        """
        raise NotImplementedError

    def _fill_zeros(self, buffer, count: int) -> None:
        """Set the first ``count`` values of a device buffer to zero, in queue order."""
        raise NotImplementedError

    def _mask_values(self, mask: OnDevice | None, n: int, shape) -> OnDevice:
        """Mode none's given mask as compute-type values on the device (zeros without one)."""
        if mask is None:
            return OnDevice(self._zeros(n), shape, self._fetch)
        source = self._stored_dtype(mask)
        if source == np.dtype(self.np_real):
            return OnDevice(mask.data, shape, self._fetch)
        values = self._empty(n)
        self._unit_values(mask, n, values)
        return OnDevice(values, shape, self._fetch)

    def put(self, image) -> OnDevice:
        """An input on the device in its stored dtype, for :meth:`accumulate` and the checks.

        Args:
            image: ``H x W x 3`` (or an ``n x H x W x 3`` stack of frames, or a list of ``n``
                frames of one size and dtype) as stored: uint8 or uint16 codes go as they
                are, floats as the compute type; a host array is copied once.
        """
        if isinstance(image, (list, tuple)):
            image = np.stack(image)
        dtype = source_dtype(image, self.np_real)
        return self._input(self._upload(image, dtype), np.shape(image), dtype)

    def pinned(self, shape, dtype=np.float32) -> np.ndarray:
        """An uninitialized host array in page-locked memory this backend copies directly.

        An input batch filled in it (``np.stack(frames, out=...)``) uploads with no staging
        copy, and ``out=`` arrays made here receive the results straight from the device: the
        bus's rate instead of the host's copy rate. Page-locking is slow: make them once and
        reuse them.
        """
        dtype = np.dtype(dtype)
        nbytes = max(int(np.prod(shape)) * dtype.itemsize, 1)
        keep, address = self._pinned_bytes(nbytes)
        flat = np.asarray(PinnedHost(self, keep, address, nbytes))
        return flat[:int(np.prod(shape)) * dtype.itemsize].view(dtype).reshape(shape)

    def _pinned_bytes(self, nbytes: int) -> tuple:
        """(what holds it, its address): ``nbytes`` of page-locked host memory."""
        raise NotImplementedError

    def _direct(self, x, dtype=None) -> bool:
        """Whether ``x`` copies straight to or from the device (no staging).

        So it does when it is a host array in this backend's :meth:`pinned` memory,
        contiguous, in ``dtype`` (default: the dtype it travels in).
        """
        if not isinstance(x, np.ndarray):
            return False
        dtype = source_dtype(x, self.np_real) if dtype is None else np.dtype(dtype)
        return x.dtype == dtype and x.flags.c_contiguous and pinned_owner(x) is self

    def _input(self, data, shape, dtype) -> OnDevice:
        """An input put on the device, ``dtype`` recorded for codes (None: the compute type)."""
        return OnDevice(data, shape, self._fetch,
                        None if np.dtype(dtype) == np.dtype(self.np_real) else dtype)

    def _staged_parts(self, image) -> tuple:
        """A host input for a put through pinned staging (``overlap``), and the buffer it takes.

        ``image``: an array, or a list of frames of one size and dtype (copied one after
        another: no stacked host copy). Returns (parts, shape, dtype it travels in, values,
        slot): two pinned input buffers take turns, so filling one overlaps the other's upload.
        """
        frames = isinstance(image, (list, tuple))
        parts = list(image) if frames else [np.asarray(image)]
        shape = (len(parts), *parts[0].shape) if frames else parts[0].shape
        slot = ("put", self._put_turn)
        self._put_turn ^= 1
        return (parts, shape, source_dtype(parts[0], self.np_real), parts[0].size * len(parts),
                slot)

    @staticmethod
    def _fill_staging(host: np.ndarray, parts) -> None:
        """Copy ``parts`` one after another into the flat pinned array ``host`` (threads)."""
        copy_values(host[:parts[0].size * len(parts)], list(parts))

    def consecutive(self, images: Sequence[OnDevice]) -> OnDevice | None:
        """``images`` as one ``B x shape`` image, where they lie back to back in one buffer.

        Else None; see :meth:`spaced` (here the images are exactly their size apart).
        """
        spaced = self.spaced(images)
        size = int(np.prod(images[0].shape)) if images else 0
        if spaced is None or spaced[1] != size:
            return None
        return OnDevice(spaced[0], (len(images), *images[0].shape), self._fetch,
                        images[0].dtype)

    def spaced(self, images: Sequence[OnDevice]) -> tuple[object, int] | None:
        """(one flat buffer from the first image's first value, the values between images).

        Where ``images``, of one shape and dtype, lie evenly spaced in one device buffer (a
        torch or CuPy batch on a Warp device; the middle frames of a batch of frame stacks),
        batched launches read them at once; else None. Only a language with views of device
        memory (Warp) finds them (:meth:`_spaced_data`).
        """
        if not images or any(i.shape != images[0].shape or i.dtype != images[0].dtype
                             for i in images):
            return None
        return self._spaced_data([i.data for i in images])

    def _spaced_runs(self, images: Sequence[OnDevice]) -> list[list[OnDevice]]:
        """``images`` cut, in order, into runs of one image or of evenly spaced ones.

        Evenly spaced: lying in one device buffer a fixed number of values apart
        (:meth:`spaced`).
        """
        runs: list[list[OnDevice]] = []
        stride = None  # the last run's spacing
        for image in images:
            last = runs[-1][-1] if runs else None
            gap = (self._gap(last.data, image.data) if last is not None
                   and (last.shape, last.dtype) == (image.shape, image.dtype) else None)
            if gap is not None and (len(runs[-1]) == 1 or gap == stride):
                runs[-1].append(image)
                stride = gap
            else:
                runs.append([image])
        return runs

    def _spaced_data(self, buffers: Sequence) -> tuple[object, int] | None:
        """:meth:`spaced` of device buffers of one size and dtype."""
        return None

    def _gap(self, first, second) -> int | None:
        """Values from device buffer ``first``'s start to ``second``'s, or None.

        None unless both are alike (size, dtype, device, contiguous) and ``second`` starts
        at or after ``first``'s end: they are two of a run :meth:`spaced` finds.
        """
        return None

    def frame(self, stack: OnDevice, index: int) -> OnDevice:
        """Frame ``index`` of an ``n x H x W x 3`` stack :meth:`put` on the device."""
        n = int(np.prod(stack.shape[1:]))
        return OnDevice(self._part(stack.data, index * n, n, stack.dtype), stack.shape[1:],
                        self._fetch, stack.dtype)

    def _part(self, buffer, start: int, count: int, dtype):
        """Values ``start .. start + count`` of a device buffer (a view, or a device copy)."""
        raise NotImplementedError

    def export(self, values: OnDevice, region: Region, into) -> None:
        """Copy ``region`` of a whole-image device result into ``into``, a host array."""
        np.copyto(into, region.of(values.numpy(into.dtype)))

    def _average(self, config: PassConfig, frames, region: Region, linear, sat_mask) -> None:
        """Mode average: the mean of the frames, a stack of frames per launch."""
        source = source_dtype(frames[0], self.np_real)
        k = self._pass_kernels(config, source)
        n = region.h * region.w * 3
        # running compensated sums (sum, rounding errors, saturation counts) are only
        # needed between launches: one stack of frames is summed in registers
        sums = ((self._empty(n), self._empty(n), self._empty(n, np.uint32))
                if len(frames) > FRAMES_PER_LAUNCH
                else (linear, sat_mask, self._empty(1, np.uint32)))
        done = 0
        for stack, count in self._frame_stacks(frames, region):
            last = done + count == len(frames)
            with self._timed(sync=last):
                self._sum_frames(k, config, source, stack, count, n, sums, done == 0,
                                 len(frames) if last else 0, linear, sat_mask)
            done += count

    def _blur_photo(self, k, mode: str, params: dict, photo, source, region: Region, linear,
                    sat_mask) -> None:
        """Modes kernel and trajectory: one photo, linearized over the blur's halo, blurred."""
        view = region.expand(blur.blur_halo(mode, params, region.full_h, region.full_w))
        vn = view.h * view.w * 3
        src, indicator = self._empty(vn), self._empty(vn)
        image = self._upload(photo if isinstance(photo, OnDevice) else view.of(photo), source)
        with self._timed(sync=False):
            self._launch(k, "linearize", vn, image, src, indicator)
        del image
        grid = (region.h, region.w)
        if mode == "kernel":  # a batch of one
            n = region.h * region.w * 3
            with self._timed():
                self._blur_kernels(k, [Drawn(params, 0, 0)], Slots(src, 1, vn),
                                   Slots(indicator, 1, vn), view, region, Slots(linear, 1, n),
                                   Slots(sat_mask, 1, n))
            return
        # compensated sums (sum, compensation) of the image and of its indicator, 3 values a
        # pixel, and of the poses' weights on the image, 1 a pixel (reference.shake, "Edges")
        pixels = region.h * region.w
        sums = ([self._zeros(3 * pixels) for _ in range(4)]
                + [self._zeros(pixels) for _ in range(2)])
        hom = params["homographies"]
        inverses = [self._rows(np.ravel(h).astype(self.position_dtype))  # as the reference:
                    for h in fixedmath.inverse3(hom)]  # the same bits on every host CPU
        with self._timed():
            for hinv in inverses:  # one pose at a time
                self._launch(k, "blur_trajectory_add", grid, src, indicator,
                             *_view_geometry(view), hinv, *sums, *_out_geometry(region))
            self._launch(k, "blur_trajectory_finish", 3 * pixels, *sums, linear, sat_mask)

    def _interpolated_average(self, plan: Plan, config: PassConfig, params: dict,
                              frames: Sequence[np.ndarray], region: Region, linear,
                              sat_mask) -> None:
        """Mode average at ``blur.interpolation`` times the frame rate, into linear, sat_mask.

        One gap at a time, in time order: frame i+1 and the gap's two flows upload over the
        region plus the flows' halo (frame i stays from the gap before), then the original
        frame and the intermediates after it join one set of compensated sums (the
        interpolate kernels); intermediate frames are never stored.
        """
        params = with_flows(plan, params, frames)
        regions = gap_regions(plan, params, len(frames) - 1)
        factors = regions.gaps
        if max(factors, default=1) == 1:  # interpolation auto, no gap moves: a plain average
            self._average(config, frames, region, linear, sat_mask)
            return
        # each gap's frames stand for M / f frames (reference.interpolate, steps 6 and 7), f
        # the factor of the pixel's region: all 1 for one factor everywhere, so a fixed factor
        # adds exactly what it always did
        most = max(factors)
        _, total = gap_weights(factors)
        # the gaps' region factors, then one region of M for the last frame (weight 1)
        per_gap, cols = regions.factors[0].size, regions.factors.shape[2]
        maps = self._empty(regions.factors.size + 1, np.uint32)
        self._write(maps, np.append(regions.factors.ravel(), most).astype(np.uint32))

        def weights(gap: int) -> tuple[Arg, ...]:  # a gap's factors per region, and M
            if gap == len(factors):
                return maps, *_index(regions.factors.size, 0, 1), Arg("uint", most)
            return maps, *_index(gap * per_gap, regions.side, cols), Arg("uint", most)

        source = source_dtype(frames[0], self.np_real)
        k = self._pass_kernels(config, source, interpolate=True)
        flows = params["flows"]
        view = region.expand(blur.blur_halo("average", params, region.full_h, region.full_w))
        n = region.h * region.w * 3
        sums = (self._zeros(n), self._zeros(n), self._zeros(n))
        geometry = _index(view.x0, view.y0, view.w)
        full = _index(region.full_w, region.full_h)
        test = (Arg("position", CONSISTENCY_RELATIVE), Arg("position", CONSISTENCY_ABSOLUTE_PX2))
        grid = (region.h, region.w)
        frame_bufs = [self._empty(view.h * view.w * 3, source) for _ in range(min(2, len(frames)))]
        flow_bufs = [self._empty(view.h * view.w * 2, np.float32) for _ in range(2)]
        for i in range(len(frames)):
            self._write(frame_bufs[i % 2], np.ascontiguousarray(view.of(frames[i]), source))
            factor = factors[i - 1] if i > 0 else 1
            if factor > 1:  # a gap without intermediates reads no flows
                for buf, flow in zip(flow_bufs, flows[i - 1], strict=True):
                    self._write(buf, np.ascontiguousarray(view.of(flow)))
            with self._timed(sync=False):
                for step in range(1, factor):
                    self._launch(k, "blur_interpolate_add", grid, frame_bufs[(i - 1) % 2],
                                 frame_bufs[i % 2], *flow_bufs, *geometry, *full,
                                 Arg("position", step / factor), *test,
                                 Arg("uint", step), Arg("uint", factor), *weights(i - 1),
                                 *sums, *_out_geometry(region))
                self._launch(k, "blur_interpolate_add_frame", grid, frame_bufs[i % 2],
                             *geometry, *weights(i), *sums, *_out_geometry(region))
        with self._timed():
            self._launch(k, "blur_interpolate_finish", n, *sums, Arg("uint", total), linear,
                         sat_mask)

    # -- pass 2: to_raw --------------------------------------------------------------------
    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear, mask,
               origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[OnDevice, OnDevice]:
        """Saturation to noisy RAW on the device (see NumpyBackend.to_raw): a batch of one."""
        h, w = linear.shape[:2]
        n = h * w * 3
        saturated = self.slots(1, n)
        raw = self.slots(1, h * w if plan.raw_round_trip else 1)
        self.to_raw_batch(plan, camera, [Drawn(params, sample_index, 0)],
                          Slots(self._upload(linear), 1, n), Slots(self._upload(mask), 1, n),
                          saturated, raw, origin, (h, w), seed=seed)
        rgb = OnDevice(saturated.buffer, (h, w, 3), self._fetch)
        if not plan.raw_round_trip:
            return self._out(saturated.buffer, (h, w, 3), Pass.TO_RAW, origin), rgb
        return self._out(raw.buffer, (h, w), Pass.TO_RAW, origin), rgb

    def to_raw_batch(self, plan: Plan, camera: Camera, samples: Sequence[Drawn], linear: Slots,
                     mask: Slots, saturated: Slots, raw: Slots, origin: tuple[int, int],
                     size: tuple[int, int], *, seed: int) -> None:
        """The to_raw pass of samples of one plan in one launch, each in its slot.

        Args:
            plan: the samples' plan.
            camera: their camera.
            samples: each sample's draws, index and slot.
            linear: the accumulate pass's ``h x w x 3`` linear images, a slot per sample.
            mask: its saturation masks, the same way.
            saturated: takes each sample's ``h x w x 3`` saturated image.
            raw: takes each sample's ``h x w`` mosaic (the RAW round trip; else slots of one
                value, never written).
            origin: (row, column) of the buffers' first pixel in the whole image.
            size: (h, w).
            seed: the data set's seed.
        """
        k = self._pass_kernels(self._of_plan(plan)[Pass.TO_RAW])
        h, w = size
        _check_slots(samples, (("linear", linear, 3 * h * w), ("mask", mask, 3 * h * w),
                               ("saturated", saturated, 3 * h * w),
                               ("raw", raw, h * w if plan.raw_round_trip else 1)))
        tables = self._tables(samples)
        matrix = self._constant(camera.linear_to_camera)
        with self._timed():
            self._launch(k, "to_raw", (len(samples), h, w), *to_raw_args(
                plan, tables, origin, h, w, (self._slots(linear), self._slots(mask)), matrix,
                (self._slots(saturated), self._slots(raw)), seed=seed))

    # -- pass 3: finish --------------------------------------------------------------------
    def finish(self, plan: Plan, params: dict, camera: Camera, image, saturated, view: Region,
               out: Region, *, seed: int, sample_index: int) -> OnDevice:
        """Demosaic and finish on the device, over ``out`` (see NumpyBackend.finish).

        A batch of one.
        """
        raw = image if plan.raw_round_trip else np.zeros(1)
        n = out.h * out.w * 3
        result = self.slots(1, n)
        self.finish_batch(plan, camera, [Drawn(params, sample_index, 0)],
                          Slots(self._upload(raw), 1, int(np.prod(np.shape(raw)))),
                          Slots(self._upload(saturated), 1, view.h * view.w * 3), view, out,
                          result, seed=seed)
        return self._out(result.buffer, (out.h, out.w, 3), Pass.FINISH, out.origin)

    def finish_batch(self, plan: Plan, camera: Camera, samples: Sequence[Drawn], raw: Slots,
                     saturated: Slots, view: Region, out: Region, result: Slots, *,
                     seed: int) -> None:
        """The finish pass of samples of one plan in one launch, each in its slot.

        ``raw`` (``view.h x view.w`` a slot, or placeholders without the RAW round trip) and
        ``saturated`` (``view.h x view.w x 3``) are :meth:`to_raw_batch`'s outputs over
        ``view``; ``result`` takes each sample's ``out.h x out.w x 3`` image.
        """
        derived = self._of_plan(plan, camera)
        k = self._pass_kernels(derived[Pass.FINISH])
        polynomial, table = derived["curves"]
        pixels = view.h * view.w
        _check_slots(samples, (("raw", raw, pixels if plan.raw_round_trip else 1),
                               ("saturated", saturated, 3 * pixels),
                               ("result", result, 3 * out.h * out.w)))
        tables = self._tables(samples)
        matrix = self._constant(camera.camera_to_linear)
        pairs = (out.x0 % 2 + out.w + 1) // 2  # the kernel's column pairs (finish.cl)
        with self._timed():
            self._launch(k, "finish", (len(samples), out.h, pairs), *finish_args(
                plan, tables, view, out, (self._slots(raw), self._slots(saturated)), matrix,
                (self._constant(polynomial), polynomial.size),
                (self._constant(table), table.size), self._slots(result), seed=seed))

    def slots(self, count: int, values: int) -> Slots:
        """A new batch buffer of ``count`` slots of ``values`` values each, back to back."""
        return Slots(self._empty(count * values), count, values)

    def _tables(self, samples: Sequence[Drawn]) -> tuple:
        """:func:`sample_tables` on the device, as the kernels read them.

        The last upload is kept: the finish pass of the samples whose to_raw pass just ran
        reads the same tables (the buffers stay alive while the launches that read them run).
        """
        values, words = sample_tables(samples)
        values = values.astype(self.np_real)
        key = (values.tobytes(), words.tobytes())
        if self._last_tables is None or self._last_tables[0] != key:
            self._last_tables = (key, (self._rows(values), self._rows(words)))
        return self._last_tables[1]

    def _rows(self, table: np.ndarray):
        """A small host table (a sample's draws, its kernel taps) on the device, in its dtype.

        Flat where the language indexes by hand (OpenCL); Warp keeps its shape and, on CUDA,
        queues the copy instead of waiting for the device.
        """
        return self._upload(table, table.dtype)

    def _slots(self, slots: Slots) -> tuple:
        """A batch buffer as its kernels take it: (flat buffer, stride); Warp: a 2-D view.

        The stride is an ``extent`` (OpenCL steps by it); Warp's view is ``count x stride``.
        """
        return slots.buffer, Arg("index", slots.stride, extent=True)

    # -- inputs on the device: checks and the sharp reference ------------------------------
    def _input_kernels(self, config: PassConfig | None, source):
        """The kernels over input images stored as ``source`` (uint8, uint16, compute type).

        ``config`` None: ``inspect`` and ``unit_values``; else (:func:`sharp_config`)
        ``render_sharp`` and, for 8/16-bit codes, ``gather_codes``, built for it.
        """
        raise NotImplementedError

    def _stored_dtype(self, image: OnDevice) -> np.dtype:
        """The dtype an input image is stored in on the device: uint8, uint16 or the compute type.

        Raises:
            ValueError: for any other dtype, naming it and the ones allowed.
        """
        dtype = np.dtype(self.np_real) if image.dtype is None else image.dtype
        if dtype not in (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(self.np_real)):
            raise ValueError(f"an input image on the device holds {dtype} values; the kernels "
                             f"read uint8, uint16 or {np.dtype(self.np_real)} (the compute "
                             "type): convert it before the upload")
        return dtype

    def inspect(self, images: Sequence[OnDevice]) -> np.ndarray:
        """Counts over input images as stored on the device, for the checks on them.

        One launch per image, all into one small device buffer read back once; no value of
        the images reaches the host.

        Args:
            images: ``OnDevice`` images whose ``dtype`` is uint8 or uint16 (codes) or None
                or the compute type (values), any shape.

        Returns:
            int64 array ``len(images) x 6``, one row per image, the columns of
            :data:`INSPECT_COLUMNS`: NaN, infinite, below 0, above 1, at the clip level (>= 1.0
            for values, the top code 2^bits - 1 for codes: ``gpu_blur.pipeline``'s
            ``_reaches_clip_level``), above 0 (a mask's "anything to saturate").
        """
        return self.inspect_queued(images)()

    def inspect_queued(self, images: Sequence[OnDevice]) -> Callable[[], np.ndarray]:
        """:meth:`inspect`'s launches, queued; returns the function that reads their counts.

        The counts' copy to the host is queued right after the launches, and reading waits
        for it alone: a batch queues its passes in between, and the device goes on with them
        (and with the batch before, still queued) while the host reads. A run of images that
        lie evenly spaced in one device buffer (:meth:`spaced`: a device batch's samples)
        takes one launch, each image still counted into its own row.
        """
        if not images:
            return lambda: np.zeros((0, len(INSPECT_COLUMNS)), np.int64)
        sources = [self._stored_dtype(image) for image in images]
        # each count as two uint32 words, (low, high)
        words = len(images) * len(INSPECT_COLUMNS) * 2
        counts = self._zeros(words, np.uint32)
        with self._timed(sync=False):
            row = 0
            for run in self._spaced_runs(images):
                spaced = self.spaced(run) if len(run) > 1 else None
                data, stride = spaced or (run[0].data, 0)
                n = int(np.prod(run[0].shape))
                items = inspect_items(n, len(run))
                k = self._input_kernels(None, sources[row])
                self._launch(k, "inspect", (len(run), items), data, *_index(n, items), counts,
                             *_index(row, stride))
                row += len(run)
        host, kept = self._counts_words(words)
        with timer("copies"):
            copied = self._fetch_queued(counts, host)

        def read() -> np.ndarray:
            with timer("copies"):
                copied()
            pairs = host.reshape(len(images), len(INSPECT_COLUMNS), 2).astype(np.int64)
            if kept:
                self._counts_reader = None
            return pairs[..., 0] + (pairs[..., 1] << 32)

        if kept:
            self._counts_reader = weakref.ref(read)
        return read

    def to_codes(self, values: OnDevice, bits: int, into=None) -> OnDevice:
        """An output's integer codes, on the device: uint8 for ``bits`` 8, uint16 for 16.

        The codes :func:`gpu_blur.reference.output.to_integers` gives the values (the finish
        pass's quantize_code: exact for every float32 value; a float64 build rounds exactly,
        which to_integers matches away from the rounding boundaries, where no quantized
        output lies): a quarter (a half) of the float32 bytes to fetch, no host conversion.
        ``into``: a device buffer of exactly that many codes to write (:meth:`codes_buffer`),
        else a new one.
        """
        dtype = code_dtype(bits)
        count = int(np.prod(values.shape))
        codes = self._empty(count, dtype) if into is None else into
        with self._timed():
            self._launch(self._input_kernels(None, dtype), "to_codes", count, values.data,
                         codes)
        return OnDevice(codes, values.shape, self._fetch, dtype)

    def codes_buffer(self, count: int, bits: int):
        """A kept device buffer for ``count`` codes of ``bits`` bits (:meth:`to_codes`).

        For codes fetched before the next call asks for it (queue order): a new device
        buffer for every batch costs more than its codes' download (on an H200 a batch of
        16 RSBlur samples from pinned memory took 1.91 ms a sample so, 1.50 with a kept one).
        """
        key = (count, bits)
        if key not in self._kept_codes:
            if len(self._kept_codes) >= 2:  # a batch's parts and its last, smaller one
                self._kept_codes.clear()
            self._kept_codes[key] = self._empty(count, code_dtype(bits))
        return self._kept_codes[key]

    def _counts_words(self, words: int) -> tuple[np.ndarray, bool]:
        """(pinned host words for one inspect's counts, whether they are the kept ones).

        The kept ones unless a read of them is still to come (then new ones; a read dropped
        unread, by an error, frees them). Pinned memory is slow to make and, on CUDA, to free
        (that waits for the whole device).
        """
        if self._counts_reader is not None and self._counts_reader() is not None:
            return self.pinned((words,), np.uint32), False
        if self._counts_host is None or self._counts_host.size < words:
            self._counts_host = self.pinned((max(words, 4096),), np.uint32)
        return self._counts_host[:words], True

    def render_sharp(self, plan: Plan, camera: Camera, image: OnDevice, out: Region,
                     into: tuple[Slots, int] | None = None) -> OnDevice:
        """The sharp reference as the output holds it, rendered on the device.

        As ``gpu_blur.pipeline.render_sharp`` on the host: sRGB values re-toned by the finish
        pass's device functions when the plan re-tones, linear and clipped without the tone
        stage, quantized when the plan quantizes.

        Args:
            plan: the sample's plan.
            camera: its camera (``output.crf = "camera"``: its fitted response).
            image: the sharp image as stored on the device, ``H x W x 3``: ``dtype`` uint8 or
                uint16 (codes, divided on the device as ``linearize`` divides them), or None or
                the compute type (sRGB values).
            out: the region of ``image`` to render (the output crop: the image less
                ``output.crop`` pixels on every side).
            into: (a batch buffer, a slot): write the result there (in place where the
                language has views of a buffer, else copied in), else into a new buffer.

        Returns:
            A new ``out.h x out.w x 3`` image of the compute type on the device.

        Raises:
            ValueError: when ``out`` does not lie within the image, or for an image of another
                dtype.
        """
        count = out.h * out.w * 3
        result = None if into is None else self._in_slot(*into, count)
        in_place = result is not None
        if result is None:
            result = self._empty(count)
        self._render_sharp(plan, camera, image, 1, 0, out, result, 0)
        if into is not None and not in_place:
            self._copy(into[0].buffer, result, count, into[1] * into[0].stride)
        return OnDevice(result, (out.h, out.w, 3), self._fetch)

    def render_sharp_batch(self, plans: Sequence[Plan], camera: Camera,
                           images: Sequence[OnDevice], out: Region, into: Slots) -> None:
        """:meth:`render_sharp` of every sample b's ``images[b]`` into slot b of ``into``.

        One launch for the batch where the images lie evenly spaced in one device buffer
        (:meth:`spaced`: a torch or CuPy batch on a Warp device) and the plans render the
        sharp image alike; else one launch per sample.
        """
        spaced = self.spaced(images)
        first = self._of_plan(plans[0], camera)
        alike = all(self._renders_like(first, self._of_plan(p, camera)) for p in plans[1:])
        if spaced is None or not alike:
            for b, (p, image) in enumerate(zip(plans, images, strict=True)):
                self.render_sharp(p, camera, image, out, into=(into, b))
            return
        if into.count < len(images) or into.stride < out.h * out.w * 3:
            raise ValueError(f"render_sharp_batch: {into.count} slot(s) of {into.stride} "
                             f"values for {len(images)} outputs of {out.h} x {out.w} x 3 (a "
                             "gpu_blur bug: please report it)")
        whole = OnDevice(spaced[0], images[0].shape, self._fetch, images[0].dtype)
        self._render_sharp(plans[0], camera, whole, len(images), spaced[1], out, into.buffer,
                           into.stride)

    @staticmethod
    def _renders_like(one: dict, other: dict) -> bool:
        """Whether two plans' derived values (:meth:`_of_plan`) render sharp images alike."""
        return one["sharp"] == other["sharp"] and all(
            np.array_equal(a, b) for a, b in zip(one["curves"], other["curves"], strict=True))

    def _render_sharp(self, plan: Plan, camera: Camera, image: OnDevice, samples: int,
                      image_stride: int, out: Region, result, out_stride: int) -> None:
        """The sharp-reference launch over ``samples`` images.

        Image b starts ``image_stride`` values after image b - 1 in ``image``; its ``out``
        region goes to ``result``, ``out_stride`` values after output b - 1's.
        """
        source = self._stored_dtype(image)
        h, w = image.shape[-3:-1]
        if not (0 <= out.y0 and 0 <= out.x0 and out.y0 + out.h <= h and out.x0 + out.w <= w
                and out.h > 0 and out.w > 0):
            raise ValueError(f"render_sharp: the output region {out.h} x {out.w} at (row "
                             f"{out.y0}, column {out.x0}) does not lie within the {h} x {w} "
                             "image: pass a region of the image (e.g. the image less "
                             "output.crop pixels on every side)")
        derived = self._of_plan(plan, camera)
        k = self._input_kernels(derived["sharp"], source)
        polynomial, table = derived["curves"]
        curves = (self._constant(polynomial), Arg("int", polynomial.size, extent=True),
                  self._constant(table), Arg("int", table.size, extent=True))
        grid = (samples, out.h, out.w)
        with self._timed():
            if source == self.np_real:
                self._launch(k, "render_sharp", grid, image.data, *_index(w, image_stride),
                             *_out_geometry(out), *curves, result, *_index(out_stride))
                return
            # codes: the curve of every code (one pixel per 3 codes; once per build and
            # curve), then a gather, as the host renders them (pipeline.render_sharp)
            key = (derived["sharp"], polynomial.tobytes(), table.size, source.str)
            if key not in self._sharp_tables:
                top = np.iinfo(source).max
                every = np.minimum(np.arange(-(-(top + 1) // 3) * 3), top)
                codes = Region.whole(1, every.size // 3)
                rendered = self._empty(every.size)
                self._launch(k, "render_sharp", (1, *codes.shape),
                             self._constant(every, source), *_index(codes.w, 0),
                             *_out_geometry(codes), *curves, rendered, *_index(0))
                self._sharp_tables[key] = rendered
            self._launch(k, "gather_codes", grid, image.data, *_index(w, image_stride),
                         *_out_geometry(out), self._sharp_tables[key], result,
                         *_index(out_stride))


def average_args(stack, count: int, n: int, sums, first: bool, mean_of: int, linear, sat_mask,
                 table) -> tuple:
    """The average's summing kernel's arguments, in order.

    ``count`` frames of ``n`` values each from ``stack`` join ``sums``; ``mean_of`` > 0 writes
    the means instead.
    """
    return (stack, Arg("uint", count), Arg("index", n), *sums, Arg("int", int(first)),
            Arg("uint", mean_of), linear, sat_mask, table)


#: The columns of :meth:`KernelBackend.inspect`'s counts, in order (kernels/opencl/inputs.cl,
#: gpu_blur/warp_kernels/inputs.py write them in this order).
INSPECT_COLUMNS = ("nan", "infinite", "below_0", "above_1", "clip_level", "above_0")

#: Work items of one inspect launch: enough for a GPU's memory system; each counts a strided
#: share of the image in registers and adds it once per non-zero count (no atomic per value).
INSPECT_ITEMS = 65536


def inspect_items(n: int, images: int = 1) -> int:
    """Work items per image for inspecting ``images`` images of ``n`` values in one launch.

    :data:`INSPECT_ITEMS` shared by the images (each item adds its counts to its image's row
    with atomics, so more items per row cost more than they gain: on one H200 16 RealBlur-J
    images took 0.128 ms a sample with 65,536 items each; sharing them, the batch's device
    time is within 0.005 ms a sample of counting the whole batch as one image, 0.039), fewer
    for small images, and enough that no item counts 2^32 values (its counts are 32-bit).
    """
    return max(min(n, INSPECT_ITEMS // images), -(-n // (2**32 - 1)), 1)


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
