"""Geometry generation and rasterization into the k-buffers (paper Secs. 4.1-4.2, phases P1
and P2), on the CPU: numba kernels parallel over triangles (set-up) and over bands of pixel
rows (rasterization; a band's pixels belong to one thread, so no atomics are needed).

Camera space: x right, y up, looking along -z; depth z = -z_cam from v*, metres. Image
coordinates u = x / z, v = y / z in [-tan, tan]; pixel column (u / tan + 1) res / 2, row
(1 - v / tan) res / 2. Fragments are sampled at pixel centres; depth is perspective-correct
(1 / z interpolated in screen space), float64.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from visibility.borrow import NO_REFCOUNT
from visibility.cancel import flag_set
from visibility.cores.trim_regions.kbuffer import (
    BACK,
    FRONT,
    LANE_BITS,
    LANE_MASK,
    SEALED,
    TRIM,
    TRIMMED,
    K,
    band_stride,
    joined_pieces,
    trim_holds,
)
from visibility.cores.trim_regions.silhouettes import PIECE_COLUMN


class SetUp(NamedTuple):
    """A view's set-up static triangles (``setup_triangles``), as ``raster_surfaces`` reads
    them: ``tri_ids`` (m,) the triangle id of each row, ``facing`` (m,) > 0 for a front face
    from v*, ``poly`` (m, P, 3) the near-clipped polygon (pixel x, y and 1 / depth),
    ``npoly`` (m,) its corner count and ``box`` (m, 4) its pixel box (x0, x1, y0, y1)."""

    tri_ids: np.ndarray
    facing: np.ndarray
    poly: np.ndarray
    npoly: np.ndarray
    box: np.ndarray


class Camera(NamedTuple):
    """A view from v*: ``vstar`` (3,) metres, world-to-camera ``rot`` (3, 3), ``tan`` the
    widened face's half-angle tangent and ``res`` pixels across it."""

    vstar: np.ndarray
    rot: np.ndarray
    tan: float
    res: int

#: Rows of pixels per band of the parallel rasterization.
BAND_ROWS = 8
#: Triangles per parallel chunk of ``setup_triangles`` (one scratch polygon each).
SETUP_CHUNK = 512


@njit(cache=True, nogil=True, parallel=True)
def to_camera(verts, vstar, rot):  # pragma: no cover - numba
    """(n, 3) camera-space positions of ``verts`` (n, 3) metres for viewpoint and rotation."""
    n = verts.shape[0]
    out = np.empty((n, 3))
    for i in prange(n):
        p0 = verts[i, 0] - vstar[0]
        p1 = verts[i, 1] - vstar[1]
        p2 = verts[i, 2] - vstar[2]
        for r in range(3):
            out[i, r] = rot[r, 0] * p0 + rot[r, 1] * p1 + rot[r, 2] * p2
    return out


@njit(cache=True, nogil=True, parallel=True)
def boxes_to_camera(lo, hi, sel, vstar, rot):  # pragma: no cover - numba
    """(8 k, 3) camera-space corners of the boxes [lo, hi] (n, 3) metres picked by ``sel``
    (k,), corner c of a box taking its high end along axis a where bit a of c is set:
    ``to_camera`` of those corners, without making them."""
    k = sel.shape[0]
    out = np.empty((8 * k, 3))
    for i in prange(k):
        b = sel[i]
        for c in range(8):
            p0 = (hi[b, 0] if c & 1 else lo[b, 0]) - vstar[0]
            p1 = (hi[b, 1] if c & 2 else lo[b, 1]) - vstar[1]
            p2 = (hi[b, 2] if c & 4 else lo[b, 2]) - vstar[2]
            for r in range(3):
                out[8 * i + c, r] = rot[r, 0] * p0 + rot[r, 1] * p1 + rot[r, 2] * p2
    return out


@njit(cache=True, nogil=True, inline="always")
def _clip_edge(px, py, pz, qx, qy, qz, near, pts, m):  # pragma: no cover - numba
    """Append to ``pts`` (4, 3) from row m the corners edge p-q (camera space) gives a polygon
    clipped to depth ``near``: p when it is in front, and the crossing when p and q lie on
    either side. Returns the new count. Scalars, not array views: a view per corner counted a
    reference to ``cam`` on the cache line the other threads count theirs on."""
    zp = -pz
    zq = -qz
    pin = zp >= near
    if pin:
        pts[m, 0] = px
        pts[m, 1] = py
        pts[m, 2] = pz
        m += 1
    if pin != (zq >= near):
        t = (zp - near) / (zp - zq)
        pts[m, 0] = px + t * (qx - px)
        pts[m, 1] = py + t * (qy - py)
        pts[m, 2] = pz + t * (qz - pz)
        m += 1
    return m


@njit(cache=True, nogil=True, parallel=True)
def setup_triangles(cam, faces, rows, need, near, tan, res, facing, poly, npoly,
                    box):  # pragma: no cover
    """Clip triangles to the near plane and project them (P1).

    Parameters
    ----------
    cam : (n, 3) camera-space vertices; faces : (m, 3) int64 vertex rows; rows : (s,) int64
        the triangles (rows of ``faces``) to set up.
    need : (s,) bool, the rows to clip and project (those of the leaves a view draws); every
        row gets its ``facing`` (silhouettes need it), the others no polygon (``npoly`` 0).
    near, tan, res : near depth (m), half-angle tangent, pixels across.
    facing : (s,) int8 out, +1 front-facing (counter-clockwise towards v*), -1 back-facing,
        0 edge-on (geometric: also set for triangles wholly nearer than ``near``).
    poly : (s, 4, 3) out, clipped polygon corners as (column, row, 1 / depth), in pixels.
    npoly : (s,) int64 out, corners (0: nothing in front of the near plane).
    box : (s, 4) int64 out, pixel range [x0, x1) x [y0, y1) of the corners (may be empty).
    """
    half = 0.5 * res
    n_rows = rows.shape[0]
    # Scratch per chunk of triangles: an allocation per triangle cost as much as its set-up.
    for ch in prange((n_rows + SETUP_CHUNK - 1) // SETUP_CHUNK):
        pts = np.empty((4, 3))
        for i in range(ch * SETUP_CHUNK, min(n_rows, (ch + 1) * SETUP_CHUNK)):
            f = rows[i]
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = cam[i0, 0], cam[i0, 1], cam[i0, 2]
            bx, by, bz = cam[i1, 0], cam[i1, 1], cam[i1, 2]
            cx, cy, cz = cam[i2, 0], cam[i2, 1], cam[i2, 2]
            e1x, e1y, e1z = bx - ax, by - ay, bz - az
            e2x, e2y, e2z = cx - ax, cy - ay, cz - az
            nx = e1y * e2z - e1z * e2y
            ny = e1z * e2x - e1x * e2z
            nz = e1x * e2y - e1y * e2x
            sd = -(nx * ax + ny * ay + nz * az)
            facing[i] = 1 if sd > 0 else (-1 if sd < 0 else 0)
            if not need[i]:
                npoly[i] = 0
                box[i, 0] = 0
                box[i, 1] = 0
                box[i, 2] = 0
                box[i, 3] = 0
                continue
            m = _clip_edge(ax, ay, az, bx, by, bz, near, pts, 0)
            m = _clip_edge(bx, by, bz, cx, cy, cz, near, pts, m)
            m = _clip_edge(cx, cy, cz, ax, ay, az, near, pts, m)
            npoly[i] = m
            if m == 0:
                box[i, 0] = 0
                box[i, 1] = 0
                box[i, 2] = 0
                box[i, 3] = 0
                continue
            x0, x1, y0, y1 = 1e300, -1e300, 1e300, -1e300
            for k in range(m):
                z = -pts[k, 2]
                px = (pts[k, 0] / z / tan + 1.0) * half
                py = (1.0 - pts[k, 1] / z / tan) * half
                poly[i, k, 0] = px
                poly[i, k, 1] = py
                poly[i, k, 2] = 1.0 / z
                x0 = min(x0, px)
                x1 = max(x1, px)
                y0 = min(y0, py)
                y1 = max(y1, py)
            box[i, 0] = max(0, int(np.floor(x0 - 0.5)))
            box[i, 1] = min(res, int(np.ceil(x1 + 0.5)))
            box[i, 2] = max(0, int(np.floor(y0 - 0.5)))
            box[i, 3] = min(res, int(np.ceil(y1 + 0.5)))


@njit(cache=True, nogil=True, inline="always")
def _gap(a0, a1, b0, b1):  # pragma: no cover - numba
    """Depth between the ranges [a0, a1] and [b0, b1] (0 where they meet)."""
    return max(0.0, max(b0 - a1, a0 - b1))


@njit(cache=True, nogil=True, inline="always")
def _join(p, a, b, depth, idents, umbra, far):  # pragma: no cover - numba
    """Merge held trim b of pixel p into held trim a (slot b is then free)."""
    i, j = a >> LANE_BITS, a & LANE_MASK
    k, m = b >> LANE_BITS, b & LANE_MASK
    depth[i, p, j] = min(depth[i, p, j], depth[k, p, m])
    far[i, p, j] = max(far[i, p, j], far[k, p, m])
    umbra[i, p, j] = min(umbra[i, p, j], umbra[k, p, m])
    idents[i, p, j] = joined_pieces(idents[i, p, j], idents[k, p, m])


@njit(cache=True, nogil=True, inline="always")
def _ident_bit(ident):  # pragma: no cover - numba
    """One of 64 bits for a trim's ident (a piece or piece set): equal idents, equal bits."""
    return np.uint64(1) << ((np.uint64(ident) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(58))


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _nearest_pair(p, depth, kinds, idents, far, c, same_only):  # pragma: no cover - numba
    """The two held trims of pixel p (c entries, ``kbuffer.KBuffer`` layout) nearest to each
    other in depth, two of one piece (or one piece set) if there are: (a, b, same), a = -1
    when there is no such pair (with ``same_only``, no pair of one piece). Among pairs as near,
    the first in slot order (a, then b).

    A full buffer in clutter holds trims of many pieces, and this runs at every insertion
    into it: pairs of one piece are looked for only among trims whose ident shares a bit
    (``_ident_bit``) with another's, and a walk ends at the first pair that touches (none can
    come nearer)."""
    seen = np.uint64(0)
    dup = np.uint64(0)
    for q in range(c):
        i, j = q >> LANE_BITS, q & LANE_MASK
        if kinds[i, p, j] == TRIM:
            bit = _ident_bit(idents[i, p, j])
            dup |= seen & bit
            seen |= bit
    if dup != 0:
        a, b = _first_nearest(p, depth, kinds, idents, far, c, dup, np.bool_(True))
        if a >= 0:
            return a, b, True
    if same_only:
        return -1, -1, False
    a, b = _first_nearest(p, depth, kinds, idents, far, c, dup, np.bool_(False))
    return a, b, False


@njit(cache=True, nogil=True, inline="always")
def _first_nearest(p, depth, kinds, idents, far, c, dup, one_piece):  # pragma: no cover
    """``_nearest_pair``'s walk: the first pair (a, b) in slot order of held trims of pixel p
    nearest in depth, (-1, -1) for none; with ``one_piece`` only pairs of one ident, among
    the trims whose ident bit (``_ident_bit``) is in ``dup``."""
    a = -1
    b = -1
    gbest = np.inf
    for q in range(c):
        i, j = q >> LANE_BITS, q & LANE_MASK
        if kinds[i, p, j] != TRIM or (one_piece and (_ident_bit(idents[i, p, j]) & dup) == 0):
            continue
        for r in range(q + 1, c):
            k, m = r >> LANE_BITS, r & LANE_MASK
            if kinds[k, p, m] == TRIM and (not one_piece or idents[i, p, j] == idents[k, p, m]):
                g = _gap(depth[i, p, j], far[i, p, j], depth[k, p, m], far[k, p, m])
                if g < gbest:
                    gbest = g
                    a = q
                    b = r
                    if g == 0.0:
                        # No pair comes nearer than touching.
                        return a, b
    return a, b


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _merge_trims(p, d, kind, ident, um, depth, kinds, idents, umbra, far,
                 c):  # pragma: no cover - numba
    """Room in pixel p's full k-buffer (c entries; entry q at [q >> LANE_BITS, p,
    q & LANE_MASK], ``kbuffer.KBuffer``) by merging trim fragments. A merged trim spans both
    depth ranges with the nearer umbra (``kbuffer`` docstring: it validates every interval
    either one did and hides no deeper); trims of two pieces merge into one of both (a piece
    set, ``kbuffer.piece_bits``), which validates more, so pieces are kept apart while they
    can be. An incoming trim (``kind`` TRIM at depth d, umbra um, of piece ``ident``) joins
    the nearest held trim of its piece; with none, the two nearest held trims of one piece
    merge and it takes the freed slot; with no such pair either, it joins the nearest held
    trim. For an incoming surface the two held trims nearest to each other merge, two of one
    piece if there are. Returns -2 when the incoming trim was absorbed, the freed slot, or -1
    when fewer than two trims leave no room."""
    if kind == TRIM:
        best = -1
        gbest = np.inf
        for q in range(c):
            i, j = q >> LANE_BITS, q & LANE_MASK
            if kinds[i, p, j] == TRIM and trim_holds(idents[i, p, j], ident):
                g = _gap(depth[i, p, j], far[i, p, j], d, d)
                if g < gbest:
                    gbest = g
                    best = q
                    if g == 0.0:
                        break  # a range of its piece holding d: none is nearer
        if best < 0:
            # np.bool_, not literals: _nearest_pair compiles once for both calls.
            a, b, same = _nearest_pair(p, depth, kinds, idents, far, c, np.bool_(True))
            if a >= 0:
                _join(p, a, b, depth, idents, umbra, far)
                return b
            for q in range(c):
                i, j = q >> LANE_BITS, q & LANE_MASK
                if kinds[i, p, j] == TRIM:
                    g = _gap(depth[i, p, j], far[i, p, j], d, d)
                    if g < gbest:
                        gbest = g
                        best = q
        if best < 0:
            return -1
        i, j = best >> LANE_BITS, best & LANE_MASK
        depth[i, p, j] = min(depth[i, p, j], d)
        far[i, p, j] = max(far[i, p, j], d)
        umbra[i, p, j] = min(umbra[i, p, j], um)
        idents[i, p, j] = joined_pieces(idents[i, p, j], ident)
        return -2
    a, b, same = _nearest_pair(p, depth, kinds, idents, far, c, np.bool_(False))
    if a < 0:
        return -1
    _join(p, a, b, depth, idents, umbra, far)
    return b


#: How many of a pixel's last entries an incoming trim fragment may join (``_insert``), and
#: the relative depth tolerance within which it joins one.
JOIN_LAST = 4
JOIN_TOL = 1e-3


@njit(cache=True, nogil=True, inline="always")
def _insert(p, d, kind, ident, um, depth, kinds, idents, umbra, far, count, overflow,
            vis):  # pragma: no cover - numba
    """Append an entry to pixel p's k-buffer (the arrays of ``kbuffer.KBuffer``, entry q at
    [q >> LANE_BITS, p, q & LANE_MASK]). A full buffer merges trim fragments to make room
    (``_merge_trims``); one that cannot overflows: it reports what it holds and everything
    that comes later (no occlusion there any more)."""
    if overflow[p]:
        if kind != TRIM:
            vis[ident] = 1
        return
    c = count[p]
    if kind == TRIM:
        # A trim at the depth of one of the last few held (the next edges of one silhouette
        # chain, drawn one after another) joins it: the same merge as a full buffer's, within
        # a depth tolerance, so a pixel crossed by many strips of one object holds one entry
        # (one holding both pieces where two meet: keeping them apart filled the buffers of
        # the kitchen's clutter, and its merges cost a fifth of the raster time).
        for q in range(c - 1, max(c - JOIN_LAST, 0) - 1, -1):
            i, j = q >> LANE_BITS, q & LANE_MASK
            if (kinds[i, p, j] == TRIM and depth[i, p, j] * (1.0 - JOIN_TOL) <= d
                    and d <= far[i, p, j] * (1.0 + JOIN_TOL)):
                depth[i, p, j] = min(depth[i, p, j], d)
                far[i, p, j] = max(far[i, p, j], d)
                umbra[i, p, j] = min(umbra[i, p, j], um)
                idents[i, p, j] = joined_pieces(idents[i, p, j], ident)
                return
    slot = c
    if c == K:
        # kind is the literal TRIM where the caller passes the constant (this is inlined):
        # int64, or _merge_trims compiles once more for it.
        slot = _merge_trims(p, d, np.int64(kind), ident, um, depth, kinds, idents, umbra, far,
                            c)
        if slot == -2:
            return
        if slot < 0:
            overflow[p] = 1
            for q in range(c):
                i, j = q >> LANE_BITS, q & LANE_MASK
                if kinds[i, p, j] != TRIM:
                    vis[idents[i, p, j]] = 1
            count[p] = 0
            if kind != TRIM:
                vis[ident] = 1
            return
    i, j = slot >> LANE_BITS, slot & LANE_MASK
    depth[i, p, j] = d
    kinds[i, p, j] = kind
    idents[i, p, j] = ident
    if kind == TRIM:
        # A surface's umbra and far end are never read (``_gap``, ``resolve``: trims only).
        umbra[i, p, j] = um
        far[i, p, j] = d
    if slot == c:
        count[p] = c + 1


@njit(cache=True, nogil=True)
def band_lists(ylo, yhi, n_bands):  # pragma: no cover - numba
    """The items each band of 8 pixel rows meets, as lists: item q spans rows [ylo[q],
    yhi[q]) (empty when yhi <= ylo). Returns (start (n_bands + 1,), items): band b's items,
    in increasing q, are items[start[b]:start[b + 1]]. The rasterizers' bands then visit
    only what reaches them, where each visited every item of the layer."""
    start = np.zeros(n_bands + 1, dtype=np.int64)
    for q in range(ylo.shape[0]):
        if yhi[q] > ylo[q]:
            for b in range(ylo[q] >> 3, ((yhi[q] - 1) >> 3) + 1):
                start[b + 1] += 1
    for b in range(n_bands):
        start[b + 1] += start[b]
    items = np.empty(start[n_bands], dtype=np.int64)
    fill = start[:n_bands].copy()
    for q in range(ylo.shape[0]):
        if yhi[q] > ylo[q]:
            for b in range(ylo[q] >> 3, ((yhi[q] - 1) >> 3) + 1):
                items[fill[b]] = q
                fill[b] += 1
    return start, items


@njit(cache=True, nogil=True)
def _leaf_window(lo, hi, vstar, rot, tan, res, out):  # pragma: no cover - numba
    """Write to ``out`` (4,) the pixel columns and rows [x0, x1) x [y0, y1) outside which no
    pixel centre's ray meets the box [lo, hi] (metres, v*'s frame): its corners' projection
    widened by two pixels; the whole face when a corner lies near or behind v*'s plane."""
    half = 0.5 * res
    size = max(hi[0] - lo[0], max(hi[1] - lo[1], hi[2] - lo[2]))
    x0 = np.inf
    x1 = -np.inf
    y0 = np.inf
    y1 = -np.inf
    for k in range(8):
        w0 = hi[0] if k & 1 else lo[0]
        w1 = hi[1] if k & 2 else lo[1]
        w2 = hi[2] if k & 4 else lo[2]
        p0, p1, p2 = w0 - vstar[0], w1 - vstar[1], w2 - vstar[2]
        cx = rot[0, 0] * p0 + rot[0, 1] * p1 + rot[0, 2] * p2
        cy = rot[1, 0] * p0 + rot[1, 1] * p1 + rot[1, 2] * p2
        z = -(rot[2, 0] * p0 + rot[2, 1] * p1 + rot[2, 2] * p2)
        # Near v*'s plane a corner's image runs off to infinity (and the fragments' leaf
        # tolerance grows in pixels): no window.
        if not z > LEAF_WINDOW_DEPTH * size:
            out[0], out[1], out[2], out[3] = 0, res, 0, res
            return
        px = (cx / z / tan + 1.0) * half
        py = (1.0 - cy / z / tan) * half
        x0, x1 = min(x0, px), max(x1, px)
        y0, y1 = min(y0, py), max(y1, py)
    out[0] = max(0, min(res, int(np.floor(x0)) - 2))
    out[1] = max(0, min(res, int(np.ceil(x1)) + 2))
    out[2] = max(0, min(res, int(np.floor(y0)) - 2))
    out[3] = max(0, min(res, int(np.ceil(y1)) + 2))


#: Depth (in leaf sizes) in front of v*'s plane within which a leaf gets no pixel window
#: (``_leaf_window``).
LEAF_WINDOW_DEPTH = 1e-2


@njit(cache=True, nogil=True, inline="always")
def _all_sealed(stencil, res, win):  # pragma: no cover - numba
    """Whether every pixel of the window [x0, x1) x [y0, y1) (``win``) is sealed (true for an
    empty window)."""
    for y in range(win[2], win[3]):
        for x in range(win[0], win[1]):
            if stencil[y * res + x] != SEALED:
                return False
    return True


@njit(cache=True, nogil=True, parallel=True)
def raster_surfaces(inst_row, inst_leaf, tris, leaf_lo, leaf_hi, cam, kb, vis,
                    stop):  # pragma: no cover - numba
    """Rasterize one layer's (triangle, leaf) instances into the k-buffers ``kb``
    (``kbuffer.KBuffer``) (P2).

    ``inst_row`` (k,) rows into the set-up triangles ``tris`` (``SetUp``), ``inst_leaf`` (k,)
    the leaf each instance belongs to: a fragment whose 3D point lies outside that leaf's box
    (``leaf_lo``/``leaf_hi`` (L, 3), metres, same frame as the view ``cam``'s v*) is dropped,
    so a triangle that crosses leaves delivers each fragment once, in the layer of the leaf it
    lies in, and layers stay in depth order along every ray. Sealed pixels take nothing (early
    ray termination), and a leaf whose window (``_leaf_window``) is sealed all over is not
    drawn: the resolved layers hide it (the paper's future work, leaves culled against what is
    resolved). Returns the instances so left out.
    """
    tri_ids, facing, poly, npoly, box = tris
    vstar, rot, tan, res = cam
    # Unpacked before the parallel loop: numba loses writes made inside a prange body through
    # a named tuple's field (numba issue #7135, open in 0.68; test_raster catches it).
    depth, kinds, idents, umbra, count = kb.depth, kb.kind, kb.ident, kb.umbra, kb.count
    far, stencil, active, overflow = kb.far, kb.stencil, kb.active, kb.overflow
    queue, queued, held_entries = kb.queue, kb.queued, kb.held_entries
    n_bands = (res + 7) // 8
    half = 0.5 * res
    stride = band_stride(n_bands)
    n_inst = inst_row.shape[0]
    ylo = np.empty(n_inst, dtype=np.int64)
    yhi = np.empty(n_inst, dtype=np.int64)
    # A triangle crossing leaves is drawn once per leaf, each instance keeping the fragments
    # inside its leaf: each draws only over its leaf's image (``_leaf_window``).
    n_leaves = leaf_lo.shape[0]
    windows = np.full((n_leaves, 4), -1, dtype=np.int64)
    # Read on the stencil itself, once per leaf and layer, stopping at the first open pixel:
    # a pyramid over the seals would have to be rebuilt after every layer's resolve.
    hidden = np.zeros(n_leaves, dtype=np.bool_)
    culled = 0
    win = np.empty(4, dtype=np.int64)
    for q in range(n_inst):
        i = inst_row[q]
        leaf = inst_leaf[q]
        if windows[leaf, 0] < 0:
            _leaf_window(leaf_lo[leaf], leaf_hi[leaf], vstar, rot, tan, res, win)
            windows[leaf, :] = win
            hidden[leaf] = _all_sealed(stencil, res, win)
        ylo[q] = max(0, box[i, 2], windows[leaf, 2])
        yhi[q] = min(res, box[i, 3], windows[leaf, 3])
        culled += hidden[leaf]
        if hidden[leaf] or box[i, 1] <= box[i, 0] or max(box[i, 0], windows[leaf, 0]) >= min(
                box[i, 1], windows[leaf, 1]):
            yhi[q] = ylo[q]
        yhi[q] = max(yhi[q], ylo[q])
    start, items = band_lists(ylo, yhi, n_bands)
    for j in prange(n_bands):
        band = (j * stride) % n_bands
        if flag_set(stop):
            continue
        r0 = band * 8
        r1 = min(res, r0 + 8)
        for k in range(start[band], start[band + 1]):
            q = items[k]
            i = inst_row[q]
            kind = FRONT if facing[i] > 0 else BACK
            leaf = inst_leaf[q]
            tol = 1e-6 * (leaf_hi[leaf, 0] - leaf_lo[leaf, 0])
            ya = max(r0, ylo[q])
            yb = min(r1, yhi[q])
            wx0 = windows[leaf, 0]
            wx1 = windows[leaf, 1]
            for t in range(1, npoly[i] - 1):
                ax, ay, az = poly[i, 0, 0], poly[i, 0, 1], poly[i, 0, 2]
                bx, by, bz = poly[i, t, 0], poly[i, t, 1], poly[i, t, 2]
                cx, cy, cz = poly[i, t + 1, 0], poly[i, t + 1, 1], poly[i, t + 1, 2]
                area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                if abs(area) < 1e-300:
                    continue
                inv = 1.0 / area
                xa = max(box[i, 0], wx0, int(np.floor(min(ax, min(bx, cx)) - 0.5)))
                xb = min(box[i, 1], wx1, int(np.ceil(max(ax, max(bx, cx)) + 0.5)))
                ty0 = max(ya, int(np.floor(min(ay, min(by, cy)) - 0.5)))
                ty1 = min(yb, int(np.ceil(max(ay, max(by, cy)) + 0.5)))
                for y in range(ty0, ty1):
                    py = y + 0.5
                    for x in range(xa, xb):
                        # Sealed first: behind the resolved layers most pixels are, and the
                        # test is one read where the barycentrics are a dozen operations.
                        p = y * res + x
                        if stencil[p] == SEALED:
                            continue
                        px = x + 0.5
                        w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv
                        w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv
                        w2 = 1.0 - w0 - w1
                        if w0 < -1e-9 or w1 < -1e-9 or w2 < -1e-9:
                            continue
                        iz = w0 * az + w1 * bz + w2 * cz
                        if iz <= 0.0:
                            continue
                        z = 1.0 / iz
                        u = (px / half - 1.0) * tan
                        v = (1.0 - py / half) * tan
                        cxp, cyp, czp = u * z, v * z, -z
                        inside = True
                        for a in range(3):
                            w = vstar[a] + rot[0, a] * cxp + rot[1, a] * cyp + rot[2, a] * czp
                            if w < leaf_lo[leaf, a] - tol or w > leaf_hi[leaf, a] + tol:
                                inside = False
                                break
                        if not inside:
                            continue
                        c0 = count[p]
                        _insert(p, z, kind, tri_ids[i], 0.0, depth, kinds, idents, umbra,
                                far, count, overflow, vis)
                        held_entries[band] += count[p] - c0
                        if not active[p]:
                            # The band's list of pixels to resolve after this layer.
                            active[p] = 1
                            queue[r0 * res + queued[band]] = p
                            queued[band] += 1
    return culled


#: Pixels by which a trim row's column bounds are widened against rounding (``raster_trims``).
COLUMN_SLACK = 1e-3


@njit(cache=True, nogil=True, inline="always")
def _affine_range(a, b, lo, hi):  # pragma: no cover - numba
    """The u with lo <= a u + b <= hi, as (u0, u1) (u0 > u1: none), clamped to +-1e300."""
    if a > 0.0:
        return max(-1e300, (lo - b) / a), min(1e300, (hi - b) / a)
    if a < 0.0:
        return max(-1e300, (hi - b) / a), min(1e300, (lo - b) / a)
    if lo <= b <= hi:
        return -1e300, 1e300
    return 1.0, -1.0


@njit(cache=True, nogil=True, parallel=True)
def raster_trims(trims, res, tan, margin, kb, vis, stop):  # pragma: no cover - numba
    """Rasterize one layer's trim region quads (P2) with their umbrae into the k-buffers ``kb``
    (``kbuffer.KBuffer``).

    ``trims`` (t, 13): plane normal of (v*, edge) in camera space (3), inner side sign, end
    points u0, v0, u1, v1 (tan units), 1 / depth at both ends, widths W0, W1 (tan units, the
    safety margin included), the edge's connected piece (``silhouettes.PIECE_COLUMN``, kept
    as the entry's ident).
    A pixel centre is in the region when its distance to the edge line on the inner side is at
    most the width interpolated along the edge (and at least ``-margin``), and it projects
    within the edge extended by ``margin`` (tan units). Its entry holds the silhouette depth
    and the umbra depth t / (1 - d / W) (the depth up to which every eye of the sphere sees the
    ray blocked by the trimmed occluder: Sec. 3.3, Fig. 4). A region whose pixel box is
    sealed all over is not drawn; returns how many were so left out.
    """
    # Unpacked before the parallel loop (see ``raster_surfaces``).
    depth, kinds, idents, umbra, count = kb.depth, kb.kind, kb.ident, kb.umbra, kb.count
    far, stencil, overflow, held_entries = kb.far, kb.stencil, kb.overflow, kb.held_entries
    n_bands = (res + 7) // 8
    half = 0.5 * res
    stride = band_stride(n_bands)
    # Pixel box of each region: the edge widened by the larger width on every side.
    n_trims = trims.shape[0]
    ylo = np.empty(n_trims, dtype=np.int64)
    yhi = np.empty(n_trims, dtype=np.int64)
    xlo = np.empty(n_trims, dtype=np.int64)
    xhi = np.empty(n_trims, dtype=np.int64)
    culled = 0
    for q in range(n_trims):
        u0, v0, u1, v1 = trims[q, 4], trims[q, 5], trims[q, 6], trims[q, 7]
        wmax = max(trims[q, 10], trims[q, 11])
        vlo = min(v0, v1) - wmax - margin
        vhi = max(v0, v1) + wmax + margin
        ylo[q] = max(0, int(np.floor((1.0 - vhi / tan) * half)))
        yhi[q] = min(res, int(np.ceil((1.0 - vlo / tan) * half)) + 1)
        xlo[q] = max(0, int(np.floor(((min(u0, u1) - wmax - margin) / tan + 1.0) * half)))
        xhi[q] = min(res, int(np.ceil(((max(u0, u1) + wmax + margin) / tan + 1.0) * half)) + 1)
        if xlo[q] >= xhi[q]:
            yhi[q] = ylo[q]
        elif _all_sealed(stencil, res, (xlo[q], xhi[q], ylo[q], yhi[q])):
            # Every pixel it could reach is sealed: it would insert nothing.
            yhi[q] = ylo[q]
            culled += 1
    start, items = band_lists(ylo, yhi, n_bands)
    for j in prange(n_bands):
        band = (j * stride) % n_bands
        if flag_set(stop):
            continue
        r0 = band * 8
        r1 = min(res, r0 + 8)
        for k in range(start[band], start[band + 1]):
            q = items[k]
            nx, ny, nz, side = trims[q, 0], trims[q, 1], trims[q, 2], trims[q, 3]
            u0, v0, u1, v1 = trims[q, 4], trims[q, 5], trims[q, 6], trims[q, 7]
            iz0, iz1, w0, w1 = trims[q, 8], trims[q, 9], trims[q, 10], trims[q, 11]
            piece = int(trims[q, PIECE_COLUMN])
            wmax = max(w0, w1)
            ya = max(r0, ylo[q])
            yb = min(r1, yhi[q])
            xa = xlo[q]
            xb = xhi[q]
            nl = np.sqrt(nx * nx + ny * ny)
            if nl == 0.0:
                continue
            ex, ey = u1 - u0, v1 - v0
            el2 = ex * ex + ey * ey
            el = np.sqrt(el2)
            lm = margin / el if el > 0 else 1e300
            # Along a row d and lam are affine in u (d = ad u + bd, lam = al u + bl): the columns
            # where both can pass (d in [-margin, wmax], lam in [-lm, 1 + lm]), widened by
            # COLUMN_SLACK against rounding; the exact test below decides. A trim's box is mostly
            # empty (a short edge near v* trims a strip across the whole view).
            ad = side * nx / nl
            al = ex / el2 if el2 > 0 else 0.0
            for y in range(ya, yb):
                v = (1.0 - (y + 0.5) / half) * tan
                bd = side * (ny * v - nz) / nl
                ua, ub = _affine_range(ad, bd, -margin, wmax)
                bl = 0.0
                if el2 > 0:
                    bl = ((v - v0) * ey - u0 * ex) / el2
                    la, lb = _affine_range(al, bl, -lm, 1.0 + lm)
                    ua = max(ua, la)
                    ub = min(ub, lb)
                if not ua <= ub:
                    continue
                fa = min(max((ua / tan + 1.0) * half - 0.5, -2.0), res + 2.0)
                fb = min(max((ub / tan + 1.0) * half - 0.5, -2.0), res + 2.0)
                xs = max(xa, int(np.ceil(fa - COLUMN_SLACK)))
                xe = min(xb, int(np.floor(fb + COLUMN_SLACK)) + 1)
                for x in range(xs, xe):
                    p = y * res + x
                    if stencil[p] == SEALED:
                        continue
                    u = ((x + 0.5) / half - 1.0) * tan
                    d = side * (nx * u + ny * v - nz) / nl
                    if d < -margin:
                        continue
                    lam = ((u - u0) * ex + (v - v0) * ey) / el2 if el2 > 0 else 0.0
                    if lam < -lm or lam > 1.0 + lm:
                        continue
                    lc = min(1.0, max(0.0, lam))
                    wid = (1.0 - lc) * w0 + lc * w1
                    if d > wid:
                        continue
                    t = 1.0 / ((1.0 - lc) * iz0 + lc * iz1)
                    frac = d / wid if wid > 0 else 0.0
                    um = t / (1.0 - frac) if frac < 1.0 - 1e-12 else np.inf
                    if um < t:
                        um = t
                    if stencil[p] == 0:
                        stencil[p] = TRIMMED
                    c0 = count[p]
                    _insert(p, t, TRIM, piece, um, depth, kinds, idents, umbra, far, count,
                            overflow, vis)
                    held_entries[band] += count[p] - c0
    return culled
