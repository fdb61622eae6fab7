"""One sample's three Warp passes on the GPU, for a profiler: ``ncu`` sees each pass's kernel.

The sample of ``bench/gpu_targets.py`` (9 uint8 frames of 1920 x 1200 already on the device,
RSBlur-like plan, float32; or, with ``--scene realblur_j``, its RealBlur-J sample): a first
sample builds the kernels and the 8-bit table, then ``--samples`` more run for the profiler.
On the GPU machine, from the repository root::

    cd bench && ncu --kernel-name regex:"blur_average_exact|linearize|unit_values|to_raw|finish" \
        --launch-skip 3 --launch-count 3 --section SpeedOfLight --section Occupancy \
        --section LaunchStats --section InstructionStats python3 profile_passes.py > ncu.txt

(RealBlur-J's first pass is two kernels, linearize and unit_values: skip and count 4.) Then
``python3 profile_passes.py --read ncu.txt OUT.json`` keeps each profiled kernel's main
readings (duration, throughputs, registers, occupancy, instructions) as JSON.
"""

from __future__ import annotations

import argparse
import json
import re
import sys

from gpu_targets import REALBLUR_J, SCENE, H, W, make_frames, prepared, realblur_j_inputs

from gpu_blur.tiling import Region

#: ncu's readings kept by ``--read``: its row name -> the JSON key.
READINGS = {
    "Duration": "duration_us",
    "DRAM Throughput": "dram_throughput_percent",
    "Memory Throughput": "memory_throughput_percent",
    "L1/TEX Cache Throughput": "l1_throughput_percent",
    "L2 Cache Throughput": "l2_throughput_percent",
    "Compute (SM) Throughput": "sm_throughput_percent",
    "Issue Slots Busy": "issue_slots_busy_percent",
    "Registers Per Thread": "registers_per_thread",
    "Theoretical Occupancy": "theoretical_occupancy_percent",
    "Achieved Occupancy": "achieved_occupancy_percent",
    "Executed Instructions": "executed_warp_instructions",
}


def read_ncu(text: str) -> dict:
    """Each profiled kernel's :data:`READINGS` from ncu's text report, by kernel name."""
    kernels: dict = {}
    current = None
    for line in text.splitlines():
        head = re.match(r"^  (\S+) \((\d+), (\d+), (\d+)\)x\((\d+), 1, 1\)", line)
        if head:
            name = re.sub(r"_[0-9a-f]{8}_cuda_kernel_forward$", "", head.group(1))
            current = kernels.setdefault(name.split("__locals__")[-1], {})
            current["grid_blocks"] = int(head.group(2)) * int(head.group(3)) * int(head.group(4))
            current["block_threads"] = int(head.group(5))
            continue
        row = re.match(r"^    (\S.*?\S)\s{2,}(\S+)?\s+([\d,.]+)$", line)
        if current is not None and row and row.group(1) in READINGS:
            key = READINGS[row.group(1)]
            if key not in current:  # the first of a kernel's rows of that name
                current[key] = float(row.group(3).replace(",", ""))
    return kernels


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=1, help="samples after the first (default 1)")
    p.add_argument("--device", default="cuda:0", help="Warp device (default cuda:0)")
    p.add_argument("--scene", choices=("rsblur", REALBLUR_J), default="rsblur",
                   help="the RSBlur-like 9-frame sample (default) or the RealBlur-J one")
    p.add_argument("--read", nargs=2, metavar=("NCU_TXT", "OUT_JSON"),
                   help="read an ncu text report instead of running; write its readings")
    args = p.parse_args(argv)
    if args.read:
        with open(args.read[0]) as f:
            readings = read_ncu(f.read())
        with open(args.read[1], "w") as f:
            json.dump(readings, f, indent=1)
        print(json.dumps(readings, indent=1))
        return 0
    import warp as wp

    from gpu_blur.backends.warp import WarpBackend

    wp.config.quiet = True
    realblur = args.scene == REALBLUR_J
    _, plan, camera, params = prepared(REALBLUR_J if realblur else SCENE)
    backend = WarpBackend(f"warp:{args.device}", "float32")
    region = Region.whole(H, W)
    frames = make_frames()
    if realblur:
        image, mask = (backend.put(a) for a in realblur_j_inputs(frames))
    else:
        image, mask = backend.put(frames), None
    for _ in range(1 + args.samples):
        linear, sat_mask = backend.accumulate(plan, params, image, mask, region)
        raw, saturated = backend.to_raw(plan, params, camera, linear, sat_mask, (0, 0), seed=1,
                                        sample_index=0)
        backend.finish(plan, params, camera, raw, saturated, region, region, seed=1,
                       sample_index=0)
    wp.synchronize_device(args.device)
    print(f"ran {1 + args.samples} {args.scene} samples, {W} x {H}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
