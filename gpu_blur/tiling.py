"""Regions of an image: tiles, their halos, and where one region sits inside another."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

__all__ = ["Region", "tiles"]


@dataclasses.dataclass(frozen=True)
class Region:
    """A rectangle of a full image, in global pixel coordinates.

    Attributes:
        y0, x0: global row and column of the region's first pixel.
        h, w: its size in pixels.
        full_h, full_w: the size of the full image it belongs to.
    """

    y0: int
    x0: int
    h: int
    w: int
    full_h: int
    full_w: int

    @classmethod
    def whole(cls, height: int, width: int) -> Region:
        """The full image as one region."""
        return cls(0, 0, height, width, height, width)

    @property
    def origin(self) -> tuple[int, int]:
        """(row, column) of the first pixel."""
        return self.y0, self.x0

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w)."""
        return self.h, self.w

    def expand(self, halo: int) -> Region:
        """The region grown by ``halo`` pixels on every side, clipped to the full image."""
        y0, x0 = max(self.y0 - halo, 0), max(self.x0 - halo, 0)
        y1 = min(self.y0 + self.h + halo, self.full_h)
        x1 = min(self.x0 + self.w + halo, self.full_w)
        return Region(y0, x0, y1 - y0, x1 - x0, self.full_h, self.full_w)

    def aligned(self, step: int) -> Region:
        """The smallest region holding this one with edges on multiples of ``step``.

        Edges stop at the full image's edges. Views for the Bayer steps use ``step = 2``, so
        they start and end on a 2 x 2 cell.
        """
        y0, x0 = self.y0 - self.y0 % step, self.x0 - self.x0 % step
        y1 = min(-(-(self.y0 + self.h) // step) * step, self.full_h)
        x1 = min(-(-(self.x0 + self.w) // step) * step, self.full_w)
        return Region(y0, x0, y1 - y0, x1 - x0, self.full_h, self.full_w)

    def within(self, outer: Region) -> tuple[slice, slice]:
        """Slices that cut this region out of an array covering ``outer``."""
        if not (outer.y0 <= self.y0 and outer.x0 <= self.x0
                and self.y0 + self.h <= outer.y0 + outer.h
                and self.x0 + self.w <= outer.x0 + outer.w):
            raise ValueError(f"{self} does not lie within {outer}")
        return (slice(self.y0 - outer.y0, self.y0 - outer.y0 + self.h),
                slice(self.x0 - outer.x0, self.x0 - outer.x0 + self.w))

    def of(self, full):
        """The region's view of an array covering the full image."""
        return full[self.y0:self.y0 + self.h, self.x0:self.x0 + self.w]


def tiles(height: int, width: int, tile: tuple[int, int] | None) -> Iterator[Region]:
    """Row-major tiles of at most ``tile = (th, tw)`` pixels covering the image.

    ``tile = None`` gives the image itself. Tiles may start at odd offsets: every stage works in
    global coordinates, so the Bayer phase and the random draws do not depend on them.
    """
    if tile is None:
        yield Region.whole(height, width)
        return
    th, tw = tile
    if th < 1 or tw < 1:
        raise ValueError(f"tile size must be positive, got {tile}")
    for y0 in range(0, height, th):
        for x0 in range(0, width, tw):
            yield Region(y0, x0, min(th, height - y0), min(tw, width - x0), height, width)
