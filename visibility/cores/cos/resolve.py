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
  the occluder under every offset and delta, and one point of K (its centroid) decides. Inside:
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

Every listed triangle then becomes an occluder (ln 37-47), visible or not, unless a coverall
occluder hides it: the depth test makes any triangle a sound occluder, and a hidden or unseen
neighbour still closes the silhouette of the surface it belongs to (the paper keeps only
visible ones). It is fused with every occluder
triangle that shares one of its edges (welded vertex ids), merging their groups. A group whose
silhouette stays clear of the whole offset region and covers it is flagged *coverall* (ln
44-45): later triangles skip straight to the depth test.
Hulls (moving triangles, spheres) are occludees only; a triangle seen edge-on in the COS (no
robust area) does not occlude.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.cores.cos.lists import TILE, region_at
from visibility.cores.cos.space import (
    MAX_POLY,
    area2,
    capsule_hits,
    in_triangle,
    load_prim,
    project,
    region_polygon,
)


@njit(cache=True, nogil=True)
def _clear_of_silhouette(g, head, nxt, ov, ow, oact, wref, h, kx, ky, nk):  # pragma: no cover
    """True when no active edge capsule of group g (frame of depth wref) meets polygon K."""
    r = head[g]
    while r >= 0:
        for f in range(3):
            if oact[r, f]:
                b = (f + 1) % 3
                rad = max(abs(ow[r, f] - wref), abs(ow[r, b] - wref)) * h
                if capsule_hits(ov[r, f, 0], ov[r, f, 1], ov[r, b, 0], ov[r, b, 1], rad,
                                kx, ky, nk):
                    return False
        r = nxt[r]
    return True


@njit(cache=True, nogil=True)
def _covers(g, head, nxt, ov, ow, oact, gbb, wref, h, kx, ky, nk):  # pragma: no cover - numba
    """Whether group g covers polygon K (frame of depth wref) under every offset in it and
    every delta."""
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
    if x0 < gbb[g, 0] or x1 > gbb[g, 1] or y0 < gbb[g, 2] or y1 > gbb[g, 3]:
        return False
    if not _clear_of_silhouette(g, head, nxt, ov, ow, oact, wref, h, kx, ky, nk):
        return False
    cx /= nk
    cy /= nk
    r = head[g]
    while r >= 0:
        if in_triangle(cx, cy, ov[r]):
            return True
        r = nxt[r]
    return False


@njit(cache=True, nogil=True)
def _in_front(g, head, nxt, obb, owr, ouse, oplane, wref, h, kx0, kx1, ky0, ky1, qcam,
              nq):  # pragma: no cover - numba
    """Whether every triangle of group g that can reach K's box is in front of all of Q."""
    r = head[g]
    while r >= 0:
        grow = max(abs(owr[r, 0] - wref), abs(owr[r, 1] - wref)) * h
        if not (obb[r, 1] + grow < kx0 or obb[r, 0] - grow > kx1 or obb[r, 3] + grow < ky0
                or obb[r, 2] - grow > ky1):
            if not ouse[r]:
                return False
            nx, ny, nz, d, tol = oplane[r, 0], oplane[r, 1], oplane[r, 2], oplane[r, 3], \
                oplane[r, 4]
            # Behind or on the plane, strictly behind somewhere: the rays that meet Q on T's
            # plane meet T at the same point, a set of no measure (a shared edge).
            behind = False
            for i in range(nq):
                dist = nx * qcam[i, 0] + ny * qcam[i, 1] + nz * qcam[i, 2] - d
                if dist > tol:
                    return False
                if dist < -tol:
                    behind = True
            if not behind:
                return False
        r = nxt[r]
    return True


@njit(cache=True, nogil=True)
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
def _edge_slot(hk0, hk1, mask, va, vb):  # pragma: no cover - numba
    """Slot of directed edge (va, vb) in the open-addressing table (hk0, hk1) of ``mask + 1``
    slots: the slot holding it, or the empty one (hk0 == -1) where it would go."""
    x = va * 0x9E3779B1 + vb * 0x85EBCA77  # may wrap for huge ids: only spreads the bits
    x ^= x >> 17
    k = x & mask
    while hk0[k] >= 0 and (hk0[k] != va or hk1[k] != vb):
        k = (k + 1) & mask
    return k


@njit(cache=True, nogil=True)
def _merge(g1, g2, grp, head, tail, nxt, gbb, gcov, alive):  # pragma: no cover - numba
    if g1 == g2:
        return g1
    r = head[g2]
    while r >= 0:
        grp[r] = g1
        r = nxt[r]
    nxt[tail[g1]] = head[g2]
    tail[g1] = tail[g2]
    gbb[g1, 0] = min(gbb[g1, 0], gbb[g2, 0])
    gbb[g1, 1] = max(gbb[g1, 1], gbb[g2, 1])
    gbb[g1, 2] = min(gbb[g1, 2], gbb[g2, 2])
    gbb[g1, 3] = max(gbb[g1, 3], gbb[g2, 3])
    gcov[g1] = gcov[g1] or gcov[g2]
    alive[g2] = False
    return g1


@njit(cache=True, nogil=True, parallel=True)
def resolve_tiles(pts, start, npts, kind, vid, gap, entries, list_off, tile0, tile1, tiles_x,
                  nx, ny, x_lo, y_lo, pw, origin, perm, sign, corners, plane_tol, known, vis,
                  counters):  # pragma: no cover - numba
    """Run Alg. 1 on every pixel of tiles [tile0, tile1): set ``vis[p] = 1`` for each primitive
    p found visible. ``entries`` holds the lists of those tiles from ``list_off[tile0 * TILE^2]``
    on, each in nondecreasing ``gap`` (the distance from the cell box to the primitive's
    bounding box, metres); ``known[p]`` marks primitives already known visible (tested no more,
    still occluders). ``counters[tile]`` gets (entries tested, entries found occluded, occluder
    triangles, entries cut by the early-z depth)."""
    h = 0.5 * pw
    npix = TILE * TILE
    base = list_off[tile0 * npix]
    # Largest camera depth of the view's camera rectangle (0 for a front frustum).
    wcam = max(corners[0, 2], corners[1, 2], corners[2, 2], corners[3, 2])
    for tile in prange(tile0, tile1):
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        pix0 = tile * npix
        lmax = 0
        for loc in range(npix):
            lmax = max(lmax, list_off[pix0 + loc + 1] - list_off[pix0 + loc])
        if lmax == 0:
            continue
        cam = np.empty((8, 3))
        qv = np.empty((8, 2))
        qr = np.empty(8)
        rv = np.empty((4, 2))
        rr = np.empty(4)
        kx = np.empty(MAX_POLY)
        ky = np.empty(MAX_POLY)
        tx_ = np.empty(MAX_POLY)
        ty_ = np.empty(MAX_POLY)
        rx = np.empty(MAX_POLY)
        ry = np.empty(MAX_POLY)
        ov = np.empty((lmax, 3, 2))
        ow = np.empty((lmax, 3))
        owr = np.empty((lmax, 2))
        oid = np.empty((lmax, 3), dtype=np.int64)
        oact = np.empty((lmax, 3), dtype=np.bool_)
        oplane = np.empty((lmax, 5))
        ouse = np.empty(lmax, dtype=np.bool_)
        obb = np.empty((lmax, 4))
        grp = np.empty(lmax, dtype=np.int64)
        nxt = np.empty(lmax, dtype=np.int64)
        head = np.empty(lmax, dtype=np.int64)
        tail = np.empty(lmax, dtype=np.int64)
        gbb = np.empty((lmax, 4))
        gcov = np.empty(lmax, dtype=np.bool_)
        alive = np.empty(lmax, dtype=np.bool_)
        cov = np.empty(lmax, dtype=np.int64)
        # Edge hash (fusion): directed edge (hk0, hk1) -> first occluder edge q * 3 + e holding
        # it (hfirst), chained in insertion order through enext; at most a half full.
        hcap = 8
        while hcap < 6 * lmax:
            hcap *= 2
        hk0 = np.empty(hcap, dtype=np.int64)
        hk1 = np.empty(hcap, dtype=np.int64)
        hfirst = np.empty(hcap, dtype=np.int64)
        hlast = np.empty(hcap, dtype=np.int64)
        enext = np.empty(3 * lmax, dtype=np.int64)
        tested = 0
        hidden = 0
        occl = 0
        cut = 0
        for loc in range(npix):
            i = ty * TILE + loc // TILE
            j = tx * TILE + loc % TILE
            if i >= ny or j >= nx:
                continue
            a = list_off[pix0 + loc] - base
            b = list_off[pix0 + loc + 1] - base
            if a == b:
                continue
            sx = x_lo + (j + 0.5) * pw
            sy = y_lo + (i + 0.5) * pw
            # Longest ray per unit of depth over the pixel's directions: a point at distance g
            # from the box (so from every camera position, which lies on the box) is at depth
            # at least g / lray on any ray of this pixel.
            lray = np.sqrt(1.0 + (abs(sx) + h) ** 2 + (abs(sy) + h) ** 2)
            hs = 8
            while hs < 6 * (b - a):
                hs *= 2
            hmask = hs - 1
            hk0[:hs] = -1
            n_polys = 0
            n_cov = 0
            # Early z: every ray of the pixel (any camera position, any direction in it) meets
            # a coverall occluder at depth <= zcut, before anything wholly deeper.
            zcut = np.inf
            for k in range(a, b):
                p = entries[k]
                if gap[p] > zcut * lray + plane_tol:
                    # The lists are sorted by gap: this entry and all later ones lie beyond
                    # zcut on every ray of the pixel.
                    cut += b - k
                    break
                n = npts[p]
                tri = kind[p] == 0
                load_prim(pts, start[p], n, origin, perm, sign, cam)
                wmin = cam[0, 2]
                for c in range(1, n):
                    wmin = min(wmin, cam[c, 2])
                if wmin > zcut + plane_tol:
                    cut += 1
                    continue
                # Reference depth: Q's mean depth, so Q barely moves and each occluder moves
                # by its depth difference to Q (the relative motion that matters).
                wref = 0.0
                for c in range(n):
                    wref += cam[c, 2]
                wref /= n
                project(cam, n, sx, sy, h, wref, qv, qr)
                if known[p] == 0:
                    region_at(corners, sx, sy, h, wref, rv, rr)
                    nk = region_polygon(qv, qr, n, tri, rv, rr, kx, ky, tx_, ty_)
                    if nk > 0:
                        tested += 1
                        kx0 = np.inf
                        kx1 = -np.inf
                        ky0 = np.inf
                        ky1 = -np.inf
                        for e in range(nk):
                            kx0 = min(kx0, kx[e])
                            kx1 = max(kx1, kx[e])
                            ky0 = min(ky0, ky[e])
                            ky1 = max(ky1, ky[e])
                        occluded = False
                        # Coverall occluders first (the paper's early discard): they need
                        # only the depth test.
                        for c in range(n_cov):
                            g = cov[c]
                            if alive[g] and _in_front(g, head, nxt, obb, owr, ouse, oplane, wref,
                                                      h, kx0, kx1, ky0, ky1, cam, n):
                                occluded = True
                                break
                        if occluded:
                            # Hidden behind a surface that covers every offset: it adds
                            # nothing as an occluder, and keeping it would make long lists
                            # quadratic.
                            hidden += 1
                            continue
                        for g in range(n_polys):
                            if not alive[g] or gcov[g]:
                                continue
                            if not _covers(g, head, nxt, ov, ow, oact, gbb, wref, h, kx, ky, nk):
                                continue
                            if _in_front(g, head, nxt, obb, owr, ouse, oplane, wref, h, kx0, kx1,
                                         ky0, ky1, cam, n):
                                occluded = True
                                break
                        if occluded:
                            hidden += 1
                        else:
                            vis[p] = 1
                if not tri:
                    continue
                # Become an occluder: counter-clockwise in the COS, robust area only.
                ar = area2(qv)
                e1 = np.hypot(qv[1, 0] - qv[0, 0], qv[1, 1] - qv[0, 1])
                e2 = np.hypot(qv[2, 0] - qv[0, 0], qv[2, 1] - qv[0, 1])
                if not abs(ar) > 1e-9 * e1 * e2:
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
                ux, uy, uz = cam[1, 0] - cam[0, 0], cam[1, 1] - cam[0, 1], cam[1, 2] - cam[0, 2]
                wx, wy, wz = cam[2, 0] - cam[0, 0], cam[2, 1] - cam[0, 1], cam[2, 2] - cam[0, 2]
                pnx = uy * wz - uz * wy
                pny = uz * wx - ux * wz
                pnz = ux * wy - uy * wx
                pd = pnx * cam[0, 0] + pny * cam[0, 1] + pnz * cam[0, 2]
                tol = plane_tol * np.sqrt(pnx * pnx + pny * pny + pnz * pnz)
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
                gbb[q, 0] = min(ov[q, 0, 0], ov[q, 1, 0], ov[q, 2, 0])
                gbb[q, 1] = max(ov[q, 0, 0], ov[q, 1, 0], ov[q, 2, 0])
                gbb[q, 2] = min(ov[q, 0, 1], ov[q, 1, 1], ov[q, 2, 1])
                gbb[q, 3] = max(ov[q, 0, 1], ov[q, 1, 1], ov[q, 2, 1])
                grp[q] = q
                head[q] = q
                tail[q] = q
                nxt[q] = -1
                gcov[q] = False
                alive[q] = True
                # Fuse along shared edges: the neighbour holds the edge reversed. The first
                # active occluder edge (in the order they were added) that does is taken.
                for e in range(3):
                    va = oid[q, e]
                    vb = oid[q, (e + 1) % 3]
                    if va < 0 or vb < 0:
                        continue
                    slot = _edge_slot(hk0, hk1, hmask, vb, va)
                    if hk0[slot] < 0:
                        continue
                    node = hfirst[slot]
                    while node >= 0:
                        r = node // 3
                        f = node - 3 * r
                        if oact[r, f]:
                            oact[r, f] = False
                            oact[q, e] = False
                            was = gcov[grp[r]]
                            g1 = _merge(grp[r], grp[q], grp, head, tail, nxt, gbb, gcov, alive)
                            if gcov[g1] and not was:
                                cov[n_cov] = g1
                                n_cov += 1
                            break
                        node = enext[node]
                # Register q's edges still active (an inactive edge never fuses again).
                for e in range(3):
                    va = oid[q, e]
                    vb = oid[q, (e + 1) % 3]
                    if va < 0 or vb < 0 or not oact[q, e]:
                        continue
                    slot = _edge_slot(hk0, hk1, hmask, va, vb)
                    node = 3 * q + e
                    enext[node] = -1
                    if hk0[slot] < 0:
                        hk0[slot] = va
                        hk1[slot] = vb
                        hfirst[slot] = node
                    else:
                        enext[hlast[slot]] = node
                    hlast[slot] = node
                g = grp[q]
                if not gcov[g]:
                    # Coverall holds for every delta whatever frame proves it; the new
                    # triangle's depth is as good a frame as any.
                    region_at(corners, sx, sy, h, wref, rv, rr)
                    n_r = region_polygon(rv, rr, 4, False, rv, rr, rx, ry, tx_, ty_)
                    if n_r > 0:
                        gcov[g] = _covers(g, head, nxt, ov, ow, oact, gbb, wref, h, rx, ry,
                                          n_r)
                        if gcov[g]:
                            cov[n_cov] = g
                            n_cov += 1
                            zcut = min(zcut, _cover_depth(g, head, nxt, obb, owr, wcam,
                                                          plane_tol, h, rx, ry, n_r, wref))
        counters[tile, 0] = tested
        counters[tile, 1] = hidden
        counters[tile, 2] = occl
        counters[tile, 3] = cut
