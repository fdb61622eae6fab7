"""What the plan saves: per example scene and backend, the passes' time with the scene's plan
against every stage forced on, and what each stage costs (``gpu-blur plan --cost``'s figures).

Run from the repository root: ``python bench/plan_cost.py [--size WxH] [--backends B,B]
[OUT.json]`` (default: 480 x 320 on numpy, opencl:0:0 and warp:cpu;
``bench/results/plan_cost_<host>.json``). On a GPU: ``--backends numpy,opencl:0:0,warp:cuda:0
--size 1920x1200``. Input: the built-in photo panned 2 px a frame
(:func:`gpu_blur.analysis.stage_cost.bench_inputs`). Times are medians of 5 runs after a warm-up
(kernel builds), the device synchronized; stages of a fused pass are timed as the passes with
less without them, each with the interval of that median difference (a stage whose interval
holds 0 costs nothing measurable here; :mod:`gpu_blur.analysis.stage_cost`).
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

from gpu_blur.analysis.bench.host import cpu_name
from gpu_blur.analysis.stage_cost import stage_costs

SCENES = ("minimal", "realblur_j", "rsblur")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", type=Path,
                        default=Path(f"bench/results/plan_cost_{platform.node()}.json"))
    parser.add_argument("--size", default="480x320")
    parser.add_argument("--backends", default="numpy,opencl:0:0,warp:cpu")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    rows = []
    for scene in SCENES:
        for backend in args.backends.split(","):
            c = stage_costs(scene, backend, (h, w))
            rows.append({
                "scene": scene, "backend": backend, "device": c.device,
                "accumulate_ms": round(c.accumulate * 1e3, 2),
                "with_plan_ms": round(c.with_plan * 1e3, 2),
                "every_stage_on_ms": round(c.every_stage * 1e3, 2),
                "saved_fraction": round(1 - c.with_plan / c.every_stage, 3),
                "stages_ms": {name: {"kept": kept, "ms": round(s * 1e3, 2),
                                     "interval_ms": [round(t * 1e3, 2) for t in c.intervals[name]]}
                              for name, (kept, s) in c.switches.items()}})
            print(f"{scene:<11} {backend:<11} plan {rows[-1]['with_plan_ms']:8.1f} ms, "
                  f"every stage on {rows[-1]['every_stage_on_ms']:8.1f} ms", flush=True)
    result = {"host": cpu_name(), "size_wxh": [w, h], "input": "built-in photo panned 2 px a "
              "frame (9 frames for rsblur's average, one photo otherwise)", "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
