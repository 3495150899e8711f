"""Viewcells: axis-aligned boxes of eye positions tiling where people walk.

The grid is regular in X and Z (cell size ``s``, origin at the walk area's min corner); each grid
column may hold several cells, one per floor level (a multi-storey level has cells on each).
A cell's Y range is the eye-height range above its floor, lowered under a low ceiling.
Cell ids are indices 0..n-1 into the grid's arrays, stable for a given scene and cell size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visibility.scene import Scene, WalkArea

#: Default horizontal cell size in metres (a walker at 1.4 m/s crosses one in about 3 s).
DEFAULT_CELL_SIZE = 4.0
#: Floors closer than this (metres) in one column are the same level.
LEVEL_MERGE = 0.5
#: Largest floor step (metres) between neighbouring cells that still connects them.
MAX_STEP = 1.0
#: Most viewcells a grid builds (counted before levels merge). A cell costs ~170 bytes here
#: and more in every server table keyed by cell, so 2^20 cells (~200 MB) is the ceiling; the
#: largest real scene (Lyon at 4 m) has 278 000. A walk area of kilometres at a small cell size
#: is refused with a ValueError naming this limit instead of filling memory.
MAX_VIEWCELLS = 1 << 20
#: Smallest extent (metres) a viewcell box keeps on an axis: a thinner axis collapses to zero
#: extent (max = min), the degenerate region it is. Eyes a micrometre apart see the same
#: thing at any resolution a core renders or samples at, while cores that divide by an extent
#: or step through it (samples per metre, a box's own frame) meet denormals, overflow or
#: billions of steps in a 1e-300 m box; every core already answers zero-extent boxes (points,
#: segments, flat cells), so the collapse trades nothing for that.
MIN_EXTENT = 1e-6
#: ... and at least this many float64 steps (ulps) of the axis's coordinates. An absolute floor
#: alone stops working far from the origin, where a few ulps exceed a micrometre (past about
#: 1e8 m) and an extent could be rounding noise; this relative floor collapses such an extent
#: at any magnitude. Below ~1e8 m (every real scene) MIN_EXTENT is the larger of the two.
MIN_EXTENT_ULPS = 64


def collapse_thin_axes(box: np.ndarray) -> np.ndarray:
    """``box`` (2, 3) [min, max], metres, or a stack of them (c, 2, 3), with every axis
    thinner than ``min_extent`` collapsed to its min (max = min): a copy, float64.

    Parameters
    ----------
    box : (2, 3) or (c, 2, 3) float64, finite, max >= min.

    Returns
    -------
    The same shape, [min, max] metres.
    """
    out = np.array(box, dtype=np.float64)
    if out.ndim != 3:
        out = out.reshape(2, 3)
    thin = (out[..., 1, :] - out[..., 0, :]) < min_extent(out)
    out[..., 1, :] = np.where(thin, out[..., 0, :], out[..., 1, :])
    return out


def min_extent(box: np.ndarray) -> np.ndarray:
    """(3,) metres (or (c, 3) for a stack of boxes): the smallest extent each axis of ``box``
    (2, 3) keeps, the larger of ``MIN_EXTENT`` and ``MIN_EXTENT_ULPS`` float64 steps at the
    axis's largest magnitude."""
    magnitude = np.abs(np.asarray(box, dtype=np.float64)).max(axis=-2)
    return np.maximum(MIN_EXTENT, MIN_EXTENT_ULPS * np.spacing(magnitude))


@dataclass(frozen=True)
class Viewcell:
    """An axis-aligned box of eye positions. ``box`` is (2, 3) [min, max] metres; ``id`` is the
    cell's index in its grid, or -1 for an ad-hoc box. An axis thinner than ``min_extent``
    (``MIN_EXTENT`` metres, or a few ulps far from the origin) is collapsed to zero extent, so
    a box of 1e-300 m is the point it is (``collapse_thin_axes``)."""

    box: np.ndarray
    id: int = -1

    def __post_init__(self) -> None:
        b = np.asarray(self.box, dtype=np.float64).reshape(2, 3)
        if not np.all(np.isfinite(b)):
            raise ValueError("viewcell box must be finite")
        if np.any(b[1] < b[0]):
            raise ValueError(f"viewcell box max < min: {b.tolist()}")
        object.__setattr__(self, "box", collapse_thin_axes(b))

    @property
    def center(self) -> np.ndarray:
        return self.box.mean(axis=0)

    @property
    def size(self) -> np.ndarray:
        return self.box[1] - self.box[0]


def spread_evenly(ids: np.ndarray, k: int) -> list[int]:
    """``k`` of ``ids`` (cell ids, in their order) spread evenly over it, its two ends left out
    (the middle one for ``k`` = 1); sorted and deterministic, fewer when ``ids`` is shorter."""
    ids = np.asarray(ids)
    m = len(ids)
    if m == 0 or k <= 0:
        return []
    pos = np.linspace(0, m - 1, min(k, m) + 2)[1:-1].round().astype(int)
    return sorted({int(ids[i]) for i in pos})


class ViewcellGrid:
    """Viewcells over a scene's walk area.

    Attributes
    ----------
    cell_size : float, metres (X and Z).
    origin : (2,) float64, the XZ corner of grid column (0, 0).
    ij : (c, 2) int64 grid column of each cell.
    floor : (c,) float64 floor height of each cell, metres.
    boxes : (c, 2, 3) float64 [min, max] of each cell, metres.
    """

    def __init__(
        self,
        walk: WalkArea,
        cell_size: float = DEFAULT_CELL_SIZE,
    ) -> None:
        if not (np.isfinite(cell_size) and cell_size > 0):
            raise ValueError(f"cell_size must be a positive number of metres, got {cell_size}")
        self.cell_size = float(cell_size)
        self.walk = walk
        rects = walk.rects
        s = self.cell_size
        if len(rects) == 0:
            self.origin = np.zeros(2)
            self._nz = 1
            self._set_cells(np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.zeros(0))
            return
        lo = rects[:, :2].min(axis=0)
        hi = rects[:, 2:4].max(axis=0)
        self.origin = lo.copy()
        with np.errstate(over="ignore"):
            span = (hi - lo) / s
        if not np.all(np.isfinite(span)):
            raise ValueError(f"walk area {lo.tolist()} to {hi.tolist()} m is too wide for float64")
        nx = max(1, int(np.ceil(span[0] - 1e-9)))
        nz = max(1, int(np.ceil(span[1] - 1e-9)))
        self._nz = nz
        # Columns whose centre lies inside each rectangle, expanded without a Python loop.
        # Counted in floats first, so a huge walk area is refused before anything is allocated.
        i0 = np.maximum(np.ceil((rects[:, 0] - lo[0]) / s - 0.5 - 1e-9), 0)
        i1 = np.minimum(np.floor((rects[:, 2] - lo[0]) / s - 0.5 + 1e-9), nx - 1)
        k0 = np.maximum(np.ceil((rects[:, 1] - lo[1]) / s - 0.5 - 1e-9), 0)
        k1 = np.minimum(np.floor((rects[:, 3] - lo[1]) / s - 0.5 + 1e-9), nz - 1)
        # A rectangle narrower than a cell may hold no column centre along an axis (a 10 m
        # street under 50 m cells): along that axis it takes every column it overlaps, so
        # every walkable point lies in some cell.
        for a0, a1, c0, c1, n in ((i0, i1, 0, 2, nx), (k0, k1, 1, 3, nz)):
            thin = a0 > a1
            a0[thin] = np.clip(np.floor((rects[thin, c0] - lo[c0]) / s), 0, n - 1)
            a1[thin] = np.clip(np.ceil((rects[thin, c1] - lo[c0]) / s) - 1, a0[thin], n - 1)
        total = float(np.sum(np.maximum(i1 - i0 + 1, 0) * np.maximum(k1 - k0 + 1, 0)))
        if total > MAX_VIEWCELLS:
            raise ValueError(
                f"the walk area ({hi[0] - lo[0]:.0f} x {hi[1] - lo[1]:.0f} m) holds {total:.3g} "
                f"cells of {s:g} m, more than MAX_VIEWCELLS = {MAX_VIEWCELLS}; use a larger "
                f"cell size")
        i0, i1, k0, k1 = (a.astype(np.int64) for a in (i0, i1, k0, k1))
        ni = np.maximum(i1 - i0 + 1, 0)
        nk = np.maximum(k1 - k0 + 1, 0)
        per = ni * nk
        r = np.repeat(np.arange(len(rects)), per)
        o = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
        ii = i0[r] + o // np.maximum(nk[r], 1)
        kk = k0[r] + o % np.maximum(nk[r], 1)
        floor, ceil = rects[r, 4], rects[r, 5]
        order = np.lexsort((floor, kk, ii))
        ii, kk, floor, ceil = ii[order], kk[order], floor[order], ceil[order]
        # One cell per (column, level): floors closer than LEVEL_MERGE are one level, whose
        # lowest ceiling bounds the eye.
        new = np.ones(len(ii), dtype=bool)
        new[1:] = (ii[1:] != ii[:-1]) | (kk[1:] != kk[:-1]) | (np.diff(floor) >= LEVEL_MERGE)
        starts = np.nonzero(new)[0]
        ij = np.stack([ii[starts], kk[starts]], axis=1)
        ceilings = np.minimum.reduceat(ceil, starts) if len(starts) else np.zeros(0)
        self._set_cells(ij, floor[starts], ceilings)

    def _set_cells(self, ij: np.ndarray, floor: np.ndarray, ceiling: np.ndarray) -> None:
        s, lo, walk = self.cell_size, self.origin, self.walk
        self.ij = ij.astype(np.int64).reshape(-1, 2)
        self.floor = floor.astype(np.float64)
        self.ceiling = ceiling.astype(np.float64)
        n = len(self.ij)
        boxes = np.empty((n, 2, 3))
        boxes[:, 0, 0] = lo[0] + self.ij[:, 0] * s
        boxes[:, 1, 0] = boxes[:, 0, 0] + s
        boxes[:, 0, 2] = lo[1] + self.ij[:, 1] * s
        boxes[:, 1, 2] = boxes[:, 0, 2] + s
        boxes[:, 0, 1] = self.floor + walk.eye_range[0]
        # Under a low ceiling the eye range shrinks and, if need be, moves down under it.
        top = np.minimum(self.floor + walk.eye_range[1], self.ceiling - 0.1)
        boxes[:, 1, 1] = top
        boxes[:, 0, 1] = np.minimum(boxes[:, 0, 1], top)
        self.boxes = boxes
        # Cells are sorted by column key (i * nz + k), so a column's levels are contiguous.
        self._keys = self.ij[:, 0] * self._nz + self.ij[:, 1]

    def _column(self, i: int, k: int) -> range:
        if k < 0 or k >= self._nz or i < 0:
            return range(0)
        key = i * self._nz + k
        lo = int(np.searchsorted(self._keys, key, side="left"))
        hi = int(np.searchsorted(self._keys, key, side="right"))
        return range(lo, hi)

    # ----------------------------------------------------------------------------- access
    def __len__(self) -> int:
        return int(len(self.ij))

    def cell(self, cell_id: int) -> Viewcell:
        """The Viewcell with this id; IndexError when out of range."""
        cid = int(cell_id)
        if not 0 <= cid < len(self):
            raise IndexError(f"cell {cell_id} out of range [0, {len(self)})")
        return Viewcell(self.boxes[cid], cid)

    def centers(self) -> np.ndarray:
        """(c, 3) centre of every cell, metres: ``cell(i).center`` for all i at once."""
        return collapse_thin_axes(self.boxes).mean(axis=1)

    def walk_point(self, cell_id: int) -> np.ndarray:
        """(3,) a point of cell ``cell_id`` where one may walk, metres: the box centre when the
        walk area holds it, else (a cell over a street narrower than a cell, whose centre may
        lie in a wall) the nearest point of a walk rectangle under the cell, at the centre's
        height."""
        box = self.boxes[int(cell_id)]
        c = box.mean(axis=0)
        r = self.walk.rects
        if not len(r):
            return c
        if np.any((c[0] >= r[:, 0]) & (c[0] <= r[:, 2]) & (c[2] >= r[:, 1]) & (c[2] <= r[:, 3])):
            return c
        under = r[(r[:, 0] <= box[1, 0]) & (r[:, 2] >= box[0, 0]) & (r[:, 1] <= box[1, 2])
                  & (r[:, 3] >= box[0, 2])]
        if not len(under):
            return c
        # Nearest point of each rectangle's part inside the box.
        x = np.clip(c[0], np.maximum(under[:, 0], box[0, 0]), np.minimum(under[:, 2], box[1, 0]))
        z = np.clip(c[2], np.maximum(under[:, 1], box[0, 2]), np.minimum(under[:, 3], box[1, 2]))
        k = int(np.argmin((x - c[0]) ** 2 + (z - c[2]) ** 2))
        return np.array([x[k], c[1], z[k]])

    def cell_of(self, point: np.ndarray) -> int | None:
        """Id of the cell containing the eye position ``point`` (metres), or None.

        X and Z pick the column; among its levels the one whose floor is the highest at or
        below the eye (with 0.5 m slack) wins, so a walker whose head bobs stays in their cell.
        """
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(p)):
            return None
        i = int(np.floor((p[0] - self.origin[0]) / self.cell_size))
        k = int(np.floor((p[2] - self.origin[1]) / self.cell_size))
        ids = self._column(i, k)
        best, best_floor = None, -np.inf
        for cid in ids:
            f = self.floor[cid]
            if f <= p[1] + 0.5 and f > best_floor and p[1] <= self.boxes[cid, 1, 1] + 3.0:
                best, best_floor = cid, f
        return best

    def neighbours(self, cell_id: int) -> list[int]:
        """Ids of the cells in the 8-neighbourhood of ``cell_id`` reachable by a step of at most
        MAX_STEP metres, sorted."""
        cid = int(cell_id)
        self.cell(cid)
        i, k = self.ij[cid]
        out = []
        for di in (-1, 0, 1):
            for dk in (-1, 0, 1):
                if di == 0 and dk == 0:
                    continue
                for n in self._column(int(i + di), int(k + dk)):
                    if abs(self.floor[n] - self.floor[cid]) <= MAX_STEP:
                        out.append(n)
        return sorted(out)

    def bounds(self) -> np.ndarray:
        """(2, 3) box around every cell."""
        if len(self) == 0:
            return np.zeros((2, 3))
        return np.stack([self.boxes[:, 0].min(axis=0), self.boxes[:, 1].max(axis=0)])

    def to_dict(self, include_cells: bool = False) -> dict:
        """JSON-friendly description; with ``include_cells`` every cell's id, grid column, box,
        floor height and a point where one may walk (``walk_point``)."""
        d = {
            "cell_size": self.cell_size,
            "origin_xz": self.origin.tolist(),
            "cells": len(self),
            "levels": int(len(np.unique(np.round(self.floor, 1)))) if len(self) else 0,
            "eye_range": list(self.walk.eye_range),
            "bounds": self.bounds().tolist(),
        }
        if include_cells:
            d["cell_list"] = [
                {"id": i, "ij": self.ij[i].tolist(), "box": self.boxes[i].tolist(),
                 "floor": float(self.floor[i]), "walk": self.walk_point(i).tolist()}
                for i in range(len(self))
            ]
        return d

    # ----------------------------------------------------------------------------- builders
    @classmethod
    def for_scene(cls, scene: Scene, cell_size: float | None = None) -> ViewcellGrid:
        """The grid for a scene: its own walk area (generators, sidecars) or one detected from
        the geometry (see ``visibility.walkable``)."""
        from visibility.walkable import detect_walk_area

        if cell_size is None:
            cell_size = scene.meta.get("cell_size") or DEFAULT_CELL_SIZE
        size = float(cell_size)
        if scene.walk is not None:
            return cls(scene.walk, size)
        eye = scene.meta.get("eye_height") or 1.7
        eye_range = tuple(scene.meta.get("eye_range") or (1.5, 1.9))
        return cls(detect_walk_area(scene, size, eye, eye_range), size)
