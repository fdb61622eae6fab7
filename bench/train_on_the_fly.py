"""Train a small deblurring network on pairs synthesized on the fly (issue 16).

Two loops train the same network (a few 3 x 3 convolutions with a residual connection, L1
loss, Adam) for ``--steps`` steps of ``--batch`` random ``--crop`` crops, and report samples
per second and where each step's time goes:

* **on the fly**: DataLoader workers decode and crop the sharp inputs (uint8,
  :mod:`gpu_blur.datasets`); :class:`gpu_blur.torch.RealisticBlur` synthesizes the blurred
  and sharp pair on the training device (Warp on CUDA, ``warp:cpu`` with ``--device cpu``).
  Synthesis share: the transform's time (synchronized before and after) over the step time.
* **CPU workers**: the same data set, each worker also running the numpy float64 path
  (``gpu_blur.synthesize(..., backend="numpy")``) on its items, as a CPU DataLoader
  pipeline would. Synthesis share: the time the step waits for the loader over the step time.

Inputs: ``--input`` with a scene of blur mode none reads the RSBlur authors' averaged layouts
(:class:`~gpu_blur.datasets.BlurredImages`); a folder of photos or, by default, the built-in
photo (:class:`~gpu_blur.datasets.Photos`) for the other modes. The first step of each loop
(worker start, kernel builds) is not timed.

Run from the repository root, on a GPU:
``PYTHONPATH=$PWD python bench/train_on_the_fly.py --json OUT.json`` (defaults: 300 steps of
16 crops of 256, 8 workers);
a check on a CPU: ``--device cpu --steps 3 --batch 2 --crop 64 --workers 2``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch

import gpu_blur
from gpu_blur.datasets import BlurredImages, Photos, epoch_seed
from gpu_blur.scene import load_scene, scene_from_dict
from gpu_blur.torch import RealisticBlur

#: The default scene: GoPro_U-style random motion kernels over one photo, saturation,
#: Poisson-Gaussian noise and the RAW round trip; float output, no border crop.
DEFAULT_SCENE = {"blur": {"mode": "kernel"}, "output": {"bits": 0, "crop": 0}}


class Deblur(torch.nn.Module):
    """A small residual CNN: ``depth`` 3 x 3 convolutions of ``width`` channels."""

    def __init__(self, width: int = 32, depth: int = 4):
        super().__init__()
        layers, channels = [], 3
        for _ in range(depth - 1):
            layers += [torch.nn.Conv2d(channels, width, 3, padding=1), torch.nn.ReLU()]
            channels = width
        layers.append(torch.nn.Conv2d(channels, 3, 3, padding=1))
        self.body = torch.nn.Sequential(*layers)

    def forward(self, x):
        return x + self.body(x)


class NumpySynthesis(torch.utils.data.Dataset):
    """The data set's items synthesized in the worker by the numpy path.

    Items: (index, blurred, sharp), H x W x 3 float32, drawn from (seed, epoch, index) as the
    transform draws them.
    """

    def __init__(self, data, scene, seed: int):
        self.data, self.scene, self.seed = data, scene, seed

    def __len__(self):
        return len(self.data)

    def __getitem__(self, i):
        index, *images = self.data[i]
        inputs = (dict(zip(("blurred", "mask", "sharp"), images, strict=True))
                  if self.scene.blur.mode == "none" else images[0])
        out = gpu_blur.synthesize(inputs, self.scene, seed=epoch_seed(self.seed, self.data.epoch),
                                  sample_index=index, backend="numpy")
        return index, out.blurred, out.sharp


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def train(net, loader, device, steps: int, synthesize) -> dict:
    """``steps`` timed steps after one untimed: samples/s and the shares of the step time.

    ``synthesize(batch)`` gives (blurred, sharp), B x 3 x H x W on ``device``; its time is
    taken between two device synchronizations (which cost the loop a little overlap).
    """
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    batches = iter(loader)
    waited = synthesized = 0.0
    samples = 0
    for step in range(steps + 1):
        if step == 1:
            sync(device)
            start, waited, synthesized, samples = time.perf_counter(), 0.0, 0.0, 0
        t0 = time.perf_counter()
        try:
            batch = next(batches)
        except StopIteration:
            batches = iter(loader)
            batch = next(batches)
        t1 = time.perf_counter()
        sync(device)
        t2 = time.perf_counter()
        blurred, sharp = synthesize(batch)
        sync(device)
        t3 = time.perf_counter()
        loss = torch.nn.functional.l1_loss(net(blurred), sharp)
        opt.zero_grad()
        loss.backward()
        opt.step()
        waited += t1 - t0
        synthesized += t3 - t2
        samples += blurred.shape[0]
    sync(device)
    took = time.perf_counter() - start
    return {"samples_per_s": samples / took, "step_ms": 1e3 * took / steps,
            "waiting_for_data_share": waited / took, "transform_share": synthesized / took,
            "final_loss": float(loss.item()), "steps": steps}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=300, help="timed training steps per loop")
    p.add_argument("--batch", type=int, default=16, help="samples per step")
    p.add_argument("--crop", type=int, default=256, help="crop size (even)")
    p.add_argument("--workers", type=int, default=8, help="DataLoader workers")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--scene", help="scene TOML or built-in name (default: random kernels)")
    p.add_argument("--input", help="data folder (default: the built-in photo)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write the results here")
    args = p.parse_args()
    device = torch.device(args.device)
    scene = load_scene(args.scene) if args.scene else scene_from_dict(DEFAULT_SCENE)
    items = args.steps * args.batch * 2  # enough for both loops without a second epoch
    if scene.blur.mode == "none":
        data = BlurredImages(args.input, crop=args.crop, flips=True, seed=args.seed)
    else:
        data = Photos(args.input, samples_per_photo=1 if args.input else items,
                      crop=args.crop, flips=True, seed=args.seed)
    backend = (f"warp:cuda:{device.index or 0}" if device.type == "cuda" else "warp:cpu")
    blur = RealisticBlur(scene, seed=args.seed, backend=backend, channels_first=False)
    loader_options = {"batch_size": args.batch, "shuffle": True, "drop_last": True,
                      "num_workers": args.workers, "pin_memory": device.type == "cuda",
                      "persistent_workers": args.workers > 0}

    def on_device(batch):
        index, *images = batch
        images = [x.to(device, non_blocking=True) for x in images]
        blurred, sharp = blur(*images, indices=index, epoch=0)
        return blurred.permute(0, 3, 1, 2), sharp.permute(0, 3, 1, 2)

    def from_workers(batch):
        _, blurred, sharp = batch
        return tuple(x.to(device, non_blocking=True).permute(0, 3, 1, 2)
                     for x in (blurred, sharp))

    torch.manual_seed(args.seed)
    results = {"device": (torch.cuda.get_device_name(device) if device.type == "cuda"
                          else f"CPU ({platform.processor() or platform.machine()})"),
               "backend": backend, "scene": scene.to_dict(), "batch": args.batch,
               "crop": args.crop, "workers": args.workers, "items": len(data),
               "input": args.input or "built-in photo"}
    for name, loader, step in (
            ("on_the_fly", torch.utils.data.DataLoader(data, **loader_options), on_device),
            ("cpu_workers", torch.utils.data.DataLoader(
                NumpySynthesis(data, scene, args.seed), **loader_options), from_workers)):
        net = Deblur().to(device)
        results[name] = train(net, loader, device, args.steps, step)
        r = results[name]
        print(f"{name}: {r['samples_per_s']:.1f} samples/s, {r['step_ms']:.1f} ms/step, "
              f"waiting for data {100 * r['waiting_for_data_share']:.1f} %, transform "
              f"{100 * r['transform_share']:.1f} %", flush=True)
    results["synthesis_share"] = {"on_the_fly": results["on_the_fly"]["transform_share"],
                                  "cpu_workers": results["cpu_workers"]["waiting_for_data_share"]}
    results["speedup"] = (results["on_the_fly"]["samples_per_s"]
                          / results["cpu_workers"]["samples_per_s"])
    print(f"on {results['device']}: on the fly {results['speedup']:.2f}x the CPU workers; "
          f"synthesis share {100 * results['synthesis_share']['on_the_fly']:.1f} % vs "
          f"{100 * results['synthesis_share']['cpu_workers']:.1f} % (waiting for workers)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=float)


if __name__ == "__main__":
    main()
