"""PNG files written and read by the fastest codec present that keeps every pixel.

Chosen by bench/png_codecs.py, on one core and through pools of threads (its tables:
docs/performance.md, "PNG codecs"):

* writing (:func:`encode_png`), ``output.png`` in the scene (:data:`PNG_MODES`):

  - ``fast`` (the default): the rows filtered with Sub (each byte less the byte one pixel to
    its left, the filter OpenCV's default also uses) in numpy, then deflate with Huffman
    coding alone (no matches: on noisy rows they gain little), by zlib-ng (``zlib-ng``) or,
    without it, Python's zlib: both write the same bytes (zlib's ``Z_HUFFMAN_ONLY`` stream),
    so the file depends on the pixels alone. The file is put together here (IHDR, IDAT,
    IEND).
  - ``fastest``: the same rows compressed by ISA-L's deflate at level 1 (``isal``), faster
    still on the host (a Warp GPU deflates ``fast``'s files itself, faster again:
    :mod:`gpu_blur.png_device`), but its bytes are not always the same: on the host of two
    H200s one file of 29,696 came out as another stream of the same rows (the same pixels;
    bench/results/png_fast_libdeflate_h200x2.json). ``fast`` without ``isal``.
  - ``small``: the smallest of a few files: OpenCV's libpng with its own filter choice per
    row at level 1 with run-length matches (on noisy images smaller than any level with the
    default strategy, whose longer matches rarely pay), for 16 bits also at level 6 (which
    wins where the high bytes repeat, as in 8-bit content stored as 16 bits), and the
    ``fast`` file (16-bit noise, where libpng finds little more); so never the larger.
  - ``stored``: the rows unfiltered in stored deflate blocks (:func:`stored_zlib`): no
    compression, so files the size of the raw codes (on noisy 8-bit images 1.7 times
    ``fast``'s), but a core writes them in a few ms and reads them back as fast (what a data
    loader decodes too). Whether that makes a run faster depends on the host's memory and
    disk: on an H100 host ``generate`` ran slower with it (docs/performance.md).

* reading (:func:`decode_png`): files whose rows are filtered with None, Sub or Up only (as
  OpenCV's default and ``fast`` write them) are inflated by libdeflate (``deflate``), else by
  ISA-L (``isal``), and unfiltered in numpy, all without holding the GIL, so I/O threads
  decode in parallel; every other file goes through OpenCV, as before. On a 16-core host
  (bench/png_codecs.py --threads) libdeflate's path decoded more files a second through 16
  threads than ISA-L's and than OpenCV's, and ISA-L's fewer than OpenCV's on noisy images, so
  ISA-L decodes only a few files at a time (:data:`_ISAL_SLOTS`). libspng (``pyspng``)
  decoded 8-bit files faster than OpenCV on one core, but holds the GIL while it decodes, so a
  pool of I/O threads would decode one file at a time; it is not used.

Every mode and decoder gives the same pixels (tests/io/test_png_codecs.py); only the size of
the file and the time differ.
"""

from __future__ import annotations

import struct
import threading
import zlib

import numpy as np

__all__ = ["DEFAULT_PNG_MODE", "PNG_MODES", "PNG_SIGNATURE", "chunk", "decode_png",
           "decoder_name", "encode_png", "encoder_name", "filtered_rows", "huffman_zlib",
           "png_file", "stored_zlib"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: ``output.png``: the mode and how it writes.
PNG_MODES = {
    "fast": "numpy's Sub filter and deflate's Huffman coding alone (zlib-ng, or Python's "
            "zlib: the same bytes): a file's bytes depend on its pixels alone",
    "fastest": "numpy's Sub filter and ISA-L's deflate at level 1 (isal; without it fast): "
               "faster than fast on the host (where a Warp GPU deflates fast's files, fast "
               "is the faster), but a file's bytes may differ from run to run (its pixels "
               "never)",
    "small": "the smallest of OpenCV's libpng (a filter chosen per row, level 1 with "
             "run-length matches; 16-bit also level 6) and the fast file",
    "stored": "rows unfiltered in stored (uncompressed) deflate blocks: the largest files, "
              "the least CPU to write and to read",
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


def stored_zlib(data) -> bytes:
    """``data`` as a zlib stream of stored deflate blocks (RFC 1950; RFC 1951, 3.2.4).

    Blocks of at most 65,535 bytes, each led by its final-block bit, its length and the
    length's complement; the stream ends with the Adler-32 of ``data`` (ISA-L's where the
    ``isal`` package is installed, else zlib's).
    """
    view = memoryview(data).cast("B")
    isal = _isal()
    adler = (isal.adler32 if isal is not None else zlib.adler32)(view)
    parts = [b"\x78\x01"]  # deflate, 32 KB window, no dictionary; FCHECK: 0x7801 % 31 == 0
    for start in range(0, max(len(view), 1), 65535):
        size = min(65535, len(view) - start)
        final = start + size == len(view)
        parts += [struct.pack("<BHH", final, size, size ^ 0xFFFF), view[start:start + size]]
    parts.append(struct.pack(">I", adler))
    return b"".join(parts)


def png_file(codes: np.ndarray, idat) -> bytes:
    """A PNG file of ``codes``' header and ``idat``, the zlib stream of its filtered rows.

    ``idat``: the stream as bytes, or as a sequence of consecutive parts, joined here into the
    file: the stream is copied once, by a join, which releases the GIL for data this large
    (adding bytes objects holds it while copying, and the making thread waits for the GIL).
    """
    parts = [idat] if isinstance(idat, (bytes, bytearray, memoryview)) else list(idat)
    height, width = codes.shape[:2]
    channels = codes.shape[2] if codes.ndim == 3 else 1
    header = struct.pack(">IIBBBBB", width, height, 8 * codes.itemsize,
                         _COLOUR_TYPES[channels], 0, 0, 0)
    crc = _crc32()
    checksum = crc(b"IDAT")
    for part in parts:
        checksum = crc(part, checksum)
    return b"".join((PNG_SIGNATURE, chunk(b"IHDR", header),
                     struct.pack(">I", sum(len(part) for part in parts)), b"IDAT", *parts,
                     struct.pack(">I", checksum), chunk(b"IEND", b"")))


def _isal():
    try:
        from isal import isal_zlib
    except ImportError:
        return None
    return isal_zlib


def _zlib_ng():
    try:
        from zlib_ng import zlib_ng
    except ImportError:
        return None
    return zlib_ng


def huffman_zlib(data) -> bytes:
    """``data`` as a zlib stream of Huffman-coded deflate blocks (``Z_HUFFMAN_ONLY``).

    zlib-ng's where the ``zlib-ng`` package is installed, else Python's zlib: the same bytes
    (tests/io/test_png_codecs.py), without the GIL.
    """
    return b"".join(_huffman_parts(data))


def _huffman_parts(data) -> tuple[bytes, bytes]:
    """:func:`huffman_zlib`'s stream in two consecutive parts (what compress and flush give)."""
    lib = _zlib_ng() or zlib
    compressor = lib.compressobj(1, lib.DEFLATED, lib.MAX_WBITS, lib.DEF_MEM_LEVEL,
                                 lib.Z_HUFFMAN_ONLY)
    return compressor.compress(data), compressor.flush()


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
    if mode == "stored":
        return png_file(codes, stored_zlib(filtered_rows(codes, "none")))
    isal = _isal() if mode == "fastest" else None
    if isal is not None:  # its bytes may vary (PNG_MODES)
        return png_file(codes, isal.compress(filtered_rows(codes, "sub"), 1))
    if mode in ("fast", "fastest"):
        return png_file(codes, _huffman_parts(filtered_rows(codes, "sub")))
    import cv2

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
    made.append(encode_png(codes, "fast"))  # also grey + alpha, which OpenCV cannot write
    return min(made, key=len)


def encoder_name(mode: str) -> str:
    """Which library writes ``mode`` here, e.g. ``zlib-ng 1.1.0 (deflate, Huffman only, ...)``."""
    if mode == "stored":
        return "gpu_blur (stored deflate blocks, rows unfiltered)"
    if mode == "fastest" and _isal() is not None:
        return (f"isal {_package_version('isal')} (ISA-L deflate, level 1, numpy's Sub filter; "
                "bytes may vary)")
    fast = (f"zlib-ng {_package_version('zlib_ng')}" if _zlib_ng() is not None
            else f"Python's zlib {zlib.ZLIB_RUNTIME_VERSION}")
    fast += " (deflate, Huffman only, numpy's Sub filter)"
    if mode == "small":
        import cv2

        return f"OpenCV {cv2.__version__} (libpng) or {fast}, the smaller"
    return fast


def _package_version(name: str) -> str:
    """An installed package's own ``__version__`` (a copied folder has no metadata to ask)."""
    import importlib

    return str(getattr(importlib.import_module(name), "__version__", "unknown version"))


def decoder_name() -> str:
    """Which library decodes the PNG files :func:`decode_png` takes here."""
    inflater = _inflater()
    if inflater is not None:
        name = inflater[0]
        library = "libdeflate" if name == "deflate" else "ISA-L"
        return f"{name} {_package_version(name)} ({library} inflate, numpy's unfiltering)"
    import cv2

    return f"OpenCV {cv2.__version__} (libpng)"


def _inflater():
    """The fastest zlib inflater present, ``(distribution, inflate)``, or None.

    ``inflate(stream, size)``: the bytes ``stream`` inflates to, at most ``size`` of them
    (None past that or for a stream that is damaged, or whose Adler-32 fails), without the
    GIL. libdeflate (``deflate``) first, then ISA-L (``isal``).
    """
    return _libdeflate_inflater() or _isal_inflater()


def _libdeflate_inflater():
    try:
        import deflate
    except ImportError:
        return None

    def inflate(stream: bytes, size: int) -> bytes | None:
        try:
            return deflate.zlib_decompress(stream, size)
        except deflate.DeflateError:
            return None

    return "deflate", inflate


def _isal_inflater():
    isal = _isal()
    if isal is None:
        return None

    def inflate(stream: bytes, size: int) -> bytes | None:
        inflater = isal.decompressobj()
        try:  # one byte more than asked: a stream that goes on is refused, not inflated
            raw = inflater.decompress(stream, size + 1)
        except isal.error:
            return None
        return raw if inflater.eof and len(raw) <= size else None  # eof: Adler-32 checked

    return "isal", inflate


#: Files ISA-L's path of :func:`decode_png` decodes at a time. ISA-L's inflate scales less
#: well through threads than OpenCV's decoder, which releases the GIL throughout and takes
#: the files of the threads beyond these. On a 16-core host (bench/png_codecs.py --threads),
#: 8-bit: 3.1 times OpenCV's files a second on 1 thread, 1.6 on 4, 1.1 on 16; 4 slots fell
#: to 0.9 on 16. libdeflate's path has no such limit.
_ISAL_SLOTS = threading.BoundedSemaphore(2)
#: Rows decompressed first, whose filter types say whether the file is one to go on with.
_FIRST_ROWS = 16


def _idat(data: bytes) -> tuple[int, int, int, int, list[memoryview]] | None:
    """(width, height, bits, channels, IDAT data) of a PNG file :func:`decode_png` takes.

    The IDAT data: each IDAT chunk's, in order; together the zlib stream of the rows.

    8- or 16-bit grey, RGB or RGBA (colour types 0, 2, 6), not interlaced, no tRNS chunk,
    an IHDR with the CRC-32 it stores, the chunks walked to IEND; else None.

    The IDAT chunks' own CRCs are not checked: the zlib stream's Adler-32 (checked by ISA-L)
    covers every byte they hold once inflated, and a CRC per chunk would cost a call per
    chunk (OpenCV writes chunks of 8 KiB), each releasing and taking back the GIL behind
    the other I/O threads: with them 16 threads decoded 0.8 times as many files a second as
    one (bench/png_codecs.py --threads, a 16-core host). So a file whose only damage is a
    stored IDAT CRC, its pixels intact, is decoded here where libpng refuses it.
    """
    if not data.startswith(PNG_SIGNATURE) or len(data) < 33 or data[12:16] != b"IHDR":
        return None
    width, height, depth, colour, _, _, interlace = struct.unpack_from(">IIBBBBB", data, 16)
    if depth not in (8, 16) or colour not in (0, 2, 6) or interlace or not width * height:
        return None
    if _crc32()(memoryview(data)[12:29]) != struct.unpack_from(">I", data, 29)[0]:
        return None
    view, pos, parts = memoryview(data), 33, []
    while pos + 12 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        end = pos + 8 + length
        if end + 4 > len(data) or kind == b"tRNS":
            return None
        if kind == b"IDAT":
            parts.append(view[pos + 8:end])
        elif kind == b"IEND":
            channels = {0: 1, 2: 3, 6: 4}[colour]
            return width, height, depth, channels, parts
        pos = end + 4
    return None


def _unfilter(kinds: np.ndarray, body: np.ndarray, step: int) -> np.ndarray | None:
    """Rows filtered with None, Sub or Up (9.2) undone: H x (W * step) uint8, or None.

    Vectorised where every row has the same filter (Sub: a running sum along the row,
    modulo 256, per byte of a pixel; Up: along the columns), else one row at a time. None
    for Average and Paeth rows, whose predictions depend on the bytes just decoded.

    Sub's running sum by doubling shifts instead (log2 of the row's pixels whole-row
    additions, in blocks of 256 rows) decoded a 1920 x 1200 frame in 24 ms against 37 on one
    core of the AMD EPYC build machine, but on the H200's 16-core Xeon host it lost: 33.6
    files a second on one thread against cumsum's 36.5, 202 against 339 on 16 (all rows at
    once: 276; the passes' memory traffic, shared by the threads, the likely cause). So
    cumsum stays.
    """
    height = body.shape[0]
    if np.all(kinds == 1):
        return np.cumsum(body.reshape(height, -1, step), axis=1, dtype=np.uint8)
    if np.all(kinds == 2):
        return np.cumsum(body, axis=0, dtype=np.uint8)
    if np.all(kinds == 0):
        return body.copy()
    if np.any(kinds > 2):
        return None
    out = np.empty(body.shape, np.uint8)
    above = np.zeros(body.shape[1], np.uint8)
    for row, kind in enumerate(kinds.tolist()):
        if kind == 1:
            np.cumsum(body[row].reshape(-1, step), axis=0, dtype=np.uint8,
                      out=out[row].reshape(-1, step))
        elif kind == 2:
            np.add(body[row], above, out=out[row])
        else:
            out[row] = body[row]
        above = out[row]
    return out


def decode_png(data: bytes) -> np.ndarray | None:
    """A PNG file's codes through libdeflate's or ISA-L's inflate and numpy, RGB(A), or None.

    Taken: the files of :func:`_idat` whose rows are filtered with None, Sub or Up only, as
    OpenCV's default and ``output.png = "fast"`` write them (every row Sub). The zlib
    stream's Adler-32 is checked by the inflater (not the IDAT chunks' CRCs, see
    :func:`_idat`), its length against the header here; the filter types of the first rows
    are read before the rest is inflated, so a file of Average or Paeth rows (libpng's
    per-row choice) costs little before OpenCV takes it. None without an inflater
    (:func:`_inflater`) and for every other file, damaged ones included, and while ISA-L's
    :data:`_ISAL_SLOTS` are taken: the caller decodes those with OpenCV, which says what is
    wrong.

    Returns:
        H x W x 3 (RGB), H x W x 4 (RGBA) or H x W (grey), uint8 or uint16: OpenCV's
        IMREAD_UNCHANGED with red and blue in RGB order.
    """
    inflater = _inflater()
    if inflater is None:
        return None
    name, inflate = inflater
    if name != "isal":
        return _decode(inflate, data)
    if not _ISAL_SLOTS.acquire(blocking=False):
        return None
    try:
        return _decode(inflate, data)
    finally:
        _ISAL_SLOTS.release()


def _decode(inflate, data: bytes) -> np.ndarray | None:
    """:func:`decode_png` with ``inflate`` (:func:`_inflater`'s)."""
    found = _idat(data)
    if found is None:
        return None
    width, height, depth, channels, parts = found
    step = channels * depth // 8
    stride = 1 + width * step
    head, peek = b"", zlib.decompressobj()  # the first rows' filter types: Paeth goes at once
    try:
        for part in parts:
            tail = peek.unconsumed_tail
            wanted = min(height, _FIRST_ROWS) * stride - len(head)
            head += peek.decompress(tail + part if tail else part, wanted)
            if len(head) >= min(height, _FIRST_ROWS) * stride or peek.eof:
                break
    except zlib.error:
        return None
    if np.any(np.frombuffer(head, np.uint8)[::stride] > 2):
        return None
    # at most the image's rows: a small file whose stream inflates past its header's size
    # (a decompression bomb) costs no more memory than its image, and goes to OpenCV, which
    # refuses it
    raw = inflate(parts[0] if len(parts) == 1 else b"".join(parts), height * stride)
    if raw is None or len(raw) != height * stride:
        return None
    rows = np.frombuffer(raw, np.uint8).reshape(height, stride)
    codes = _unfilter(rows[:, 0], rows[:, 1:], step)
    if codes is None:
        return None
    if depth == 16:
        codes = codes.view(">u2").astype(np.uint16)
    shape = (height, width) if channels == 1 else (height, width, channels)
    return codes.reshape(shape)
