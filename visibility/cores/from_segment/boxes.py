"""Screen boxes of the primitives of a view segment, per cube face, and their binning into tiles.

Pixels a primitive can touch: its swept volume (the convex hull of its corners at both ends,
relative to the eye) clipped at the near plane and projected: the paper's hull of six points,
made safe for points behind the eye.

Whole clusters (``_cluster_boxes``), the triangles of expanded clusters (``_expanded_boxes``) and
spheres (``_sphere_boxes``) each get a pixel box, a smallest depth and flags (``FLAG_*``) per
face; ``_sort_and_bin`` orders them front to back and lists them per TILE x TILE pixel tile.
Expanded triangles also keep their projected swept hull (``hull``), so that binning and the
tiles' scan skip the parts of the box the hull does not reach.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.borrow import NO_REFCOUNT, borrow, keep_alive
from visibility.cores.from_segment.hull import HMAX, Hulls, hull_cols, store_hull
from visibility.cores.from_segment.spheres import sphere_box
from visibility.raster.camera import cube_face_rotations
from visibility.raster.face_pixels import pixel_range

#: Side of a square screen tile in pixels (unit of parallel work and of occlusion culling).
TILE = 16
#: A cluster whose box covers more tiles than this (or reaches the near plane) is expanded.
EXPAND_TILES = 4
#: Expanded triangles whose box has fewer pixels than this scan it whole (no hull): below it,
#: hulling costs more than the cover tests it saves.
HULL_MIN_PIXELS = 16
#: Depth buckets of the front-to-back counting sort.
N_BUCKETS = 2048

FLAG_PRESENT = 1
FLAG_MOVING = 2
FLAG_SLOW = 4  # may reach the near plane: per-pixel near constraint (and clipping) needed
FLAG_SPHERE = 8
FLAG_CLUSTER = 16

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Helpers called per primitive, tile or row that allocate nothing: no reference counting.
_JIT_NO_NRT = dict(_JIT, **NO_REFCOUNT)
_PJIT = dict(cache=True, nogil=True, parallel=True, error_model="numpy")


def _face_permutation() -> tuple[np.ndarray, np.ndarray]:
    """(6, 3) axis index and sign such that face camera coords = sign * cube coords[axis]."""
    rots = cube_face_rotations(None)
    perm = np.abs(rots).argmax(axis=2).astype(np.int64)
    sgn = np.take_along_axis(rots, perm[..., None], axis=2)[..., 0].copy()
    return perm, sgn


_PERM, _SGN = _face_permutation()



@njit(**_JIT_NO_NRT)
def _hull_box(cube, npts, f, perm, sgn, near, res, box, pad, uv):
    """Pixel box on cube face f of the convex hull of ``cube[:npts]`` (cube space, relative to
    the eye) clipped to depth >= near. Returns (non-empty, smallest depth of the clipped hull,
    hull reaches the near plane, n): ``uv[:n]`` (at least npts + npts^2 / 4 rows) are the NDC
    points whose 2D hull is the clipped hull's projection."""
    ax = perm[f, 2]
    ix = perm[f, 0]
    iy = perm[f, 1]
    sd = -sgn[f, 2]
    sx = sgn[f, 0]
    sy = sgn[f, 1]
    out_r = True
    out_l = True
    out_t = True
    out_b = True
    out_n = True
    for q in range(npts):
        x = sx * cube[q, ix]
        y = sy * cube[q, iy]
        d = sd * cube[q, ax]
        if x <= d:
            out_r = False
        if -x <= d:
            out_l = False
        if y <= d:
            out_t = False
        if -y <= d:
            out_b = False
        if d >= near:
            out_n = False
    if out_r or out_l or out_t or out_b or out_n:
        return False, 0.0, False, 0
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    zm = np.inf
    slow = False
    n = 0
    for q in range(npts):
        d = sd * cube[q, ax]
        if d >= near:
            uv[n, 0] = sx * cube[q, ix] / d
            uv[n, 1] = sy * cube[q, iy] / d
            zm = min(zm, d)
            n += 1
        else:
            slow = True
    if slow:
        # The clipped hull's vertices on the near plane lie on segments between the points.
        zm = near
        for q1 in range(npts):
            d1 = sd * cube[q1, ax]
            for q2 in range(q1 + 1, npts):
                d2 = sd * cube[q2, ax]
                if (d1 >= near) != (d2 >= near):
                    s = (near - d1) / (d2 - d1)
                    uv[n, 0] = sx * (cube[q1, ix] + s * (cube[q2, ix] - cube[q1, ix])) / near
                    uv[n, 1] = sy * (cube[q1, iy] + s * (cube[q2, iy] - cube[q1, iy])) / near
                    n += 1
    # The box of the clipped hull's points.
    for q in range(n):
        umin = min(umin, uv[q, 0])
        umax = max(umax, uv[q, 0])
        vmin = min(vmin, uv[q, 1])
        vmax = max(vmax, uv[q, 1])
    if not (umin <= umax and vmin <= vmax):
        return False, 0.0, False, 0
    if not pixel_range(umin, umax, vmin, vmax, res, box, pad):
        return False, 0.0, False, 0
    return True, zm, slow, n


@njit(**_JIT_NO_NRT)
def _sole_face(cube, npts, near):
    """The one cube face whose frustum strictly holds all points beyond the near plane (then the
    hull touches no other face), or -1."""
    ax = 0
    big = abs(cube[0, 0])
    if abs(cube[0, 1]) > big:
        ax = 1
        big = abs(cube[0, 1])
    if abs(cube[0, 2]) > big:
        ax = 2
    sg = 1.0 if cube[0, ax] >= 0.0 else -1.0
    i1 = (ax + 1) % 3
    i2 = (ax + 2) % 3
    for q in range(npts):
        d = sg * cube[q, ax]
        if not (d >= near and abs(cube[q, i1]) < d and abs(cube[q, i2]) < d):
            return -1
    return 2 * ax + (0 if sg > 0.0 else 1)


@njit(**_JIT_NO_NRT)
def _to_cube(rb, x, y, z, cube, q):
    for r in range(3):
        cube[q, r] = rb[r, 0] * x + rb[r, 1] * y + rb[r, 2] * z


@njit(**_JIT)
def _cluster_boxes_range(lo_c, hi_c, v0, dvec, rb, perm, sgn, res, near, pad, out_box, out_z,
                         out_flag, first, last):  # pragma: no cover - numba
    """Per cluster and cube face: pixel box and smallest depth of the swept bounding box (its 8
    corners at t = 0 and t = 1, relative to the eye), flags (0 = absent)."""
    # Borrowed (``visibility.borrow``): no reference counting at each helper's call, which on
    # the shared arrays the threads would fight over.
    lo_c, hi_c, v0, dvec, rb = borrow(lo_c), borrow(hi_c), borrow(v0), borrow(dvec), borrow(rb)
    perm, sgn = borrow(perm), borrow(sgn)
    out_box, out_z, out_flag = borrow(out_box), borrow(out_z), borrow(out_flag)
    own = (np.empty((16, 3)), np.empty((16 + 64, 2)), np.empty(4, dtype=np.int64))
    cube, uv, bx = borrow(own[0]), borrow(own[1]), borrow(own[2])
    for c in range(first, last):
        for k in range(8):
            x = (lo_c[c, 0] if k & 1 else hi_c[c, 0]) - v0[0]
            y = (lo_c[c, 1] if k & 2 else hi_c[c, 1]) - v0[1]
            z = (lo_c[c, 2] if k & 4 else hi_c[c, 2]) - v0[2]
            _to_cube(rb, x, y, z, cube, k)
            _to_cube(rb, x - dvec[0], y - dvec[1], z - dvec[2], cube, k + 8)
        for f in range(6):
            out_flag[c, f] = 0
        sole = _sole_face(cube, 16, near)
        f_lo = 0 if sole < 0 else sole
        f_hi = 6 if sole < 0 else sole + 1
        for f in range(f_lo, f_hi):
            # np.int64 point counts, not literals: _hull_box compiles once for its callers.
            ok, zm, slow, _ = _hull_box(cube, np.int64(16), f, perm, sgn, near, res, bx, pad,
                                        uv)
            if ok:
                for r in range(4):
                    out_box[c, f, r] = bx[r]
                out_z[c, f] = zm
                out_flag[c, f] = FLAG_PRESENT | (FLAG_SLOW if slow else 0)
    keep_alive(own)


@njit(**_PJIT)
def _cluster_boxes(lo_c, hi_c, v0, dvec, rb, perm, sgn, res, near, pad, out_box, out_z,
                   out_flag):  # pragma: no cover - numba
    n = lo_c.shape[0]
    nch = min(n, 256)
    for ch in prange(nch):
        _cluster_boxes_range(lo_c, hi_c, v0, dvec, rb, perm, sgn, res, near, pad, out_box, out_z,
                             out_flag, ch * n // nch, (ch + 1) * n // nch)


@njit(**_JIT_NO_NRT)
def _tri_cube(verts0, verts1, faces, t, v0, dvec, rb, cube):
    """The six cube-space points of triangle t: corners at t = 0 and t = 1 relative to the eye."""
    for c in range(3):
        vi = faces[t, c]
        _to_cube(rb, verts0[vi, 0] - v0[0], verts0[vi, 1] - v0[1], verts0[vi, 2] - v0[2], cube, c)
        _to_cube(rb, verts1[vi, 0] - v0[0] - dvec[0], verts1[vi, 1] - v0[1] - dvec[1],
                 verts1[vi, 2] - v0[2] - dvec[2], cube, c + 3)


@njit(**_JIT)
def _expanded_boxes_range(geom, exp_tri, exp_face, frame, out_box, out_z, out_flag, out_hull,
                          first, last):  # pragma: no cover - numba
    """``_expanded_boxes`` for entries [first, last)."""
    verts0, verts1 = borrow(geom.verts0), borrow(geom.verts1)
    faces, moving = borrow(geom.faces), borrow(geom.moving)
    v0, dvec, rb, perm, sgn, res, near, pad = frame
    v0, dvec, rb, perm, sgn = borrow(v0), borrow(dvec), borrow(rb), borrow(perm), borrow(sgn)
    exp_tri, exp_face = borrow(exp_tri), borrow(exp_face)
    out_box, out_z, out_flag = borrow(out_box), borrow(out_z), borrow(out_flag)
    hull_pts, hull_count = borrow(out_hull.pts), borrow(out_hull.count)
    own = (np.empty((6, 3)), np.empty((HMAX, 2)), np.empty((3 * HMAX + 2, 2)),
           np.empty(4, dtype=np.int64))
    cube, uv, scratch, bx = borrow(own[0]), borrow(own[1]), borrow(own[2]), borrow(own[3])
    for k in range(first, last):
        t = exp_tri[k]
        f = exp_face[k]
        out_flag[k] = 0
        hull_count[k] = 0
        _tri_cube(verts0, verts1, faces, t, v0, dvec, rb, cube)
        ok, zm, slow, n = _hull_box(cube, np.int64(6), f, perm, sgn, near, res, bx, pad, uv)
        if ok:
            for r in range(4):
                out_box[k, r] = bx[r]
            out_z[k] = zm
            # Both ends of a moving triangle's corners hold every position between them, so
            # the same hull bounds its sweep. A small box is cheaper to scan than to hull.
            if (bx[1] - bx[0] + 1) * (bx[3] - bx[2] + 1) >= HULL_MIN_PIXELS:
                hull_count[k] = store_hull(uv, n, res, scratch, hull_pts, k)
            out_flag[k] = FLAG_PRESENT | (FLAG_MOVING if moving[t] else 0) | (
                FLAG_SLOW if slow else 0)
    keep_alive(own)


@njit(**_PJIT)
def _expanded_boxes(geom, exp_tri, exp_face, frame, out_box, out_z, out_flag,
                    out_hull):  # pragma: no cover - numba
    """Pixel box, smallest depth and flags of each (triangle ``exp_tri[k]``, face
    ``exp_face[k]``) of the expanded clusters (of ``geom``, ``groups.GeometryArrays``, seen in the
    cube ``frame``, ``groups.CubeFrame``), and its projected swept hull: ``out_hull``
    (``hull.Hulls``, index unused) gets ``pts[k]`` and ``count[k]`` (0 = scan the box)."""
    n = exp_tri.shape[0]
    nch = min(n, 256)
    for ch in prange(nch):
        _expanded_boxes_range(geom, exp_tri, exp_face, frame, out_box, out_z, out_flag,
                              out_hull, ch * n // nch, (ch + 1) * n // nch)


@njit(**_PJIT)
def _expanded_area(geom, exp_tri, exp_face, frame):  # pragma: no cover - numba
    """Sum of the pixel box areas ``_expanded_boxes`` would give the same entries (no hulls,
    nothing stored): what a piece's split decision needs."""
    verts0, verts1, faces = borrow(geom.verts0), borrow(geom.verts1), borrow(geom.faces)
    v0, dvec, rb, perm, sgn, res, near, pad = frame
    v0, dvec, rb, perm, sgn = borrow(v0), borrow(dvec), borrow(rb), borrow(perm), borrow(sgn)
    exp_tri, exp_face = borrow(exp_tri), borrow(exp_face)
    n = exp_tri.shape[0]
    nch = min(n, 256)
    sums = np.zeros(max(nch, 1), dtype=np.int64)
    for ch in prange(nch):
        own = (np.empty((6, 3)), np.empty((HMAX, 2)), np.empty(4, dtype=np.int64))
        cube, uv, bx = borrow(own[0]), borrow(own[1]), borrow(own[2])
        acc = 0
        for k in range(ch * n // nch, (ch + 1) * n // nch):
            _tri_cube(verts0, verts1, faces, exp_tri[k], v0, dvec, rb, cube)
            ok, _, _, _ = _hull_box(cube, np.int64(6), exp_face[k], perm, sgn, near, res, bx,
                                    pad, uv)
            if ok:
                acc += (bx[1] - bx[0] + 1) * (bx[3] - bx[2] + 1)
        sums[ch] = acc
        keep_alive(own)
    return sums.sum()


@njit(**_JIT_NO_NRT)
def _expands(cbox, c, f, fl):  # pragma: no cover - numba
    """Whether cluster c's primitive on face f (flags fl) is split into its triangles: it may
    reach the near plane, or its box spans more than ``EXPAND_TILES`` tiles."""
    span = (cbox[c, f, 1] // TILE - cbox[c, f, 0] // TILE + 1) * (
        cbox[c, f, 3] // TILE - cbox[c, f, 2] // TILE + 1)
    return bool(fl & FLAG_SLOW) or span > EXPAND_TILES


@njit(**_JIT)
def _split_clusters(cl_start, cl_tris, cbox, cz, cflag, first, res):  # pragma: no cover
    """Cluster prims (kept whole) and the (triangle, face) list of the expanded ones.

    Returns (keep_cluster, keep_face, keep_box, keep_z, keep_flag, exp_tri, exp_face); cluster
    indices are offset by ``first`` (the batch start)."""
    nc = cflag.shape[0]
    n_keep = 0
    n_exp = 0
    # Per (cluster, face): 0 absent, 1 kept whole, 2 split into its triangles.
    mode = np.zeros((nc, 6), dtype=np.int8)
    for c in range(nc):
        for f in range(6):
            fl = cflag[c, f]
            if fl == 0:
                continue
            if _expands(cbox, c, f, fl):
                mode[c, f] = 2
                n_exp += cl_start[first + c + 1] - cl_start[first + c]
            else:
                mode[c, f] = 1
                n_keep += 1
    keep_cluster = np.empty(n_keep, dtype=np.int32)
    keep_face = np.empty(n_keep, dtype=np.int32)
    keep_box = np.empty((n_keep, 4), dtype=np.int32)
    keep_z = np.empty(n_keep)
    keep_flag = np.empty(n_keep, dtype=np.uint8)
    exp_tri = np.empty(n_exp, dtype=np.int64)
    exp_face = np.empty(n_exp, dtype=np.int64)
    a = 0
    b = 0
    for c in range(nc):
        for f in range(6):
            if mode[c, f] == 2:
                for k in range(cl_start[first + c], cl_start[first + c + 1]):
                    exp_tri[b] = cl_tris[k]
                    exp_face[b] = f
                    b += 1
            elif mode[c, f] == 1:
                keep_cluster[a] = first + c
                keep_face[a] = f
                for r in range(4):
                    keep_box[a, r] = cbox[c, f, r]
                keep_z[a] = cz[c, f]
                keep_flag[a] = FLAG_PRESENT | FLAG_CLUSTER
                a += 1
    return keep_cluster, keep_face, keep_box, keep_z, keep_flag, exp_tri, exp_face


@njit(**_JIT)
def _sphere_boxes(c0, c1, radii, sel, v0, dvec, rots, res, near, pad, out_box, out_z,
                  out_flag):  # pragma: no cover - numba
    """Per selected sphere and cube face: pixel box, smallest depth and flags (0 = absent)."""
    p0 = np.empty(3)
    p1 = np.empty(3)
    bx = np.empty(4, dtype=np.int64)
    for k in range(sel.shape[0]):
        s = sel[k]
        for f in range(6):
            out_flag[k, f] = 0
            for r in range(3):
                p0[r] = 0.0
                p1[r] = 0.0
                for c in range(3):
                    p0[r] += rots[f, r, c] * (c0[s, c] - v0[c])
                    p1[r] += rots[f, r, c] * (c1[s, c] - v0[c] - dvec[c])
            ok, zm, slow = sphere_box(p0, p1, radii[s], near, res, bx, pad)
            if ok:
                for r in range(4):
                    out_box[k, f, r] = bx[r]
                out_z[k, f] = zm
                out_flag[k, f] = FLAG_PRESENT | FLAG_SPHERE | FLAG_MOVING | (
                    FLAG_SLOW if slow else 0)


@njit(**_JIT_NO_NRT)
def _tile_cols(hulls, p, prim_box, ty, pad):  # pragma: no cover - numba
    """Tile columns [tx0, tx1] of primitive p in tile row ty: those its hull reaches (when it
    has one) within its box, else its box's."""
    j0 = prim_box[p, 2]
    j1 = prim_box[p, 3]
    # int64 row and count (the arrays hold int32 and int8), as raster's calls pass: hull_cols
    # compiles once.
    h = np.int64(hulls.index[p])
    m = np.int64(hulls.count[h]) if h >= 0 else np.int64(0)
    # One column of tiles: a hull cannot drop any that its box's rows hold.
    if m > 0 and j0 // TILE < j1 // TILE:
        a, b = hull_cols(hulls.pts, h, m, max(ty * TILE, prim_box[p, 0]),
                         min(ty * TILE + TILE - 1, prim_box[p, 1]), pad)
        j0 = max(j0, a)
        j1 = min(j1, b)
        if j0 > j1:
            return 1, 0
    return j0 // TILE, j1 // TILE


@njit(**_PJIT)
def _tile_ranges(prim_box, hulls, pad):  # pragma: no cover - numba
    """Each primitive's tile columns per tile row of its box (``_tile_cols``), computed once for
    the counting and the filling pass of ``_sort_and_bin``: (rstart (n + 1,) int64, cols
    (rstart[n], 2) int32), primitive p's tile row ty at rstart[p] + ty - prim_box[p, 0] // TILE."""
    n = prim_box.shape[0]
    rstart = np.empty(n + 1, dtype=np.int64)
    rstart[0] = 0
    for p in range(n):
        rstart[p + 1] = rstart[p] + prim_box[p, 1] // TILE - prim_box[p, 0] // TILE + 1
    cols = np.empty((rstart[n], 2), dtype=np.int32)
    prim_box = borrow(prim_box)
    hulls = Hulls(borrow(hulls.index), borrow(hulls.pts), borrow(hulls.count))
    for p in prange(n):
        ty0 = prim_box[p, 0] // TILE
        for ty in range(ty0, prim_box[p, 1] // TILE + 1):
            # The prange index is unsigned: cast, or _tile_cols compiles twice.
            tx0, tx1 = _tile_cols(hulls, np.int64(p), prim_box, ty, pad)
            cols[rstart[p] + ty - ty0, 0] = tx0
            cols[rstart[p] + ty - ty0, 1] = tx1
    return rstart, cols


@njit(**_JIT)
def _sort_and_bin(prim_face, prim_box, prim_z, rstart, cols, res, near):  # pragma: no cover
    """Approximate front-to-back order (log-depth buckets) and per-tile CSR lists in that order.
    Primitive p is listed in the tiles ``_tile_ranges`` gives it (rstart, cols): those of its box
    that its hull, if any, reaches.

    Returns (zkey, tile_start, tile_items): zkey[p] <= prim_z[p] is non-decreasing along each
    tile's list, so a tile can stop at the first primitive whose key is behind its bound."""
    n = prim_z.shape[0]
    zmax = near
    for p in range(n):
        zmax = max(zmax, prim_z[p])
    span = np.log(zmax / near) + 1e-9
    scale = (N_BUCKETS - 1) / span
    bucket = np.empty(n, dtype=np.int64)
    counts = np.zeros(N_BUCKETS + 1, dtype=np.int64)
    zkey = np.empty(n)
    for p in range(n):
        z = max(prim_z[p], near)
        b = min(int(np.log(z / near) * scale), N_BUCKETS - 1)
        bucket[p] = b
        counts[b + 1] += 1
        # Lower edge of the bucket, nudged down against rounding.
        zkey[p] = min(prim_z[p], near * np.exp(b / scale) * (1.0 - 1e-12))
    for b in range(N_BUCKETS):
        counts[b + 1] += counts[b]
    order = np.empty(n, dtype=np.int64)
    for p in range(n):
        b = bucket[p]
        order[counts[b]] = p
        counts[b] += 1
    ntx = (res + TILE - 1) // TILE
    per_face = ntx * ntx
    ntiles = 6 * per_face
    tile_start = np.zeros(ntiles + 1, dtype=np.int64)
    for p in range(n):
        base = prim_face[p] * per_face
        ty0 = prim_box[p, 0] // TILE
        for ty in range(ty0, prim_box[p, 1] // TILE + 1):
            k = rstart[p] + ty - ty0
            for tx in range(cols[k, 0], cols[k, 1] + 1):
                tile_start[base + ty * ntx + tx + 1] += 1
    for i in range(ntiles):
        tile_start[i + 1] += tile_start[i]
    fill = tile_start[:-1].copy()
    items = np.empty(tile_start[ntiles], dtype=np.int32)
    for q in range(n):
        p = order[q]
        base = prim_face[p] * per_face
        ty0 = prim_box[p, 0] // TILE
        for ty in range(ty0, prim_box[p, 1] // TILE + 1):
            k = rstart[p] + ty - ty0
            for tx in range(cols[k, 0], cols[k, 1] + 1):
                tl = base + ty * ntx + tx
                items[fill[tl]] = p
                fill[tl] += 1
    return zkey, tile_start, items
