"""Coverage of static triangles along a view segment (Popescu et al. 2024, Eqs. 1-2): the
coefficients of a triangle (``static_setup``) and, per pixel ray, the interval of t it covers
and the depths at its ends (``static_cover``).

Relative to the moving eye a static triangle translates by ``-t d``.
With ``w`` the pixel ray, the edge value ``w . ((P - t d) x (Q - t d))`` is linear in t and equals
the barycentric weight of the opposite corner times ``w . N`` (N the triangle normal), so the
coverage interval is the intersection of three half-lines; the hit depth
``(A . N - t d . N) / (w . N)`` is linear too, and ``depth >= near`` is one more half-line: this is
how triangles crossing the near plane, or behind the eye for part of the segment, are handled per
pixel, exactly as a near-clipping rasterizer decides. Edges are evaluated from their corners in a
canonical order so triangles sharing an edge get bit-identical event times (no cracks).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.borrow import NO_REFCOUNT

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Helpers called per primitive, tile or row that allocate nothing: no reference counting.
_JIT_NO_NRT = dict(_JIT, **NO_REFCOUNT)
#: Hot callees of the pixel loop, inlined into it (numba IR inlining): the configuration the
#: published bench_segment runs measured; the arrays they take are borrowed by the caller.
_JIT_INLINE = dict(_JIT, inline="always")


@njit(**_JIT)
def _less(ax, ay, az, bx, by, bz):
    if ax != bx:
        return ax < bx
    if ay != by:
        return ay < by
    return az < bz


@njit(**_JIT)
def edge_order(W, e):  # pragma: no cover - numba
    """Edge e of a triangle with world corners ``W`` (3, 3) in canonical order: (i, j, sign),
    the corners from the lexicographically smaller, sign -1 where that reverses the edge (so
    triangles sharing an edge compute it from the same corners, bit for bit)."""
    i = e
    j = (e + 1) % 3
    if _less(W[j, 0], W[j, 1], W[j, 2], W[i, 0], W[i, 1], W[i, 2]):
        return j, i, -1.0
    return i, j, 1.0


@njit(**_JIT_NO_NRT)
def static_setup(P: np.ndarray, W: np.ndarray, d: np.ndarray, coef: np.ndarray) -> None:
    """Coefficients of a static triangle for ``static_cover``.

    P : (3, 3) camera-space corners relative to the eye at t = 0; W : (3, 3) world corners (edge
    order only); d : (3,) camera-space eye motion over the segment. ``coef`` (>= 25) receives per
    edge the vectors whose dot with the ray (x, y, -1) gives the edge value at t = 0 and its rate
    (canonically oriented), then N, A . N, d . N and |N|^2.
    """
    for e in range(3):
        i, j, sg = edge_order(W, e)
        px, py, pz = P[i, 0], P[i, 1], P[i, 2]
        qx, qy, qz = P[j, 0], P[j, 1], P[j, 2]
        ex, ey, ez = qx - px, qy - py, qz - pz
        o = 6 * e
        coef[o] = sg * (py * qz - pz * qy)
        coef[o + 1] = sg * (pz * qx - px * qz)
        coef[o + 2] = sg * (px * qy - py * qx)
        # d/dt of (P - t d) x (Q - t d) = (Q - P) x d.
        coef[o + 3] = sg * (ey * d[2] - ez * d[1])
        coef[o + 4] = sg * (ez * d[0] - ex * d[2])
        coef[o + 5] = sg * (ex * d[1] - ey * d[0])
    ux, uy, uz = P[1, 0] - P[0, 0], P[1, 1] - P[0, 1], P[1, 2] - P[0, 2]
    vx, vy, vz = P[2, 0] - P[0, 0], P[2, 1] - P[0, 1], P[2, 2] - P[0, 2]
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    coef[18] = nx
    coef[19] = ny
    coef[20] = nz
    coef[21] = P[0, 0] * nx + P[0, 1] * ny + P[0, 2] * nz
    coef[22] = d[0] * nx + d[1] * ny + d[2] * nz
    coef[23] = nx * nx + ny * ny + nz * nz


@njit(**_JIT_INLINE)
def static_cover(coef: np.ndarray, x: float, y: float, near: float,
                 slow: bool) -> tuple[bool, float, float, float, float]:
    """Coverage interval and end depths of a static triangle at the pixel ray (x, y, -1).

    Returns (covered, ts, tf, depth at ts, depth at tf); the depth is linear in t in between.
    A ray (nearly) in the triangle's plane sees nothing, as in a rasterizer.
    """
    wn = coef[18] * x + coef[19] * y - coef[20]
    if not (wn * wn > 1e-24 * coef[23] * (x * x + y * y + 1.0)):
        return False, 0.0, 0.0, 0.0, 0.0
    lo = 0.0
    hi = 1.0
    for e in range(3):
        o = 6 * e
        c = coef[o] * x + coef[o + 1] * y - coef[o + 2]
        s = coef[o + 3] * x + coef[o + 4] * y - coef[o + 5]
        if wn < 0.0:
            c = -c
            s = -s
        # Inside this edge while c + s t >= 0; a root only when the sign changes on [0, 1].
        c1 = c + s
        if c >= 0.0 and c1 >= 0.0:
            continue
        if c < 0.0 and c1 < 0.0:
            return False, 0.0, 0.0, 0.0, 0.0
        r = -c / s
        if c < 0.0:
            lo = max(lo, r)
        else:
            hi = min(hi, r)
    va = coef[21]
    dn = coef[22]
    if slow:
        # (va - t dn) / wn >= near
        c = va - near * wn
        s = -dn
        if wn < 0.0:
            c = -c
            s = -s
        c1 = c + s
        if c < 0.0 and c1 < 0.0:
            return False, 0.0, 0.0, 0.0, 0.0
        if not (c >= 0.0 and c1 >= 0.0):
            r = -c / s
            if c < 0.0:
                lo = max(lo, r)
            else:
                hi = min(hi, r)
    if not (hi > lo):
        return False, 0.0, 0.0, 0.0, 0.0
    zs = (va - lo * dn) / wn
    zf = (va - hi * dn) / wn
    return True, lo, hi, max(zs, 0.0), max(zf, 0.0)
