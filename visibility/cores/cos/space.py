"""Camera offset space geometry for one pixel (paper Sec. 3, 4.5), as numba kernels.

The 2D COS of a pixel is a parallel projection. A camera offset Delta (in the plane w = 0 of the
view) sees the point X = (x, y, w) at the sample direction s = (s_x, s_y, 1) exactly when
Delta = (x - w s_x, y - w s_y) (Eq. 8 with Delta_w = 0): the map is affine in X, so a triangle's
COS is the triangle of its vertices' COS points (the prism slice of Fig. 5), its depth along the
ray is affine over it (Eq. 9), and a camera that moves along the ray (the side frusta's forward
offsets) keeps its COS point. The supported offsets are the camera rectangle's projection: the
rectangle C itself for a front frustum, a parallelogram for a side one.

Between-sample directions (Sec. 4.5, Eq. 10): over the pixel's square of directions,
s + delta with |delta| <= h (L-infinity, h = half a pixel in tangent units), a point's COS image
moves by -w delta, i.e. within an L-infinity square of radius |w| h around its pixel-centre
image. Only relative motion matters to a containment test, so each test picks a reference depth
w_ref and works in the frame that moves by -w_ref delta (a translation of everything, the same
for all objects at a given delta); a point then moves within a square of radius |w - w_ref| h.
Every object is carried at the pixel centre with that per-vertex *motion radius*: an occludee
grows to the convex hull of its vertex squares, an occluder silhouette edge
to the hull of its two end squares (a "capsule"); no moving silhouette edge can reach a point
outside its capsule, so a region clear of every capsule stays inside (or outside) the occluder
under every delta. This replaces the paper's per-edge sliding-and-rotating analysis by a bound
that is simpler and never smaller.

Conventions: COS points are float64 metres relative to the view origin; polygons are arrays
(k, 2) with a count; "separated" tests are strict, so touching counts as overlapping
(conservative for occlusion).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.borrow import NO_REFCOUNT

#: Largest vertex count of a clipped polygon (4 box sides + 3 triangle + 4 region half-planes).
MAX_POLY = 16


@njit(cache=True, nogil=True, inline="always")
def cam_point(pts, i, origin, perm, sign):  # pragma: no cover - numba
    """Camera coordinates (x, y, w) of point i; the shift by the origin comes first, in float64."""
    return (sign[0] * (pts[i, perm[0]] - origin[perm[0]]),
            sign[1] * (pts[i, perm[1]] - origin[perm[1]]),
            sign[2] * (pts[i, perm[2]] - origin[perm[2]]))


@njit(cache=True, nogil=True, inline="always")
def load_prim(pts, start, n, origin, perm, sign, cam):  # pragma: no cover - numba
    """Fill ``cam`` (>= n, 3) with the camera coordinates of a primitive's n points."""
    for i in range(n):
        x, y, w = cam_point(pts, start + i, origin, perm, sign)
        cam[i, 0] = x
        cam[i, 1] = y
        cam[i, 2] = w


@njit(cache=True, nogil=True, inline="always")
def project(cam, n, sx, sy, h, wref, v, r):  # pragma: no cover - numba
    """COS images ``v`` (n, 2) and motion radii ``r`` (n,) of n camera-space points at the pixel
    centre (sx, sy) with half-pixel h, in the frame that moves with depth ``wref``."""
    for i in range(n):
        w = cam[i, 2]
        v[i, 0] = cam[i, 0] - w * sx
        v[i, 1] = cam[i, 1] - w * sy
        r[i] = abs(w - wref) * h


@njit(cache=True, nogil=True, inline="always")
def support(v, r, n, nx, ny):  # pragma: no cover - numba
    """(min, max) of n . p over the hull of the squares (v_i, r_i)."""
    l1 = abs(nx) + abs(ny)
    lo = np.inf
    hi = -np.inf
    for i in range(n):
        d = nx * v[i, 0] + ny * v[i, 1]
        lo = min(lo, d - r[i] * l1)
        hi = max(hi, d + r[i] * l1)
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def tri_normal(p):  # pragma: no cover - numba
    """The (unnormalised) normal (p1 - p0) x (p2 - p0) of the triangle p (3, 3) and its
    length."""
    ux, uy, uz = p[1, 0] - p[0, 0], p[1, 1] - p[0, 1], p[1, 2] - p[0, 2]
    vx, vy, vz = p[2, 0] - p[0, 0], p[2, 1] - p[0, 1], p[2, 2] - p[0, 2]
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    return nx, ny, nz, np.sqrt(nx * nx + ny * ny + nz * nz)


@njit(cache=True, nogil=True, inline="always")
def winding_step(ax, ay, bx, by, cx, cy):  # pragma: no cover - numba
    """Edge ab's share of the winding number of (cx, cy): +1 or -1 where it crosses the ray
    from (cx, cy) towards +x upwards or downwards, 0 where it does not, 2 where (cx, cy) lies
    on it up to rounding (inside cannot be decided)."""
    up = ay <= cy < by
    down = by <= cy < ay
    if not (up or down):
        return 0
    t1 = (bx - ax) * (cy - ay)
    t2 = (cx - ax) * (by - ay)
    side = t1 - t2
    if abs(side) <= 1e-12 * (abs(t1) + abs(t2)):
        return 2
    if up and side > 0.0:
        return 1
    if down and side < 0.0:
        return -1
    return 0


@njit(cache=True, nogil=True, inline="always")
def polygon_centroid(px, py, n):  # pragma: no cover - numba
    """Twice the signed area of the polygon (px, py)[:n] and its centroid (the centroid is
    not finite where the area is zero)."""
    ar = 0.0
    cx = 0.0
    cy = 0.0
    for i in range(n):
        j = (i + 1) % n
        cr = px[i] * py[j] - px[j] * py[i]
        ar += cr
        cx += (px[i] + px[j]) * cr
        cy += (py[i] + py[j]) * cr
    if ar == 0.0:
        return 0.0, np.nan, np.nan
    return ar, cx / (3.0 * ar), cy / (3.0 * ar)


@njit(cache=True, nogil=True, inline="always")
def area2(v):  # pragma: no cover - numba
    """Twice the signed area of the COS triangle v[0..2]."""
    return ((v[1, 0] - v[0, 0]) * (v[2, 1] - v[0, 1])
            - (v[1, 1] - v[0, 1]) * (v[2, 0] - v[0, 0]))


@njit(cache=True, nogil=True, inline="always")
def bbox(v, r, n):  # pragma: no cover - numba
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    for i in range(n):
        x0 = min(x0, v[i, 0] - r[i])
        x1 = max(x1, v[i, 0] + r[i])
        y0 = min(y0, v[i, 1] - r[i])
        y1 = max(y1, v[i, 1] + r[i])
    return x0, x1, y0, y1


@njit(cache=True, nogil=True, inline="always")
def edges_separate(pv, m, qv, qr, nq, rv, rr):  # pragma: no cover - numba
    """Whether an edge normal of polygon ``pv`` (m corners) separates the grown occludee
    (qv, qr, nq) from the grown region (rv, rr, 4 squares)."""
    for a in range(m):
        b = (a + 1) % m
        nx = pv[b, 1] - pv[a, 1]
        ny = pv[a, 0] - pv[b, 0]
        if nx == 0.0 and ny == 0.0:
            continue
        lq, hq = support(qv, qr, nq, nx, ny)
        lr, hr = support(rv, rr, 4, nx, ny)
        if hq < lr or hr < lq:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def region_share(rv, rr, reg):  # pragma: no cover - numba
    """What every overlap test against the grown offset region (hull of the 4 squares (rv,
    rr)) reuses, into ``reg`` (12,): its box (x0, x1, y0, y1), then per edge a of its quad the
    region's own support (lo, hi) along that edge's normal."""
    x0, x1, y0, y1 = bbox(rv, rr, 4)
    reg[0] = x0
    reg[1] = x1
    reg[2] = y0
    reg[3] = y1
    for a in range(4):
        b = (a + 1) % 4
        lr, hr = support(rv, rr, 4, rv[b, 1] - rv[a, 1], rv[a, 0] - rv[b, 0])
        reg[4 + 2 * a] = lr
        reg[5 + 2 * a] = hr


@njit(cache=True, nogil=True, inline="always")
def overlaps_share(qv, qr, nq, tri, rv, rr, reg):  # pragma: no cover - numba
    """``overlaps`` with the region's share already computed (``region_share``): the lists
    test many occludees against one pixel's region."""
    qx0, qx1, qy0, qy1 = bbox(qv, qr, nq)
    if qx1 < reg[0] or reg[1] < qx0 or qy1 < reg[2] or reg[3] < qy0:
        return False
    if tri and edges_separate(qv, 3, qv, qr, nq, rv, rr):
        return False
    for a in range(4):
        b = (a + 1) % 4
        nx = rv[b, 1] - rv[a, 1]
        ny = rv[a, 0] - rv[b, 0]
        if nx == 0.0 and ny == 0.0:
            continue
        lq, hq = support(qv, qr, nq, nx, ny)
        if hq < reg[4 + 2 * a] or reg[5 + 2 * a] < lq:
            return False
    return True


@njit(cache=True, nogil=True)
def overlaps(qv, qr, nq, tri, rv, rr):  # pragma: no cover - numba
    """Whether the grown occludee (hull of squares (qv, qr), n = nq) may meet the grown offset
    region (hull of the 4 squares (rv, rr)): separating-axis test on the axes x, y, the
    triangle's edge normals (``tri``) and the region's edge normals. Conservative: True unless
    an axis separates them (the list-building test of Sec. 4.2 with the Sec. 4.5 half pixel)."""
    reg = np.empty(12)
    region_share(rv, rr, reg)
    return overlaps_share(qv, qr, nq, tri, rv, rr, reg)


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def clip_halfplane(px, py, n, nx, ny, c, ox, oy):  # pragma: no cover - numba
    """Clip polygon (px, py)[:n] to nx x + ny y <= c, writing into (ox, oy); returns the count."""
    m = 0
    if n == 0:
        return 0
    for i in range(n):
        j = (i + 1) % n
        di = nx * px[i] + ny * py[i] - c
        dj = nx * px[j] + ny * py[j] - c
        if di <= 0.0:
            ox[m] = px[i]
            oy[m] = py[i]
            m += 1
        if (di < 0.0 < dj) or (dj < 0.0 < di):
            t = di / (di - dj)
            ox[m] = px[i] + t * (px[j] - px[i])
            oy[m] = py[i] + t * (py[j] - py[i])
            m += 1
    return m


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def region_polygon(qv, qr, nq, tri, rv, rr, kx, ky, tx, ty):  # pragma: no cover - numba
    """A convex polygon K (kx, ky) holding (grown occludee) n (grown offset region): their
    bounding-box overlap clipped by the occludee's edge half-planes and the region's, each
    pushed out to the support of the grown set. Returns the vertex count (0: disjoint)."""
    qx0, qx1, qy0, qy1 = bbox(qv, qr, nq)
    rx0, rx1, ry0, ry1 = bbox(rv, rr, 4)
    x0, x1 = max(qx0, rx0), min(qx1, rx1)
    y0, y1 = max(qy0, ry0), min(qy1, ry1)
    if x0 > x1 or y0 > y1:
        return 0
    kx[0], ky[0] = x0, y0
    kx[1], ky[1] = x1, y0
    kx[2], ky[2] = x1, y1
    kx[3], ky[3] = x0, y1
    # int64, not literals: each callee is compiled for one signature.
    n = np.int64(4)
    if tri:
        n = clip_by_grown_edges(kx, ky, n, qv, qr, np.int64(3), tx, ty)
    if n == 0:
        return 0
    return clip_by_grown_edges(kx, ky, n, rv, rr, np.int64(4), tx, ty)


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def clip_by_grown_edges(kx, ky, n, pv, pr, m, tx, ty):  # pragma: no cover - numba
    """Clip the convex polygon (kx, ky) of ``n`` vertices, in place, by the edge half-planes
    of the convex polygon ``pv`` (its first ``m`` rows, in either winding) grown by ``pr``,
    each pushed out to the support of the grown set (``support``). Returns the new vertex
    count (0: empty). ``tx, ty``: scratch of the same size as ``kx, ky``."""
    s = 1.0 if area2(pv) >= 0.0 else -1.0
    for a in range(m):
        b = (a + 1) % m
        # Outward normal of a counter-clockwise edge a -> b.
        nx = s * (pv[b, 1] - pv[a, 1])
        ny = s * (pv[a, 0] - pv[b, 0])
        if nx == 0.0 and ny == 0.0:
            continue
        _, h = support(pv, pr, m, nx, ny)
        n = clip_halfplane(kx, ky, n, nx, ny, h, tx, ty)
        for i in range(n):
            kx[i] = tx[i]
            ky[i] = ty[i]
        if n == 0:
            return 0
    return n


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def polygon_axes(kx, ky, nk, kbox, knx, kny, klo, khi):  # pragma: no cover - numba
    """Precompute polygon K's box (kbox (4,): x0, x1, y0, y1) and, per edge e, its normal
    (knx, kny) and K's extent (klo, khi) along it, for ``capsule_meets``."""
    kbox[0] = np.inf
    kbox[1] = -np.inf
    kbox[2] = np.inf
    kbox[3] = -np.inf
    for i in range(nk):
        kbox[0] = min(kbox[0], kx[i])
        kbox[1] = max(kbox[1], kx[i])
        kbox[2] = min(kbox[2], ky[i])
        kbox[3] = max(kbox[3], ky[i])
    for e in range(nk):
        j = (e + 1) % nk
        nx = ky[j] - ky[e]
        ny = kx[e] - kx[j]
        knx[e] = nx
        kny[e] = ny
        lo = np.inf
        hi = -np.inf
        for i in range(nk):
            d = nx * kx[i] + ny * ky[i]
            lo = min(lo, d)
            hi = max(hi, d)
        klo[e] = lo
        khi[e] = hi


@njit(cache=True, nogil=True, inline="always")
def capsule_meets(ax, ay, bx, by, r, kx, ky, nk, kbox, knx, kny, klo, khi):  # pragma: no cover
    """``capsule_hits`` with K's box and edge axes precomputed (``polygon_axes``)."""
    if max(ax, bx) + r < kbox[0] or min(ax, bx) - r > kbox[1]:
        return False
    if max(ay, by) + r < kbox[2] or min(ay, by) - r > kbox[3]:
        return False
    for e in range(nk):
        nx = knx[e]
        ny = kny[e]
        if nx == 0.0 and ny == 0.0:
            continue
        l1 = r * (abs(nx) + abs(ny))
        da = nx * ax + ny * ay
        db = nx * bx + ny * by
        if max(da, db) + l1 < klo[e] or khi[e] < min(da, db) - l1:
            return False
    # The segment's own normal.
    nx = by - ay
    ny = ax - bx
    if nx == 0.0 and ny == 0.0:
        return True
    l1 = r * (abs(nx) + abs(ny))
    da = nx * ax + ny * ay
    db = nx * bx + ny * by
    clo = min(da, db) - l1
    chi = max(da, db) + l1
    lo = np.inf
    hi = -np.inf
    for i in range(nk):
        d = nx * kx[i] + ny * ky[i]
        lo = min(lo, d)
        hi = max(hi, d)
    return not (chi < lo or hi < clo)


@njit(cache=True, nogil=True)
def capsule_hits(ax, ay, bx, by, r, kx, ky, nk):  # pragma: no cover - numba
    """Whether the hull of the squares of radius r around a and b meets polygon K (nk >= 1).

    Separating axes of the two convex sets: x, y, K's edge normals and the segment's normal.
    Touching counts as meeting."""
    kbox = np.empty(4)
    knx = np.empty(nk)
    kny = np.empty(nk)
    klo = np.empty(nk)
    khi = np.empty(nk)
    polygon_axes(kx, ky, nk, kbox, knx, kny, klo, khi)
    return capsule_meets(ax, ay, bx, by, r, kx, ky, nk, kbox, knx, kny, klo, khi)


@njit(cache=True, nogil=True, inline="always")
def in_triangle(px, py, v):  # pragma: no cover - numba
    """Whether (px, py) lies in the closed counter-clockwise COS triangle v (3, 2)."""
    for e in range(3):
        a = e
        b = (e + 1) % 3
        c = ((v[b, 0] - v[a, 0]) * (py - v[a, 1]) - (v[b, 1] - v[a, 1]) * (px - v[a, 0]))
        if c < 0.0:
            return False
    return True



@njit(cache=True, nogil=True, inline="always")
def robust_area(ar, v):  # pragma: no cover - numba
    """Whether twice the signed area ``ar`` of the COS triangle v (3, 2) exceeds 1e-9 times
    the product of its two edges from vertex 0 (a triangle not seen edge-on). Squared: the
    lists' early z and the resolution's occluders ask it per entry, and libm hypot calls
    showed in their profiles."""
    ax = v[1, 0] - v[0, 0]
    ay = v[1, 1] - v[0, 1]
    bx = v[2, 0] - v[0, 0]
    by = v[2, 1] - v[0, 1]
    return ar * ar > 1e-18 * (ax * ax + ay * ay) * (bx * bx + by * by)


@njit(cache=True, nogil=True, inline="always")
def triangle_holds(v, r, rv, rr):  # pragma: no cover - numba
    """Whether the COS triangle v (3, 2) with motion radii r (3,) holds the grown offset
    region (hull of the squares (rv (4, 2), rr (4,))) for every between-sample direction.

    Every corner square lies inside each edge's line by more than that edge's motion (the
    larger of its ends' radii, in the L1 support of the edge normal), so the region is inside
    the triangle and meets no edge's capsule: then, as the directions move, the moving region
    never meets the moving boundary and stays inside (the argument of ``resolve._covers_q``)."""
    ar = area2(v)
    if not robust_area(ar, v):
        return False
    s = 1.0 if ar > 0.0 else -1.0
    for a in range(3):
        b = (a + 1) % 3
        # Inward normal of the edge a -> b.
        nx = -s * (v[b, 1] - v[a, 1])
        ny = s * (v[b, 0] - v[a, 0])
        l1 = abs(nx) + abs(ny)
        c = nx * v[a, 0] + ny * v[a, 1] + max(r[a], r[b]) * l1
        for k in range(4):
            if not nx * rv[k, 0] + ny * rv[k, 1] - rr[k] * l1 > c:
                return False
    return True


@njit(cache=True, nogil=True, inline="always")
def _outside_edge(ax, ay, bx, by, rad, rv, rr):  # pragma: no cover - numba
    """Whether some corner square of the region (rv (4, 2), rr (4,)) comes within ``rad`` of
    the line of the counter-clockwise edge a -> b, or lies beyond it (L1 support of the
    edge normal)."""
    nx = ay - by
    ny = bx - ax
    l1 = abs(nx) + abs(ny)
    c = nx * ax + ny * ay + rad * l1
    for k in range(4):
        if not nx * rv[k, 0] + ny * rv[k, 1] - rr[k] * l1 > c:
            return True
    return False


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def quad_holds(tv, tr, tid, cv, cr, cid, rv, rr):  # pragma: no cover - numba
    """Whether COS triangles T (tv (3, 2), motion radii tr (3,), welded vertex ids tid (3,))
    and C (cv, cr, cid), fused along an edge they share (two ids in common, C on the far
    side of it), together hold the grown offset region (rv, rr) for every between-sample
    direction.

    The region lies inside each of the pair's four outer edges by more than that edge's
    motion: their capsules miss it and, at the pixel centre, it is inside the quad. Taken
    counter-clockwise each, the two triangles traverse the shared edge in opposite
    directions, so the winding number of the outer edges around a point is the number of
    the two holding it; no outer edge comes near the region as the directions move, so it
    stays 1 there: every point of the region is held by T or C (``resolve._covers_q``'
    argument for a fused group)."""
    su = -1
    sv = -1
    for a in range(3):
        if tid[a] < 0 or cid[a] < 0:
            return False
        for b in range(3):
            if tid[a] == cid[b]:
                if su < 0:
                    su = a
                else:
                    sv = a
    if sv < 0:
        return False
    ar = area2(tv)
    if not robust_area(ar, tv):
        return False
    if not robust_area(area2(cv), cv):
        return False
    # T counter-clockwise: u -> v -> o with {u, v} the shared vertices.
    o = 3 - su - sv
    if ar > 0.0:
        u, v = (su, sv) if (su + 1) % 3 == sv else (sv, su)
    else:
        u, v = (su, sv) if (su + 2) % 3 == sv else (sv, su)
    # C's vertex off the shared edge, strictly on the right of u -> v.
    co = 0
    while co < 3 and (cid[co] == tid[u] or cid[co] == tid[v]):
        co += 1
    if co == 3:
        return False
    ux, uy = tv[u, 0], tv[u, 1]
    vx, vy = tv[v, 0], tv[v, 1]
    ox, oy = cv[co, 0], cv[co, 1]
    if not (vx - ux) * (oy - uy) - (vy - uy) * (ox - ux) < 0.0:
        return False
    # The outer edges, counter-clockwise: u -> co -> v (C's), v -> o -> u (T's).
    if _outside_edge(ux, uy, ox, oy, max(tr[u], cr[co]), rv, rr):
        return False
    if _outside_edge(ox, oy, vx, vy, max(cr[co], tr[v]), rv, rr):
        return False
    if _outside_edge(vx, vy, tv[o, 0], tv[o, 1], max(tr[v], tr[o]), rv, rr):
        return False
    return not _outside_edge(tv[o, 0], tv[o, 1], ux, uy, max(tr[o], tr[u]), rv, rr)
