"""Test hooks: environment variables that make gpu_blur misbehave on purpose, for tests only.

None of these is an option: never set them outside a test. Each lets a test put the product at
a known failure point that it could not reach from outside (a killed run, a lost Ray node, a
wrong kernel). The product calls the functions below at those points; with the variables unset
they do nothing.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

__all__ = ["TEST_FAIL_ONCE", "TEST_FAULT", "TEST_SLEEP_AFTER", "fail_once", "fail_once_setting",
           "fault_planted", "planted_fault", "sleep_after"]

#: ``GPU_BLUR_TEST_SLEEP_AFTER=<n>``: ``gpu-blur generate`` sleeps for an hour right after
#: sample ``n``'s manifest line is written, so a test can kill it at a known point
#: (tests/io/test_resume.py, tests/io/test_output_folder.py, tests/io/test_faults.py).
TEST_SLEEP_AFTER = "GPU_BLUR_TEST_SLEEP_AFTER"

#: ``GPU_BLUR_TEST_FAULT=<pass>`` or ``<pass>@<row>,<col>`` (``pass`` one of accumulate,
#: to_raw, finish): the kernel backends (OpenCL, Warp) corrupt that pass's output at global
#: pixel (row, col) (default 0, 0) by 0.25, in every tile whose output holds the pixel, so a
#: test can check that spot checks (``--verify``) catch a wrong kernel
#: (tests/synthesis/test_scheduler.py).
TEST_FAULT = "GPU_BLUR_TEST_FAULT"

#: ``GPU_BLUR_TEST_FAIL_ONCE=<index>:<marker file>`` in the driver's environment: the Ray task
#: that makes sample ``index`` kills its worker process (as a lost node would) unless the marker
#: file exists, creating it first: only the first attempt fails (tests/io/test_distributed.py).
TEST_FAIL_ONCE = "GPU_BLUR_TEST_FAIL_ONCE"


def sleep_after(index: int) -> None:
    """Sleep for an hour if :data:`TEST_SLEEP_AFTER` names sample ``index``."""
    value = os.environ.get(TEST_SLEEP_AFTER)
    if value is not None and str(index) == value.strip():
        time.sleep(3600)


def fault_planted(pass_: str) -> bool:
    """Whether :data:`TEST_FAULT` names ``pass_`` (cheap; checked per pass)."""
    fault = os.environ.get(TEST_FAULT)
    return bool(fault) and fault.partition("@")[0].strip() == pass_


def planted_fault(pass_: str, values: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """Apply :data:`TEST_FAULT` to a pass's output (in place); returns it.

    Args:
        pass_: the pass that made ``values``.
        values: its host output, ``h x w`` or ``h x w x 3``, writable.
        origin: global (row, column) of ``values[0, 0]``.
    """
    fault = os.environ.get(TEST_FAULT)
    if not fault:
        return values
    name, _, at = fault.partition("@")
    if name.strip() != pass_:
        return values
    y, x = (int(v) for v in at.split(",")) if at else (0, 0)
    ly, lx = y - origin[0], x - origin[1]
    if 0 <= ly < values.shape[0] and 0 <= lx < values.shape[1]:
        v = values[ly, lx]
        values[ly, lx] = np.where(v < 0.5, v + 0.25, v - 0.25)
    return values


def fail_once_setting() -> tuple[int, str] | None:
    """:data:`TEST_FAIL_ONCE` read on the driver: ``(sample index, marker file)`` or None."""
    value = os.environ.get(TEST_FAIL_ONCE)
    if not value:
        return None
    index, marker = value.split(":", 1)
    return int(index), marker


def fail_once(setting: tuple[int, str] | None, indices) -> None:
    """In a Ray worker: end the process if ``setting`` names one of ``indices``, the first time.

    Args:
        setting: what :func:`fail_once_setting` read on the driver (workers may not see its
            environment).
        indices: the sample indices this task makes.
    """
    if setting is None:
        return
    index, marker = setting
    if index in indices and not Path(marker).exists():
        Path(marker).write_text("failed once\n")
        os._exit(1)  # the worker dies, as on a lost node
