"""Progressive visibility resolution per pixel (paper Alg. 1, Sec. 4.4), as numba kernels.

Each pixel walks its list front to back. A triangle Q not yet known to be visible gets its COS
region K (its grown COS image clipped to the grown offsets, ``space.region_polygon``); K empty
means Q is not seen at this pixel at all (Alg. 1 ln 12). Otherwise Q is tested against each
occluder, a group of triangles fused along shared edges:

* Silhouette test (ln 17-28): the occluder's *active* edges are its silhouette (edges shared by
  two fused triangles are set inactive, ln 40). If any active edge's capsule (the hull of its two
  end squares, ``space``) meets K, the silhouette may cross Q under some offset and some
  between-sample direction: not covered, next occluder.
* Reference point (ln 31-32): with no silhouette near K, K lies wholly inside or wholly outside
  the occluder under every offset and delta, and one point of K (its centroid) decides: the
  winding number of the active edges around it, which counts the group's triangles holding it
  (see below), is at least one. Inside:
  Fig. 8 cases (a) Q inside the occluder and (b) inside it within C_Delta. Outside: cases (e)
  and (f), disjoint (within C_Delta). Cases (c) and (d), the occluder inside Q (within C_Delta),
  put silhouette edges inside K and are caught by the silhouette test. (The paper needs its
  occluder reference points for (c)/(d) because it only tests silhouette crossings; testing
  every active edge against K covers them directly.)
* Depth (ln 33-36): every occluder triangle T that can cover part of K (its grown bounding box
  meets K's) must be in front of Q for *every* offset and direction: all camera positions of the
  view strictly on one side of T's plane and all of Q on the other (or on the plane itself,
  with some of Q strictly beyond: Q's points on the plane are met at T's own depth, a set of
  rays of no measure, as where a back face meets a front face along the silhouette). Then any
  ray from a camera position to a point of Q crosses T's plane between the two, and where the
  ray meets T at all it meets it there, in front of Q. This is exact for the non-penetrating
  case the paper assumes and stays conservative for penetrating, coplanar or near-camera
  triangles, which the paper's single reference-point depth comparison does not.

An occluder's union covers K under every delta because the winding number of its silhouette
around a point of K cannot change while no silhouette edge comes near it, and fused triangles
are oriented consistently (both counter-clockwise in the COS, sharing the edge in opposite
directions), so a winding number of one at delta = 0 means covered for every delta.

Only a triangle found visible (or known visible) becomes an occluder that later entries are
tested against (ln 37-47). It is fused with every occluder triangle that shares one of its
edges (welded vertex ids), merging their groups. A group whose silhouette stays clear of the
whole offset region and covers it is flagged *coverall* (ln 44-45): later triangles skip
straight to the depth test.

Sub-pixels (``Screen.refine``, ``_refined_hide``): an entry no group hides over the whole pixel
may be tested again at the pixel's 2 x 2 sub-pixels, each split again where none hides it;
hidden at every one (by any group each), it is hidden at the pixel, whose directions they make
up. A silhouette capsule's growth is the pixel's half-width times the edge's depth difference
to Q, so far occludees beside near silhouettes (a skyline) fail the pixel's test where a
sub-pixel's passes. The same walk takes a busy tile's samples of b x b pixels
(``TileLists.block``) down to single pixels, log2 b levels before ``refine``'s own. With
separate groups (``fusion="groups"``), a sub-pixel no group hides alone is tried with the
groups together (``_fused_sub``), as a pixel is (``_fused_hide``): two walls, one ending where
the other begins behind it, overlap in the offsets by less than a pixel's capsules.

A triangle hidden by a coverall group is dropped. One hidden by another group, or not seen at
the pixel (K empty, ln 12), is kept *dormant*: it joins the edge hash and fuses with its
neighbours, but a group made only of dormant triangles is never tested against (nor checked
for coverall, nor given a depth grid); once it fuses with a tested group, the merged group is
tested. Dormant triangles only close the silhouettes of the surfaces they border: without
them a visible triangle whose neighbour across an edge is hidden keeps that edge on its
silhouette, and the surface behind it leaks through (leaving hidden triangles out entirely,
as the paper does, loosens the answer far more than keeping them dormant: docs/cores/cos.md).

Why this stays conservative. Hiding is decided only by ``_covers_q`` and ``_hides`` on some
group, and both are sound for any set of listed triangles fused along shared edges with
consistent orientation: the winding-number argument below and the per-triangle depth test
hold whatever triangles the group holds. Leaving a triangle out of every group, or leaving a
group untested, can only make a later entry's test fail, never succeed wrongly. Nothing is
lost in tightness either where the left-out triangle Q is hidden: for every offset and
direction of the pixel that reaches Q, a group in front of Q is met first, so whatever Q
would hide lies behind those groups too; what is lost is fusion (the cover test asks a single
group to cover K, and Q may have joined two of them or closed a silhouette), which is why
hidden triangles stay dormant rather than dropped.
Hulls (moving triangles, spheres) are occludees only; a triangle seen edge-on in the COS (no
robust area) does not occlude, nor does one a client's near plane can cut (``solid`` false:
it comes within ``prims.NEAR_CLEARANCE`` of the cell, and a client standing there sees through
it).

Cost (issue 13; dense clutter gives lists of 10^5 entries): nothing per entry scales with the
number of groups or with a group's triangle count in the common cases.

* Fusion finds the neighbour across an edge through the tile's edge slots: each undirected
  welded edge of the tile's items gets one, once per tile (a hash per pixel over its list,
  as before, cost more than the rest of an insertion: its tables left the cache), and a
  pixel chains its occluder edges per slot; groups merge smaller into larger; each keeps its
  active edges in one block of an edge pool (``groups.EdgePool``), so the cover test walks
  the silhouette, not the triangles, in memory order (chasing a linked list through the
  pixel's occluders stalled on every edge).
* Only live groups (not coverall, not merged away) are tried, oldest first.
* Early z (paper Sec. 5): when a group becomes coverall, every ray of the pixel meets it no
  deeper than zcut, the deepest vertex of its triangles that can reach the offset region (valid
  when those lie beyond every camera position). An entry wholly deeper is hidden without a
  test; and since a point at distance g from the box is at depth >= g / |(s, 1)| on any ray of
  the pixel, and the lists are sorted by that distance (``prims.distance_order``), the rest of
  the list is cut once it passes zcut |(s, 1)|.
* Depth shortcuts: a group that covers K and lies wholly nearer than Q (and beyond the cameras)
  hides it by the same argument, without the per-triangle plane test. Groups of ``GRID_MIN``
  triangles or more keep a grid over the offset region (in a frame moving with their own
  depth) with per-cell depth ranges and member lists: the shortcut then holds per cell around
  K, and the plane test walks only the members listed there.
* A primitive found visible at one pixel of a tile is not tested again in that tile's later
  pixels (still an occluder), as for those known from earlier views.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.borrow import NO_REFCOUNT, borrow, keep_alive
from visibility.cancel import flag_set
from visibility.cores.cos.groups import (
    EdgePool,
    Marks,
    PrimArrays,
    Screen,
    ShareScratch,
    TileLists,
)
from visibility.cores.cos.lists import region_at
from visibility.cores.cos.space import (
    MAX_POLY,
    area2,
    bbox,
    capsule_meets,
    clip_halfplane,
    load_prim,
    polygon_axes,
    polygon_centroid,
    project,
    region_polygon,
    robust_area,
    tri_normal,
    winding_step,
)
from visibility.cycles import cycles
from visibility.planar import convex_hull
from visibility.shares import run_shares


@njit(cache=True, nogil=True, inline="always")
def _k_box(kx, ky, nk, kb):  # pragma: no cover - numba
    """K's box and centroid (kb (7,): x0, x1, y0, y1, cx, cy, axes ready); the edge axes
    (``polygon_axes``) are left for the first silhouette test that needs them."""
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    cx = 0.0
    cy = 0.0
    for i in range(nk):
        x0 = min(x0, kx[i])
        x1 = max(x1, kx[i])
        y0 = min(y0, ky[i])
        y1 = max(y1, ky[i])
        cx += kx[i]
        cy += ky[i]
    kb[0] = x0
    kb[1] = x1
    kb[2] = y0
    kb[3] = y1
    kb[4] = cx / nk
    kb[5] = cy / nk
    kb[6] = 0.0


@njit(cache=True, nogil=True, inline="always")
def _load_depths(pts, first, n, origin, perm, sign, cam):  # pragma: no cover - numba
    """Load an occludee's n points into ``cam`` (camera coordinates, ``space.load_prim``) and
    return their least and mean depth w: the mean is the frame its region K is made in (Q
    barely moves there, and each occluder moves by its depth difference to Q)."""
    load_prim(pts, first, n, origin, perm, sign, cam)
    wmin = cam[0, 2]
    wsum = cam[0, 2]
    for c in range(1, n):
        wmin = min(wmin, cam[c, 2])
        wsum += cam[c, 2]
    return wmin, wsum / n


@njit(cache=True, nogil=True, inline="always")
def _occludee_k(qv, qr, n, tri, corners, sx, sy, h, wref, rv, rr, kx, ky, tx, ty,
                kb):  # pragma: no cover - numba
    """An occludee's region K at pixel (sx, sy), half-width h, in the frame of depth ``wref``:
    its images (qv, qr) clipped to the pixel's grown offsets (rv, rr, set here); K's corners to
    (kx, ky), its box and centroid to ``kb`` (``_k_box``) where it is not empty. Returns K's
    corner count (0: no ray of the pixel meets the occludee)."""
    region_at(corners, sx, sy, h, wref, rv, rr)
    nk = region_polygon(qv, qr, n, tri, rv, rr, kx, ky, tx, ty)
    if nk > 0:
        _k_box(kx, ky, nk, kb)
    return nk


#: Layout of a test's Q context (``qctx``, float64): whether the relaxed edge tests may be
#: used, Q's plane (camera coordinates: normal, offset, tolerance), the pixel centre, the frame
#: of the region polygon, the witness state and point, Q's pixel-centre COS corners.
QC_RELAX = 0
QC_PLANE = 1
QC_TOL = 5
QC_SX = 6
QC_SY = 7
QC_FRAME = 8
QC_WIT = 9
QC_WX = 10
QC_WY = 11
QC_V = 12
QC_DX = 18
QC_DY = 19
QC_SEEN = 20
QC_W = 21
QC_WREF = 24
QC_CW = 25
QC_CXY = 29
QC_H = 37
QC_SIZE = 38


@njit(cache=True, nogil=True, inline="always")
def _q_context(qctx, cam, n, tri, qv, sx, sy, h, fr, wmin, wcam, tol,
               corners):  # pragma: no cover - numba
    """Fill ``qctx`` (``QC_*``) for occludee Q (camera points ``cam``, pixel-centre COS
    ``qv``): the relaxed tests need a triangle beyond every camera position with a plane."""
    qctx[QC_RELAX] = 0.0
    qctx[QC_WIT] = 0.0
    qctx[QC_SX] = sx
    qctx[QC_SY] = sy
    qctx[QC_FRAME] = fr
    if not tri:
        return
    nx, ny, nz, nn = tri_normal(cam)
    if not nn > 0.0:
        return
    qctx[QC_PLANE] = nx
    qctx[QC_PLANE + 1] = ny
    qctx[QC_PLANE + 2] = nz
    qctx[QC_PLANE + 3] = nx * cam[0, 0] + ny * cam[0, 1] + nz * cam[0, 2]
    qctx[QC_TOL] = tol * nn
    for c in range(3):
        qctx[QC_V + 2 * c] = qv[c, 0]
        qctx[QC_V + 2 * c + 1] = qv[c, 1]
        qctx[QC_W + c] = cam[c, 2]
    qctx[QC_WREF] = (cam[0, 2] + cam[1, 2] + cam[2, 2]) / 3.0
    for a in range(4):
        qctx[QC_CW + a] = corners[a, 2]
        qctx[QC_CXY + 2 * a] = corners[a, 0]
        qctx[QC_CXY + 2 * a + 1] = corners[a, 1]
    qctx[QC_H] = h
    qctx[QC_SEEN] = -1.0
    if wmin > wcam + tol:
        qctx[QC_RELAX] = 1.0


#: Points whose hull bounds a pixel's between-sample directions (``_directions``): from each
#: of the camera rectangle's 4 corners to each of Q's 3. Witness scratch ``wpt`` holds them and
#: their hull: (3 DIR_PTS, 2).
DIR_PTS = 12


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _directions(qctx, ws, wpt):  # pragma: no cover - numba
    """The between-sample directions under which some camera position sees Q (Q beyond them
    all): the directions from the rectangle's corners to Q's form a convex polygon (the image
    of the convex set rectangle x Q under the perspective map), clipped to the pixel's square.
    ``QC_SEEN`` 0 when it has no area (no ray of the pixel meets Q), else its centroid, a
    delta at which S(delta) has an interior, goes to ``QC_DX``, ``QC_DY``."""
    sx = qctx[QC_SX]
    sy = qctx[QC_SY]
    h = qctx[QC_H]
    pts = wpt[:DIR_PTS]
    m = np.int64(0)  # not a literal 0: the callees are compiled for one type (``_resolve_share``)
    for i in range(3):
        wi = qctx[QC_W + i]
        xi = qctx[QC_V + 2 * i] + wi * sx
        yi = qctx[QC_V + 2 * i + 1] + wi * sy
        for j in range(4):
            dw = wi - qctx[QC_CW + j]
            pts[m, 0] = (xi - qctx[QC_CXY + 2 * j]) / dw - sx
            pts[m, 1] = (yi - qctx[QC_CXY + 2 * j + 1]) / dw - sy
            m += 1
    hull = wpt[DIR_PTS:]
    nh = convex_hull(pts, m, hull)
    dx = ws[0]
    dy = ws[1]
    tx = ws[2]
    ty = ws[3]
    for i in range(nh):
        dx[i] = hull[i, 0]
        dy[i] = hull[i, 1]
    # Clip to the pixel's square (grown by a rounding margin).
    g = h * (1.0 + 1e-9) + 1e-15
    nh = clip_halfplane(dx, dy, nh, 1.0, 0.0, g, tx, ty)
    nh = clip_halfplane(tx, ty, nh, -1.0, 0.0, g, dx, dy)
    nh = clip_halfplane(dx, dy, nh, 0.0, 1.0, g, tx, ty)
    nh = clip_halfplane(tx, ty, nh, 0.0, -1.0, g, dx, dy)
    qctx[QC_SEEN] = 0.0
    if nh < 3:
        return
    ar, cx, cy = polygon_centroid(dx, dy, nh)
    if not abs(ar) > 1e-12 * h * h:
        return
    qctx[QC_SEEN] = 1.0
    qctx[QC_DX] = cx
    qctx[QC_DY] = cy


@njit(cache=True, nogil=True, inline="always")
def _q_extent(nx, ny, qctx):  # pragma: no cover - numba
    """The extent (lo, hi) of Q's pixel-centre COS triangle along the axis (nx, ny)."""
    qlo = np.inf
    qhi = -np.inf
    for c in range(3):
        d = nx * qctx[QC_V + 2 * c] + ny * qctx[QC_V + 2 * c + 1]
        qlo = min(qlo, d)
        qhi = max(qhi, d)
    return qlo, qhi


@njit(cache=True, nogil=True, inline="always")
def _tri_off_q(r, ov, qctx):  # pragma: no cover - numba
    """Whether occluder triangle r's pixel-centre COS triangle and Q's have disjoint interiors
    (an edge normal of either separates them, touching allowed up to rounding)."""
    scale = 1e-9 * (abs(ov[r, 0, 0]) + abs(ov[r, 0, 1]) + abs(qctx[QC_V]) + abs(qctx[QC_V + 1])
                    + 1.0)
    for e in range(6):
        if e < 3:
            ax = ov[r, e, 0]
            ay = ov[r, e, 1]
            bx = ov[r, (e + 1) % 3, 0]
            by = ov[r, (e + 1) % 3, 1]
        else:
            ax = qctx[QC_V + 2 * (e - 3)]
            ay = qctx[QC_V + 2 * (e - 3) + 1]
            bx = qctx[QC_V + 2 * ((e - 2) % 3)]
            by = qctx[QC_V + 2 * ((e - 2) % 3) + 1]
        nx = by - ay
        ny = ax - bx
        ln = abs(nx) + abs(ny)
        if ln == 0.0:
            continue
        tlo = np.inf
        thi = -np.inf
        for c in range(3):
            d = nx * ov[r, c, 0] + ny * ov[r, c, 1]
            tlo = min(tlo, d)
            thi = max(thi, d)
        qlo, qhi = _q_extent(nx, ny, qctx)
        tol = scale * ln
        if thi <= qlo + tol or qhi <= tlo + tol:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _seg_off_triangle(ax, ay, bx, by, qctx):  # pragma: no cover - numba
    """Whether segment ab stays off the interior of Q's pixel-centre COS triangle (it may touch
    its boundary): some axis (Q's edge normals, the segment's normal) separates them, touching
    allowed up to rounding."""
    scale = 1e-9 * (abs(ax) + abs(ay) + abs(bx) + abs(by) + 1.0)
    for e in range(4):
        if e < 3:
            i0 = QC_V + 2 * e
            i1 = QC_V + 2 * ((e + 1) % 3)
            nx = qctx[i1 + 1] - qctx[i0 + 1]
            ny = qctx[i0] - qctx[i1]
        else:
            nx = by - ay
            ny = ax - bx
        ln = abs(nx) + abs(ny)
        if ln == 0.0:
            continue
        qlo, qhi = _q_extent(nx, ny, qctx)
        da = nx * ax + ny * ay
        db = nx * bx + ny * by
        tol = scale * ln
        if max(da, db) <= qlo + tol or min(da, db) >= qhi - tol:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _cross_moved(ax, ay, aw, bx, by, bw, dx, dy):  # pragma: no cover - numba
    """Cross product of two COS vectors (ax, ay) and (bx, by), of depth differences aw and bw,
    seen at delta (dx, dy) off the pixel's centre: each moves by -depth x delta. It is linear
    in the delta (the products of two delta terms cancel)."""
    return (ax - aw * dx) * (by - bw * dy) - (ay - aw * dy) * (bx - bw * dx)


@njit(cache=True, nogil=True, inline="always")
def _corner_out(ax, ay, wa, bx, by, wb, qctx):  # pragma: no cover - numba
    """Whether edge ab, one of whose end points is a corner V of Q (the same COS point and
    depth), leaves Q's image at V outwards under every delta of the pixel: its image never
    enters Q's, whatever the delta (a column's side edge below the corner of its top).

    At delta d a vector of COS offset (x, y) and depth difference w is seen as (x, y) - w d,
    so the cross products of the edge's direction with Q's two edges at V, and of those two,
    are linear in d: their signs at the pixel's four corner deltas bound them over all of
    it. Q's corner spans the cone of its two edges (a constant orientation, else no answer);
    the edge stays out of the cone's interior where one cross product with it is never
    positive in that orientation, and then out of Q's image, a triangle inside the cone.
    Exact end points only, and a margin against rounding: a near miss is left to the other
    tests."""
    h = qctx[QC_H]
    for end in range(2):
        px, py, pw = (ax, ay, wa) if end == 0 else (bx, by, wb)
        ex, ey, ew = (bx - ax, by - ay, wb - wa) if end == 0 else (ax - bx, ay - by, wa - wb)
        for c in range(3):
            if (px != qctx[QC_V + 2 * c] or py != qctx[QC_V + 2 * c + 1]
                    or pw != qctx[QC_W + c]):
                continue
            c1 = (c + 1) % 3
            c2 = (c + 2) % 3
            ux = qctx[QC_V + 2 * c1] - px
            uy = qctx[QC_V + 2 * c1 + 1] - py
            uw = qctx[QC_W + c1] - pw
            vx = qctx[QC_V + 2 * c2] - px
            vy = qctx[QC_V + 2 * c2 + 1] - py
            vw = qctx[QC_W + c2] - pw
            lu = abs(ux) + abs(uy) + abs(uw) * h
            lv = abs(vx) + abs(vy) + abs(vw) * h
            le = abs(ex) + abs(ey) + abs(ew) * h
            tol = 1e-9
            o_pos = True
            o_neg = True
            for k in range(4):
                dx = h if k & 1 else -h
                dy = h if k & 2 else -h
                o = _cross_moved(ux, uy, uw, vx, vy, vw, dx, dy)
                o_pos = o_pos and o > tol * lu * lv
                o_neg = o_neg and o < -tol * lu * lv
            if not (o_pos or o_neg):
                return False
            sg = 1.0 if o_pos else -1.0
            out_u = True
            out_v = True
            for k in range(4):
                dx = h if k & 1 else -h
                dy = h if k & 2 else -h
                out_u = out_u and sg * _cross_moved(ux, uy, uw, ex, ey, ew, dx, dy) < -tol * lu * le
                out_v = out_v and sg * _cross_moved(ex, ey, ew, vx, vy, vw, dx, dy) < -tol * lv * le
            return out_u or out_v
    return False


@njit(cache=True, nogil=True, inline="always")
def _on_q_plane(x, y, w, qctx):  # pragma: no cover - numba
    """Whether the camera-space point (x, y, w) lies in Q's plane (within its tolerance)."""
    d = (qctx[QC_PLANE] * x + qctx[QC_PLANE + 1] * y + qctx[QC_PLANE + 2] * w
         - qctx[QC_PLANE + 3])
    return abs(d) <= qctx[QC_TOL]


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _witness(qctx, rv, ws, wpt):  # pragma: no cover - numba
    """A point inside S(delta0), the offsets whose ray in direction s + delta0 meets Q (Q's COS
    triangle clipped to the camera rectangle's image, both moved to delta0 in the frame of
    depth wref), kept in ``qctx`` (QC_WIT 1; -1 when it has no robust interior). delta0 is
    ``_directions``' centroid; ``ws``, ``wpt``: scratch as there."""
    wx = ws[0]
    wy = ws[1]
    wtx = ws[2]
    wty = ws[3]
    # S(delta0) in the frame of depth wref: every point at depth w moves by -(w - wref) delta0.
    d0x = qctx[QC_DX]
    d0y = qctx[QC_DY]
    wr = qctx[QC_WREF]
    for c in range(3):
        wx[c] = qctx[QC_V + 2 * c] - (qctx[QC_W + c] - wr) * d0x
        wy[c] = qctx[QC_V + 2 * c + 1] - (qctx[QC_W + c] - wr) * d0y
    m = np.int64(3)
    rq = wpt[:4]  # the camera rectangle moved to delta0 (``_directions``' points are spent)
    for a in range(4):
        rq[a, 0] = rv[a, 0] - (qctx[QC_CW + a] - wr) * d0x
        rq[a, 1] = rv[a, 1] - (qctx[QC_CW + a] - wr) * d0y
    s = 1.0 if polygon_centroid(rq[:, 0], rq[:, 1], 4)[0] >= 0.0 else -1.0
    for a in range(4):
        b = (a + 1) % 4
        nx = s * (rq[b, 1] - rq[a, 1])
        ny = s * (rq[a, 0] - rq[b, 0])
        if nx == 0.0 and ny == 0.0:
            continue
        m = clip_halfplane(wx, wy, m, nx, ny, nx * rq[a, 0] + ny * rq[a, 1], wtx, wty)
        for i in range(m):
            wx[i] = wtx[i]
            wy[i] = wty[i]
        if m == 0:
            break
    qctx[QC_WIT] = -1.0
    if m < 3:
        return
    ar, cx, cy = polygon_centroid(wx, wy, m)
    span = 0.0
    for i in range(m):
        span = max(span, abs(wx[i] - wx[0]) + abs(wy[i] - wy[0]))
    if not abs(ar) > 1e-12 * span * span or span == 0.0:
        return
    qctx[QC_WIT] = 1.0
    qctx[QC_WX] = cx
    qctx[QC_WY] = cy


@njit(cache=True, nogil=True, inline="always")
def _wind_in(g, edges, wref, d0x, d0y, cx, cy):  # pragma: no cover - numba
    """Whether (cx, cy) lies inside group g's silhouette (``edges``, ``groups.EdgePool``) at
    delta (d0x, d0y) in the frame of depth wref (winding number >= 1; a point on an edge, up
    to rounding, is not inside)."""
    geo = edges.geo
    wn = 0
    i0 = edges.start[g]
    for i in range(i0, i0 + edges.length[g]):
        ax = geo[i, 0] - (geo[i, 4] - wref) * d0x
        ay = geo[i, 1] - (geo[i, 4] - wref) * d0y
        bx = geo[i, 2] - (geo[i, 5] - wref) * d0x
        by = geo[i, 3] - (geo[i, 5] - wref) * d0y
        step = winding_step(ax, ay, bx, by, cx, cy)
        if step == 2:
            return False
        wn += step
    return wn >= 1


@njit(cache=True, nogil=True, inline="always")
def _edge_first(i, i0, edges):  # pragma: no cover - numba
    """Swap record i of a block (``groups.EdgePool``) with its first, i0: the edge that just
    ended a cover walk is the first the block's next walk meets (the next test is often of a
    like region, which the same edge fails)."""
    if i == i0:
        return
    geo, enode, pos = edges.geo, edges.node, edges.pos
    for c in range(6):
        t = geo[i, c]
        geo[i, c] = geo[i0, c]
        geo[i0, c] = t
    na = enode[i]
    nb = enode[i0]
    enode[i] = nb
    enode[i0] = na
    pos[nb] = i
    pos[na] = i0


@njit(cache=True, nogil=True, inline="always")
def _covers_q(g, edges, gbb, gwlo, gwhi, wref, h, kx, ky, nk, kb, knx, kny,
              klo, khi, qctx, rpoly, nrp, rpb, rv, ws, wpt,
              work):  # pragma: no cover - numba
    """Whether group g covers polygon K (frame of depth wref; ``_k_box`` geometry) under
    every offset in it and every delta: K's box inside the group's, no active edge capsule
    meeting K, and a winding number of at least one of the active edges (the silhouette)
    around K's centroid.

    The active edges are walked in the group's block of ``edges`` (``groups.EdgePool``), in
    memory order, so the cost is the silhouette's length, not the group's triangle count.
    Fused triangles are counter-clockwise and hold their shared edges in opposite
    directions, so the active edges' winding number around a point is the number of the
    group's triangles holding it; a crossing too close to call counts as not covered.
    ``work[0]`` counts the silhouette edges walked.

    With ``qctx[QC_RELAX]`` set (K is the region of an occludee Q, ``_q_context``), two more
    ways for a silhouette edge to pass when its capsule meets K (which is grown for the camera
    rectangle's motion in Q's frame, so an edge near the rectangle's edge fails there however
    far it stays from it):

    * the edge lies in Q's plane and off Q's interior: the parallel projection maps that plane
      the same way for every offset and direction, so its image never crosses Q's;
    * its capsule in a frame near the cameras (``QC_FRAME``) misses the camera rectangle's
      grown image there (``rpoly``): it never crosses the offsets at all.

    Either way the edge never crosses S(delta), the offsets whose ray in direction s + delta
    meets Q; no silhouette does, so S(delta) lies wholly inside or outside the group for each
    delta. The deltas where S(delta) has an interior form a convex set (the directions from
    the camera rectangle to Q, beyond it), so one witness point of S(delta0) inside the group
    at delta0 decides for all of them (``_directions``, ``_witness``; where no direction of
    the pixel reaches Q, no ray does and Q is covered vacuously). With no relaxed edge, K's
    centroid decides. ``ws`` (4, MAX_POLY) and ``wpt`` (3 DIR_PTS, 2): the witness's
    scratch."""
    if qctx[QC_RELAX] == 0.0:
        if kb[0] < gbb[g, 0] or kb[1] > gbb[g, 1] or kb[2] < gbb[g, 2] or kb[3] > gbb[g, 3]:
            return False
    else:
        # K may reach past the group where no ray of the pixel does, so its box cannot reject;
        # the witness can: outside the group's silhouette at delta0 (its box moved by delta0),
        # S(delta0) is not inside the group.
        if qctx[QC_SEEN] < 0.0:
            _directions(qctx, ws, wpt)
        if qctx[QC_SEEN] > 0.0:
            if qctx[QC_WIT] == 0.0:
                _witness(qctx, rv, ws, wpt)
            if qctx[QC_WIT] > 0.0:
                m = max(abs(gwlo[g] - wref), abs(gwhi[g] - wref))
                ex = m * abs(qctx[QC_DX])
                ey = m * abs(qctx[QC_DY])
                if (qctx[QC_WX] < gbb[g, 0] - ex or qctx[QC_WX] > gbb[g, 1] + ex
                        or qctx[QC_WY] < gbb[g, 2] - ey or qctx[QC_WY] > gbb[g, 3] + ey):
                    return False
                # Nor inside its silhouette there (a walk of cheap tests before the capsules;
                # where the strict test passes, the witness, inside K, is inside too).
                if not _wind_in(g, edges, wref, qctx[QC_DX], qctx[QC_DY], qctx[QC_WX],
                                qctx[QC_WY]):
                    return False
    if kb[6] == 0.0:
        polygon_axes(kx, ky, nk, kb, knx, kny, klo, khi)
        kb[6] = 1.0
    # The winding number around K's centroid is summed in the same walk: where no edge is
    # relaxed, it decides (a second walk would cost as much again).
    cx = kb[4]
    cy = kb[5]
    wn = 0
    on_edge = False
    relaxed = False
    geo = edges.geo
    i0 = edges.start[g]
    for i in range(i0, i0 + edges.length[g]):
        ax = geo[i, 0]
        ay = geo[i, 1]
        bx = geo[i, 2]
        by = geo[i, 3]
        wa = geo[i, 4]
        wb = geo[i, 5]
        rad = max(abs(wa - wref), abs(wb - wref)) * h
        work[0] += 1
        step = winding_step(ax, ay, bx, by, cx, cy)
        if step == 2:
            if qctx[QC_RELAX] == 0.0:
                _edge_first(i, i0, edges)
                return False
            on_edge = True
        else:
            wn += step
        if capsule_meets(ax, ay, bx, by, rad, kx, ky, nk, kb, knx, kny, klo, khi):
            if qctx[QC_RELAX] == 0.0:
                _edge_first(i, i0, edges)
                return False
            sx = qctx[QC_SX]
            sy = qctx[QC_SY]
            if (_on_q_plane(ax + wa * sx, ay + wa * sy, wa, qctx)
                    and _on_q_plane(bx + wb * sx, by + wb * sy, wb, qctx)
                    and _seg_off_triangle(ax, ay, bx, by, qctx)):
                relaxed = True
            elif _corner_out(ax, ay, wa, bx, by, wb, qctx):
                relaxed = True
            else:
                fr = qctx[QC_FRAME]
                rad0 = max(abs(wa - fr), abs(wb - fr)) * h
                if nrp > 0 and not capsule_meets(ax, ay, bx, by, rad0, rpoly[:, 0], rpoly[:, 1],
                                                 nrp, rpb, rpoly[:, 2], rpoly[:, 3],
                                                 rpoly[:, 4], rpoly[:, 5]):
                    relaxed = True
                else:
                    _edge_first(i, i0, edges)
                    return False
    if not relaxed:
        return not on_edge and wn >= 1
    if qctx[QC_SEEN] < 0.0:
        _directions(qctx, ws, wpt)
    if qctx[QC_SEEN] == 0.0:
        return True  # no ray of the pixel meets Q: covered, vacuously
    if qctx[QC_WIT] == 0.0:
        _witness(qctx, rv, ws, wpt)
    if qctx[QC_WIT] < 0.0:
        return False
    # The silhouette at the witness's delta (frame of depth wref).
    return _wind_in(g, edges, wref, qctx[QC_DX], qctx[QC_DY], qctx[QC_WX], qctx[QC_WY])


@njit(cache=True, nogil=True, inline="always")
def _front_of(r, obb, owr, ouse, oplane, wref, h, kx0, kx1, ky0, ky1, qcam,
              nq, ov, qctx, wq, wcam, ztol, work):  # pragma: no cover - numba
    """Whether occluder triangle r cannot reach K's box or is in front of all of Q (nearest
    depth wq; cameras at depths up to wcam, depths compared with tolerance ztol), or lies in
    Q's plane without overlapping it (``_tri_off_q``) (``work[1]`` counts the calls)."""
    work[1] += 1
    grow = max(abs(owr[r, 0] - wref), abs(owr[r, 1] - wref)) * h
    if (obb[r, 1] + grow < kx0 or obb[r, 0] - grow > kx1 or obb[r, 3] + grow < ky0
            or obb[r, 2] - grow > ky1):
        return True
    # Wholly nearer than Q's nearest point and beyond every camera: a ray from a camera meets
    # r, where it does, at a smaller depth than any point of Q, whatever r's slant (its
    # plane may still cut Q's, which fails the plane test below).
    if owr[r, 1] + ztol < wq and owr[r, 0] >= wcam + ztol:
        return True
    if not ouse[r]:
        return False
    nx, ny, nz, d, tol = oplane[r, 0], oplane[r, 1], oplane[r, 2], oplane[r, 3], oplane[r, 4]
    # Behind or on the plane, strictly behind somewhere: the rays that meet Q on T's plane
    # meet T at the same point, a set of no measure (a shared edge).
    behind = False
    for i in range(nq):
        dist = nx * qcam[i, 0] + ny * qcam[i, 1] + nz * qcam[i, 2] - d
        if dist > tol:
            return False
        if dist < -tol:
            behind = True
    if not behind and nq == 3 and qctx[QC_RELAX] != 0.0:
        # Q lies in T's plane: a ray meets that plane once, so where T and Q do not overlap
        # no ray that meets Q meets T (beyond a set of no measure): T cannot be what hides Q,
        # and the others must.
        return _tri_off_q(r, ov, qctx)
    return behind


# A call: inlined, its copies make the kernel slow to compile.
@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _in_front(g, head, nxt, obb, owr, ouse, oplane, wref, h, kx0, kx1, ky0, ky1, qcam,
              nq, ov, qctx, wq, wcam, tol, work):  # pragma: no cover - numba
    """Whether every triangle of group g that can reach K's box is in front of all of Q."""
    r = head[g]
    while r >= 0:
        if not _front_of(r, obb, owr, ouse, oplane, wref, h, kx0, kx1, ky0, ky1, qcam, nq, ov,
                         qctx, wq, wcam, tol, work):
            return False
        r = nxt[r]
    return True


#: Depth grid of a large occluder group: GRID x GRID cells over the pixel's offset region,
#: each with the depth range of the group's triangles that can reach it and a list of them,
#: in the frame moving with a depth inside the group's range (so a compact group's triangles
#: barely move and stay in few cells); groups of at least GRID_MIN triangles get one. A
#: triangle over more than GRID_WIDE cells goes to the grid's list of wide ones instead.
GRID = 16
GRID_MIN = 32
#: Column of a grid's row of ``shead`` holding the last member entered (``_grid_sync``), and
#: its value for a grid not built yet.
GRID_CURSOR = GRID * GRID + 2
GRID_NEW = -2
#: Entries of one pixel's list between two polls of the stop flag.
STOP_EVERY = 256
#: Columns of ``resolve_tiles``'s counters per tile: entries tested, found occluded, occluder
#: triangles, cut by early z, silhouette edges walked, plane tests, then CPU cycles testing,
#: inserting occluders and checking coverall in one entry of every TIME_STRIDE of a list,
#: and in the whole tile, then entries hidden by separate groups together, entries hidden at
#: sub-pixels and sub-pixels resolved (``_refined_hide``), then entries a hidden leaf box
#: spared their pixel, leaf boxes tested and found hidden (``_leaf_hidden``), then the parts
#: of the timed entries' cycles (``CYCLE_PARTS``, from column ``CYCLE_PART0``): the test's
#: region K, its single-group tests (cover and depth), its tests by separate groups, at
#: sub-pixels and at busy tiles' sub-samples, its leaf box; the insertion's set-up, its edge
#: slots (an item's first in the tile), its fusion along shared edges; then, from column
#: ``WALK0``, the sub-pixel walks (``_refined_hide``, at sub-pixels and busy tiles'
#: sub-samples) that ended with the entry seen, and the sub-pixels those resolved (the
#: others ended with it hidden: the entries hidden at sub-pixels).
N_COUNTERS = 26
CYCLE_PART0 = 16
WALK0 = 23
#: Column of the entries hidden by a group's part in front of them (``_front_part``).
FRONT_PARTS = 25
#: Per-tile counters the helpers add to (``ShareScratch.work``).
N_WORK = 8
CYCLE_PARTS = ("test_region", "test_groups", "test_subpixels", "test_leaf", "insert_setup",
               "insert_slots", "insert_fusion")
TIME_STRIDE = 8
GRID_WIDE = 16
#: Records of the edge pool (``groups.EdgePool``) per entry of the longest list: a pixel's
#: active edges take at most 3 per occluder, a block that grows takes twice its size anew,
#: so 9 always fit once the pool is compacted; the rest spares compactions.
EDGE_ROOM = 12


@njit(cache=True, nogil=True, inline="always")
def _cell(x, lo, inv):  # pragma: no cover - numba
    """Grid column (or row) of coordinate x: monotone in x, clamped to [0, GRID - 1]."""
    t = (x - lo) * inv
    if not t > 0.0:
        return 0
    if t >= GRID - 1:
        return GRID - 1
    return int(t)


@njit(cache=True, nogil=True, inline="always")
def _grid_add(slot, r, obb, owr, h, dom, sg, sfr, shead, pool,
              pdep):  # pragma: no cover - numba
    """Enter occluder triangle r (its pixel-centre box grown by its largest motion in the
    frame of depth sfr[slot]) in grid ``slot``: sg[slot, 0 / 1, cell] (depth range), shead
    [slot, cell] (member list; shead[slot, GRID^2] the wide ones) over the node pool
    (pool[0]: nodes used, pool[1]: capacity, then (triangle, next) pairs from pool[2]; pdep
    the depth range of each node's list from it to its end, ``_push``)."""
    grow = max(abs(owr[r, 0] - sfr[slot]), abs(owr[r, 1] - sfr[slot])) * h
    c0 = _cell(obb[r, 0] - grow, dom[0], dom[4])
    c1 = _cell(obb[r, 1] + grow, dom[0], dom[4])
    r0 = _cell(obb[r, 2] - grow, dom[2], dom[5])
    r1 = _cell(obb[r, 3] + grow, dom[2], dom[5])
    wide = (r1 - r0 + 1) * (c1 - c0 + 1) > GRID_WIDE
    for i in range(r0, r1 + 1):
        for j in range(c0, c1 + 1):
            c = i * GRID + j
            sg[slot, 0, c] = min(sg[slot, 0, c], owr[r, 0])
            sg[slot, 1, c] = max(sg[slot, 1, c], owr[r, 1])
            if not wide:
                _push(slot, c, r, shead, pool, pdep, owr)
    if wide:
        _push(slot, GRID * GRID, r, shead, pool, pdep, owr)


@njit(cache=True, nogil=True, inline="always")
def _push(slot, c, r, shead, pool, pdep, owr):  # pragma: no cover - numba
    """Prepend triangle r to list c of grid ``slot``; a full pool marks the grid's lists
    incomplete (shead[slot, GRID^2 + 1] = 1)."""
    k = pool[0]
    if k >= pool[1]:
        shead[slot, GRID * GRID + 1] = 1
        return
    pool[0] = k + 1
    pool[2 + 2 * k] = r
    nx = shead[slot, c]
    pool[3 + 2 * k] = nx
    # The deepest and the nearest vertex of this node's triangle and every one after it in the
    # list: a walk can stop where the rest all lie nearer than Q and beyond the cameras.
    hi = owr[r, 1]
    lo = owr[r, 0]
    if nx >= 0:
        hi = max(hi, pdep[2 * nx])
        lo = min(lo, pdep[2 * nx + 1])
    pdep[2 * k] = hi
    pdep[2 * k + 1] = lo
    shead[slot, c] = k


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _grid_sync(g, slot, head, nxt, obb, owr, gwlo, gwhi, h, dom, sg, sfr, shead, pool,
               pdep):  # pragma: no cover - numba
    """Bring group g's depth grid ``slot`` up to date: enter the members added since its last
    sync (a merge appends the smaller group's members after the survivor's, so they follow
    the last one entered, shead[slot, GRID_CURSOR]), or build it whole in the frame of the
    group's middle depth when it has none yet (cursor ``GRID_NEW``)."""
    cur = shead[slot, GRID_CURSOR]
    if cur == GRID_NEW:
        sg[slot, 0, :] = np.inf
        sg[slot, 1, :] = -np.inf
        shead[slot, :GRID_CURSOR] = -1
        shead[slot, GRID * GRID + 1] = 0
        sfr[slot] = 0.5 * (gwlo[g] + gwhi[g])
        r = head[g]
    else:
        r = nxt[cur]
    while r >= 0:
        _grid_add(slot, r, obb, owr, h, dom, sg, sfr, shead, pool, pdep)
        cur = r
        r = nxt[r]
    shead[slot, GRID_CURSOR] = cur


@njit(cache=True, nogil=True, inline="always")
def _hides(g, head, nxt, obb, owr, ouse, oplane, gwlo, gwhi, gslot, sg, sfr, shead, pool, pdep,
           dom, wcam, tol, wref, h, kb, qcam, nq, wq, ov, qctx, work):  # pragma: no cover
    """Whether group g, which covers K (box ``kb``), hides Q (nearest depth wq).

    Every ray of the pixel that meets Q meets g, at a point of one of g's triangles whose
    box, grown by its motion in the grid's frame f, meets K's box grown by |wref - f| h (the
    frame change; the triangle's growth in Q's frame is at most its growth in f plus that):
    at a depth no larger than that triangle's deepest vertex and, when the triangle lies
    beyond every camera position, on the ray itself. So g hides Q when all its triangles that
    can meet K are nearer than Q and beyond the cameras: checked on g's depth range, then on
    its depth grid's cells over K. Failing both, the per-triangle test (``_front_of``: the
    same depth argument for the triangle alone, then its plane) on the triangles listed in
    those cells, or on all of g's. A cell's list
    runs newest first, so roughly deepest first: its walk stops where every triangle left in
    it lies nearer than Q and beyond the cameras (the same depth argument per triangle; in
    dense clutter the lists hold hundreds of a surface's triangles in front of Q)."""
    if gwhi[g] + tol < wq and gwlo[g] >= wcam + tol:
        return True
    slot = gslot[g]
    if slot >= 0:
        _grid_sync(g, slot, head, nxt, obb, owr, gwlo, gwhi, h, dom, sg, sfr, shead, pool, pdep)
    if slot < 0:
        return _in_front(g, head, nxt, obb, owr, ouse, oplane, wref, h, kb[0], kb[1], kb[2],
                         kb[3], qcam, nq, ov, qctx, wq, wcam, tol, work)
    grow = abs(wref - sfr[slot]) * h
    c0 = _cell(kb[0] - grow, dom[0], dom[4])
    c1 = _cell(kb[1] + grow, dom[0], dom[4])
    r0 = _cell(kb[2] - grow, dom[2], dom[5])
    r1 = _cell(kb[3] + grow, dom[2], dom[5])
    zlo = np.inf
    zhi = -np.inf
    for i in range(r0, r1 + 1):
        for j in range(c0, c1 + 1):
            zlo = min(zlo, sg[slot, 0, i * GRID + j])
            zhi = max(zhi, sg[slot, 1, i * GRID + j])
    if zhi + tol < wq and zlo >= wcam + tol:
        return True
    if shead[slot, GRID * GRID + 1] != 0:
        return _in_front(g, head, nxt, obb, owr, ouse, oplane, wref, h, kb[0], kb[1], kb[2],
                         kb[3], qcam, nq, ov, qctx, wq, wcam, tol, work)
    # The cells around K, then the list of wide triangles.
    wc = c1 - c0 + 1
    nc = (r1 - r0 + 1) * wc
    for t in range(nc + 1):
        c = (r0 + t // wc) * GRID + c0 + t % wc if t < nc else GRID * GRID
        k = shead[slot, c]
        while k >= 0:
            if pdep[2 * k] + tol < wq and pdep[2 * k + 1] >= wcam + tol:
                break
            if not _front_of(pool[2 + 2 * k], obb, owr, ouse, oplane, wref, h, kb[0], kb[1],
                             kb[2], kb[3], qcam, nq, ov, qctx, wq, wcam, tol, work):
                return False
            k = pool[3 + 2 * k]
    return True


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _front_build(g, occ, front, wref, h, kb, qcam, nq, wq, wcam, tol,
                 work):  # pragma: no cover - numba
    """Write the part of group g in front of Q into ``front``'s scratch ``EdgePool`` (its
    group 0, box and depth range); whether there is one to test: some of g's triangles that
    can reach K's box ``kb`` are not in front of Q (``_front_of``), and some are.

    The part is g less those triangles: every triangle left can reach no ray that meets Q or
    is in front of Q along it. Its silhouette is g's active edges of the triangles left and
    the edges they were fused along with the ones left out (``ShareScratch.opart``); a
    subset of a group is oriented as the group is, so the winding argument of ``_covers_q``
    holds for it as it is, and the part takes the same cover tests as a group. ``occ``: the
    occluders (as ``_refined_hide``'s); ``front``: (ow, oact, opart, obad, part, pbb, pwlo,
    pwhi) of ``groups.ShareScratch`` and ``_covers_q``'s (rpoly, rpb, ws, wpt)."""
    head, nxt, obb, owr, ouse, oplane, ov = occ[0], occ[1], occ[2], occ[3], occ[4], occ[5], occ[6]
    qctx = occ[14]
    ow, oact, opart, obad, part, pbb, pwlo, pwhi = (front[0], front[1], front[2], front[3],
                                                    front[4], front[5], front[6], front[7])
    n_out = 0
    n_all = 0
    r = head[g]
    while r >= 0:
        out = not _front_of(r, obb, owr, ouse, oplane, wref, h, kb[0], kb[1], kb[2], kb[3],
                            qcam, nq, ov, qctx, wq, wcam, tol, work)
        obad[r] = out
        n_out += 1 if out else 0
        n_all += 1
        r = nxt[r]
    m = 0
    if 0 < n_out < n_all:
        geo = part.geo
        x0 = np.inf
        x1 = -np.inf
        y0 = np.inf
        y1 = -np.inf
        w0 = np.inf
        w1 = -np.inf
        r = head[g]
        while r >= 0:
            if not obad[r]:
                for e in range(3):
                    pe = opart[r, e]
                    if oact[r, e] or (pe >= 0 and obad[pe // 3]):
                        _edge_record(geo, m, r, e, ov, ow)
                        part.node[m] = m
                        part.pos[m] = m
                        m += 1
                x0 = min(x0, obb[r, 0])
                x1 = max(x1, obb[r, 1])
                y0 = min(y0, obb[r, 2])
                y1 = max(y1, obb[r, 3])
                w0 = min(w0, owr[r, 0])
                w1 = max(w1, owr[r, 1])
            r = nxt[r]
        pbb[0, 0] = x0
        pbb[0, 1] = x1
        pbb[0, 2] = y0
        pbb[0, 3] = y1
        pwlo[0] = w0
        pwhi[0] = w1
    part.start[0] = 0
    part.length[0] = m
    part.cap[0] = m
    r = head[g]
    while r >= 0:
        obad[r] = False
        r = nxt[r]
    return m > 0


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _front_part(g, occ, front, wref, h, hs, dx, dy, kx, ky, nk, kb, knx, kny, klo, khi, qcam,
                nq, wq, wcam, tol, nrp, rv, work):  # pragma: no cover - numba
    """Whether the part of group g in front of Q (``_front_build``) covers K on its own: g
    covers K but failed the depth test (``_hides``), some of its triangles that can reach K
    not lying in front of Q (a wall fused with a floor or wall that runs on behind Q). The
    cover test is the pixel's (``_covers_q``) with ``hs`` 0, a sub-pixel's of half-width
    ``hs`` centred ``(dx, dy)`` off the pixel's (``_covers_sub``) otherwise; the depth test
    is the pixel's."""
    if not _front_build(g, occ, front, wref, h, kb, qcam, nq, wq, wcam, tol, work):
        return False
    qctx = occ[14]
    part, pbb, pwlo, pwhi, rpoly, rpb, ws, wpt = (front[4], front[5], front[6], front[7],
                                                  front[8], front[9], front[10], front[11])
    if hs == 0.0:
        return _covers_q(0, part, pbb, pwlo, pwhi, wref, h, kx, ky, nk, kb, knx, kny, klo, khi,
                         qctx, rpoly, nrp, rpb, rv, ws, wpt, work)
    return _covers_sub(0, part, pbb, pwlo, pwhi, wref, hs, dx, dy, kx, ky, nk, kb, knx, kny,
                       klo, khi, work)


@njit(cache=True, nogil=True, inline="always")
def _near_k(g, gbb, gwlo, gwhi, wref, h, kb):  # pragma: no cover - numba
    """Whether group g's box, grown by its largest motion over the pixel (half-width h, frame
    of depth wref), meets K's box ``kb``: only such a group can cover a part of K."""
    m = max(abs(gwlo[g] - wref), abs(gwhi[g] - wref)) * h
    return not (kb[1] < gbb[g, 0] - m or kb[0] > gbb[g, 1] + m or kb[3] < gbb[g, 2] - m
                or kb[2] > gbb[g, 3] + m)


@njit(cache=True, nogil=True, inline="always")
def _covers_sub(g, edges, gbb, gwlo, gwhi, wref, hs, dx, dy, kx, ky, nk, kb, knx, kny, klo,
                khi, work):  # pragma: no cover - numba
    """``_covers_q``'s strict test at a sub-pixel: its centre ``(dx, dy)`` off the pixel's,
    half-width ``hs``, K (``kb``'s geometry, axes ready) in the pixel's frame of depth wref.

    In that frame a point of depth w sits at its pixel-centre image moved by
    -(w - wref) (dx, dy) at the sub-pixel's centre and moves by |w - wref| hs over its
    directions, so each active edge is moved and grown by that, and the winding argument
    of ``_covers_q`` holds as it is."""
    m = max(abs(gwlo[g] - wref), abs(gwhi[g] - wref))
    ex = m * abs(dx)
    ey = m * abs(dy)
    if (kb[0] < gbb[g, 0] - ex or kb[1] > gbb[g, 1] + ex or kb[2] < gbb[g, 2] - ey
            or kb[3] > gbb[g, 3] + ey):
        return False
    cx = kb[4]
    cy = kb[5]
    wn = 0
    geo = edges.geo
    i0 = edges.start[g]
    for i in range(i0, i0 + edges.length[g]):
        da = geo[i, 4] - wref
        db = geo[i, 5] - wref
        ax = geo[i, 0] - da * dx
        ay = geo[i, 1] - da * dy
        bx = geo[i, 2] - db * dx
        by = geo[i, 3] - db * dy
        work[0] += 1
        step = winding_step(ax, ay, bx, by, cx, cy)
        if step == 2:
            _edge_first(i, i0, edges)
            return False
        wn += step
        if capsule_meets(ax, ay, bx, by, max(abs(da), abs(db)) * hs, kx, ky, nk, kb, knx, kny,
                         klo, khi):
            _edge_first(i, i0, edges)
            return False
    return wn >= 1


@njit(cache=True, nogil=True, inline="always")
def _fused_start(live, lpos, n_live, gbb, gwlo, gwhi, edges, wref, hs, dx, dy, kx, ky, nk,
                 kb, cand):  # pragma: no cover - numba
    """The live groups ``_fused_hide`` and ``_fused_sub`` take together, into ``cand`` (ids,
    depth verdicts 0), and how many (0: the test cannot pass). At directions ``(dx, dy)`` off
    the pixel's centre, ``hs`` half-wide (the pixel: 0, 0, h), a group can cover a part of K
    only if its box, moved and grown for those directions, meets K's (``kb``); at most
    ``FUSE_GROUPS`` are taken. A corner of K inside no group's moved box, or a centroid
    inside no group's silhouette there, lies in no covered part."""
    nc = 0
    for c in range(n_live):
        g = live[c]
        if lpos[g] != c:
            continue
        m = max(abs(gwlo[g] - wref), abs(gwhi[g] - wref))
        ex = m * (abs(dx) + hs)
        ey = m * (abs(dy) + hs)
        if (kb[1] < gbb[g, 0] - ex or kb[0] > gbb[g, 1] + ex or kb[3] < gbb[g, 2] - ey
                or kb[2] > gbb[g, 3] + ey):
            continue
        cand[0, nc] = g
        cand[1, nc] = 0
        nc += 1
        if nc == FUSE_GROUPS:
            break
    if nc < 2:
        return 0
    for i in range(nk):
        inside = False
        for c in range(nc):
            g = cand[0, c]
            m = max(abs(gwlo[g] - wref), abs(gwhi[g] - wref))
            ex = m * abs(dx)
            ey = m * abs(dy)
            if (gbb[g, 0] - ex <= kx[i] <= gbb[g, 1] + ex
                    and gbb[g, 2] - ey <= ky[i] <= gbb[g, 3] + ey):
                inside = True
                break
        if not inside:
            return 0
    for c in range(nc):
        if _wind_in(cand[0, c], edges, wref, dx, dy, kb[4], kb[5]):
            return nc
    return 0


@njit(cache=True, nogil=True, inline="always")
def _cells_start(stack, kb):  # pragma: no cover - numba
    """Start a depth-first split of K's box ``kb`` into cells (``stack`` rows: x0, x1, y0,
    y1, level): its root; the stack's new top."""
    stack[0, 0] = kb[0]
    stack[0, 1] = kb[1]
    stack[0, 2] = kb[2]
    stack[0, 3] = kb[3]
    stack[0, 4] = 0.0
    return 1


@njit(cache=True, nogil=True, inline="always")
def _cell_part(kx, ky, nk, stack, top, poly):  # pragma: no cover - numba
    """K (``kx``, ``ky``, ``nk`` corners) clipped to the cell ``stack[top]``, into ``poly[0]``
    and ``poly[1]`` (``poly[2]``, ``poly[3]`` scratch): its corner count, under 3 where the
    cell holds no part of K of any area."""
    px = poly[0]
    py = poly[1]
    tx = poly[2]
    ty = poly[3]
    for i in range(nk):
        px[i] = kx[i]
        py[i] = ky[i]
    m = clip_halfplane(px, py, nk, -1.0, 0.0, -stack[top, 0], tx, ty)
    m = clip_halfplane(tx, ty, m, 1.0, 0.0, stack[top, 1], px, py)
    m = clip_halfplane(px, py, m, 0.0, -1.0, -stack[top, 2], tx, ty)
    return clip_halfplane(tx, ty, m, 0.0, 1.0, stack[top, 3], px, py)


@njit(cache=True, nogil=True, inline="always")
def _cell_split(stack, top, cell):  # pragma: no cover - numba
    """Push the four quarters of ``cell`` (x0, x1, y0, y1, level), a level deeper; the stack's
    new top."""
    x0 = cell[0]
    x1 = cell[1]
    y0 = cell[2]
    y1 = cell[3]
    xm = 0.5 * (x0 + x1)
    ym = 0.5 * (y0 + y1)
    for q in range(4):
        stack[top, 0] = x0 if q & 1 == 0 else xm
        stack[top, 1] = xm if q & 1 == 0 else x1
        stack[top, 2] = y0 if q & 2 == 0 else ym
        stack[top, 3] = ym if q & 2 == 0 else y1
        stack[top, 4] = cell[4] + 1.0
        top += 1
    return top


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _fused_sub(live, lpos, n_live, gbb, gwlo, gwhi, edges, occ, cam, n, wcam, tol, wref, h,
               hs, dx, dy, wmin, kx, ky, nk, kb, fuse, work,
               front):  # pragma: no cover - numba
    """``_fused_hide`` at a sub-pixel of ``_refined_hide``: whether live groups hide Q together
    over the sub-pixel's K (``kx``, ``ky``, ``kb``; its centre ``(dx, dy)`` off the pixel's,
    half-width ``hs``). Each cell of K's box, split depth first, must be covered by one group
    at the sub-pixel (``_covers_sub``: edges moved to its centre and grown for its width)
    that passes the depth test over the sub-pixel's K (``_hides``, run once per group).
    Abutting or barely overlapping surfaces (a wall and the one behind its end) overlap in
    the offset space by less than a pixel's capsules: a sub-pixel's are that much thinner.
    As there, the first group that covers a cell but fails the depth test is taken on as its
    part in front of Q (``_front_build``; ``front`` its scratch)."""
    (head, nxt, obb, owr, ouse, oplane, ov, gslot, sg, sfr, shead, pool, pdep, dom,
     qctx) = occ
    cand, stack, poly, pb = fuse
    part, pbb, pwlo, pwhi = front[4], front[5], front[6], front[7]
    part_free = True
    m0 = _fused_start(live, lpos, n_live, gbb, gwlo, gwhi, edges, wref, hs, dx, dy, kx, ky,
                      nk, kb, cand)
    if m0 == 0:
        return False
    px = poly[0]
    py = poly[1]
    cell = poly[8]
    top = _cells_start(stack, kb)
    cells = 0
    while top > 0:
        top -= 1
        cells += 1
        if cells > FUSE_CELLS:
            return False
        m = _cell_part(kx, ky, nk, stack, top, poly)
        if m < 3:
            continue
        for i in range(5):
            cell[i] = stack[top, i]
        _k_box(px, py, m, pb)
        polygon_axes(px, py, m, pb, poly[4], poly[5], poly[6], poly[7])
        pb[6] = 1.0
        covered = False
        for c in range(m0):
            if cand[1, c] < 0:
                continue
            g = cand[0, c]
            if not _covers_sub(g, edges, gbb, gwlo, gwhi, wref, hs, dx, dy, px, py, m, pb,
                               poly[4], poly[5], poly[6], poly[7], work):
                continue
            if cand[1, c] == 0:
                cand[1, c] = 1 if _hides(g, head, nxt, obb, owr, ouse, oplane, gwlo, gwhi,
                                         gslot, sg, sfr, shead, pool, pdep, dom, wcam, tol,
                                         wref, h, kb, cam, n, wmin, ov, qctx,
                                         work) else -1
                if cand[1, c] < 0 and part_free and _front_build(g, occ, front, wref, h, kb,
                                                                 cam, n, wmin, wcam, tol,
                                                                 work):
                    cand[1, c] = 2
                    part_free = False
            if cand[1, c] == 2 and not _covers_sub(0, part, pbb, pwlo, pwhi, wref, hs, dx, dy,
                                                   px, py, m, pb, poly[4], poly[5], poly[6],
                                                   poly[7], work):
                continue
            if cand[1, c] > 0:
                covered = True
                break
        if covered:
            continue
        if cell[4] >= FUSE_DEPTH:
            return False
        top = _cell_split(stack, top, cell)
    return True


#: Most levels of ``_refined_hide`` (``core.REFINE_MAX``: a 256th of a pixel's width), and
#: the sub-pixels of its depth-first walk waiting at once: 3 per level, and 4.
REFINE_LEVELS = 8
REFINE_STACK = 3 * REFINE_LEVELS + 4


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _refined_hide(levels, covl, n_cov, live, lpos, n_live, gbb, gwlo, gwhi, edges, occ, front,
                  cam, n, tri, corners, sx, sy, h, wref, wmin, wcam, tol, kb0, sub,
                  work, fuse_on, fuse):  # pragma: no cover - numba
    """Whether Q, which no group hides over the whole pixel, is hidden at every one of its
    sub-pixels, split in 2 x 2 down to ``levels`` levels (depth first; a sub-pixel hidden
    behind some group is not split further, one left unhidden at the last level ends the
    walk: Q is seen).

    The pixel's directions are the union of its sub-pixels', so Q hidden at each (each
    sub-pixel's own K, grown only for its own directions, behind a coverall or live group
    that covers it, ``_covers_sub``, and passes the pixel's depth test over it, ``_hides``)
    is hidden at the pixel. A silhouette edge's capsule grows with the pixel's width times
    its depth difference to Q, so a far occludee beside a near roof line fails the pixel's
    test however far its rays pass from the roof: a sub-pixel's capsules are that much
    thinner. Only the groups whose boxes, grown for the pixel, meet K's (``kb0``) can cover
    a sub-pixel's K, which lies inside K; with ``fuse_on``, a group that covers it but fails
    the depth test is tried again as its part in front of Q (``_front_part``, its scratch in
    ``front``). ``occ``: the occluders' arrays ``_hides`` reads;
    ``sub``: scratch (Q's and the camera rectangle's images, K and its geometry, the walk's
    stack, the candidate groups); ``work[2]`` counts the sub-pixels resolved, ``work[6]``
    and ``work[7]`` the walks that end with Q seen and the sub-pixels they resolved."""
    (head, nxt, obb, owr, ouse, oplane, ov, gslot, sg, sfr, shead, pool, pdep, dom,
     qctx) = occ
    qv, qr, rv, rr, kx, ky, tx, ty, kb, knx, kny, klo, khi, stack, cand = sub
    nc = 0
    for c in range(n_cov):
        cand[nc] = -1 - covl[c]
        nc += 1
    for c in range(n_live):
        g = live[c]
        if lpos[g] == c and _near_k(g, gbb, gwlo, gwhi, wref, h, kb0):
            cand[nc] = g
            nc += 1
    if nc == 0:
        return False
    resolved = work[2]
    top = 0
    hs = 0.5 * h
    for c in range(4):
        stack[top, 0] = hs if c & 1 else -hs
        stack[top, 1] = hs if c & 2 else -hs
        stack[top, 2] = hs
        stack[top, 3] = 1.0
        top += 1
    first = 0  # the candidate that hid the last sub-pixel is tried first
    while top > 0:
        top -= 1
        dx = stack[top, 0]
        dy = stack[top, 1]
        hs = stack[top, 2]
        lev = stack[top, 3]
        work[2] += 1
        project(cam, n, sx + dx, sy + dy, hs, wref, qv, qr)
        region_at(corners, sx + dx, sy + dy, hs, wref, rv, rr)
        nk = region_polygon(qv, qr, n, tri, rv, rr, kx, ky, tx, ty)
        if nk == 0:
            continue  # no ray of the sub-pixel meets Q
        # Into the pixel's frame: the sub-pixel centre's images are the pixel-frame ones
        # moved by -wref (dx, dy), the same for every point.
        for i in range(nk):
            kx[i] += wref * dx
            ky[i] += wref * dy
        _k_box(kx, ky, nk, kb)
        polygon_axes(kx, ky, nk, kb, knx, kny, klo, khi)
        kb[6] = 1.0
        hidden = False
        for t in range(nc):
            c = (first + t) % nc
            g = cand[c]
            if g < 0:
                g = -1 - g  # coverall: it covers the whole pixel's offsets
            elif not _covers_sub(g, edges, gbb, gwlo, gwhi, wref, hs, dx, dy, kx, ky, nk, kb,
                                 knx, kny, klo, khi, work):
                continue
            if _hides(g, head, nxt, obb, owr, ouse, oplane, gwlo, gwhi, gslot, sg, sfr, shead,
                      pool, pdep, dom, wcam, tol, wref, h, kb, cam, n, wmin, ov, qctx, work):
                hidden = True
                first = c
                break
            if fuse_on and _front_part(g, occ, front, wref, h, hs, dx, dy, kx, ky, nk, kb, knx,
                                       kny, klo, khi, cam, n, wmin, wcam, tol, 0, rv, work):
                hidden = True
                first = c
                break
        if not hidden and fuse_on:
            hidden = _fused_sub(live, lpos, n_live, gbb, gwlo, gwhi, edges, occ, cam, n,
                                wcam, tol, wref, h, hs, dx, dy, wmin, kx, ky, nk, kb, fuse,
                                work, front)
        if hidden:
            continue
        if lev >= levels:
            work[6] += 1
            work[7] += work[2] - resolved
            return False
        hs2 = 0.5 * hs
        for c in range(4):
            stack[top, 0] = dx + (hs2 if c & 1 else -hs2)
            stack[top, 1] = dy + (hs2 if c & 2 else -hs2)
            stack[top, 2] = hs2
            stack[top, 3] = lev + 1.0
            top += 1
    return True


#: Separate occluders (``_fused_hide``): at most this many groups, each in front of Q over K,
#: are tried together, and K's box is split into quarters down to this depth.
FUSE_GROUPS = 64
FUSE_DEPTH = 6
#: Cells of K's box one test may visit, at most (then Q is not found hidden).
FUSE_CELLS = 256
#: Cells of ``_fused_hide``'s depth-first walk waiting at once (3 per level, and the root).
FUSE_STACK = 3 * FUSE_DEPTH + 2
#: Room for K clipped to a cell: each of the cell's four sides adds at most one corner.
FUSE_POLY = MAX_POLY + 4


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _fused_hide(live, lpos, n_live, gbb, gwlo, gwhi, edges, ov, head, nxt, obb,
                owr, ouse, oplane, gslot, sg, sfr, shead, pool, pdep, dom, wcam, tol, wref, h,
                kx, ky, nk, kb, qcam, nq, wmin, qctx, rpoly, rpb, rv, ws, wpt, work,
                fuse, occ, front):  # pragma: no cover - numba
    """Whether several separate groups hide Q together where none does alone.

    The paper fuses only triangles that share edges, so two walls one behind the other, or
    two buildings side by side, each covering part of K, hide nothing; from a cell metres
    wide that is most occlusion. Here the live groups whose boxes come near K's, at most
    ``FUSE_GROUPS``, are taken together: K's box is split into quarters, depth first, down to
    ``FUSE_DEPTH`` levels (``FUSE_CELLS`` cells in all), and each cell's part of K must be
    covered by one of them (``_covers_q``, strict: no silhouette capsule meets the part, a
    winding number of at least one inside it) that also passes the depth test a group
    passes alone (``_hides``: its triangles that can reach K's box all lie in front of Q; run
    once per group, when it first covers a part). Every ray of the pixel that meets Q passes
    through some point of K, which lies in a covered part, so for every delta that ray meets
    a group whose triangles there lie in front of Q: Q is hidden. A part no group covers at
    the last level ends the test (Q is not found hidden). The first group that covers a
    part but fails the depth test is taken on as its part in front of Q (``_front_build``,
    verdict 2; ``occ`` and ``front`` as there), which a part must then be covered by.
    ``fuse`` holds the scratch:
    candidate ids and depth verdicts (int64 (2, FUSE_GROUPS)), the cell stack (FUSE_STACK,
    5), the clipped polygon, its axes and the cell at hand (9, FUSE_POLY) and its box (7,)."""
    cand, stack, poly, pb = fuse
    part, pbb, pwlo, pwhi = front[4], front[5], front[6], front[7]
    part_free = True
    relax = qctx[QC_RELAX]
    # cand[1] holds each group's depth verdict (0 not yet run, 1 in front of Q, -1 not): run
    # only for a group that covers some part, since most near K never do.
    nc = _fused_start(live, lpos, n_live, gbb, gwlo, gwhi, edges, wref, h, 0.0, 0.0, kx, ky,
                      nk, kb, cand)
    if nc == 0:
        return False
    qctx[QC_RELAX] = 0.0
    px = poly[0]
    py = poly[1]
    cell = poly[8]
    top = _cells_start(stack, kb)
    ok = True
    cells = 0
    while top > 0:
        top -= 1
        cells += 1
        if cells > FUSE_CELLS:
            ok = False
            break
        m = _cell_part(kx, ky, nk, stack, top, poly)
        if m < 3:
            continue  # no part of K of any area here
        for i in range(5):
            cell[i] = stack[top, i]
        _k_box(px, py, m, pb)
        covered = False
        for c in range(nc):
            if cand[1, c] < 0:
                continue
            g = cand[0, c]
            if not _covers_q(g, edges, gbb, gwlo, gwhi, wref, h, px, py, m,
                             pb, poly[4], poly[5], poly[6], poly[7], qctx, rpoly, 0, rpb, rv,
                             ws, wpt, work):
                continue
            if cand[1, c] == 0:
                qctx[QC_RELAX] = relax
                cand[1, c] = 1 if _hides(g, head, nxt, obb, owr, ouse, oplane, gwlo, gwhi,
                                         gslot, sg, sfr, shead, pool, pdep, dom, wcam, tol,
                                         wref, h, kb, qcam, nq, wmin, ov, qctx,
                                         work) else -1
                if cand[1, c] < 0 and part_free and _front_build(g, occ, front, wref, h, kb,
                                                                 qcam, nq, wmin, wcam, tol,
                                                                 work):
                    cand[1, c] = 2
                    part_free = False
                qctx[QC_RELAX] = 0.0
            if cand[1, c] == 2 and not _covers_q(0, part, pbb, pwlo, pwhi, wref, h, px, py,
                                                 m, pb, poly[4], poly[5], poly[6], poly[7],
                                                 qctx, rpoly, 0, rpb, rv, ws, wpt, work):
                continue
            if cand[1, c] > 0:
                covered = True
                break
        if covered:
            continue
        if cell[4] >= FUSE_DEPTH:
            ok = False
            break
        top = _cell_split(stack, top, cell)
    qctx[QC_RELAX] = relax
    return ok


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _cover_depth(g, head, nxt, obb, owr, wcam, tol, h, kx, ky, nk, wref):  # pragma: no cover
    """Depth (camera w) by which every ray of the pixel meets coverall group g, or inf.

    g covers the grown offset region (polygon K, frame of depth wref) for every delta: every
    ray of the pixel, extended back to w = 0, meets one of g's triangles whose grown bounding
    box meets K's, at a depth no larger than that triangle's deepest vertex. When all those
    triangles lie at w >= wcam (the deepest camera position), the meeting point is on the ray
    itself, in front of its camera position: the largest such deepest vertex bounds it."""
    kx0 = np.inf
    kx1 = -np.inf
    ky0 = np.inf
    ky1 = -np.inf
    for i in range(nk):
        kx0 = min(kx0, kx[i])
        kx1 = max(kx1, kx[i])
        ky0 = min(ky0, ky[i])
        ky1 = max(ky1, ky[i])
    z = -np.inf
    r = head[g]
    while r >= 0:
        grow = max(abs(owr[r, 0] - wref), abs(owr[r, 1] - wref)) * h
        if not (obb[r, 1] + grow < kx0 or obb[r, 0] - grow > kx1 or obb[r, 3] + grow < ky0
                or obb[r, 2] - grow > ky1):
            if not owr[r, 0] >= wcam + tol:
                return np.inf
            z = max(z, owr[r, 1])
        r = nxt[r]
    return z if z > -np.inf else np.inf


@njit(cache=True, nogil=True, inline="always")
def _edge_slot(thash, mask, stamp, va, vb):  # pragma: no cover - numba
    """Row of edge (va, vb), va < vb, in the open-addressing table ``thash`` (rows: stamp, va,
    vb, edge slot) of ``mask + 1`` rows: the row holding it, or the empty one (a stamp other
    than ``stamp``, the tile's) where it would go."""
    x = va * 0x9E3779B1 + vb * 0x85EBCA77  # may wrap for huge ids: only spreads the bits
    x ^= x >> 17
    k = x & mask
    while thash[k, 0] == stamp and (thash[k, 1] != va or thash[k, 2] != vb):
        k = (k + 1) & mask
    return k


@njit(cache=True, nogil=True, inline="always")
def _to_coverall(g, lpos, covl, cpos, n_cov, n_dead):  # pragma: no cover - numba
    """Move group g from the live list (marked dead in ``lpos``) to the coverall list
    ``covl``; returns the new (n_cov, n_dead)."""
    if lpos[g] >= 0:
        lpos[g] = -1
        n_dead += 1
    covl[n_cov] = g
    cpos[g] = n_cov
    return n_cov + 1, n_dead


@njit(cache=True, nogil=True, inline="always")
def _list_drop(g, pos, lst, n):  # pragma: no cover - numba
    """Remove group g from the unordered list lst[:n] (pos[g] its index, -1 when absent);
    returns the new length."""
    k = pos[g]
    if k < 0:
        return n
    last = lst[n - 1]
    lst[k] = last
    pos[last] = k
    pos[g] = -1
    return n - 1


@njit(cache=True, nogil=True, inline="always")
def _edge_kill(node, g, edges):  # pragma: no cover - numba
    """Active edge ``node`` of group g is active no more (``groups.EdgePool``): the block's
    last record takes its place, so blocks hold active edges only."""
    geo, enode, pos = edges.geo, edges.node, edges.pos
    p = pos[node]
    last = edges.start[g] + edges.length[g] - 1
    if p != last:
        for c in range(6):
            geo[p, c] = geo[last, c]
        enode[p] = enode[last]
        pos[enode[p]] = p
    enode[last] = -1
    edges.length[g] -= 1
    if edges.length[g] == 0:
        # A closed surface: no silhouette, and no block (a compaction moves only live ones).
        edges.cap[g] = 0


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _edges_gc(grp, edges):  # pragma: no cover - numba
    """Slide every block's records down to the pool's start, in order, dropping the copies
    left behind by blocks that moved; each group's block then holds exactly its edges."""
    geo, enode, pos, start, length = edges.geo, edges.node, edges.pos, edges.start, edges.length
    j = 0
    for i in range(edges.top[0]):
        nd = enode[i]
        if nd < 0 or pos[nd] != i:
            continue
        g = grp[nd // 3]
        if start[g] + length[g] != j:
            # The group's first record in this sweep (its records are contiguous, and were
            # at j or beyond).
            start[g] = j
            length[g] = 0
        length[g] += 1
        edges.cap[g] = length[g]
        for c in range(6):
            geo[j, c] = geo[i, c]
        enode[j] = nd
        pos[nd] = j
        j += 1
    edges.top[0] = j


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _edges_grow(g, need, grp, edges):  # pragma: no cover - numba
    """Room for ``need`` more records at the end of group g's block: the last block grows
    where it is, any other moves to the pool's end with twice the room it needs (the pool
    compacted first when full: ``_edges_gc``)."""
    geo, enode, pos, start, length, cap = (edges.geo, edges.node, edges.pos, edges.start,
                                           edges.length, edges.cap)
    want = max(8, 2 * (length[g] + need))
    top = edges.top[0]
    s = start[g]
    if s + cap[g] == top and s + want <= geo.shape[0]:
        edges.top[0] = s + want
        cap[g] = want
        return
    if top + want > geo.shape[0]:
        _edges_gc(grp, edges)
        top = edges.top[0]
        s = start[g]
    for i in range(length[g]):
        for c in range(6):
            geo[top + i, c] = geo[s + i, c]
        nd = enode[s + i]
        enode[top + i] = nd
        pos[nd] = top + i
        enode[s + i] = -1
    start[g] = top
    cap[g] = want
    edges.top[0] = top + want


@njit(cache=True, nogil=True, inline="always")
def _edges_join(g1, g2, grp, edges):  # pragma: no cover - numba
    """Append group g2's edges to g1's block (g2 keeps none)."""
    n2 = edges.length[g2]
    if n2 > 0:
        if edges.length[g1] + n2 > edges.cap[g1]:
            _edges_grow(g1, n2, grp, edges)
        geo, enode, pos = edges.geo, edges.node, edges.pos
        j = edges.start[g1] + edges.length[g1]
        s = edges.start[g2]
        for i in range(s, s + n2):
            for c in range(6):
                geo[j, c] = geo[i, c]
            nd = enode[i]
            enode[j] = nd
            pos[nd] = j
            enode[i] = -1
            j += 1
        edges.length[g1] += n2
    edges.length[g2] = 0
    edges.cap[g2] = 0


@njit(cache=True, nogil=True, inline="always")
def _edge_record(geo, i, q, e, ov, ow):  # pragma: no cover - numba
    """Write edge e of occluder triangle q (COS corners ``ov``, depths ``ow``) into record i
    of an ``EdgePool``'s ``geo``: its end points, then their depths."""
    b = (e + 1) % 3
    geo[i, 0] = ov[q, e, 0]
    geo[i, 1] = ov[q, e, 1]
    geo[i, 2] = ov[q, b, 0]
    geo[i, 3] = ov[q, b, 1]
    geo[i, 4] = ow[q, e]
    geo[i, 5] = ow[q, b]


@njit(cache=True, nogil=True, inline="always")
def _edges_new(q, ov, ow, grp, edges):  # pragma: no cover - numba
    """Occluder triangle q's three edges, all active, as a new block (group q)."""
    if edges.top[0] + 3 > edges.geo.shape[0]:
        _edges_gc(grp, edges)
    t = edges.top[0]
    geo = edges.geo
    for e in range(3):
        _edge_record(geo, t + e, q, e, ov, ow)
        edges.node[t + e] = 3 * q + e
        edges.pos[3 * q + e] = t + e
    edges.start[q] = t
    edges.length[q] = 3
    edges.cap[q] = 3
    edges.top[0] = t + 3


@njit(cache=True, nogil=True, inline="always")
def _merge(g1, g2, grp, head, tail, nxt, gsize, gbb, gwlo, gwhi, gcov, alive,
           edges):  # pragma: no cover - numba
    """Merge groups g1 and g2 (the smaller into the larger); returns the survivor."""
    if g1 == g2:
        return g1
    if gsize[g1] < gsize[g2]:
        g1, g2 = g2, g1
    # The edges first: a compaction on the way finds each record's group through grp.
    _edges_join(g1, g2, grp, edges)
    r = head[g2]
    while r >= 0:
        grp[r] = g1
        r = nxt[r]
    nxt[tail[g1]] = head[g2]
    tail[g1] = tail[g2]
    gsize[g1] += gsize[g2]
    gbb[g1, 0] = min(gbb[g1, 0], gbb[g2, 0])
    gbb[g1, 1] = max(gbb[g1, 1], gbb[g2, 1])
    gbb[g1, 2] = min(gbb[g1, 2], gbb[g2, 2])
    gbb[g1, 3] = max(gbb[g1, 3], gbb[g2, 3])
    gwlo[g1] = min(gwlo[g1], gwlo[g2])
    gwhi[g1] = max(gwhi[g1], gwhi[g2])
    gcov[g1] = gcov[g1] or gcov[g2]
    alive[g2] = False
    return g1


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _leaf_hidden(lf, g, coverall, leaf_pts, origin, perm, sign, sx, sy, h, corners, wcam, tol,
                 edges, gbb, gwlo, gwhi, occ, lsc, strict, rpoly, rpb, ws, wpt,
                 work):  # pragma: no cover - numba
    """Whether group g, which has just hidden a primitive of leaf ``lf`` (a run of
    consecutive triangle ids, ``core._leaf_boxes``), also hides the leaf's box (its 8
    corners at ``leaf_pts[8 lf:]``) at this pixel (sx, sy, half-width h): the box's region
    K in its own mean-depth frame, covered by g (``_covers_q``, strict; a coverall group
    covers every region) and every triangle of g that can reach K in front of all 8 corners
    (``_hides``). Every ray of the pixel that meets a primitive of the leaf meets its box,
    so the test hides each of them at once.

    A box reaching the cameras' depths is never hidden, nor tested. ``occ``: the occluders'
    arrays ``_hides`` reads; ``lsc``: scratch (the box's camera points, images and radii, the
    pixel's region, K and its scratch, K's geometry and axes). Not inlined: called once per
    leaf and pixel at most, it spares the kernel another copy of both tests."""
    (head, nxt, obb, owr, ouse, oplane, ov, gslot, sg, sfr, shead, pool, pdep, dom,
     qctx) = occ
    cam, qv, qr, rv, rr, kx, ky, tx, ty, kb, knx, kny, klo, khi = lsc
    wmin, wref = _load_depths(leaf_pts, 8 * lf, np.int64(8), origin, perm, sign, cam)
    if not wmin > wcam + tol:
        return False
    project(cam, 8, sx, sy, h, wref, qv, qr)
    nk = _occludee_k(qv, qr, np.int64(8), np.bool_(False), corners, sx, sy, h, wref, rv, rr,
                     kx, ky, tx, ty, kb)
    if nk == 0:
        return True  # no ray of the pixel meets the box
    if not coverall and not _covers_q(g, edges, gbb, gwlo, gwhi, wref, h, kx, ky, nk, kb, knx,
                                      kny, klo, khi, strict, rpoly, 0, rpb, rv, ws, wpt, work):
        return False
    return _hides(g, head, nxt, obb, owr, ouse, oplane, gwlo, gwhi, gslot, sg, sfr, shead, pool,
                  pdep, dom, wcam, tol, wref, h, kb, cam, np.int64(8), wmin, ov, strict, work)


@njit(cache=True, nogil=True)
def _share_scratch(lmax, tmax, imax, n_known, fuse):
    """The scratch arrays of one share of ``resolve_tiles`` (``groups.ShareScratch``, owners),
    for lists of at most ``lmax`` entries, tiles of at most ``tmax`` entries and ``imax``
    items, and ``n_known`` primitives; ``fuse``: whether separate groups hide (the front
    parts' scratch, ``_front_part``, is sized for a whole pixel's occluders only then)."""
    nslot = lmax // GRID_MIN + 2
    proom = 3 * lmax if fuse else 1
    hcap = 8  # the edge hash at most half full
    while hcap < 6 * imax:
        hcap *= 2
    return ShareScratch(
        cam=np.empty((8, 3)), qv=np.empty((8, 2)), qr=np.empty(8), rv=np.empty((4, 2)),
        rr=np.empty(4), kx=np.empty(MAX_POLY), ky=np.empty(MAX_POLY), tx_=np.empty(MAX_POLY),
        ty_=np.empty(MAX_POLY), rx=np.empty(MAX_POLY), ry=np.empty(MAX_POLY), kb=np.empty(7),
        qctx=np.zeros(QC_SIZE), rpoly=np.empty((MAX_POLY, 6)), rpb=np.empty(7),
        ws=np.empty((4, MAX_POLY)), wpt=np.empty((3 * DIR_PTS, 2)), knx=np.empty(MAX_POLY),
        kny=np.empty(MAX_POLY), klo=np.empty(MAX_POLY), khi=np.empty(MAX_POLY), rb=np.empty(7),
        rnx=np.empty(MAX_POLY), rny=np.empty(MAX_POLY), rlo=np.empty(MAX_POLY),
        rhi=np.empty(MAX_POLY), ov=np.empty((lmax, 3, 2)), ow=np.empty((lmax, 3)),
        owr=np.empty((lmax, 2)), oid=np.empty((lmax, 3), dtype=np.int64),
        oact=np.empty((lmax, 3), dtype=np.bool_), oplane=np.empty((lmax, 5)),
        ouse=np.empty(lmax, dtype=np.bool_), obb=np.empty((lmax, 4)),
        grp=np.empty(lmax, dtype=np.int64), nxt=np.empty(lmax, dtype=np.int64),
        head=np.empty(lmax, dtype=np.int64), tail=np.empty(lmax, dtype=np.int64),
        gsize=np.empty(lmax, dtype=np.int64), gbb=np.empty((lmax, 4)), gwlo=np.empty(lmax),
        gwhi=np.empty(lmax), gcov=np.empty(lmax, dtype=np.bool_),
        alive=np.empty(lmax, dtype=np.bool_), gdorm=np.empty(lmax, dtype=np.bool_),
        edges=EdgePool(geo=np.empty((EDGE_ROOM * lmax + 64, 6)),
                       node=np.empty(EDGE_ROOM * lmax + 64, dtype=np.int64),
                       pos=np.empty(3 * lmax, dtype=np.int64),
                       start=np.empty(lmax, dtype=np.int64), length=np.empty(lmax, dtype=np.int64),
                       cap=np.empty(lmax, dtype=np.int64), top=np.zeros(1, dtype=np.int64)),
        live=np.empty(lmax, dtype=np.int64), lpos=np.empty(lmax, dtype=np.int64),
        covl=np.empty(lmax, dtype=np.int64), cand=np.empty(lmax + 1, dtype=np.int64),
        cpos=np.empty(lmax, dtype=np.int64), gslot=np.empty(lmax, dtype=np.int64),
        sg=np.empty((nslot, 2, GRID * GRID)),
        shead=np.empty((nslot, GRID * GRID + 3), dtype=np.int64),
        pool=np.empty(2 + 2 * 8 * lmax, dtype=np.int64), pdep=np.empty(2 * 8 * lmax),
        fslot=np.empty(nslot, dtype=np.int64), sfr=np.empty(nslot), dom=np.empty(6),
        thash=np.full((hcap, 4), -1, dtype=np.int64), eslot=np.empty(3 * imax, dtype=np.int64),
        eready=np.full(imax, -1, dtype=np.int64),
        sstate=np.full((3 * imax, 2), -1, dtype=np.int64),
        enext=np.empty(3 * lmax, dtype=np.int64),
        tseen=np.zeros((n_known + 7) // 8, dtype=np.uint8), tset=np.empty(tmax, dtype=np.int64),
        work=np.zeros(N_WORK, dtype=np.int64),
        opart=np.empty((lmax, 3), dtype=np.int64), obad=np.zeros(lmax, dtype=np.bool_),
        part=EdgePool(geo=np.empty((proom, 6)), node=np.empty(proom, dtype=np.int64),
                      pos=np.empty(proom, dtype=np.int64), start=np.zeros(1, dtype=np.int64),
                      length=np.zeros(1, dtype=np.int64), cap=np.zeros(1, dtype=np.int64),
                      top=np.zeros(1, dtype=np.int64)),
        pbb=np.empty((1, 4)), pwlo=np.empty(1), pwhi=np.empty(1))


def resolve_tiles(prims: PrimArrays, lists: TileLists, screen: Screen, marks: Marks) -> None:
    """Run Alg. 1 on every pixel of tiles [tile0, tile1): set ``vis[p] = 1`` for each primitive
    p found visible. Only triangles with ``solid[p]`` become occluders (``prims.solid_mask``:
    the ones a client's near plane cannot cut). ``entries`` holds the lists of those tiles
    (``lists.fill_lists``: pixel ``loc`` of tile ``tile`` at ``pstart[(tile - tile0) * tsz^2 +
    loc]``, ``pcount[...]`` long, naming the tile's items ``items[ioff[tile]:]`` by place;
    tiles of ``tsz`` x ``tsz`` pixels of width ``pw``), each in
    nondecreasing ``gap`` (the distance from the cell box to the primitive's bounding box,
    metres), taken in the order ``torder`` (a permutation of [tile0, tile1) whose
    ``shares`` contiguous shares, one per thread, carry a like mix of costs); ``known[p]``
    marks primitives already known visible (tested no more, still occluders), as are those
    found visible at an earlier pixel of the same tile.
    ``hid``, unless empty, gets 1 at each entry found hidden or not seen at its pixel (the
    coarse pass: ``core``, one pixel per tile).
    ``counters[tile]`` gets (entries tested, entries found occluded, occluder triangles,
    entries cut by the early-z depth, silhouette edges walked by the cover tests, occluder
    triangles put through the depth test: the last two are where dense clutter's time goes;
    then CPU cycles: testing entries, inserting occluders, checking coverall, the whole tile;
    then entries hidden by separate groups together (``screen.fuse``, ``_fused_hide``),
    entries hidden at sub-pixels and sub-pixels resolved (``screen.refine``,
    ``_refined_hide``), entries a hidden leaf box spared their pixel, leaf boxes tested and
    found hidden (``screen.leaf_list``, ``_leaf_hidden``): ``N_COUNTERS`` columns).
    ``stop`` ((1,) uint8, ``visibility.cancel.stop_flag``) is polled between pixels and every
    ``STOP_EVERY`` entries: once it is set the kernel returns with ``vis`` incomplete, and the
    caller's checkpoint raises.

    The arrays come in named groups (``groups``): ``prims`` (``PrimArrays``), ``lists``
    (``TileLists``), ``screen`` (``Screen``) and ``marks`` (``Marks``)."""
    n_t = lists.tile1 - lists.tile0
    # Threads, not a prange loop: compiled into a parallel loop, the share's kernel was
    # compiled twice (``visibility.shares``).
    run_shares(_resolve_share, max(1, min(lists.shares, n_t)), prims, lists, screen, marks)


@njit(cache=True, nogil=True)
def _resolve_share(prims, lists, screen, marks, share, k_sh):  # pragma: no cover - numba
    """Share ``share`` of the ``k_sh`` shares of ``resolve_tiles``'s tiles (its arguments)."""
    pts, start, npts, kind, vid, solid, gap, leaf, leaf_pts = prims
    entries, pstart, pcount, tile0, tile1, torder, tiles_x, tsz, shares, items, ioff, block = (
        lists)
    (origin, perm, sign, corners, nx, ny, x_lo, y_lo, pw, plane_tol, relaxed, fuse_on,
     refine, leaf_list) = screen
    known, vis, hid, counters, stop = marks
    # Borrowed (``visibility.borrow``): the helpers called per entry and per pixel count no
    # references to them, which the threads would otherwise fight over (shared arrays) or
    # pay for at every call (their own scratch, borrowed below).
    pts, start, npts, kind = borrow(pts), borrow(start), borrow(npts), borrow(kind)
    vid, solid, gap, entries = borrow(vid), borrow(solid), borrow(gap), borrow(entries)
    pstart, pcount, torder, origin = borrow(pstart), borrow(pcount), borrow(torder), borrow(origin)
    perm, sign, corners, known = borrow(perm), borrow(sign), borrow(corners), borrow(known)
    stop, items, ioff, block = borrow(stop), borrow(items), borrow(ioff), borrow(block)
    leaf, leaf_pts = borrow(leaf), borrow(leaf_pts)
    # What the parallel loop writes (vis, hid, counters) stays owned: ``visibility.borrow``.
    h = 0.5 * pw
    npix = tsz * tsz
    mark = hid.shape[0] > 0
    # Largest camera depth of the view's camera rectangle (0 for a front frustum).
    wcam = max(corners[0, 2], corners[1, 2], corners[2, 2], corners[3, 2])
    # The threads' shares of the tiles, as ``core._balanced_order`` deals them (share b:
    # every k-th tile of the costliest-first ranking), each run with one set of scratch
    # arrays sized for its longest list: allocating them per tile cost as much as the
    # resolution of an open scene's short lists.
    n_t = tile1 - tile0
    it0 = 0
    for b in range(share):
        it0 += (n_t - b + k_sh - 1) // k_sh
    it1 = it0 + (n_t - share + k_sh - 1) // k_sh
    # Typed int64 from the start (np.int64, not a literal 0): numba's type inference meets the
    # calls below while these are still Literal[int](0) and compiled a specialization of the
    # callee for each such guess, each one as costly to compile as the one that runs.
    lmax = np.int64(0)
    tmax = np.int64(0)
    imax = np.int64(0)
    for it in range(it0, it1):
        pix0 = (torder[it] - tile0) * npix
        imax = max(imax, ioff[torder[it] + 1] - ioff[torder[it]])
        tlen = 0
        for loc in range(npix):
            lmax = max(lmax, pcount[pix0 + loc])
            tlen += pcount[pix0 + loc]
        tmax = max(tmax, tlen)
    if lmax == 0:
        return
    # Per share scratch (``groups.ShareScratch``), sized for its longest list; owned by
    # ``own`` until the share is done, borrowed for the helpers.
    own = _share_scratch(lmax, tmax, imax, known.shape[0], fuse_on)
    (cam, qv, qr, rv, rr, kx, ky, tx_, ty_, rx, ry, kb, qctx, rpoly, rpb, ws, wpt, knx, kny,
     klo, khi, rb, rnx, rny, rlo, rhi, ov, ow, owr, oid, oact, oplane, ouse, obb, grp, nxt,
     head, tail, gsize, gbb, gwlo, gwhi, gcov, alive, gdorm, edges,
     live, lpos, covl, cand, cpos, gslot, sg, shead, pool, pdep, fslot, sfr, dom, thash,
     eslot, eready, sstate, enext, tseen, tset, work, opart, obad, part, pbb, pwlo,
     pwhi) = borrow(own)
    strict = np.zeros(QC_SIZE)  # the strict test's context (QC_RELAX 0): coverall
    fuse = (np.empty((2, FUSE_GROUPS), dtype=np.int64), np.empty((FUSE_STACK, 5)),
            np.empty((9, FUSE_POLY)), np.empty(7))
    # The sub-pixels' scratch (``_refined_hide``): Q's and the camera rectangle's images, K,
    # its geometry, the walk's stack and the candidate groups.
    sub = (np.empty((8, 2)), np.empty(8), np.empty((4, 2)), np.empty(4), np.empty(MAX_POLY),
           np.empty(MAX_POLY), np.empty(MAX_POLY), np.empty(MAX_POLY), np.empty(7),
           np.empty(MAX_POLY), np.empty(MAX_POLY), np.empty(MAX_POLY), np.empty(MAX_POLY),
           np.empty((REFINE_STACK, 4)), np.empty(lmax + 1, dtype=np.int64))
    occ = (head, nxt, obb, owr, ouse, oplane, ov, gslot, sg, sfr, shead, pool, pdep, dom,
           qctx)
    front = (ow, oact, opart, obad, part, pbb, pwlo, pwhi, rpoly, rpb, ws, wpt)
    pool[1] = 8 * lmax
    n_leaf = leaf_pts.shape[0] // 8
    # Per leaf (``core._leaf_boxes``): the pixel its box was last found hidden at, and the
    # pixel it was last tested at (``_leaf_hidden``).
    lstamp = np.full(n_leaf, -1, dtype=np.int64)
    ltried = np.full(n_leaf, -1, dtype=np.int64)
    lsc = (np.empty((8, 3)), np.empty((8, 2)), np.empty(8), rv, rr, rx, ry, tx_, ty_,
           np.empty(7), rnx, rny, rlo, rhi)
    hmask = thash.shape[0] - 1
    # A tile's parts of its test and insertion cycles (``CYCLE_PARTS``).
    cyc_part = np.zeros(len(CYCLE_PARTS), dtype=np.int64)
    pstamp = 0  # the pixel's, in sstate
    for it in range(it0, it1):
        tile = torder[it]
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        pix0 = (tile - tile0) * npix
        # The tile's samples: b x b pixels each (``groups.TileLists.block``).
        bs = block[tile]
        h = 0.5 * pw * bs
        # A sample of bs x bs pixels: where its own test leaves an entry unhidden, its
        # sub-samples are tested down to single pixels (log2 bs levels), then ``refine`` more.
        lv = refine
        b = bs
        while b > 1:
            lv += 1
            b //= 2
        lv = min(lv, REFINE_LEVELS)
        # The tile's items name its entries; each undirected welded edge of the tile gets a
        # slot (eslot: three per item, -1 for none), where a pixel chains the occluder edges
        # it has along it: made at an item's first insertion in the tile, once for all its
        # pixels (made for every item, they cost open scenes more than they saved, an item
        # being listed at about one pixel there).
        i0 = ioff[tile]
        n_slots = 0
        n_set = 0
        for c in range(N_WORK):
            work[c] = 0
        tested = 0
        hidden = 0
        fused = 0
        fronts = 0
        refined = 0
        occl = 0
        cut = 0
        cyc_tile = cycles()
        cyc_test = 0
        cyc_cover = 0
        cyc_part[:] = 0
        for loc in range(npix):
            if flag_set(stop):
                break
            i = ty * tsz + (loc // tsz) * bs
            j = tx * tsz + (loc % tsz) * bs
            if i >= ny or j >= nx:
                continue
            a = pstart[pix0 + loc]
            b = a + pcount[pix0 + loc]
            if a == b:
                continue
            sx = x_lo + (j + 0.5 * bs) * pw
            sy = y_lo + (i + 0.5 * bs) * pw
            # Longest ray per unit of depth over the pixel's directions: a point at distance g
            # from the box (so from every camera position, which lies on the box) is at depth
            # at least g / lray on any ray of this pixel.
            lray = np.sqrt(1.0 + (abs(sx) + h) ** 2 + (abs(sy) + h) ** 2)
            pstamp += 1
            n_polys = 0
            # Not literal 0s: ``_fused_hide`` and ``_refined_hide`` are compiled once each.
            n_live = np.int64(0)
            n_dead = 0
            last_g = -1
            n_cov = np.int64(0)
            n_slot = 0
            n_free = 0
            pool[0] = 0
            edges.top[0] = 0
            # The depth grids' domain: the offset region's frame-0 box (what lies outside
            # falls in the border cells).
            region_at(corners, sx, sy, h, 0.0, rv, rr)
            dom[0] = np.inf
            dom[1] = -np.inf
            dom[2] = np.inf
            dom[3] = -np.inf
            for c in range(4):
                dom[0] = min(dom[0], rv[c, 0] - rr[c])
                dom[1] = max(dom[1], rv[c, 0] + rr[c])
                dom[2] = min(dom[2], rv[c, 1] - rr[c])
                dom[3] = max(dom[3], rv[c, 1] + rr[c])
            dom[4] = GRID / (dom[1] - dom[0]) if dom[1] > dom[0] else 0.0
            dom[5] = GRID / (dom[3] - dom[2]) if dom[3] > dom[2] else 0.0
            # The camera rectangle's image in a frame that moves with the cameras' middle
            # depth, where it barely grows (``_covers_q``).
            fr = 0.5 * wcam
            nrp = 0
            if relaxed:
                region_at(corners, sx, sy, h, fr, rv, rr)
                nrp = region_polygon(rv, rr, np.int64(4), np.bool_(False), rv, rr, ws[0], ws[1],
                                     ws[2], ws[3])
                for c in range(nrp):
                    rpoly[c, 0] = ws[0, c]
                    rpoly[c, 1] = ws[1, c]
                if nrp > 0:
                    polygon_axes(rpoly[:, 0], rpoly[:, 1], nrp, rpb, rpoly[:, 2],
                                 rpoly[:, 3], rpoly[:, 4], rpoly[:, 5])
            # Early z: every ray of the pixel (any camera position, any direction in it) meets
            # a coverall occluder at depth <= zcut, before anything wholly deeper.
            zcut = np.inf
            # Occluders listed after the last entry still to be tested serve no test: the
            # list ends there (the rest are primitives known visible).
            while b > a and (known[items[i0 + entries[b - 1]]] != 0
                             or (tseen[items[i0 + entries[b - 1]] >> 3]
                                 >> (items[i0 + entries[b - 1]] & 7)) & 1):
                b -= 1
            for k in range(a, b):
                if (k - a) % STOP_EVERY == STOP_EVERY - 1 and flag_set(stop):
                    break  # one pixel's list of 10^5 entries takes seconds in dense clutter
                it_k = entries[k]
                p = items[i0 + it_k]
                lf = leaf[p]
                if lf >= 0 and lstamp[lf] == pstamp:
                    # Its leaf's box is hidden at this pixel, so it is too, and it needs no
                    # occluder: whatever it would hide lies behind what hides the box, or
                    # is hidden less, never wrongly, without it.
                    work[3] += 1
                    if mark:
                        hid[k] = 1
                    continue
                # One entry in TIME_STRIDE is timed by step: four counter reads at every
                # entry would weigh on short lists, whose entries are cheap.
                timed = (k - a) % TIME_STRIDE == 0
                if gap[p] > zcut * lray + plane_tol:
                    # The lists are sorted by gap: this entry and all later ones lie beyond
                    # zcut on every ray of the pixel.
                    cut += b - k
                    if mark:
                        hid[k:b] = 1
                    break
                n = npts[p]
                tri = kind[p] == 0
                wmin, wref = _load_depths(pts, start[p], n, origin, perm, sign, cam)
                if wmin > zcut + plane_tol:
                    cut += 1
                    if mark:
                        hid[k] = 1
                    continue
                project(cam, n, sx, sy, h, wref, qv, qr)
                dorm = False
                if known[p] == 0 and not (tseen[p >> 3] >> (p & 7)) & 1:
                    c0 = cycles() if timed else 0
                    nk = _occludee_k(qv, qr, n, tri, corners, sx, sy, h, wref, rv, rr, kx, ky,
                                     tx_, ty_, kb)
                    if nk > 0:
                        tested += 1
                        qctx[QC_RELAX] = 0.0
                        if relaxed:
                            _q_context(qctx, cam, n, tri, qv, sx, sy, h, fr, wmin, wcam,
                                       plane_tol, corners)
                        occluded = False
                        by_cov = False
                        hider = -1
                        by_part = False
                        if 2 * n_dead > n_live:
                            # Compact the live list (oldest groups first, as they came).
                            m = 0
                            for c in range(n_live):
                                g = live[c]
                                if lpos[g] >= 0:
                                    live[m] = g
                                    lpos[g] = m
                                    m += 1
                            n_live = m
                            n_dead = 0
                        # Coverall occluders first (the paper's early discard): they need
                        # only the depth test. Then the live groups, which must cover K: the
                        # one that hid the last entry first (neighbours in the list are often
                        # hidden by the same surface), then the rest. (One loop, so the
                        # inlined tests are compiled once.)
                        # The strict cover test first for every group; the relaxed one
                        # (dearer: a meeting edge does not end the walk, and K's box cannot
                        # reject) only when the strict one hid Q behind none, and only for
                        # the groups that came near K (``cand``; -1 - g for coverall ones).
                        relax_ok = qctx[QC_RELAX]
                        qctx[QC_RELAX] = 0.0
                        c_grp = cycles() if timed else 0
                        cyc_part[0] += c_grp - c0 if timed else 0
                        nl = n_cov + 1 + n_live
                        ncand = 0
                        for cc in range(2 * nl):
                            isc = False
                            if cc < nl:
                                c = cc
                                if c < n_cov:
                                    g = covl[c]
                                    isc = True
                                else:
                                    if c == n_cov:
                                        g = last_g
                                        if g < 0 or lpos[g] < 0:
                                            continue
                                    else:
                                        g = live[c - n_cov - 1]
                                        if lpos[g] != c - n_cov - 1 or g == last_g:
                                            continue
                                if relax_ok != 0.0:
                                    m = max(abs(gwlo[g] - wref), abs(gwhi[g] - wref)) * h
                                    if isc:
                                        cand[ncand] = -1 - g
                                        ncand += 1
                                    elif not (kb[1] < gbb[g, 0] - m or kb[0] > gbb[g, 1] + m
                                              or kb[3] < gbb[g, 2] - m
                                              or kb[2] > gbb[g, 3] + m):
                                        cand[ncand] = g
                                        ncand += 1
                            else:
                                if relax_ok == 0.0 or cc - nl >= ncand:
                                    break
                                qctx[QC_RELAX] = relax_ok
                                g = cand[cc - nl]
                                if g < 0:
                                    g = -1 - g
                                    isc = True
                            if not isc:
                                if not _covers_q(g, edges, gbb, gwlo, gwhi,
                                                 wref, h, kx, ky, nk, kb, knx, kny, klo,
                                                 khi, qctx, rpoly, nrp, rpb, rv, ws, wpt,
                                                 work):
                                    continue
                            if _hides(g, head, nxt, obb, owr, ouse, oplane, gwlo, gwhi, gslot,
                                      sg, sfr, shead, pool, pdep, dom, wcam, plane_tol, wref,
                                      h, kb, cam, n, wmin, ov, qctx, work):
                                occluded = True
                                by_cov = isc
                                hider = g
                                if not by_cov:
                                    last_g = g
                                break
                            if fuse_on and _front_part(g, occ, front, wref, h, 0.0, 0.0, 0.0,
                                                       kx, ky, nk, kb, knx, kny, klo, khi, cam,
                                                       n, wmin, wcam, plane_tol, nrp, rv,
                                                       work):
                                occluded = True
                                by_part = True
                                break
                        c_sub = cycles() if timed else 0
                        cyc_part[1] += c_sub - c_grp if timed else 0
                        fronts += 1 if by_part else 0
                        by_fuse = False
                        if not occluded and fuse_on and n_live - n_dead >= 2:
                            by_fuse = _fused_hide(
                                live, lpos, n_live, gbb, gwlo, gwhi, edges, ov,
                                head, nxt, obb, owr, ouse, oplane, gslot, sg, sfr, shead, pool,
                                pdep, dom, wcam, plane_tol, wref, h, kx, ky, nk, kb, cam, n,
                                wmin, qctx, rpoly, rpb, rv, ws, wpt, work, fuse, occ,
                                front)
                            occluded = by_fuse
                            fused += 1 if by_fuse else 0
                        by_sub = False
                        if not occluded and lv > 0:
                            qctx[QC_RELAX] = 0.0
                            by_sub = _refined_hide(
                                lv, covl, n_cov, live, lpos, n_live, gbb, gwlo, gwhi,
                                edges, occ, front, cam, n, tri, corners, sx, sy, h, wref,
                                wmin, wcam, plane_tol, kb, sub, work, fuse_on, fuse)
                            occluded = by_sub
                            refined += 1 if by_sub else 0
                        c_leaf = cycles() if timed else 0
                        cyc_part[2] += c_leaf - c_sub if timed else 0
                        if (hider >= 0 and lf >= 0 and ltried[lf] != pstamp
                                and b - a >= leaf_list and leaf_list > 0):
                            # The group that hid Q may hide the box of Q's whole leaf.
                            ltried[lf] = pstamp
                            work[4] += 1
                            if _leaf_hidden(lf, hider, by_cov, leaf_pts, origin, perm, sign,
                                            sx, sy, h, corners, wcam, plane_tol, edges, gbb,
                                            gwlo, gwhi, occ, lsc, strict, rpoly, rpb, ws, wpt,
                                            work):
                                lstamp[lf] = pstamp
                                work[5] += 1
                        cyc_part[3] += cycles() - c_leaf if timed else 0
                        if by_cov:
                            # Hidden behind a surface that covers every offset: it adds
                            # nothing as an occluder, and keeping it would make long lists
                            # quadratic.
                            hidden += 1
                            if mark:
                                hid[k] = 1
                            cyc_test += cycles() - c0 if timed else 0
                            continue
                        if occluded:
                            # Hidden (Alg. 1 ln 37): kept only to close the silhouettes of
                            # the surfaces it borders (the module docstring).
                            hidden += 1
                            # Hidden by separate groups together: it occludes as a visible
                            # one would (any listed triangle may), since no single group
                            # stands for it in later single-group tests.
                            dorm = not (by_fuse or by_sub or by_part)
                            if mark:
                                hid[k] = 1
                        else:
                            vis[p] = 1
                            tseen[p >> 3] |= np.uint8(1 << (p & 7))
                        tset[n_set] = p
                        n_set += 1
                    else:
                        dorm = True  # not seen at this pixel at all (Alg. 1 ln 12)
                        if mark:
                            hid[k] = 1
                        cyc_part[0] += cycles() - c0 if timed else 0
                    cyc_test += cycles() - c0 if timed else 0
                if not tri or not solid[p]:
                    continue
                c0 = cycles() if timed else 0
                # Become an occluder: counter-clockwise in the COS, robust area only.
                ar = area2(qv)
                if not robust_area(ar, qv):
                    continue
                q = n_polys
                n_polys += 1
                occl += 1
                for c in range(3):
                    src = c if ar > 0.0 else (3 - c) % 3
                    ov[q, c, 0] = qv[src, 0]
                    ov[q, c, 1] = qv[src, 1]
                    ow[q, c] = cam[src, 2]
                    oid[q, c] = vid[p, src]
                    oact[q, c] = True
                    opart[q, c] = -1
                pnx, pny, pnz, pnn = tri_normal(cam)
                pd = pnx * cam[0, 0] + pny * cam[0, 1] + pnz * cam[0, 2]
                tol = plane_tol * pnn
                pos = 0
                neg = 0
                for c in range(4):
                    dist = pnx * corners[c, 0] + pny * corners[c, 1] + pnz * corners[c, 2] - pd
                    if dist > tol:
                        pos += 1
                    elif dist < -tol:
                        neg += 1
                if neg == 4:
                    pnx, pny, pnz, pd = -pnx, -pny, -pnz, -pd
                ouse[q] = (pos == 4 or neg == 4) and tol > 0.0
                oplane[q, 0] = pnx
                oplane[q, 1] = pny
                oplane[q, 2] = pnz
                oplane[q, 3] = pd
                oplane[q, 4] = tol
                obb[q, 0] = min(ov[q, 0, 0], ov[q, 1, 0], ov[q, 2, 0])
                obb[q, 1] = max(ov[q, 0, 0], ov[q, 1, 0], ov[q, 2, 0])
                obb[q, 2] = min(ov[q, 0, 1], ov[q, 1, 1], ov[q, 2, 1])
                obb[q, 3] = max(ov[q, 0, 1], ov[q, 1, 1], ov[q, 2, 1])
                owr[q, 0] = min(ow[q, 0], ow[q, 1], ow[q, 2])
                owr[q, 1] = max(ow[q, 0], ow[q, 1], ow[q, 2])
                gbb[q, 0] = obb[q, 0]
                gbb[q, 1] = obb[q, 1]
                gbb[q, 2] = obb[q, 2]
                gbb[q, 3] = obb[q, 3]
                gwlo[q] = owr[q, 0]
                gwhi[q] = owr[q, 1]
                grp[q] = q
                head[q] = q
                tail[q] = q
                nxt[q] = -1
                gsize[q] = 1
                gcov[q] = False
                alive[q] = True
                _edges_new(q, ov, ow, grp, edges)
                gdorm[q] = dorm
                if dorm:
                    lpos[q] = -1
                else:
                    live[n_live] = q
                    lpos[q] = n_live
                    n_live += 1
                cpos[q] = -1
                gslot[q] = -1
                c_slot = cycles() if timed else 0
                cyc_part[4] += c_slot - c0 if timed else 0
                if eready[it_k] != tile:
                    eready[it_k] = tile
                    for e in range(3):
                        va = vid[p, e]
                        vb = vid[p, (e + 1) % 3]
                        if va < 0 or vb < 0:
                            eslot[3 * it_k + e] = -1
                            continue
                        lo_, hi_ = min(va, vb), max(va, vb)
                        row = _edge_slot(thash, hmask, tile, lo_, hi_)
                        if thash[row, 0] != tile:
                            thash[row, 0] = tile
                            thash[row, 1] = lo_
                            thash[row, 2] = hi_
                            thash[row, 3] = n_slots
                            n_slots += 1
                        eslot[3 * it_k + e] = thash[row, 3]
                c_fuse = cycles() if timed else 0
                cyc_part[5] += c_fuse - c_slot if timed else 0
                # Fuse along shared edges: the neighbour holds the edge reversed. The first
                # active occluder edge (in the order they were added) that does is taken.
                for e in range(3):
                    va = oid[q, e]
                    vb = oid[q, (e + 1) % 3]
                    if va < 0 or vb < 0:
                        continue
                    # q's edge e is its item's edge e, or 2 - e where q was turned round.
                    sid = eslot[3 * it_k + (e if ar > 0.0 else 2 - e)]
                    if sid < 0 or sstate[sid, 0] != pstamp:
                        continue
                    # The edge's chain runs newest first: the oldest active edge held the
                    # other way is taken.
                    node = -1
                    nd = sstate[sid, 1]
                    while nd >= 0:
                        if oact[nd // 3, nd % 3] and oid[nd // 3, nd % 3] == vb:
                            node = nd
                        nd = enext[nd]
                    while node >= 0:
                        r = node // 3
                        f = node - 3 * r
                        if oact[r, f]:
                            oact[r, f] = False
                            oact[q, e] = False
                            opart[r, f] = 3 * q + e
                            opart[q, e] = node
                            _edge_kill(node, grp[r], edges)
                            _edge_kill(3 * q + e, grp[q], edges)
                            g1 = grp[r]
                            g2 = grp[q]
                            if g1 != g2:
                                c1 = gcov[g1]
                                c2 = gcov[g2]
                                gs = _merge(g1, g2, grp, head, tail, nxt, gsize, gbb, gwlo,
                                            gwhi, gcov, alive, edges)
                                gd = g2 if gs == g1 else g1
                                if lpos[gd] >= 0:
                                    lpos[gd] = -1
                                    n_dead += 1
                                if gdorm[gs] and not gdorm[gd]:
                                    # A dormant group joins a tested one: it is tested now.
                                    gdorm[gs] = False
                                    if not gcov[gs]:
                                        live[n_live] = gs
                                        lpos[gs] = n_live
                                        n_live += 1
                                n_cov = _list_drop(gd, cpos, covl, n_cov)
                                if gcov[gs] and not (c1 if gs == g1 else c2):
                                    # The survivor takes the coverall flag of the other.
                                    n_cov, n_dead = _to_coverall(gs, lpos, covl, cpos, n_cov,
                                                                 n_dead)
                                # Depth grids: every group of GRID_MIN or more has one.
                                sd = gslot[gd]
                                ss = gslot[gs]
                                if sd >= 0:
                                    gslot[gd] = -1
                                    fslot[n_free] = sd
                                    n_free += 1
                                # The other's triangles join the survivor's grid when a
                                # test next asks for it (``_grid_sync``): a merge does not
                                # pay for a grid no test reads.
                                if ss < 0 and gsize[gs] >= GRID_MIN and not gdorm[gs]:
                                    if n_free > 0:
                                        n_free -= 1
                                        ss = fslot[n_free]
                                    else:
                                        ss = n_slot
                                        n_slot += 1
                                    gslot[gs] = ss
                                    shead[ss, GRID_CURSOR] = GRID_NEW
                            break
                        node = enext[node]
                # Register q's edges still active (an inactive edge never fuses again).
                for e in range(3):
                    va = oid[q, e]
                    vb = oid[q, (e + 1) % 3]
                    if va < 0 or vb < 0 or not oact[q, e]:
                        continue
                    sid = eslot[3 * it_k + (e if ar > 0.0 else 2 - e)]
                    if sid < 0:
                        continue
                    node = 3 * q + e
                    if sstate[sid, 0] != pstamp:
                        sstate[sid, 0] = pstamp
                        enext[node] = -1
                    else:
                        enext[node] = sstate[sid, 1]
                    sstate[sid, 1] = node
                c1 = cycles() if timed else 0
                cyc_part[6] += c1 - c_fuse if timed else 0
                g = grp[q]
                if not gcov[g] and not gdorm[g]:
                    # Coverall holds for every delta whatever frame proves it; the new
                    # triangle's depth is as good a frame as any.
                    region_at(corners, sx, sy, h, wref, rv, rr)
                    # The region polygon's box is the box of its corner squares, and a group
                    # covers it only inside its own box: most insertions stop at this
                    # comparison (in dense clutter, building the polygon for every one
                    # took a sixth of the resolution).
                    bx0, bx1, by0, by1 = bbox(rv, rr, 4)
                    n_r = 0
                    if (bx0 >= gbb[g, 0] and bx1 <= gbb[g, 1] and by0 >= gbb[g, 2]
                            and by1 <= gbb[g, 3]):
                        n_r = region_polygon(rv, rr, np.int64(4), np.bool_(False), rv, rr,
                                             rx, ry, tx_, ty_)
                    if n_r > 0:
                        _k_box(rx, ry, n_r, rb)
                    if n_r > 0 and _covers_q(g, edges, gbb, gwlo, gwhi,
                                             wref, h, rx, ry, n_r, rb, rnx, rny, rlo, rhi,
                                             strict, rpoly, 0, rpb, rv, ws, wpt,
                                             work):
                        gcov[g] = True
                        n_cov, n_dead = _to_coverall(g, lpos, covl, cpos, n_cov, n_dead)
                        zcut = min(zcut, _cover_depth(g, head, nxt, obb, owr, wcam, plane_tol,
                                                      h, rx, ry, n_r, wref))
                cyc_cover += cycles() - c1 if timed else 0
        counters[tile, 0] = tested
        counters[tile, 1] = hidden
        counters[tile, 2] = occl
        counters[tile, 3] = cut
        counters[tile, 4] = work[0]
        counters[tile, 5] = work[1]
        counters[tile, 6] = cyc_test
        # Making occluders: its three parts, which run back to back.
        counters[tile, 7] = cyc_part[4] + cyc_part[5] + cyc_part[6]
        counters[tile, 8] = cyc_cover
        counters[tile, 9] = cycles() - cyc_tile
        counters[tile, 10] = fused
        counters[tile, 11] = refined
        counters[tile, FRONT_PARTS] = fronts
        counters[tile, 12] = work[2]
        counters[tile, 13] = work[3]
        counters[tile, 14] = work[4]
        counters[tile, 15] = work[5]
        for c in range(len(CYCLE_PARTS)):
            counters[tile, CYCLE_PART0 + c] = cyc_part[c]
        for c in range(2):
            counters[tile, WALK0 + c] = work[6 + c]
        for c in range(n_set):
            tseen[tset[c] >> 3] = 0
    keep_alive(own)
