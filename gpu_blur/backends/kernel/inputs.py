"""Inputs on the device for the kernel backend: their checks, codes and the sharp reference.

:meth:`Inputs.inspect` counts what the input checks need with no value of an image reaching
the host; :meth:`Inputs.to_codes` makes an output's 8/16-bit codes on the device;
:meth:`Inputs.render_sharp` renders the sharp reference with the finish pass's device
functions.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence

import numpy as np

from gpu_blur.backends import OnDevice
from gpu_blur.backends.kernel.buffers import Slots
from gpu_blur.backends.kernel.config import Arg, PassConfig, _index, _out_geometry
from gpu_blur.cameras import Camera
from gpu_blur.planning import Plan
from gpu_blur.reference.output import code_dtype
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

__all__ = ["INSPECT_COLUMNS", "INSPECT_ITEMS", "Inputs", "inspect_items"]

#: The columns of :meth:`KernelBackend.inspect`'s counts, in order (kernels/opencl/inputs.cl,
#: gpu_blur/warp_kernels/inputs.py write them in this order).
INSPECT_COLUMNS = ("nan", "infinite", "below_0", "above_1", "clip_level", "above_0")

#: Work items of one inspect launch: enough for a GPU's memory system; each counts a strided
#: share of the image in registers and adds it once per non-zero count (no atomic per value).
INSPECT_ITEMS = 65536


def inspect_items(n: int, images: int = 1) -> int:
    """Work items per image for inspecting ``images`` images of ``n`` values in one launch.

    :data:`INSPECT_ITEMS` shared by the images (each item adds its counts to its image's row
    with atomics, so more items per row cost more than they gain: see
    docs/performance.md#input-checks), fewer for small images, and enough that no item counts
    2^32 values (its counts are 32-bit).
    """
    return max(min(n, INSPECT_ITEMS // images), -(-n // (2**32 - 1)), 1)


class Inputs:
    """Input images on the device of :class:`~gpu_blur.backends.kernel.KernelBackend`.

    One of its parts: checks (``inspect``), codes (``to_codes``) and the sharp reference
    (``render_sharp``).
    """

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
            for values, the top code 2^bits - 1 for codes:
            ``gpu_blur.synthesis.inputs.reaches_clip_level``), above 0 (a mask's "anything to
            saturate").
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
            for run, spaced in self._spaced_runs(images):
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
        buffer for every batch costs more than its codes' download
        (docs/performance.md#codes-buffer).
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

        As ``synthesis.host.render_sharp`` on the host: sRGB values re-toned by the finish
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
            # curve), then a gather, as the host renders them (synthesis.host.render_sharp)
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
