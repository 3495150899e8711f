"""The winding number on the front side of the triangles of closed surfaces, by ray parity.

A closed, consistently wound surface (each edge held by two of its triangles, in opposite
directions) has a winding number w(x) at every point off it: 0 far from it, and one more on a
triangle's back than on its front (the front is the side its right-hand normal points to).
Where the surface does not pass through itself, w is 0 on one side of every triangle and +-1 on
the other. A surface that passes through itself can also hold pieces with w = 0 on their back,
or on their front facing in: there an eye from outside may see the side it faces. So the side
of a triangle facing an eye far from the surface (where w = 0) is hidden by the surface itself
exactly where w on that side is not 0: a ray from the eye had to cross the surface to get
there. ``front_windings`` finds w on each triangle's front side by counting the signed
crossings of a ray from the triangle to infinity.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.walkable import bin_triangles

#: ``front_windings``' value for a triangle whose rays it could not count (each passed too
#: near an edge, or met a triangle too near its start): nothing may be concluded there.
UNDECIDED = -32768

#: Interior points a triangle's ray may start from (barycentric): the next is tried when a
#: ray passes too near an edge of another triangle.
_STARTS = np.array([[1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0], [0.2, 0.35, 0.45], [0.45, 0.2, 0.35],
                    [0.35, 0.45, 0.2], [0.6, 0.25, 0.15]])

#: Relative tolerance of the edge and depth tests: a ray nearer than this to another triangle's
#: edge, or meeting a triangle this near its start, leaves the count undecided.
_TOL = 1e-9


def front_windings(tris: np.ndarray, part: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """The winding number on the front side of each triangle of ``todo``, counting only the
    triangles of its own part (a closed surface).

    Parameters
    ----------
    tris : (k, 3, 3) float64 triangles, metres (counter-clockwise seen from the front).
    part : (k,) int64 the closed surface each triangle belongs to.
    todo : (k,) bool the triangles to count for (the others are still crossed by the rays).

    Returns
    -------
    (k,) int32: w just in front of the triangle (just behind it: w + 1); ``UNDECIDED`` where
    no ray could be counted, and for the triangles not in ``todo``.
    """
    k = len(tris)
    out = np.full(k, UNDECIDED, dtype=np.int32)
    if k == 0 or not todo.any():
        return out
    # Writable and contiguous whatever the caller holds (a scene's arrays may be read-only):
    # the kernel compiles once.
    tris = np.require(tris, np.float64, ("C", "W"))
    part = np.require(part, np.int64, ("C", "W"))
    lo = tris.min(axis=1)
    hi = tris.max(axis=1)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    axis = np.argmax(np.abs(n), axis=1).astype(np.int64)
    for a in range(3):
        sel = np.flatnonzero(todo & (axis == a)).astype(np.int64)
        if len(sel):
            cstart, cells, origin, size, nb = _grid(lo, hi, a)
            _count(tris, lo, hi, n, part, sel, a,
                   cstart, cells, origin, size, nb, _STARTS, out)
    return out


def _grid(lo: np.ndarray, hi: np.ndarray, a: int) -> tuple:
    """Triangles binned on a grid of square bins over the plane across axis a (its other two
    axes in order, ``walkable.bin_triangles``): (bin starts, triangle per slot, the grid's
    origin (2,), bin size, bins along each of the two axes)."""
    b, c = (a + 1) % 3, (a + 2) % 3
    bmin = np.ascontiguousarray(lo[:, [b, c]])
    bmax = np.ascontiguousarray(hi[:, [b, c]])
    origin = bmin.min(axis=0)
    ext = bmax.max(axis=0) - origin
    size = max(float(ext.max()) / max(np.sqrt(len(lo)) / 2.0, 1.0), 1e-300)
    nb = np.minimum(np.ceil(ext / size).astype(np.int64), 1024) + 1
    starts, items = bin_triangles(bmin, bmax, origin, size, int(nb[0]), int(nb[1]))
    return starts, items, origin, size, nb


@njit(cache=True, nogil=True, parallel=True)
def _count(tris, lo, hi, n, part, sel, a, cstart, cells, origin, size, nb, starts,
           out):  # pragma: no cover - numba
    """``front_windings`` for the triangles ``sel``, whose normals lie nearest axis a: rays
    along +-a (towards the front) from the points ``starts`` of each, through the bins
    (``_grid``) of the plane across a."""
    b = (a + 1) % 3
    c = (a + 2) % 3
    for q in prange(len(sel)):
        t = sel[q]
        s = 1.0 if n[t, a] > 0.0 else -1.0
        for st in range(starts.shape[0]):
            pa = starts[st, 0] * tris[t, 0, a] + starts[st, 1] * tris[t, 1, a] \
                + starts[st, 2] * tris[t, 2, a]
            pb = starts[st, 0] * tris[t, 0, b] + starts[st, 1] * tris[t, 1, b] \
                + starts[st, 2] * tris[t, 2, b]
            pc = starts[st, 0] * tris[t, 0, c] + starts[st, 1] * tris[t, 1, c] \
                + starts[st, 2] * tris[t, 2, c]
            i = min(max(int(np.floor((pb - origin[0]) / size)), 0), nb[0] - 1)
            j = min(max(int(np.floor((pc - origin[1]) / size)), 0), nb[1] - 1)
            w = 0
            ok = True
            for m in range(cstart[i * nb[1] + j], cstart[i * nb[1] + j + 1]):
                u = cells[m]
                if u == t or part[u] != part[t]:
                    continue
                if pb < lo[u, b] or pb > hi[u, b] or pc < lo[u, c] or pc > hi[u, c]:
                    continue
                if (s > 0.0 and hi[u, a] < pa) or (s < 0.0 and lo[u, a] > pa):
                    continue
                hit = _ray_hit(tris[u], a, b, c, pa, pb, pc, s)
                if hit == 2:
                    ok = False
                    break
                if hit == 1:
                    w += 1 if s * n[u, a] > 0.0 else -1
            if ok:
                out[t] = w
                break


@njit(cache=True, inline="always")
def _ray_hit(tri, a, b, c, pa, pb, pc, s):  # pragma: no cover - numba
    """Whether the ray from (pa, pb, pc) (axis order a, b, c) along s * axis a meets triangle
    ``tri``, whose box holds (pb, pc) across a: 1 it crosses it, 0 it misses, 2 too near to
    tell (an edge, a triangle along the ray, or a crossing near the start)."""
    area = 0.0
    ext = 0.0
    span = 0.0
    e_long = 0
    for e in range(3):
        f = (e + 1) % 3
        area += tri[e, b] * tri[f, c] - tri[f, b] * tri[e, c]
        ext = max(ext, abs(tri[e, b] - pb) + abs(tri[e, c] - pc))
        ln = abs(tri[f, b] - tri[e, b]) + abs(tri[f, c] - tri[e, c])
        if ln > span:
            span = ln
            e_long = e
    if span == 0.0:
        return 0  # seen end on: a ray meets it only at a point, a set of no measure
    if abs(area) <= _TOL * span * span:
        # Along the ray: it meets the triangle only by grazing its plane, where no count holds.
        f = (e_long + 1) % 3
        eb = tri[f, b] - tri[e_long, b]
        ec = tri[f, c] - tri[e_long, c]
        side = eb * (pc - tri[e_long, c]) - ec * (pb - tri[e_long, b])
        return 2 if abs(side) <= _TOL * span * (span + ext) else 0
    inside = True
    near = False
    for e in range(3):
        f = (e + 1) % 3
        eb = tri[f, b] - tri[e, b]
        ec = tri[f, c] - tri[e, c]
        side = eb * (pc - tri[e, c]) - ec * (pb - tri[e, b])
        if abs(side) <= _TOL * (abs(eb) + abs(ec)) * (abs(eb) + abs(ec) + ext):
            near = True
        elif (side > 0.0) != (area > 0.0):
            inside = False
    if not inside:
        return 0
    if near:
        return 2
    # The crossing's coordinate along a: the triangle's plane at (pb, pc), by barycentrics.
    l0 = ((tri[1, b] - pb) * (tri[2, c] - pc) - (tri[2, b] - pb) * (tri[1, c] - pc)) / area
    l1 = ((tri[2, b] - pb) * (tri[0, c] - pc) - (tri[0, b] - pb) * (tri[2, c] - pc)) / area
    l2 = 1.0 - l0 - l1
    xa = l0 * tri[0, a] + l1 * tri[1, a] + l2 * tri[2, a]
    d = s * (xa - pa)
    if abs(d) <= _TOL * (abs(pa) + ext + span):
        return 2
    return 1 if d > 0.0 else 0
