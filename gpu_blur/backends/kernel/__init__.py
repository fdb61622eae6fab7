"""The kernel backend written once: the plan's passes as launches, for any kernel language.

:class:`KernelBackend` holds the host logic of the three passes (which kernels run, in what
order, on which buffers, with which arguments); :mod:`gpu_blur.backends.opencl` and
:mod:`gpu_blur.backends.warp` subclass it and keep only what differs: devices, buffers,
queues or streams, launching, and rendering a :class:`PassConfig` into ``-D`` defines or Warp
static flags.

Its parts, a module each (``KernelBackend`` joins their classes):

* :mod:`~gpu_blur.backends.kernel.config`: :func:`pass_config`, (plan, pass) -> the settings a
  pass's kernels are built with, and the ``*_args`` functions, each kernel's ordered arguments
  as typed :class:`Arg` values;
* :mod:`~gpu_blur.backends.kernel.buffers`: device buffers, batch :class:`Slots`, puts and
  pinned staging;
* :mod:`~gpu_blur.backends.kernel.accumulate`: pass 1 of one sample, every blur mode;
* :mod:`~gpu_blur.backends.kernel.batch`: a batch's accumulate, to_raw and finish passes;
* :mod:`~gpu_blur.backends.kernel.inputs`: input checks (``inspect``), codes (``to_codes``)
  and the sharp reference (``render_sharp``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur.backends.kernel.accumulate import Accumulate
from gpu_blur.backends.kernel.batch import Batch
from gpu_blur.backends.kernel.buffers import Buffers, Slots
from gpu_blur.backends.kernel.config import (
    Arg,
    Drawn,
    PassConfig,
    average_args,
    finish_args,
    pass_config,
    retone_curves,
    sample_tables,
    sharp_config,
    source_dtype,
    stage_values,
    to_raw_args,
)
from gpu_blur.backends.kernel.inputs import INSPECT_COLUMNS, INSPECT_ITEMS, Inputs, inspect_items
from gpu_blur.cameras import Camera
from gpu_blur.planning import Pass, Plan
from gpu_blur.tiling import Region

__all__ = [
    "INSPECT_COLUMNS",
    "INSPECT_ITEMS",
    "Arg",
    "Drawn",
    "KernelBackend",
    "PassConfig",
    "Slots",
    "average_args",
    "finish_args",
    "inspect_items",
    "pass_config",
    "retone_curves",
    "sample_tables",
    "sharp_config",
    "source_dtype",
    "stage_values",
    "to_raw_args",
]


class KernelBackend(Inputs, Batch, Accumulate, Buffers):
    """The passes of a plan as kernel launches (see :mod:`gpu_blur.backends`).

    A subclass sets ``name``, ``precision``, ``device``, ``np_real`` (the compute type as a
    numpy dtype) and ``position_dtype`` (float64 where the device has it), and supplies the
    primitives: buffers (``_upload``, ``_empty``, ``_zeros``, ``_write``, ``_fetch``: see
    :class:`~gpu_blur.backends.kernel.buffers.Buffers`), kernels (``_pass_kernels``,
    ``_launch``, ``_timed``, below; ``_input_kernels``) and ``_frame_stacks``.
    """

    name: str
    precision: str
    device: str
    device_arrays = False
    #: Whether each pass waits for its launches (its "kernels" time is then device time).
    #: False queues every launch back to back (a batch: :class:`gpu_blur.Synthesizer`, or a
    #: CUDA graph capture: bench/gpu_targets.py); timings then hold launch times only.
    sync_passes = True
    #: The Warp device (``cuda:0``, ``cpu``) on Warp; None elsewhere.
    wp_device: str | None = None

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

    def wait_for(self, stream) -> None:
        """Launches and copies queued from now on wait for the work queued on ``stream``.

        Only a backend with ``device_arrays`` (Warp) is handed a caller's stream.
        """
        raise NotImplementedError

    def hand_to(self, stream) -> None:
        """Work queued on ``stream`` from now on waits for what this backend queued so far.

        Only a backend with ``device_arrays`` (Warp) is handed a caller's stream.
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
