"""Train small deblurring networks on pairs synthesized on the fly (issue 16).

Each network (``--nets``: ``tiny``, a few 3 x 3 convolutions; ``unet``, a U-Net the size of
MIMO-UNet) trains with L1 loss and Adam for ``--steps`` steps of ``--batch`` random ``--crop``
crops, in four loops over the same DataLoader (workers decode and crop the sharp inputs,
uint8, :mod:`gpu_blur.datasets`):

* **on the fly**: :class:`gpu_blur.torch.RealisticBlur` synthesizes each batch on the training
  device (Warp on CUDA, ``warp:cpu`` with ``--device cpu``); nothing else waits for the device,
  as in a real training loop.
* **presynthesized**: the same loop, with the synthesis replaced by one batch synthesized before
  it (the loader still runs). **Synthesis share** = 1 - its step time / on the fly's: what
  synthesizing on the fly adds to a step.
* **synchronized**: on the fly with the device synchronized before and after the transform;
  its time over the step time is the transform's share with no overlap at all (an upper
  bound, the share this file reported before).
* **CPU workers**: each DataLoader worker also runs the numpy float64 path
  (``gpu_blur.synthesize(..., backend="numpy")``) on its items, as a CPU pipeline would; its
  share is the time the step waits for the loader.

Inputs: ``--input`` with a scene of blur mode none reads the RSBlur authors' averaged layouts
(:class:`~gpu_blur.datasets.BlurredImages`); a folder of photos or, by default, the built-in
photo (:class:`~gpu_blur.datasets.Photos`) for the other modes. The first step of each loop
(worker start, kernel builds) is not timed.

Run from the repository root, on a GPU:
``PYTHONPATH=$PWD python bench/train_on_the_fly.py --json OUT.json`` (defaults: both
networks, 300 steps of 16 crops of 256, 8 workers);
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


class Tiny(torch.nn.Module):
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


def _blocks(channels: int, count: int) -> torch.nn.Sequential:
    """``count`` residual blocks of two 3 x 3 convolutions (ReLU between)."""

    class Block(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.body = torch.nn.Sequential(
                torch.nn.Conv2d(channels, channels, 3, padding=1), torch.nn.ReLU(),
                torch.nn.Conv2d(channels, channels, 3, padding=1))

        def forward(self, x):
            return x + self.body(x)

    return torch.nn.Sequential(*(Block() for _ in range(count)))


class UNet(torch.nn.Module):
    """An encoder-decoder deblurring network of MIMO-UNet's size, single scale.

    Three scales of ``width``, 2 ``width`` and 4 ``width`` channels with ``blocks`` residual
    blocks in each encoder and decoder stage, stride-2 convolutions down, transposed ones up,
    skip connections added, a global residual: the layout and size of MIMO-UNet (Cho et al.,
    ICCV 2021: 32 channels, 8 blocks a stage, 6.8 M parameters) without its multi-scale inputs
    and outputs. Crops: multiples of 4.
    """

    def __init__(self, width: int = 32, blocks: int = 8):
        super().__init__()
        c1, c2, c3 = width, 2 * width, 4 * width
        conv = torch.nn.Conv2d
        self.head = conv(3, c1, 3, padding=1)
        self.enc1, self.enc2, self.mid = _blocks(c1, blocks), _blocks(c2, blocks), _blocks(
            c3, blocks)
        self.down1, self.down2 = conv(c1, c2, 3, stride=2, padding=1), conv(c2, c3, 3, stride=2,
                                                                            padding=1)
        self.up2 = torch.nn.ConvTranspose2d(c3, c2, 4, stride=2, padding=1)
        self.up1 = torch.nn.ConvTranspose2d(c2, c1, 4, stride=2, padding=1)
        self.dec2, self.dec1 = _blocks(c2, blocks), _blocks(c1, blocks)
        self.tail = conv(c1, 3, 3, padding=1)

    def forward(self, x):
        e1 = self.enc1(self.head(x))
        e2 = self.enc2(self.down1(e1))
        d2 = self.dec2(self.up2(self.mid(self.down2(e2))) + e2)
        return x + self.tail(self.dec1(self.up1(d2) + e1))


NETS = {"tiny": Tiny, "unet": UNet}


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


def train(net, loader, device, steps: int, synthesize, *, synchronized: bool = False) -> dict:
    """``steps`` timed steps after one untimed: samples/s and where the step time goes.

    ``synthesize(batch)`` gives (blurred, sharp), B x 3 x H x W on ``device``. With
    ``synchronized`` the device is synchronized before and after it, and its time (host and
    device, with no overlap) is reported as ``transform_share``.
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
        if synchronized:
            sync(device)
        t2 = time.perf_counter()
        blurred, sharp = synthesize(batch)
        if synchronized:
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
    result = {"samples_per_s": samples / took, "step_ms": 1e3 * took / steps,
              "waiting_for_data_share": waited / took, "final_loss": float(loss.item()),
              "steps": steps}
    if synchronized:
        result["transform_share"] = synthesized / took
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=300, help="timed training steps per loop")
    p.add_argument("--batch", type=int, default=16, help="samples per step")
    p.add_argument("--crop", type=int, default=256, help="crop size (a multiple of 4)")
    p.add_argument("--workers", type=int, default=8, help="DataLoader workers")
    p.add_argument("--nets", default="tiny,unet",
                   help=f"networks to train, comma-separated, of {', '.join(NETS)}")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--scene", help="scene TOML or built-in name (default: random kernels)")
    p.add_argument("--input", help="data folder (default: the built-in photo)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write the results here")
    args = p.parse_args()
    nets = args.nets.split(",")
    unknown = sorted(set(nets) - set(NETS))
    if unknown:
        p.error(f"--nets {unknown[0]!r} is not a network; choose from {', '.join(NETS)}")
    if args.crop % 4:
        p.error(f"--crop {args.crop} must be a multiple of 4 (the U-Net halves it twice)")
    device = torch.device(args.device)
    scene = load_scene(args.scene) if args.scene else scene_from_dict(DEFAULT_SCENE)
    items = args.steps * args.batch * 2  # enough for two loops without a second epoch
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

    made = on_device(next(iter(torch.utils.data.DataLoader(data, **{
        **loader_options, "num_workers": 0, "persistent_workers": False}))))

    def presynthesized(batch):
        return made

    results = {"device": (torch.cuda.get_device_name(device) if device.type == "cuda"
                          else f"CPU ({platform.processor() or platform.machine()})"),
               "backend": backend, "scene": scene.to_dict(), "batch": args.batch,
               "crop": args.crop, "workers": args.workers, "items": len(data),
               "input": args.input or "built-in photo", "nets": {}}
    loops = (("on_the_fly", data, on_device, False),
             ("presynthesized", data, presynthesized, False),
             ("synchronized", data, on_device, True),
             ("cpu_workers", NumpySynthesis(data, scene, args.seed), from_workers, False))
    for name in nets:
        net_results = results["nets"][name] = {}
        for loop, items_of, step, synchronized in loops:
            torch.manual_seed(args.seed)
            net = NETS[name]().to(device)
            loader = torch.utils.data.DataLoader(items_of, **loader_options)
            r = net_results[loop] = train(net, loader, device, args.steps, step,
                                          synchronized=synchronized)
            del loader  # its workers end before the next loop's start
            print(f"{name} {loop}: {r['samples_per_s']:.1f} samples/s, {r['step_ms']:.1f} "
                  f"ms/step, waiting for data {100 * r['waiting_for_data_share']:.1f} %"
                  + (f", transform {100 * r['transform_share']:.1f} %" if synchronized else ""),
                  flush=True)
        r = net_results
        r["parameters"] = sum(x.numel() for x in NETS[name]().parameters())
        r["synthesis_share"] = 1 - r["presynthesized"]["step_ms"] / r["on_the_fly"]["step_ms"]
        r["speedup_over_cpu_workers"] = (r["on_the_fly"]["samples_per_s"]
                                         / r["cpu_workers"]["samples_per_s"])
        print(f"{name} on {results['device']}: synthesis share {100 * r['synthesis_share']:.1f} %"
              f" (synchronized: {100 * r['synchronized']['transform_share']:.1f} %); on the fly "
              f"{r['speedup_over_cpu_workers']:.2f}x the CPU workers", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=float)


if __name__ == "__main__":
    main()
