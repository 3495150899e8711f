"""A uniform grid over triangles for exact (float64) first hits of rays.

The float64 judge of the ray references (``ray_reference.ExactCaster``) tests every triangle
per ray: 3 ms a ray on a 1M-triangle scene, too slow to confirm tens of thousands of finds.
This grid gives the same answer faster. Each triangle is entered in every cell its box, padded
by ``PAD`` of the scene's extent, meets (more than ``BIG_CELLS`` cells: a list tested by every
ray instead); a ray walks the cells it crosses in order (Amanatides and Woo's 3D DDA, in
float64) and tests their triangles with the same Moller-Trumbore as the brute force
(``ray_triangle``, here), stopping once its nearest hit lies within the cells walked.
A hit point lies in its triangle's box, so the padding covers where rounding puts the walk a
cell beside the true line. Ties in distance go to the lower row, as the brute force's order
gives them, so both answer alike (``tests/visibility/test_exact_grid.py`` compares them).

Conventions: any frame (the references cast in one centred on the cell), metres.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

#: Cells per triangle the grid aims at.
CELLS_PER_TRIANGLE = 2.0
#: Most cells along one axis, and in all.
MAX_DIM = 1024
MAX_CELLS = 1 << 23
#: A triangle whose box meets more cells than this is tested by every ray instead.
BIG_CELLS = 64
#: Padding of each triangle's box, as a share of the grid's largest extent: far above the
#: rounding of a walk in float64, far below any cell.
PAD = 1e-9


@njit(cache=True, nogil=True, inline="always")
def ray_triangle(tri, i, ox, oy, oz, dx, dy, dz):  # pragma: no cover - numba
    """Distance along the ray to triangle i of ``tri`` (k, 3, 3), or inf: Moller-Trumbore in
    float64, closed triangle, any facing."""
    ax, ay, az = tri[i, 0, 0], tri[i, 0, 1], tri[i, 0, 2]
    e1x, e1y, e1z = tri[i, 1, 0] - ax, tri[i, 1, 1] - ay, tri[i, 1, 2] - az
    e2x, e2y, e2z = tri[i, 2, 0] - ax, tri[i, 2, 1] - ay, tri[i, 2, 2] - az
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return np.inf
    inv = 1.0 / det
    sx, sy, sz = ox - ax, oy - ay, oz - az
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return np.inf
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return np.inf
    return (e2x * qx + e2y * qy + e2z * qz) * inv


class TriangleGrid(NamedTuple):
    """The grid: ``lo`` (3,) its corner, ``cell`` (3,) cell sizes, ``dims`` (3,) cells per
    axis, ``start`` (n_cells + 1,) offsets into ``items`` (triangle rows per cell, x fastest),
    ``big`` (b,) rows tested by every ray, ``pad`` the boxes' padding."""

    lo: np.ndarray
    cell: np.ndarray
    dims: np.ndarray
    start: np.ndarray
    items: np.ndarray
    big: np.ndarray
    pad: float


def build_grid(lo: np.ndarray, hi: np.ndarray) -> TriangleGrid:
    """The grid over triangles with boxes ``lo``, ``hi`` (k, 3)."""
    k = len(lo)
    glo = lo.min(axis=0) if k else np.zeros(3)
    ghi = hi.max(axis=0) if k else np.ones(3)
    ext = ghi - glo
    scale = max(float(ext.max()), 1e-12)
    pad = PAD * scale
    # A flat scene gets one cell across its thin axis.
    ext = np.maximum(ext, scale * 1e-3)
    s = (max(k, 1) * CELLS_PER_TRIANGLE / float(np.prod(ext))) ** (1.0 / 3.0)
    dims = np.clip(np.ceil(ext * s), 1, MAX_DIM).astype(np.int64)
    while int(np.prod(dims)) > MAX_CELLS:
        dims = np.maximum(1, dims // 2)
    glo = glo - pad
    cell = (ext + 2.0 * pad) / dims
    count = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
    is_big = np.zeros(k, dtype=np.bool_)
    _bin(lo, hi, glo, cell, dims, pad, count, is_big, np.empty(0, np.int64), False)
    start = np.zeros_like(count)
    np.cumsum(count[:-1], out=start[1:])
    items = np.empty(int(start[-1]), dtype=np.int64)
    fill = start.copy()
    _bin(lo, hi, glo, cell, dims, pad, fill, is_big, items, True)
    return TriangleGrid(glo, cell, dims, start, items, np.flatnonzero(is_big).astype(np.int64),
                        pad)


@njit(cache=True, nogil=True)
def _cells_of(lo, hi, i, glo, cell, dims, pad, out):  # pragma: no cover - numba
    """Cell index range (out[0:3] first, out[3:6] last) of triangle i's padded box."""
    for a in range(3):
        c0 = int(np.floor((lo[i, a] - pad - glo[a]) / cell[a]))
        c1 = int(np.floor((hi[i, a] + pad - glo[a]) / cell[a]))
        out[a] = min(max(c0, 0), dims[a] - 1)
        out[3 + a] = min(max(c1, 0), dims[a] - 1)


@njit(cache=True, nogil=True)
def _bin(lo, hi, glo, cell, dims, pad, slot, is_big, items, write):  # pragma: no cover
    """Count (``write`` False: into ``slot``, marking ``is_big``) or enter (``write`` True:
    at ``slot``'s running offsets) each triangle in its cells."""
    rng = np.empty(6, dtype=np.int64)
    for i in range(lo.shape[0]):
        _cells_of(lo, hi, i, glo, cell, dims, pad, rng)
        n = (rng[3] - rng[0] + 1) * (rng[4] - rng[1] + 1) * (rng[5] - rng[2] + 1)
        if n > BIG_CELLS:
            is_big[i] = True
            continue
        for z in range(rng[2], rng[5] + 1):
            for y in range(rng[1], rng[4] + 1):
                for x in range(rng[0], rng[3] + 1):
                    c = (z * dims[1] + y) * dims[0] + x
                    if write:
                        items[slot[c]] = i
                    slot[c] += 1


@njit(cache=True, nogil=True, inline="always")
def _take(tri, i, ox, oy, oz, dx, dy, dz, t0, best, bid):  # pragma: no cover - numba
    """(best, bid) after testing triangle i: nearer at or beyond t0, ties to the lower row."""
    t = ray_triangle(tri, i, ox, oy, oz, dx, dy, dz)
    if t >= t0 and (t < best or (t == best and i < bid)):
        return t, i
    return best, bid


@njit(cache=True, nogil=True, parallel=True)
def grid_first_hits(tri, grid, orig, dirs, tmin, out_id, out_t):  # pragma: no cover - numba
    """``ray_reference.exact_first_hits``'s answer through ``grid`` (``TriangleGrid``)."""
    glo, cell, dims, start, items, big, pad = grid
    for r in prange(orig.shape[0]):
        ox, oy, oz = orig[r, 0], orig[r, 1], orig[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        t0 = tmin[r]
        best = np.inf
        bid = -1
        for j in range(big.shape[0]):
            best, bid = _take(tri, big[j], ox, oy, oz, dx, dy, dz, t0, best, bid)
        # The ray's span inside the grid's box, from t0 on.
        ta = t0
        tb = np.inf
        o3 = (ox, oy, oz)
        d3 = (dx, dy, dz)
        inside = True
        for a in range(3):
            g0 = glo[a]
            g1 = glo[a] + cell[a] * dims[a]
            if d3[a] == 0.0:
                if o3[a] < g0 or o3[a] > g1:
                    inside = False
                continue
            s0 = (g0 - o3[a]) / d3[a]
            s1 = (g1 - o3[a]) / d3[a]
            if s0 > s1:
                s0, s1 = s1, s0
            ta = max(ta, s0)
            tb = min(tb, s1)
        if inside and ta <= tb and ta <= best:
            idx = np.empty(3, dtype=np.int64)
            step = np.empty(3, dtype=np.int64)
            tnext = np.empty(3)
            tdelta = np.empty(3)
            for a in range(3):
                p = o3[a] + ta * d3[a]
                c = int(np.floor((p - glo[a]) / cell[a]))
                idx[a] = min(max(c, 0), dims[a] - 1)
                if d3[a] > 0.0:
                    step[a] = 1
                    tnext[a] = (glo[a] + (idx[a] + 1) * cell[a] - o3[a]) / d3[a]
                    tdelta[a] = cell[a] / d3[a]
                elif d3[a] < 0.0:
                    step[a] = -1
                    tnext[a] = (glo[a] + idx[a] * cell[a] - o3[a]) / d3[a]
                    tdelta[a] = -cell[a] / d3[a]
                else:
                    step[a] = 0
                    tnext[a] = np.inf
                    tdelta[a] = np.inf
            while True:
                c = (idx[2] * dims[1] + idx[1]) * dims[0] + idx[0]
                for j in range(start[c], start[c + 1]):
                    best, bid = _take(tri, items[j], ox, oy, oz, dx, dy, dz, t0, best, bid)
                a = 0
                if tnext[1] < tnext[a]:
                    a = 1
                if tnext[2] < tnext[a]:
                    a = 2
                # Every hit nearer than the cell's exit lies in the cells walked (padded).
                if best <= tnext[a] or tnext[a] > tb:
                    break
                idx[a] += step[a]
                if idx[a] < 0 or idx[a] >= dims[a]:
                    break
                tnext[a] += tdelta[a]
        out_id[r] = bid
        out_t[r] = best
