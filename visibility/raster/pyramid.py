"""The depth pyramid (hierarchical z) over inverse-depth buffers, for occlusion culling.

Level 0 is a view's ``1 / depth`` buffer (0 where nothing is drawn) itself, not a copy; each
level above holds, per tile of 2 x 2 tiles below, their minimum: the inverse of the farthest
depth drawn in the tile. Something whose nearest depth is farther than a tile's farthest drawn
depth is hidden at every pixel centre of the tile (an empty pixel, 0, hides nothing). One
pyramid layout serves every view of a render (F views of the same size) and every core that
culls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange


@dataclass(frozen=True)
class PyramidLayout:
    """Where each level of an (H, W) pyramid lies in a flat per-view array.

    ``heights``, ``widths``, ``offsets``: (L,) int64 per level, level 0 being (H, W); level 0
    is the inverse-depth buffer itself, so the flat array starts with level 1 (``offsets[1]``
    is 0; ``offsets[0]`` is unused); ``size``: the flat length per view (levels 1 and up, a
    third of level 0's).
    """

    heights: np.ndarray
    widths: np.ndarray
    offsets: np.ndarray
    size: int

    @classmethod
    def of(cls, height: int, width: int) -> PyramidLayout:
        """The layout of an (height, width) buffer's pyramid, halving (rounding up) to 1 x 1."""
        hs, ws = [int(height)], [int(width)]
        while hs[-1] > 1 or ws[-1] > 1:
            hs.append((hs[-1] + 1) // 2)
            ws.append((ws[-1] + 1) // 2)
        sizes = np.array(hs, dtype=np.int64) * np.array(ws, dtype=np.int64)
        sizes[0] = 0
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        return cls(np.array(hs, dtype=np.int64), np.array(ws, dtype=np.int64), offsets,
                   int(sizes.sum()))

    def empty(self, n_views: int) -> np.ndarray:
        """(n_views, size) float64 storage of levels 1 and up, all 0 (nothing drawn)."""
        return np.zeros((n_views, self.size), dtype=np.float64)


@njit(cache=True, nogil=True, inline="always")
def _level_min(invd, hz, k, heights, widths, offsets, lv, i, j):  # pragma: no cover - numba
    """Level ``lv`` (>= 1) at row i, column j: the minimum of its 2 x 2 children (those
    inside the level below; level 0 read from ``invd``)."""
    hp, wp, op = heights[lv - 1], widths[lv - 1], offsets[lv - 1]
    i0 = 2 * i
    i1 = min(i0 + 1, hp - 1)
    j0 = 2 * j
    j1 = min(j0 + 1, wp - 1)
    if lv == 1:
        m = min(invd[k, i0, j0], invd[k, i0, j1])
        m = min(m, invd[k, i1, j0])
        return min(m, invd[k, i1, j1])
    m = min(hz[k, op + i0 * wp + j0], hz[k, op + i0 * wp + j1])
    m = min(m, hz[k, op + i1 * wp + j0])
    return min(m, hz[k, op + i1 * wp + j1])


@njit(cache=True, nogil=True, parallel=True)
def build_pyramid(invd, heights, widths, offsets, hz):  # pragma: no cover - numba
    """Fill ``hz`` (F, size), levels 1 and up, from ``invd`` (F, H, W), level 0."""
    n_views = invd.shape[0]
    for k in prange(n_views):
        for lv in range(1, heights.shape[0]):
            h, w, o = heights[lv], widths[lv], offsets[lv]
            for i in range(h):
                for j in range(w):
                    hz[k, o + i * w + j] = _level_min(invd, hz, k, heights, widths, offsets,
                                                      lv, i, j)


@njit(cache=True, nogil=True)
def rect_min(invd, hz, k, heights, widths, offsets, x0, x1, y0, y1):  # pragma: no cover - numba
    """Minimum inverse depth over pixels [x0, x1] x [y0, y1] (inclusive) of view k, or less:
    read at the finest level where the rectangle spans at most 8 x 8 tiles (a tile's minimum
    is over a superset of the rectangle's pixels, so the answer never exceeds the exact one);
    level 0 is ``invd`` (F, H, W), the levels above ``hz`` (F, size)."""
    lv = 0
    while (x1 >> lv) - (x0 >> lv) > 7 or (y1 >> lv) - (y0 >> lv) > 7:
        lv += 1
    if lv >= heights.shape[0]:
        lv = heights.shape[0] - 1
    m = np.inf
    if lv == 0:
        for i in range(y0, y1 + 1):
            for j in range(x0, x1 + 1):
                m = min(m, invd[k, i, j])
        return m
    w, o = widths[lv], offsets[lv]
    for i in range(y0 >> lv, (y1 >> lv) + 1):
        for j in range(x0 >> lv, (x1 >> lv) + 1):
            m = min(m, hz[k, o + i * w + j])
    return m


@njit(cache=True, nogil=True)
def update_pyramid(invd, heights, widths, offsets, hz, dirty):  # pragma: no cover - numba
    """``build_pyramid`` over the tiles above the pixels of ``dirty`` (F, 4) [x0, x1, y0, y1]
    per view (inclusive; x0 > x1: unchanged) only."""
    for k in range(invd.shape[0]):
        x0, x1, y0, y1 = dirty[k, 0], dirty[k, 1], dirty[k, 2], dirty[k, 3]
        if x0 > x1 or y0 > y1:
            continue
        for lv in range(1, heights.shape[0]):
            w, o = widths[lv], offsets[lv]
            x0, x1, y0, y1 = x0 >> 1, x1 >> 1, y0 >> 1, y1 >> 1
            for i in range(y0, y1 + 1):
                for j in range(x0, x1 + 1):
                    hz[k, o + i * w + j] = _level_min(invd, hz, k, heights, widths, offsets,
                                                      lv, i, j)
