"""From-segment coverage of spheres as first-class primitives (Popescu et al. 2024, Sec. 3.3).

Camera space relative to the eye at t = 0 (float64). The centre relative to the moving eye is
``O + t U`` (``U`` = the centre's own motion minus the camera's). For the pixel ray ``w`` the ray's
line meets the sphere while ``G(t) = |(O + t U) x w|^2 - r^2 |w|^2 <= 0`` (Eqs. 5-6 reduce to this
quadratic in t). The near hit is at depth ``(o.w - sqrt(-G)) / |w|^2``; when the sphere may cross
the near plane the far hit is used where the near one is closer than ``near`` (what a rasterized,
near-clipped sphere without back-face culling shows), and the sign changes of
``L = o.w - near |w|^2`` and ``Q = |o - near w|^2 - r^2`` bound those regimes. No tessellation; the
pixels a sphere can touch are a conservative box around the projections of both end spheres.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.cores.from_segment.dynamic import add_roots01, emit_chords, quad_range01, sort_small
from visibility.raster.face_pixels import pixel_range

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def sphere_setup(O: np.ndarray, U: np.ndarray, r: float, coef: np.ndarray) -> None:
    """Fill ``coef`` (>= 7) with the centre O (3,), its velocity U (3,) relative to the moving
    eye (camera space) and the radius r, as ``sphere_cover`` and ``depth_at`` read them."""
    for k in range(3):
        coef[k] = O[k]
        coef[3 + k] = U[k]
    coef[6] = r


@njit(**_JIT)
def _kind(g, lin, q, slow):
    if g > 0.0:
        return 0
    if not slow:
        return 1
    if lin >= 0.0 and q >= 0.0:
        return 1
    if lin >= 0.0 or q <= 0.0:
        return 2
    return 0


@njit(**_JIT)
def sphere_cover(coef: np.ndarray, x: float, y: float, near: float, slow: bool, knots: int,
                 t0: np.ndarray, t1: np.ndarray, z0: np.ndarray, z1: np.ndarray,
                 brk: np.ndarray, stack: np.ndarray) -> int:
    """Depth pieces of a (moving) sphere at the pixel ray (x, y, -1) over t in [0, 1].

    Returns the number of chords written to t0, t1, z0, z1 (split adaptively, exact depth at
    their ends: ``emit_chords``); ``brk`` (>= 48) and ``stack`` (>= 64, 4) are scratch.
    """
    ox, oy, oz = coef[0], coef[1], coef[2]
    ux, uy, uz = coef[3], coef[4], coef[5]
    r = coef[6]
    ww = x * x + y * y + 1.0
    # o x w and u x w with w = (x, y, -1).
    ax, ay, az = -oy - oz * y, oz * x + ox, ox * y - oy * x
    bx, by, bz = -uy - uz * y, uz * x + ux, ux * y - uy * x
    g0 = ax * ax + ay * ay + az * az - r * r * ww
    g1 = 2.0 * (ax * bx + ay * by + az * bz)
    g2 = bx * bx + by * by + bz * bz
    ow = ox * x + oy * y - oz
    uw = ux * x + uy * y - uz
    l0 = ow - near * ww
    px, py, pz = ox - near * x, oy - near * y, oz + near
    q0 = px * px + py * py + pz * pz - r * r
    q1 = 2.0 * (px * ux + py * uy + pz * uz)
    q2 = ux * ux + uy * uy + uz * uz
    if not slow:
        lo, hi = quad_range01(g0, g1, g2)
        if lo > 0.0:
            return 0  # the ray's line misses the sphere all along
    pc = brk[32:40]
    pc[0] = ow
    pc[1] = uw
    pc[2] = -g0
    pc[3] = -g1
    pc[4] = -g2
    pc[5] = ww
    k = 0
    brk[k] = 0.0
    k += 1
    k = add_roots01(g2, g1, g0, brk, k)
    if slow:
        if uw != 0.0:
            tl = -l0 / uw
            if tl > 0.0 and tl < 1.0:
                brk[k] = tl
                k += 1
        k = add_roots01(q2, q1, q0, brk, k)
    brk[k] = 1.0
    k += 1
    sort_small(brk, k)
    # Typed int64 from the start (not literal 0s): emit_chords compiles once, not also for
    # the literals numba's inference tries first.
    n = np.int64(0)
    start = 0.0
    cur = np.int64(0)
    for s in range(k - 1):
        a = brk[s]
        b = brk[s + 1]
        if not (b > a):
            continue
        m = 0.5 * (a + b)
        kind = _kind((g2 * m + g1) * m + g0, l0 + m * uw, (q2 * m + q1) * m + q0, slow)
        if kind != cur:
            if cur != 0:
                n = emit_chords(start, a, knots, cur, pc, t0, t1, z0, z1, n, stack)
            start = a
            cur = kind
    if cur != 0:
        n = emit_chords(start, 1.0, knots, cur, pc, t0, t1, z0, z1, n, stack)
    return n


@njit(**_JIT)
def _tangent_range(c, d, r):
    """Range of x / depth over a disc of centre (c, d) and radius r with d > r (2D)."""
    den = d * d - r * r
    root = r * np.sqrt(c * c + den)
    return (c * d - root) / den, (c * d + root) / den


@njit(**_JIT)
def sphere_box(c0: np.ndarray, c1: np.ndarray, r: float, near: float, res: int,
               box: np.ndarray, pad: float = 0.0) -> tuple[bool, float, bool]:
    """Pixel-centre box of a sphere swept from camera-space centre c0 (t = 0) to c1 (t = 1).

    Writes [row0, row1, col0, col1] (inclusive) to ``box``; returns (touches the face, smallest
    depth it can have, may cross the near plane). The swept sphere (a capsule) is convex and
    x / depth is quasi-linear, so the box of the two end projections bounds every intermediate
    one; when the capsule reaches the near plane the whole face is taken. ``pad`` widens the
    box by that many pixels (jittered samples, ``face_pixels.pixel_range``).
    """
    d0 = -c0[2]
    d1 = -c1[2]
    s2 = np.sqrt(0.5)
    # Outside one side plane of the 90-degree frustum (tan = 1) at both ends: not on this face.
    for sx, sy in ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
        e0 = (sx * c0[0] + sy * c0[1] - d0) * s2
        e1 = (sx * c1[0] + sy * c1[1] - d1) * s2
        if e0 > r and e1 > r:
            return False, 0.0, False
    if max(d0, d1) + r < near:
        return False, 0.0, False
    zmin = min(d0, d1) - r
    if zmin < near * (1.0 + 1e-9):
        box[0] = 0
        box[1] = res - 1
        box[2] = 0
        box[3] = res - 1
        return True, near, True
    xa0, xb0 = _tangent_range(c0[0], d0, r)
    xa1, xb1 = _tangent_range(c1[0], d1, r)
    ya0, yb0 = _tangent_range(c0[1], d0, r)
    ya1, yb1 = _tangent_range(c1[1], d1, r)
    u0 = min(xa0, xa1)
    u1 = max(xb0, xb1)
    v0 = min(ya0, ya1)
    v1 = max(yb0, yb1)
    if not pixel_range(u0, u1, v0, v1, res, box, pad):
        return False, 0.0, False
    return True, zmin, False
