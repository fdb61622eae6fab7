"""The Warp backend: the plan's three passes as NVIDIA Warp kernels (gpu_blur/warp_kernels/).

Devices: ``warp`` (the first CUDA device if there is one, else the CPU), ``warp:cpu``,
``warp:cuda:N``. Only the stages a plan keeps are generated (``wp.static`` flags); float32 by
default, float64 on request. Random draws repeat :mod:`gpu_blur.reference.rng` bit for bit.
On CUDA, :meth:`WarpBackend.finish_on_device` leaves the result on the GPU as a ``wp.array``
that ``torch.from_dlpack`` takes without a copy.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import warp as wp

from gpu_blur.backends import cfa_bits, planted_fault
from gpu_blur.cameras import Camera
from gpu_blur.plan import Plan
from gpu_blur.reference import blur
from gpu_blur.reference.rng import key_from_seed
from gpu_blur.tiling import Region
from gpu_blur.timings import timer

wp.config.log_level = wp.LOG_WARNING  # no banner or per-module load lines

#: Warp arrays have int32 shapes, and the kernels index with Warp ``int``: one buffer holds at
#: most this many values (an RGB region ~715 M pixels). OpenCL kernels index with 64 bits.
MAX_BUFFER_VALUES = 2**31 - 1


def warp_devices() -> list[dict]:
    """Warp's devices as ``gpu-blur devices`` lists them."""
    wp.init()
    found = []
    for d in wp.get_devices():
        memory = int(getattr(d, "total_memory", 0) or 0)
        found.append({"spec": f"warp:{d.alias}", "name": d.name, "kind": "GPU" if d.is_cuda
                      else "CPU", "fp64": True, "memory_bytes": memory})
    return found


def _device(spec: str) -> str:
    wp.init()
    if spec == "warp":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    alias = spec.split(":", 1)[1]
    known = [d.alias for d in wp.get_devices()]
    if alias not in known:
        raise ValueError(f"no Warp device {spec!r}; present: "
                         + ", ".join(f"warp:{a}" for a in known))
    return alias


class WarpBackend:
    """Runs a plan as Warp kernels on one device (see :mod:`gpu_blur.backends`)."""

    name = "warp"

    def __init__(self, spec: str = "warp", precision: str = "float32"):
        if precision not in ("float32", "float64"):
            raise ValueError(f"precision must be float32 or float64, got {precision!r}")
        self.wp_device = _device(spec)
        self.precision = precision
        self.real = wp.float64 if precision == "float64" else wp.float32
        self.np_real = np.float64 if precision == "float64" else np.float32
        name = wp.get_device(self.wp_device).name
        self.device = f"warp:{self.wp_device} {name}, {precision}"

    # -- buffers (uploads and downloads are timed as "copies", gpu_blur.timings) --------------
    @staticmethod
    def _check_size(count: int) -> None:
        """Refuse, before any allocation, a buffer larger than Warp's int32 indices reach."""
        if count > MAX_BUFFER_VALUES:
            raise ValueError(
                f"a Warp buffer of {count:,} values: Warp indexes arrays with 32-bit integers "
                f"(at most {MAX_BUFFER_VALUES:,} values, about 715 M RGB pixels); run the "
                "image in tiles (synthesize(..., tile=(4096, 4096)), gpu-blur generate --tile "
                "4096 4096) or on an OpenCL backend")

    def _array(self, values, dtype=None) -> wp.array:
        self._check_size(int(np.size(values)))
        with timer("copies"):
            data = np.ascontiguousarray(np.ravel(values), dtype=dtype or self.np_real)
            return wp.array(data, device=self.wp_device)

    def _zeros(self, count: int, dtype=None) -> wp.array:
        self._check_size(count)
        return wp.zeros(max(count, 1), dtype=dtype or self.real, device=self.wp_device)

    def _launch(self, kernel, dim, *args) -> None:
        wp.launch(kernel, dim=dim, inputs=list(args), device=self.wp_device)

    def _kernels(self, sync: bool = True):
        """Time launches as "kernels"; ``sync`` waits for them (``wp.synchronize_device``)."""
        return timer("kernels", self._synchronize if sync else None)

    def _synchronize(self) -> None:
        wp.synchronize_device(self.wp_device)

    @staticmethod
    def _host(array: wp.array, shape) -> np.ndarray:
        with timer("copies"):
            return array.numpy()[:int(np.prod(shape))].reshape(shape).astype(np.float64)

    # -- pass 1: accumulate ------------------------------------------------------------------
    def accumulate(self, plan: Plan, params: dict, frames: Sequence[np.ndarray],
                   mask: np.ndarray | None, region: Region) -> tuple[np.ndarray, np.ndarray]:
        """Linearize and blur on the device; return (linear, mask) over ``region``."""
        from gpu_blur.warp_kernels.passes import accumulate_kernels

        k = accumulate_kernels(self.real)
        mode = plan.variant("blur") or "none"
        n = region.h * region.w * 3
        shape = (region.h, region.w, 3)
        if mode == "average":
            # a compensated sum (the sum and its rounding errors) and the saturation counts
            total, compensation = self._zeros(n), self._zeros(n)
            saturated = self._zeros(n, wp.uint32)
            count = 0
            for frame in frames:  # one frame uploading while the previous one is summed
                source = self._array(region.of(frame))
                with self._kernels(sync=False):
                    self._launch(k["blur_average_add"], n, source, total, compensation,
                                 saturated)
                del source
                count += 1
            linear, sat_mask = self._zeros(n), self._zeros(n)
            with self._kernels():
                self._launch(k["blur_average_finish"], n, total, compensation, saturated,
                             count, linear, sat_mask)
            return self._linear_out(linear, sat_mask, shape, region)
        if mode == "none":
            linear, indicator = self._zeros(n), self._zeros(n)
            source = self._array(region.of(frames[0]))
            with self._kernels():
                self._launch(k["linearize"], n, source, linear, indicator)
            del source
            sat_mask = np.zeros(shape) if mask is None else region.of(mask).astype(np.float64)
            return planted_fault("accumulate", self._host(linear, shape), region.origin), sat_mask
        view = region.expand(blur.blur_halo(mode, params, region.full_h, region.full_w))
        vn = view.h * view.w * 3
        src, indicator = self._zeros(vn), self._zeros(vn)
        source = self._array(view.of(frames[0]))
        with self._kernels(sync=False):
            self._launch(k["linearize"], vn, source, src, indicator)
        del source
        geometry = (view.x0, view.y0, view.w, region.full_w, region.full_h)
        linear, sat_mask = self._zeros(n), self._zeros(n)
        grid = (region.h, region.w)
        if mode == "kernel":
            kernel = blur.normalize_kernel(params["kernel"])
            kw = self._array(kernel)
            kh, kwid = kernel.shape
            with self._kernels():
                for image, out in ((src, linear), (indicator, sat_mask)):
                    self._launch(k["blur_kernel"], grid, image, *geometry, kw, kh, kwid, out,
                                 region.x0, region.y0, region.w)
            return self._linear_out(linear, sat_mask, shape, region)
        # compensated sums of the image and of its indicator: (sum, compensation) each
        sums = [self._zeros(n) for _ in range(4)]
        hom = params["homographies"]
        inverses = [self._array(np.linalg.inv(h), np.float64) for h in hom]
        with self._kernels():
            for hinv in inverses:  # one pose at a time
                self._launch(k["blur_trajectory_add"], grid, src, indicator, *geometry, hinv,
                             *sums, region.x0, region.y0, region.w)
            self._launch(k["blur_trajectory_finish"], n, *sums, len(hom), linear, sat_mask)
        return self._linear_out(linear, sat_mask, shape, region)

    def _linear_out(self, linear, sat_mask, shape, region: Region):
        """The accumulate pass's (linear, mask) on the host."""
        linear = planted_fault("accumulate", self._host(linear, shape), region.origin)
        return linear, self._host(sat_mask, shape)

    # -- pass 2: to_raw ----------------------------------------------------------------------
    def to_raw(self, plan: Plan, params: dict, camera: Camera, linear: np.ndarray,
               mask: np.ndarray, origin: tuple[int, int] = (0, 0), *, seed: int,
               sample_index: int) -> tuple[np.ndarray, np.ndarray]:
        """Saturation to noisy RAW on the device (see NumpyBackend.to_raw)."""
        from gpu_blur.warp_kernels.passes import to_raw_kernel

        kernel = to_raw_kernel(
            self.real, plan.kept("saturate"), plan.kept("mosaic"),
            plan.kept("linear_to_camera") and plan["linear_to_camera"].options["clip"],
            plan.kept("poisson_gaussian_noise"))
        h, w = linear.shape[:2]
        saturated, raw = self._zeros(h * w * 3), self._zeros(h * w)
        key = key_from_seed(seed)
        r = self.np_real
        inputs = (self._array(linear), self._array(mask))
        matrix = self._array(camera.linear_to_camera)
        with self._kernels():
            self._launch(
                kernel, (h, w), *inputs, origin[1], origin[0], w,
                r(params.get("alpha", 0.0)), matrix,
                cfa_bits(params.get("pattern")), r(params.get("red_gain", 1.0)),
                r(params.get("blue_gain", 1.0)), r(params.get("shot_noise_k", 1.0)),
                r(params.get("read_noise_std", 0.0)), wp.uint32(int(key[0])),
                wp.uint32(int(key[1])), wp.uint32(sample_index), saturated, raw)
        del inputs
        sat = self._host(saturated, (h, w, 3))
        if not plan.raw_round_trip:
            return planted_fault("to_raw", sat, origin), sat
        return planted_fault("to_raw", self._host(raw, (h, w)), origin), sat

    # -- pass 3: finish ----------------------------------------------------------------------
    def finish_on_device(self, plan: Plan, params: dict, camera: Camera, image: np.ndarray,
                         saturated: np.ndarray, view: Region, out: Region, *, seed: int,
                         sample_index: int) -> wp.array:
        """:meth:`finish`, leaving the ``out.h x out.w x 3`` result on the device."""
        from gpu_blur.constants import A7R3_CRF_POLYNOMIAL, A7R3_CRF_TABLE_X255
        from gpu_blur.warp_kernels.passes import finish_kernel

        demosaic = plan["demosaic"].options if plan.raw_round_trip else None
        kernel = finish_kernel(
            self.real, demosaic["method"] if demosaic else "",
            bool(demosaic and demosaic["border"] == "zero"), bool(demosaic and demosaic["clip"]),
            plan.kept("tone"), plan.kept("gaussian_noise"), plan.kept("restore_saturated"),
            plan["retone"].options["crf"] if plan.kept("retone") else "",
            plan["quantize"].options["bits"] if plan.kept("quantize") else 0)
        result = self._zeros(out.h * out.w * 3)
        key = key_from_seed(seed)
        raw = image if plan.raw_round_trip else np.zeros(1)
        inputs = (self._array(raw), self._array(saturated))
        constants = (self._array(camera.camera_to_linear), self._array(A7R3_CRF_POLYNOMIAL),
                     self._array(A7R3_CRF_TABLE_X255 / 255.0))
        with self._kernels():
            self._launch(
                kernel, (out.h, out.w), *inputs, view.x0, view.y0, view.w, view.full_w,
                view.full_h, out.x0, out.y0, out.w, cfa_bits(params.get("pattern")),
                constants[0], self.np_real(params.get("gaussian_std", 0.0)),
                wp.uint32(int(key[0])), wp.uint32(int(key[1])), wp.uint32(sample_index),
                constants[1], constants[2], result)
        return result.reshape((out.h, out.w, 3))

    def finish(self, plan: Plan, params: dict, camera: Camera, image: np.ndarray,
               saturated: np.ndarray, view: Region, out: Region, *, seed: int,
               sample_index: int) -> np.ndarray:
        """Demosaic and finish on the device, over ``out`` (see NumpyBackend.finish)."""
        result = self.finish_on_device(plan, params, camera, image, saturated, view, out,
                                       seed=seed, sample_index=sample_index)
        with timer("copies"):
            result = result.numpy().astype(np.float64)
        return planted_fault("finish", result, out.origin)

    def retone(self, plan: Plan, image: np.ndarray) -> np.ndarray:
        """The output tone curve for the sharp reference (host side, float64)."""
        from gpu_blur.backends.numpy import NumpyBackend

        return NumpyBackend().retone(plan, image)
