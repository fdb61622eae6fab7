"""JPEG inputs decoded on a CUDA GPU by nvJPEG through torchvision (``--jpeg-decoder gpu``).

The decoding is here; when it runs is ``gpu_blur.generate.run_pipelined``'s. For a sample
whose files are all JPEGs (:meth:`JpegBatches.takes`), the I/O threads read each file's bytes
and check them as :func:`~gpu_blur.image_reading.read_image` does (size from the header,
damage: :func:`~gpu_blur.image_reading.read_checked`) instead of decoding them; the making
thread then decodes a group of such samples' files in one call and hands the Synthesizer the
pixels as one torch CUDA batch (:meth:`JpegBatches.make`).

What nvJPEG is not given goes the CPU's way, as without this module: a file that is not a
baseline 8-bit YCbCr JPEG (:func:`nvjpeg_size`: progressive, greyscale, CMYK, RGB-coded) is
decoded by OpenCV in its I/O thread; a sample whose files fail a check, and a group whose
decode or batch fails, are made from their paths, so the error names the file in the CPU
decoder's words.

nvJPEG's IDCT and chroma upsampling are not libjpeg-turbo's (OpenCV's decoder), so a decoded
pixel may differ by a few codes (measured: see bench/results/jpeg_gpu_*.json). That is why
the GPU decoder is opt-in, recorded in the set's run.json (a resume must use the same) and
named on each manifest line it decoded (``"jpeg_decoder": "gpu"``).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from gpu_blur.image_reading import WAY_OUT, read_checked, read_image

__all__ = ["JPEG_DECODERS", "JPEG_SUFFIXES", "JpegBatches", "NVJPEG_MAX_DIFFERENCE",
           "NVJPEG_MEAN_DIFFERENCE", "for_backend", "nvjpeg_decode", "nvjpeg_size"]

#: ``--jpeg-decoder``'s values: OpenCV on the CPU (the default), nvJPEG on the GPU.
JPEG_DECODERS = ("cpu", "gpu")
#: The file names taken for JPEGs: a sample whose inputs all end so goes to :class:`JpegBatches`.
JPEG_SUFFIXES = (".jpg", ".jpeg")

#: How far nvJPEG's pixels may lie from OpenCV's, in 8-bit codes: the largest difference of
#: a channel, and the mean over every channel of an image. Measured on an H200 (torchvision
#: 0.26, bench/results/jpeg_gpu_h200.json), 1920 x 1200 frames of the built-in photo: 4:2:0
#: at quality 95 and 90 up to 28 codes, mean 0.42 (the chroma upsampling differs); 4:4:4 the
#: same pixels. A decode in BGR order (mean 72) or of another image is far outside.
NVJPEG_MAX_DIFFERENCE = 32
NVJPEG_MEAN_DIFFERENCE = 2.0

#: Frame headers of the JPEGs nvJPEG is given: baseline and extended sequential Huffman
#: (ITU-T T.81, Table B.1: SOF0, SOF1). Progressive and arithmetic-coded ones go to the CPU.
_SEQUENTIAL = (0xC0, 0xC1)
#: The luma sampling factors (horizontal, vertical) given to nvJPEG, with 1 x 1 chroma:
#: 4:4:4, 4:2:2, 4:4:0 and 4:2:0, the layouts its docs list and cameras write.
_LUMA_FACTORS = ((1, 1), (2, 1), (1, 2), (2, 2))
#: Component ids 'R', 'G', 'B': libjpeg takes such a file as stored in RGB, not YCbCr.
_RGB_IDS = (0x52, 0x47, 0x42)

#: ``(files' bytes, device) -> pixels``: each file's bytes as 1-D uint8 arrays in, each
#: decoded image as a 3 x H x W uint8 torch tensor in RGB order out.
Decode = Callable[[list[np.ndarray], str], list]


def nvjpeg_size(data: bytes | np.ndarray) -> tuple[int, int] | None:
    """(width, height) of a JPEG that nvJPEG decodes as libjpeg would, else None.

    Such a file is sequential (SOF0 or SOF1), of 8-bit samples, with three components coded
    as YCbCr (not an Adobe APP14 segment with transform 0, nor component ids R, G, B, which
    libjpeg reads as RGB) and sampled 4:4:4, 4:2:2, 4:4:0 or 4:2:0. The segments before the
    frame header are walked by their lengths (T.81, B.1.1.4); nothing after it is read.
    """
    data = data.tobytes() if isinstance(data, np.ndarray) else data
    if not data.startswith(b"\xff\xd8"):
        return None
    pos, adobe_rgb = 2, False
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xFF:  # a fill byte
            pos += 1
            continue
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        body = data[pos + 4:pos + 2 + length]
        if marker == 0xEE and body.startswith(b"Adobe") and len(body) >= 12:
            adobe_rgb = body[11] == 0  # Adobe's transform flag: 0 is RGB or CMYK as stored
        elif 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # a frame header
            if marker not in _SEQUENTIAL or len(body) != 15 or body[0] != 8 or body[5] != 3:
                return None
            ids = tuple(body[6:15:3])
            factors = [(b >> 4, b & 15) for b in body[7:15:3]]
            if (adobe_rgb or ids == _RGB_IDS or factors[0] not in _LUMA_FACTORS
                    or factors[1:] != [(1, 1), (1, 1)]):
                return None
            return int.from_bytes(body[3:5], "big"), int.from_bytes(body[1:3], "big")
        elif marker in (0xD9, 0xDA):  # end of image, or a scan before any frame header
            return None
        pos += 2 + length
    return None


def nvjpeg_decode(files: list[np.ndarray], device: str) -> list:
    """JPEG files decoded by nvJPEG in one batched call (torchvision's ``decode_jpeg``).

    Args:
        files: each file's bytes, 1-D uint8 arrays in host memory.
        device: the CUDA device, ``cuda:N``.

    Returns:
        3 x H x W uint8 torch tensors on ``device``, RGB order, EXIF orientation not applied
        (as OpenCV's ``IMREAD_UNCHANGED`` leaves it).
    """
    import torch
    from torchvision.io import ImageReadMode, decode_jpeg

    with warnings.catch_warnings():  # the frame cache's arrays are read-only; torch only reads
        warnings.simplefilter("ignore", UserWarning)
        data = [torch.from_numpy(f) for f in files]
    return decode_jpeg(data, mode=ImageReadMode.RGB, device=device)


def for_backend(backend, frames: bool) -> JpegBatches:
    """``--jpeg-decoder gpu``'s decoder for ``backend``, once it can run there.

    Args:
        backend: the run's backend (:func:`gpu_blur.backends.get_backend`).
        frames: the scene averages frames (``blur.mode = "average"``).

    Raises:
        ValueError: what is missing (a Warp backend on CUDA, torch with CUDA, torchvision
            whose decode_jpeg runs there), why, and the way out.
    """
    leave = "or leave --jpeg-decoder at cpu (OpenCV's decoder, the default)"
    device = getattr(backend, "wp_device", None) or ""
    if backend.name != "warp" or not device.startswith("cuda"):
        raise ValueError(f"--jpeg-decoder gpu: the backend runs on {backend.device}, not a "
                         "CUDA GPU; nvJPEG decodes into CUDA memory, which the Warp backend "
                         f"reads where it lies: give --backend warp:cuda:N, {leave}")
    try:
        import torch
        import torchvision
        import torchvision.io  # noqa: F401  (its decode_jpeg runs nvJPEG)
    except Exception as e:  # ImportError, or a torchvision built for another torch
        raise ValueError(f"--jpeg-decoder gpu needs torch and torchvision (decode_jpeg runs "
                         f"nvJPEG), and importing them failed ({type(e).__name__}: {e}): pip "
                         f"install torchvision built for the installed torch, {leave}"
                         ) from None
    if not torch.cuda.is_available():
        raise ValueError(f"--jpeg-decoder gpu: torch {torch.__version__} sees no CUDA device "
                         f"(a CPU build of torch?), so nvJPEG cannot decode into {device}: "
                         f"install torch and torchvision built for CUDA, {leave}")
    batches = JpegBatches(device, frames)
    batches.libraries = {"torchvision": torchvision.__version__,
                         "cuda": str(torch.version.cuda)}
    batches.probe()
    return batches


def _read(path: Path) -> np.ndarray:
    """A JPEG file as an I/O thread leaves it: checked bytes (1-D uint8), or decoded pixels.

    The pixels (read_image's) where nvJPEG would not decode the file as libjpeg does.
    """
    data = read_checked(path, str(path), f"; {WAY_OUT}")
    if nvjpeg_size(data) is None:
        return read_image(path)
    return np.frombuffer(data, np.uint8)


def _encoded(image: np.ndarray) -> bool:
    return image.ndim == 1


def _on_host(made: tuple) -> tuple:
    """A made sample's ``(spec, result, error)`` with torch images copied into numpy."""
    spec, result, error = made
    if result is None:
        return made

    def host(x):
        return x if x is None or isinstance(x, np.ndarray) else x.cpu().numpy()

    return spec, dataclasses.replace(result, blurred=host(result.blurred),
                                     sharp=host(result.sharp), _mask=host(result._mask)), error


class JpegBatches:
    """Samples whose files are all JPEGs: read in the I/O threads, decoded in groups on the GPU.

    Args:
        device: the torch device the pixels go to (the Warp backend's, ``cuda:N``).
        frames: each sample is a stack of frames (B x F x H x W x 3 batches, blur mode
            average), else one photo (B x H x W x 3).
        decode: :data:`Decode`, :func:`nvjpeg_decode` by default (tests give the CPU
            decoder's pixels).

    Attributes:
        gpu: indices of the samples whose files ``decode`` decoded.
        cpu: samples of JPEG files decoded on the CPU instead (a file not for nvJPEG, a
            failed check, a failed group).
        files: files ``decode`` decoded.
        seconds: the making thread's time in ``decode`` and stacking its pixels.
        libraries: the versions of the libraries that decode, for the set's run.json
            (:func:`for_backend` names torchvision's and torch's CUDA).
    """

    def __init__(self, device: str, frames: bool, decode: Decode | None = None):
        self.device, self.frames = device, frames
        self.decode = decode or nvjpeg_decode
        self.gpu: set[int] = set()
        self.cpu = self.files = 0
        self.seconds = 0.0
        self.libraries: dict[str, str] = {}

    def probe(self) -> None:
        """Decode a small JPEG on the device, so a broken install fails before any sample."""
        import cv2

        ok, data = cv2.imencode(".jpg", np.zeros((16, 16, 3), np.uint8))
        try:
            self.decode([data.ravel()], self.device)
        except Exception as e:
            raise ValueError(f"--jpeg-decoder gpu: torchvision's decode_jpeg fails on "
                             f"{self.device} ({type(e).__name__}: {e}); install torchvision "
                             "built for the installed torch and CUDA, or leave "
                             "--jpeg-decoder at cpu") from None

    @staticmethod
    def takes(spec) -> bool:
        """Whether a sample's files are read for the GPU: all JPEGs, no roles (mode none)."""
        return bool(spec.inputs) and not spec.problem and not spec.roles and all(
            Path(path).suffix.lower() in JPEG_SUFFIXES for path in spec.inputs)

    @staticmethod
    def read(path: Path) -> np.ndarray:
        """One file in an I/O thread: checked bytes, or decoded pixels (a frame cache's reader).

        Raises:
            ValueError: the file fails a check (:func:`~gpu_blur.image_reading.read_checked`).
        """
        return _read(Path(path))

    @staticmethod
    def checked(spec, images: list | None,
                check: Callable[[object, list], tuple | None]) -> tuple | None:
        """A sample's files as :meth:`make` takes them, in the I/O thread that read the last.

        All bytes of one size: as they are, for the GPU. Otherwise the bytes are decoded on
        the CPU here and the arrays go through ``check`` (``gpu_blur.generate``'s
        ``checked_inputs``). None, as there, when a file failed: the sample is made from its
        paths.
        """
        if images is None:
            return None
        if all(_encoded(i) for i in images) and len({nvjpeg_size(i) for i in images}) == 1:
            return tuple(images)
        try:
            images = [read_image(path) if _encoded(image) else image
                      for path, image in zip(spec.inputs, images, strict=True)]
        except Exception:  # synthesize meets it again, and says what it is
            return None
        return check(spec, images)

    def make(self, specs: Sequence, inputs: Sequence[tuple | None],
             make_batch: Callable[[list, object], list | None],
             make_sample: Callable[[object, tuple | None], tuple]) -> list[tuple]:
        """A group's samples made, in order: ``(spec, result, error)`` each.

        Samples whose files are bytes (:meth:`checked`) are decoded in one call and made in
        batches of one size (``make_batch(specs, batch)``, a torch batch on :attr:`device`;
        results copied to numpy). The others, and all of a group whose decode or batch fails,
        go to ``make_sample(spec, inputs)``: with their CPU-decoded arrays, or None (read
        from their paths, so an error names the file).
        """
        made: list[tuple | None] = [None] * len(specs)
        encoded = [i for i, given in enumerate(inputs) if given and _encoded(given[0])]
        pixels = self._decoded([inputs[i] for i in encoded]) if encoded else None
        if pixels is not None:
            import torch

            sizes: dict[tuple, dict[int, object]] = {}
            for i, sample in zip(encoded, pixels, strict=True):
                sizes.setdefault(tuple(sample.shape), {})[i] = sample
            for members in sizes.values():
                results = make_batch([specs[i] for i in members],
                                     torch.stack(list(members.values())))
                for i, result in zip(members, results or (), strict=False):
                    made[i] = _on_host(result)
                    self.gpu.add(specs[i].index)
        for i, spec in enumerate(specs):
            if made[i] is None:
                self.cpu += 1
                made[i] = make_sample(spec, None if i in encoded else inputs[i])
        return made

    def _decoded(self, samples: list[tuple]) -> list | None:
        """Each sample's pixels, F x H x W x 3 (or H x W x 3), from one ``decode``; or None."""
        import torch

        start = time.perf_counter()
        files = [data for sample in samples for data in sample]
        try:
            images = self.decode(files, self.device)
        except Exception:  # a decoder's error: made from their paths on the CPU instead
            self.seconds += time.perf_counter() - start
            return None
        self.files += len(files)
        out, at = [], 0
        for sample in samples:
            frames = torch.stack(images[at:at + len(sample)]).permute(0, 2, 3, 1)
            out.append(frames if self.frames else frames[0])
            at += len(sample)
        self.seconds += time.perf_counter() - start
        return out

    def record(self, spec) -> dict:
        """What a sample's manifest line adds: ``{"jpeg_decoder": "gpu"}`` if decoded here."""
        return {"jpeg_decoder": "gpu"} if spec.index in self.gpu else {}

    def summary(self) -> str:
        """The run summary's line: the decoder, and the samples each decoder took."""
        return (f"JPEG decoder: gpu (nvJPEG on {self.device}): {len(self.gpu)} samples, "
                f"{self.files} files, {self.seconds:.2f} s on the making thread; "
                f"{self.cpu} samples of JPEG files decoded on the CPU instead (not baseline "
                "YCbCr, a file refused, or a failed group)")
