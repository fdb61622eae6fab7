"""Tolerances, in one table, and the comparison helper every test uses.

A tolerance is a claim about a stage on a backend at a precision: ``(stage, backend, dtype) ->
(rtol, atol)``. Tests never write numbers of their own; they name the row they rely on.
"""

from __future__ import annotations

import numpy as np

#: (stage, backend, dtype) -> (rtol, atol). "independent" rows compare the reference with an
#: outside implementation of the same maths (colour-demosaicing, OpenCV, a literal transcription).
TOLERANCES: dict[tuple[str, str, str], tuple[float, float]] = {
    # -- transfer functions --
    # Against a scalar transcription of the defining formula with math.pow.
    ("srgb_transfer", "independent", "float64"): (1e-15, 1e-17),
    # EOTF(OETF(x)): the IEC knees disagree (12.92 * 0.0031308 != 0.04045), which costs up to
    # 2.3e-9 absolute just above the linear knee; elsewhere the round trip is ~1e-16.
    ("srgb_round_trip", "numpy", "float64"): (1e-13, 2.5e-9),
    # Horner against numpy's polyval: rounding in a degree-7 sum with coefficients up to 368.
    ("crf_polynomial", "independent", "float64"): (0.0, 1e-12),
    # -- colour --
    # Composed 3 x 3 matrices against the stage-by-stage chain and the authors' derived values.
    ("color_matrix", "independent", "float64"): (1e-12, 1e-13),
    # lin -> cam -> lin with float64 inverses (condition numbers <= 5.2).
    ("color_round_trip", "numpy", "float64"): (0.0, 1e-13),
    # -- whole pipeline --
    # The RealBlur-J chain with noise off against a literal transcription of the note's steps
    # (row-vector matrices, packed 4-plane mosaic, stored-order gains, correlate with zero pad).
    ("pipeline_realblur_j", "independent", "float64"): (0.0, 1e-9),
    # WB and colour steps cancel with noise off, on a flat field (issue 2: <= 1e-9).
    ("pipeline_wb_color_cancel", "numpy", "float64"): (0.0, 1e-9),
    # -- Bayer and demosaicing --
    # Against colour-demosaicing 0.2.7 (scipy convolve) on photographs: measured bit-identical
    # (max abs difference 0.0); 1e-12 leaves room for another summation order only.
    ("demosaic_malvar2004", "independent", "float64"): (0.0, 1e-12),
    ("demosaic_bilinear", "independent", "float64"): (0.0, 1e-12),
    # A flat field must come back flat: rounding only (Malvar measured <= 4.2e-16 relative).
    ("demosaic_flat_field", "numpy", "float64"): (2e-15, 0.0),
    # x / g * g: two roundings, <= 2.2e-16 relative measured.
    ("white_balance_round_trip", "numpy", "float64"): (1e-15, 0.0),
    # -- random numbers and noise --
    # log(k!) against 50-digit decimal values, k = 16 .. 1e12 (the table below 16 is tested for
    # equality): the Stirling branch measured <= 4.9e-16 relative (at k = 16).
    ("log_factorial", "numpy", "float64"): (6e-16, 0.0),
    # Box-Muller through numpy's log/cos/sin against Python's math (libm): measured over 2e5
    # pairs <= 2.2e-16 absolute and <= 3.5e-16 relative.
    ("box_muller", "independent", "float64"): (5e-16, 5e-16),
    # -- blur --
    # FrameAccumulator's plain float64 running sum of 1,000 frames in [0, 1) against np.mean
    # and an exact math.fsum mean: the running sum's bound (n - 1) * 2**-53 = 1.1e-13 relative.
    ("blur_average", "independent", "float64"): (1.2e-13, 0.0),
    # FFT convolution against cv2.filter2D / a direct sum / exact shifts, images of values
    # <= 1.5, kernels 3x3 .. 65x65: FFT rounding is absolute, a few 1e-16 times max |image|
    # (measured <= 1.4e-15).
    ("blur_convolve", "independent", "float64"): (0.0, 4e-15),
    # Bilinear warp against cv2.warpPerspective: OpenCV rounds positions to 1/32 px, an error up
    # to (|dI/dx| + |dI/dy|) / 64 = 1.8e-3 on the test's sinusoids (gradients <= 0.068, 0.047).
    ("blur_warp_opencv", "independent", "float64"): (0.0, 2e-3),
    # Bilinear warp against scipy.ndimage.map_coordinates(order=1, mode="mirror"): same maths,
    # float64 positions; the order of operations moves positions by ~1e-14 px (measured
    # <= 6e-15 on values in [0, 1]).
    ("blur_warp_bilinear", "independent", "float64"): (0.0, 2e-14),
    # A motion kernel's sum after normalisation, and a blurred point's mass.
    ("kernel_sum", "numpy", "float64"): (0.0, 1e-14),
    # A motion kernel's centroid against its centre pixel, in pixels (asked: 0.5; bilinear
    # splatting keeps the first moment, so only rounding remains: measured <= 3.6e-15).
    ("kernel_centroid", "numpy", "float64"): (0.0, 1e-12),
    # Centre's path extent against extent_px: the iteration stops at 1e-13 relative
    # (SHAKE_EXTENT_RTOL); the test re-measures it with its own rounding.
    ("shake_extent", "numpy", "float64"): (2e-13, 0.0),
    # K^-1 H K against a rotation (orthonormality, determinant).
    ("shake_rotation", "numpy", "float64"): (0.0, 1e-14),
    # The mean of n <= 9 identical frames or warps by a running sum: (n - 1) * 2**-53 relative.
    ("blur_mean_of_copies", "numpy", "float64"): (1e-15, 0.0),
}


def tolerance(stage: str, backend: str = "numpy", dtype: str = "float64") -> tuple[float, float]:
    """Return ``(rtol, atol)`` for a stage; a missing row is an error, never a silent default."""
    try:
        return TOLERANCES[(stage, backend, dtype)]
    except KeyError:
        raise KeyError(
            f"no tolerance row for stage={stage!r}, backend={backend!r}, dtype={dtype!r}; "
            "add one to gpu_blur.testing.TOLERANCES"
        ) from None


def assert_close(
    actual, expected, stage: str, backend: str = "numpy", dtype: str = "float64"
) -> None:
    """Assert ``|actual - expected| <= atol + rtol * |expected|`` under the table's row."""
    rtol, atol = tolerance(stage, backend, dtype)
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    if actual.shape != expected.shape:
        raise AssertionError(f"{stage}: shape {actual.shape} != expected {expected.shape}")
    err = np.abs(actual - expected)
    bound = atol + rtol * np.abs(expected)
    bad = ~(err <= bound)
    if bad.any():
        idx = np.unravel_index(np.argmax(np.where(bad, err - bound, -np.inf)), err.shape)
        raise AssertionError(
            f"{stage} on {backend}/{dtype}: {int(bad.sum())} of {err.size} values out of "
            f"tolerance (rtol={rtol:g}, atol={atol:g}); worst at {idx}: "
            f"{actual[idx]!r} vs {expected[idx]!r} (max abs error {np.nanmax(err):.3g})"
        )
