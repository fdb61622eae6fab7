"""Whole-pipeline outputs are bit for bit what tests/data/golden_outputs.json recorded.

The record holds one digest per case under what its bits depend on (tests/golden.py's
``record_key``: numpy alone; a kernel device with its runtime's version and target); a key not
recorded is skipped, never compared with another runtime's digest. CI runs the example scenes
and the interpolated case; ``GPU_BLUR_HEAVY=1`` runs every case and the tiled runs.
"""

import json
import os

import pytest
from conftest import BACKEND_SPECS, TEST_DATA
from golden import CASES, TILED, run_case

RECORD = json.loads((TEST_DATA / "golden_outputs.json").read_text())
HEAVY = os.environ.get("GPU_BLUR_HEAVY") == "1"
RUNS = [(c, None) for c in (CASES if HEAVY else ("minimal", "rsblur", "realblur_j",
                                                 "interpolated"))]
RUNS += list(TILED.items()) if HEAVY else []


@pytest.mark.parametrize("spec", BACKEND_SPECS)
@pytest.mark.parametrize("case,tile", RUNS)
@pytest.mark.bits
def test_outputs_match_the_recorded_digests(spec, case, tile):
    got = run_case(case, spec, tile)
    if got is None:
        return  # the case does not exist at this precision (fast_math in float64)
    digest, key = got
    name = case if tile is None else f"{case}@{tile[0]}x{tile[1]}"
    if name not in RECORD.get(key, {}):
        pytest.skip(f"{spec} is {key}, whose outputs were not recorded")
    assert digest == RECORD[key][name], f"{key} {name}: the output changed"


def test_numpy_digests_are_recorded_whatever_the_cpu():
    # numpy's bits depend on nothing but the code: its key names no CPU, runtime or version
    for case in ("minimal", "rsblur", "realblur_j"):
        assert case in RECORD["numpy float64 (host CPU)"], case
