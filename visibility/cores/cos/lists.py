"""Per-pixel triangle lists of one view (paper Sec. 4.2, 5): conservative footprints, binning
into screen tiles, then one pass per tile into a slot sized by the tile's footprint pixels.

A primitive is listed at a pixel when its COS image, grown by the between-sample motion
(``space``), may meet the supported offsets there: it may cover some direction of the pixel
from some camera position. The pixel box where that can happen comes from projecting the
primitive from the four corners of the camera rectangle (a vertex seen from every offset lies
in the projective image of the rectangle, a convex quad spanned by the corner projections),
plus half a pixel. Points closer than ``View.near_w`` cannot be projected that way; a primitive
reaching into ``View.near_box`` is listed at every pixel of the view and left to the exact
per-pixel test, one that stays outside it is clipped to w >= near_w first (no ray of the view
reaches its nearer part).

Pixels are numbered tile-major (tiles of ``TILE`` x ``TILE``): the view is processed in runs of
tiles whose slots fit the memory budget.
Every primitive enters the lists in the order of ``order`` (front to back), so the lists come
out sorted without a per-list sort.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.borrow import borrow, keep_alive
from visibility.cores.cos.groups import PrimArrays, Screen, TileLists
from visibility.cores.cos.space import (
    load_prim,
    overlaps_share,
    project,
    quad_holds,
    region_share,
    tri_normal,
    triangle_holds,
)
from visibility.shares import run_shares, take_next

#: Screen tile side in pixels.
TILE = 8
#: Recent triangles per pixel that the early z of ``fill_lists`` tries to pair with the next
#: one along a shared edge.
PAIR_CANDIDATES = 4
#: Primitives per parallel chunk of ``footprints``.
FOOTPRINT_CHUNK = 256


@njit(cache=True, nogil=True, inline="always")
def region_at(corners, sx, sy, h, wref, rv, rr):  # pragma: no cover - numba
    """COS images (rv (4, 2)) and motion radii (rr (4,)) of the camera rectangle's corners at
    pixel centre (sx, sy), in the frame moving with depth ``wref``: the supported offsets (the
    paper's C_Delta) grown for the pixel."""
    for k in range(4):
        w = corners[k, 2]
        rv[k, 0] = corners[k, 0] - w * sx
        rv[k, 1] = corners[k, 1] - w * sy
        rr[k] = abs(w - wref) * h


@njit(cache=True, nogil=True)
def _edge_on(cam, corners, cscale):  # pragma: no cover - numba
    """Whether every camera position of the view lies in the triangle's plane: then each sees
    it edge-on, as a segment of no area, and it covers no sample. ``cscale``: the largest
    |coordinate| of ``corners`` (the same for every primitive of a view).

    Up to rounding only (64 ulps of the largest coordinate involved), never the plane tests'
    tolerance: a triangle parallel to the camera rectangle a nanometre in front of it is seen
    face-on from every camera position, and with that tolerance (1e-9 m) it was skipped here
    and missed (a patch 1e-9 m beyond a cell face, within its outline)."""
    nx, ny, nz, nn = tri_normal(cam)
    if not nn > 0.0:
        return False
    scale = cscale
    for i in range(3):
        for c in range(3):
            scale = max(scale, abs(cam[i, c]))
    tol = 64.0 * np.finfo(np.float64).eps * scale
    for k in range(4):
        d = (nx * (corners[k, 0] - cam[0, 0]) + ny * (corners[k, 1] - cam[0, 1])
             + nz * (corners[k, 2] - cam[0, 2]))
        if abs(d) > tol * nn:
            return False
    return True


@njit(cache=True, nogil=True)
def _pixel_span(lo, hi, origin, pw, size):  # pragma: no cover - numba
    """Inclusive range of pixels (width pw from ``origin``) whose closed square meets [lo, hi],
    widened by 1e-6 pixel against rounding."""
    a = (lo - origin) / pw - 1.0 - 1e-6
    b = (hi - origin) / pw + 1e-6
    a = max(a, -1.0)
    b = min(b, size + 1.0)
    if not a <= b:
        return 1, 0
    return max(int(np.ceil(a)), 0), min(int(np.floor(b)), size - 1)


@njit(cache=True, nogil=True, parallel=True)
def footprints(pts, start, npts, kind, order, sel, origin, perm, sign, corners, near_box,
               near_w, nx, ny, x_lo, y_lo, pw, plane_tol, rng):  # pragma: no cover - numba
    """Pixel box (rng[t] = i0, i1, j0, j1; i0 > i1 when empty) of primitive order[t], for the
    positions t in ``sel`` (the others are left as they are)."""
    # Chunks of primitives, each with its own scratch: an allocation per primitive cost as
    # much as its projection.
    n_sel = sel.shape[0]
    # Borrowed (``visibility.borrow``): no reference counting at the helpers' calls.
    pts = borrow(pts)
    start = borrow(start)
    npts = borrow(npts)
    kind = borrow(kind)
    order = borrow(order)
    sel = borrow(sel)
    origin = borrow(origin)
    perm = borrow(perm)
    sign = borrow(sign)
    corners = borrow(corners)
    near_box = borrow(near_box)
    # rng, which footprints writes in its parallel loop, stays owned (``visibility.borrow``).
    cscale = 0.0
    for k in range(4):
        for c in range(3):
            cscale = max(cscale, abs(corners[k, c]))
    # The corners lie at one or two depths (a front view's on w = 0, a side view's on w = 0
    # and w = 2 C): per depth, their x and y ranges bound the corners' projections with one
    # division per point and depth ((x - corner x) / (w - corner w) is monotone in the
    # corner's x, the depth difference being positive beyond near_w).
    cw = np.empty(4)
    cx = np.empty((4, 4))
    nw = 0
    for k in range(4):
        j = 0
        while j < nw and cw[j] != corners[k, 2]:
            j += 1
        if j == nw:
            cw[j] = corners[k, 2]
            cx[j, 0] = np.inf
            cx[j, 1] = -np.inf
            cx[j, 2] = np.inf
            cx[j, 3] = -np.inf
            nw += 1
        cx[j, 0] = min(cx[j, 0], corners[k, 0])
        cx[j, 1] = max(cx[j, 1], corners[k, 0])
        cx[j, 2] = min(cx[j, 2], corners[k, 1])
        cx[j, 3] = max(cx[j, 3], corners[k, 1])
    for c0 in prange((n_sel + FOOTPRINT_CHUNK - 1) // FOOTPRINT_CHUNK):
        cam_own = np.empty((8, 3))
        cam = borrow(cam_own)
        lo_own = np.empty(3)
        lo = borrow(lo_own)
        hi_own = np.empty(3)
        hi = borrow(hi_own)
        clip_own = np.empty((8, 3))
        clip = borrow(clip_own)
        for s in range(c0 * FOOTPRINT_CHUNK, min(n_sel, (c0 + 1) * FOOTPRINT_CHUNK)):
            t = sel[s]
            rng[t, 0] = 1
            rng[t, 1] = 0
            rng[t, 2] = 1
            rng[t, 3] = 0
            p = order[t]
            n = npts[p]
            load_prim(pts, start[p], n, origin, perm, sign, cam)
            for k in range(3):
                lo[k] = np.inf
                hi[k] = -np.inf
                for i in range(n):
                    lo[k] = min(lo[k], cam[i, k])
                    hi[k] = max(hi[k], cam[i, k])
            if not hi[2] > 0.0:
                continue  # behind every camera position of the view
            if kind[p] == 0 and _edge_on(cam, corners, cscale):
                continue
            if (lo[0] <= near_box[1] and hi[0] >= near_box[0] and lo[1] <= near_box[3]
                    and hi[1] >= near_box[2] and lo[2] <= near_box[5] and hi[2] >= near_box[4]):
                rng[t, 0] = 0
                rng[t, 1] = ny - 1
                rng[t, 2] = 0
                rng[t, 3] = nx - 1
                continue
            # Clip to w >= near_w: triangles by Sutherland-Hodgman, hulls (boxes) by their w range.
            m = 0
            if kind[p] == 0:
                for i in range(3):
                    j = (i + 1) % 3
                    wi = cam[i, 2]
                    wj = cam[j, 2]
                    if wi >= near_w:
                        clip[m, 0] = cam[i, 0]
                        clip[m, 1] = cam[i, 1]
                        clip[m, 2] = wi
                        m += 1
                    if (wi < near_w) != (wj < near_w):
                        s = (near_w - wi) / (wj - wi)
                        clip[m, 0] = cam[i, 0] + s * (cam[j, 0] - cam[i, 0])
                        clip[m, 1] = cam[i, 1] + s * (cam[j, 1] - cam[i, 1])
                        clip[m, 2] = near_w
                        m += 1
            else:
                w0 = max(lo[2], near_w)
                if w0 <= hi[2]:
                    for c in range(8):
                        clip[m, 0] = hi[0] if c & 1 else lo[0]
                        clip[m, 1] = hi[1] if c & 2 else lo[1]
                        clip[m, 2] = hi[2] if c & 4 else w0
                        m += 1
            if m == 0:
                continue
            ux0 = np.inf
            ux1 = -np.inf
            uy0 = np.inf
            uy1 = -np.inf
            for i in range(m):
                for j in range(nw):
                    # One division for both coordinates: a relative error of an ulp or two,
                    # far inside the spans' 1e-6 pixel widening. (clip w >= near_w lies
                    # beyond every corner.)
                    d = 1.0 / (clip[i, 2] - cw[j])
                    ux0 = min(ux0, (clip[i, 0] - cx[j, 1]) * d)
                    ux1 = max(ux1, (clip[i, 0] - cx[j, 0]) * d)
                    uy0 = min(uy0, (clip[i, 1] - cx[j, 3]) * d)
                    uy1 = max(uy1, (clip[i, 1] - cx[j, 2]) * d)
            j0, j1 = _pixel_span(ux0, ux1, x_lo, pw, nx)
            i0, i1 = _pixel_span(uy0, uy1, y_lo, pw, ny)
            if j0 > j1 or i0 > i1:
                continue
            rng[t, 0] = i0
            rng[t, 1] = i1
            rng[t, 2] = j0
            rng[t, 3] = j1
        keep_alive((cam_own, lo_own, hi_own, clip_own,))


@njit(cache=True, nogil=True)
def bin_tiles(rng, sel, tiles_x, tiles_y):  # pragma: no cover - numba
    """CSR (offsets (T + 1,), items) of the positions t in ``sel`` (increasing; the rows of
    ``rng`` ``footprints`` wrote) whose pixel box meets each tile, in increasing t (so in
    front-to-back order), and per tile the pixels of those boxes inside it (T,): a bound on
    the tile's list entries."""
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, dtype=np.int64)
    bound = np.zeros(n_tiles, dtype=np.int64)
    for s in range(sel.shape[0]):
        t = sel[s]
        if rng[t, 0] > rng[t, 1]:
            continue
        for ty in range(rng[t, 0] // TILE, rng[t, 1] // TILE + 1):
            rows = min(rng[t, 1], ty * TILE + TILE - 1) - max(rng[t, 0], ty * TILE) + 1
            for tx in range(rng[t, 2] // TILE, rng[t, 3] // TILE + 1):
                cols = min(rng[t, 3], tx * TILE + TILE - 1) - max(rng[t, 2], tx * TILE) + 1
                counts[ty * tiles_x + tx + 1] += 1
                bound[ty * tiles_x + tx] += rows * cols
    for k in range(n_tiles):
        counts[k + 1] += counts[k]
    fill = counts[:-1].copy()
    items = np.empty(counts[n_tiles], dtype=np.int64)
    for s in range(sel.shape[0]):
        t = sel[s]
        if rng[t, 0] > rng[t, 1]:
            continue
        for ty in range(rng[t, 0] // TILE, rng[t, 1] // TILE + 1):
            for tx in range(rng[t, 2] // TILE, rng[t, 3] // TILE + 1):
                k = ty * tiles_x + tx
                items[fill[k]] = t
                fill[k] += 1
    return counts, items, bound


def fill_lists(prims: PrimArrays, screen: Screen, order: np.ndarray, rng: np.ndarray,
               tile_off: np.ndarray, tile_items: np.ndarray, drop: np.ndarray, slot: np.ndarray,
               lists: TileLists, cut: np.ndarray) -> None:
    """The lists of tiles [tile0, tile1), in one pass: tile ``tile``'s go to ``entries`` from
    ``slot[tile - tile0]`` on (slot: prefix sums of the tiles' ``bin_tiles`` bounds), pixel by
    pixel, each in the order of ``order``, an entry naming its item by its place k -
    ``tile_off[tile]`` among the tile's (``groups.TileLists.items``); pixel ``loc`` of the
    tile (tile-major) starts at
    ``pstart[(tile - tile0) * TILE^2 + loc]`` and holds ``pcount[...]`` entries. Tiles are
    taken in the order ``torder`` (a permutation of [tile0, tile1)). Item k of ``tile_items``
    is left out where ``drop[k]`` is set (``drop`` empty: none are): the coarse pass found it
    hidden for the whole tile. ``prims`` (``groups.PrimArrays``), ``screen``
    (``groups.Screen``) and ``lists`` (``groups.TileLists``, filled here) are named groups.

    Early z while the lists are built (paper Sec. 5): a solid triangle that alone holds a
    pixel's whole offset region under every between-sample direction (``space.triangle_holds``),
    or with one of the last ``PAIR_CANDIDATES`` such triangles listed there that shares an
    edge with it (``space.quad_holds``), and lies beyond every camera position, meets every
    ray of the pixel no deeper than its (their) deepest vertex z; an item whose distance
    from the box exceeds z |(s, 1)| lies wholly beyond it on every ray (the argument of
    ``resolve``'s early z) and is not listed there.
    Items come front to back, so the cut only drops entries after the triangle that set it.
    ``cut[tile - tile0]`` gets the entries so dropped."""
    n_tiles = lists.tile1 - lists.tile0
    # One tile at a time to each of ``lists.shares`` threads, each taking the next as it
    # finishes one (tiles differ in work by orders of magnitude). Threads, not a prange loop:
    # compiled into a parallel loop, the tile's kernel was compiled twice
    # (``visibility.shares``).
    nxt = np.zeros(1, dtype=np.int64)
    run_shares(_fill_share, max(1, min(lists.shares, n_tiles)), prims, screen, order, rng,
               tile_off, tile_items, drop, slot, lists, cut, nxt)


@njit(cache=True, nogil=True)
def _fill_share(prims, screen, order, rng, tile_off, tile_items, drop, slot, lists, cut, nxt,
                share, k):  # pragma: no cover - numba
    """Share ``share`` of ``fill_lists``'s ``k`` (its arguments): the next tile of ``nxt``
    (shared by the shares) until none is left."""
    n_tiles = lists.tile1 - lists.tile0
    while True:
        it = take_next(nxt)
        if it >= n_tiles:
            break
        _fill_tile(it, prims, screen, order, rng, tile_off, tile_items, drop, slot, lists, cut)


@njit(cache=True, nogil=True)
def _fill_tile(it, prims, screen, order, rng, tile_off, tile_items, drop, slot, lists,
               cut):  # pragma: no cover - numba
    """The lists of the tile ``lists.torder[it]`` (``fill_lists``, its arguments)."""
    pts, start, npts, kind = prims.pts, prims.start, prims.npts, prims.kind
    vid, solid, gap = prims.vid, prims.solid, prims.gap
    origin, perm, sign, corners = screen.origin, screen.perm, screen.sign, screen.corners
    x_lo, y_lo, pw, plane_tol = screen.x_lo, screen.y_lo, screen.pw, screen.plane_tol
    entries, pstart, pcount, tile0, tile1, torder, tiles_x, _, _, _, _, block = lists
    npix = TILE * TILE
    wcam = max(corners[0, 2], corners[1, 2], corners[2, 2], corners[3, 2])
    # Borrowed (``visibility.borrow``): no reference counting at the helpers' calls.
    pts = borrow(pts)
    start = borrow(start)
    npts = borrow(npts)
    kind = borrow(kind)
    vid = borrow(vid)
    solid = borrow(solid)
    gap = borrow(gap)
    origin = borrow(origin)
    perm = borrow(perm)
    sign = borrow(sign)
    corners = borrow(corners)
    # entries, pstart, pcount and cut, which the parallel loop writes, stay owned
    # (``visibility.borrow``).
    torder = borrow(torder)
    order = borrow(order)
    tile_off = borrow(tile_off)
    tile_items = borrow(tile_items)
    drop = borrow(drop)
    slot = borrow(slot)
    tile = torder[it]
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    # The tile's samples: b x b pixels each (``groups.TileLists.block``).
    bs = block[tile]
    h = 0.5 * pw * bs
    base = slot[tile - tile0]
    size = slot[tile - tile0 + 1] - base
    pix0 = (tile - tile0) * npix
    if tile_off[tile] == tile_off[tile + 1]:
        # No item (open sky: nearly half an open scene's tiles): spared the scratch below.
        for loc in range(npix):
            pstart[pix0 + loc] = base
            pcount[pix0 + loc] = 0
        cut[tile - tile0] = 0
        return
    # The tile's scratch, owned by ``own`` to the tile's end and borrowed for the helpers:
    # the items' entries and pixels (tmp, tloc, cnt), an item's camera-space corners and
    # projection (cam, qv, qr); the offset region of each of the tile's pixels, computed once
    # for all its items (prv, prr, preg); the early-z cut (an item farther than zgap from the
    # box is hidden at the pixel; lray its rays' longest slope); early-z triangles that did
    # not hold a pixel's region alone, a ring per pixel (cand, czmax, cbox, cnext): the next
    # one may, fused with one of them along a shared edge (a wall's quad), and their scratch
    # (ccam, cv, cr); and whether a pixel is set up, at its first item (ready: open scenes
    # leave many pixels of a tile empty).
    own = (np.empty(size, dtype=np.int32), np.empty(size, dtype=np.int16),
           np.zeros(npix, dtype=np.int64), np.empty((8, 3)), np.empty((8, 2)), np.empty(8),
           np.empty((npix, 4, 2)), np.empty((npix, 4)), np.empty((npix, 12)), np.empty(npix),
           np.full(npix, np.inf), np.full((npix, PAIR_CANDIDATES), -1, dtype=np.int64),
           np.empty((npix, PAIR_CANDIDATES)), np.empty((npix, PAIR_CANDIDATES, 4)),
           np.zeros(npix, dtype=np.int64), np.empty((3, 3)), np.empty((3, 2)), np.empty(3),
           np.zeros(npix, dtype=np.bool_))
    (tmp, tloc, cnt, cam, qv, qr, prv, prr, preg, lray, zgap, cand, czmax, cbox, cnext, ccam,
     cv, cr, ready) = borrow(own)
    m = 0
    ncut = 0
    zall = np.inf  # the largest zgap of the tile's pixels
    skip = drop.shape[0] > 0
    for k in range(tile_off[tile], tile_off[tile + 1]):
        if skip and drop[k]:
            continue
        t = tile_items[k]
        p = order[t]
        if gap[p] > zall:
            # Hidden at every pixel of the tile, as is every later item.
            for k2 in range(k, tile_off[tile + 1]):
                t2 = tile_items[k2]
                if not (skip and drop[k2]):
                    ncut += (((min(rng[t2, 1], ty * TILE + TILE - 1) - ty * TILE) // bs
                              - (max(rng[t2, 0], ty * TILE) - ty * TILE) // bs + 1)
                             * ((min(rng[t2, 3], tx * TILE + TILE - 1) - tx * TILE) // bs
                                - (max(rng[t2, 2], tx * TILE) - tx * TILE) // bs + 1))
            break
        # The item's samples in the tile (rows i0..i1, columns j0..j1 of them).
        i0 = (max(rng[t, 0], ty * TILE) - ty * TILE) // bs
        i1 = (min(rng[t, 1], ty * TILE + TILE - 1) - ty * TILE) // bs
        j0 = (max(rng[t, 2], tx * TILE) - tx * TILE) // bs
        j1 = (min(rng[t, 3], tx * TILE + TILE - 1) - tx * TILE) // bs
        # Cut at every sample it meets (behind what holds each): the item costs no more.
        alive = False
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                if not gap[p] > zgap[i * TILE + j]:
                    alive = True
                    break
            if alive:
                break
        if not alive:
            ncut += (i1 - i0 + 1) * (j1 - j0 + 1)
            continue
        n = npts[p]
        load_prim(pts, start[p], n, origin, perm, sign, cam)
        tri = kind[p] == 0
        # A possible early-z occluder: solid, beyond every camera position.
        occ = tri and solid[p] != 0
        zmax = -np.inf
        for c in range(n):
            if not cam[c, 2] >= wcam + plane_tol:
                occ = False
            zmax = max(zmax, cam[c, 2])
        newz = False
        for i in range(i0, i1 + 1):
            sy = y_lo + (ty * TILE + (i + 0.5) * bs) * pw
            for j in range(j0, j1 + 1):
                sx = x_lo + (tx * TILE + (j + 0.5) * bs) * pw
                loc = i * TILE + j
                if not ready[loc]:
                    ready[loc] = True
                    region_at(corners, sx, sy, h, 0.0, prv[loc], prr[loc])
                    region_share(prv[loc], prr[loc], preg[loc])
                    lray[loc] = np.sqrt(1.0 + (abs(sx) + h) ** 2 + (abs(sy) + h) ** 2)
                if gap[p] > zgap[loc]:
                    ncut += 1
                    continue
                project(cam, n, sx, sy, h, 0.0, qv, qr)
                if not overlaps_share(qv, qr, n, tri, prv[loc], prr[loc], preg[loc]):
                    continue
                tmp[m] = k - tile_off[tile]  # the item, within its tile
                tloc[m] = loc
                cnt[loc] += 1
                m += 1
                if not occ or zmax * lray[loc] + plane_tol >= zgap[loc]:
                    continue
                # The region's box (``preg``) inside the triangle's: most stop here.
                if (min(qv[0, 0], qv[1, 0], qv[2, 0]) <= preg[loc, 0]
                        and max(qv[0, 0], qv[1, 0], qv[2, 0]) >= preg[loc, 1]
                        and min(qv[0, 1], qv[1, 1], qv[2, 1]) <= preg[loc, 2]
                        and max(qv[0, 1], qv[1, 1], qv[2, 1]) >= preg[loc, 3]
                        and triangle_holds(qv, qr, prv[loc], prr[loc])):
                    zgap[loc] = zmax * lray[loc] + plane_tol
                    newz = True
                    continue
                bx0 = min(qv[0, 0], qv[1, 0], qv[2, 0])
                bx1 = max(qv[0, 0], qv[1, 0], qv[2, 0])
                by0 = min(qv[0, 1], qv[1, 1], qv[2, 1])
                by1 = max(qv[0, 1], qv[1, 1], qv[2, 1])
                for c in range(PAIR_CANDIDATES):
                    pc = cand[loc, c]
                    zq = max(zmax, czmax[loc, c])
                    if pc < 0 or zq * lray[loc] + plane_tol >= zgap[loc]:
                        continue
                    # The pair's box must hold the region's, and they must share an edge.
                    if (min(bx0, cbox[loc, c, 0]) > preg[loc, 0]
                            or max(bx1, cbox[loc, c, 1]) < preg[loc, 1]
                            or min(by0, cbox[loc, c, 2]) > preg[loc, 2]
                            or max(by1, cbox[loc, c, 3]) < preg[loc, 3]):
                        continue
                    common = 0
                    for a in range(3):
                        for b in range(3):
                            if vid[p, a] == vid[pc, b]:
                                common += 1
                    if common < 2:
                        continue
                    load_prim(pts, start[pc], 3, origin, perm, sign, ccam)
                    project(ccam, 3, sx, sy, h, 0.0, cv, cr)
                    if quad_holds(qv, qr, vid[p], cv, cr, vid[pc], prv[loc], prr[loc]):
                        zgap[loc] = zq * lray[loc] + plane_tol
                        newz = True
                        break
                c = cnext[loc]
                cand[loc, c] = p
                czmax[loc, c] = zmax
                cbox[loc, c, 0] = bx0
                cbox[loc, c, 1] = bx1
                cbox[loc, c, 2] = by0
                cbox[loc, c, 3] = by1
                cnext[loc] = (c + 1) % PAIR_CANDIDATES
        if newz:
            zall = -np.inf
            for loc in range(npix):
                zall = max(zall, zgap[loc])
    cut[tile - tile0] = ncut
    pos = base
    for loc in range(npix):
        pstart[pix0 + loc] = pos
        pcount[pix0 + loc] = cnt[loc]
        cnt[loc] = pos
        pos += pcount[pix0 + loc]
    for e in range(m):
        loc = tloc[e]
        entries[cnt[loc]] = tmp[e]
        cnt[loc] += 1
    keep_alive(own)
