"""What per-tile saturation skipping saves: a tiled sample with and without it.

Run from the repository root: ``python bench/tile_saturation.py [--size WxH] [--tile R,C]
[--backends B,B] [OUT.json]`` (default: 480 x 320 in 64 x 64 tiles on numpy, opencl:0:0,
opencl:1:0 and warp:cpu; ``bench/results/tile_saturation_<host>.json``).

Input: the built-in photo (its spoon and cup rim clip, the rest does not), scene ``rsblur``
with ``saturation.mode = "on"`` and a camera-shake blur, so some tiles hold clipped pixels and
most do not. Each backend runs the tiled sample with the skip (tiles whose mask is 0 and whose
linear image lies in [0, 1) run to_raw and finish without saturate and restore:
``gpu_blur.scheduler.saturation_is_identity``) and with it turned off (every tile runs them),
alternating, median of 5 runs after a warm-up (kernel builds); the outputs are compared bit
for bit. Times are whole ``Synthesizer.sample`` calls.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path
from unittest import mock

import cv2
import numpy as np

from gpu_blur import scheduler
from gpu_blur.analysis.bench.host import cpu_name
from gpu_blur.dataset import default_photo
from gpu_blur.imageio import read_image
from gpu_blur.pipeline import Synthesizer
from gpu_blur.scene import load_scene, scene_from_dict

RUNS = 5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", type=Path,
                        default=Path(f"bench/results/tile_saturation_{platform.node()}.json"))
    parser.add_argument("--size", default="480x320")
    parser.add_argument("--tile", default="64,64")
    parser.add_argument("--backends", default="numpy,opencl:0:0,opencl:1:0,warp:cpu")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    tile = tuple(int(v) for v in args.tile.split(","))
    photo = cv2.resize(read_image(default_photo()), (w, h), interpolation=cv2.INTER_AREA)
    settings = load_scene("rsblur").to_dict()
    settings["blur"].update(mode="trajectory", extent=[6.0, 6.0])
    settings["saturation"]["mode"] = "on"
    scene = scene_from_dict(settings)
    rows = []
    for backend in args.backends.split(","):
        synth = Synthesizer(scene, backend=backend, schedule=scheduler.Schedule(tile=tile))
        skip = synth.sample([photo])  # warm-up: kernel builds, both plans
        with mock.patch.object(scheduler, "saturation_is_identity", return_value=False):
            every = synth.sample([photo])
        times = {"skip": [], "every_tile": []}
        for _ in range(RUNS):
            for name in times:
                patch = (mock.patch.object(scheduler, "saturation_is_identity",
                                           return_value=False) if name == "every_tile"
                         else mock.MagicMock())
                with patch:
                    start = time.perf_counter()
                    synth.sample([photo])
                    times[name].append(time.perf_counter() - start)
        row = {"backend": backend, "device": synth.runner.model, "tiles": skip.tiles,
               "unsaturated_tiles": skip.unsaturated_tiles,
               "same_bits": bool(np.array_equal(skip.blurred, every.blurred)),
               **{f"{k}_ms": round(statistics.median(v) * 1e3, 2) for k, v in times.items()}}
        row["saved_fraction"] = round(1 - row["skip_ms"] / row["every_tile_ms"], 3)
        rows.append(row)
        print(f"{backend:<12} {row['unsaturated_tiles']}/{row['tiles']} tiles skip: "
              f"{row['skip_ms']:8.1f} ms vs {row['every_tile_ms']:8.1f} ms every tile, "
              f"same bits {row['same_bits']}", flush=True)
    result = {"host": cpu_name(), "size_wxh": [w, h], "tile": list(tile), "runs": RUNS,
              "input": "built-in photo, scene rsblur with saturation on and camera shake",
              "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
