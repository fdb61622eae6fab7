"""``output.png = "fast"`` streams made on the device, byte for byte what the host writes.

A finished batch's 8-bit codes are on the device already: :class:`DeviceDeflate` Sub-filters
and deflates them there (gpu_blur.warp_kernels.deflate, zlib's ``Z_HUFFMAN_ONLY`` blocks
reproduced) and brings back each image's zlib stream, so an I/O thread only checksums the
chunk and writes the file (:func:`gpu_blur.png_codecs.png_file`), instead of spending a
core's 45 ms deflating a 1920 x 1200 image (an H200 host's Xeon; bench/png_device.py: the
kernels take 0.4 ms an image in batches of 16). The stream is
:func:`gpu_blur.png_codecs.huffman_zlib`'s of the same rows, bit for bit
(tests/io/test_png_device.py), so the files are the same whichever side wrote them.

Warp devices only (CUDA, and Warp's CPU device in tests); 8-bit images of 1 to 4 channels.
"""

from __future__ import annotations

import contextlib

import numpy as np

from gpu_blur import notices
from gpu_blur.warp_kernels import deflate as k

__all__ = ["DeviceDeflate", "DevicePngs", "PendingStream", "ZLIB_HEADER", "blocks_of",
           "stream_parts", "words_for"]

#: The two bytes leading every stream of huffman_zlib: deflate, a 32 KiB window, level
#: flags 0 (RFC 1950, 2.2; zlib writes 0 for level 1 and for Z_HUFFMAN_ONLY).
ZLIB_HEADER = b"\x78\x01"
#: The code-length symbols' order in a dynamic block's header (RFC 1951, 3.2.7).
_ORDER = (16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15)


def words_for(height: int, width: int, channels: int) -> int:
    """The 32-bit words an image's deflate data may take, at most.

    A block is never larger stored than its literals and 5 bytes (zlib stores a block that
    its codes would make larger).
    """
    literals = height * (1 + width * channels)
    return (literals + 5 * blocks_of(literals) + 8) // 4 + 1


def blocks_of(literals: int) -> int:
    """The deflate blocks zlib writes for ``literals`` bytes.

    One per 16,383, and a last one with the rest, which is empty when they divide evenly
    (``deflate_huff`` ends the stream with a block).
    """
    return literals // k.BLOCK + 1


class DeviceDeflate:
    """zlib streams of images' Sub-filtered rows, made on one Warp device.

    Args:
        device: the Warp device (``"cuda:0"``, ``"cpu"``) the codes are on.
    """

    def __init__(self, device):
        import warp as wp

        self.wp, self.device = wp, wp.get_device(device)
        self._scratch: tuple | None = None
        self._order = wp.array(np.array(_ORDER, np.int32), dtype=wp.int32, device=self.device)
        self._fixed = wp.array(k.static_codes(), dtype=wp.int32, device=self.device)

    def _arrays(self, images: int, blocks: int, words: int) -> dict:
        """Scratch for ``images`` images of ``blocks`` blocks and ``words`` output words.

        Kept for later calls of the same image size and at most as many images (a batch's
        last, smaller part among them).
        """
        key = (blocks, words)
        if (self._scratch is None or self._scratch[0] != key
                or self._scratch[1] < images):
            self._scratch = None  # freed before the new one is made
            wp, n = self.wp, images * blocks

            def new(shape, dtype):
                return wp.empty(shape, dtype=dtype, device=self.device)

            self._scratch = (key, images, {
                "counts": new((n, 256), wp.int32),
                "sums": new((n, k.SEGMENTS, 2), wp.int64),
                "trees": [new((n * k.TREES, k.HEAP), wp.int32) for _ in range(5)],
                "bit_count": new((n * k.TREES, 16), wp.int32),
                "code": new((n * k.TREES, k.HEAP), wp.int32),
                "sizes": new((n, 2), wp.int64),
                "header": new((n, k.HEADER_WORDS), wp.uint32),
                "info": new((n, k.BLOCK_COLUMNS), wp.int64),
                "offsets": new((n, k.SEGMENTS), wp.int32),
                "out": new((images, words), wp.uint32),
                "streams": new((images, 2), wp.int64),
            })
        return self._scratch[2]

    def deflate(self, codes, images: int, height: int, width: int, channels: int
                ) -> tuple[object, object]:
        """Queue the streams of ``images`` images in ``codes`` on the device's stream.

        ``codes``: a flat ``wp.array`` of uint8, the images one after another, each
        ``height x width x channels``, row-major.

        Returns:
            (words, streams), device arrays: ``images x W`` uint32, image i's deflate data
            (its first ``streams[i, 0]`` bytes, without zlib's header and Adler-32), and
            ``images x 2`` int64: the bytes, the Adler-32 of its filtered rows.
        """
        wp = self.wp
        stride = 1 + width * channels
        literals = height * stride
        pixels = height * width * channels
        blocks = blocks_of(literals)
        s = self._arrays(images, blocks, words_for(height, width, channels))
        freq, dad, lengths, depth, heap = s["trees"]
        out, streams = s["out"][:images], s["streams"][:images]
        s["counts"].zero_()
        out.zero_()
        shape = (images, blocks, k.SEGMENTS)
        common = [codes, pixels, stride, channels, literals, blocks]
        wp.launch(k.count_kernel, dim=shape, inputs=[*common, s["counts"], s["sums"]],
                  device=self.device)
        wp.launch(k.trees_kernel, dim=(images, blocks),
                  inputs=[s["counts"], literals, blocks, self._order, freq, dad, lengths, depth,
                          heap, s["bit_count"], s["code"], s["sizes"], s["header"],
                          self._fixed, s["info"]], device=self.device)
        wp.launch(k.sizes_kernel, dim=shape,
                  inputs=[*common, s["info"], s["code"], lengths, self._fixed, s["offsets"]],
                  device=self.device)
        wp.launch(k.offsets_kernel, dim=images * blocks,
                  inputs=[s["offsets"], s["sums"], s["info"]], device=self.device)
        wp.launch(k.layout_kernel, dim=images, inputs=[literals, blocks, s["info"], streams],
                  device=self.device)
        wp.launch(k.write_kernel, dim=(images, blocks, k.SEGMENTS + 1),
                  inputs=[*common, s["info"], s["code"], lengths, self._fixed, s["offsets"],
                          s["header"], out], device=self.device)
        return out, streams

    def streams(self, codes, images: int, height: int, width: int, channels: int
                ) -> list[bytes]:
        """Each image's zlib stream, as :func:`gpu_blur.png_codecs.huffman_zlib` writes it."""
        words, streams = self.deflate(codes, images, height, width, channels)
        sizes = streams.numpy()
        data = words.numpy()
        return [stream_bytes(data[i], sizes[i]) for i in range(images)]


def stream_parts(words: np.ndarray, stream: np.ndarray) -> tuple:
    """One image's zlib stream, in three parts, from its rows of :meth:`DeviceDeflate.deflate`.

    ``words``: its row of the data (a view: the stream's middle part stays over it).
    """
    size, adler = int(stream[0]), int(stream[1])
    return ZLIB_HEADER, words.view(np.uint8)[:size].data, adler.to_bytes(4, "big")


def stream_bytes(words: np.ndarray, stream: np.ndarray) -> bytes:
    """One image's zlib stream from its rows of :meth:`DeviceDeflate.deflate`'s results."""
    return b"".join(stream_parts(words, stream))


class DevicePngs:
    """A batch's PNG streams deflated on the device as its codes leave it.

    For a Synthesizer on a Warp CUDA device whose set is written as 8-bit PNG files with
    ``output.png = "fast"``: :meth:`queue` (as each image stack's codes are exported) copies
    the codes aside and queues their deflate, and the copies of the streams into page-locked
    blocks ``lend`` gives, on a CUDA stream of its own, so the next batch's passes run beside
    it and the batch is not waited for on its account; :meth:`take` gives each sample's
    streams, which wait for their deflate when first read (:class:`PendingStream`);
    :meth:`start` begins each batch, so a failed batch's streams go to no later one. Where
    ``lend`` gives nothing (past its limit) those images get none, and the host encodes them;
    where the deflate itself fails (a kernel build), a notice says so and the host encodes
    every file from then on.
    On Warp's CPU device (tests) everything runs in queue order.

    Args:
        backend: the Warp backend (its ``wp_device``).
        lend: ``lend([(shape, dtype), ...])``: page-locked arrays, or None
            (:meth:`gpu_blur.staging.LentResults.take`).
    """

    def __init__(self, backend, lend):
        import warp as wp

        self.device = wp.get_device(backend.wp_device)
        self._lend = lend
        self._deflate = DeviceDeflate(self.device)
        self._stream = wp.Stream(self.device) if self.device.is_cuda else None
        #: name -> (the codes copied aside, the event after their last deflate's copies)
        self._aside: dict[str, tuple] = {}
        self._queued: list[tuple[str, int, tuple | None, object]] = []
        #: why the device's deflate failed (then the host encodes every file), or None
        self.failed: str | None = None

    @staticmethod
    def for_backend(backend, scene) -> bool:
        """Whether a batch of ``scene`` on ``backend`` gets its PNGs deflated on the device."""
        wp_device = getattr(backend, "wp_device", None)
        if wp_device is None or scene.output.bits != 8 or scene.output.png != "fast":
            return False
        import warp as wp

        return wp.get_device(wp_device).is_cuda

    def start(self) -> None:
        """A new batch: what an earlier one queued and never took (it failed) is dropped."""
        self._queued = []

    def queue(self, name: str, codes, count: int) -> None:
        """Deflate ``count`` images of ``codes`` (an OnDevice, ``count x h x w x c`` uint8).

        ``codes`` is read on the device's current stream, in queue order: it may be written
        again by what is queued after this call.
        """
        height, width, channels = codes.shape[-3:]
        into = None if self.failed else self._lend(
            [((count, words_for(height, width, channels)), np.uint32), ((count, 2), np.int64)])
        done = None
        if into is not None:
            try:
                done = self._deflated(name, codes.data, count, (height, width, channels), into)
            except Exception as error:  # a kernel that does not build or launch here
                into, self.failed = None, f"{type(error).__name__}: {error}"
                if notices.verbosity() >= notices.NORMAL:
                    notices.say(f"PNG deflate on {self.device}: {self.failed}; the host "
                                "encodes the files from here on (the same bytes)")
        self._queued.append((name, count, into, done))

    def _deflated(self, name: str, codes, count: int, shape: tuple, into: list):
        """:meth:`queue`'s deflate and copies into ``into``; the event after them, or None."""
        import warp as wp

        source, done = codes, None
        if self._stream is not None:
            source = self._aside_copy(name, codes, count * int(np.prod(shape)))
        on_stream = (contextlib.nullcontext() if self._stream is None
                     else wp.ScopedStream(self._stream))
        with on_stream:
            words, streams = self._deflate.deflate(source, count, *shape)
            for host, device in zip(into, (words, streams), strict=True):
                view = wp.array(ptr=host.ctypes.data, dtype=device.dtype, shape=device.shape,
                                device="cpu")
                wp.copy(view, device)
            if self._stream is not None:
                done = self._stream.record_event()
                self._aside[name] = (self._aside[name][0], done)
        return done

    def _aside_copy(self, name: str, codes, size: int):
        """``size`` codes copied aside, on the current stream, into ``name``'s device buffer.

        The deflate stream waits for the copy; the copy for the buffer's last deflate.
        """
        import warp as wp

        compute = wp.get_stream(self.device)
        held, last = self._aside.get(name, (None, None))
        if last is not None:
            if held.size < size:  # dropped below: nothing may read it any more
                wp.synchronize_event(last)
            else:
                compute.wait_event(last)  # its last deflate has read it
        if held is None or held.size < size:
            held = wp.empty(size, dtype=wp.uint8, device=self.device)
        wp.copy(held, codes, count=size)
        self._stream.wait_event(compute.record_event())
        self._aside[name] = (held, last)
        return held

    def take(self) -> list[dict[str, PendingStream]]:
        """Each sample's streams, ``{name: stream}``, in batch order.

        For the images :meth:`queue` queued since the last call; an image without a stream
        (nothing lent for it) is absent from its sample's dictionary.
        """
        samples: dict[str, list] = {}
        for name, count, into, done in self._queued:
            made = samples.setdefault(name, [])
            made += ([None] * count if into is None
                     else [PendingStream(into[0][i], into[1][i], done) for i in range(count)])
        self._queued = []
        count = max((len(v) for v in samples.values()), default=0)
        return [{name: made[b] for name, made in samples.items() if made[b] is not None}
                for b in range(count)]


class PendingStream:
    """An image's zlib stream from the device, in parts, once its deflate is done.

    Iterating waits for the Warp event ``done`` (None: done already; the wait releases the
    GIL), then gives :func:`stream_parts` of the image's rows of the page-locked results.
    """

    __slots__ = ("words", "sizes", "done")

    def __init__(self, words: np.ndarray, sizes: np.ndarray, done=None):
        self.words, self.sizes, self.done = words, sizes, done

    def __iter__(self):
        if self.done is not None:
            import warp as wp

            wp.synchronize_event(self.done)
        return iter(stream_parts(self.words, self.sizes))
