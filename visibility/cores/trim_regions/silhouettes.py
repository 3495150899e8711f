"""Silhouette edges and their trim region quads as seen from v* (paper Secs. 3.3, 3.6, 4.1;
Fig. 7), phase P1.

An edge is a silhouette when its two triangles face v* differently, when it has one triangle
(a border: a single-sided wall trims at its rim) or more than two (non-manifold). Its trim
region is the edge extruded in the image towards the occluder (the side its triangles lie on;
both sides where that is ambiguous) by the image-space displacement that moving the eye inside
the sphere can cause at the silhouette's depth:

    W = (Δ sqrt(1 + σ²) + σ R) / (z - R - Δ)    (at least 0)

in tan units, where z is the depth from v*, R the distance v* lies behind v0 and σ the end
point's image coordinate along the normal pointing into the occluder. It bounds, for every
eye v1 = v* + (w, a) (lateral w, forward a, (w, a - R) within Δ), how far behind the edge line
(as seen from v*) a point can lie and still be seen past the edge from v1: the edge's image
moves towards the occluder by (w - σ' a) / (z - a) against a point at infinity (σ' = -σ, the
coordinate along the outward normal; a nearer point moves less, by the factor
(z_p - z) / z_p), and the largest w - σ' (a - R) over the disc is Δ sqrt(1 + σ²). Forward
motion scales the image about its centre, so it widens the trim of an occluder lying away
from the centre (σ > 0) and narrows that of one lying towards it (σ < 0), down to nothing
where v*'s frustum edge grazes the sphere. Where z <= R + Δ the silhouette may be beside an
eye and the whole face is trimmed. ``TRIM_MARGIN_PX`` pixels are added for pixel-centre
sampling: a pixel whose square meets the region has its centre within sqrt(2) / 2 px of it,
so the quads are rasterized conservatively. (A wider margin bought no fewer missed pixels
and a larger PVS: docs/cores/trim_regions.md.)

Each trim quad is drawn in the earliest layer of any leaf its 3D extent meets (the edge's box
grown by the trim width at its depth), so a trim fragment is in the k-buffer no later than the
surfaces of the occlusion interval it validates.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.borrow import NO_REFCOUNT

#: ``facing_of`` code of a triangle whose plane passes through the sphere: it faces some eyes
#: and turns its back on others, so every edge it has is taken as a silhouette.
AMBIGUOUS = 2
#: Pixels added to every trim width (and around the quad's ends): sqrt(2) / 2, rounded up.
TRIM_MARGIN_PX = 0.75
#: Columns of a trim row (see ``raster.raster_trims``).
TRIM_COLUMNS = 13
#: The column holding the connected piece of the trim's edge (``topology.connected_pieces``).
PIECE_COLUMN = 12
#: Most fine-grid cells a trim's layer lookup scans; a larger extent goes to the first layer.
MAX_LOOKUP_CELLS = 4096
#: A fine-grid cell with no leaf, in ``_cell_layers``.
_NO_LAYER = np.int32(np.iinfo(np.int32).max)
#: Fine-grid cells per side of the blocks a trim's layer lookup skips by (``_trim_layer``).
BLOCK = 4
#: Edges per parallel chunk of ``silhouette_trims`` (one set of scratch arrays each).
EDGE_CHUNK = 1024


@njit(cache=True, nogil=True, inline="always")
def _side(n, q):  # pragma: no cover - numba
    s = n[0] * q[0] + n[1] * q[1] + n[2] * q[2]
    return 1.0 if s > 0 else (-1.0 if s < 0 else 0.0)


@njit(cache=True, nogil=True, inline="always")
def _coplanar(cam, ev, eo, e):  # pragma: no cover - numba
    """Whether edge e's second opposite corner lies in the plane of its first triangle
    (relative tolerance 1e-9)."""
    a = ev[e, 0]
    ux = cam[ev[e, 1], 0] - cam[a, 0]
    uy = cam[ev[e, 1], 1] - cam[a, 1]
    uz = cam[ev[e, 1], 2] - cam[a, 2]
    vx = cam[eo[e, 0], 0] - cam[a, 0]
    vy = cam[eo[e, 0], 1] - cam[a, 1]
    vz = cam[eo[e, 0], 2] - cam[a, 2]
    wx = cam[eo[e, 1], 0] - cam[a, 0]
    wy = cam[eo[e, 1], 1] - cam[a, 1]
    wz = cam[eo[e, 1], 2] - cam[a, 2]
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    scale = (np.sqrt(nx * nx + ny * ny + nz * nz)
             * max(np.sqrt(wx * wx + wy * wy + wz * wz), np.sqrt(ux * ux + uy * uy + uz * uz)))
    return abs(nx * wx + ny * wy + nz * wz) <= 1e-9 * scale


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _trim_layer(pa, pb, grow, grid_origin, cell, cell_layer, block_layer, first,
                part):  # pragma: no cover
    """Earliest layer of the leaves meeting the box of points pa, pb (camera frame's world
    positions, metres) grown by ``grow`` metres: the least of ``cell_layer`` (the fine grid's
    cells' layers, ``_cell_layers``) over the box, read a block at a time where
    ``block_layer`` allows; ``first`` (the least there is) as soon as it is met. ``part``
    (p, 4) int32 is scratch for the blocks the box cuts."""
    g = cell_layer.shape[0]
    lo = (0, 0, 0)
    hi = (0, 0, 0)
    n = 1
    for a in range(3):
        mn = min(pa[a], pb[a]) - grow - grid_origin[a]
        mx = max(pa[a], pb[a]) + grow - grid_origin[a]
        la = min(g - 1, max(0, int(np.floor(mn / cell))))
        ha = min(g - 1, max(0, int(np.floor(mx / cell))))
        if a == 0:
            lo = (la, lo[1], lo[2])
            hi = (ha, hi[1], hi[2])
        elif a == 1:
            lo = (lo[0], la, lo[2])
            hi = (hi[0], ha, hi[2])
        else:
            lo = (lo[0], lo[1], la)
            hi = (hi[0], hi[1], ha)
        n *= ha - la + 1
    if n > MAX_LOOKUP_CELLS:
        return 0
    # Blocks of BLOCK^3 cells keep their least layer: a block wholly inside the box gives
    # it at once; the others are scanned in the order of their least layers, and none whose
    # least cannot lower the answer is scanned.
    b_lo = (lo[0] // BLOCK, lo[1] // BLOCK, lo[2] // BLOCK)
    b_hi = (hi[0] // BLOCK, hi[1] // BLOCK, hi[2] // BLOCK)
    best = _NO_LAYER
    n_part = 0
    for bi in range(b_lo[0], b_hi[0] + 1):
        full_i = lo[0] <= bi * BLOCK and bi * BLOCK + BLOCK - 1 <= hi[0]
        for bj in range(b_lo[1], b_hi[1] + 1):
            full_j = lo[1] <= bj * BLOCK and bj * BLOCK + BLOCK - 1 <= hi[1]
            for bk in range(b_lo[2], b_hi[2] + 1):
                bm = block_layer[bi, bj, bk]
                if bm >= best:
                    continue
                if full_i and full_j and lo[2] <= bk * BLOCK and bk * BLOCK + BLOCK - 1 <= hi[2]:
                    best = bm
                elif n_part < part.shape[0]:
                    part[n_part, 0] = bm
                    part[n_part, 1] = bi
                    part[n_part, 2] = bj
                    part[n_part, 3] = bk
                    n_part += 1
                else:
                    best = min(best, _block_min(cell_layer, lo, hi, bi, bj, bk))
    while best > first:
        # The partial block of least layer still under the answer.
        q = -1
        for r in range(n_part):
            if part[r, 0] < best and (q < 0 or part[r, 0] < part[q, 0]):
                q = r
        if q < 0:
            break
        best = min(best, _block_min(cell_layer, lo, hi, part[q, 1], part[q, 2], part[q, 3]))
        part[q, 0] = _NO_LAYER
    return 0 if best == _NO_LAYER else best


@njit(cache=True, nogil=True, inline="always")
def _block_min(cell_layer, lo, hi, bi, bj, bk):  # pragma: no cover - numba
    """Least of ``cell_layer`` over block (bi, bj, bk)'s cells within [lo, hi]."""
    best = _NO_LAYER
    for i in range(max(lo[0], bi * BLOCK), min(hi[0], bi * BLOCK + BLOCK - 1) + 1):
        for j in range(max(lo[1], bj * BLOCK), min(hi[1], bj * BLOCK + BLOCK - 1) + 1):
            for k in range(max(lo[2], bk * BLOCK), min(hi[2], bk * BLOCK + BLOCK - 1) + 1):
                best = min(best, cell_layer[i, j, k])
    return best


@njit(cache=True, nogil=True)
def _cell_layers(leaf_of_cell, leaf_layer, cell_layer, block_layer):  # pragma: no cover
    """Fill ``cell_layer`` (g, g, g) with the layer of each fine-grid cell's leaf
    (``_NO_LAYER`` where none) and ``block_layer`` (ceil(g / BLOCK) per axis) with the least
    of each block of cells; returns the least layer."""
    g0, g1, g2 = leaf_of_cell.shape
    block_layer[:] = _NO_LAYER
    first = _NO_LAYER
    for i in range(g0):
        for j in range(g1):
            for k in range(g2):
                leaf = leaf_of_cell[i, j, k]
                v = _NO_LAYER if leaf < 0 else np.int32(leaf_layer[leaf])
                cell_layer[i, j, k] = v
                b = block_layer[i // BLOCK, j // BLOCK, k // BLOCK]
                block_layer[i // BLOCK, j // BLOCK, k // BLOCK] = min(b, v)
                first = min(first, v)
    return first


@njit(cache=True, nogil=True, inline="always")
def _one_edge(cam, e, ev, ef, eo, many, facing_of, near, tan, delta, back, margin,
              out, sides, widths, pts):  # pragma: no cover - numba
    """Trim rows of edge e: the number of sides (0, 1 or 2) written to ``sides``; the shared
    part of the row (normal, ends, depths, the larger widths) is written to ``out``, the
    widths at both ends of a trim into side +1 and side -1 to ``widths`` (2, 2). ``pts``
    (3, 3) is scratch (the clipped ends and the normal). Inlined: called once per edge of the
    view, most of which return at the facing test, its arguments cost more as a call."""
    f0 = ef[e, 0]
    f1 = ef[e, 1]
    a0 = facing_of[f0]
    either = a0 == AMBIGUOUS
    if f1 >= 0:
        a1 = facing_of[f1]
        either = either or a1 == AMBIGUOUS
        if a0 == a1 and not many[e] and not either:
            return 0
        if either and a0 == a1 and _coplanar(cam, ev, eo, e):
            return 0  # two triangles of one plane: no eye sees a silhouette between them
    elif a0 == 0:
        return 0
    a = pts[0]
    b = pts[1]
    for k in range(3):
        a[k] = cam[ev[e, 0], k]
        b[k] = cam[ev[e, 1], k]
    za, zb = -a[2], -b[2]
    if za < near and zb < near:
        return 0
    if za < near:
        t = (zb - near) / (zb - za)
        for k in range(3):
            a[k] = b[k] + t * (a[k] - b[k])
    elif zb < near:
        t = (za - near) / (za - zb)
        for k in range(3):
            b[k] = a[k] + t * (b[k] - a[k])
    # Normal of the plane through v* (the origin) and the edge: its trace in the image is
    # the edge line, and the side of a point is the sign of n . (u, v, -1).
    n = pts[2]
    n[0] = a[1] * b[2] - a[2] * b[1]
    n[1] = a[2] * b[0] - a[0] * b[2]
    n[2] = a[0] * b[1] - a[1] * b[0]
    nl = np.sqrt(n[0] * n[0] + n[1] * n[1])
    if nl == 0.0:
        return 0
    s0 = _side(n, cam[eo[e, 0]])
    s1 = _side(n, cam[eo[e, 1]]) if f1 >= 0 else s0
    za, zb = -a[2], -b[2]
    out[0], out[1], out[2] = n[0], n[1], n[2]
    out[4], out[5] = a[0] / za, a[1] / za
    out[6], out[7] = b[0] / zb, b[1] / zb
    out[8], out[9] = 1.0 / za, 1.0 / zb
    big = 4.0 * tan
    for k in range(2):
        z = za if k == 0 else zb
        u = out[4 + 2 * k]
        v = out[5 + 2 * k]
        den = z - back - delta
        sg = (n[0] * u + n[1] * v) / nl
        for q in range(2):
            w = big
            if den > 1e-9 * z:
                # The end point's image coordinate towards the occluder on side +1 / -1 is
                # +sg / -sg: forward motion only widens the trim of an occluder lying away
                # from the image centre.
                into = sg if q == 0 else -sg
                w = delta * np.sqrt(1.0 + sg * sg) + into * back
                w = min(big, max(0.0, w / den))
            widths[q, k] = w + margin
        out[10 + k] = max(widths[0, k], widths[1, k])
    # Outside the view: the strip lies within its larger width (and the margin) of the edge,
    # so an edge whose ends both lie that far beyond one side of the face trims no pixel.
    reach = tan + max(out[10], out[11]) + margin
    if ((out[4] > reach and out[6] > reach) or (out[4] < -reach and out[6] < -reach)
            or (out[5] > reach and out[7] > reach) or (out[5] < -reach and out[7] < -reach)):
        return 0
    m = 0
    if s0 == s1 and s0 != 0.0 and not many[e] and not either:
        sides[0] = s0
        m = 1
    else:
        sides[0] = 1.0
        sides[1] = -1.0
        m = 2
    return m


@njit(cache=True, nogil=True, parallel=True)
def silhouette_trims(cam, ev, ef, eo, many, facing_of, edge_on, near, tan, res, delta, back,
                     margin_px, vstar, rot, grid_origin, cell, leaf_of_cell,
                     leaf_layer, piece):  # pragma: no cover
    """Trim region rows of every silhouette edge of one view, and their layers.

    Parameters
    ----------
    cam : (n, 3) camera-space vertices, metres.
    ev, ef, eo : (E, 2) int64 edge end points, triangles and opposite corners
        (``edges.Edges``); many : (E,) bool non-manifold.
    facing_of : (m,) int8 facing of each triangle id (+1 front, -1 back, 0 edge-on,
        ``AMBIGUOUS`` when its plane passes through the eyes: every edge it shares with
        a triangle of another plane, and every border of it, trims both sides).
    edge_on : (E,) bool, the edges to consider: those of the triangles in the leaves the view
        draws (an edge of triangles wholly outside the frustum is in no eye's view of this
        face, whatever its strip covers in v*'s image).
    near, tan, res, delta, back : the view (``frustum.View``); margin_px : trim margin, px.
    vstar, rot : viewpoint and rotation (to place the trims in the octree).
    grid_origin, cell, leaf_of_cell, leaf_layer : the octree's fine grid (origin in the
        view's frame, metres) and the layer of each leaf in this view.
    piece : (m,) int64 connected piece of each triangle id (``topology.connected_pieces``),
        written to each row's ``PIECE_COLUMN``.

    Returns
    -------
    trims : (t, TRIM_COLUMNS) float64 rows for ``raster.raster_trims``.
    layer : (t,) int64 the layer each trim is drawn in.
    """
    n_e = ev.shape[0]
    margin = margin_px * 2.0 * tan / res
    # One byte per edge (0-2 trims): the counts of a million edges are allocated per view.
    counts = np.empty(n_e, dtype=np.int8)
    n_chunks = (n_e + EDGE_CHUNK - 1) // EDGE_CHUNK
    # Scratch per chunk of edges: an allocation per edge cost more than most edges' test.
    for c in prange(n_chunks):
        row = np.empty(TRIM_COLUMNS)
        sides = np.empty(2)
        widths = np.empty((2, 2))
        pts = np.empty((3, 3))
        for e in range(c * EDGE_CHUNK, min(n_e, (c + 1) * EDGE_CHUNK)):
            counts[e] = 0
            if edge_on[e]:
                counts[e] = _one_edge(cam, e, ev, ef, eo, many, facing_of, near, tan, delta,
                                      back, margin, row, sides, widths, pts)
    # The trimming edges and where their rows start.
    sil = np.flatnonzero(counts)
    n_sil = sil.shape[0]
    start = np.zeros(n_sil + 1, dtype=np.int64)
    start[1:] = np.cumsum(counts[sil].astype(np.int64))
    n_rows = start[n_sil]
    trims = np.empty((n_rows, TRIM_COLUMNS))
    layer = np.empty(n_rows, dtype=np.int64)
    if n_sil == 0:
        return trims, layer
    cell_layer = np.empty(leaf_of_cell.shape, dtype=np.int32)
    g0, g1, g2 = leaf_of_cell.shape
    block_layer = np.empty(((g0 + BLOCK - 1) // BLOCK, (g1 + BLOCK - 1) // BLOCK,
                            (g2 + BLOCK - 1) // BLOCK), dtype=np.int32)
    first = _cell_layers(leaf_of_cell, leaf_layer, cell_layer, block_layer)
    n_chunks = (n_sil + EDGE_CHUNK - 1) // EDGE_CHUNK
    for c in prange(n_chunks):
        row = np.empty(TRIM_COLUMNS)
        sides = np.empty(2)
        widths = np.empty((2, 2))
        pts = np.empty((3, 3))
        pa = np.empty(3)
        pb = np.empty(3)
        part = np.empty((64, 4), dtype=np.int32)
        for s_ in range(c * EDGE_CHUNK, min(n_sil, (c + 1) * EDGE_CHUNK)):
            e = sil[s_]
            m = _one_edge(cam, e, ev, ef, eo, many, facing_of, near, tan, delta, back, margin,
                          row, sides, widths, pts)
            # World positions of the (clipped) ends: back from the image ends at their depths.
            za = 1.0 / row[8]
            zb = 1.0 / row[9]
            ca = (row[4] * za, row[5] * za, -za)
            cb = (row[6] * zb, row[7] * zb, -zb)
            for k in range(3):
                pa[k] = vstar[k] + rot[0, k] * ca[0] + rot[1, k] * ca[1] + rot[2, k] * ca[2]
                pb[k] = vstar[k] + rot[0, k] * cb[0] + rot[1, k] * cb[1] + rot[2, k] * cb[2]
            grow = max(row[10] * za, row[11] * zb)
            lay = _trim_layer(pa, pb, grow, grid_origin, cell, cell_layer, block_layer,
                              first, part)
            for q in range(m):
                w = start[s_] + q
                for k in range(TRIM_COLUMNS):
                    trims[w, k] = row[k]
                trims[w, 3] = sides[q]
                trims[w, 10] = widths[0 if sides[q] > 0 else 1, 0]
                trims[w, 11] = widths[0 if sides[q] > 0 else 1, 1]
                trims[w, PIECE_COLUMN] = piece[ef[e, 0]]
                layer[w] = lay
    return trims, layer
