"""Draw README's pipeline picture: sharp photo, synthesized blur, and a noise close-up.

Run from the repository root: ``python bench/readme_figure.py`` (writes
``bench/results/readme_pipeline.png``).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

import gpu_blur
from gpu_blur.discovery import default_photo
from gpu_blur.reference.output import to_integers

OUT = Path(__file__).parent / "results" / "readme_pipeline.png"
CLOSE_UP = (slice(236, 300), slice(330, 394))  # the spoon's clipped highlights, 64 x 64 px
ZOOM = 400 // 64 + 1


def label(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    cv2.putText(out, text, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 4, cv2.LINE_AA)
    cv2.putText(out, text, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2,
                cv2.LINE_AA)
    return out


def main() -> None:
    result = gpu_blur.synthesize([default_photo()], seed=0, sample_index=2)
    sharp, blurred = to_integers(result.sharp, 8), to_integers(result.blurred, 8)
    close = np.kron(blurred[CLOSE_UP], np.ones((ZOOM, ZOOM, 1), np.uint8))[:400, :400]
    boxed = blurred.copy()
    r, c = CLOSE_UP
    cv2.rectangle(boxed, (c.start, r.start), (c.stop, r.stop), (255, 255, 0), 2)
    p = result.params
    panel = np.hstack([
        label(sharp, "sharp (built-in photo)"),
        label(boxed, f"synthesized: shake {p['extent_px']:.0f} px, alpha {p['alpha']:.2f}"),
        label(close, f"close-up x{ZOOM}: noise, {p['pattern']} demosaic"),
    ])
    OUT.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT), panel[:, :, ::-1])
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
