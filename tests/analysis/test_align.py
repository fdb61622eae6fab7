import json
import math
import os

import cv2
import numpy as np
import pytest

from gpu_blur.analysis import metrics
from gpu_blur.analysis.align import (
    MIN_LEVEL_SIDE,
    AlignmentError,
    align_ecc,
    corner_displacement,
    inside_mask,
    warp_to_reference,
)
from gpu_blur.cli import main
from gpu_blur.reference.shake import warp_homography
from gpu_blur.testing import tolerance

# PSNR over the scored pixels of the moving image warped back with the estimated homography,
# against the same with the true one ("rotation" motion): measured 0.002 dB (coffee) and
# 0.025 dB (rocket) lower. The homography used the wrong way round (its inverse) costs 13.6 to
# 17.8 dB.
WARP_BACK_DB = 0.2
# The same warp-back, true homography, against the reference itself: bilinear resampling twice
# smooths detail, measured 34.0 dB (coffee) and 36.5 dB (rocket); 34.0 dB for coffee through
# 8-bit PNGs and the estimated homography (the align command's test).
WARP_BACK_MIN_DB = 32.0


def rotation(degrees, tx, ty, px=0.0, py=0.0):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, tx], [s, c, ty], [px, py, 1.0]])


HOMOGRAPHIES = {
    "rotation": rotation(1.5, 4.3, -2.7, 2e-5, -1e-5),
    "affine+perspective": np.array([[1.01, 0.004, -6.2], [-0.003, 0.995, 3.9],
                                    [-1.5e-5, 2e-5, 1.0]]),
}
MARGIN = 60


def moved_pair(photo, homography):
    """(reference, moving, true homography) cut from a photo and its warp, away from borders.

    ``warp_homography`` moves content at p to H p, so moving(H x) = photo(x): the homography
    from a reference pixel to a moving pixel is H, conjugated by the crop's offset.
    """
    moved = warp_homography(photo, homography)
    h, w = photo.shape[:2]
    offset = np.array([[1, 0, MARGIN], [0, 1, MARGIN], [0, 0, 1.0]])
    cut = (slice(MARGIN, h - MARGIN), slice(MARGIN, w - MARGIN))
    return photo[cut], moved[cut], np.linalg.inv(offset) @ homography @ offset


@pytest.fixture(params=["coffee", "rocket"])
def photo(request, coffee_rgb, rocket_rgb):
    return {"coffee": coffee_rgb, "rocket": rocket_rgb}[request.param]


def corners_within_tolerance(found, expected, shape):
    _, atol = tolerance("ecc_corners_px", "opencv", "float32")
    error = corner_displacement(found, expected, shape)
    assert error <= atol, f"corners {error:.3f} px off (allowed {atol} px)"


@pytest.mark.parametrize("levels", [1, 3])
@pytest.mark.parametrize("motion", sorted(HOMOGRAPHIES))
def test_ecc_recovers_a_known_homography_of_a_photograph(photo, motion, levels):
    reference, moving, truth = moved_pair(photo, HOMOGRAPHIES[motion])
    result = align_ecc(reference, moving, levels=levels)
    assert result.converged and result.levels == levels
    assert len(result.iterations) == levels and result.iterations[-1] < 100
    assert result.correlation > 0.999
    corners_within_tolerance(result.homography, truth, reference.shape)


def test_ecc_pyramid_recovers_a_large_motion(photo):
    reference, moving, truth = moved_pair(photo, rotation(2.0, 24.0, -14.4, 1e-5, -1e-5))
    result = align_ecc(reference, moving, levels=3)
    assert result.converged
    corners_within_tolerance(result.homography, truth, reference.shape)


def test_ecc_aligns_images_with_independent_noise(coffee_rgb):
    reference, moving, truth = moved_pair(coffee_rgb, HOMOGRAPHIES["rotation"])
    rng = np.random.default_rng(4)
    reference = np.clip(np.rint(255 * reference + rng.normal(0, 2.55, reference.shape)), 0, 255)
    moving = np.clip(np.rint(255 * moving + rng.normal(0, 3.8, moving.shape)), 0, 255)
    result = align_ecc(reference.astype(np.uint8), moving.astype(np.uint8))
    assert result.converged
    corners_within_tolerance(result.homography, truth, reference.shape)


def test_warping_back_with_the_estimate_restores_the_reference(photo):
    reference, moving, truth = moved_pair(photo, HOMOGRAPHIES["rotation"])
    found = align_ecc(reference, moving).homography
    with_truth, mask = warp_to_reference(moving, truth, reference.shape)
    with_found, mask_found = warp_to_reference(moving, found, reference.shape)
    best = metrics.psnr(reference, with_truth, mask=mask)
    assert best >= WARP_BACK_MIN_DB
    assert best - metrics.psnr(reference, with_found, mask=mask_found) <= WARP_BACK_DB
    backwards, mask_back = warp_to_reference(moving, np.linalg.inv(found), reference.shape)
    assert metrics.psnr(reference, backwards, mask=mask_back) < best - 10  # convention


def test_warp_with_the_identity_returns_the_image_unchanged(rocket_rgb):
    warped, mask = warp_to_reference(rocket_rgb, np.eye(3), rocket_rgb.shape)
    assert np.array_equal(warped, rocket_rgb) and mask.all()


def test_inside_mask_keeps_the_pixels_that_map_into_the_moving_image():
    shift = np.array([[1, 0, 3.5], [0, 1, -2.25], [0, 0, 1.0]])
    mask = inside_mask(shift, (20, 30), (20, 30))
    # column x maps to x + 3.5 <= 29: x <= 25; row y maps to y - 2.25 >= 0: y >= 3
    expected = np.zeros((20, 30), bool)
    expected[3:, :26] = True
    assert np.array_equal(mask, expected)


def test_warp_reflects_positions_outside_the_image():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    shift = np.array([[1, 0, -1], [0, 1, 0], [0, 0, 1.0]])  # output x reads input x - 1
    warped, mask = warp_to_reference(image, shift, image.shape)
    # BORDER_REFLECT mirrors about the edge pixel itself: input column -1 reads column 0
    assert np.array_equal(warped[:, 0], image[:, 0]) and not mask[:, 0].any()
    assert np.array_equal(warped[:, 1:], image[:, :3]) and mask[:, 1:].all()


def test_ecc_flags_a_run_that_stops_at_the_iteration_limit(coffee_rgb):
    reference, moving, _ = moved_pair(coffee_rgb, HOMOGRAPHIES["rotation"])
    result = align_ecc(reference, moving, levels=1, max_iterations=1)
    assert not result.converged and result.iterations == (1,)


def test_ecc_refuses_a_flat_image_with_opencvs_reason(coffee_rgb):
    with pytest.raises(AlignmentError, match=r"ECC failed at iteration 1 at pyramid level 1 "
                       r"of 3, on 100 x 150 images \(OpenCV: .*\); the images may be flat"):
        align_ecc(np.full_like(coffee_rgb, 0.5), coffee_rgb)
    with pytest.raises(AlignmentError, match=r"iteration 1, on 400 x 600 images"):
        align_ecc(np.full_like(coffee_rgb, 0.5), coffee_rgb, levels=1)


def test_ecc_refuses_unrelated_images(coffee_rgb):
    with pytest.raises(AlignmentError, match="ECC failed"):
        align_ecc(coffee_rgb, coffee_rgb[::-1].copy(), levels=1)


def test_pyramid_stops_before_levels_get_too_small(coffee_rgb):
    small = coffee_rgb[:2 * MIN_LEVEL_SIDE - 1, :200]
    assert align_ecc(small, small, levels=3).levels == 1


# -- gpu-blur align --------------------------------------------------------------------------

def write_png(path, image):
    cv2.imwrite(str(path), np.rint(np.clip(image, 0, 1)[:, :, ::-1] * 255).astype(np.uint8))
    return str(path)


def test_align_command_warps_the_frames_onto_the_real_image(tmp_path, coffee_rgb, capsys):
    reference, moving, truth = moved_pair(coffee_rgb, HOMOGRAPHIES["rotation"])
    real = write_png(tmp_path / "real.png", reference)
    synth = write_png(tmp_path / "synth.png", moving)
    frame = write_png(tmp_path / "frame.png", moving)
    out = tmp_path / "aligned"
    assert main(["align", real, synth, frame, "--output", str(out)]) == 0
    assert "converged" in capsys.readouterr().out
    record = json.loads((out / "alignment.json").read_text())
    assert record["converged"] and record["frames"][0]["output"] == str(out / "frame.png")
    corners_within_tolerance(record["homography"], truth, reference.shape)
    warped = cv2.imread(str(out / "frame.png"))[:, :, ::-1] / 255.0
    assert warped.shape == reference.shape
    mask = inside_mask(record["homography"], reference.shape, moving.shape)
    assert metrics.psnr(reference, warped, mask=mask) >= WARP_BACK_MIN_DB


def test_align_command_needs_an_output_folder_for_frames(tmp_path, coffee_rgb, capsys):
    path = write_png(tmp_path / "a.png", coffee_rgb)
    assert main(["align", path, path, path]) == 2
    assert "give --output DIR" in capsys.readouterr().err


@pytest.mark.parametrize("place", ["same folder", "symlinked folder", "hard link"])
def test_align_command_refuses_an_output_folder_where_it_would_overwrite_a_frame(
        tmp_path, coffee_rgb, capsys, place):
    small = coffee_rgb[:64, :96]
    seq = tmp_path / "seq"
    seq.mkdir()
    real = write_png(tmp_path / "real.png", small)
    frames = [write_png(seq / f"{i}.png", small) for i in range(2)]
    out = seq
    if place == "symlinked folder":
        out = tmp_path / "link"
        out.symlink_to(seq)
    elif place == "hard link":
        out = tmp_path / "aligned"
        out.mkdir()
        os.link(frames[1], out / "1.png")
    hit = 1 if place == "hard link" else 0  # the first frame written over
    before = {p: p.read_bytes() for p in seq.iterdir()}
    assert main(["align", real, real, *frames, "--output", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--output {out}: it would write {out / f'{hit}.png'}, which is FRAME " \
           f"{frames[hit]} (the same file)" in err
    assert "give --output a folder that holds none of the inputs" in err
    assert {p: p.read_bytes() for p in seq.iterdir()} == before  # nothing written, no json


def test_align_command_replaces_earlier_outputs_only_with_overwrite(tmp_path, coffee_rgb,
                                                                     capsys):
    small = coffee_rgb[:64, :96]
    real = write_png(tmp_path / "real.png", small)
    frame = write_png(tmp_path / "frame.png", small)
    out = tmp_path / "aligned"
    out.mkdir()
    (out / "frame.png").write_bytes(b"someone's own file")
    assert main(["align", real, real, frame, "--output", str(out)]) == 2
    assert f"--output {out} holds {out / 'frame.png'} already; pass --overwrite" in (
        capsys.readouterr().err)
    assert (out / "frame.png").read_bytes() == b"someone's own file"
    assert main(["align", real, real, frame, "--output", str(out), "--overwrite"]) == 0
    assert cv2.imread(str(out / "frame.png")).shape == small.shape
