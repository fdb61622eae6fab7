"""Fixtures shared by the tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1] / "gpu_blur" / "data"


@pytest.fixture(scope="session")
def coffee_rgb() -> np.ndarray:
    """scikit-image's CC0 "coffee" photograph: 400 x 600 x 3 float64 sRGB in [0, 1], R, G, B.

    Read-only, so a test cannot change it for the others.
    """
    import cv2

    bgr = cv2.imread(str(DATA / "coffee.png"), cv2.IMREAD_COLOR)
    assert bgr is not None, f"cannot read {DATA / 'coffee.png'}"
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0
    rgb.setflags(write=False)
    return rgb


@pytest.fixture(scope="session")
def rocket_rgb() -> np.ndarray:
    """SpaceX's public-domain DSCOVR launch photo: 427 x 640 x 3 float64 sRGB, R, G, B.

    Cropped to 426 x 640 so the Bayer steps get even sizes. Read-only.
    """
    import cv2

    path = Path(__file__).resolve().parent / "data" / "rocket.jpg"
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, f"cannot read {path}"
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)[:426].astype(np.float64) / 255.0
    rgb.setflags(write=False)
    return rgb
