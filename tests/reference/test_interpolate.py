"""Frame interpolation before averaging: the reference, the scene and plan, kernels, backends.

Reference (gpu_blur.reference.interpolate): a translation sequence made of integer shifts of a
real photo, with its exact flows, has intermediates at sub-pixel shifts whose true values are the
photo's bilinear reconstruction there; factor 1 is plain averaging bit for bit; the occlusion
rule on a constructed case; OpenCV's flows on a translated photo. Kernels: OpenCL's
``gb_blur_interpolate_add`` and Warp's ``blur_interpolate_add`` add one intermediate frame as the
reference computes it, and a tile with its halo gives the whole image's sums bit for bit.
Backends: every kernel backend's accumulate pass against the numpy reference on a real sequence,
tiled and budgeted runs equal to whole-image runs bit for bit (with spot checks), and
``gpu-blur generate`` on a scene with ``interpolation = 2``.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS, ROOT, make_backend, spec_backend, spec_dtype

import gpu_blur
from gpu_blur.backends.flows import with_flows
from gpu_blur.planning import plan
from gpu_blur.reference.average import FrameAccumulator, average_frames
from gpu_blur.reference.blur import blur_halo
from gpu_blur.reference.flow import optical_flow, sequence_flows
from gpu_blur.reference.interpolate import (
    CONSISTENCY_ABSOLUTE_PX2,
    CONSISTENCY_RELATIVE,
    flow_consistent,
    interpolate_frame,
    interpolated_average,
    interpolation_halo,
    interpolation_times,
)
from gpu_blur.reference.transfer import srgb_to_linear
from gpu_blur.scene import SceneError, scene_from_dict
from gpu_blur.scheduler import Footprint
from gpu_blur.testing import assert_close
from gpu_blur.tiling import Region

# -- a translation sequence --------------------------------------------------------------------

#: Size of the test frames (pixels), cut from the rocket photo away from its edges.
FRAME_H, FRAME_W = 48, 64
#: Top-left corner of frame 0 in the photo.
ORIGIN_Y, ORIGIN_X = 150, 250


def shifted(photo: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """The frame whose content is the photo moved by ``(sx, sy)`` pixels: ``F(x) = P(x - s)``.

    Integer shifts are crops; a fractional shift is the photo's bilinear reconstruction there,
    written out from the four integer-shifted crops (independent of the reference's sampler).
    """
    ix, iy = int(np.floor(sx)), int(np.floor(sy))
    fx, fy = sx - ix, sy - iy

    def crop(dx: int, dy: int) -> np.ndarray:
        y, x = ORIGIN_Y - dy, ORIGIN_X - dx
        return photo[y:y + FRAME_H, x:x + FRAME_W]

    top = (1 - fx) * crop(ix, iy) + fx * crop(ix + 1, iy)
    bottom = (1 - fx) * crop(ix, iy + 1) + fx * crop(ix + 1, iy + 1)
    return (1 - fy) * top + fy * bottom


def translation(photo, velocity, frames: int):
    """Frames moving by ``velocity`` (integer px per frame) and their exact flows."""
    seq = [shifted(photo, k * velocity[0], k * velocity[1]) for k in range(frames)]
    forward = np.broadcast_to(np.asarray(velocity, np.float32), (FRAME_H, FRAME_W, 2))
    pair = np.stack([forward, -forward])
    return seq, np.broadcast_to(pair, (frames - 1, *pair.shape))


def interior(image: np.ndarray, margin: int) -> np.ndarray:
    """``image`` without ``margin`` pixels on each side (where reads may leave the frame)."""
    return image[margin:-margin, margin:-margin]


@pytest.mark.parametrize("velocity, factor", [((3, -2), 4), ((1, 0), 2), ((-5, 7), 8)])
def test_translation_intermediates_match_exactly_shifted_frames(rocket_rgb, velocity, factor):
    frames, flows = translation(rocket_rgb, velocity, 2)
    margin = interpolation_halo(flows)
    for t in interpolation_times(factor):
        got = interpolate_frame(frames[0], frames[1], flows[0, 0], flows[0, 1], t)
        expected = shifted(rocket_rgb, t * velocity[0], t * velocity[1])
        assert_close(interior(got, margin), interior(expected, margin), "interpolate_translation")


def test_translation_average_is_the_mean_of_exactly_shifted_frames(rocket_rgb):
    velocity, factor, n = (3, -2), 4, 3
    frames, flows = translation(rocket_rgb, velocity, n)
    blurred, mask = interpolated_average(frames, factor, flows)
    steps = [k / factor for k in range((n - 1) * factor + 1)]
    expected, expected_mask = average_frames(
        srgb_to_linear(shifted(rocket_rgb, s * velocity[0], s * velocity[1])) for s in steps)
    margin = (n - 1) * interpolation_halo(flows)
    assert_close(interior(blurred, margin), interior(expected, margin), "interpolate_translation")
    assert np.array_equal(interior(mask, margin), interior(expected_mask, margin))


def test_average_is_the_accumulated_intermediate_frames_bitwise(pair):
    """interpolated_average tests each gap's flows once for all its times: the same frames."""
    frame0, frame1, fw, bw = pair
    flows = np.stack([fw, bw])[None]
    blurred, mask = interpolated_average([frame0, frame1], 4, flows)
    acc = FrameAccumulator(*frame0.shape)
    acc.add(srgb_to_linear(frame0))
    for t in interpolation_times(4):
        values, saturated = interpolate_frame(frame0, frame1, fw, bw, t, saturation=True)
        acc.add(srgb_to_linear(values), saturated)
    acc.add(srgb_to_linear(frame1))
    expected, expected_mask = acc.result()
    assert np.array_equal(blurred, expected) and np.array_equal(mask, expected_mask)


def test_factor_1_is_plain_averaging_bitwise(coffee_rgb):
    frames = [coffee_rgb[k:k + 40, 2 * k:2 * k + 50] for k in range(4)]
    frames[1] = frames[1].copy()
    frames[1][:5] = 1.0  # saturated rows, so the mask is not all zero
    blurred, mask = interpolated_average(frames, 1)
    plain, plain_mask = average_frames(srgb_to_linear(f) for f in frames)
    assert np.array_equal(blurred, plain) and np.array_equal(mask, plain_mask)
    assert mask.max() > 0


def hair_off_saturated_stripes(h: int = 6, w: int = 16):
    """Two 8-bit frames of columns 255, 254, 255, ... and flows of 2 px plus a hair, its weight.

    At t = 1/2 each odd column samples a 255 neighbour with weight 1 - 1.2e-6 and a 254 one
    with 1.2e-6 in both frames: its blended value, 1 - 4.7e-9, is under 1 in float64 and
    rounds to 1 in float32, the case where a test on the value makes precisions disagree.
    """
    frame = np.full((h, w, 3), 255, np.uint8)
    frame[:, 1::2] = 254
    hair = np.float32(2.0000024)  # 2 + 2.4e-6, at float32's spacing
    flows = np.zeros((1, 2, h, w, 2), np.float32)
    flows[0, 0, ..., 0], flows[0, 1, ..., 0] = hair, -hair
    return [frame, frame.copy()], flows, (float(hair) - 2.0) / 2  # the weight, at t = 1/2


def test_intermediate_saturation_is_the_weight_of_its_saturated_neighbours():
    frames, flows, hair = hair_off_saturated_stripes()
    f0, f1 = (f / 255.0 for f in frames)
    values, saturated = interpolate_frame(f0, f1, flows[0, 0], flows[0, 1], 0.5,
                                          saturation=True)
    odd = saturated[:, 1::2]
    assert np.all(values[:, 1::2] < 1.0) and np.all(np.float32(values[:, 1::2]) == 1.0)
    assert np.allclose(odd, 1.0 - hair, rtol=0, atol=1e-12)
    assert np.allclose(saturated[:, 0::2], hair, rtol=0, atol=1e-12)
    # the mask over the two frames and the intermediate: originals count 0 or 1
    _, mask = interpolated_average([f0, f1], 2, flows)
    assert np.allclose(mask[:, 1::2], (1.0 - hair) / 3, rtol=0, atol=1e-12)
    assert np.allclose(mask[:, 0::2], (2.0 + hair) / 3, rtol=0, atol=1e-12)


def test_occlusion_rule_keeps_the_trusted_sample_only():
    """Where only one flow passes the forward-backward test, that frame's sample alone."""
    h, w, t = 12, 20, 0.25
    frame0, frame1 = np.full((h, w, 3), 0.2), np.full((h, w, 3), 0.8)
    forward = np.zeros((h, w, 2))
    forward[..., 0] = 2.0
    backward = -forward
    backward[:, 8:12, 0] = 5.0  # columns 8..11: F_bw points the wrong way
    got = interpolate_frame(frame0, frame1, forward, backward, t)[:, :, 0]
    # frame0's sample (0.2) came along F_bw: distrusted on columns 8..11. frame1's (0.8) came
    # along F_fw, whose check reads F_bw at x + 2: distrusted on columns 6..9.
    blend = (1 - t) * 0.2 + t * 0.8
    expected = np.full(w, blend)
    expected[6:8] = 0.2  # only frame0's sample trusted
    expected[10:12] = 0.8  # only frame1's
    assert np.array_equal(got, np.broadcast_to(expected, (h, w)))


@pytest.mark.parametrize("flow, error, consistent", [
    (1.0, 0.7, True),    # 0.49 <= 0.01 (1 + 0.09) + 0.5
    (1.0, 0.72, False),  # 0.5184 > 0.01 (1 + 0.0784) + 0.5
    (20.0, 2.5, True),   # 6.25 <= 0.01 (400 + 306.25) + 0.5: the bound grows with the motion
    (20.0, 3.0, False),  # 9 > 0.01 (400 + 289) + 0.5
])
def test_consistency_bound_is_relative_plus_absolute(flow, error, consistent):
    forward = np.zeros((5, 40, 2))
    forward[..., 0] = flow
    backward = np.zeros_like(forward)
    backward[..., 0] = error - flow
    assert (CONSISTENCY_RELATIVE, CONSISTENCY_ABSOLUTE_PX2) == (0.01, 0.5)  # the cases' bound
    assert (flow_consistent(forward, backward) == consistent).all()


#: OpenCV on the coffee photo moved by an integer shift: share of textured interior pixels
#: (Sobel gradient magnitude > 40 codes) whose flow lies within 0.5 px of the true shift.
#: Measured for shifts (3, -2) and (1, 4): DIS medium 0.928 and 0.943, Farneback 0.970 and
#: 0.969 (flat regions, 72 % of the crop, are left out: no method sees motion there, and warping
#: flat content needs none).
FLOW_WITHIN_HALF_PIXEL_MIN = 0.9
#: Median flow error over those pixels, px (measured 0.054 and 0.050 for DIS, 0.0034 and 0.0046
#: for Farneback).
FLOW_MEDIAN_ERROR_MAX_PX = 0.1


@pytest.mark.parametrize("method", ["dis", "farneback"])
@pytest.mark.parametrize("shift", [(3, -2), (1, 4)])
def test_opencv_flow_of_a_translated_photo_is_the_shift(coffee_rgb, method, shift):
    import cv2

    sx, sy = shift
    frame0 = coffee_rgb[100:300, 150:450]
    frame1 = coffee_rgb[100 - sy:300 - sy, 150 - sx:450 - sx]
    flow = optical_flow(frame0, frame1, method)
    assert flow.dtype == np.float32 and flow.shape == (200, 300, 2)
    gray = cv2.cvtColor(np.rint(frame0 * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    gradient = np.hypot(cv2.Sobel(gray, cv2.CV_64F, 1, 0), cv2.Sobel(gray, cv2.CV_64F, 0, 1))
    textured = interior(gradient > 40, 10)
    error = interior(np.hypot(flow[..., 0] - sx, flow[..., 1] - sy), 10)[textured]
    assert textured.mean() > 0.2
    assert (error < 0.5).mean() >= FLOW_WITHIN_HALF_PIXEL_MIN
    assert np.median(error) <= FLOW_MEDIAN_ERROR_MAX_PX
    assert np.array_equal(flow, optical_flow(frame0, frame1, method))  # deterministic


def test_sequence_flows_hold_forward_and_backward_per_pair(coffee_rgb):
    frames = [coffee_rgb[50 + k:110 + k, 60:140] for k in range(3)]
    flows = sequence_flows(frames)
    assert flows.shape == (2, 2, 60, 80, 2) and flows.dtype == np.float32
    assert np.array_equal(flows[1, 0], optical_flow(frames[1], frames[2]))
    assert np.array_equal(flows[1, 1], optical_flow(frames[2], frames[1]))


def test_tile_with_halo_gives_the_whole_image_values(coffee_rgb):
    """A window of region + halo, mirrored at its own edges, never reads past them."""
    frames = [coffee_rgb[40:120, 100:200], coffee_rgb[43:123, 98:198]]
    flows = sequence_flows(frames)
    halo = interpolation_halo(flows)
    whole = interpolate_frame(frames[0], frames[1], flows[0, 0], flows[0, 1], 0.375)
    y0, y1, x0, x1 = 30, 50, 40, 70  # the region, at least the halo from the image's edges
    assert halo < min(y0, x0, 80 - y1, 100 - x1)
    win = (slice(y0 - halo, y1 + halo), slice(x0 - halo, x1 + halo))
    tile = interpolate_frame(frames[0][win], frames[1][win], flows[0, 0][win], flows[0, 1][win],
                             0.375)
    assert np.array_equal(tile[halo:-halo, halo:-halo], whole[y0:y1, x0:x1])


def test_interpolation_halo_is_largest_flow_component_plus_one():
    flows = np.zeros((2, 2, 4, 5, 2), np.float32)
    assert interpolation_halo(flows) == 1
    flows[1, 0, 2, 3, 1] = -6.25
    assert interpolation_halo(flows) == 8
    assert interpolation_halo(np.zeros((0, 2, 4, 5, 2))) == 0
    assert interpolation_halo(flows.astype(np.float64)) == 8
    for bad in (np.nan, np.inf, -np.inf):  # one value among finite ones is enough
        spoiled = flows.copy()
        spoiled[0, 1, 1, 1, 0] = bad
        with pytest.raises(ValueError, match="flows must be finite"):
            interpolation_halo(spoiled)


@pytest.mark.parametrize("call, message", [
    (lambda f, fl: interpolate_frame(f, f, fl, fl, 1.0), "t must lie in the open interval"),
    (lambda f, fl: interpolate_frame(f, f, fl[:, :3], fl, 0.5), "flow_fw must be H x W x 2"),
    (lambda f, fl: interpolated_average([f, f], 3, None), "must be one of (1, 2, 4, 8)"),
    (lambda f, fl: optical_flow(f, f, "lucas-kanade"), "flow method 'lucas-kanade' is unknown"),
    (lambda f, fl: interpolated_average([f, f], 2, fl[None, None]), "flows must be (n - 1) x"),
    (lambda f, fl: interpolation_halo(np.full(2, np.nan)), "flows must be finite"),
])
def test_bad_input_names_the_value_and_the_rule(call, message):
    frame, flow = np.zeros((4, 5, 3)), np.zeros((4, 5, 2))
    with pytest.raises(ValueError) as e:
        call(frame, flow)
    assert message in str(e.value)


# -- scene and plan ----------------------------------------------------------------------------

def test_scene_interpolation_defaults_to_plain_averaging_with_dis():
    scene = scene_from_dict({"blur": {"mode": "average"}})
    assert scene.blur.interpolation == 1 and scene.blur.flow == "dis"
    stage = plan(scene)["blur"]
    assert stage.options == {"interpolation": 1, "flow": "dis"}
    assert stage.reason == "mean of 9 linear frames and their saturation masks"


def test_plan_says_the_frames_are_interpolated(tmp_path, capsys):
    from gpu_blur.cli import main

    path = tmp_path / "rsblur65.toml"
    path.write_text('[blur]\nmode = "average"\nframes = 9\ninterpolation = 8\n'
                    'flow = "farneback"\n')
    assert main(["plan", str(path)]) == 0
    out = capsys.readouterr().out
    assert ("mean of 65 linear frames and their saturation masks: 9 frames and 7 interpolated "
            "in each gap (8x frame rate, farneback optical flow)") in out


@pytest.mark.parametrize("data, message", [
    ({"blur": {"mode": "trajectory", "interpolation": 2}},
     "blur.interpolation = 2 needs blur.mode = 'average' (it is 'trajectory')"),
    ({"blur": {"mode": "average", "interpolation": 3}},
     "blur.interpolation = 3 is invalid; allowed: 1 | 2 | 4 | 8"),
    ({"blur": {"mode": "average", "interpolation": True}}, "blur.interpolation = True is invalid"),
    ({"blur": {"mode": "average", "flow": "raft"}},
     "blur.flow = 'raft' is invalid; allowed: 'dis' | 'farneback'"),
])
def test_scene_refuses_bad_interpolation_settings(data, message):
    with pytest.raises(SceneError) as e:
        scene_from_dict(data, "my.toml")
    assert str(e.value).startswith("my.toml: ") and message in str(e.value)


# -- kernels: one intermediate frame against the reference -------------------------------------

#: Kernel test frames: two crops of the coffee photo 3 px apart with a saturated patch, and
#: their DIS flows (whose borders and the patch fail the occlusion test here and there).
KERNEL_H, KERNEL_W = 36, 52


@pytest.fixture(scope="module")
def pair(coffee_rgb):
    """(frame0, frame1, flow_fw, flow_bw): a real pair with both trust states present."""
    frame0 = coffee_rgb[150:150 + KERNEL_H, 200:200 + KERNEL_W].copy()
    frame1 = coffee_rgb[152:152 + KERNEL_H, 197:197 + KERNEL_W].copy()
    frame0[10:16, 20:30] = 1.0
    frame1[12:18, 26:36] = 1.0
    flows = sequence_flows([frame0, frame1])
    trust = flow_consistent(flows[0, 1], flows[0, 0]), flow_consistent(flows[0, 0], flows[0, 1])
    assert (trust[0] != trust[1]).any() and (trust[0] == trust[1]).any()
    return frame0, frame1, flows[0, 0], flows[0, 1]


def expected_add(pair, t, real):
    """What one added intermediate frame contributes: linear values and saturated fractions."""
    frame0, frame1, fw, bw = pair
    f0 = frame0.astype(real).astype(np.float64)
    f1 = frame1.astype(real).astype(np.float64)
    values, saturated = interpolate_frame(f0, f1, fw, bw, t, saturation=True)
    return srgb_to_linear(values), saturated


#: Output region of the tile test (rows y0:y1, columns x0:x1) inside the kernel frames.
TILE = (9, 27, 14, 40)


@dataclasses.dataclass(frozen=True)
class HaloView:
    """A kernel launch's geometry: the output region and the view holding it and its halo.

    Attributes:
        view: (rows, columns) slices of the frames and flows to upload.
        vx0, vy0, vw: the view's first pixel and width.
        x0, y0, dw, dh: the output region's first pixel and size.
        full_w, full_h: the whole frame's size.
    """

    view: tuple[slice, slice]
    vx0: int
    vy0: int
    vw: int
    x0: int
    y0: int
    dw: int
    dh: int
    full_w: int
    full_h: int

    @classmethod
    def of(cls, pair, region=None) -> HaloView:
        """Region (y0, y1, x0, x1) of the pair (whole when None) with the flows' halo."""
        frame0, _, fw, bw = pair
        h, w = frame0.shape[:2]
        y0, y1, x0, x1 = region or (0, h, 0, w)
        halo = interpolation_halo(np.stack([fw, bw]))
        vy0, vy1 = max(y0 - halo, 0), min(y1 + halo, h)
        vx0, vx1 = max(x0 - halo, 0), min(x1 + halo, w)
        return cls((slice(vy0, vy1), slice(vx0, vx1)), vx0, vy0, vx1 - vx0, x0, y0, x1 - x0,
                   y1 - y0, w, h)


def check_add_is_the_reference_frame(k, pair, t):
    """A kernel's sums after one intermediate frame equal the reference's frame at t."""
    total, comp, saturated = k.add(pair, t)
    linear, indicator = expected_add(pair, t, k.real)
    assert_close(total.astype(np.float64) + comp, linear, "interpolate", k.backend, k.dtype)
    assert_close(saturated, indicator, "interpolate", k.backend, k.dtype)
    assert (indicator == 1).any() and ((indicator > 0) & (indicator < 1)).any()


def check_tile_equals_whole_image(k, pair):
    """A tile with its halo gives the whole image's sums there, bit for bit."""
    y0, y1, x0, x1 = TILE
    whole = k.add(pair, 0.25)
    tile = k.add(pair, 0.25, TILE)
    for a, b in zip(tile, whole, strict=True):
        assert np.array_equal(a, b[y0:y1, x0:x1])

OPENCL_DIR = ROOT / "kernels" / "opencl"


class OpenCLInterpolate:
    """interpolate.cl built for one precision on the tests' OpenCL device."""

    backend = "opencl"

    def __init__(self, cl, context, queue, dtype: str):
        self.cl, self.context, self.queue, self.dtype = cl, context, queue, dtype
        self.real = np.dtype(dtype)
        device = context.devices[0]
        self.pos = np.float64 if "cl_khr_fp64" in device.extensions else np.float32
        options = ["-I", str(OPENCL_DIR / "include")]
        options += ["-DGB_FP64=1"] if dtype == "float64" else []
        options += ["-DGB_HAS_FP64=1"] if self.pos is np.float64 else []
        source = (OPENCL_DIR / "interpolate.cl").read_text()
        with warnings.catch_warnings():  # the compiler's log of a successful build
            warnings.simplefilter("ignore", cl.CompilerWarning)
            program = cl.Program(context, source).build(options=options)
        self.kernel = cl.Kernel(program, "gb_blur_interpolate_add")

    def buffer(self, array, dtype):
        mf = self.cl.mem_flags
        host = np.ascontiguousarray(array, dtype=dtype)
        return self.cl.Buffer(self.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=host)

    def add(self, pair, t, region=None):
        """Sums after adding the frame at t over region (y0, y1, x0, x1), from its halo view."""
        frame0, frame1, fw, bw = pair
        g = HaloView.of(pair, region)
        view, dh, dw = g.view, g.dh, g.dw
        total, comp, saturated = (self.buffer(np.zeros((dh, dw, 3)), self.real)
                                  for _ in range(3))
        i64, pos = np.int64, self.pos
        self.kernel(self.queue, (dw, dh), None,
                    self.buffer(frame0[view], self.real), self.buffer(frame1[view], self.real),
                    self.buffer(fw[view], np.float32), self.buffer(bw[view], np.float32),
                    i64(g.vx0), i64(g.vy0), i64(g.vw), i64(g.full_w), i64(g.full_h), pos(t),
                    pos(CONSISTENCY_RELATIVE), pos(CONSISTENCY_ABSOLUTE_PX2), *self.weight_one(t),
                    total, comp, saturated, i64(g.x0), i64(g.y0), i64(dw), i64(dh))  # fmt: skip
        out = [np.empty((dh, dw, 3), self.real) for _ in range(3)]
        for host, buf in zip(out, (total, comp, saturated), strict=True):
            self.cl.enqueue_copy(self.queue, host, buf)
        return out

    def weight_one(self, t):
        """The step, factor and region arguments of the frame at ``t`` with weight 1."""
        step, factor = factor_step(t)
        return (np.uint32(step), np.uint32(factor),
                self.buffer(np.array([factor]), np.uint32), np.int64(0), np.int64(0),
                np.int64(1), np.uint32(factor))


def factor_step(t) -> tuple[int, int]:
    """``t`` as ``step / factor``, factor 8 (every test time is a multiple of 1/8)."""
    assert (t * 8) % 1 == 0
    return int(t * 8), 8


@pytest.fixture(scope="module", params=["float32", "float64"])
def opencl_interpolate(request, opencl_queue):
    cl, context, queue = opencl_queue
    device = context.devices[0]
    if request.param == "float64" and "cl_khr_fp64" not in device.extensions:
        pytest.skip(f"{device.name} has no cl_khr_fp64")
    return OpenCLInterpolate(cl, context, queue, request.param)


@pytest.mark.parametrize("t", [0.125, 0.5, 0.75])
def test_opencl_interpolate_add_is_the_reference_frame(opencl_interpolate, pair, t):
    check_add_is_the_reference_frame(opencl_interpolate, pair, t)


def test_opencl_interpolate_tile_equals_whole_image(opencl_interpolate, pair):
    check_tile_equals_whole_image(opencl_interpolate, pair)


class WarpInterpolate:
    """gpu_blur.warp_kernels.interpolate for one precision on one Warp device."""

    backend = "warp"

    def __init__(self, device: str, dtype: str):
        import warp as wp

        from gpu_blur.warp_kernels.interpolate import interpolate_kernels

        wp.config.quiet = True
        self.wp, self.device, self.dtype = wp, device, dtype
        self.real = np.dtype(dtype)
        self.kernel = interpolate_kernels({"float32": wp.float32,
                                           "float64": wp.float64}[dtype])["blur_interpolate_add"]

    def array(self, values, dtype):
        return self.wp.array(np.ascontiguousarray(values, dtype=dtype).ravel(),
                             device=self.device)

    def add(self, pair, t, region=None):
        """Sums after adding the frame at t over region (y0, y1, x0, x1), from its halo view."""
        frame0, frame1, fw, bw = pair
        g = HaloView.of(pair, region)
        view, dh, dw = g.view, g.dh, g.dw
        out = [self.array(np.zeros((dh, dw, 3)), self.real) for _ in range(3)]
        self.wp.launch(self.kernel, dim=(dh, dw), device=self.device, inputs=[
            self.array(frame0[view], self.real), self.array(frame1[view], self.real),
            self.array(fw[view], np.float32), self.array(bw[view], np.float32),
            g.vx0, g.vy0, g.vw, g.full_w, g.full_h, t, CONSISTENCY_RELATIVE,
            CONSISTENCY_ABSOLUTE_PX2, *self.weight_one(t), *out, g.x0, g.y0, dw])
        return [a.numpy().reshape(dh, dw, 3) for a in out]

    def weight_one(self, t):
        """The step, factor and region arguments of the frame at ``t`` with weight 1."""
        step, factor = factor_step(t)
        table = self.wp.array(np.array([factor], np.uint32), dtype=self.wp.uint32,
                              device=self.device)
        return step, factor, table, 0, 0, 1, factor


def warp_devices() -> list[str]:
    try:
        import warp as wp
    except ImportError:
        return []
    wp.config.quiet = True
    return ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(scope="module", params=[(d, p) for d in warp_devices() or ["none"]
                                        for p in ("float32", "float64")],
                ids=lambda v: f"{v[0]}-{v[1]}")
def warp_interpolate(request):
    device, dtype = request.param
    if device == "none":
        pytest.skip("warp is not installed")
    return WarpInterpolate(device, dtype)


@pytest.mark.parametrize("t", [0.125, 0.5, 0.75])
def test_warp_interpolate_add_is_the_reference_frame(warp_interpolate, pair, t):
    check_add_is_the_reference_frame(warp_interpolate, pair, t)


def test_warp_interpolate_tile_equals_whole_image(warp_interpolate, pair):
    check_tile_equals_whole_image(warp_interpolate, pair)


# -- backends: the accumulate pass, tiles, budgets, the command line --------------------------

#: Frames of the backend tests (pixels): small, so every backend runs them in a second.
SEQUENCE_H, SEQUENCE_W = 40, 56


@pytest.fixture(scope="module")
def sequence(coffee_rgb):
    """Three 8-bit frames of the coffee photo moving by (-3, 2) px per frame, a patch clipped."""
    codes = np.rint(coffee_rgb * 255).astype(np.uint8)
    frames = [np.ascontiguousarray(codes[120 + 2 * k:120 + 2 * k + SEQUENCE_H,
                                         220 - 3 * k:220 - 3 * k + SEQUENCE_W]) for k in range(3)]
    frames[1][14:20, 22:31] = 255
    return frames


def interpolating_scene(factor: int = 4, **sections):
    """Mode average over 3 frames at ``factor`` times the frame rate."""
    return scene_from_dict({"blur": {"mode": "average", "frames": 3, "interpolation": factor},
                            **sections})


def test_interpolation_halo_is_the_blur_halo_of_interpolated_averaging(sequence):
    scene = interpolating_scene()
    params = with_flows(plan(scene), {}, sequence)
    halo = interpolation_halo(params["flows"])
    assert halo >= 4  # the motion is 3 px per frame
    assert blur_halo("average", params, SEQUENCE_H, SEQUENCE_W) == halo
    assert blur_halo("average", {}, SEQUENCE_H, SEQUENCE_W) == 0
    assert with_flows(plan(interpolating_scene(1)), {}, sequence) == {}


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_backend_accumulates_interpolated_frames_as_the_reference(spec, sequence):
    p = plan(interpolating_scene())
    whole = Region.whole(SEQUENCE_H, SEQUENCE_W)
    params = with_flows(p, {}, sequence)
    linear, mask = make_backend(spec).accumulate(p, params, sequence, None, whole)
    expected, expected_mask = make_backend("numpy").accumulate(p, params, sequence, None, whole)
    backend, dtype = spec_backend(spec), spec_dtype(spec)
    assert_close(linear, expected, "accumulate", backend, dtype)
    assert_close(mask, expected_mask, "accumulate", backend, dtype)
    # not plain averaging: the intermediates move the blur and count in the mask (of 9 frames)
    plain, _ = make_backend("numpy").accumulate(plan(interpolating_scene(1)), {}, sequence, None,
                                                whole)
    assert np.abs(expected - plain).max() > 0.01
    assert set(np.unique(np.rint(expected_mask * 9))) > {0.0, 1.0}
    # without flows the backend computes the same ones itself
    alone, _ = make_backend(spec).accumulate(p, {}, sequence, None, whole)
    assert np.array_equal(alone, linear)


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_backend_mask_agrees_with_the_reference_a_hair_off_saturated_pixels(spec):
    """The regression of a whole-frame disagreement: float32 once counted 1 - 4.7e-9 as 1."""
    frames, flows, _ = hair_off_saturated_stripes()
    h, w = frames[0].shape[:2]
    scene = scene_from_dict({"blur": {"mode": "average", "frames": 2, "interpolation": 2}})
    p, params, whole = plan(scene), {"flows": flows}, Region.whole(h, w)
    _, mask = make_backend(spec).accumulate(p, params, frames, None, whole)
    _, expected = make_backend("numpy").accumulate(p, params, frames, None, whole)
    assert_close(mask, expected, "accumulate", spec_backend(spec), spec_dtype(spec))


@pytest.mark.parametrize("spec", KERNEL_BACKEND_SPECS)
def test_tiles_and_budgets_give_the_whole_image_bitwise(spec, sequence):
    name, _, precision = spec.partition("/")
    scene = interpolating_scene(output={"precision": precision})
    whole = gpu_blur.synthesize(sequence, scene, seed=3, sample_index=1, backend=name)
    tiled = gpu_blur.synthesize(sequence, scene, seed=3, sample_index=1, backend=name,
                                tile=(16, 24), verify=1.0)
    need = Footprint.of(whole.plan, with_flows(whole.plan, whole.params, sequence),
                        SEQUENCE_H, SEQUENCE_W, precision, 3, np.uint8)
    budget = need.tile_bytes(SEQUENCE_H, SEQUENCE_W) // 2
    budgeted = gpu_blur.synthesize(sequence, scene, seed=3, sample_index=1, backend=name,
                                   max_device_memory=budget)
    assert whole.tiles == 1 and tiled.tiles > 1 and tiled.spot_checks == tiled.tiles
    assert budgeted.tiles > 1
    for run in (tiled, budgeted):
        assert np.array_equal(run.blurred, whole.blurred)
        assert np.array_equal(run.mask, np.asarray(whole.mask))


def test_memory_formula_counts_frames_and_flows_over_the_halo():
    p = plan(interpolating_scene())
    f = Footprint(100, 200, "average", False, 0, 5, 4, frames=3, source_itemsize=1,
                  interpolation=4)
    view, source = 20 * 30, 30 * 40
    assert f.pass_bytes(20, 30)["accumulate"] == 6 * source + 16 * source + 3 * view * 20
    assert Footprint.of(p, {}, 100, 200, "float32", 3, np.uint8).interpolation == 4


def test_generate_runs_a_scene_with_interpolation_2(tmp_path, sequence):
    import json

    import cv2

    from gpu_blur.cli import main

    folder = tmp_path / "in" / "GOPR0001" / "sharp"
    folder.mkdir(parents=True)
    for i, frame in enumerate(sequence):
        cv2.imwrite(str(folder / f"{i:06d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    blurred = {}
    for factor in (1, 2):
        scene = tmp_path / f"x{factor}.toml"
        scene.write_text(f'[blur]\nmode = "average"\nframes = 3\ninterpolation = {factor}\n')
        out = tmp_path / f"out{factor}"
        assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out),
                     "--scene", str(scene), "--quiet"]) == 0
        (line,) = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
        assert line["status"] == "ok" and "flows" not in line["params"]
        blurred[factor] = cv2.imread(str(out / line["blurred"]), cv2.IMREAD_UNCHANGED)
    assert blurred[2].shape == (SEQUENCE_H, SEQUENCE_W, 3)
    assert not np.array_equal(blurred[1], blurred[2])
