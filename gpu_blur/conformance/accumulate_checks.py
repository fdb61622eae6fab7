"""Checks of the accumulate pass: the blur modes on a photo, long sums, paths leaving the image.

Registered into :data:`gpu_blur.conformance.checks.CHECKS` on import, in the order
``gpu-blur validate`` runs them.
"""

from __future__ import annotations

import functools

import numpy as np

from gpu_blur.backends import to_host
from gpu_blur.conformance import (
    POSES_LEAVING_THE_IMAGE,
    StreamedFrames,
    coffee_crop,
    on_device,
    prepare,
)
from gpu_blur.conformance.checks import (
    CHECKS,
    REFERENCE,
    Check,
    Outcome,
    Target,
    check,
    exact,
    holds,
    within,
)
from gpu_blur.tiling import Region

__all__: list[str] = []


def _accumulate_mode(t: Target, mode: str) -> list[Outcome]:
    photo = coffee_crop()
    h, w = photo.shape[:2]
    p, _, params = prepare(t.precision, {"blur": {"mode": mode, "frames": 3}}, (h, w))
    frames = [photo, np.roll(photo, 3, axis=1), np.roll(photo, -2, axis=0)]
    frames = frames if mode == "average" else frames[:1]
    mask = np.linspace(0, 1, h * w * 3).reshape(h, w, 3) if mode == "none" else None
    region = Region.whole(h, w)
    linear, sat = t.backend.accumulate(p, params, frames, mask, region)
    ref_linear, ref_sat = REFERENCE.accumulate(p, params, frames, mask, region)
    return [within("accumulate", t, linear, ref_linear),
            within("accumulate", t, sat, ref_sat)]


for _mode in ("trajectory", "average", "kernel", "none"):
    CHECKS.append(Check(f"accumulate: blur mode {_mode}, photo",
                        functools.partial(_accumulate_mode, mode=_mode),
                        quick=_mode == "trajectory"))


@check("accumulate: mean of 1,000 streamed frames")
def _long_average(t: Target) -> list[Outcome]:
    frames = StreamedFrames(1000)
    h, w = frames.shape[:2]
    p, _, params = prepare(t.precision, {"blur": {"mode": "average", "frames": 1000}}, (h, w))
    linear, mask = t.backend.accumulate(p, params, frames, None, Region.whole(h, w))
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, StreamedFrames(1000), None,
                                                Region.whole(h, w))
    return [within("accumulate_long_sum", t, linear, ref_linear),
            exact("saturation count", to_host(mask), on_device(t.precision, ref_mask),
                  "count / n rounded once to the compute type"),
            holds(frames.max_alive <= 1, "frames read one at a time")]


@check("accumulate: camera path of 1,000 poses")
def _long_path(t: Target) -> list[Outcome]:
    photo = coffee_crop(slice(240, 272), slice(330, 362))
    settings = {"blur": {"mode": "trajectory", "steps": 1000, "extent": [6.0, 6.0]}}
    p, _, params = prepare(t.precision, settings, photo.shape[:2])
    region = Region.whole(*photo.shape[:2])
    linear, mask = t.backend.accumulate(p, params, [photo], None, region)
    ref_linear, ref_mask = REFERENCE.accumulate(p, params, [photo], None, region)
    return [within("accumulate_long_sum", t, linear, ref_linear),
            within("accumulate_long_sum", t, mask, ref_mask)]


@check("accumulate: camera path leaving the image, in tiles")
def _path_leaving(t: Target) -> list[Outcome]:
    photo = coffee_crop(slice(250, 274), slice(330, 362))
    h, w = photo.shape[:2]
    p, _, params = prepare(t.precision, {"blur": {"mode": "trajectory"}}, (h, w),
                           overrides={"homographies": POSES_LEAVING_THE_IMAGE})
    ref_linear, ref_mask = (to_host(a).reshape(h, w, 3) for a in REFERENCE.accumulate(
        p, params, [photo], None, Region.whole(h, w)))
    out = []
    for y0, x0, th, tw in [(0, 0, h, w), (10, 12, 14, 20)]:
        linear, mask = t.backend.accumulate(p, params, [photo], None, Region(y0, x0, th, tw, h, w))
        inside = (slice(y0, y0 + th), slice(x0, x0 + tw))
        out += [within("accumulate", t, to_host(linear).reshape(th, tw, 3),
                       ref_linear[inside]),
                within("accumulate", t, to_host(mask).reshape(th, tw, 3),
                       ref_mask[inside])]
    return out
