"""PNG files written and read by the fastest codec present that keeps every pixel.

Chosen by bench/png_codecs.py on one core (its table: docs/performance.md, "PNG codecs"):

* writing (:func:`encode_png`), ``output.png`` in the scene (:data:`PNG_MODES`):

  - ``fast`` (the default): the rows filtered with Sub (each byte less the byte one pixel to
    its left, the filter OpenCV's default also uses) in numpy, compressed by ISA-L's deflate
    at level 1 (``isal``), the file put together here (IHDR, IDAT, IEND). Without ``isal``:
    OpenCV's default (libpng, level 1, run-length matches, Sub).
  - ``small``: the smallest of a few files: OpenCV's libpng with its own filter choice per
    row at level 1 with run-length matches (on noisy images smaller than any level with the
    default strategy, whose longer matches rarely pay), for 16 bits also at level 6 (which
    wins where the high bytes repeat, as in 8-bit content stored as 16 bits), and the
    ``fast`` file (16-bit noise, where libpng finds little more); so never the larger.

* reading (:func:`decode_png`): 8-bit files through libspng (``pyspng``), which decoded them
  fastest; 16-bit ones through OpenCV, as libspng gives 16-bit RGB only as RGBA and the
  alpha dropped costs more than it saves. libspng takes the files whose pixels it gives as
  OpenCV does: 8-bit grey, RGB or RGBA, not interlaced, without a transparency chunk; any
  other file, and any it refuses, is left to OpenCV, whose errors the caller reports.
  ``pyspng`` skips the chunk checksums, so those of IHDR and IDAT are checked here first
  (libpng refuses a file when they fail; it only warns for the other chunks).

Every mode and decoder gives the same pixels (tests/io/test_png_codecs.py); only the size of
the file and the time differ.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

__all__ = ["DEFAULT_PNG_MODE", "PNG_MODES", "PNG_SIGNATURE", "chunk", "decode_png",
           "decoder_name", "encode_png", "encoder_name", "filtered_rows", "png_file"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: ``output.png``: the mode and how it writes.
PNG_MODES = {
    "fast": "numpy's Sub filter and ISA-L's deflate at level 1 (isal; without it OpenCV's "
            "default)",
    "small": "the smallest of OpenCV's libpng (a filter chosen per row, level 1 with "
             "run-length matches; 16-bit also level 6) and the fast file",
}
DEFAULT_PNG_MODE = "fast"

#: PNG colour types (PNG specification, third edition, 11.2.1) by channel count.
_COLOUR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}
#: PNG filter types (9.2).
_FILTERS = {"none": 0, "sub": 1, "up": 2, "paeth": 4}


def _crc32():
    """The fastest CRC-32 present: ISA-L's (10 times Python's zlib on 4 MB), else zlib's."""
    try:
        from isal import isal_zlib
    except ImportError:
        return zlib.crc32
    return isal_zlib.crc32


def chunk(kind: bytes, body: bytes) -> bytes:
    """One PNG chunk: length, type, data, and the CRC-32 of type and data (5.3)."""
    crc = _crc32()
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc(body, crc(kind)))


def _rows(codes: np.ndarray) -> np.ndarray:
    """The image's rows as PNG stores them: H x (W * channels * bytes), 16-bit big-endian."""
    if codes.dtype == np.uint16 and codes.dtype.byteorder != ">":
        codes = codes.astype(">u2")
    return np.ascontiguousarray(codes).view(np.uint8).reshape(codes.shape[0], -1)


def filtered_rows(codes: np.ndarray, kind: str = "sub") -> np.ndarray:
    """``codes`` (H x W x C or H x W, uint8 or uint16) as PNG rows led by their filter byte.

    ``kind``: ``none``, ``sub`` (each byte less the one a pixel to its left), ``up`` (less
    the one above) or ``paeth`` (less the Paeth predictor of left, above and upper left,
    9.4), every row alike. Vectorised: encoding predicts from unfiltered neighbours only.

    Returns:
        H x (1 + W * C * bytes) uint8: the data the IDAT chunks compress.
    """
    raw = _rows(codes)
    step = codes.itemsize * (codes.shape[2] if codes.ndim == 3 else 1)  # bytes a pixel
    out = np.empty((raw.shape[0], raw.shape[1] + 1), np.uint8)
    out[:, 0] = _FILTERS[kind]
    body = out[:, 1:]
    if kind == "none":
        body[...] = raw
    elif kind == "sub":
        body[:, :step] = raw[:, :step]
        np.subtract(raw[:, step:], raw[:, :-step], out=body[:, step:])
    elif kind == "up":
        body[0] = raw[0]
        np.subtract(raw[1:], raw[:-1], out=body[1:])
    else:  # paeth
        left = np.zeros(raw.shape, np.int16)
        left[:, step:] = raw[:, :-step]
        up = np.zeros_like(left)
        up[1:] = raw[:-1]
        corner = np.zeros_like(left)
        corner[1:, step:] = raw[:-1, :-step]
        pa, pb, pc = np.abs(up - corner), np.abs(left - corner), np.abs(left + up - 2 * corner)
        guess = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, corner))
        np.subtract(raw, guess.astype(np.uint8), out=body)
    return out


def png_file(codes: np.ndarray, idat: bytes) -> bytes:
    """A PNG file of ``codes``' header and ``idat``, the zlib stream of its filtered rows."""
    height, width = codes.shape[:2]
    channels = codes.shape[2] if codes.ndim == 3 else 1
    header = struct.pack(">IIBBBBB", width, height, 8 * codes.itemsize,
                         _COLOUR_TYPES[channels], 0, 0, 0)
    return b"".join((PNG_SIGNATURE, chunk(b"IHDR", header), chunk(b"IDAT", idat),
                     chunk(b"IEND", b"")))


def _isal():
    try:
        from isal import isal_zlib
    except ImportError:
        return None
    return isal_zlib


def encode_png(codes: np.ndarray, mode: str = DEFAULT_PNG_MODE) -> bytes:
    """``codes`` as a PNG file: H x W x 3 (RGB) or 4 (RGBA), or H x W grey; uint8 or uint16.

    ``mode``: one of :data:`PNG_MODES`; every mode decodes to the same codes.

    Raises:
        ValueError: an unknown mode, or an image PNG cannot hold.
    """
    if mode not in PNG_MODES:
        raise ValueError(f"PNG mode {mode!r}: expected one of {', '.join(PNG_MODES)}")
    if codes.dtype not in (np.uint8, np.uint16) or codes.ndim not in (2, 3) or (
            codes.ndim == 3 and codes.shape[2] not in _COLOUR_TYPES) or 0 in codes.shape:
        raise ValueError(f"a {' x '.join(map(str, codes.shape))} {codes.dtype} array is no "
                         "PNG image (uint8 or uint16, 1 to 4 channels)")
    isal = _isal()
    if mode == "fast" and isal is not None:
        return png_file(codes, isal.compress(filtered_rows(codes, "sub"), 1))
    import cv2

    if mode == "fast":
        settings = [[]]  # OpenCV's own default: level 1, Z_RLE, Sub
    else:
        settings = [[cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
                     cv2.IMWRITE_PNG_STRATEGY_RLE]]
        if codes.dtype == np.uint16:
            settings.append([cv2.IMWRITE_PNG_COMPRESSION, 6])
    bgr = codes
    if codes.ndim == 3 and codes.shape[2] >= 3:
        bgr = cv2.cvtColor(codes, cv2.COLOR_RGB2BGR if codes.shape[2] == 3
                           else cv2.COLOR_RGBA2BGRA)
    made = []
    for params in settings:
        try:
            ok, data = cv2.imencode(".png", bgr, params)
        except cv2.error:
            ok = False
        if ok:
            made.append(data.tobytes())
    if mode == "small" and isal is not None:
        made.append(encode_png(codes, "fast"))  # also grey + alpha, which OpenCV cannot write
    if not made:
        raise ValueError(f"OpenCV could not encode a {' x '.join(map(str, codes.shape))} "
                         f"{codes.dtype} image as PNG")
    return min(made, key=len)


def encoder_name(mode: str) -> str:
    """Which library writes ``mode`` here, e.g. ``isal 1.9.1 (ISA-L deflate, level 1)``."""
    isal = _isal() if mode == "fast" else None
    if isal is not None:
        from importlib.metadata import version

        return f"isal {version('isal')} (ISA-L deflate, level 1, numpy's Sub filter)"
    import cv2

    return f"OpenCV {cv2.__version__} (libpng)"


def _spng():
    try:
        import pyspng
    except ImportError:
        return None
    return pyspng


def decoder_name(bits: int) -> str:
    """Which library decodes the simple PNG files (see the module) of ``bits`` here."""
    if bits == 8 and _spng() is not None:
        from importlib.metadata import version

        return f"pyspng {version('pyspng')} (libspng)"
    import cv2

    return f"OpenCV {cv2.__version__} (libpng)"


def _spng_takes(data: bytes) -> bool:
    """Whether ``data`` is a PNG file libspng decodes to OpenCV's pixels, checksums right.

    8-bit grey, RGB or RGBA (colour types 0, 2, 6), not interlaced, no tRNS chunk; the
    CRC-32 of IHDR and of every IDAT chunk as stored. The chunks are walked to IEND (a
    file without one was refused before, :func:`gpu_blur.image_reading.decode_file`).
    """
    if not data.startswith(PNG_SIGNATURE) or len(data) < 33 or data[12:16] != b"IHDR":
        return False
    depth, colour, interlace = data[24], data[25], data[28]
    if depth != 8 or colour not in (0, 2, 6) or interlace != 0:
        return False
    crc, view, pos = _crc32(), memoryview(data), 8
    while pos + 12 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        end = pos + 8 + length
        if end + 4 > len(data) or kind == b"tRNS":
            return False
        if kind in (b"IHDR", b"IDAT") and (crc(view[pos + 4:end])
                                           != struct.unpack_from(">I", data, end)[0]):
            return False
        if kind == b"IEND":
            return True
        pos = end + 4
    return False


def decode_png(data: bytes) -> np.ndarray | None:
    """The pixels of a PNG file through libspng, in RGB(A) order, or None.

    None when ``pyspng`` is not installed, or the file is not one libspng decodes as OpenCV
    would (see :func:`_spng_takes`), or libspng refuses it: the caller decodes those with
    OpenCV, which says what is wrong.

    Returns:
        H x W x 3 (RGB) or H x W x 4 (RGBA) or H x W (grey) uint8, as OpenCV's
        IMREAD_UNCHANGED with red and blue in RGB order.
    """
    spng = _spng()
    if spng is None or not _spng_takes(data):
        return None
    try:
        return spng.load(data)
    except Exception:  # pyspng raises RuntimeError, and more for odd files: OpenCV decides
        return None
