"""Reading image files: format sniffing, sizes from headers, the pixel budget, damage checks.

A file's width and height come from its header before anything is decoded (a small file that
claims a huge image costs no memory); PNG and JPEG files are checked for truncation and damage
that their decoders pass over; OpenCV then decodes them as stored.
"""

from __future__ import annotations

import io
import re
import struct
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from gpu_blur import limits
from gpu_blur.image_arrays import swap_red_blue
from gpu_blur.png_codecs import decode_png

__all__ = ["READ_FORMATS", "WAY_OUT", "decode_file", "opencv_reason", "read_checked", "read_image",
           "too_many_pixels"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: The way out a bad input file's message ends with.
WAY_OUT = "re-export or re-copy the file, or remove it from the input"


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


def read_checked(path: Path, where: str, fix: str,
                 refuse: Callable[[int, int], str | None] = too_many_pixels) -> bytes:
    """An image file's bytes, once its header and structure pass :func:`decode_file`'s checks.

    The checks before decoding: not empty, a size in the header (:func:`_header_size`) that
    ``refuse`` lets through, no damage (:func:`_damage`). A decoder other than OpenCV's
    (nvJPEG, :mod:`gpu_blur.gpu_jpeg`) takes the bytes from here.

    Raises:
        ValueError: as :func:`decode_file`, naming ``where``.
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
    return data


def decode_file(path: Path, where: str, fix: str,
                refuse: Callable[[int, int], str | None] = too_many_pixels,
                rgb: bool = False) -> np.ndarray:
    """An image file decoded by OpenCV as stored (IMREAD_UNCHANGED), after :func:`_damage`.

    With ``rgb``, colour comes in RGB(A) order, and PNG files filtered as OpenCV's default
    and gpu_blur write them are inflated by libdeflate (or ISA-L) and unfiltered by numpy,
    faster, to the same pixels
    (:func:`gpu_blur.png_codecs.decode_png`).
    Its width and height are checked with ``refuse`` first, from the header
    (:func:`_header_size`), before anything is decoded, so a small file that claims a huge
    image costs no memory; a file whose header gives no size (another format, or damaged)
    is refused, and the decoded image is checked again.

    Raises:
        ValueError: ``where``, what is wrong (unreadable, no regular file, empty, too large,
            damaged, not an image of :data:`READ_FORMATS`), then ``fix`` (a size has its own:
            what ``refuse`` says).
    """
    data = read_checked(path, where, fix, refuse)
    image = decode_png(data) if rgb else None
    if image is None:
        try:
            image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:
            image = None
        if image is None:
            raise ValueError(f"{where}: not a readable image (corrupt, truncated or a format "
                             f"OpenCV does not read){fix}")
        if rgb and image.ndim == 3 and image.shape[2] in (3, 4):
            image = (swap_red_blue(image) if image.shape[2] == 3
                     else image[:, :, [2, 1, 0, 3]])
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
    image = decode_file(path, str(path), f"; {WAY_OUT}", rgb=True)
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
    return np.ascontiguousarray(image)



def opencv_reason(error: cv2.error) -> str:
    """OpenCV's own sentence from a cv2.error, without its source file and line."""
    text = " ".join(str(error).split())
    match = re.search(r"error: \(-?\d+:[^)]*\) (.*?)(?: in function .*)?$", text)
    return (match.group(1) if match else text).strip().rstrip(".")
