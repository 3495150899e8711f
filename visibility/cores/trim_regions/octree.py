"""The scene octree of the trim region core (paper Sec. 5.1): built once per scene, cached.

Nodes split while they hold more than ``max_prims`` triangles (by bounding-box overlap, so a
triangle that crosses a node border is sorted into every node it touches) and the depth limit
allows; then neighbouring leaves are balanced to at most two levels apart. Leaves are addressed
on a fine integer grid of ``2**max_depth`` cells per axis (``leaf_of_cell``), which gives the
face neighbours the layer peeling (``frustum.layers``) walks.

Coordinates are metres, relative to ``origin`` (the scene is shifted there in float64 so the
octree stays exact far from the world origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

#: Largest depth of the octree (the fine grid has 2**MAX_DEPTH cells per axis).
MAX_DEPTH = 6


@dataclass
class Octree:
    """Leaves of the scene octree.

    Attributes
    ----------
    origin : (3,) float64, world position of the root's min corner, metres.
    cell : float, side of one fine-grid cell, metres (the root is ``cell * 2**depth`` wide).
    depth : int, the fine grid has ``2**depth`` cells per axis.
    leaf_cells : (L, 2, 3) int64, each leaf's [min, max) range on the fine grid.
    leaf_level : (L,) int64, octree level of each leaf (root 0).
    tri_start : (L + 1,) int64 and ``tri_items`` (k,) int64: CSR of the triangle ids per leaf.
    leaf_of_cell : (G, G, G) int32, the leaf holding each fine cell.
    nbr_start : (L + 1,) int64, ``nbr_items`` (n,) int64, ``nbr_face`` (n,) int8: CSR of face
        neighbours, the face as ``2 * axis + (0 for min, 1 for max side)``.
    """

    origin: np.ndarray
    cell: float
    depth: int
    leaf_cells: np.ndarray
    leaf_level: np.ndarray
    tri_start: np.ndarray
    tri_items: np.ndarray
    leaf_of_cell: np.ndarray
    nbr_start: np.ndarray
    nbr_items: np.ndarray
    nbr_face: np.ndarray

    def __len__(self) -> int:
        return int(len(self.leaf_level))

    def leaf_boxes(self) -> np.ndarray:
        """(L, 2, 3) float64 leaf boxes, metres relative to ``origin``."""
        return self.leaf_cells.astype(np.float64) * self.cell


def _overlapping(lo: np.ndarray, hi: np.ndarray, box_lo: np.ndarray,
                 box_hi: np.ndarray) -> np.ndarray:
    return np.all((lo <= box_hi) & (hi >= box_lo), axis=1)


def build_octree(tri_lo: np.ndarray, tri_hi: np.ndarray, ids: np.ndarray, max_prims: int = 256,
                 max_depth: int = MAX_DEPTH) -> Octree:
    """Octree over triangle bounding boxes.

    Parameters
    ----------
    tri_lo, tri_hi : (m, 3) float64 bounding boxes of the triangles, metres (world).
    ids : (m,) int64 triangle ids the leaves list.
    max_prims : a node holding more triangles than this splits (until ``max_depth``).
    max_depth : deepest level.

    Returns
    -------
    The ``Octree``; an empty scene gives one empty leaf around the origin.
    """
    if len(ids):
        lo = tri_lo.min(axis=0)
        hi = tri_hi.max(axis=0)
    else:
        lo, hi = np.zeros(3), np.ones(3)
    side = float(np.max(hi - lo))
    side = side * (1 + 1e-9) + 1e-9 * max(1.0, float(np.max(np.abs(lo))))
    g = 1 << max_depth
    cell = side / g
    rlo = tri_lo - lo
    rhi = tri_hi - lo
    # Work list of nodes: (level, integer min corner at the node's own level, triangle rows).
    leaves: list[tuple[int, np.ndarray, np.ndarray]] = []
    stack = [(0, np.zeros(3, dtype=np.int64), np.arange(len(ids)))]
    while stack:
        level, corner, rows = stack.pop()
        if len(rows) <= max_prims or level >= max_depth:
            leaves.append((level, corner, rows))
            continue
        stack.extend(_split(level, corner, rows, rlo, rhi, cell, max_depth))
    leaves = _balance(leaves, rlo, rhi, cell, max_depth)
    n = len(leaves)
    leaf_cells = np.empty((n, 2, 3), dtype=np.int64)
    level_arr = np.empty(n, dtype=np.int64)
    counts = np.empty(n, dtype=np.int64)
    for k, (level, corner, rows) in enumerate(leaves):
        span = 1 << (max_depth - level)
        leaf_cells[k, 0] = corner * span
        leaf_cells[k, 1] = (corner + 1) * span
        level_arr[k] = level
        counts[k] = len(rows)
    tri_start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=tri_start[1:])
    tri_items = (np.concatenate([ids[r] for _, _, r in leaves]).astype(np.int64)
                 if n else np.zeros(0, dtype=np.int64))
    loc = _leaf_grid(leaf_cells, g)
    nbr_start, nbr_items, nbr_face = _neighbours(leaf_cells, loc)
    return Octree(lo.astype(np.float64), cell, max_depth, leaf_cells, level_arr, tri_start,
                  tri_items, loc, nbr_start, nbr_items, nbr_face)


def _split(level: int, corner: np.ndarray, rows: np.ndarray, rlo: np.ndarray, rhi: np.ndarray,
           cell: float, max_depth: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The eight children of a node with the triangle rows overlapping each."""
    child_span = (1 << (max_depth - level - 1)) * cell
    out = []
    for c in range(8):
        off = np.array([(c >> a) & 1 for a in range(3)], dtype=np.int64)
        cc = corner * 2 + off
        blo = cc * child_span
        keep = rows[_overlapping(rlo[rows], rhi[rows], blo, blo + child_span)]
        out.append((level + 1, cc, keep))
    return out


def _balance(leaves: list, rlo: np.ndarray, rhi: np.ndarray, cell: float,
             max_depth: int) -> list:
    """Split leaves until face neighbours differ by at most two levels (paper Sec. 5.1: an
    excessive level difference makes the neighbour walk of the layer peeling inefficient)."""
    g = 1 << max_depth
    while True:
        cells = np.array([[c * (1 << (max_depth - lv)), (c + 1) * (1 << (max_depth - lv))]
                          for lv, c, _ in leaves], dtype=np.int64).reshape(-1, 2, 3)
        levels = np.array([lv for lv, _, _ in leaves], dtype=np.int64)
        loc = _leaf_grid(cells, g)
        start, items, _ = _neighbours(cells, loc)
        finest = np.zeros(len(leaves), dtype=np.int64)
        for k in range(len(leaves)):
            nb = items[start[k]:start[k + 1]]
            finest[k] = levels[nb].max() if len(nb) else 0
        bad = np.flatnonzero(finest > levels + 2)
        if not len(bad):
            return leaves
        bad_set = set(bad.tolist())
        out = []
        for k, (lv, c, rows) in enumerate(leaves):
            if k in bad_set and lv < max_depth:
                out.extend(_split(lv, c, rows, rlo, rhi, cell, max_depth))
            else:
                out.append((lv, c, rows))
        if len(out) == len(leaves):
            return leaves
        leaves = out


@njit(cache=True, nogil=True)
def _leaf_grid(leaf_cells, g):  # pragma: no cover - numba
    loc = np.full((g, g, g), -1, dtype=np.int32)
    for k in range(leaf_cells.shape[0]):
        a = leaf_cells[k]
        loc[a[0, 0]:a[1, 0], a[0, 1]:a[1, 1], a[0, 2]:a[1, 2]] = k
    return loc


@njit(cache=True, nogil=True)
def _face_nbrs(leaf_cells, loc, k, face, out):  # pragma: no cover - numba
    """Distinct leaves across one face of leaf k, written to ``out``; returns their count."""
    g = loc.shape[0]
    axis = face // 2
    a1 = (axis + 1) % 3
    a2 = (axis + 2) % 3
    if face % 2 == 0:
        plane = leaf_cells[k, 0, axis] - 1
    else:
        plane = leaf_cells[k, 1, axis]
    if plane < 0 or plane >= g:
        return 0
    n = 0
    idx = np.empty(3, dtype=np.int64)
    idx[axis] = plane
    for i in range(leaf_cells[k, 0, a1], leaf_cells[k, 1, a1]):
        for j in range(leaf_cells[k, 0, a2], leaf_cells[k, 1, a2]):
            idx[a1] = i
            idx[a2] = j
            leaf = loc[idx[0], idx[1], idx[2]]
            if leaf < 0:
                continue
            seen = False
            for q in range(n):
                if out[q] == leaf:
                    seen = True
                    break
            if not seen:
                out[n] = leaf
                n += 1
    return n


@njit(cache=True, nogil=True, parallel=True)
def _neighbours(leaf_cells, loc):  # pragma: no cover - numba
    n = leaf_cells.shape[0]
    counts = np.zeros(n, dtype=np.int64)
    g = loc.shape[0]
    for k in prange(n):
        buf = np.empty(g * g, dtype=np.int64)
        c = 0
        for face in range(6):
            # The prange index is unsigned: cast, or _face_nbrs compiles twice.
            c += _face_nbrs(leaf_cells, loc, np.int64(k), face, buf)
        counts[k] = c
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(n):
        start[k + 1] = start[k] + counts[k]
    items = np.empty(start[n], dtype=np.int64)
    faces = np.empty(start[n], dtype=np.int8)
    for k in prange(n):
        buf = np.empty(g * g, dtype=np.int64)
        w = start[k]
        for face in range(6):
            m = _face_nbrs(leaf_cells, loc, np.int64(k), face, buf)
            for q in range(m):
                items[w] = buf[q]
                faces[w] = face
                w += 1
    return start, items, faces
