"""shake_blur gives the bits of its plain per-pixel form on every kind of input.

shake_blur lays the image out one plane per channel, with a zero column that taps outside the
image read, inverts each pose once and looks at the border weight only where a tap leaves the
image. The functions below are the form it had before (the image kept ``H x W x 2C``, each tap
multiplied by its inside mask, every pose inverted per band of rows, the border weight chosen
over every pixel); shake_blur must give their bits exactly, outside taps, bands and all.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpu_blur.reference import fixedmath, shake
from gpu_blur.reference.average import saturation_indicator
from gpu_blur.reference.sampling import as_image
from gpu_blur.reference.shake import SHAKE_UNIFORMS, camera_shake_homographies, shake_blur


# -- the oracle: shake_blur as it was, per pixel, channels last -----------------------------
# (where a pixel samples is shake._positions', unchanged, of the pose inverted per band)
def plain_inside_share(first, frac, n):
    in0 = (first >= 0) & (first < n)
    in1 = (first >= -1) & (first < n - 1)
    return np.where(in0 & in1, 1.0, np.where(in1, frac, np.where(in0, 1.0 - frac, 0.0)))


def plain_warp_inside(stack, homography, rows):
    h, w, c = stack.shape
    px, py = shake._positions(fixedmath.inverse3(homography), h, w, rows)
    x0, y0 = np.floor(px), np.floor(py)
    fx, fy = px - x0, py - y0
    xi, yi = x0.astype(np.intp), y0.astype(np.intp)
    flat = stack.reshape(h * w, c)
    xs = [((x >= 0) & (x < w), np.clip(x, 0, w - 1)) for x in (xi, xi + 1)]
    ys = [((y >= 0) & (y < h), np.clip(y, 0, h - 1) * w) for y in (yi, yi + 1)]

    def taps(row, col):
        return np.take(flat, row[1] + col[1], axis=0) * (row[0] & col[0])[..., None]

    def lerp(a, b, f):
        b -= a
        b *= f[..., None]
        a += b
        return a

    top = lerp(taps(ys[0], xs[0]), taps(ys[0], xs[1]), fx)
    bottom = lerp(taps(ys[1], xs[0]), taps(ys[1], xs[1]), fx)
    values = lerp(top, bottom, fy)
    weights = plain_inside_share(xi, fx, w) * plain_inside_share(yi, fy, h)
    return values, weights[..., None]


def plain_shake_blur(image, homographies, band_rows=32):
    img = as_image(image)
    hom = np.asarray(homographies, dtype=np.float64)
    if hom.ndim != 3 or hom.shape[1:] != (3, 3) or hom.shape[0] < 1:
        raise ValueError(f"homographies must be (steps >= 1, 3, 3); got {hom.shape}")
    stack = img if img.ndim == 3 else img[:, :, None]
    c = stack.shape[2]
    both = np.concatenate([stack, saturation_indicator(stack)], axis=2)
    total = np.zeros_like(both)
    weight = np.zeros(both.shape[:2] + (1,))
    poses = [shake._as_homography(m) for m in hom]
    h = both.shape[0]
    for start in range(0, h, band_rows):
        rows = range(start, min(h, start + band_rows))
        for m in poses:
            values, weights = plain_warp_inside(both, m, rows)
            total[start:rows.stop] += values
            weight[start:rows.stop] += weights
    seen = np.broadcast_to(weight > 0.0, total.shape)
    total = np.divide(total, weight, out=np.zeros_like(total), where=seen)
    return (
        np.ascontiguousarray(total[:, :, :c]).reshape(img.shape),
        np.ascontiguousarray(total[:, :, c:]).reshape(img.shape),
    )


# -- inputs ----------------------------------------------------------------------------------
def about_centre(height, width, angle_deg=0.0, scale=1.0, tx=0.0, ty=0.0, tilt=(0.0, 0.0)):
    """Rotation by ``angle_deg`` and scaling about the image centre, then a shift and a tilt."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    a = math.radians(angle_deg)
    c, s = scale * math.cos(a), scale * math.sin(a)
    m = np.array([[c, -s, cx - c * cx + s * cy + tx], [s, c, cy - s * cx - c * cy + ty],
                  [0.0, 0.0, 1.0]])
    m[2, :2] = tilt
    m[2, 2] = 1.0 - tilt[0] * cx - tilt[1] * cy  # the centre keeps w = 1
    return m


def edge_values(rng, shape):
    """Values at and near 0 and 1 (both signs of zero, neighbours of 1, subnormals), spread."""
    specials = np.array([0.0, -0.0, 1.0, np.nextafter(1.0, 0.0), np.nextafter(1.0, 2.0),
                         5e-324, -5e-324, 2.2250738585072014e-308, 1e-300, -1e-300,
                         np.nextafter(0.0, 1.0) * 3, 0.5, -0.5, -1.0, 2.0, 1e-17, 1.0 - 1e-16])
    out = rng.choice(specials, size=shape)
    mixed = rng.random(shape) < 0.4
    out[mixed] = rng.uniform(-0.5, 1.5, size=shape)[mixed]
    return out


def poses_for(height, width):
    """Identity, shifts off every side (part way and all the way), big turns, zoom, tilt."""
    big = max(height, width) + 2.0
    return [
        np.eye(3),
        about_centre(height, width, tx=0.37, ty=-0.61),
        about_centre(height, width, tx=-2.5, ty=1.25),
        about_centre(height, width, tx=3.0, ty=-3.0),  # integer shift: zero fractions
        about_centre(height, width, tx=big, ty=0.5),  # right off the image
        about_centre(height, width, tx=-big, ty=-0.5),
        about_centre(height, width, tx=0.25, ty=big),
        about_centre(height, width, tx=-0.25, ty=-big),
        about_centre(height, width, angle_deg=33.0),
        about_centre(height, width, angle_deg=90.0, tx=0.5),
        about_centre(height, width, angle_deg=-135.0, scale=0.7),
        about_centre(height, width, angle_deg=180.0),
        about_centre(height, width, scale=1.9, tx=0.3),
        about_centre(height, width, scale=0.45, ty=-0.2),
        about_centre(height, width, angle_deg=7.0, tilt=(1e-3, -2e-3)),
    ]


def assert_same_bits(new, old):
    for a, b in zip(new, old, strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype == np.float64
        assert np.array_equal(a.view(np.uint64), b.view(np.uint64))


SHAPES = [(1, 1), (1, 1, 1), (1, 9), (9, 1), (1, 7, 3), (7, 1, 2), (2, 2, 3), (3, 5),
          (5, 3, 1), (17, 23, 3), (33, 31, 2), (45, 70, 3)]


# -- tests -----------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)))
def test_shake_blur_gives_the_plain_bits_for_every_size_and_pose(shape):
    rng = np.random.default_rng(sum(shape) * 7919 + len(shape))
    image = edge_values(rng, shape)
    poses = poses_for(shape[0], shape[1])
    assert_same_bits(shake_blur(image, poses), plain_shake_blur(image, poses))
    for pose in poses:  # each pose alone too: a sum of one term, zero weights included
        assert_same_bits(shake_blur(image, [pose]), plain_shake_blur(image, [pose]))


@pytest.mark.parametrize("band_rows", [1, 2, 5, 32, 1000])
def test_shake_blur_gives_the_plain_bits_for_any_band_of_rows(monkeypatch, band_rows):
    rng = np.random.default_rng(band_rows)
    image = edge_values(rng, (37, 29, 3))
    poses = poses_for(37, 29)
    monkeypatch.setattr(shake, "SHAKE_BAND_ROWS", band_rows)
    assert_same_bits(shake_blur(image, poses), plain_shake_blur(image, poses, band_rows))


def test_shake_blur_of_negative_values_off_the_image_gives_no_negative_zero():
    # the plain form's outside taps are x * 0 = -0 for negative x; a tap of +0 gives the same
    # sums, and a pixel that sums to zero is +0 in both
    image = -np.ones((6, 8, 2))
    image[2:4, 3:5] = -0.0
    poses = [about_centre(6, 8, tx=tx, ty=ty) for tx, ty in
             [(0.5, 0.0), (-0.5, 0.25), (8.5, 0.0), (0.0, -6.5), (0.0, 0.0), (-1.0, 1.0)]]
    new, old = shake_blur(image, poses), plain_shake_blur(image, poses)
    assert_same_bits(new, old)
    for out in new:
        zeros = out[out == 0.0]
        assert not np.signbit(zeros).any()


def test_shake_blur_gives_the_plain_bits_for_drawn_camera_shake():
    rng = np.random.default_rng(11)
    image = edge_values(rng, (40, 57, 3))
    for seed, steps, extent, roll in [(1, 9, 6.0, 2.0), (2, 8, 15.0, 25.0), (3, 1, 0.0, 0.0),
                                      (4, 21, 30.0, 30.0)]:
        u = np.clip(np.random.default_rng(seed).random(SHAKE_UNIFORMS), 1e-12, 1 - 1e-12)
        hom = camera_shake_homographies(u, 40, 57, steps, extent, roll)
        assert_same_bits(shake_blur(image, hom), plain_shake_blur(image, hom))


def test_shake_blur_gives_the_plain_bits_for_huge_values():
    # differences of huge values overflow to inf, and 0 * inf is NaN: the same in both
    image = np.array([[1e308, -1e308, 1e308], [-1e308, 0.0, 1e308], [1e308, 1e308, -1e308]])
    poses = [np.eye(3), about_centre(3, 3, tx=0.5, ty=0.5), about_centre(3, 3, tx=-1.5)]
    with np.errstate(over="ignore", invalid="ignore"):
        new, old = shake_blur(image, poses), plain_shake_blur(image, poses)
    assert_same_bits(new, old)
    assert not np.isfinite(new[0]).all()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_shake_blur_refuses_a_non_finite_image_as_before(bad):
    image = np.ones((4, 5))
    image[1, 2] = bad
    for blur in (shake_blur, plain_shake_blur):
        with pytest.raises(ValueError, match="finite"):
            blur(image, [np.eye(3)])


def test_shake_blur_refuses_a_pose_through_infinity_with_the_same_error():
    tilted = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.0, 1.0]])  # w <= 0 from x = 2
    poses = [np.eye(3), tilted]
    messages = []
    for blur in (shake_blur, plain_shake_blur):
        with pytest.raises(ValueError) as err:
            blur(np.ones((5, 6, 3)), poses)
        messages.append(str(err.value))
    assert messages[0] == messages[1]
    assert "infinity" in messages[0]
