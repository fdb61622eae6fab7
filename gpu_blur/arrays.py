"""The array types a batch comes in and goes back as: numpy, torch, CuPy and ``wp.array``.

:class:`gpu_blur.Synthesizer` takes a batch in any of them and returns its results in the same
type on the same device (torch in, torch out). Arrays on a CUDA device reach a Warp backend on
that device through DLPack without a copy; every other pairing goes through host memory.
torch, CuPy and Warp are imported only when an array of theirs is passed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DTYPES", "WarpFrames", "as_real", "as_warp", "channels_first", "channels_last",
           "check_dense", "cuda_device", "dtype_name", "from_numpy", "from_warp", "library",
           "on_warp_device", "producer_stream", "to_numpy", "view_at", "warp_samples"]

#: Input dtypes a batch may have (floats are sRGB values in [0, 1]).
DTYPES = ("uint8", "uint16", "float16", "float32", "float64")


class WarpFrames:
    """A B x F x H x W x C batch of frames in one flat ``wp.array``: a Warp batch.

    Warp's arrays stop at four dimensions; ``generate`` puts batches of frames together on
    its device (:class:`~gpu_blur.staging.DeviceFrames`) and hands them over in this, which
    ``Synthesizer`` reads as it reads a ``wp.array`` (:func:`warp_samples` views).
    """

    is_contiguous = True

    def __init__(self, flat, shape: tuple[int, ...]):
        self.shape, self._flat = tuple(shape), flat

    @property
    def ndim(self) -> int:
        """5."""
        return len(self.shape)

    @property
    def dtype(self):
        """The Warp dtype of its values."""
        return self._flat.dtype

    @property
    def device(self):
        """The Warp device it lies on."""
        return self._flat.device

    def flatten(self):
        """The flat ``wp.array`` (no copy), as ``wp.array.flatten`` of a contiguous one."""
        return self._flat


def library(x) -> str:
    """Which library an array belongs to: ``numpy``, ``torch``, ``cupy`` or ``warp``.

    Raises:
        TypeError: for anything else, naming its type.
    """
    if isinstance(x, np.ndarray):
        return "numpy"
    if isinstance(x, WarpFrames):
        return "warp"
    module = type(x).__module__.split(".")[0]
    if module in ("torch", "cupy", "warp"):
        return module
    raise TypeError(f"a batch must be a numpy array, a torch tensor, a CuPy array or a "
                    f"wp.array; got {type(x).__name__}")


def dtype_name(x) -> str:
    """The array's dtype as numpy names it (``uint8``, ``float32``, ...)."""
    if library(x) == "warp":
        import warp as wp

        return np.dtype(wp.dtype_to_numpy(x.dtype)).name
    return str(x.dtype).removeprefix("torch.")


def check_dense(x, key: str) -> None:
    """Refuse a torch tensor that is not plain values: nested, sparse (or other layout), meta.

    Raises:
        ValueError: naming ``key``, the layout or device, and the fix.
    """
    if type(x).__module__.split(".")[0] != "torch":  # anything else passes
        return
    import torch

    if x.is_nested:
        raise ValueError(f"{key}: a nested tensor; a batch is one array: stack same-size "
                         "samples (torch.stack)")
    if x.layout != torch.strided:
        raise ValueError(f"{key}: a {x.layout} tensor; pass a dense one (x.to_dense())")
    if x.device.type == "meta":
        raise ValueError(f"{key}: a tensor on the meta device holds no values; pass one on "
                         "the CPU or a CUDA device")


def cuda_device(x) -> int | None:
    """The CUDA device ordinal an array lives on, None for host memory."""
    lib = library(x)
    if lib == "torch":
        return x.device.index if x.device.type == "cuda" else None
    if lib == "cupy":
        return x.device.id
    if lib == "warp":
        return x.device.ordinal if x.device.is_cuda else None
    return None


def channels_last(x, lib: str):
    """A channels-first batch as channels-last, contiguous, on its own device.

    ``B x 3 x H x W`` becomes ``B x H x W x 3``; frame stacks ``B x F x 3 x H x W`` become
    ``B x F x H x W x 3``.
    """
    if lib == "torch":
        return x.movedim(-3, -1).contiguous()
    if lib == "warp":
        raise ValueError("channels_first is for torch, numpy and CuPy batches; a wp.array "
                         "batch must be B x H x W x 3 (or B x F x H x W x 3)")
    module = np if lib == "numpy" else __import__("cupy")
    return module.ascontiguousarray(module.moveaxis(x, -3, -1))


def channels_first(x, lib: str):
    """A ``B x H x W x 3`` result as a ``B x 3 x H x W`` view."""
    if lib == "torch":
        return x.movedim(-1, -3)
    module = np if lib == "numpy" else __import__("cupy")
    return module.moveaxis(x, -1, -3)


def as_real(x, lib: str, real: str):
    """A float batch as ``real`` (``float32``, ``float64``), converted on its own device."""
    if lib == "torch":
        import torch

        return x.to(getattr(torch, real))
    if lib == "warp":
        raise ValueError(f"a wp.array batch must hold uint8, uint16 or {real} values (the "
                         f"backend's precision); got {dtype_name(x)}")
    return x.astype(real)


def to_numpy(x, lib: str) -> np.ndarray:
    """A host copy (or view, for host memory) of an array."""
    if lib == "numpy":
        return x
    if lib == "torch":
        return x.detach().cpu().numpy()
    if lib == "cupy":
        return x.get()
    return x.numpy()


def on_warp_device(x, lib: str, device: str) -> bool:
    """Whether ``x`` lives on Warp device ``device`` (a Warp backend takes it without a copy)."""
    import warp as wp

    if lib == "warp":
        return str(x.device) == str(wp.get_device(device))
    ordinal = cuda_device(x)
    return ordinal is not None and f"cuda:{ordinal}" == str(wp.get_device(device))


def as_warp(x, lib: str):
    """A ``wp.array`` view of an array on a CUDA device (at most 4 dimensions, Warp's limit)."""
    import warp as wp

    if lib == "warp":
        return x
    if lib == "torch" and dtype_name(x) != "uint16":  # from_torch knows no uint16
        return wp.from_torch(x)
    return wp.from_dlpack(x)


def warp_samples(x, lib: str) -> list | None:
    """``x[b]`` for every b as ``wp.array`` views made from addresses, else None.

    None unless ``x`` is contiguous on a CUDA device (or a ``wp.array``). One DLPack
    hand-over for the batch instead of one per sample (on the 2-core CI CPU a
    ``wp.from_torch`` took 26 us, a view from an address 5). Each view keeps the batch's
    ``wp.array`` alive.
    """
    import warp as wp

    contiguous = {"torch": lambda: x.is_contiguous(), "warp": lambda: x.is_contiguous,
                  "cupy": lambda: x.flags.c_contiguous}[lib]()
    if not contiguous or x.shape[0] == 0:
        return None
    flat = as_warp(x.reshape(-1) if lib != "warp" else x.flatten(), lib)
    shape = tuple(x.shape[1:])
    step = int(np.prod(shape)) * wp.types.type_size_in_bytes(flat.dtype)
    return [view_at(flat.ptr + b * step, flat.dtype, shape, [flat])
            for b in range(x.shape[0])]


def view_at(address: int, dtype, shape, owners: list):
    """A ``wp.array`` of ``shape`` at ``address``, in memory the ``owners`` hold.

    On ``owners[0]``'s device; the ``owners`` are ``wp.array``: a view by address owns
    nothing, so it keeps them alive.
    """
    import warp as wp

    view = wp.array(ptr=address, dtype=dtype, shape=shape, device=owners[0].device)
    view._gb_sources = owners
    return view


def producer_stream(x, lib: str):
    """The ``wp.Stream`` that work writing ``x`` is queued on, or None.

    torch's or CuPy's current stream on ``x``'s device; None for ``wp.array`` (queued on
    Warp's own streams). A Warp stream reading ``x`` waits for it first: a non-default
    torch or CuPy stream (a prefetcher's) does not synchronize with Warp's streams by itself.
    """
    import warp as wp

    if lib == "torch":
        import torch

        return wp.stream_from_torch(torch.cuda.current_stream(x.device))
    if lib == "cupy":
        import cupy

        with cupy.cuda.Device(x.device.id):
            stream = cupy.cuda.get_current_stream()
        return wp.Stream(wp.get_cuda_device(x.device.id), cuda_stream=stream.ptr)
    return None


def from_warp(out, lib: str, like):
    """A ``wp.array`` result as the input's type (no copy for torch and CuPy)."""
    import warp as wp

    if lib == "torch":
        return wp.to_torch(out)
    if lib == "cupy":
        import cupy

        return cupy.from_dlpack(out)
    return out


def from_numpy(out: np.ndarray, lib: str, like):
    """A host result as the input's type, on the input's device."""
    if lib == "numpy":
        return out
    if lib == "torch":
        import torch

        return torch.from_numpy(out).to(like.device)
    if lib == "cupy":
        import cupy

        with cupy.cuda.Device(like.device.id):
            return cupy.asarray(out)
    import warp as wp

    return wp.array(out, device=like.device)
