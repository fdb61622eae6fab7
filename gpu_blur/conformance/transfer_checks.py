"""Checks of the transfer curves: the sRGB EOTF and OETF, their round trips, the A7R3 curves.

Registered into :data:`gpu_blur.conformance.checks.CHECKS` on import, in the order
``gpu-blur validate`` runs them.
"""

from __future__ import annotations

import numpy as np

from gpu_blur.conformance import (
    A7R3_DIP_POINTS,
    A7R3_POLYNOMIAL_POINTS,
    decode_on,
    finish_on,
    on_device,
    transfer_points,
)
from gpu_blur.conformance.checks import REFERENCE, Outcome, Target, check, holds, within
from gpu_blur.reference import transfer

__all__: list[str] = []


@check("accumulate: sRGB decode at 0, 1, knees, denormals", quick=True)
def _srgb_decode(t: Target) -> list[Outcome]:
    x = on_device(t.precision, transfer_points())
    got = decode_on(t.backend, x)
    return [within("srgb_to_linear", t, got, transfer.srgb_to_linear(x)),
            holds(np.all(np.diff(got) >= 0), "monotone"),
            holds(np.all(got[x == 1] == 1) and np.all(got[x == 0] == 0),
                  "0 and 1 stay exactly 0 and 1")]


@check("finish: sRGB encode at 0, 1, knees, denormals", quick=True)
def _srgb_encode(t: Target) -> list[Outcome]:
    x = on_device(t.precision, transfer_points())
    got = finish_on(t.backend, x)
    return [within("linear_to_srgb", t, got, np.clip(transfer.linear_to_srgb(x), 0, 1))]


@check("accumulate + finish: sRGB round trips")
def _srgb_round_trips(t: Target) -> list[Outcome]:
    x = on_device(t.precision, transfer_points())
    return [within("srgb_round_trip", t, decode_on(t.backend, finish_on(t.backend, x)), x),
            within("srgb_decode_encode", t, finish_on(t.backend, decode_on(t.backend, x)),
                   x)]


@check("finish: A7R3 polynomial clips outside [0, 1]")
def _a7r3_polynomial(t: Target) -> list[Outcome]:
    x = on_device(t.precision, A7R3_POLYNOMIAL_POINTS)
    got = finish_on(t.backend, x, crf="a7r3")
    return [within("finish_crf_polynomial", t, got, finish_on(REFERENCE, x, crf="a7r3")),
            holds(np.all(got[x <= 1e-6] == 0) and np.all(got[x >= 1] == 1),
                  "clips to exactly 0 and 1")]


@check("finish: A7R3 table near 0.86, where the polynomial dips")
def _a7r3_table(t: Target) -> list[Outcome]:
    x = on_device(t.precision, A7R3_DIP_POINTS)
    got = finish_on(t.backend, x, crf="a7r3-lut")
    return [within("finish", t, got, finish_on(REFERENCE, x, crf="a7r3-lut")),
            holds(np.all(np.diff(got) >= 0), "monotone")]
