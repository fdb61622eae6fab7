"""Outputs beyond the blurred/sharp pair: the JPEG stage, the saturation mask, the RAW mosaic.

JPEG (``output.jpeg_quality``): the last stage, a round trip of the quantized 8-bit blurred
image through OpenCV's libjpeg on the host, after the device's output, so every backend gives
the same bytes. Chroma is subsampled 4:2:0 (2 x 2), as camera JPEGs and libjpeg's default
are; the sharp reference is left as it is (a training target without JPEG artefacts).
"""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np

from gpu_blur.image_arrays import swap_red_blue

__all__ = ["RAW_BLACK_LEVEL", "RAW_WHITE_LEVEL", "dng_bytes", "jpeg_round_trip", "raw_codes",
           "raw_metadata", "write_dng", "write_mask"]

#: float32(c / 255) for every 8-bit code c, as quantization gives them (a gather, not a divide).
_CODE_VALUES = (np.arange(256) / 255.0).astype(np.float32)


def jpeg_round_trip(image: np.ndarray, quality: int) -> np.ndarray:
    """``image`` encoded as a JPEG of ``quality`` and decoded again.

    Args:
        image: H x W x 3 RGB values on the 8-bit grid (multiples of 1/255, as
            ``output.bits = 8`` gives them), any float dtype.
        quality: libjpeg quality, 1 to 100.

    Returns:
        H x W x 3 float32 in [0, 1], multiples of 1/255.
    """
    image = np.asarray(image)
    codes = np.rint(image * image.dtype.type(255)).astype(np.uint8)  # exact: c / 255 * 255
    ok, data = cv2.imencode(".jpg", swap_red_blue(codes),
                            [cv2.IMWRITE_JPEG_QUALITY, int(quality),
                             cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                             cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420])
    if not ok:
        raise ValueError(f"OpenCV could not encode a {codes.shape[1]} x {codes.shape[0]} "
                         f"image as JPEG (quality {quality})")
    decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return _CODE_VALUES[swap_red_blue(decoded)]


# -- the RAW mosaic ------------------------------------------------------------------------------
#: How RAW files store the mosaic: 16-bit codes ``black + s * (white - black)``, rounded and
#: clipped to [0, 65535], where ``s`` is the sensor value (the white-balanced mosaic the to_raw
#: pass leaves, divided by its site's white-balance gain: what the noise was drawn on, as a
#: camera's RAW holds it). One unit of ``s`` is 2^14 codes (a 14-bit sensor's range, exact in
#: binary); the black level leaves room for noise below 0 (down to -0.125, five times the
#: largest read-noise std the scene allows), and codes above the white level hold the values
#: saturation synthesis pushes past 1 (up to 3.875), which RAW developers clip as a camera's.
RAW_BLACK_LEVEL = 2048
RAW_WHITE_LEVEL = RAW_BLACK_LEVEL + 2**14
#: The DNG CFAPattern codes of the colours (TIFF/EP: 0 red, 1 green, 2 blue).
_CFA_CODES = {"R": 0, "G": 1, "B": 2}


def raw_metadata(params: dict, camera, crop: int) -> dict:
    """What a sample's RAW mosaic needs to be read: the ``raw`` entry of its manifest line.

    Args:
        params: the sample's drawn values (``pattern``, ``red_gain``, ``blue_gain``).
        camera: its :class:`~gpu_blur.cameras.Camera`.
        crop: ``output.crop``: the mosaic is cut like the outputs, which may move the pattern.

    Returns:
        A dict of plain values: ``cfa_pattern`` (the colours at (0, 0), (0, 1), (1, 0), (1, 1)
        of the stored mosaic), ``black_level``, ``white_level``, ``wb_gains`` (red, green,
        blue), ``camera_to_linear`` (white-balanced camera RGB -> linear sRGB, row-major),
        ``encoding`` (how the stored codes map to the pipeline's values).
    """
    from gpu_blur.reference.bayer import BayerPattern

    pattern = BayerPattern(params["pattern"]).shifted(crop, crop).value
    return {
        "cfa_pattern": pattern,
        "black_level": RAW_BLACK_LEVEL,
        "white_level": RAW_WHITE_LEVEL,
        "wb_gains": [float(params["red_gain"]), 1.0, float(params["blue_gain"])],
        "camera_to_linear": np.asarray(camera.camera_to_linear, np.float64).tolist(),
        "encoding": "code = clip(round(black_level + v / gain * (white_level - black_level)), "
                    "0, 65535): v the white-balanced noisy mosaic before demosaicing (the to_raw "
                    "pass's output), gain the wb_gains entry of the site's colour; a RAW "
                    "developer's (code - black) / (white - black) is the sensor value",
    }


def raw_codes(raw: np.ndarray, info: dict) -> np.ndarray:
    """A white-balanced mosaic (``Batch.raw``) as the 16-bit codes of :func:`raw_metadata`."""
    gains = np.asarray(info["wb_gains"], np.float64)
    channel = np.array([_CFA_CODES[c] for c in info["cfa_pattern"]]).reshape(2, 2)
    h, w = raw.shape
    sites = np.tile(channel, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    sensor = np.asarray(raw, np.float64) / gains[sites]
    scale = info["white_level"] - info["black_level"]
    return np.clip(np.rint(info["black_level"] + sensor * scale), 0, 65535).astype(np.uint16)


def write_dng(path, raw: np.ndarray, info: dict) -> None:
    """Write a mosaic as a 16-bit DNG a RAW developer opens (LibRaw/rawpy, darktable, ...).

    The tags: CFA pattern, black and white levels, AsShotNeutral (1 / the white-balance
    gains) and ColorMatrix1 under D65, chosen so that a developer's white balance and colour
    transform equal the pipeline's: ColorMatrix1 = diag(1 / gains) Lin2Cam XYZ->sRGB, the
    XYZ -> camera map whose neutral is AsShotNeutral.

    The file appears complete or not at all (as :func:`gpu_blur.file_writing.write_image`).
    """
    from gpu_blur.file_writing import write_whole

    write_whole(Path(path), dng_bytes(raw, info))


def dng_bytes(raw: np.ndarray, info: dict) -> bytes:
    """The bytes of the DNG :func:`write_dng` writes."""
    import tifffile

    from gpu_blur.constants import XYZ_TO_SRGB
    from gpu_blur.reference.fixedmath import inverse3, matmul3

    gains = np.asarray(info["wb_gains"], np.float64)
    lin2cam = inverse3(np.asarray(info["camera_to_linear"], np.float64))  # fixed order: the
    xyz_to_camera = matmul3(matmul3(np.diag(1.0 / gains), lin2cam), XYZ_TO_SRGB)  # same bits
    neutral = 1.0 / gains
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, "gpu_blur synthetic camera", True),  # UniqueCameraModel
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in info["cfa_pattern"]), True),
        (50710, "B", 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, "H", 1, 1, True),  # CFALayout: rectangular
        (50714, "H", 1, info["black_level"], True),  # BlackLevel
        (50717, "H", 1, info["white_level"], True),  # WhiteLevel
        (50721, "2i", 9, _rationals(xyz_to_camera.ravel()), True),  # ColorMatrix1
        (50728, "2I", 3, _rationals(neutral), True),  # AsShotNeutral
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
    ]
    encoded = io.BytesIO()
    tifffile.imwrite(encoded, raw_codes(raw, info), photometric="cfa", extratags=tags,
                     subfiletype=0)
    return encoded.getvalue()


_DENOMINATOR = 10**6


def _rationals(values) -> tuple[int, ...]:
    """TIFF rationals (numerator, denominator, ...) of ``values``, to 1e-6."""
    return tuple(v for x in values for v in (round(float(x) * _DENOMINATOR), _DENOMINATOR))


def write_mask(path, mask: np.ndarray) -> None:
    """A saturation mask (H x W x 3 in [0, 1]) as a 16-bit PNG, codes ``round(m * 65535)``."""
    from gpu_blur.file_writing import write_image

    write_image(path, mask, 16)
