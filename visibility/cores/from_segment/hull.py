"""Scan conversion of a triangle's projected swept hull (the paper's Alg. 1 line 6).

A triangle's swept volume (its corners at both segment ends, relative to the eye, clipped at the
near plane) projects to a convex polygon on a cube face; ``boxes._expanded_boxes`` stores that
polygon per (triangle, face) in a ``Hulls`` group, and the tiles visit per pixel row only the
columns whose sample can fall inside it (``hull_cols``) instead of the polygon's whole bounding
box: a thin diagonal sliver has a box far larger than its hull.

Coordinates are pixel units: pixel (row i, column j) has its centre at (col, row) = (j, i), so
NDC (u, v) is (col, row) = ((u + 1) res / 2 - 0.5, (1 - v) res / 2 - 0.5).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from visibility.borrow import NO_REFCOUNT
from visibility.planar import convex_hull

#: Most vertices of a stored hull: a triangle's six swept corners clipped at the near plane give
#: at most 12 candidate points (k corners behind: 6 - k in front, k (6 - k) crossing edges).
HMAX = 12
#: Absolute and relative (to the largest coordinate) widening of every span, in pixels: the
#: hull is stored in float32 (2^-24 relative rounding) and computed from divisions that the
#: cover tests do differently.
EPS_ABS = 1e-6
EPS_REL = 2e-7

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Helpers called per primitive, tile or row that allocate nothing: no reference counting.
_JIT_NO_NRT = dict(_JIT, **NO_REFCOUNT)


class Hulls(NamedTuple):
    """Projected swept hulls of some of a segment's primitives, as the kernels read them.

    index : (n_prims,) int32 row of primitive p's hull, -1 = none (its box is scanned whole:
        whole clusters, whose triangles get their own boxes per tile, and spheres, whose swept
        capsule projects to no polygon of a few points).
    pts : (m, HMAX, 2) float32 hull vertices (col, row) in pixel units, in order around it.
    count : (m,) int8 vertices; 0 = no hull (scan the box).
    """

    index: np.ndarray
    pts: np.ndarray
    count: np.ndarray


def no_hulls(n_prims: int) -> Hulls:
    """A ``Hulls`` group in which no primitive has a hull (every box is scanned whole)."""
    return Hulls(np.full(n_prims, -1, dtype=np.int32), np.zeros((0, HMAX, 2), np.float32),
                 np.zeros(0, np.int8))


@njit(**_JIT_NO_NRT)
def store_hull(uv: np.ndarray, n: int, res: int, scratch: np.ndarray, out_pts: np.ndarray,
               k: int) -> int:
    """Hull of the NDC points ``uv[:n]`` (n, 2) in pixel units, written to ``out_pts[k]``
    (float32). ``scratch`` (2 n + 2, 2) float64. Returns the vertex count, 0 when the hull
    cannot be stored (too many vertices, or coordinates float32 cannot hold): scan the box."""
    h = 0.5 * res
    for q in range(n):
        scratch[q, 0] = (uv[q, 0] + 1.0) * h - 0.5
        scratch[q, 1] = (1.0 - uv[q, 1]) * h - 0.5
        if not (abs(scratch[q, 0]) < 1e30 and abs(scratch[q, 1]) < 1e30):
            return 0
    m = convex_hull(scratch[:n], n, scratch[n:])
    if m < 1 or m > HMAX:
        return 0
    for q in range(m):
        out_pts[k, q, 0] = scratch[n + q, 0]
        out_pts[k, q, 1] = scratch[n + q, 1]
    return m


@njit(**_JIT_NO_NRT)
def _hull_eps(pts: np.ndarray, k: int, m: int) -> float:
    """The widening of stored hull ``pts[k, :m]``'s spans against rounding, in pixels."""
    scale = 0.0
    for q in range(m):
        scale = max(scale, abs(float(pts[k, q, 0])), abs(float(pts[k, q, 1])))
    return EPS_ABS + EPS_REL * scale


@njit(**_JIT_NO_NRT)
def _edge_in_band(pts: np.ndarray, k: int, m: int, q: int, lo: float, hi: float, cmin: float,
                  cmax: float) -> tuple[float, float]:
    """(cmin, cmax) widened by what edge q of the stored hull (from vertex q to the next) holds
    in the band of rows [lo, hi]: its first vertex if inside, and where it crosses the band's
    two lines (its other end is the next edge's first vertex)."""
    ca = float(pts[k, q, 0])
    ra = float(pts[k, q, 1])
    nq = q + 1 if q + 1 < m else 0
    cb = float(pts[k, nq, 0])
    rb = float(pts[k, nq, 1])
    if lo <= ra <= hi:
        cmin = min(cmin, ca)
        cmax = max(cmax, ca)
    for r in (lo, hi):
        if (ra < r < rb) or (rb < r < ra):
            c = ca + (r - ra) * (cb - ca) / (rb - ra)
            cmin = min(cmin, c)
            cmax = max(cmax, c)
    return cmin, cmax


@njit(**_JIT_NO_NRT)
def _band_cols(cmin: float, cmax: float, pad: float, eps: float) -> tuple[float, float]:
    """The columns (as floats; cmin > cmax: none) whose sample, up to ``pad`` off centre, can
    reach the hull's extent [cmin, cmax] in a band."""
    if not cmin <= cmax:
        return np.inf, -np.inf
    # Far beyond any face (points near the near plane): keep the ints in range.
    cmin = max(cmin, -1e15)
    cmax = min(cmax, 1e15)
    return np.ceil(cmin - pad - eps), np.floor(cmax + pad + eps)


@njit(**_JIT_NO_NRT)
def hull_cols(pts: np.ndarray, k: int, m: int, rlo: float, rhi: float,
              pad: float) -> tuple[int, int]:
    """Columns [j0, j1] (inclusive, unclamped; j0 > j1 when none) of the pixels in rows
    [rlo, rhi] whose sample, up to ``pad`` pixels off its centre per axis, can fall inside the
    stored hull ``pts[k, :m]``: the hull cut by the band of sample rows [rlo - pad, rhi + pad],
    widened by ``pad`` (and by EPS_ABS / EPS_REL against rounding)."""
    eps = _hull_eps(pts, k, m)
    lo = rlo - pad - eps
    hi = rhi + pad + eps
    cmin = np.inf
    cmax = -np.inf
    for q in range(m):
        cmin, cmax = _edge_in_band(pts, k, m, q, lo, hi, cmin, cmax)
    a, b = _band_cols(cmin, cmax, pad, eps)
    if not a <= b:
        return 1, 0
    return int(a), int(b)


@njit(**_JIT_NO_NRT)
def hull_rows(pts: np.ndarray, k: int, m: int, ia: int, ib: int, pad: float, r0: int,
              ext: np.ndarray) -> None:
    """``hull_cols(pts, k, m, i, i, pad)`` for every row i of [ia, ib] at once, as floats:
    ext[i - r0] = (first, last) column (first > last: none). One pass over the hull's edges,
    each visiting only the rows its band can touch: a thin sliver across a tile's 16 rows
    costs about two edges' rows, where a call per row read every edge (and the scale) again."""
    eps = _hull_eps(pts, k, m)
    for i in range(ia, ib + 1):
        ext[i - r0, 0] = np.inf
        ext[i - r0, 1] = -np.inf
    w = pad + eps
    for q in range(m):
        ra = float(pts[k, q, 1])
        rb = float(pts[k, q + 1 if q + 1 < m else 0, 1])
        # The rows whose band [i - w, i + w] can meet the edge, one wider each side against
        # rounding (``_edge_in_band`` decides, as for hull_cols).
        ea = max(min(ra, rb) - w, ia - 1.0)
        eb = min(max(ra, rb) + w, ib + 1.0)
        if not ea <= eb:
            continue
        for i in range(max(ia, int(np.floor(ea)) - 1), min(ib, int(np.ceil(eb)) + 1) + 1):
            ext[i - r0, 0], ext[i - r0, 1] = _edge_in_band(
                pts, k, m, q, i - pad - eps, i + pad + eps, ext[i - r0, 0], ext[i - r0, 1])
    for i in range(ia, ib + 1):
        ext[i - r0, 0], ext[i - r0, 1] = _band_cols(ext[i - r0, 0], ext[i - r0, 1], pad, eps)
