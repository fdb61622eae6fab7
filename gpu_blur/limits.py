"""The allowed range of every numeric setting, with its reason: one check for every number.

Scene keys (:data:`gpu_blur.scene.FIELDS`), camera files (:func:`gpu_blur.cameras.load_camera`)
and overrides of drawn values (:func:`gpu_blur.params.draw_params`) check a number with
:meth:`Limit.problem` against the constants below, so a value is refused in the same words
wherever it is given: the caller names the file and the key, the limit says what is allowed
and why. Input files are bounded here too: an image's pixels (:func:`max_pixels`) and a given
kernel's sides (:data:`KERNEL_SIDE`), both read from the file's header before it is decoded.

Every number must be finite. The ranges are physical, with a margin (a white-balance gain of
1e30 is no camera), and chosen so that float32 kernels stay within the tolerance table of the
numpy reference (:mod:`gpu_blur.tolerances`). Measured on Intel's CPU OpenCL runtime
``opencl:0:0`` and Warp ``cpu``, float32, the values given as overrides (blur mode none, RAW
round trip, A7R3 camera unless said):

* Representable (16 x 16 photo, float output against the reference): K failed at 1e-40 (a
  denormal, flushed to 0: OpenCL all black, Warp all NaN) and at 1e39 (inf), and agreed from
  1e-38 to 1e38 (within 3.3e-6); a WB gain failed at 1e-37 (the rate x / (gain K) overflows:
  OpenCL off by up to 1, Warp NaN) and at 1e39, agreed from 1e-30 to 1e37; the read-noise std
  failed at 1e38 (std z overflows), agreed up to 1e37; alpha failed at 1e39 (inf x 0 = NaN:
  black); the sRGB Gaussian std never did (to 1e39: the sum clips as in the reference).
* Within the tolerance table (64 x 64 and 128 x 128 photos, 1 to 6 samples, 8-bit output,
  ``verify=1``: every pass against the reference, see :mod:`gpu_blur.scheduler`): the noise
  in RAW units, ``gain * sqrt(K x + std^2)``, sets the RAW values' size, and the to_raw and
  finish rows are absolute. With gain 8: K 0.25 with std 0.05 passed 6 samples, K 0.25 with
  std 0.1 failed one of 3 on OpenCL (finish), K 1 with std 0.1 failed (to_raw, 8.1e-7 >
  5e-7); gain 10 with K 1 failed; gain 100 failed from K 1e-4 with std 0.1; gains 1 and 4
  passed up to K 1 with std 0.1, gain 0.1 up to K 0.2 with std 0.2. A Lin2Cam of 8 x the
  identity (RAW values to 8) failed at the default noise; a Cam2Lin with rows [8, -4, -3]
  passed; sRGB Gaussian noise of std 0.5 and 1 passed.

So K <= 0.125, std <= 0.025 and gains <= 8: K and the std of a sample are drawn in
``level * (1 +- noise.spread)``, spread <= 1 (:func:`gpu_blur.reference.noise.draw_noise_levels`),
so a drawn K lies in [2^-23 * 1e-9, 0.25] and a drawn std in [0, 0.05], the passing corner
above. Drawn values are therefore not checked again; overrides are held to the ranges of the
levels.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os

from gpu_blur.reference.shake import SHAKE_AUTO_STEPS_RANGE, SHAKE_ROLL_MAX_DEG

__all__ = ["ALPHA", "CAM2LIN_LARGEST", "CRF_TABLE_SIZE", "CROP", "EXTENT", "FRAMES", "GAUSSIAN_STD",
           "IMAGE_PIXELS", "INTERPOLATION_REGION", "INTERPOLATION_TOLERANCE", "JPEG_QUALITY",
           "KERNEL_SIDE", "KERNEL_SIZE", "LIN2CAM_LARGEST", "Limit", "MAX_PIXELS",
           "MAX_PIXELS_VARIABLE", "NORMAL_ABOVE", "READ_NOISE_STD", "ROLL", "SHOT_NOISE_K",
           "SPREAD", "STEPS", "STRIDE", "VIGNETTING", "WB_GAIN", "WB_WEIGHT", "max_pixels"]


@dataclasses.dataclass(frozen=True)
class Limit:
    """The allowed values of one numeric setting.

    Attributes:
        low: the smallest allowed value.
        high: the largest (``math.inf``: no upper bound, but still finite).
        reason: why, for the error message: units, what the bound means, what fails beyond.
        integer: only integers (bools are not numbers here).
        low_open: ``low`` itself is not allowed (a gain of 0 divides by zero).
    """

    low: float
    high: float = math.inf
    reason: str = ""
    integer: bool = False
    low_open: bool = False

    @property
    def kind(self) -> str:
        """``int`` or ``int or float``, as messages name the type."""
        return "int" if self.integer else "int or float"

    def describe(self) -> str:
        """The range in words, e.g. ``>= 0.125 and <= 8``."""
        low = f"{'>' if self.low_open else '>='} {self.low:g}"
        return low if self.high == math.inf else f"{low} and <= {self.high:g}"

    def problem(self, value) -> str | None:
        """What ``value`` must be, when it is not allowed; ``None`` when it is.

        The text follows ``allowed:`` in a caller's message: the type and the bound it broke,
        then the reason, e.g. ``int or float <= 1 (...)``.
        """
        number = numbers.Integral if self.integer else numbers.Real
        if isinstance(value, bool) or not isinstance(value, number):
            return self._say(f"{self.kind} {self.describe()}")
        try:
            x = float(value)
        except OverflowError:  # an integer beyond float64 (JSON allows any)
            x = math.inf
        if not math.isfinite(x):
            return self._say(f"a finite {self.kind} {self.describe()}")
        if x < self.low or (self.low_open and x == self.low):
            return self._say(f"{self.kind} {'>' if self.low_open else '>='} {self.low:g}")
        if x > self.high:
            return self._say(f"{self.kind} <= {self.high:g}")
        return None

    def _say(self, allowed: str) -> str:
        return f"{allowed} ({self.reason})" if self.reason else allowed


# -- the scene's blur ---------------------------------------------------------------------------
FRAMES = Limit(1, 1024, integer=True, reason=(
    "frames averaged per sample, each held in host memory: 1,024 frames of 1920 x 1080 take "
    "6.4 GB; RSBlur averages 9"))
STRIDE = Limit(0, 1_000_000, integer=True, reason=(
    "frames from one window's first frame to the next one's in mode 'average', 0 = "
    "blur.frames (windows side by side); fewer overlap, more leave frames out between "
    "windows; a stride beyond a sequence's length takes its first window only"))
#: 8 x the auto choice's largest (reference.shake.SHAKE_AUTO_STEPS_RANGE, about one pose per
#: pixel of the path); each pose costs a bilinear read per pixel (numpy: ~0.2 us per pixel and
#: pose, 31 s for 8,192 poses on 128 x 128) and 72 bytes of float64 3 x 3 on the device.
STEPS = Limit(0, 8 * (SHAKE_AUTO_STEPS_RANGE[1] - 1), integer=True, reason=(
    "camera poses, 0 = auto: 9 to 1,025, about one per pixel of the path; more poses than "
    "pixels along the path change nothing, and each costs a read per pixel"))
INTERPOLATION_TOLERANCE = Limit(0, 1000, low_open=True, reason=(
    "pixels a step between consecutive averaged frames may span under blur.interpolation = "
    "'auto': a gap moving more gets 2, 4 or 8 x its frames (8 at most, so a tiny tolerance "
    "gives 8x everywhere); a tolerance above the motion inserts nothing"))
INTERPOLATION_REGION = Limit(0, 4096, integer=True, reason=(
    "pixels a side of the square regions that get their own factor under blur.interpolation "
    "= 'auto', 0 for one factor per gap; a multiple of 16 (whole pixels of the 1/4-size "
    "motion measure), and 4,096 is beyond a frame's side"))
EXTENT = Limit(0, reason="pixels the image centre moves; the image's size bounds it per sample")
ROLL = Limit(0, SHAKE_ROLL_MAX_DEG, reason="degrees of camera roll; the shake model's largest")
KERNEL_SIZE = Limit(1, 255, integer=True, reason=(
    "pixels across a random motion kernel, a read per pixel and tap: 255 x 255 is 65,025 "
    "taps; GoPro_U used 5 to 29"))
#: A side of a given kernel (a blur.kernel file, or an override), about twice KERNEL_SIZE's:
#: measured camera-shake kernels span tens of pixels (Levin et al. 2009: 13 to 27; GoPro_U's
#: random ones 5 to 29), while 511 pixels is 27 % of a 1920 x 1200 RSBlur frame's width and
#: 71 % of a GoPro frame's 720 rows, the largest images gpu_blur makes from the data sets: a
#: wider kernel is not camera shake for those. Checked on a .npy file's header and an image's
#: before they are loaded (gpu_blur.kernel_files.read_kernel).
KERNEL_SIDE = Limit(1, 511, integer=True, reason=(
    "pixels a side of a given kernel, a read per pixel and tap: 511 x 511 is 261,121 taps; "
    "measured camera-shake kernels span tens of pixels, 511 is a quarter of a 1920-pixel "
    "frame"))
# -- saturation and noise -----------------------------------------------------------------------
ALPHA = Limit(0, 100, reason=(
    "highlight boost: alpha x mask is added before clipping to 1, so alpha >= 1 already clips "
    "a fully masked pixel; RSBlur draws 0.25 to 1.75"))
SHOT_NOISE_K = Limit(1e-9, 0.125, reason=(
    "Poisson gain K, the signal one photon adds to the [0, 1] RAW range: 1e-9 is a billion "
    "photons at full scale, 0.125 eight; RealBlur 8.9e-5, RSBlur 1e-4; float32 kernels leave "
    "the tolerance table beyond (gpu_blur.limits)"))
READ_NOISE_STD = Limit(0, 0.025, reason=(
    "read-noise std in [0, 1] RAW units, 0.025 is 2.5 % of the whole range; RealBlur 2.9e-5, "
    "RSBlur 9.2e-4; float32 kernels leave the tolerance table beyond (gpu_blur.limits)"))
SPREAD = Limit(0, 1, reason="K and the std are drawn in level * (1 +- spread), so K stays > 0")
GAUSSIAN_STD = Limit(0, 0.5, reason=(
    "sRGB noise std, drawn up to twice this: 1 is noise as large as the whole range; RSBlur "
    "0.0112"))
NORMAL_ABOVE = Limit(0, reason=(
    "a Poisson rate in counts per photosite; for no approximation use noise.poisson = "
    "'exact'"))
# -- output -------------------------------------------------------------------------------------
CROP = Limit(0, integer=True, reason="pixels cropped from each side")
VIGNETTING = Limit(0, 1, reason=(
    "vignetting strength s: the gain 1 - s (r / r_corner)^2 falls from 1 at the image centre "
    "to 1 - s at its corners; above 1 it would turn negative"))
CRF_TABLE_SIZE = Limit(0, 65536, integer=True, reason=(
    "nodes of the re-toning table, 0 = the authors' 2,551"))
JPEG_QUALITY = Limit(1, 100, integer=True, reason=(
    "libjpeg's quality scale: 1 is the coarsest quantization table, 100 the finest; camera "
    "JPEGs are about 85 to 98"))
# -- camera files -------------------------------------------------------------------------------
WB_GAIN = Limit(0.125, 8.0, reason=(
    "a white-balance gain relative to green: the presets' lie within 1 and 2.92; it scales "
    "the RAW noise, and float32 kernels leave the tolerance table beyond (gpu_blur.limits)"))
WB_WEIGHT = Limit(0, 1e12, low_open=True, reason=(
    "how often a (red, blue) pair is drawn, e.g. its row count; RealBlur's list: up to 1,380"))
#: How far a camera's matrices may scale a colour: the largest |output| of an input in
#: [0, 1]^3 (per row, the sum of the positive entries or of the negative ones). Lin2Cam gives
#: the RAW signal of a linear colour, which must stay near [0, 1] for the float32 tolerance (a
#: Lin2Cam of 8 x the identity failed, see above); presets: 1.0 to 1.11 (a desaturating Cam2Lin
#: of tests/backends/test_hard_cases.py: 1.6). Cam2Lin turns RAW into linear sRGB; presets: 1.0
#: to 2.2 (a Cam2Lin with rows [8, -4, -3] passed).
LIN2CAM_LARGEST = Limit(0, 2.0, reason=(
    "the largest RAW value Lin2Cam, the inverse of Cam2Lin, gives a [0, 1] colour; the "
    "presets' is at most 1.11"))
CAM2LIN_LARGEST = Limit(0, 8.0, reason=(
    "the largest linear value Cam2Lin gives a [0, 1] camera colour; the presets' is at most "
    "2.2"))
# -- input files --------------------------------------------------------------------------------
#: The environment variable that replaces :data:`MAX_PIXELS` (see :func:`max_pixels`).
MAX_PIXELS_VARIABLE = "GPU_BLUR_MAX_PIXELS"
#: The most pixels (width x height) an image file may hold by default: 2^28, 268 MP. It is
#: read from the file's header before anything is decoded (gpu_blur.image_reading.read_image), as
#: a PNG of one colour is a few hundred KB at 12000 x 12000 and decoding takes at least 3 bytes
#: a pixel (8-bit RGB; 6 for 16 bits, 12 for float TIFFs), then 24 as float64: 0.8 GB and
#: 6.4 GB at 2^28. One frame of the largest camera sensors is about 150 MP; the data sets
#: gpu_blur reads are at most 1920 x 1200, the largest image of the tests and benchmarks
#: 5000 x 5000. Raise it with GPU_BLUR_MAX_PIXELS for larger images (e.g. stitched
#: panoramas); OpenCV's own limit, 2^30 (its OPENCV_IO_MAX_IMAGE_PIXELS), applies after it.
MAX_PIXELS = 2**28
IMAGE_PIXELS = Limit(1, integer=True, reason=(
    "pixels (width x height) an image file may hold, read from its header before decoding"))


def max_pixels() -> int:
    """The pixel budget of an image file: ``GPU_BLUR_MAX_PIXELS`` when set, else MAX_PIXELS.

    The variable is read at each call, so it may be set after import.

    Raises:
        ValueError: naming the variable and its value when it is not a whole number >= 1.
    """
    text = os.environ.get(MAX_PIXELS_VARIABLE, "").strip()
    if not text:
        return MAX_PIXELS
    try:
        value = int(text)
    except ValueError:
        value = None
    problem = IMAGE_PIXELS.problem(text if value is None else value)
    if problem:
        raise ValueError(
            f"environment variable {MAX_PIXELS_VARIABLE} = {text!r} is invalid; allowed: "
            f"{problem}; set it to a number of pixels such as {2 * MAX_PIXELS} (2^29), or "
            f"unset it for the default, {MAX_PIXELS} (2^28)")
    return value
