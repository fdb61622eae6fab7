from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gpu_blur.reference.average import FrameAccumulator, average_frames, saturation_indicator
from gpu_blur.reference.motion_kernel import (
    GOPRO_U_KERNEL_SIZES,
    KERNEL_EXTENT_MIN,
    KERNEL_UNIFORMS,
    KERNEL_WALK_VALUES,
    convolve_kernel,
    kernel_halo,
    kernel_walk_values,
    normalize_kernel,
    random_motion_kernel,
)
from gpu_blur.reference.shake import (
    SHAKE_UNIFORMS,
    auto_shake_steps,
    camera_shake_homographies,
    shake_blur,
    shake_halo,
    warp_homography,
)
from gpu_blur.testing import assert_close


def uniforms(seed: int, count: int) -> np.ndarray:
    """Uniforms in the open interval (0, 1), as the caller's generator would hand them over."""
    return np.clip(np.random.default_rng(seed).random(count), 1e-12, 1.0 - 1e-12)


def translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def intrinsics(height: int, width: int) -> np.ndarray:
    f = float(max(height, width))
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def reflect101(index: np.ndarray, n: int) -> np.ndarray:
    """Mirror without repeating the edge, written out independently of the module."""
    index = np.asarray(index)
    if n == 1:
        return np.zeros_like(index)
    out = index.copy()
    for _ in range(64):  # bounce until inside
        out = np.where(out < 0, -out, out)
        out = np.where(out > n - 1, 2 * (n - 1) - out, out)
    return out


def smooth_image(height: int, width: int) -> np.ndarray:
    """Sinusoids with |d/dx| <= 0.4 * 2 pi / 37 and |d/dy| <= 0.4 * 2 pi / 53 per pixel."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    phases = (0.0, 1.0, 2.0)
    return np.stack(
        [
            0.5 + 0.4 * np.sin(2 * np.pi * x / 37 + p) * np.cos(2 * np.pi * y / 53 - p)
            for p in phases
        ],
        axis=2,
    )


# ---------------------------------------------------------------------------------------
# Averaging and the saturation indicator
# ---------------------------------------------------------------------------------------


def test_average_of_identical_frames_is_the_frame():
    frame = np.random.default_rng(0).random((6, 7, 3))
    blurred, mask = average_frames(frame.copy() for _ in range(8))
    # the running sum x + x + ... rounds at 3x, 5x, ...: (n - 1) * 2**-53 relative at most
    assert_close(blurred, frame, "blur_mean_of_copies")
    np.testing.assert_array_equal(mask, np.zeros_like(frame))


def test_saturation_mask_is_the_per_channel_fraction_of_saturated_frames():
    frames = [np.full((2, 3, 3), 0.25) for _ in range(4)]
    frames[0][0, 0, 1] = 1.0  # green saturated in 2 of 4 frames at (0, 0)
    frames[2][0, 0, 1] = 1.0
    frames[1][1, 2, :] = 1.0  # all channels in 1 of 4 frames at (1, 2)
    frames[3][1, 2, 0] = 1.0  # red also in a second frame
    _, mask = average_frames(frames)
    expected = np.zeros((2, 3, 3))
    expected[0, 0] = (0.0, 0.5, 0.0)  # neither "any channel" (0.5, 0.5, 0.5) nor "all" (0, 0, 0)
    expected[1, 2] = (0.5, 0.25, 0.25)
    np.testing.assert_array_equal(mask, expected)


def test_saturation_counts_values_at_or_above_one_only():
    values = np.array([0.999999999, 1.0, 1.5, 0.0, -1.0, np.nan])
    np.testing.assert_array_equal(saturation_indicator(values), [0, 1, 1, 0, 0, 0])
    assert saturation_indicator(values).dtype == np.float64


def test_average_of_1000_random_frames_matches_numpy_mean():
    rng = np.random.default_rng(1)
    frames = rng.random((1000, 8, 9, 3))
    acc = FrameAccumulator(8, 9)
    for frame in frames:
        acc.add(frame)
    blurred, mask = acc.result()
    assert acc.count == 1000
    assert_close(blurred, frames.mean(axis=0), "blur_average", "independent")
    exact = np.apply_along_axis(math.fsum, 0, frames) / 1000  # correctly rounded sums
    assert_close(blurred, exact, "blur_average", "independent")
    np.testing.assert_array_equal(mask, np.zeros((8, 9, 3)))


def test_accumulator_result_can_be_read_before_more_frames_are_added():
    acc = FrameAccumulator(1, 2)
    acc.add(np.full((1, 2, 3), 0.5))
    first, _ = acc.result()
    acc.add(np.full((1, 2, 3), 1.0))
    second, mask = acc.result()
    np.testing.assert_array_equal(first, np.full((1, 2, 3), 0.5))
    np.testing.assert_array_equal(second, np.full((1, 2, 3), 0.75))
    np.testing.assert_array_equal(mask, np.full((1, 2, 3), 0.5))


def test_zero_frames_is_an_error():
    with pytest.raises(ValueError, match="zero frames"):
        average_frames([])
    with pytest.raises(ValueError, match="zero frames"):
        FrameAccumulator(4, 4).result()


def test_frame_shape_mismatch_error_names_both_shapes():
    acc = FrameAccumulator(4, 5)
    acc.add(np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match=r"\(5, 4, 3\).*\(4, 5, 3\)"):
        acc.add(np.zeros((5, 4, 3)))
    with pytest.raises(ValueError, match=r"\(4, 5, 1\).*\(4, 5, 3\)"):
        average_frames([np.zeros((4, 5, 3)), np.zeros((4, 5, 1))])


def test_non_finite_frames_are_rejected():
    with pytest.raises(ValueError, match="finite"):
        FrameAccumulator(1, 1).add(np.array([[[0.0, np.nan, 0.0]]]))


# ---------------------------------------------------------------------------------------
# Kernel blur
# ---------------------------------------------------------------------------------------


def opencv_convolve(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """cv2.filter2D correlates: flip the kernel for a convolution; anchor at its centre."""
    k = normalize_kernel(kernel)[::-1, ::-1].copy()
    planes = image if image.ndim == 3 else image[:, :, None]
    out = np.stack(
        [
            cv2.filter2D(
                np.ascontiguousarray(planes[:, :, c]),
                cv2.CV_64F,
                k,
                anchor=(-1, -1),
                borderType=cv2.BORDER_REFLECT_101,
            )
            for c in range(planes.shape[2])
        ],
        axis=2,
    )
    return out.reshape(image.shape)


@pytest.mark.parametrize(
    "kernel_shape, image_shape",
    [
        ((3, 3), (61, 47, 3)),
        ((7, 5), (40, 53, 3)),  # asymmetric and not square
        ((29, 29), (90, 75, 1)),
        ((65, 65), (120, 140)),
    ],
)
def test_convolve_matches_opencv_filter2d_reflect101(kernel_shape, image_shape):
    rng = np.random.default_rng(2)
    image = rng.random(image_shape)
    kernel = rng.random(kernel_shape) ** 4  # lopsided weights: a flip would show
    kernel[0, 0] = 0.0
    assert_close(
        convolve_kernel(image, kernel),
        opencv_convolve(image, kernel),
        "blur_convolve",
        "independent",
    )


def test_convolve_matches_opencv_with_a_motion_kernel(coffee_rgb):
    kernel = random_motion_kernel(uniforms(3, KERNEL_UNIFORMS), 29)
    image = coffee_rgb[:200, :300]
    assert_close(
        convolve_kernel(image, kernel),
        opencv_convolve(image, kernel),
        "blur_convolve",
        "independent",
    )


def test_convolve_flips_the_kernel():
    image = np.random.default_rng(4).random((20, 30))
    kernel = np.zeros((5, 5))
    kernel[2, 4] = 1.0  # mass two pixels right of the centre: content moves right by two
    kernel[1, 2] = 1.0  # and one pixel up
    out = convolve_kernel(image, kernel)
    expected = 0.5 * (np.roll(image, 2, axis=1) + np.roll(image, -1, axis=0))
    assert_close(out[2:-2, 3:-3], expected[2:-2, 3:-3], "blur_convolve", "independent")


def test_convolve_with_a_kernel_larger_than_the_image_mirrors_periodically():
    rng = np.random.default_rng(5)
    image = rng.random((4, 6))
    kernel = rng.random((11, 13))
    k = kernel / kernel.sum()
    rows, cols = np.arange(4), np.arange(6)
    expected = np.zeros_like(image)
    for i in range(11):
        for j in range(13):
            src_r = reflect101(rows + 5 - i, 4)
            src_c = reflect101(cols + 6 - j, 6)
            expected += k[i, j] * image[np.ix_(src_r, src_c)]
    assert_close(convolve_kernel(image, kernel), expected, "blur_convolve", "independent")


def test_delta_kernel_is_the_identity():
    image = np.random.default_rng(6).random((33, 17, 3))
    kernel = np.zeros((9, 9))
    kernel[4, 4] = 3.0
    assert_close(convolve_kernel(image, kernel), image, "blur_convolve", "independent")


def test_kernel_is_normalized_to_sum_one():
    rng = np.random.default_rng(7)
    image = rng.random((25, 31, 3))
    kernel = rng.random((5, 5))
    assert math.isclose(normalize_kernel(7.0 * kernel).sum(), 1.0, rel_tol=1e-15)
    assert_close(
        convolve_kernel(image, 7.0 * kernel),
        convolve_kernel(image, kernel),
        "blur_convolve",
        "independent",
    )
    flat = np.full((25, 31, 3), 0.3)
    assert_close(convolve_kernel(flat, 7.0 * kernel), flat, "blur_convolve", "independent")


@pytest.mark.parametrize("shape", [(12, 10), (12, 10, 1), (12, 10, 3), (1, 1, 3), (12, 10, 6)])
def test_convolve_keeps_the_input_shape(shape):
    out = convolve_kernel(np.ones(shape), np.ones((3, 3)))
    assert out.shape == shape
    assert out.dtype == np.float64


@pytest.mark.parametrize(
    "kernel, message",
    [
        (np.ones((4, 4)), "odd"),
        (np.ones((3, 4)), "odd"),
        (np.ones(3), "odd"),
        (np.zeros((3, 3)), "positive"),
        (np.array([[0.0, 0.0, 0.0], [0.0, 1.0, -0.1], [0.0, 0.0, 0.0]]), "non-negative"),
        (np.array([[0.0, 0.0, 0.0], [0.0, 1.0, np.nan], [0.0, 0.0, 0.0]]), "finite"),
    ],
)
def test_bad_kernels_are_rejected(kernel, message):
    with pytest.raises(ValueError, match=message):
        convolve_kernel(np.ones((8, 8, 3)), kernel)


def test_kernel_halo_is_half_the_size():
    assert kernel_halo(np.ones((29, 29))) == 14
    assert kernel_halo(np.ones((5, 9))) == 4
    assert kernel_halo(5) == 2
    with pytest.raises(ValueError):
        kernel_halo(4)


# ---------------------------------------------------------------------------------------
# Random motion kernels
# ---------------------------------------------------------------------------------------


def centroid(kernel: np.ndarray) -> tuple[float, float]:
    rows, cols = np.mgrid[0 : kernel.shape[0], 0 : kernel.shape[1]]
    return float((kernel * rows).sum()), float((kernel * cols).sum())


@pytest.mark.parametrize("size", GOPRO_U_KERNEL_SIZES)
def test_motion_kernel_is_a_centred_normalised_kernel_that_fits(size):
    for seed in range(8):
        kernel = random_motion_kernel(uniforms(100 * size + seed, KERNEL_UNIFORMS), size)
        assert kernel.shape == (size, size)
        assert (kernel >= 0).all()
        assert_close(kernel.sum(), 1.0, "kernel_sum")
        # the centroid is the centre pixel (asked for: within half a pixel; we claim ~1e-9)
        assert_close(centroid(kernel), (size // 2, size // 2), "kernel_centroid")
        # the path uses its grid: it reaches at least KERNEL_EXTENT_MIN of the half-size
        rows, cols = np.nonzero(kernel > 0)
        reach = max(np.abs(rows - size // 2).max(), np.abs(cols - size // 2).max())
        assert reach >= math.floor(KERNEL_EXTENT_MIN * (size // 2))
        # it is a blur, not a spike: no pixel holds more than half the mass
        assert kernel.max() < 0.5


@pytest.mark.bits
def test_motion_kernels_keep_their_recorded_bits():
    """3,000 kernels of every GoPro_U size from the pipeline's own draws hash as recorded when
    the walk's Box-Muller, turns and lengths moved to fixedmath and plain IEEE operations
    (the same digest with numpy's AVX-512 paths off: tests/reference/test_fixedmath.py runs this
    draw in both); any change to a kernel's bits would move every kernel-blur output."""
    import hashlib

    from gpu_blur.reference import rng

    digest = hashlib.sha256()
    for i in range(3000):
        u = rng.image_uniforms(11, i, rng.Stream.KERNEL, KERNEL_UNIFORMS)
        digest.update(random_motion_kernel(u, 5 + 2 * (i % 13)).tobytes())
    assert digest.hexdigest()[:32] == "a26f2660a1c300bac43178f9546867b6"


def test_motion_kernels_walk_values_made_for_a_batch_give_the_same_bits():
    """kernel_walk_values of many rows at once, each row handed to random_motion_kernel, makes
    each kernel's bits as one made alone (a batch's draws take them so); a wrong shape is named."""
    rows = np.stack([uniforms(40 + i, KERNEL_UNIFORMS) for i in range(16)])
    walks = kernel_walk_values(rows)
    assert walks.shape == (16, KERNEL_WALK_VALUES)
    for u, walk in zip(rows, walks, strict=True):
        assert random_motion_kernel(u, 23, walk).tobytes() == random_motion_kernel(u, 23).tobytes()
    with pytest.raises(ValueError, match=f"needs \\({KERNEL_WALK_VALUES},\\) walk values"):
        random_motion_kernel(rows[0], 23, walks[0][:-1])


def test_motion_kernel_is_deterministic_in_its_uniforms():
    u = uniforms(11, KERNEL_UNIFORMS)
    first = random_motion_kernel(u, 21)
    np.testing.assert_array_equal(first, random_motion_kernel(u.copy(), 21))
    other = random_motion_kernel(uniforms(12, KERNEL_UNIFORMS), 21)
    assert np.abs(first - other).sum() > 0.1
    nudged = u.copy()
    nudged[5] = 1.0 - nudged[5]  # the first step's Gaussian turn
    assert np.abs(first - random_motion_kernel(nudged, 21)).sum() > 1e-6


@pytest.mark.parametrize(
    "u, size, message",
    [
        (np.full(KERNEL_UNIFORMS - 1, 0.5), 9, "exactly"),
        (np.full(KERNEL_UNIFORMS + 1, 0.5), 9, "exactly"),
        (np.concatenate([[0.0], np.full(KERNEL_UNIFORMS - 1, 0.5)]), 9, "open interval"),
        (np.concatenate([[1.0], np.full(KERNEL_UNIFORMS - 1, 0.5)]), 9, "open interval"),
        (np.full(KERNEL_UNIFORMS, 0.5), 8, "odd"),
        (np.full(KERNEL_UNIFORMS, 0.5), 1, "odd"),
    ],
)
def test_motion_kernel_rejects_bad_arguments(u, size, message):
    with pytest.raises(ValueError, match=message):
        random_motion_kernel(u, size)


# ---------------------------------------------------------------------------------------
# Camera-shake homographies
# ---------------------------------------------------------------------------------------


def centre_path(homographies: np.ndarray, height: int, width: int) -> np.ndarray:
    centre = np.array([(width - 1) / 2, (height - 1) / 2, 1.0])
    p = homographies @ centre
    return p[:, :2] / p[:, 2:]


def rotations(homographies: np.ndarray, height: int, width: int) -> np.ndarray:
    k = intrinsics(height, width)
    return np.linalg.inv(k) @ homographies @ k


@pytest.mark.parametrize("steps", [1, 3, 17, 65])
def test_homographies_have_the_identity_at_the_middle_step(steps):
    hom = camera_shake_homographies(uniforms(20, SHAKE_UNIFORMS), 400, 600, steps, 30.0, 2.0)
    assert hom.shape == (steps, 3, 3)
    assert hom.dtype == np.float64
    np.testing.assert_array_equal(hom[steps // 2], np.eye(3))
    if steps > 1:
        assert np.abs(hom[0] - np.eye(3)).max() > 1e-4


def test_one_step_is_the_identity():
    hom = camera_shake_homographies(uniforms(21, SHAKE_UNIFORMS), 100, 80, 1, 20.0, 5.0)
    np.testing.assert_array_equal(hom, np.eye(3)[None])


@pytest.mark.parametrize("extent_px", [0.5, 10.0, 40.0, 150.0])
@pytest.mark.parametrize("seed", [22, 23])
def test_centre_path_extent_is_extent_px(extent_px, seed):
    height, width = 400, 600
    hom = camera_shake_homographies(
        uniforms(seed, SHAKE_UNIFORMS), height, width, 17, extent_px, 3.0
    )
    path = centre_path(hom, height, width)
    diagonal = math.hypot(np.ptp(path[:, 0]), np.ptp(path[:, 1]))
    assert_close(diagonal, extent_px, "shake_extent")


@pytest.mark.parametrize(
    "height, width, extent_px", [(6, 8, 11.0), (16, 16, 11.0), (200, 300, 450.0)]
)
def test_extents_large_next_to_the_focal_length_are_still_met(height, width, extent_px):
    # f = max(H, W); here extent_px / f reaches 1.5, where the extent is far from linear in
    # the angles and the search falls back from fixed-point steps to bisection
    for seed in range(60, 66):
        hom = camera_shake_homographies(
            uniforms(seed, SHAKE_UNIFORMS), height, width, 17, extent_px, 2.0
        )
        path = centre_path(hom, height, width)
        assert_close(math.hypot(np.ptp(path[:, 0]), np.ptp(path[:, 1])), extent_px, "shake_extent")
        den = np.linalg.inv(hom)[:, 2] @ np.array(
            [[0, width - 1, 0, width - 1], [0, 0, height - 1, height - 1], [1, 1, 1, 1]]
        )
        assert (den > 0).all()


def test_an_extent_that_turns_the_view_behind_the_camera_is_refused():
    messages = set()
    for seed in range(70, 90):
        try:
            camera_shake_homographies(uniforms(seed, SHAKE_UNIFORMS), 200, 300, 17, 600.0, 2.0)
        except ValueError as error:
            messages.add("behind" if "behind the camera" in str(error) else str(error)[-30:])
    assert "behind" in messages


def test_homographies_are_camera_rotations_with_bounded_roll():
    height, width, roll_deg = 300, 500, 2.5
    for seed in range(24, 30):
        hom = camera_shake_homographies(
            uniforms(seed, SHAKE_UNIFORMS), height, width, 33, 25.0, roll_deg
        )
        rot = rotations(hom, height, width)
        # K^-1 H K is a rotation: orthonormal, determinant 1
        assert_close(
            rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), "shake_rotation"
        )
        assert_close(np.linalg.det(rot), np.ones(33), "shake_rotation")
        # R = R_z(roll) R_x(pitch) R_y(yaw): R[0, 1] = -sin(roll) cos(pitch), R[1, 1] = cos cos
        roll = np.degrees(np.arctan2(-rot[:, 0, 1], rot[:, 1, 1]))
        assert np.abs(roll).max() <= roll_deg * (1 + 1e-12)
        assert np.abs(roll).max() > 0.0


def test_different_uniforms_give_different_paths():
    a = camera_shake_homographies(uniforms(31, SHAKE_UNIFORMS), 200, 300, 9, 15.0, 1.0)
    b = camera_shake_homographies(uniforms(32, SHAKE_UNIFORMS), 200, 300, 9, 15.0, 1.0)
    assert np.abs(centre_path(a, 200, 300) - centre_path(b, 200, 300)).max() > 1.0
    np.testing.assert_array_equal(
        a, camera_shake_homographies(uniforms(31, SHAKE_UNIFORMS), 200, 300, 9, 15.0, 1.0)
    )


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"steps": 0}, "steps"),
        ({"extent_px": -1.0}, "extent_px"),
        ({"extent_px": 1e6}, "beyond 60 degrees"),
        ({"extent_px": float("nan")}, "extent_px"),
        ({"roll_deg": -1.0}, "roll_deg"),
        ({"roll_deg": 45.0}, "roll_deg"),
        ({"uniforms": np.full(SHAKE_UNIFORMS - 1, 0.5)}, "exactly"),
    ],
)
def test_homographies_reject_bad_arguments(kwargs, message):
    args = {
        "uniforms": uniforms(33, SHAKE_UNIFORMS),
        "height": 200,
        "width": 300,
        "steps": 9,
        "extent_px": 10.0,
        "roll_deg": 1.0,
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        camera_shake_homographies(**args)


# ---------------------------------------------------------------------------------------
# Warps
# ---------------------------------------------------------------------------------------


def test_warp_identity_is_exact():
    image = np.random.default_rng(40).random((23, 31, 3))
    np.testing.assert_array_equal(warp_homography(image, np.eye(3)), image)
    np.testing.assert_array_equal(warp_homography(image[:, :, 0], 2.0 * np.eye(3)), image[:, :, 0])


@settings(max_examples=40, deadline=None)
@given(tx=st.integers(-40, 40), ty=st.integers(-40, 40))
def test_warp_integer_translation_is_an_exact_shift(tx, ty):
    height, width = 13, 17
    image = np.random.default_rng(41).random((height, width, 2))
    out = warp_homography(image, translation(tx, ty))
    # away from the borders: a plain shift; everywhere: the reflect-101 extension
    rows = reflect101(np.arange(height) - ty, height)
    cols = reflect101(np.arange(width) - tx, width)
    np.testing.assert_array_equal(out, image[np.ix_(rows, cols)])
    if abs(tx) < width and abs(ty) < height:
        inner = out[max(ty, 0) : height + min(ty, 0), max(tx, 0) : width + min(tx, 0)]
        source = image[max(-ty, 0) : height + min(-ty, 0), max(-tx, 0) : width + min(-tx, 0)]
        np.testing.assert_array_equal(inner, source)


def test_warp_far_outside_tiles_mirrored_copies():
    image = np.random.default_rng(42).random((9, 12, 3))
    # a shift by the mirror's period 2 (n - 1) is the identity; by n - 1 it is the mirror image
    np.testing.assert_array_equal(
        warp_homography(image, translation(2 * 11 * 7, -2 * 8 * 5)), image
    )
    np.testing.assert_array_equal(warp_homography(image, translation(11, 0)), image[:, ::-1])


def test_warp_matches_opencv_warp_perspective():
    height, width = 120, 160
    image = smooth_image(height, width)
    hom = camera_shake_homographies(uniforms(43, SHAKE_UNIFORMS), height, width, 5, 12.0, 4.0)[0]
    hom = hom @ translation(0.37, -0.81)  # make sure positions are not on a nice grid
    expected = cv2.warpPerspective(
        image,
        np.linalg.inv(hom),
        (width, height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT_101,
    )
    # OpenCV rounds sample positions to 1/32 pixel (INTER_BITS = 5): up to 1/64 px per axis,
    # i.e. up to (|dI/dx| + |dI/dy|) / 64 <= (0.068 + 0.047) / 64 = 1.8e-3 on this image
    assert_close(warp_homography(image, hom), expected, "blur_warp_opencv", "independent")


def test_warp_matches_scipy_bilinear_mirror():
    ndimage = pytest.importorskip("scipy.ndimage")
    height, width = 40, 50
    image = np.random.default_rng(44).random((height, width))
    hom = camera_shake_homographies(uniforms(45, SHAKE_UNIFORMS), height, width, 3, 6.0, 8.0)[0]
    hom = hom @ translation(1.3, -2.6)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    src = np.linalg.inv(hom) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    coords = np.stack([src[1] / src[2], src[0] / src[2]])
    # scipy's "mirror" is reflect-101; order=1 is bilinear (without the 1/32 quantization)
    expected = ndimage.map_coordinates(image, coords, order=1, mode="mirror").reshape(height, width)
    assert (coords < 0).any()  # the comparison reaches past the border
    assert_close(warp_homography(image, hom), expected, "blur_warp_bilinear", "independent")


def test_warp_rejects_bad_arguments():
    image = np.ones((8, 8, 3))
    with pytest.raises(ValueError, match="border"):
        warp_homography(image, np.eye(3), border="constant")
    with pytest.raises(ValueError, match="3 x 3"):
        warp_homography(image, np.eye(2))
    with pytest.raises(ValueError, match="invertible"):
        warp_homography(image, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="infinity"):
        warp_homography(image, np.array([[1.0, 0, 0], [0, 1, 0], [0.5, 0, 1]]))


# ---------------------------------------------------------------------------------------
# Shake blur
# ---------------------------------------------------------------------------------------


def test_shake_blur_with_zero_extent_returns_the_image_and_its_indicator(coffee_rgb):
    image = coffee_rgb[100:160, 260:340] ** 2.2 * 1.3  # about a third of the values >= 1
    hom = camera_shake_homographies(uniforms(50, SHAKE_UNIFORMS), 60, 80, 9, 0.0, 0.0)
    np.testing.assert_array_equal(hom, np.broadcast_to(np.eye(3), (9, 3, 3)))
    blurred, mask = shake_blur(image, hom)
    assert_close(blurred, image, "blur_mean_of_copies")
    np.testing.assert_array_equal(mask, saturation_indicator(image))
    assert 0 < mask.mean() < 1


def shifted_on_image(image: np.ndarray, tx: int, ty: int) -> tuple[np.ndarray, np.ndarray]:
    """``image`` moved by (tx, ty) with zeros where it came from outside, and where it did not."""
    h, w = image.shape[:2]
    padded = np.zeros((h + 2 * 8, w + 2 * 8) + image.shape[2:])
    padded[8:-8, 8:-8] = image
    seen = np.zeros((h + 2 * 8, w + 2 * 8))
    seen[8:-8, 8:-8] = 1.0
    rows, cols = slice(8 - ty, 8 - ty + h), slice(8 - tx, 8 - tx + w)
    return padded[rows, cols], seen[rows, cols]


def test_shake_blur_of_integer_translations_averages_the_shifts_that_stay_on_the_image(coffee_rgb):
    """Inside: the kernel convolution. At the edges: the mean over the shifts whose source
    pixel is on the image (no mirrored content), i.e. normalized convolution."""
    image = coffee_rgb[100:150, 260:330] * 1.5  # about a quarter of the values >= 1
    shifts = [(0, 0), (1, 0), (2, 1), (3, 1), (3, 2), (-1, 3), (-2, 3)]
    hom = np.stack([translation(tx, ty) for tx, ty in shifts])
    kernel = np.zeros((7, 7))
    for tx, ty in shifts:
        kernel[3 + ty, 3 + tx] += 1.0
    blurred, mask = shake_blur(image, hom)
    for values, out in ((image, blurred), (saturation_indicator(image), mask)):
        moved = [shifted_on_image(values, tx, ty) for tx, ty in shifts]
        total = sum(v for v, _ in moved)
        count = sum(c for _, c in moved)[..., None]
        assert_close(out, total / count, "blur_convolve", "independent")
        # away from the edges (3 px, the kernel's reach) it is the kernel convolution
        assert_close(out[3:-3, 3:-3], convolve_kernel(values, kernel)[3:-3, 3:-3],
                     "blur_convolve", "independent")
    assert 0 < mask.max() and mask.min() < 1


def test_shake_blur_never_shows_mirrored_content_at_the_edges():
    """A path that leaves the image over its top edge: the top rows average only the rows the
    image holds along the path (a mirrored border would bring the dark rows back up)."""
    h, w = 20, 12
    image = np.zeros((h, w, 3))
    image[:2] = 1.0  # a bright band along the top edge ...
    image[2:6] = 0.25  # ... over dark rows
    hom = np.stack([translation(0, float(t)) for t in range(0, 9)])  # content moves down 0..8
    blurred, mask = shake_blur(image, hom)
    # row y sees rows y, y - 1, ..., y - 8 of the image, those >= 0 only
    for y in range(h):
        rows = [y - t for t in range(9) if y - t >= 0]
        np.testing.assert_allclose(blurred[y], image[rows].mean(axis=0), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(blurred[0], 1.0)  # the edge row: only itself, bright
    np.testing.assert_array_equal(mask[0], 1.0)


def test_shake_blur_at_fractional_positions_weighs_taps_by_their_share_on_the_image():
    """A half-pixel shift out of the image: the edge pixel keeps its own value, weighted by the
    half of its bilinear weight that falls on the image."""
    image = np.arange(1.0, 4.0)[None, :, None] * np.ones((1, 1, 3))  # 1 x 3: 1, 2, 3
    hom = np.stack([np.eye(3), translation(0.5, 0.0)])  # content moves right by 0, 1/2
    blurred, _ = shake_blur(image, hom)
    # column 0: itself (weight 1) and half of pixel 0 (weight 1/2): 1; column 1: 2 and 1.5
    np.testing.assert_array_equal(blurred[0, :, 0], [1.0, (2.0 + 1.5) / 2, (3.0 + 2.5) / 2])


def test_shake_blur_is_zero_where_no_pose_sees_the_image():
    """Two poses, both moving the content 2 px right: the first two columns see nothing."""
    image = np.ones((4, 6, 3))
    blurred, mask = shake_blur(image, np.stack([translation(2, 0), translation(2, 0)]))
    np.testing.assert_array_equal(blurred[:, :2], 0.0)
    np.testing.assert_array_equal(blurred[:, 2:], 1.0)
    np.testing.assert_array_equal(mask[:, 2:], 1.0)


def test_shake_blur_mask_is_the_blurred_indicator():
    image = np.zeros((40, 50, 3))
    image[15:25, 20:30, 0] = 1.0  # a saturated red square
    image[10:12, 5:8, :] = 0.9  # bright, not saturated
    hom = camera_shake_homographies(uniforms(51, SHAKE_UNIFORMS), 40, 50, 9, 6.0, 2.0)
    _, mask = shake_blur(image, hom)
    indicator_blur, _ = shake_blur(saturation_indicator(image), hom)
    np.testing.assert_array_equal(mask, indicator_blur)
    assert 0 < mask[..., 0].max() <= 1 and np.any((mask > 0) & (mask < 1))
    np.testing.assert_array_equal(mask[..., 1:], 0.0)


def point_spread(blurred: np.ndarray, y: int, x: int, radius: int) -> np.ndarray:
    patch = blurred[y - radius : y + radius + 1, x - radius : x + radius + 1, 0]
    return patch / patch.sum()


def test_shake_blur_with_roll_varies_across_the_image():
    height, width, radius = 160, 240, 18
    points = [
        (20, 20),
        (20, width - 21),
        (height - 21, 20),
        (height - 21, width - 21),
        (height // 2, width // 2),
    ]
    image = np.zeros((height, width, 3))
    for y, x in points:
        image[y, x] = 1.0
    hom = camera_shake_homographies(uniforms(52, SHAKE_UNIFORMS), height, width, 33, 8.0, 4.0)
    blurred, _ = shake_blur(image, hom)
    spreads = [point_spread(blurred, y, x, radius) for y, x in points]
    for s in spreads:
        assert_close(s.sum(), 1.0, "kernel_sum")
    # the corners' kernels differ from each other and from the centre's
    for i in range(len(spreads)):
        for j in range(i + 1, len(spreads)):
            assert np.abs(spreads[i] - spreads[j]).sum() > 0.5, (points[i], points[j])
    # without roll and with a pure translation the kernel is the same everywhere
    flat = np.stack([translation(t, 0.5 * t) for t in range(-4, 5)])
    blurred, _ = shake_blur(image, flat)
    same = [point_spread(blurred, y, x, radius) for y, x in points]
    for s in same[1:]:
        assert_close(s, same[0], "blur_convolve", "independent")


def test_shake_halo_covers_the_largest_displacement():
    hom = np.stack([translation(5, -3), translation(-2, 1), np.eye(3)])
    assert shake_halo(hom, 50, 60) == 7  # 5 px, +1 bilinear neighbour, +1 margin
    rolled = camera_shake_homographies(uniforms(53, SHAKE_UNIFORMS), 400, 600, 9, 20.0, 3.0)
    corners = np.array([[0, 0, 1], [599, 0, 1], [0, 399, 1], [599, 399, 1]], dtype=np.float64).T
    reach = 0.0
    for m in rolled:
        q = np.linalg.inv(m) @ corners
        reach = max(reach, np.abs(q[:2] / q[2] - corners[:2]).max())
    assert reach + 1 <= shake_halo(rolled, 400, 600) <= reach + 3


def test_auto_shake_steps_keep_every_pixel_within_about_a_pixel_per_pose():
    u = np.random.default_rng(11).uniform(size=SHAKE_UNIFORMS)
    h, w = 400, 600
    steps = auto_shake_steps(u, h, w, 30.0, 2.0)
    assert steps % 2 == 1 and steps >= 31
    hom = camera_shake_homographies(u, h, w, steps, 30.0, 2.0)
    corners = np.array([[0, 0, 1.0], [w - 1, 0, 1.0], [0, h - 1, 1.0], [w - 1, h - 1, 1.0]])
    p = np.einsum("sij,nj->sni", hom, corners)
    step_px = np.linalg.norm(np.diff(p[..., :2] / p[..., 2:], axis=0), axis=-1)
    assert step_px.max() <= 1.05  # measured <= 0.994 over 60 draws


def test_generate_blurs_only_what_the_photo_holds_at_its_edges(tmp_path, coffee_rgb):
    """``gpu-blur generate``: the saved blurred image is, to the edges, the mean of the photo's
    samples along each saved pose over their weight on the photo (scipy's bilinear sampling of
    the zero-extended photo and of its support), not a mirrored continuation."""
    from scipy.ndimage import map_coordinates

    from gpu_blur.cli import main
    from gpu_blur.image_reading import read_image
    from gpu_blur.reference.transfer import linear_to_srgb, srgb_to_linear

    photo = np.round(coffee_rgb[120:168, 180:244] * 255).astype(np.uint8)
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "p.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    scene = tmp_path / "shake.toml"
    scene.write_text('[blur]\nmode = "trajectory"\nextent = [14.0, 14.0]\nroll = 3.0\n'
                     '[saturation]\nmode = "off"\n[noise]\nmodel = "none"\n[output]\nbits = 0\n')
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                 "--scene", str(scene), "--quiet"]) == 0
    line = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    blurred = read_image(out / line["blurred"]).astype(np.float64)
    with np.load(out / line["arrays"]) as arrays:
        homographies = arrays["homographies"]
    linear = srgb_to_linear(photo / 255.0)
    h, w = photo.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    total, weight = np.zeros((h, w, 3)), np.zeros((h, w))
    for m in homographies:
        q = np.linalg.inv(m) @ np.stack([xs.ravel(), ys.ravel(), np.ones(h * w)])
        where = [(q[1] / q[2]).reshape(h, w), (q[0] / q[2]).reshape(h, w)]
        for values, into in [(np.ones((h, w)), weight)] + [
                (linear[..., c], total[..., c]) for c in range(3)]:
            into += map_coordinates(values, where, order=1, mode="grid-constant", cval=0.0)
    assert weight.min() < len(homographies) - 1  # the path leaves the photo somewhere
    expected = linear_to_srgb(np.clip(total / weight[..., None], 0.0, 1.0))
    assert_close(blurred, expected, "float32_output", "independent")


def test_shake_blur_in_bands_of_rows_equals_the_whole_image_bit_for_bit(monkeypatch):
    from gpu_blur.reference import shake

    rng = np.random.default_rng(3)
    image = rng.random((71, 45, 3))
    image[10:14, 5:9] = 1.0  # saturated, so the mask has content too
    poses = []  # shifts across band edges and a small rotation about the centre
    for t in np.linspace(-1, 1, 7):
        c, s = np.cos(0.02 * t), np.sin(0.02 * t)
        poses.append(np.array([[c, -s, 4.5 * t + 22 * (1 - c) + 35 * s],
                               [s, c, 6.3 * t + 35 * (1 - c) - 22 * s], [0, 0, 1.0]]))
    monkeypatch.setattr(shake, "SHAKE_BAND_ROWS", 1000)
    whole = shake.shake_blur(image, poses)
    monkeypatch.setattr(shake, "SHAKE_BAND_ROWS", 8)  # 71 rows: 8 full bands and a short one
    banded = shake.shake_blur(image, poses)
    for a, b in zip(whole, banded, strict=True):
        assert np.array_equal(a.view(np.uint64), b.view(np.uint64))
