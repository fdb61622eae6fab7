"""Accuracy against time for every accuracy knob, on numpy and every OpenCL and Warp device.

Run from the repository root: ``python bench/accuracy_vs_time.py [--size WxH] [--backends
LIST] [--quick] [--runs N] [--output DIR] [--tag TAG]`` (default output ``bench/results``).
The same as ``gpu-blur bench``; what it measures and how is in ``gpu_blur/analysis/bench/``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from gpu_blur.analysis.bench import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], default_output=Path(__file__).parent / "results"))
