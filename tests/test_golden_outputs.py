"""Whole-pipeline outputs are bit for bit what tests/data/golden_outputs.json recorded.

The record holds one digest per case and device (see tests/golden.py). CI runs
the example scenes; ``GPU_BLUR_HEAVY=1`` runs every case and the tiled runs.
"""

import json
import os
from pathlib import Path

import pytest
from conftest import BACKEND_SPECS
from golden import CASES, TILED, by_device, device_key, run_case

RECORD = by_device(json.loads((Path(__file__).parent / "data" / "golden_outputs.json").read_text()))
HEAVY = os.environ.get("GPU_BLUR_HEAVY") == "1"
RUNS = [(c, None) for c in (CASES if HEAVY else ("minimal", "rsblur", "realblur_j"))]
RUNS += list(TILED.items()) if HEAVY else []


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("case,tile", RUNS)
@pytest.mark.bits
def test_outputs_match_the_recorded_digests(spec, case, tile):
    got = run_case(case, spec, tile)
    if got is None:
        return  # the case does not exist at this precision (fast_math in float64)
    digest, device = got
    if device_key(device) not in RECORD:
        pytest.skip(f"{spec} is {device}, whose outputs were not recorded")
    key = case if tile is None else f"{case}@{tile[0]}x{tile[1]}"
    assert digest == RECORD[device_key(device)][key], f"{device} {key}: the output changed"
