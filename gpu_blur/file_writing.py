"""Writing files that appear complete or not at all: images (PNG, float TIFF) and text.

Each file is written to a new temporary file beside it (:func:`temporary_path`), then renamed
into place.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from gpu_blur.image_arrays import swap_red_blue
from gpu_blur.png_codecs import DEFAULT_PNG_MODE, PNG_MODES, encode_png, png_file
from gpu_blur.reference.output import code_dtype, to_integers

__all__ = ["ENCODED_BYTES", "EncodedImages", "encode_image", "temporary_path", "write_image",
           "write_new", "write_text", "write_whole"]

#: Bytes of encoded files :class:`EncodedImages` keeps at most: about 24 noisy 8-bit
#: 1920 x 1200 PNGs, more than the samples between two that share a sharp reference in
#: generate's order (consecutive windows, consecutive draws of a photo).
ENCODED_BYTES = 64 << 20


def temporary_path(path: Path, pid: int | None = None) -> Path:
    """Where ``path`` is written before it is renamed into place.

    ``.<name>.<pid>.part<suffix>`` beside it: the process id keeps two processes apart, the
    suffix keeps the format. Written with :func:`write_new`. ``pid``: the process whose name
    it bears, default this one's (a ``--devices`` worker writes under its driver's, the pid
    the set's lock file records, so a later run knows a file it left for the driver's).
    """
    return path.with_name(f".{path.name}.{os.getpid() if pid is None else pid}.part"
                          f"{path.suffix}")


def write_new(path: Path, data: bytes) -> Path:
    """``data`` as the new regular file ``path`` of its folder; returns ``path``.

    Whatever is there is removed first (a file a killed run left, or a link someone put
    there: the link itself, not what it points to); then ``O_EXCL | O_NOFOLLOW`` make sure
    the bytes land in a file made here, never through a link onto another file (Windows has
    no ``O_NOFOLLOW``; ``O_EXCL`` alone refuses a link there, and ``O_BINARY`` keeps the bytes).

    Raises:
        OSError: the file cannot be made (also when something appears there in between).
    """
    path.unlink(missing_ok=True)
    flags = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
    with os.fdopen(os.open(path, flags, 0o666), "wb") as f:
        f.write(data)
    return path


def write_whole(path: Path, data: bytes, check: Callable[[Path], None] | None = None,
                pid: int | None = None) -> None:
    """``data`` as the file ``path``, which appears complete or not at all.

    Written to :func:`temporary_path` (``pid`` as there), then renamed onto ``path``; the
    temporary file is removed on failure. ``check``: called with the temporary file before
    the rename; what it raises leaves ``path`` as it was.
    """
    tmp = temporary_path(path, pid)
    try:
        write_new(tmp, data)
        if check is not None:
            check(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_image(path: str | Path, image: np.ndarray, bits: int,
                png: str = DEFAULT_PNG_MODE) -> None:
    """Write an H x W x 3 RGB image in [0, 1]: PNG with 8/16 bits, or float32 TIFF for bits 0.

    ``png``: how a PNG is compressed, one of :data:`gpu_blur.png_codecs.PNG_MODES` (the
    scene's ``output.png``); every mode holds the same pixels.

    ``image`` may also be its codes already (:func:`to_integers`: uint8 for 8 bits, uint16
    for 16), as a worker process sends them (:func:`gpu_blur.generate.for_driver`).
    The file appears complete or not at all (encoded, written to a new temporary file, then
    renamed; the temporary file is removed on failure).
    """
    path = Path(path)
    write_whole(path, encode_image(image, bits, str(path), png))


def _codes(image: np.ndarray, bits: int) -> np.ndarray:
    """``image`` as the codes of its ``bits``-bit PNG: as given where it holds them already."""
    image = np.asarray(image)
    return image if image.dtype == code_dtype(bits) else to_integers(image, bits)


def encode_image(image: np.ndarray, bits: int, what: str = "image",
                 png: str = DEFAULT_PNG_MODE, stream=None) -> bytes:
    """The bytes :func:`write_image` writes for ``image``: its PNG (8/16 bits) or TIFF (0).

    ``stream``: the zlib stream of the image's Sub-filtered 8-bit rows in parts, deflated on
    the device (:mod:`gpu_blur.png_device`, for ``png = "fast"``: the bytes
    :func:`~gpu_blur.png_codecs.encode_png` writes), put in the file as it is.

    Raises:
        OSError: ``what``: could not encode the image.
        ValueError: ``png`` is not one of :data:`gpu_blur.png_codecs.PNG_MODES`.
    """
    data = np.asarray(image, dtype=np.float32) if bits == 0 else _codes(image, bits)
    if bits:
        if png not in PNG_MODES:
            raise ValueError(f"PNG mode {png!r}: expected one of {', '.join(PNG_MODES)}")
        try:
            if stream is not None and png == "fast" and data.dtype == np.uint8:
                return png_file(data, stream)
            return encode_png(data, png)
        except ValueError:
            raise OSError(f"{what}: could not encode the image") from None
    try:
        ok, encoded = cv2.imencode(".tiff", swap_red_blue(data))
    except cv2.error:
        ok = False
    if not ok:
        raise OSError(f"{what}: could not encode the image")
    return encoded.tobytes()


class EncodedImages:
    """Files of images a run writes more than once, each encoded once (threads may share it).

    Windows of a sequence that share their centre frame, and draws of one photo, have the
    same sharp reference: its codes are looked up by their SHA-256 (with the shape, bits and
    PNG mode) and an image seen before gets the bytes encoded then, the least recently used
    dropped past ``limit`` bytes. The bytes are :func:`encode_image`'s either way; with
    ``output.png = "fastest"``, whose bytes may vary, the copies of an image in one run are
    one file's. A copy pickles empty (each process keeps its own).
    """

    def __init__(self, limit: int = ENCODED_BYTES):
        self.limit = limit
        self._files: OrderedDict[tuple, bytes] = OrderedDict()
        self._held = 0
        self._lock = threading.Lock()
        self.hits = 0

    def __reduce__(self):
        return EncodedImages, (self.limit,)

    def encode(self, image: np.ndarray, bits: int, what: str = "image",
               png: str = DEFAULT_PNG_MODE) -> bytes:
        """:func:`encode_image`'s bytes for ``image``, encoded only if not seen before."""
        if bits == 0:  # float TIFF: never the sharp reference of 8- or 16-bit sets
            return encode_image(image, bits, what, png)
        codes = np.ascontiguousarray(_codes(image, bits))
        key = (hashlib.sha256(memoryview(codes).cast("B")).digest(), codes.shape, bits, png)
        with self._lock:
            data = self._files.get(key)
            if data is not None:
                self._files.move_to_end(key)
                self.hits += 1
                return data
        data = encode_image(codes, bits, what, png)
        with self._lock:
            if key not in self._files and len(data) <= self.limit:
                self._files[key] = data
                self._held += len(data)
                while self._held > self.limit:
                    self._held -= len(self._files.popitem(last=False)[1])
        return data


def write_text(path: str | Path, text: str,
               check: Callable[[Path], None] | None = None) -> None:
    """Write a text file that appears complete or not at all (as :func:`write_image`).

    Args:
        path: the file.
        text: its contents.
        check: called with the temporary file before it is renamed onto ``path``; what it
            raises leaves ``path`` as it was.
    """
    path = Path(path)
    try:
        write_whole(path, text.encode(), check)
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(path)) from None  # the name asked for

