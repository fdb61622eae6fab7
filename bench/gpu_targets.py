"""The GPU targets of issues 6, 7 and 20, measured in one run on one device.

For 9-frame 1920 x 1200 samples (uint8 frames, RSBlur-like plan: average, saturation,
Poisson-Gaussian noise, RAW round trip, Malvar, A7R3 CRF, 8-bit output), float32:

* **bandwidths** of the device in the same run: device-to-device copy (bytes read + written per
  second, ``wp.copy`` of 1 GiB) and pinned host-to-device (``wp.copy`` from pinned memory, one
  sample's frames and 1 GiB);
* **frames already on the device** (Warp, a ``wp.array`` stack): a sample's three passes, wall
  time with a synchronize after each pass (median of 30), and the same passes replayed as a CUDA
  graph (no host in the way: the kernels' own time); the bytes the minimal plan moves (each
  pass reads its inputs once and writes its outputs once) over the graph's time, against the
  copy bandwidth;
* **frames in host memory**: samples per second end to end through ``gpu_blur.synthesize``
  (numpy frames, result left on the device), with overlapped copies (pinned staging buffers, a
  copy stream or queue) and with serial copies, on Warp and OpenCL; and through the backend's
  passes from a pinned ``wp.array`` stack (one sample at a time, and pipelined: the next
  sample's frames copy while this sample's passes run, :class:`Prefetcher`; with the host
  waiting for each pass, and without, as a training loop that reads results on the device's
  stream runs it), against the
  bound set by pinned host-to-device bandwidth (one sample's frames per sample);
* **each pass alone** replayed as a CUDA graph: its time and its minimal bytes per second;
* **the RealBlur-J scene** (``realblur_j.toml``: one blurred 8-bit image and its 8-bit mask on
  the device, no blur, float output): each pass and the whole sample as CUDA graphs, against
  the copy bandwidth likewise.

Run on the GPU machine from the repository root:
``PYTHONPATH=$PWD python3 bench/gpu_targets.py OUT.json``; prints a table, writes the JSON.
"""

from __future__ import annotations

import json
import platform
import statistics
import sys
import time
import traceback

import cv2
import numpy as np

import gpu_blur
from gpu_blur.cameras import get_camera
from gpu_blur.discovery import default_photo
from gpu_blur.params import draw_params
from gpu_blur.planning import plan
from gpu_blur.scene import load_scene, scene_from_dict
from gpu_blur.tiling import Region

H, W, FRAMES = 1200, 1920, 9
#: The scene of gpu_blur/data/scenes/realblur_j.toml, measured beside the RSBlur-like SCENE.
REALBLUR_J = "realblur_j"
SCENE = {"blur": {"mode": "average", "frames": FRAMES}, "saturation": {"mode": "on"},
         "noise": {"model": "poisson-gaussian"}, "isp": {"round_trip": "always"},
         "output": {"bits": 8, "precision": "float32"}}


def make_frames() -> np.ndarray:
    """FRAMES x H x W x 3 uint8: the built-in photo at 1920 x 1200, shifted 3 px per frame."""
    photo = cv2.cvtColor(cv2.imread(str(default_photo())), cv2.COLOR_BGR2RGB)
    big = cv2.resize(photo, (W, H), interpolation=cv2.INTER_CUBIC)
    return np.stack([np.roll(big, 3 * i, axis=1) for i in range(FRAMES)])


def median_seconds(fn, sync, runs: int) -> float:
    fn()
    sync()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def minimal_bytes(pixels: int, frames: int, itemsize: int = 4) -> dict[str, int]:
    """Bytes each pass must read and write once: uint8 frames in, float buffers between.

    ``frames``: the 8-bit RGB images the first pass reads (RealBlur-J: its image and mask, 2).
    """
    rgb, raw = 3 * pixels * itemsize, pixels * itemsize
    passes = {
        "accumulate": frames * 3 * pixels + 2 * rgb,  # frames in; linear image and mask out
        "to_raw": 2 * rgb + rgb + raw,  # linear image and mask in; saturated image, RAW out
        "finish": raw + rgb + rgb,  # RAW mosaic and saturated image in; result out
    }
    passes["total"] = sum(passes.values())
    return passes


def bandwidths(wp, device: str) -> dict:
    gib = 1 << 30
    a = wp.empty(gib, dtype=wp.uint8, device=device)
    b = wp.empty(gib, dtype=wp.uint8, device=device)
    d2d = median_seconds(lambda: wp.copy(b, a), lambda: wp.synchronize_device(device), 10)
    sample = FRAMES * H * W * 3
    out = {"d2d_copy_bytes_per_s": 2 * gib / d2d, "d2d_copy_seconds_1gib": d2d}
    for label, size in (("sample", sample), ("1gib", gib)):
        host = wp.empty(size, dtype=wp.uint8, device="cpu", pinned=True)
        dev = wp.empty(size, dtype=wp.uint8, device=device)
        t = median_seconds(lambda d=dev, h=host: wp.copy(d, h),
                           lambda: wp.synchronize_device(device), 10)
        out[f"pinned_h2d_bytes_per_s_{label}"] = size / t
    return out


def prepared(scene_dict):
    """(scene, plan, camera, drawn values) of sample 0 at H x W: a scene dict or a name."""
    scene = load_scene(scene_dict) if isinstance(scene_dict, str) else scene_from_dict(scene_dict)
    p = plan(scene, saturated=True)
    camera = get_camera(scene.camera.name)
    params = draw_params(scene, p, camera, seed=1, sample_index=0, image_shape=(H, W))
    return scene, p, camera, params


def warp_on_device(wp, frames: np.ndarray, device: str, band: dict) -> dict:
    from gpu_blur.backends.warp import WarpBackend

    _, p, camera, params = prepared(SCENE)
    backend = WarpBackend(f"warp:{device}", "float32")
    region = Region.whole(H, W)
    stack = wp.array(frames, dtype=wp.uint8, device=device)
    kw = {"seed": 1, "sample_index": 0}

    def sample():
        linear, mask = backend.accumulate(p, params, stack, None, region)
        image, saturated = backend.to_raw(p, params, camera, linear, mask, (0, 0), **kw)
        return backend.finish(p, params, camera, image, saturated, region, region, **kw)

    wall = median_seconds(sample, lambda: wp.synchronize_device(device), 30)
    out = {"wall_seconds_synchronized_per_pass": wall}
    backend.sync_passes = False
    wall_async = median_seconds(sample, lambda: wp.synchronize_device(device), 30)
    out["wall_seconds_one_synchronize"] = wall_async
    try:
        wp.capture_begin(device)
        try:
            sample()
        finally:
            graph = wp.capture_end(device)
        graph_time = median_seconds(lambda: wp.capture_launch(graph),
                                    lambda: wp.synchronize_device(device), 50)
        out["graph_seconds"] = graph_time
    except Exception as e:  # a capture the driver refuses: keep the other figures
        out["graph_error"] = f"{type(e).__name__}: {e}"
        graph_time = wall_async
    backend.sync_passes = True
    moved = minimal_bytes(H * W, FRAMES)
    out["minimal_bytes"] = moved
    out["kernel_bytes_per_s"] = moved["total"] / graph_time
    out["ratio_to_d2d_copy"] = out["kernel_bytes_per_s"] / band["d2d_copy_bytes_per_s"]
    return out


class Prefetcher:
    """Pinned frame stacks copied to the device on a stream of their own, ahead of their use.

    Two device stacks take turns: :meth:`start` copies into the next one once the accumulate
    pass that read it last is done (:meth:`read`), beside whatever the device is computing;
    :meth:`ready` makes the compute stream wait for the copy and gives the stack, which the
    backend takes as it is (a ``wp.array`` on its device).
    """

    def __init__(self, wp, device: str, shape: tuple, dtype):
        self.wp = wp
        self.device = device
        self.copier = wp.Stream(device)
        self.stacks = [wp.empty(shape, dtype=dtype, device=device) for _ in range(2)]
        wp.synchronize_device(device)  # allocated before the copy stream uses them
        self.done = [None, None]  # per stack: the event of the accumulate that read it
        self.turn = 0

    def start(self, frames) -> tuple[int, object]:
        """Start copying ``frames`` (pinned host memory); (its stack, the copy's event)."""
        slot, self.turn = self.turn, self.turn ^ 1
        if self.done[slot] is not None:
            self.copier.wait_event(self.done[slot])
        self.wp.copy(self.stacks[slot], frames, stream=self.copier)
        return slot, self.copier.record_event()

    def ready(self, started: tuple[int, object]):
        """The stack of :meth:`start`, the compute stream waiting for its copy."""
        slot, copied = started
        self.wp.get_stream(self.device).wait_event(copied)
        return self.stacks[slot]

    def read(self, started: tuple[int, object]) -> None:
        """The compute stream's work so far has read the stack: the next copy may fill it."""
        self.done[started[0]] = self.wp.get_stream(self.device).record_event()


def warp_from_pinned(wp, frames: np.ndarray, device: str, band: dict, samples: int) -> dict:
    from gpu_blur.backends.warp import WarpBackend

    _, p, camera, params = prepared(SCENE)
    backend = WarpBackend(f"warp:{device}", "float32")
    region = Region.whole(H, W)
    pinned = wp.array(frames, dtype=wp.uint8, device="cpu", pinned=True)
    kw = {"seed": 1, "sample_index": 0}

    def sample():
        linear, mask = backend.accumulate(p, params, pinned, None, region)
        image, saturated = backend.to_raw(p, params, camera, linear, mask, (0, 0), **kw)
        return backend.finish(p, params, camera, image, saturated, region, region, **kw)

    per_sample = median_seconds(sample, lambda: wp.synchronize_device(device), samples)
    bound = band["pinned_h2d_bytes_per_s_sample"] / frames.nbytes
    out = {"one_at_a_time": {"seconds_per_sample": per_sample, "samples_per_s": 1 / per_sample,
                             "ratio_to_bound": (1 / per_sample) / bound},
           "bound_samples_per_s": bound}
    # pipelined: sample i + 1's frames copy on the copy stream while sample i's passes run
    second = wp.array(frames[::-1].copy(), dtype=wp.uint8, device="cpu", pinned=True)
    sources = (pinned, second)
    prefetcher = Prefetcher(wp, device, pinned.shape, pinned.dtype)

    def pipelined(count):
        coming = prefetcher.start(sources[0])
        for i in range(count):
            current, coming = coming, prefetcher.start(sources[(i + 1) % 2])
            stack = prefetcher.ready(current)
            linear, mask = backend.accumulate(p, params, stack, None, region)
            prefetcher.read(current)
            image, saturated = backend.to_raw(p, params, camera, linear, mask, (0, 0), **kw)
            backend.finish(p, params, camera, image, saturated, region, region, **kw)
        wp.synchronize_device(device)

    def rate():
        pipelined(3)
        start = time.perf_counter()
        pipelined(samples)
        return samples / (time.perf_counter() - start)

    synced = rate()
    out["pipelined"] = {"samples_per_s": synced, "ratio_to_bound": synced / bound}
    # as a training loop runs it: the host queues the passes and never waits for them (the
    # consumer reads the result on the device's stream), so it queues the next copy sooner
    backend.sync_passes = False
    free = rate()
    backend.sync_passes = True
    out["pipelined_no_host_sync"] = {"samples_per_s": free, "ratio_to_bound": free / bound}
    return out


def per_pass(wp, frames: np.ndarray, device: str) -> dict:
    """Each pass replayed alone as a CUDA graph (its kernels' time), frames on the device."""
    from gpu_blur.backends.warp import WarpBackend

    _, p, camera, params = prepared(SCENE)
    backend = WarpBackend(f"warp:{device}", "float32")
    region = Region.whole(H, W)
    stack = wp.array(frames, dtype=wp.uint8, device=device)
    kw = {"seed": 1, "sample_index": 0}
    linear, mask = backend.accumulate(p, params, stack, None, region)
    image, saturated = backend.to_raw(p, params, camera, linear, mask, (0, 0), **kw)
    backend.finish(p, params, camera, image, saturated, region, region, **kw)
    backend.sync_passes = False
    passes = {
        "accumulate": lambda: backend.accumulate(p, params, stack, None, region),
        "to_raw": lambda: backend.to_raw(p, params, camera, linear, mask, (0, 0), **kw),
        "finish": lambda: backend.finish(p, params, camera, image, saturated, region, region,
                                         **kw),
    }
    moved = minimal_bytes(H * W, FRAMES)
    out = {}
    for name, fn in passes.items():
        t = graph_seconds(wp, device, fn)
        out[name] = {"seconds": t, "bytes_per_s": moved[name] / t}
    backend.sync_passes = True
    return out


def realblur_j_inputs(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RealBlur-J's inputs: the first frame as its blurred image, and an 8-bit saturation mask
    (255 in every channel of a pixel whose brightest channel is 250 or more, else 0)."""
    image = frames[0]
    bright = image.max(axis=2, keepdims=True) >= 250
    return image, np.repeat(bright, 3, axis=2).astype(np.uint8) * 255


def realblur_j_on_device(wp, frames: np.ndarray, device: str, band: dict) -> dict:
    """The RealBlur-J scene (gpu_blur/data/scenes/realblur_j.toml: no blur, saturation, A7R3
    RAW round trip with Poisson-Gaussian noise, polynomial re-toning, float output) with its
    image and mask already on the device: each pass and the whole sample as CUDA graphs."""
    from gpu_blur.backends.warp import WarpBackend

    _, p, camera, params = prepared(REALBLUR_J)
    backend = WarpBackend(f"warp:{device}", "float32")
    region = Region.whole(H, W)
    image, mask = (backend.put(a) for a in realblur_j_inputs(frames))
    kw = {"seed": 1, "sample_index": 0}

    def sample():
        linear = backend.accumulate(p, params, image, mask, region)
        raw = backend.to_raw(p, params, camera, *linear, (0, 0), **kw)
        return backend.finish(p, params, camera, *raw, region, region, **kw)

    linear = backend.accumulate(p, params, image, mask, region)
    raw = backend.to_raw(p, params, camera, *linear, (0, 0), **kw)
    sample()
    backend.sync_passes = False
    passes = {"accumulate": lambda: backend.accumulate(p, params, image, mask, region),
              "to_raw": lambda: backend.to_raw(p, params, camera, *linear, (0, 0), **kw),
              "finish": lambda: backend.finish(p, params, camera, *raw, region, region, **kw)}
    moved = minimal_bytes(H * W, 2)
    out = {"scene": REALBLUR_J, "minimal_bytes": moved, "per_pass": {}}
    for name, fn in passes.items():
        t = graph_seconds(wp, device, fn)
        out["per_pass"][name] = {"seconds": t, "bytes_per_s": moved[name] / t}
    out["graph_seconds"] = graph_seconds(wp, device, sample)
    backend.sync_passes = True
    out["kernel_bytes_per_s"] = moved["total"] / out["graph_seconds"]
    out["ratio_to_d2d_copy"] = out["kernel_bytes_per_s"] / band["d2d_copy_bytes_per_s"]
    return out


def graph_seconds(wp, device: str, fn, runs: int = 50) -> float:
    """Median time of ``fn``'s launches captured once as a CUDA graph and replayed."""
    wp.capture_begin(device)
    try:
        fn()
    finally:
        graph = wp.capture_end(device)
    return median_seconds(lambda: wp.capture_launch(graph),
                          lambda: wp.synchronize_device(device), runs)


def through_synthesize(make_backend, frames: np.ndarray, samples: int, on_device: bool) -> dict:
    scene = scene_from_dict(SCENE)
    listed = list(frames)
    out = {}
    for overlap in (True, False):
        backend = make_backend(overlap)
        gpu_blur.synthesize(listed, scene, seed=1, sample_index=0, backend=backend,
                            on_device=on_device)
        totals: dict[str, float] = {}
        start = time.perf_counter()
        for i in range(samples):
            r = gpu_blur.synthesize(listed, scene, seed=1, sample_index=i + 1, backend=backend,
                                    on_device=on_device)
            if on_device:
                np.asarray(r.blurred[0:1, 0:1].numpy())  # wait for the result
            for k, v in r.timings.items():
                totals[k] = totals.get(k, 0.0) + v
        elapsed = time.perf_counter() - start
        out["overlapped" if overlap else "serial"] = {
            "samples_per_s": samples / elapsed,
            "mean_seconds": {k: v / samples for k, v in totals.items()}}
    out["overlap_gain"] = (out["overlapped"]["samples_per_s"]
                           / out["serial"]["samples_per_s"])
    return out


def through_batches(backend: str, frames: np.ndarray, samples: int, batch: int,
                    to_torch: bool) -> dict:
    """The public batch API, ``gpu_blur.Synthesizer``: B x F x H x W x 3 uint8 numpy frames in
    host memory (or, with ``to_torch``, torch CUDA tensors) to B results of the same type.

    The first batch builds the kernels; then ``samples`` samples in batches of ``batch``.
    """
    scene = scene_from_dict(SCENE)
    stack = np.ascontiguousarray(np.broadcast_to(frames, (batch, *frames.shape)))
    if to_torch:
        import torch

        stack = torch.from_numpy(stack).cuda()
    synth = gpu_blur.Synthesizer(scene, backend=backend, seed=1)

    def wait(out):
        if to_torch:
            torch.cuda.synchronize()
        return out

    wait(synth(stack, first_index=0))
    totals: dict[str, float] = {}
    start = time.perf_counter()
    done = 0
    while done < samples:
        out = wait(synth(stack, first_index=done + batch))
        for k, v in out.timings.items():
            totals[k] = totals.get(k, 0.0) + v
        done += batch
    elapsed = time.perf_counter() - start
    return {"samples_per_s": done / elapsed, "ms_per_sample": 1e3 * elapsed / done,
            "batch": batch, "inputs": "torch CUDA uint8" if to_torch else "numpy uint8",
            "mean_seconds_per_sample": {k: v / done for k, v in totals.items()}}


def section(results: dict, name: str, fn) -> None:
    try:
        results[name] = fn()
    except Exception:
        results[name] = {"error": traceback.format_exc(limit=3)}
    print(f"{name}: {json.dumps(results[name], default=float)[:600]}", flush=True)


def main() -> int:
    out_path = sys.argv[1] if len(sys.argv) > 1 else "gpu_targets.json"
    samples = int(sys.argv[2]) if len(sys.argv) > 2 else 20
    import warp as wp

    wp.init()
    device = "cuda:0"
    frames = make_frames()
    results = {"host": platform.node(), "python": platform.python_version(),
               "warp": wp.__version__, "gpu": wp.get_device(device).name,
               "image": [H, W], "frames": FRAMES, "scene": SCENE, "samples": samples}
    section(results, "bandwidths", lambda: bandwidths(wp, device))
    band = results["bandwidths"]
    section(results, "warp_frames_on_device",
            lambda: warp_on_device(wp, frames, device, band))
    section(results, "warp_frames_in_pinned_memory",
            lambda: warp_from_pinned(wp, frames, device, band, samples))

    def warp_backend(overlap):
        from gpu_blur.backends.warp import WarpBackend
        return WarpBackend(f"warp:{device}", "float32", overlap=overlap)

    def opencl_backend(overlap):
        from gpu_blur.backends.opencl import OpenCLBackend
        return OpenCLBackend("opencl", "float32", overlap=overlap)

    section(results, "warp_per_pass", lambda: per_pass(wp, frames, device))
    section(results, "warp_realblur_j_on_device",
            lambda: realblur_j_on_device(wp, frames, device, band))
    section(results, "warp_synthesize_numpy_frames",
            lambda: through_synthesize(warp_backend, frames, samples, on_device=True))
    section(results, "opencl_synthesize_numpy_frames",
            lambda: through_synthesize(opencl_backend, frames, samples, on_device=False))
    for name in ("warp", "opencl"):
        section(results, f"{name}_batches_numpy_frames",
                lambda n=name: through_batches(n, frames, 4 * samples, 16, to_torch=False))
    section(results, "warp_batches_torch_cuda_frames",
            lambda: through_batches("warp", frames, 4 * samples, 16, to_torch=True))
    try:
        from gpu_blur.backends.opencl import OpenCLBackend
        results["opencl_device"] = OpenCLBackend("opencl").device
    except Exception as e:
        results["opencl_device"] = f"unavailable: {e}"
    with open(out_path, "w") as f:
        json.dump(results, f, indent=1, default=float)

    on_dev = results["warp_frames_on_device"]
    rows = [
        ("d2d copy GB/s", band.get("d2d_copy_bytes_per_s", float("nan")) / 1e9),
        ("pinned H2D GB/s (one sample)",
         band.get("pinned_h2d_bytes_per_s_sample", float("nan")) / 1e9),
        ("frames on device: wall ms (sync per pass)",
         1e3 * on_dev.get("wall_seconds_synchronized_per_pass", float("nan"))),
        ("frames on device: wall ms (one sync)",
         1e3 * on_dev.get("wall_seconds_one_synchronize", float("nan"))),
        ("frames on device: CUDA graph ms", 1e3 * on_dev.get("graph_seconds", float("nan"))),
        ("kernel bytes / d2d copy rate", on_dev.get("ratio_to_d2d_copy", float("nan"))),
    ]
    pinned = results["warp_frames_in_pinned_memory"]
    for mode in ("one_at_a_time", "pipelined", "pipelined_no_host_sync"):
        rows.append((f"pinned frames {mode}: samples/s",
                     pinned.get(mode, {}).get("samples_per_s", float("nan"))))
        rows.append((f"pinned frames {mode}: ratio to H2D bound",
                     pinned.get(mode, {}).get("ratio_to_bound", float("nan"))))
    for name, r in results["warp_per_pass"].items():
        if isinstance(r, dict):
            rows.append((f"{name}: graph ms", 1e3 * r["seconds"]))
            rows.append((f"{name}: GB/s of its minimal bytes", r["bytes_per_s"] / 1e9))
    realblur = results["warp_realblur_j_on_device"]
    rows.append(("RealBlur-J on device: CUDA graph ms",
                 1e3 * realblur.get("graph_seconds", float("nan"))))
    rows.append(("RealBlur-J kernel bytes / d2d copy rate",
                 realblur.get("ratio_to_d2d_copy", float("nan"))))
    for backend in ("warp", "opencl"):
        r = results[f"{backend}_synthesize_numpy_frames"]
        for mode in ("overlapped", "serial"):
            rows.append((f"{backend} synthesize {mode}: samples/s",
                         r.get(mode, {}).get("samples_per_s", float("nan"))))
    print(f"\n{results['gpu']}")
    for label, value in rows:
        print(f"  {label:45s} {value:10.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
