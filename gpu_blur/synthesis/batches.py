"""Batch input and output: array types, layouts, ``out=`` arrays, codes, the JPEG stage.

:class:`BatchIO` splits a batch (numpy, torch, CuPy or Warp arrays) into per-sample
:class:`~gpu_blur.synthesis.inputs.Inputs` and gives the results back as the batch's type,
layout and device, or in the caller's ``out=`` arrays. A torch batch of floats has its
values measured by torch where it lies (:meth:`BatchIO.value_ranges`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpu_blur import arrays
from gpu_blur.backends import Backend
from gpu_blur.outputs import jpeg_round_trip
from gpu_blur.planning import Plan, StageName
from gpu_blur.reference.output import code_dtype, to_integers
from gpu_blur.scene import Scene
from gpu_blur.synthesis.inputs import Inputs, ValueRanges, frame_count, kept_size
from gpu_blur.tiling import Region

__all__ = ["BatchIO", "jpeg_stage", "refuse_out_on_inputs"]

#: A batch's inputs by split's name -> their name in a sample's Inputs.
_INPUT_KEYS = {"batch": "frames", "mask": "mask", "sharp": "sharp"}


class BatchIO:
    """A Synthesizer's batches in and out: its scene, backend and array layout.

    Args:
        scene: the scene.
        runner: the backend.
        resident: whether batches run on the kernel backend's device
            (:class:`~gpu_blur.synthesis.resident.ResidentPath`).
        channels_first: batches come and go as B x 3 x H x W.
        with_mask: the saturation masks are returned too.
    """

    def __init__(self, scene: Scene, runner: Backend, resident: bool, channels_first: bool,
                 with_mask: bool):
        self.scene, self.runner, self.resident = scene, runner, resident
        self.channels_first, self.with_mask = channels_first, with_mask

    def result_dtypes(self, bits: int = 0) -> list:
        """The results' dtypes, blurred and sharp (and the mask, float32, ``with_mask``).

        ``bits`` 8 or 16: blurred and sharp as those codes' dtype; 0: float32.
        """
        code = code_dtype(bits) if bits else np.float32
        return [code, code, np.float32][:3 if self.with_mask else 2]

    def split(self, batch, mask, sharp, lib: str) -> list[Inputs]:
        """The batch as per-sample inputs: views of device arrays, else host arrays."""
        mode = self.scene.blur.mode
        given = {"batch": batch, "mask": mask, "sharp": sharp}
        if mode != "none":
            for key in ("mask", "sharp"):
                if given[key] is not None:
                    raise ValueError(f"{key}= is for blur.mode = none; this scene blurs "
                                     f"(blur.mode = {mode})")
        parts = {}
        for key, x in given.items():
            if x is None:
                continue
            if arrays.library(x) != lib:
                raise ValueError(f"{key} is a {arrays.library(x)} array but the batch is "
                                 f"{lib}: pass both as the same type")
            arrays.check_dense(x, key)
            parts[key] = self._normalized(x, key, lib, frames=key == "batch"
                                          and mode == "average")
        if mode == "average":
            frame_count(parts["batch"].shape[1], self.scene)
        count = parts["batch"].shape[0]
        for key, x in parts.items():
            if tuple(x.shape) != tuple(parts["batch"].shape):
                raise ValueError(f"{key} has shape {tuple(x.shape)} but the batch "
                                 f"{tuple(parts['batch'].shape)}: give one of each per sample")
        ranges = self.value_ranges(parts, lib)
        reached = self.reaches(parts["batch"], lib)
        samples = {key: (reached and arrays.warp_samples(x, lib))
                   or [self._taken(x[b], lib, reached) for b in range(count)]
                   for key, x in parts.items()}
        items = []
        for b in range(count):
            label = f"sample {b} of {count}: "
            x = samples["batch"][b]
            mine = None if ranges is None else (ranges, b)
            if mode == "average":
                names = {"frames": [f"frame {i}" for i in range(x.shape[0])]}
                items.append(Inputs(x, None, None, names, label, ranges=mine))
                continue
            m = samples["mask"][b] if "mask" in parts else None
            s = samples["sharp"][b] if "sharp" in parts else None
            name = "blurred" if mode == "none" else "photo"
            items.append(Inputs([x], m, s, {"frames": [name], "mask": "mask",
                                          "sharp": "sharp"}, label, ranges=mine))
        return items

    def value_ranges(self, parts: dict, lib: str) -> ValueRanges | None:
        """Each sample's lowest and highest value in a torch batch's float inputs, or None.

        ``parts``: split's inputs (``batch``, ``mask``, ``sharp``), laid out and of the
        backend's precision. Measured by torch where the batch lies, in place of the kernel
        backend's counts (:meth:`~gpu_blur.backends.ResidentBackend.inspect_queued`, atomics
        value by value), where that is cheaper:

        * on a CUDA device: ``torch.aminmax`` over each sample of each input (one reduction
          launch an input), the B x 2 results of all inputs copied at once to pinned host
          memory behind an event: nothing waits until the device path reads them, once the
          batch's passes are queued (one wait a batch, as for the counts);
        * in host memory, for a backend computing on the host (Warp's CPU device): numpy's
          SIMD min and max of each sample, read when the checks end.

        None for the host path (:func:`~gpu_blur.synthesis.inputs.checked_on_host` checks
        every input) and for other arrays: the kernel backend counts them.
        """
        if not self.resident or lib != "torch":
            return None
        floats = {_INPUT_KEYS[key]: x for key, x in parts.items() if x.dtype.is_floating_point}
        if not floats:
            return None
        device = next(iter(floats.values())).device
        if device.type == "cuda":
            return _torch_ranges(floats, device)
        if device.type == "cpu" and self.runner.wp_device == "cpu":
            return _host_ranges({key: arrays.to_numpy(x, lib) for key, x in floats.items()})
        return None

    def _normalized(self, x, key: str, lib: str, *, frames: bool):
        """One batch input checked for layout, channels-last, a kernel dtype, even size."""
        if self.channels_first:
            if x.ndim < 4 or x.shape[-3] != 3:
                raise ValueError(f"{key}: channels_first takes B x 3 x H x W (B x F x 3 x H x "
                                 f"W for frames); got shape {tuple(x.shape)}")
            x = arrays.channels_last(x, lib)
        want = 5 if frames else 4
        layout = "B x F x H x W x 3" if frames else "B x H x W x 3"
        if x.ndim != want or x.shape[-1] != 3 or 0 in tuple(x.shape):
            raise ValueError(f"{key}: blur.mode = {self.scene.blur.mode} takes {layout} "
                             f"batches; got shape {tuple(x.shape)}")
        dtype = arrays.dtype_name(x)
        if dtype not in arrays.DTYPES:
            raise ValueError(f"{key}: unsupported dtype {dtype}; use one of "
                             f"{', '.join(arrays.DTYPES)} (floats in [0, 1])")
        if dtype.startswith("float") and dtype != self.runner.precision and self.resident:
            x = arrays.as_real(x, lib, self.runner.precision)  # on the array's own device
        h, w = kept_size(self.scene, x.shape)
        if (h, w) != tuple(x.shape[-3:-1]):
            x = x[..., :h, :w, :]
            x = x.contiguous() if lib == "torch" else x
        return x

    def _taken(self, x, lib: str, reached: bool):
        """One sample's input as the backend takes it: a ``wp.array`` view, or host memory."""
        if reached:
            return arrays.as_warp(x, lib)
        host = arrays.to_numpy(x, lib)
        return host if self.resident else np.ascontiguousarray(host)

    def reaches(self, batch, lib: str) -> bool:
        """Whether the backend takes ``batch`` where it is (Warp, on its device): no copy."""
        return (self.resident and self.runner.device_arrays
                and arrays.on_warp_device(batch, lib, self.runner.wp_device))

    def outputs(self, count: int, region: Region, batch, lib: str, dtypes: list,
                given: Sequence | None = None) -> list:
        """The batch's output arrays, one per dtype: ``out=``'s (channels-last views), else new.

        On the device (Warp) in the compute type, where the batch lies there.
        """
        shape = (count, region.h, region.w, 3)
        if given is not None:
            return self.given_outputs(given, shape, dtypes)
        if self.reaches(batch, lib):  # new batch buffers as (count, h, w, 3) device arrays
            runner, values = self.runner, region.h * region.w * 3
            return [runner.device_array(runner.stacked(runner.slots(count, values), shape[1:]))
                    for _ in dtypes]
        return [np.empty(shape, dtype) for dtype in dtypes]

    def check_out(self, out, batch, lib: str) -> None:
        """Refuse ``out=`` for a batch whose results come back where it lives.

        ``out=`` takes numpy arrays, for numpy batches and for batches on the device this
        backend runs on (``wp.array``, a torch CUDA tensor Warp reaches): their results are
        copied into them.
        """
        if out is not None and lib != "numpy" and not self.reaches(batch, lib):
            raise ValueError(f"out= is for numpy batches and batches on the backend's device "
                             f"(the results of this {lib} batch are {lib} arrays made where "
                             "it lives); leave it out for this batch")

    def given_outputs(self, given: Sequence, shape: tuple, dtypes: list) -> list:
        """``out=``'s arrays checked against the results they take, as channels-last views."""
        n = len(dtypes)
        names = ("blurred", "sharp", "mask")[:n]
        if not isinstance(given, (list, tuple)) or len(given) != n:
            raise ValueError(f"out= takes {n} arrays, ({', '.join(names)})"
                             + ("" if self.with_mask else "; with_mask=True adds the mask"))
        want = (shape[0], 3, *shape[1:3]) if self.channels_first else shape
        views = []
        for name, array, dtype in zip(names, given, dtypes, strict=True):
            if (not isinstance(array, np.ndarray) or array.dtype != dtype
                    or array.shape != want or not array.flags.writeable):
                got = (f"a {type(array).__name__}" if not isinstance(array, np.ndarray) else
                       f"{array.dtype} {array.shape}"
                       + ("" if array.flags.writeable else ", read-only"))
                raise ValueError(f"out= {name}: needs a writeable {np.dtype(dtype).name} numpy "
                                 f"array of shape {want}; got {got}")
            if _self_overlapping(array):
                raise ValueError(f"out= {name}: its elements overlap (strides {array.strides}); "
                                 "results would overwrite each other: pass a plain array "
                                 "(np.empty)")
            for other, earlier in zip(names, views, strict=False):
                if _overlap(array, earlier):
                    raise ValueError(f"out= {name} shares memory with out= {other}; one result "
                                     "would overwrite the other: pass an array of its own for "
                                     "each")
            views.append(np.moveaxis(array, 1, -1) if self.channels_first else array)
        return views

    def returned(self, out, lib: str, like):
        """An output array as the batch's type and layout."""
        if isinstance(out, np.ndarray):
            result = arrays.from_numpy(out, lib, like)
        else:
            result = arrays.from_warp(out, lib, like)
        return arrays.channels_first(result, lib) if self.channels_first else result

    def codes_here(self, out: list, lib: str, given) -> list:
        """A batch's float blurred and sharp as their codes, made on the host.

        After the JPEG stage, and for batches run from host memory; into ``out=``'s arrays
        (checked here), else new ones. The mask as it is.
        """
        bits = self.scene.output.bits
        host = [x if isinstance(x, np.ndarray) else x.numpy() for x in out]
        made = [to_integers(x, bits) for x in host[:2]] + host[2:]
        if given is None:
            return made
        views = self.given_outputs(given, made[0].shape, self.result_dtypes(bits))
        for view, x in zip(views, made, strict=True):
            np.copyto(view, x)
        return views


def _torch_ranges(floats: dict, device) -> ValueRanges:
    """:class:`ValueRanges` of torch CUDA inputs ({key: B x ...}, of one float dtype).

    Queued on the device's current stream (the caller's, which wrote the batch): one
    ``aminmax`` per input, one stack (:func:`_torch_ends`), one copy to pinned host memory,
    one event that the read waits for.
    """
    import torch

    with torch.cuda.device(device):
        both = _torch_ends(floats)
        host = torch.empty(both.shape, dtype=both.dtype, pin_memory=True)
        host.copy_(both, non_blocking=True)
        done = torch.cuda.Event()
        done.record(torch.cuda.current_stream())

    def read() -> dict[str, np.ndarray]:
        done.synchronize()
        return _ends_by_key(host.numpy(), floats)

    return ValueRanges(floats, read)


def _torch_ends(floats: dict):
    """2K x B tensor: each of the K inputs' per-sample lowest values, then its highest.

    ``torch.aminmax`` over each sample ({key: B x ... tensor}), on the inputs' device; a NaN
    anywhere in a sample makes both of its ends NaN.
    """
    import torch

    return torch.stack([end for x in floats.values()
                        for end in torch.aminmax(x.reshape(x.shape[0], -1), dim=1)])


def _ends_by_key(ends: np.ndarray, keys) -> dict[str, np.ndarray]:
    """:func:`_torch_ends`' 2K x B values as {key: B x 2 float64 (lowest, highest)}."""
    values = np.asarray(ends, np.float64).reshape(len(keys), 2, -1)
    return {key: v.T for key, v in zip(keys, values, strict=True)}


def _host_ranges(floats: dict) -> ValueRanges:
    """:class:`ValueRanges` of inputs in host memory ({key: B x ... numpy array})."""
    def read() -> dict[str, np.ndarray]:
        return {key: np.array([(s.min(), s.max()) for s in x], np.float64)
                for key, x in floats.items()}

    return ValueRanges(floats, read)


def jpeg_stage(blurred, plans: list[Plan], params: list[dict]) -> None:
    """The JPEG stage, on the host, in place: a batch's blurred images (host or Warp array)."""
    chosen = [b for b, p in enumerate(plans) if p.kept(StageName.JPEG)]
    if not chosen:
        return
    host = blurred if isinstance(blurred, np.ndarray) else blurred.numpy()
    for b in chosen:
        host[b] = jpeg_round_trip(host[b], params[b]["jpeg_quality"])
    if host is not blurred:
        blurred.assign(host)


def refuse_out_on_inputs(out, inputs: dict) -> None:
    """Refuse an ``out=`` array that shares memory with an input (numpy batches)."""
    if not isinstance(out, (list, tuple)):
        return  # BatchIO.given_outputs says what out= takes
    for name, array in zip(("blurred", "sharp", "mask"), out, strict=False):
        for key, x in inputs.items():
            if isinstance(array, np.ndarray) and isinstance(x, np.ndarray) and _overlap(array, x):
                raise ValueError(f"out= {name} shares memory with the {key} input; results "
                                 "would overwrite the inputs they are made from: pass an "
                                 "array of its own")


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two numpy arrays share memory (a case too costly to decide counts as shared)."""
    try:
        return bool(np.shares_memory(a, b, max_work=1 << 20))
    except np.exceptions.TooHardError:
        return True


def _self_overlapping(a: np.ndarray) -> bool:
    """Whether elements of ``a`` may share bytes: an axis steps less than the axes within span."""
    span = a.itemsize
    for stride, n in sorted((abs(s), n) for s, n in zip(a.strides, a.shape, strict=True)
                            if n > 1):
        if stride < span:
            return True
        span += stride * (n - 1)
    return False
