"""Reading and writing images: RGB order, integer codes to [0, 1] and back."""

from __future__ import annotations

import io
import math
import os
import re
import struct
from collections.abc import Callable
from pathlib import Path
from tokenize import TokenError

import cv2
import numpy as np

from gpu_blur import limits
from gpu_blur.reference.output import code_dtype, to_integers

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_WAY_OUT = "re-export or re-copy the file, or remove it from the input"


_TRUNCATED_JPEG = "truncated JPEG (no end-of-image marker after the image data)"
#: Start-of-frame markers (ITU-T T.81, Table B.1): 0xC0 to 0xCF but DHT, JPG and DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: Those of DCT coding (baseline, extended, progressive), whose restart intervals count MCUs
#: of 8 x 8 blocks (T.81, A.2); the lossless and hierarchical ones are not checked as deeply.
_JPEG_SOF_DCT = frozenset({0xC0, 0xC1, 0xC2, 0xC9, 0xCA})


def _damage(data: bytes, decode: bool = True) -> str | None:
    """Why a PNG or JPEG file's bytes are truncated or corrupt, or None when they look whole.

    libpng refuses a damaged PNG by itself (each chunk's CRC and the zlib checksum) but not
    every truncated one, and libjpeg decodes a truncated or damaged JPEG with a warning at
    most (grey or garbled blocks), so both are checked here from their structure: a PNG must
    reach its IEND chunk, a JPEG must pass :func:`_jpeg_damage`, and then, with ``decode``,
    :func:`_jpeg_decode_damage`.
    """
    if data.startswith(_PNG_SIGNATURE):
        pos = len(_PNG_SIGNATURE)
        while pos + 8 <= len(data):
            length, kind = struct.unpack(">I4s", data[pos:pos + 8])
            pos += 12 + length
            if pos > len(data):
                break
            if kind == b"IEND":
                return None
        return "truncated PNG (the file ends before its IEND chunk)"
    if data.startswith(b"\xff\xd8"):
        return _jpeg_damage(data) or (_jpeg_decode_damage(data) if decode else None)
    return None


#: The start of libjpeg's warnings about damaged data (jerror.h: JWRN_HIT_MARKER,
#: JWRN_HUFF_BAD_CODE, JWRN_EXTRANEOUS_DATA, JWRN_MUST_RESYNC, JWRN_JPEG_EOF, ...).
_LIBJPEG_DAMAGE = ("Corrupt JPEG data", "Premature end of JPEG file")


def _jpeg_decode_damage(data: bytes) -> str | None:
    """The warning libjpeg gives when it decodes damaged entropy-coded data, or None.

    A JPEG has no checksum: a bad Huffman code, a segment that ends early or bytes left over
    before a marker show only while decoding, and libjpeg (OpenCV's decoder) goes on with grey
    or garbled blocks. simplejpeg (libjpeg-turbo) decodes in strict mode, where such a
    warning is an error. Decoding with the fast IDCT and upsampling is enough, as the warnings
    come from the entropy decoder: 2 ms for 640 x 427 on a 2-core AMD EPYC (OpenCV's decode:
    3 ms). On tests/data/rocket.jpg it catches 77 % of 16 overwritten bytes and 30 % of single
    bit flips in the image data (measured over 200 random places each), which the marker
    check above passes. A JPEG simplejpeg cannot decode for another reason (CMYK, 12 bits) is
    left to OpenCV.
    """
    import simplejpeg

    try:
        simplejpeg.decode_jpeg(data, fastdct=True, fastupsample=True, strict=True)
    except ValueError as e:
        if str(e).startswith(_LIBJPEG_DAMAGE):
            return f"corrupt JPEG ({str(e).strip()}, found while decoding)"
    return None


def _jpeg_damage(data: bytes) -> str | None:
    """Why a JPEG file's marker structure is broken, or None (ITU-T T.81, Annex B).

    Checked: after the start of image, segments follow each other, each a marker with a
    length that stays inside the file; one frame header before the first scan, and each scan's
    components in it; in the entropy-coded data after each scan header every 0xFF is a stuffed
    0xFF00, a restart marker RST0..RST7 in turn, or the marker that ends the scan; with a
    restart interval (DRI), each scan of a DCT frame has the restart markers its number of
    MCUs needs (one more is tolerated: libjpeg skips a trailing one); the end-of-image marker
    is reached (data after it, such as a second image, is allowed).

    Not found: damage that keeps this structure, e.g. bits flipped or bytes zeroed inside
    entropy-coded data without a restart marker in reach (JPEG has no checksum; libjpeg
    does not notice those either).
    """
    size, pos = len(data), 2
    frame: tuple[int, int, dict[int, tuple[int, int]], int] | None = None
    interval = scans = 0
    ffs = None
    while True:
        if pos >= size:
            return _TRUNCATED_JPEG
        if data[pos] != 0xFF:
            return (f"corrupt JPEG (byte {pos} is 0x{data[pos]:02X} where a marker is due: "
                    "damaged or stray data between segments)")
        while pos < size and data[pos] == 0xFF:  # fill bytes may precede a marker
            pos += 1
        if pos >= size:
            return _TRUNCATED_JPEG
        marker, at = data[pos], pos - 1
        pos += 1
        if marker == 0xD9:
            return None if scans else ("corrupt JPEG (end-of-image marker at byte "
                                       f"{at} before any image data)")
        if marker == 0x01:  # TEM: a marker without a length
            continue
        if marker < 0xC0 or 0xD0 <= marker <= 0xD8:
            return (f"corrupt JPEG (marker 0xFF{marker:02X} at byte {at} cannot stand there: "
                    "damaged data)")
        if pos + 2 > size:
            return _TRUNCATED_JPEG
        length = int.from_bytes(data[pos:pos + 2], "big")
        body, pos = data[pos + 2:pos + length], pos + length
        if pos > size:
            return _TRUNCATED_JPEG
        if length < 2:
            return f"corrupt JPEG (segment 0xFF{marker:02X} at byte {at} has length {length})"
        if marker in _JPEG_SOF:
            if frame is not None:
                return f"corrupt JPEG (a second frame header at byte {at})"
            count = body[5] if len(body) >= 6 else 0
            if count < 1 or len(body) != 6 + 3 * count:
                return f"corrupt JPEG (frame header at byte {at} is malformed)"
            comps = {body[6 + 3 * i]: (body[7 + 3 * i] >> 4, body[7 + 3 * i] & 15)
                     for i in range(count)}
            if not all(1 <= h <= 4 and 1 <= v <= 4 for h, v in comps.values()):
                return f"corrupt JPEG (frame header at byte {at} has a bad sampling factor)"
            frame = (int.from_bytes(body[1:3], "big"), int.from_bytes(body[3:5], "big"),
                     comps, marker)
        elif marker == 0xDD:
            if len(body) != 2:
                return f"corrupt JPEG (restart interval segment at byte {at} is malformed)"
            interval = int.from_bytes(body, "big")
        elif marker == 0xDA:
            if frame is None:
                return f"corrupt JPEG (a scan at byte {at} before the frame header)"
            count = body[0] if body else 0
            ids = [body[1 + 2 * i] for i in range(count)] if len(body) == 4 + 2 * count else []
            if not ids or any(i not in frame[2] for i in ids):
                return f"corrupt JPEG (scan header at byte {at} is malformed)"
            scans += 1
            if ffs is None:  # every 0xFF byte of the file, found once for all its scans
                ffs = np.flatnonzero(np.frombuffer(data, np.uint8) == 0xFF)
            pos, problem = _jpeg_scan(data, pos, interval, _jpeg_mcus(frame, ids), ffs)
            if problem:
                return f"corrupt JPEG ({problem} in scan {scans})"


def _jpeg_mcus(frame: tuple[int, int, dict[int, tuple[int, int]], int],
               ids: list[int]) -> int | None:
    """MCUs in a scan of ``ids`` of a DCT frame (T.81, A.2.2 and A.2.3); None if not known."""
    height, width, comps, marker = frame
    if marker not in _JPEG_SOF_DCT or height == 0:  # lossless, hierarchical, or DNL height
        return None
    def up(a: int, b: int) -> int:  # a / b rounded up
        return -(-a // b)

    hmax = max(h for h, _ in comps.values())
    vmax = max(v for _, v in comps.values())
    if len(ids) == 1:  # non-interleaved: one block per MCU, over the component's own size
        h, v = comps[ids[0]]
        return up(up(width * h, hmax), 8) * up(up(height * v, vmax), 8)
    return up(width, 8 * hmax) * up(height, 8 * vmax)


def _jpeg_scan(data: bytes, pos: int, interval: int, mcus: int | None,
               ffs: np.ndarray | None = None) -> tuple[int, str | None]:
    """Walk entropy-coded data from ``pos``: the marker that ends it, and what is wrong.

    Every run of 0xFF bytes from ``pos`` on is looked at at once (numpy), not one by one: the
    byte after a run says what it is (0x00 a stuffed data byte, RST0..RST7 a restart marker,
    anything else the marker that ends the scan), so a file of stuffed bytes costs no Python
    loop. ``ffs``: the positions of every 0xFF byte of ``data`` (made here if not given).
    """
    size = len(data)
    if ffs is None:
        ffs = np.flatnonzero(np.frombuffer(data, np.uint8) == 0xFF)
    ffs = ffs[np.searchsorted(ffs, pos):]
    if not len(ffs):
        return size, None  # the caller reports the missing end of image
    # runs of consecutive 0xFF bytes: where each starts and the byte just after it
    breaks = np.flatnonzero(np.diff(ffs) != 1)
    starts = ffs[np.concatenate(([0], breaks + 1))]
    after = ffs[np.concatenate((breaks, [len(ffs) - 1]))] + 1
    codes = np.frombuffer(data, np.uint8)[np.minimum(after, size - 1)].astype(np.int32)
    codes[after >= size] = -1  # a run that reaches the end of the data
    restart = (codes >= 0xD0) & (codes <= 0xD7)
    ending = np.flatnonzero((codes != 0x00) & ~restart)
    last = ending[0] if len(ending) else len(codes)
    restarts = np.flatnonzero(restart[:last])
    if len(restarts):
        first = int(starts[restarts[0]])
        if not interval:
            return first, f"restart marker at byte {first} without a restart interval"
        due = np.arange(len(restarts)) % 8
        wrong = np.flatnonzero(codes[restarts] - 0xD0 != due)
        if len(wrong):
            at, k = int(starts[restarts[wrong[0]]]), int(wrong[0])
            return at, (f"restart marker RST{codes[restarts[k]] - 0xD0} at byte {at} where "
                        f"RST{k % 8} is due: image data is missing or damaged")
    if last == len(codes) or codes[last] < 0:
        return size, None
    ff, code, found = int(starts[last]), int(codes[last]), len(restarts)
    invalid = code < 0xC0 or code == 0xD8  # the caller names that marker
    if interval and mcus is not None and not invalid:
        needed = -(-mcus // interval) - 1
        if found not in (needed, needed + 1):
            return ff, (f"{found} restart markers where its {mcus} MCUs in intervals of "
                        f"{interval} need {needed}: image data is missing or damaged")
    return ff, None


#: The formats whose width and height :func:`_header_size` reads, the only ones decoded.
READ_FORMATS = "PNG, JPEG, TIFF, BMP, GIF, WebP and PNM/PAM/PFM"


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the header of a file of :data:`READ_FORMATS`, without decoding it.

    None for another format (JPEG 2000, AVIF, Radiance HDR, Sun raster, ...: OpenCV would
    read them, but their size is not known before decoding, so they are refused) or a header
    too damaged to read. A GIF's size is its logical screen's (OpenCV refuses a frame that
    leaves it), an animated WebP's its canvas'.
    """
    if data.startswith(_PNG_SIGNATURE):  # IHDR is the first chunk (PNG spec, 11.2.2)
        if data[12:16] != b"IHDR" or len(data) < 24:
            return None
        return struct.unpack(">II", data[16:24])
    if data.startswith(b"\xff\xd8"):
        return _jpeg_size(data)
    if data[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):  # TIFF, BigTIFF
        import tifffile

        try:  # the first page, the one OpenCV decodes; its IFD only
            with tifffile.TiffFile(io.BytesIO(data)) as tif:
                page = tif.pages.first
                return int(page.imagewidth), int(page.imagelength)
        except Exception:  # a damaged header raises many kinds: OpenCV decides
            return None
    if data.startswith(b"BM") and len(data) >= 26:  # BITMAPCOREHEADER (12 bytes) or later
        if int.from_bytes(data[14:18], "little") == 12:
            return struct.unpack("<HH", data[18:22])
        width, height = struct.unpack("<ii", data[18:26])  # height < 0: stored top-down
        return abs(width), abs(height)
    if data[:6] in (b"GIF87a", b"GIF89a") and len(data) >= 10:
        return struct.unpack("<HH", data[6:10])
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return _webp_size(data)
    if len(data) >= 3 and data[:1] == b"P" and data[1] in b"1234567Ff":
        return _pnm_size(data)
    return None


def _webp_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of a WebP file from its first chunk (VP8X's canvas, VP8L, VP8), or None.

    The layouts are those of libwebp's WebPGetInfo (RFC 9649, sections 2.5 to 2.7).
    """
    chunk = data[12:16]
    if chunk == b"VP8X" and len(data) >= 30:  # 24-bit canvas width - 1 and height - 1
        return (int.from_bytes(data[24:27], "little") + 1,
                int.from_bytes(data[27:30], "little") + 1)
    if chunk == b"VP8L" and len(data) >= 25 and data[20] == 0x2F:
        bits = int.from_bytes(data[21:25], "little")  # 14 bits each: width - 1, height - 1
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8 " and len(data) >= 30 and data[23:26] == b"\x9d\x01\x2a":
        width, height = struct.unpack("<HH", data[26:30])  # 14 bits each, then a scale
        return width & 0x3FFF, height & 0x3FFF
    return None


#: How far into a PNM file its text header is looked for (comments may make it long).
_PNM_HEADER_BYTES = 65536


def _pnm_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of a PNM (P1 to P6), PAM (P7) or PFM (PF, Pf) file's header, or None.

    P1 to P6 and PFM give the width and the height as the first two numbers after the magic
    number, with ``#`` comments to the end of a line anywhere between; PAM names them in
    ``WIDTH`` and ``HEIGHT`` lines before ``ENDHDR``.
    """
    head = data[2:_PNM_HEADER_BYTES]
    if data[1:2] == b"7":
        if b"ENDHDR" not in head:
            return None
        lines = [line.split() for line in head.split(b"ENDHDR", 1)[0].splitlines()]
        sides = [[n[1] for n in lines if len(n) == 2 and n[0] == key and n[1].isdigit()]
                 for key in (b"WIDTH", b"HEIGHT")]  # a repeated line: the largest counts
        return (_header_number(max(sides[0], key=_header_number)),
                _header_number(max(sides[1], key=_header_number))) if all(sides) else None
    numbers = re.sub(rb"#[^\r\n]*", b" ", head).split(None, 2)[:2]
    if len(numbers) == 2 and all(n.isdigit() for n in numbers):
        return _header_number(numbers[0]), _header_number(numbers[1])
    return None


def _header_number(digits: bytes) -> int:
    """A header's decimal number; one of more than 18 digits as 10^18 (refused as too large)."""
    digits = digits.lstrip(b"0") or b"0"
    return int(digits) if len(digits) <= 18 else 10**18


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of a JPEG's first frame header (T.81, B.2.2), or None if none is found.

    Segments are skipped by their lengths up to the first SOF marker, so a thumbnail inside an
    APP segment is not taken for the image; the structure is checked later (:func:`_damage`).
    """
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xFF:  # a fill byte
            pos += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD7:  # TEM, RSTn: no length
            pos += 2
        elif marker in _JPEG_SOF:
            if pos + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[pos + 5:pos + 9])
            return width, height
        elif marker in (0xD9, 0xDA):  # end of image or a scan before any frame header
            return None
        else:
            pos += 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
    return None


def too_many_pixels(width: int, height: int) -> str | None:
    """Why an image of ``width`` x ``height`` is refused (:func:`gpu_blur.limits.max_pixels`)."""
    most, pixels = limits.max_pixels(), width * height
    if pixels <= most:
        return None
    memory = f", {3 * pixels / 1e9:.1f} GB decoded at least" if pixels >= 10**8 else ""
    return (f"is {width} x {height} pixels ({pixels:,}{memory}), more than the {most:,} an "
            f"image may hold; scale it down or crop it, or raise the limit with the "
            f"environment variable {limits.MAX_PIXELS_VARIABLE}={pixels}")


def _decode(path: Path, where: str, fix: str,
            refuse: Callable[[int, int], str | None] = too_many_pixels) -> np.ndarray:
    """An image file decoded by OpenCV as stored (IMREAD_UNCHANGED), after :func:`_damage`.

    Its width and height are checked with ``refuse`` first, from the header
    (:func:`_header_size`), before anything is decoded, so a small file that claims a huge
    image costs no memory; a file whose header gives no size (another format, or damaged)
    is refused, and the decoded image is checked again.

    Raises:
        ValueError: ``where``, what is wrong (unreadable, no regular file, empty, too large,
            damaged, not an image of :data:`READ_FORMATS`), then ``fix`` (a size has its own:
            what ``refuse`` says).
    """
    from gpu_blur.files import read_bytes

    data = read_bytes(path, where)
    if not data:
        raise ValueError(f"{where}: the file is empty (0 bytes){fix}")
    size = _header_size(data)
    problem = refuse(*size) if size else None
    if problem:
        raise ValueError(f"{where}: {problem}")
    problem = _damage(data, decode=size is not None)
    if problem:
        raise ValueError(f"{where}: {problem}{fix}")
    if size is None:
        raise ValueError(f"{where}: not a readable image (no width and height in its header: "
                         f"gpu_blur reads {READ_FORMATS}); convert it to PNG{fix}")
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        raise ValueError(f"{where}: not a readable image (corrupt, truncated or a format OpenCV "
                         f"does not read){fix}")
    problem = refuse(image.shape[1], image.shape[0])  # as the header said, or refused now
    if problem:
        raise ValueError(f"{where}: {problem}")
    return image


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as H x W x 3 in RGB order, keeping its codes.

    8-bit files give uint8 (later / 255), 16-bit files uint16 (later / 65535), float TIFFs
    float32 (which must lie in [0, 1]). What is accepted besides RGB:

    * grayscale (one channel) is expanded to R = G = B, as image viewers and most loaders
      show it; a deblurring set may hold a few such photos.
    * an alpha channel (RGBA, gray + alpha) is dropped when every pixel is fully opaque. Any
      pixel that is not is refused: the colour behind it is undefined, and gpu_blur does not
      guess a background. Flatten such images onto a background first.

    Images above :func:`gpu_blur.limits.max_pixels` (2^28 pixels unless
    ``GPU_BLUR_MAX_PIXELS`` says otherwise) are refused from the header before decoding;
    formats other than :data:`READ_FORMATS` are refused (their size is not known before).

    Raises:
        ValueError: naming the file and the way out when it is missing, empty, too large,
            truncated, corrupt, not an image, or has transparent pixels.
    """
    path = Path(path)
    if not path.exists():  # anything else there is refused by its kind (files.open_regular)
        raise ValueError(f"{path}: no such file")
    image = _decode(path, str(path), f"; {_WAY_OUT}")
    if image.ndim == 2:
        image = image[:, :, None]
    channels = image.shape[2]
    if channels in (2, 4):
        alpha = image[:, :, -1]
        opaque = np.iinfo(alpha.dtype).max if alpha.dtype.kind in "ui" else 1.0
        clear = int(np.count_nonzero(alpha != opaque))
        if clear:
            row, col = np.unravel_index(int(np.argmax(alpha != opaque)), alpha.shape)
            raise ValueError(
                f"{path}: {clear} of {alpha.size} pixels are not fully opaque (alpha < "
                f"{opaque}, first at row {row}, column {col}); gpu_blur does not guess the "
                "colour behind them: flatten the image onto a background first (e.g. "
                "ImageMagick: convert in.png -background white -alpha remove -alpha off out.png)")
        image = image[:, :, :-1]
        channels -= 1
    if channels == 1:
        return np.repeat(image, 3, axis=2)
    if channels != 3:
        raise ValueError(f"{path}: has {channels} channels; gpu_blur reads grayscale, RGB and "
                         "opaque RGBA images: convert it to RGB first")
    return swap_red_blue(image)


def swap_red_blue(image: np.ndarray) -> np.ndarray:
    """An H x W x 3 image with its first and last channels swapped (OpenCV's BGR <-> RGB).

    A new contiguous array of the same values: OpenCV's ``cvtColor`` for uint8, uint16 and
    float32 (a permutation; about 15 times faster than copying numpy's reversed view, 0.9
    against 16 ms for 1920 x 1200 uint8 on a 2-core VM), numpy for other dtypes.
    """
    if image.dtype in (np.uint8, np.uint16, np.float32):
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image[:, :, ::-1])


def _where(mask: np.ndarray) -> str:
    """'row r, column c, channel k' of the first True entry of an H x W x 3 mask."""
    row, col, ch = np.unravel_index(int(np.argmax(mask)), mask.shape)
    return f"row {row}, column {col}, channel {ch}"


def to_unit(image: np.ndarray, what: str = "image") -> np.ndarray:
    """uint8 / uint16 codes or floats in [0, 1] -> float64 in [0, 1], H x W x 3.

    Raises:
        ValueError: as :func:`check_image`.
    """
    return unit_values(check_image(image, what))


def unit_values(image: np.ndarray) -> np.ndarray:
    """A checked image (:func:`check_image`) as float64 in [0, 1]: codes / (2^bits - 1)."""
    if image.dtype == np.uint8:
        return image / 255.0
    if image.dtype == np.uint16:
        return image / 65535.0
    return np.asarray(image, dtype=np.float64)


def check_layout(image, what: str = "image") -> np.ndarray:
    """An H x W x 3 RGB input of uint8, uint16 or float values; the values are not read.

    Raises:
        ValueError: naming ``what`` and the way out, for a wrong shape or dtype.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        hint = (": for a grayscale image repeat it, np.repeat(x[..., None], 3, axis=2)"
                if image.ndim == 2 else "")
        raise ValueError(f"{what}: expected an H x W x 3 RGB array, got shape {image.shape}"
                         f"{hint}")
    if image.size == 0:
        raise ValueError(f"{what}: the image is empty (shape {image.shape})")
    if image.dtype not in (np.uint8, np.uint16) and not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"{what}: unsupported dtype {image.dtype}; use uint8, uint16 or float "
                         "in [0, 1] (e.g. x.astype(np.uint8) for 0..255 integers)")
    return image


def check_image(image: np.ndarray, what: str = "image") -> np.ndarray:
    """An H x W x 3 RGB input as stored: uint8 or uint16 codes, or float64 values in [0, 1].

    Frames stay in their integer codes until a backend reads them (kernels upload 1 or 2
    bytes per value and divide on the device); floats are checked and made float64. Kernel
    backends make the same checks on the device (``KernelBackend.inspect``) and come here
    only for the message.

    Raises:
        ValueError: naming ``what``, with how many bad values there are, where the first is,
            and the way out, for a wrong shape or dtype, NaN or infinity, or floats outside
            [0, 1].
    """
    image = check_layout(image, what)
    if image.dtype in (np.uint8, np.uint16):
        return image
    x = image.astype(np.float64)
    finite = np.isfinite(x)
    if not finite.all():
        nan = int(np.count_nonzero(np.isnan(x)))
        inf = x.size - int(np.count_nonzero(finite)) - nan
        raise ValueError(
            f"{what}: {nan} NaN and {inf} infinite value(s), the first at "
            f"{_where(~finite)}; float images must be finite sRGB values in [0, 1]: fix "
            "what produced them, or replace them (np.nan_to_num(x, nan=0.0, posinf=1.0, "
            "neginf=0.0))")
    if x.min() < 0:
        low = x < 0
        raise ValueError(
            f"{what}: {np.count_nonzero(low)} negative value(s), the lowest "
            f"{x.min():.6g}, the first at {_where(low)}; float images must be sRGB values "
            "in [0, 1] (not mean-subtracted or normalized data): clip rounding errors "
            "with np.clip(x, 0, 1)")
    if x.max() > 1:
        high = x > 1
        raise ValueError(
            f"{what}: {np.count_nonzero(high)} value(s) above 1, the highest "
            f"{x.max():.6g}, the first at {_where(high)}; float images must be sRGB values "
            "in [0, 1]: pass 0..255 data as uint8 (or divide it by 255), clip small "
            "overshoots with np.clip(x, 0, 1)")
    return x


def opencv_reason(error: cv2.error) -> str:
    """OpenCV's own sentence from a cv2.error, without its source file and line."""
    text = " ".join(str(error).split())
    match = re.search(r"error: \(-?\d+:[^)]*\) (.*?)(?: in function .*)?$", text)
    return (match.group(1) if match else text).strip().rstrip(".")


def temporary_path(path: Path) -> Path:
    """Where ``path`` is written before it is renamed into place.

    ``.<name>.<pid>.part<suffix>`` beside it: the process id keeps two processes apart, the
    suffix keeps the format. Written with :func:`write_new`.
    """
    return path.with_name(f".{path.name}.{os.getpid()}.part{path.suffix}")


def write_new(path: Path, data: bytes) -> Path:
    """``data`` as the new regular file ``path`` of its folder; returns ``path``.

    Whatever is there is removed first (a file a killed run left, or a link someone put
    there: the link itself, not what it points to); then ``O_EXCL | O_NOFOLLOW`` make sure
    the bytes land in a file made here, never through a link onto another file.

    Raises:
        OSError: the file cannot be made (also when something appears there in between).
    """
    path.unlink(missing_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    with os.fdopen(os.open(path, flags, 0o666), "wb") as f:
        f.write(data)
    return path


def write_whole(path: Path, data: bytes, check: Callable[[Path], None] | None = None) -> None:
    """``data`` as the file ``path``, which appears complete or not at all.

    Written to :func:`temporary_path` (:func:`write_new`), then renamed onto ``path``; the
    temporary file is removed on failure. ``check``: called with the temporary file before
    the rename; what it raises leaves ``path`` as it was.
    """
    tmp = temporary_path(path)
    try:
        write_new(tmp, data)
        if check is not None:
            check(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_image(path: str | Path, image: np.ndarray, bits: int) -> None:
    """Write an H x W x 3 RGB image in [0, 1]: PNG with 8/16 bits, or float32 TIFF for bits 0.

    ``image`` may also be its codes already (:func:`to_integers`: uint8 for 8 bits, uint16
    for 16), as a worker process sends them (:func:`gpu_blur.generate.for_driver`).
    The file appears complete or not at all (encoded, written to a new temporary file, then
    renamed; the temporary file is removed on failure).
    """
    path = Path(path)
    if bits == 0:
        data = np.asarray(image, dtype=np.float32)
    elif np.asarray(image).dtype == code_dtype(bits):
        data = np.asarray(image)
    else:
        data = to_integers(image, bits)
    try:
        ok, encoded = cv2.imencode(".tiff" if bits == 0 else ".png", swap_red_blue(data))
    except cv2.error:
        ok = False
    if not ok:
        raise OSError(f"{path}: could not encode the image")
    write_whole(path, encoded.tobytes())


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


def read_kernel(path: str | Path) -> np.ndarray:
    """A blur kernel from ``.npy`` (2-D floats) or a grayscale image (PNG, ...), as float64.

    The kernel is checked (odd sides up to :data:`gpu_blur.limits.KERNEL_SIDE`, finite,
    non-negative, positive sum) but not normalized here; the blur stage normalizes it to sum
    1. Its size is checked from the header before it is loaded (:func:`_read_npy`,
    :func:`_decode`).

    Raises:
        ValueError: naming the file (as ``blur.kernel = ...``) and what is wrong with it.
    """
    path = Path(path)
    where = f"blur.kernel = {str(path)!r}"
    if not path.exists():  # anything else there is refused by its kind (files.open_regular)
        raise ValueError(f"{where}: no such file (a relative path is taken from the scene "
                         "file's folder)")
    if path.suffix.lower() == ".npy":
        kernel = _read_npy(path, where)
    else:
        kernel = _decode(path, where, "", lambda width, height: _kernel_too_wide(height, width))
    kernel = kernel_weights(kernel, where)
    check_kernel(kernel, where)
    return kernel


def kernel_weights(kernel, where: str) -> np.ndarray:
    """A kernel's weights as float64; integers and floats only (a complex part is not dropped).

    Raises:
        ValueError: starting with ``where``, naming the dtype and the way out.
    """
    try:
        kernel = np.asarray(kernel)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: not an array of numbers; give a 2-D array of "
                         "floats") from None
    kind = kernel.dtype.kind
    if kind == "c":
        raise ValueError(f"{where}: holds {kernel.dtype} values; kernel weights are real (the "
                         "imaginary part would be lost): pass np.real(k) or np.abs(k)")
    if kind not in "iuf":
        raise ValueError(f"{where}: holds {kernel.dtype} values, not numbers; kernel weights "
                         "are integers or floats: pass k.astype(np.float64)")
    return kernel.astype(np.float64)


def _read_npy(path: Path, where: str) -> np.ndarray:
    """A kernel's ``.npy`` file, after its header's shape and dtype are checked.

    The header (format 1.0 or 2.0, what ``np.save`` writes for numbers) is read first, and a
    shape :func:`check_kernel` refuses, or one whose data does not fit in the file, is
    refused before any array is made: ``np.load`` makes the array the header asks for.
    """
    from numpy.lib import format as npy

    from gpu_blur.files import open_regular

    way_out = "save the kernel with np.save"
    with open_regular(path, where) as f:
        try:
            version = npy.read_magic(f)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"format version {version[0]}.{version[1]}, not 1.0 or 2.0")
            read_header = npy.read_array_header_1_0 if version == (1, 0) \
                else npy.read_array_header_2_0
            shape, _, dtype = read_header(f)
            start = f.tell()
        except (SyntaxError, TokenError, RecursionError):  # numpy parses the header as Python
            raise ValueError(f"{where}: not a numpy array file (its header is no valid Python "
                             f"literal); {way_out}") from None
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"{where}: not a numpy array file ({e}); {way_out}") from None
        if dtype.hasobject:
            raise ValueError(f"{where}: holds Python objects ({dtype}), which are not loaded; "
                             f"{way_out} from a float array")
        _check_kernel_shape(shape, where)
        need, have = math.prod(shape) * dtype.itemsize, os.fstat(f.fileno()).st_size - start
        if need > have:
            raise ValueError(f"{where}: its header gives a {shape[0]} x {shape[1]} array of "
                             f"{dtype} ({need:,} bytes) but {have:,} bytes follow it: the file "
                             f"is truncated or its header damaged; {way_out} again")
        try:
            f.seek(0)
            return np.load(f, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"{where}: not a numpy array file ({e}); {way_out}") from None


def _kernel_too_wide(rows: int, cols: int) -> str | None:
    """Why a kernel of ``rows`` x ``cols`` is too large or empty (limits.KERNEL_SIDE), or None."""
    if min(rows, cols) < 1:
        return (f"is {rows} x {cols}; a kernel needs at least one row and column of weights: "
                "check what wrote it")
    problem = limits.KERNEL_SIDE.problem(max(rows, cols))
    if problem is None:
        return None
    return (f"is {rows} x {cols}; allowed sides: {problem}: crop it to the rows and columns "
            "that hold its weight, or scale it down with the images it blurs")


def _check_kernel_shape(shape: tuple[int, ...], where: str) -> None:
    """Refuse a kernel shape: not 2-D, a side above limits.KERNEL_SIDE, or an even side."""
    if len(shape) != 2:
        raise ValueError(f"{where}: a kernel is 2-D (one channel), got shape {shape}")
    problem = _kernel_too_wide(*shape)
    if problem:
        raise ValueError(f"{where}: {problem}")
    if shape[0] % 2 == 0 or shape[1] % 2 == 0:
        raise ValueError(f"{where}: is {shape[0]} x {shape[1]}; a kernel needs odd "
                         "sides (its centre is the origin): pad it with a row or column of "
                         "zeros where the blur should not move")


def check_kernel(kernel: np.ndarray, where: str) -> None:
    """Refuse what :func:`gpu_blur.reference.motion_kernel.normalize_kernel` cannot normalize.

    Raises:
        ValueError: starting with ``where``, saying what is wrong and the way out.
    """
    _check_kernel_shape(kernel.shape, where)
    bad = int(np.count_nonzero(~np.isfinite(kernel)))
    if bad:
        raise ValueError(f"{where}: holds {bad} NaN or infinite weight(s); kernel weights must "
                         "be finite")
    negative = int(np.count_nonzero(kernel < 0))
    if negative:
        raise ValueError(f"{where}: holds {negative} negative weight(s), the lowest "
                         f"{float(kernel.min()):.6g}; a blur kernel is non-negative: clip them "
                         "to 0 (np.clip(k, 0, None)) or fix what made it")
    if not kernel.sum() > 0:
        raise ValueError(f"{where}: its weights sum to {float(kernel.sum()):.6g}; a blur kernel "
                         "needs some positive weight (it is scaled to sum 1)")
