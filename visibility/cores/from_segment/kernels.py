"""Continuous from-segment visibility (Popescu et al. 2024, Alg. 1) on the six faces of a cubemap.

For a view segment v0 -> v1 (t in [0, 1]) and a cube orientation, every pixel of every face gets a
lower envelope over t of the depths of the primitives that cover its sample; the primitives owning
a piece of some envelope form the segment's visible set. A pixel's sample is its centre (the
paper) or, with ``jitter``, a fixed pseudo-random point of the pixel (``sample_offset``), so that
sub-pixel triangles sliding between two rows of centres still meet samples. Conventions are
``visibility.raster.camera``'s: a sample's ray is (ndc_x, ndc_y, -1) in camera space and depth is
``-z_cam``.

Static triangles (Eqs. 1-2). Relative to the moving eye a static triangle translates by ``-t d``.
With ``w`` the pixel ray, the edge value ``w . ((P - t d) x (Q - t d))`` is linear in t and equals
the barycentric weight of the opposite corner times ``w . N`` (N the triangle normal), so the
coverage interval is the intersection of three half-lines; the hit depth
``(A . N - t d . N) / (w . N)`` is linear too, and ``depth >= near`` is one more half-line: this is
how triangles crossing the near plane, or behind the eye for part of the segment, are handled per
pixel, exactly as a near-clipping rasterizer decides. Edges are evaluated from their corners in a
canonical order so triangles sharing an edge get bit-identical event times (no cracks).
Moving triangles (Sec. 3.2) and spheres (Sec. 3.3) are in ``segment_dynamic`` / ``segment_spheres``.

Pixels a primitive can touch: its swept volume (the convex hull of its corners at both ends,
relative to the eye) clipped at the near plane and projected: the paper's hull of six points,
made safe for points behind the eye.

Pipeline per segment (or per piece of it: ``_piece`` halves a segment along which near clutter
sweeps across much of the cube), memory O(primitive-face pairs):
(1) box pass: triangles are grouped once per scene into spatial clusters of CLUSTER triangles
(Morton order); prange over clusters gives each cube face's pixel box of the cluster's swept
bounding box and its smallest depth. Clusters that are large on screen or reach the near plane are
expanded into their triangles (a box per triangle and face). (2) an approximate front-to-back
counting sort (log-depth buckets) and binning into TILE x TILE pixel tiles (CSR, order kept).
(3) prange over tiles: per pixel, the envelope of depth pieces. A pixel whose envelope covers
all of [0, 1] has a bound (its greatest depth); once every pixel of a tile has one, primitives
that cannot come nearer than the tile's bound are skipped, whole clusters at a time (hierarchical
occlusion culling; exact because an envelope only ever decreases). Tiles never share pixels, so
the result does not depend on thread scheduling.
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field

import numba
import numpy as np
from numba import njit, prange

from visibility.cancel import checkpoint
from visibility.cores.from_segment.dynamic import moving_cover, moving_setup
from visibility.cores.from_segment.spheres import sphere_box, sphere_cover, sphere_setup
from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations
from visibility.raster.face_pixels import pixel_range
from visibility.scene import Scene

#: Side of a square screen tile in pixels (unit of parallel work and of occlusion culling).
TILE = 16
#: Triangles per spatial cluster (unit of the box pass and of tile-level culling).
CLUSTER = 32
#: A cluster whose box covers more tiles than this (or reaches the near plane) is expanded.
EXPAND_TILES = 4
#: Envelope pieces shorter than this (in t) do not make a primitive visible: they are float
#: residue at seams, never seen by a sampling camera.
EPS_LEN = 1e-9
#: A segment piece whose primitives' pixel boxes add up to more than this many times the cube's
#: pixels is cut in two, at most MAX_SPLIT_DEPTH times over (``_piece``). Open scenes sit near 3
#: (the real city tile at 4 m cells); a 4 m side through a 1M-triangle kitchen reaches 80000.
#: On kitchen sides at 64 and 128 px, thresholds of 64 to 1024 came within about 20 % of each
#: other (a piece's fixed costs against its sweep), 16 cut too often (twice the time) and no cut
#: at all took two to three times as long.
SPLIT_AREA = 64
MAX_SPLIT_DEPTH = 6
#: Depth buckets of the front-to-back counting sort.
N_BUCKETS = 2048
#: Default clusters per batch of the box pass (bounds its scratch memory, ~100 bytes each).
DEFAULT_BATCH = 1 << 15
#: Envelope capacity (pieces per pixel): starting value, grown x4 in place when a tile needs
#: more, up to MAX_CAP (a memory guard: 256 pixels x MAX_CAP x 36 bytes per thread).
#: Most groups of tiles the envelope pass of one segment is split into, with a cancellation
#: checkpoint between groups (``visibility.cores.base.checkpoint``).
TILE_GROUPS = 16
START_CAP = 16
MAX_CAP = 1 << 14

FLAG_PRESENT = 1
FLAG_MOVING = 2
FLAG_SLOW = 4  # may reach the near plane: per-pixel near constraint (and clipping) needed
FLAG_SPHERE = 8
FLAG_CLUSTER = 16

_JIT = dict(cache=True, nogil=True, error_model="numpy")
_PJIT = dict(cache=True, nogil=True, parallel=True, error_model="numpy")


def _face_permutation() -> tuple[np.ndarray, np.ndarray]:
    """(6, 3) axis index and sign such that face camera coords = sign * cube coords[axis]."""
    rots = cube_face_rotations(None)
    perm = np.abs(rots).argmax(axis=2).astype(np.int64)
    sgn = np.take_along_axis(rots, perm[..., None], axis=2)[..., 0].copy()
    return perm, sgn


_PERM, _SGN = _face_permutation()


# ------------------------------------------------------------------------------ samples
_U64_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_U64_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_U64_MIX2 = np.uint64(0x94D049BB133111EB)


@njit(**_JIT)
def _unit_hash(key):
    """A float in [0, 1) from a uint64 key (splitmix64's finaliser): decorrelated for
    neighbouring keys, so neighbouring pixels get unrelated offsets."""
    z = key + _U64_GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _U64_MIX1
    z = (z ^ (z >> np.uint64(27))) * _U64_MIX2
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(**_JIT)
def sample_offset(face: int, row: int, col: int, res: int, jitter: float,
                  seed: int) -> tuple[float, float]:
    """Offset (dx, dy), in pixels along +x (columns) and +y (up, i.e. against rows), of pixel
    (face, row, col)'s sample from its centre: uniform in [-jitter, jitter]^2, a fixed hash of
    the pixel and ``seed``. ``jitter = 0`` gives the pixel centre."""
    if jitter == 0.0:
        return 0.0, 0.0
    key = ((np.uint64(seed) * np.uint64(6) + np.uint64(face)) * np.uint64(res)
           + np.uint64(row)) * np.uint64(res) + np.uint64(col)
    k2 = key + key
    return (jitter * (2.0 * _unit_hash(k2) - 1.0),
            jitter * (2.0 * _unit_hash(k2 + np.uint64(1)) - 1.0))


# ------------------------------------------------------------------------------ boxes
@njit(**_JIT)
def _hull_box(cube, npts, f, perm, sgn, near, res, box, pad):
    """Pixel box on cube face f of the convex hull of ``cube[:npts]`` (cube space, relative to
    the eye) clipped to depth >= near. Returns (non-empty, smallest depth of the clipped hull,
    hull reaches the near plane)."""
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
        return False, 0.0, False
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    zm = np.inf
    slow = False
    for q in range(npts):
        d = sd * cube[q, ax]
        if d >= near:
            u = sx * cube[q, ix] / d
            v = sy * cube[q, iy] / d
            umin = min(umin, u)
            umax = max(umax, u)
            vmin = min(vmin, v)
            vmax = max(vmax, v)
            zm = min(zm, d)
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
                    u = sx * (cube[q1, ix] + s * (cube[q2, ix] - cube[q1, ix])) / near
                    v = sy * (cube[q1, iy] + s * (cube[q2, iy] - cube[q1, iy])) / near
                    umin = min(umin, u)
                    umax = max(umax, u)
                    vmin = min(vmin, v)
                    vmax = max(vmax, v)
    if not (umin <= umax and vmin <= vmax):
        return False, 0.0, False
    if not pixel_range(umin, umax, vmin, vmax, res, box, pad):
        return False, 0.0, False
    return True, zm, slow


@njit(**_JIT)
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


@njit(**_JIT)
def _to_cube(rb, x, y, z, cube, q):
    for r in range(3):
        cube[q, r] = rb[r, 0] * x + rb[r, 1] * y + rb[r, 2] * z


@njit(**_JIT)
def _cluster_boxes_range(lo_c, hi_c, v0, dvec, rb, perm, sgn, res, near, pad, out_box, out_z,
                         out_flag, first, last):  # pragma: no cover - numba
    """Per cluster and cube face: pixel box and smallest depth of the swept bounding box (its 8
    corners at t = 0 and t = 1, relative to the eye), flags (0 = absent)."""
    cube = np.empty((16, 3))
    bx = np.empty(4, dtype=np.int64)
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
            ok, zm, slow = _hull_box(cube, 16, f, perm, sgn, near, res, bx, pad)
            if ok:
                for r in range(4):
                    out_box[c, f, r] = bx[r]
                out_z[c, f] = zm
                out_flag[c, f] = FLAG_PRESENT | (FLAG_SLOW if slow else 0)


@njit(**_PJIT)
def _cluster_boxes(lo_c, hi_c, v0, dvec, rb, perm, sgn, res, near, pad, out_box, out_z,
                   out_flag):  # pragma: no cover - numba
    n = lo_c.shape[0]
    nch = min(n, 256)
    for ch in prange(nch):
        _cluster_boxes_range(lo_c, hi_c, v0, dvec, rb, perm, sgn, res, near, pad, out_box, out_z,
                             out_flag, ch * n // nch, (ch + 1) * n // nch)


@njit(**_JIT)
def _tri_cube(verts0, verts1, faces, t, v0, dvec, rb, cube):
    """The six cube-space points of triangle t: corners at t = 0 and t = 1 relative to the eye."""
    for c in range(3):
        vi = faces[t, c]
        _to_cube(rb, verts0[vi, 0] - v0[0], verts0[vi, 1] - v0[1], verts0[vi, 2] - v0[2], cube, c)
        _to_cube(rb, verts1[vi, 0] - v0[0] - dvec[0], verts1[vi, 1] - v0[1] - dvec[1],
                 verts1[vi, 2] - v0[2] - dvec[2], cube, c + 3)


@njit(**_JIT)
def _expanded_boxes_range(verts0, verts1, faces, moving, exp_tri, exp_face, v0, dvec, rb, perm,
                          sgn, res, near, pad, out_box, out_z, out_flag, first,
                          last):  # pragma: no cover - numba
    cube = np.empty((6, 3))
    bx = np.empty(4, dtype=np.int64)
    for k in range(first, last):
        t = exp_tri[k]
        f = exp_face[k]
        out_flag[k] = 0
        _tri_cube(verts0, verts1, faces, t, v0, dvec, rb, cube)
        ok, zm, slow = _hull_box(cube, 6, f, perm, sgn, near, res, bx, pad)
        if ok:
            for r in range(4):
                out_box[k, r] = bx[r]
            out_z[k] = zm
            out_flag[k] = FLAG_PRESENT | (FLAG_MOVING if moving[t] else 0) | (
                FLAG_SLOW if slow else 0)


@njit(**_PJIT)
def _expanded_boxes(verts0, verts1, faces, moving, exp_tri, exp_face, v0, dvec, rb, perm, sgn,
                    res, near, pad, out_box, out_z, out_flag):  # pragma: no cover - numba
    """Pixel box, smallest depth and flags of each (triangle, face) of the expanded clusters."""
    n = exp_tri.shape[0]
    nch = min(n, 256)
    for ch in prange(nch):
        _expanded_boxes_range(verts0, verts1, faces, moving, exp_tri, exp_face, v0, dvec, rb,
                              perm, sgn, res, near, pad, out_box, out_z, out_flag, ch * n // nch,
                              (ch + 1) * n // nch)


@njit(**_JIT)
def _split_clusters(cl_start, cl_tris, cbox, cz, cflag, first, res):  # pragma: no cover
    """Cluster prims (kept whole) and the (triangle, face) list of the expanded ones.

    Returns (keep_cluster, keep_face, keep_box, keep_z, keep_flag, exp_tri, exp_face); cluster
    indices are offset by ``first`` (the batch start)."""
    nc = cflag.shape[0]
    n_keep = 0
    n_exp = 0
    for c in range(nc):
        for f in range(6):
            fl = cflag[c, f]
            if fl == 0:
                continue
            span = (cbox[c, f, 1] // TILE - cbox[c, f, 0] // TILE + 1) * (
                cbox[c, f, 3] // TILE - cbox[c, f, 2] // TILE + 1)
            if (fl & FLAG_SLOW) or span > EXPAND_TILES:
                n_exp += cl_start[first + c + 1] - cl_start[first + c]
            else:
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
            fl = cflag[c, f]
            if fl == 0:
                continue
            span = (cbox[c, f, 1] // TILE - cbox[c, f, 0] // TILE + 1) * (
                cbox[c, f, 3] // TILE - cbox[c, f, 2] // TILE + 1)
            if (fl & FLAG_SLOW) or span > EXPAND_TILES:
                for k in range(cl_start[first + c], cl_start[first + c + 1]):
                    exp_tri[b] = cl_tris[k]
                    exp_face[b] = f
                    b += 1
            else:
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


@njit(**_JIT)
def _sort_and_bin(prim_face, prim_box, prim_z, res, near):  # pragma: no cover - numba
    """Approximate front-to-back order (log-depth buckets) and per-tile CSR lists in that order.

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
        for ty in range(prim_box[p, 0] // TILE, prim_box[p, 1] // TILE + 1):
            for tx in range(prim_box[p, 2] // TILE, prim_box[p, 3] // TILE + 1):
                tile_start[base + ty * ntx + tx + 1] += 1
    for i in range(ntiles):
        tile_start[i + 1] += tile_start[i]
    fill = tile_start[:-1].copy()
    items = np.empty(tile_start[ntiles], dtype=np.int32)
    for q in range(n):
        p = order[q]
        base = prim_face[p] * per_face
        for ty in range(prim_box[p, 0] // TILE, prim_box[p, 1] // TILE + 1):
            for tx in range(prim_box[p, 2] // TILE, prim_box[p, 3] // TILE + 1):
                tl = base + ty * ntx + tx
                items[fill[tl]] = p
                fill[tl] += 1
    return zkey, tile_start, items


# ------------------------------------------------------------------------------ static triangles
@njit(**_JIT)
def _less(ax, ay, az, bx, by, bz):
    if ax != bx:
        return ax < bx
    if ay != by:
        return ay < by
    return az < bz


@njit(**_JIT)
def static_setup(P: np.ndarray, W: np.ndarray, d: np.ndarray, coef: np.ndarray) -> None:
    """Coefficients of a static triangle for ``static_cover``.

    P : (3, 3) camera-space corners relative to the eye at t = 0; W : (3, 3) world corners (edge
    order only); d : (3,) camera-space eye motion over the segment. ``coef`` (>= 25) receives per
    edge the vectors whose dot with the ray (x, y, -1) gives the edge value at t = 0 and its rate
    (canonically oriented), then N, A . N, d . N and |N|^2.
    """
    for e in range(3):
        i = e
        j = (e + 1) % 3
        sg = 1.0
        if _less(W[j, 0], W[j, 1], W[j, 2], W[i, 0], W[i, 1], W[i, 2]):
            i, j = j, i
            sg = -1.0
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


@njit(**_JIT)
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


# ------------------------------------------------------------------------------ envelopes
# A pixel's envelope is rows (t0, t1, z0, m) of ``env[px, :cnt]``: sorted, disjoint pieces with
# depth z0 + m (t - t0) on [t0, t1], and the owning primitive in ``eid[px, :cnt]``.


@njit(**_JIT)
def _emit(T, tid, n, a, b, za, m, pid):
    """Append piece [a, b] (depth za at a, slope m) to the scratch list, extending the previous
    piece instead when it is the same primitive's contiguous continuation on the same line."""
    if not (b > a):
        return n
    if n > 0 and tid[n - 1] == pid and T[n - 1, 1] == a and T[n - 1, 3] == m:
        T[n - 1, 1] = b
        return n
    T[n, 0] = a
    T[n, 1] = b
    T[n, 2] = za
    T[n, 3] = m
    tid[n] = pid
    return n + 1


@njit(**_JIT)
def envelope_insert(env, eid, px, cnt, a, b, za, zb, pid, T, tid):
    """Depth-composite the chord [a, b] (depth za -> zb, primitive pid) into pixel ``px``'s
    envelope.

    The nearer surface wins; exact ties keep the existing piece; crossing chords are split at
    their intersection (the hinge of intersecting triangles). Only the pieces overlapping [a, b]
    are rewritten, and nothing is when the chord is hidden. ``T`` (>= 2 cap + 4, 4) and ``tid``
    are scratch. Returns (new count, or -1 when it would exceed the capacity; changed)."""
    if not (b > a):
        return cnt, False
    mn = (zb - za) / (b - a)
    lo = 0
    while lo < cnt and env[px, lo, 1] <= a:
        lo += 1
    hi = lo
    while hi < cnt and env[px, hi, 0] < b:
        hi += 1
    cap = env.shape[1]
    if lo == hi:
        # Falls in a gap: insert as is.
        if cnt + 1 > cap:
            return -1, False
        for k in range(cnt - 1, hi - 1, -1):
            for r in range(4):
                env[px, k + 1, r] = env[px, k, r]
            eid[px, k + 1] = eid[px, k]
        env[px, lo, 0] = a
        env[px, lo, 1] = b
        env[px, lo, 2] = za
        env[px, lo, 3] = mn
        eid[px, lo] = pid
        return cnt + 1, True
    # Hidden everywhere (no gap, behind at both ends of every overlap): nothing to do.
    cur = a
    hidden = True
    for k in range(lo, hi):
        p0 = env[px, k, 0]
        if p0 > cur:
            hidden = False
            break
        o1 = min(env[px, k, 1], b)
        q0 = env[px, k, 2]
        mp = env[px, k, 3]
        if za + mn * (cur - a) < q0 + mp * (cur - p0) or za + mn * (o1 - a) < q0 + mp * (o1 - p0):
            hidden = False
            break
        cur = o1
    if hidden and cur >= b:
        return cnt, False
    n = 0
    cur = a
    won = False
    for k in range(lo, hi):
        p0 = env[px, k, 0]
        p1 = env[px, k, 1]
        q0 = env[px, k, 2]
        mp = env[px, k, 3]
        qi = eid[px, k]
        if p0 > cur:
            n = _emit(T, tid, n, cur, p0, za + mn * (cur - a), mn, pid)
            won = True
            cur = p0
        elif p0 < cur:
            n = _emit(T, tid, n, p0, cur, q0, mp, qi)
        o0 = cur
        o1 = min(p1, b)
        n0 = za + mn * (o0 - a)
        e0 = q0 + mp * (o0 - p0)
        d0 = n0 - e0
        d1 = (za + mn * (o1 - a)) - (q0 + mp * (o1 - p0))
        if d0 >= 0.0 and d1 >= 0.0:
            n = _emit(T, tid, n, o0, o1, e0, mp, qi)
        elif d0 <= 0.0 and d1 <= 0.0:
            n = _emit(T, tid, n, o0, o1, n0, mn, pid)
            won = True
        else:
            tc = o0 + (o1 - o0) * (d0 / (d0 - d1))
            tc = min(max(tc, o0), o1)
            if d0 < 0.0:
                won = won or tc > o0
                n = _emit(T, tid, n, o0, tc, n0, mn, pid)
                n = _emit(T, tid, n, tc, o1, q0 + mp * (tc - p0), mp, qi)
            else:
                won = won or o1 > tc
                n = _emit(T, tid, n, o0, tc, e0, mp, qi)
                n = _emit(T, tid, n, tc, o1, za + mn * (tc - a), mn, pid)
        cur = o1
        if p1 > b:
            n = _emit(T, tid, n, b, p1, q0 + mp * (b - p0), mp, qi)
    if cur < b:
        n = _emit(T, tid, n, cur, b, za + mn * (cur - a), mn, pid)
        won = True
    if not won:
        return cnt, False
    new_cnt = cnt - (hi - lo) + n
    if new_cnt > cap:
        return -1, False
    shift = n - (hi - lo)
    if shift > 0:
        for k in range(cnt - 1, hi - 1, -1):
            for r in range(4):
                env[px, k + shift, r] = env[px, k, r]
            eid[px, k + shift] = eid[px, k]
    elif shift < 0:
        for k in range(hi, cnt):
            for r in range(4):
                env[px, k + shift, r] = env[px, k, r]
            eid[px, k + shift] = eid[px, k]
    for k in range(n):
        for r in range(4):
            env[px, lo + k, r] = T[k, r]
        eid[px, lo + k] = tid[k]
    return new_cnt, True


@njit(**_JIT)
def _grow(env, eid, cnt, npx, cap):
    """Envelope storage with room for ``cap`` pieces per pixel, holding the current pieces of the
    first ``npx`` pixels; fresh insertion scratch to match."""
    env2 = np.empty((env.shape[0], cap, 4))
    eid2 = np.empty((env.shape[0], cap), dtype=np.int32)
    for p in range(npx):
        for k in range(cnt[p]):
            for r in range(4):
                env2[p, k, r] = env[p, k, r]
            eid2[p, k] = eid[p, k]
    return env2, eid2, np.empty((2 * cap + 8, 4)), np.empty(2 * cap + 8, dtype=np.int32)


@njit(**_JIT)
def pixel_bound(env, px, cnt):
    """Greatest depth of a pixel's envelope when it covers all of [0, 1] (gaps up to EPS_LEN),
    else +inf: no chord at or beyond it can change the envelope."""
    if cnt == 0 or env[px, 0, 0] > EPS_LEN:
        return np.inf
    prev = 0.0
    zmax = 0.0
    for k in range(cnt):
        t0 = env[px, k, 0]
        if t0 - prev > EPS_LEN:
            return np.inf
        prev = env[px, k, 1]
        z0 = env[px, k, 2]
        zmax = max(zmax, max(z0, z0 + env[px, k, 3] * (prev - t0)))
    if prev < 1.0 - EPS_LEN:
        return np.inf
    return zmax


# ------------------------------------------------------------------------------ tile resolution
@njit(**_JIT)
def _cam_corners(R, verts0, verts1, faces, t, v0, dc, P, U, W):
    """Camera-space corners P of triangle t at t = 0 (relative to the eye), their velocities U
    relative to the moving eye, and the world corners W (for canonical edge order). One formula
    for every caller, so shared edges stay bit-identical."""
    for c in range(3):
        vi = faces[t, c]
        for r in range(3):
            W[c, r] = verts0[vi, r]
        x = verts0[vi, 0] - v0[0]
        y = verts0[vi, 1] - v0[1]
        z = verts0[vi, 2] - v0[2]
        mx = verts1[vi, 0] - verts0[vi, 0]
        my = verts1[vi, 1] - verts0[vi, 1]
        mz = verts1[vi, 2] - verts0[vi, 2]
        for r in range(3):
            P[c, r] = R[r, 0] * x + R[r, 1] * y + R[r, 2] * z
            U[c, r] = R[r, 0] * mx + R[r, 1] * my + R[r, 2] * mz - dc[r]


@njit(**_JIT)
def _front_box(P, U, res, box, pad):
    """Pixel box and smallest depth of a triangle's six swept points, all known to be in front
    of the near plane (a cluster that is not near the eye)."""
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    zm = np.inf
    for c in range(3):
        for e in range(2):
            x = P[c, 0] + e * U[c, 0]
            y = P[c, 1] + e * U[c, 1]
            d = -(P[c, 2] + e * U[c, 2])
            inv = 1.0 / d
            umin = min(umin, x * inv)
            umax = max(umax, x * inv)
            vmin = min(vmin, y * inv)
            vmax = max(vmax, y * inv)
            zm = min(zm, d)
    return pixel_range(umin, umax, vmin, vmax, res, box, pad), zm


@njit(**_JIT)
def _raster(kind, pid, slow, zpr, ia, ib, ja, jb, r0, cl0, tw, npx, step, near, knots, coef,
            env, eid, cnt, bound, T, tid, pt0, pt1, pz0, pz1, brk, stk, jx, jy):
    """Composite one set-up primitive (kind 0 static triangle, 1 moving triangle, 2 sphere) into
    the envelopes of the pixels [ia, ib] x [ja, jb] of the current tile, sampled at their
    centres moved by (jx, jy)[pixel] NDC units (``sample_offset``). Returns (env, eid, T,
    tid, pixels newly bounded, overflow, pairs, pieces, grows); the storage is reallocated
    when it grows."""
    closed = 0
    pairs = 0
    pieces = 0
    grows = 0
    for i in range(ia, ib + 1):
        yc = 1.0 - (i + 0.5) * step
        for j in range(ja, jb + 1):
            px = (i - r0) * tw + (j - cl0)
            bpx = bound[px]
            if zpr >= bpx:
                continue
            x = (j + 0.5) * step - 1.0 + jx[px]
            y = yc + jy[px]
            pairs += 1
            if kind == 0:
                ok, ts, tf, zs, zf = static_cover(coef, x, y, near, slow)
                if not ok or min(zs, zf) >= bpx:
                    continue
                pt0[0] = ts
                pt1[0] = tf
                pz0[0] = zs
                pz1[0] = zf
                npc = 1
            elif kind == 1:
                npc = moving_cover(coef, x, y, near, slow, knots, pt0, pt1, pz0, pz1, brk, stk)
            else:
                npc = sphere_cover(coef, x, y, near, slow, knots, pt0, pt1, pz0, pz1, brk, stk)
            for q in range(npc):
                if min(pz0[q], pz1[q]) >= bound[px]:
                    continue
                pieces += 1
                nn, changed = envelope_insert(env, eid, px, cnt[px], pt0[q], pt1[q], pz0[q],
                                              pz1[q], pid, T, tid)
                if nn < 0:
                    # Deep envelope: grow this chunk's storage in place and retry.
                    if 4 * env.shape[1] > MAX_CAP:
                        return env, eid, T, tid, closed, True, pairs, pieces, grows
                    env, eid, T, tid = _grow(env, eid, cnt, npx, 4 * env.shape[1])
                    grows += 1
                    nn, changed = envelope_insert(env, eid, px, cnt[px], pt0[q], pt1[q],
                                                  pz0[q], pz1[q], pid, T, tid)
                if changed:
                    cnt[px] = nn
                    zb = pixel_bound(env, px, nn)
                    if zb < np.inf:
                        if bound[px] == np.inf:
                            closed += 1
                        bound[px] = zb
    return env, eid, T, tid, closed, False, pairs, pieces, grows


@njit(**_PJIT)
def _resolve(tiles, n_chunks, tile_start, tile_items, prim_src, prim_box, prim_z, prim_zkey,
             prim_flag, prim_face, verts0, verts1, faces, moving, cl_start, cl_tris, c0, c1,
             radii, n_tri, v0, dvec, rots, res, near, knots, jitter, seed, visible, overflow,
             counters, witness):  # pragma: no cover - numba
    """Envelopes of the listed tiles; marks visible primitives (global ids: triangles, then
    n_tri + sphere). A tile whose envelopes outgrow MAX_CAP sets ``overflow``, marks nothing.
    Tiles are strided over chunks so that busy screen regions spread over the threads."""
    for ch in prange(n_chunks):
        _resolve_chunk(ch, tiles, n_chunks, tile_start, tile_items, prim_src, prim_box, prim_z,
                       prim_zkey, prim_flag, prim_face, verts0, verts1, faces, moving, cl_start,
                       cl_tris, c0, c1, radii, n_tri, v0, dvec, rots, res, near, knots, jitter,
                       seed, visible, overflow, counters, witness)


@njit(**_JIT)
def _resolve_chunk(ch, tiles, n_chunks, tile_start, tile_items, prim_src, prim_box, prim_z,
                   prim_zkey, prim_flag, prim_face, verts0, verts1, faces, moving, cl_start,
                   cl_tris, c0, c1, radii, n_tri, v0, dvec, rots, res, near, knots, jitter,
                   seed, visible, overflow, counters, witness):  # pragma: no cover - numba
    ntx = (res + TILE - 1) // TILE
    per_face = ntx * ntx
    npx_max = TILE * TILE
    step = 2.0 / res
    maxp = 8 * (knots + 2) + 8
    want_witness = witness.shape[1] == visible.shape[0]
    cap = START_CAP
    env = np.empty((npx_max, cap, 4))
    eid = np.empty((npx_max, cap), dtype=np.int32)
    cnt = np.zeros(npx_max, dtype=np.int64)
    bound = np.empty(npx_max)
    T = np.empty((2 * cap + 8, 4))  # insertion scratch
    tid = np.empty(2 * cap + 8, dtype=np.int32)
    pt0 = np.empty(maxp)
    pt1 = np.empty(maxp)
    pz0 = np.empty(maxp)
    pz1 = np.empty(maxp)
    brk = np.empty(48)
    stk = np.empty((64, 4))
    coef = np.empty(40)
    P = np.empty((3, 3))
    U = np.empty((3, 3))
    W = np.empty((3, 3))
    dc = np.empty(3)
    cen = np.empty(3)
    vel = np.empty(3)
    bx = np.empty(4, dtype=np.int64)
    jx = np.zeros(npx_max)
    jy = np.zeros(npx_max)
    n_pairs = 0
    n_pieces = 0
    n_grows = 0
    n_items = 0
    n_culled = 0
    n_final = 0
    for qi in range(ch, tiles.shape[0], n_chunks):
        tile = tiles[qi]
        f = tile // per_face
        rt = tile % per_face
        r0 = (rt // ntx) * TILE
        cl0 = (rt % ntx) * TILE
        r1 = min(r0 + TILE, res)
        cl1 = min(cl0 + TILE, res)
        tw = cl1 - cl0
        npx = (r1 - r0) * tw
        for p in range(npx):
            cnt[p] = 0
            bound[p] = np.inf
            if jitter > 0.0:
                dx, dy = sample_offset(f, r0 + p // tw, cl0 + p % tw, res, jitter, seed)
                jx[p] = dx * step
                jy[p] = dy * step
        open_px = npx
        tbound = np.inf
        since = 0
        R = rots[f]
        for r in range(3):
            dc[r] = R[r, 0] * dvec[0] + R[r, 1] * dvec[1] + R[r, 2] * dvec[2]
        ovf = False
        end = tile_start[tile + 1]
        for it in range(tile_start[tile], end):
            pr = tile_items[it]
            if prim_zkey[pr] >= tbound:
                n_culled += end - it
                break
            if prim_z[pr] >= tbound:
                n_culled += 1
                continue
            n_items += 1
            src = prim_src[pr]
            flag = prim_flag[pr]
            slow = (flag & FLAG_SLOW) != 0
            closed = 0
            if flag & FLAG_CLUSTER:
                for k in range(cl_start[src], cl_start[src + 1]):
                    t = cl_tris[k]
                    _cam_corners(R, verts0, verts1, faces, t, v0, dc, P, U, W)
                    ok, zt = _front_box(P, U, res, bx, jitter)
                    if not ok or zt >= tbound:
                        continue
                    ia = max(bx[0], r0)
                    ib = min(bx[1], r1 - 1)
                    ja = max(bx[2], cl0)
                    jb = min(bx[3], cl1 - 1)
                    if ia > ib or ja > jb:
                        continue
                    if moving[t]:
                        moving_setup(P, U, W, coef)
                        kind = 1
                    else:
                        static_setup(P, W, dc, coef)
                        kind = 0
                    env, eid, T, tid, nc, ovf, a0, a1, a2 = _raster(
                        kind, t, False, zt, ia, ib, ja, jb, r0, cl0, tw, npx, step, near,
                        knots, coef, env, eid, cnt, bound, T, tid, pt0, pt1, pz0, pz1, brk, stk,
                        jx, jy)
                    closed += nc
                    n_pairs += a0
                    n_pieces += a1
                    n_grows += a2
                    if ovf:
                        break
            else:
                if flag & FLAG_SPHERE:
                    kind = 2
                    s = src - n_tri
                    for r in range(3):
                        cen[r] = R[r, 0] * (c0[s, 0] - v0[0]) + R[r, 1] * (c0[s, 1] - v0[1]) \
                            + R[r, 2] * (c0[s, 2] - v0[2])
                        vel[r] = R[r, 0] * (c1[s, 0] - c0[s, 0]) + R[r, 1] * (
                            c1[s, 1] - c0[s, 1]) + R[r, 2] * (c1[s, 2] - c0[s, 2]) - dc[r]
                    sphere_setup(cen, vel, radii[s], coef)
                else:
                    _cam_corners(R, verts0, verts1, faces, src, v0, dc, P, U, W)
                    if flag & FLAG_MOVING:
                        kind = 1
                        moving_setup(P, U, W, coef)
                    else:
                        kind = 0
                        static_setup(P, W, dc, coef)
                env, eid, T, tid, closed, ovf, a0, a1, a2 = _raster(
                    kind, src, slow, prim_z[pr], max(prim_box[pr, 0], r0),
                    min(prim_box[pr, 1], r1 - 1), max(prim_box[pr, 2], cl0),
                    min(prim_box[pr, 3], cl1 - 1), r0, cl0, tw, npx, step, near, knots, coef,
                    env, eid, cnt, bound, T, tid, pt0, pt1, pz0, pz1, brk, stk, jx, jy)
                n_pairs += a0
                n_pieces += a1
                n_grows += a2
            if ovf:
                break
            open_px -= closed
            since += 1
            if open_px == 0 and (tbound == np.inf or since >= 8):
                tb = 0.0
                for p in range(npx):
                    tb = max(tb, bound[p])
                tbound = tb
                since = 0
        if ovf:
            overflow[qi] = True
            continue
        for p in range(npx):
            n_final += cnt[p]
            for k in range(cnt[p]):
                length = env[p, k, 1] - env[p, k, 0]
                if length > EPS_LEN:
                    pid = eid[p, k]
                    visible[pid] = True
                    if want_witness and length > witness[ch, pid, 0]:
                        witness[ch, pid, 0] = length
                        witness[ch, pid, 1] = 0.5 * (env[p, k, 0] + env[p, k, 1])
                        witness[ch, pid, 2] = f
                        witness[ch, pid, 3] = r0 + p // tw
                        witness[ch, pid, 4] = cl0 + p % tw
    counters[ch, 0] += n_pairs
    counters[ch, 1] += n_pieces
    counters[ch, 2] += n_items
    counters[ch, 3] += n_culled
    counters[ch, 4] += n_final
    counters[ch, 5] += n_grows
    counters[ch, 6] = max(counters[ch, 6], env.shape[1])


# ------------------------------------------------------------------------------ geometry
@dataclass(eq=False)
class SegmentGeometry:
    """The geometry of one state interval, as the kernels read it.

    Attributes
    ----------
    verts0, verts1 : (n, 3) float64 vertex positions at the interval's start and end (the same
        array for a static scene), metres.
    faces : (m, 3) int32.
    tri_sel : (k,) int64 ids of the triangles that take part (valid faces).
    moving : (m,) bool, triangles whose corners move in this interval.
    centers0, centers1 : (s, 3) float64 sphere centres at start and end; radii : (s,) float64.
    sphere_sel : (q,) int64 ids of the spheres that take part.
    cl_start, cl_tris : spatial clusters of the selected triangles: cluster c holds
        ``cl_tris[cl_start[c]:cl_start[c + 1]]`` (CLUSTER triangles, Morton order of centroids).
    cl_lo, cl_hi : (c, 3) float64 bounding box of each cluster over both positions.
    """

    verts0: np.ndarray
    verts1: np.ndarray
    faces: np.ndarray
    tri_sel: np.ndarray
    moving: np.ndarray
    centers0: np.ndarray
    centers1: np.ndarray
    radii: np.ndarray
    sphere_sel: np.ndarray
    cl_start: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    cl_tris: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    cl_lo: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cl_hi: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def n_triangles(self) -> int:
        return int(len(self.faces))

    @property
    def n_ids(self) -> int:
        """Length of the visibility mask: triangles, then spheres."""
        return int(len(self.faces) + len(self.radii))


def _part1by2(x: np.ndarray) -> np.ndarray:
    x = x & np.uint64(0x3FF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x30000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x300F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x9249249)
    return x


def build_clusters(vertices: np.ndarray, faces: np.ndarray,
                   tri_sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cl_start (c + 1,), cl_tris (k,)): the selected triangles in Morton order of their
    centroids, cut into clusters of CLUSTER consecutive triangles."""
    k = len(tri_sel)
    if k == 0:
        return np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    f = faces[tri_sel]
    cent = vertices[f[:, 0]] + vertices[f[:, 1]] + vertices[f[:, 2]]
    lo = cent.min(axis=0)
    span = np.maximum(cent.max(axis=0) - lo, 1e-300)
    q = np.clip((cent - lo) / span * 1023.0, 0, 1023).astype(np.uint64)
    code = _part1by2(q[:, 0]) | (_part1by2(q[:, 1]) << np.uint64(1)) | (
        _part1by2(q[:, 2]) << np.uint64(2))
    cl_tris = tri_sel[np.argsort(code, kind="stable")].astype(np.int64)
    cl_start = np.append(np.arange(0, k, CLUSTER, dtype=np.int64), k)
    return cl_start, cl_tris


@njit(**_JIT)
def _cluster_bounds(verts0, verts1, faces, cl_start, cl_tris):  # pragma: no cover - numba
    """(c, 3) min and max corner of each cluster over both vertex positions."""
    nc = cl_start.shape[0] - 1
    lo = np.empty((nc, 3))
    hi = np.empty((nc, 3))
    for c in range(nc):
        for r in range(3):
            lo[c, r] = np.inf
            hi[c, r] = -np.inf
        for k in range(cl_start[c], cl_start[c + 1]):
            t = cl_tris[k]
            for j in range(3):
                vi = faces[t, j]
                for r in range(3):
                    a = verts0[vi, r]
                    b = verts1[vi, r]
                    lo[c, r] = min(lo[c, r], min(a, b))
                    hi[c, r] = max(hi[c, r], max(a, b))
    return lo, hi


_GEOMETRY_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _signature(scene: Scene) -> tuple:
    arrays = (scene.vertices, scene.faces, scene.states, scene.sphere_centers, scene.sphere_radii)
    return tuple((id(a), None if a is None else a.shape) for a in arrays)


def scene_geometries(scene: Scene) -> list[SegmentGeometry]:
    """One ``SegmentGeometry`` per consecutive pair of the scene's states (one for a static
    scene). Triangles use ``scene.valid_faces``; spheres need finite centres and radius > 0.

    Cached per scene (weakly; rebuilt if its arrays are replaced): clusters are built once.
    Scenes are treated as immutable: arrays changed in place are not noticed.
    """
    sig = _signature(scene)
    hit = _GEOMETRY_CACHE.get(scene)
    if hit is not None and hit[0] == sig:
        return hit[1]
    faces = np.ascontiguousarray(scene.faces, dtype=np.int32)
    tri_sel = np.flatnonzero(scene.valid_faces).astype(np.int64)
    m = len(faces)
    if scene.states is not None and scene.states.shape[0] > 1:
        tri_states = [np.ascontiguousarray(s) for s in scene.states]
    else:
        base = scene.vertices if scene.states is None else scene.states[0]
        tri_states = [np.ascontiguousarray(base, dtype=np.float64)]
    if scene.n_spheres:
        radii = np.ascontiguousarray(scene.sphere_radii, dtype=np.float64)
        cs = [np.ascontiguousarray(c) for c in scene.sphere_centers]
        finite = np.all(np.isfinite(scene.sphere_centers), axis=(0, 2))
        ok = finite & np.isfinite(radii) & (radii > 0)
        sphere_sel = np.flatnonzero(ok).astype(np.int64)
    else:
        radii = np.zeros(0)
        cs = [np.zeros((0, 3))]
        sphere_sel = np.zeros(0, dtype=np.int64)
    cl_start, cl_tris = build_clusters(tri_states[0], faces, tri_sel)
    pairs = max(len(tri_states), len(cs)) - 1
    out = []
    for p in range(max(pairs, 1)):
        a = tri_states[min(p, len(tri_states) - 1)]
        b = tri_states[min(p + 1, len(tri_states) - 1)]
        if a is b:
            moving = np.zeros(m, dtype=bool)
        else:
            vm = np.any(a != b, axis=1)
            moving = vm[faces].any(axis=1) if m else np.zeros(0, dtype=bool)
        lo, hi = _cluster_bounds(a, b, faces, cl_start, cl_tris)
        out.append(SegmentGeometry(
            verts0=a, verts1=b, faces=faces, tri_sel=tri_sel, moving=moving,
            centers0=cs[min(p, len(cs) - 1)], centers1=cs[min(p + 1, len(cs) - 1)], radii=radii,
            sphere_sel=sphere_sel, cl_start=cl_start, cl_tris=cl_tris, cl_lo=lo, cl_hi=hi))
    _GEOMETRY_CACHE[scene] = (sig, out)
    return out


# ------------------------------------------------------------------------------ Python driver
def _collect_prims(geom, v0, dvec, rb, rots, res, near, pad, batch, stats):
    """All (primitive, face) pairs that can touch a pixel sample of the segment's cubemap:
    whole clusters, triangles of expanded clusters, spheres (global ids n_tri + s)."""
    parts = []
    nc = len(geom.cl_start) - 1
    kept = 0
    expanded = 0
    for first in range(0, nc, batch):
        last = min(nc, first + batch)
        k = last - first
        cbox = np.empty((k, 6, 4), dtype=np.int32)
        cz = np.empty((k, 6))
        cflag = np.empty((k, 6), dtype=np.uint8)
        _cluster_boxes(geom.cl_lo[first:last], geom.cl_hi[first:last], v0, dvec, rb, _PERM, _SGN,
                       res, near, pad, cbox, cz, cflag)
        kc, kf, kb, kz, kfl, et, ef = _split_clusters(geom.cl_start, geom.cl_tris, cbox, cz,
                                                      cflag, first, res)
        parts.append((kc, kf, kb, kz, kfl))
        kept += len(kc)
        if len(et):
            ebox = np.empty((len(et), 4), dtype=np.int32)
            ez = np.empty(len(et))
            efl = np.empty(len(et), dtype=np.uint8)
            _expanded_boxes(geom.verts0, geom.verts1, geom.faces, geom.moving, et, ef, v0, dvec,
                            rb, _PERM, _SGN, res, near, pad, ebox, ez, efl)
            keep = efl != 0
            parts.append((et[keep].astype(np.int32), ef[keep].astype(np.int32), ebox[keep],
                          ez[keep], efl[keep]))
            expanded += int(keep.sum())
    if len(geom.sphere_sel):
        k = len(geom.sphere_sel)
        box = np.empty((k, 6, 4), dtype=np.int32)
        z = np.empty((k, 6))
        flag = np.empty((k, 6), dtype=np.uint8)
        _sphere_boxes(geom.centers0, geom.centers1, geom.radii, geom.sphere_sel, v0, dvec, rots,
                      res, near, pad, box, z, flag)
        si, sf = np.nonzero(flag)
        parts.append(((geom.sphere_sel[si] + geom.n_triangles).astype(np.int32),
                      sf.astype(np.int32), box[si, sf], z[si, sf], flag[si, sf]))
    if not parts:
        parts.append((np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 4), np.int32),
                      np.zeros(0), np.zeros(0, np.uint8)))
    prim_src, prim_face, prim_box, prim_z, prim_flag = (
        np.ascontiguousarray(np.concatenate([p[i] for p in parts])) for i in range(5))
    stats["prims"] = stats.get("prims", 0) + len(prim_src)
    stats["cluster_prims"] = stats.get("cluster_prims", 0) + kept
    stats["triangle_prims"] = stats.get("triangle_prims", 0) + expanded
    return prim_src, prim_face, prim_box, prim_z, prim_flag


def segment_visible(
    geom: SegmentGeometry,
    v0: np.ndarray,
    v1: np.ndarray,
    base_rotation: np.ndarray | None = None,
    resolution: int = 256,
    near: float = DEFAULT_NEAR,
    knots: int = 16,
    batch: int = DEFAULT_BATCH,
    visible: np.ndarray | None = None,
    stats: dict | None = None,
    witness: np.ndarray | None = None,
    jitter: float = 0.0,
    seed: int = 0,
    max_cuts: int | None = None,
) -> np.ndarray:
    """Primitives visible at some pixel sample of a cubemap moving along v0 -> v1.

    Parameters
    ----------
    geom : the scene's geometry for one state interval (``scene_geometries``); vertices and
        sphere centres move linearly over it while the eye moves from v0 to v1.
    v0, v1 : (3,) segment end points, metres (equal points give from-point visibility).
    base_rotation : (3, 3) world-to-cube rotation (``camera.cube_face_rotations``), None = axes.
    resolution : face resolution in pixels (90-degree square faces).
    near : near-plane distance, metres.
    knots : moving triangles' and spheres' depth chords are at most 1 / knots long (in t).
    batch : clusters per batch of the box pass.
    visible : optional (geom.n_ids,) bool mask to OR into (triangles first, then spheres).
    stats : optional dict; counters and per-phase seconds are added to it.
    witness : optional (geom.n_ids, 5) float64 array (zeros to start): for each visible primitive,
        its longest envelope piece seen so far as (length in t, mid t, face, row, col), i.e. a
        time and pixel at which it is the nearest surface (for tests and debugging; the
        pixel's sample is ``sample_offset(face, row, col, resolution, jitter, seed)`` off its
        centre).
    jitter : how far, in pixels (0 to 0.5), each pixel's sample lies off its centre, per axis:
        a fixed pseudo-random point of the pixel (``sample_offset``), the same for the whole
        segment. 0 samples pixel centres. A thin band sliding along itself between two pixel
        rows covers no centre anywhere on the segment; jittered samples do not line up, so it
        meets some.
    seed : picks the jitter pattern (non-negative).

    max_cuts : a segment along which near geometry sweeps across much of the cube is solved as
        pieces, halved up to this many times over (``_piece``, ``stats["splits"]``; None =
        ``MAX_SPLIT_DEPTH``, 0 = never), when nothing in the scene moves.

    Returns
    -------
    (geom.n_ids,) bool mask of primitives visible from the segment (``visible`` if given).
    """
    v0 = np.asarray(v0, dtype=np.float64).reshape(3)
    v1 = np.asarray(v1, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(v0)) and np.all(np.isfinite(v1))):
        raise ValueError("segment end points must be finite")
    res = int(resolution)
    if not 1 <= res <= 1 << 14:
        raise ValueError(f"resolution must be in [1, 16384], got {resolution}")
    if not (np.isfinite(near) and near > 0):
        raise ValueError(f"near must be a positive number of metres, got {near}")
    if int(knots) < 1:
        raise ValueError(f"knots must be >= 1, got {knots}")
    jitter = float(jitter)
    if not 0.0 <= jitter <= 0.5:
        raise ValueError(f"jitter must be in [0, 0.5] pixels, got {jitter}")
    if int(seed) < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    cuts = MAX_SPLIT_DEPTH if max_cuts is None else int(max_cuts)
    if not 0 <= cuts <= 16:
        raise ValueError(f"max_cuts must be in [0, 16], got {max_cuts}")
    if visible is None:
        visible = np.zeros(geom.n_ids, dtype=bool)
    elif visible.shape != (geom.n_ids,) or visible.dtype != np.bool_:
        raise ValueError(f"visible must be a ({geom.n_ids},) bool array")
    if witness is not None and witness.shape != (geom.n_ids, 5):
        raise ValueError(f"witness must be ({geom.n_ids}, 5), got {witness.shape}")
    if stats is None:
        stats = {}
    rb = np.eye(3) if base_rotation is None else np.ascontiguousarray(base_rotation, np.float64)
    rots = np.ascontiguousarray(cube_face_rotations(rb))
    # Geometry that moves with t cannot be cut at a mid time without re-interpolating it.
    splittable = geom.verts0 is geom.verts1 and geom.centers0 is geom.centers1
    _piece(geom, v0, v1 - v0, 0.0, 1.0, cuts if splittable else 0, rb, rots, res,
           float(near), int(knots), jitter, int(seed), max(1, int(batch)), visible, stats,
           witness)
    return visible


def _piece(geom, v0, dvec, ta, tb, depth, rb, rots, res, near, knots, jitter, seed, batch,
           visible, stats, witness):
    """Visible set of the eye walking v0 -> v0 + dvec (times [ta, tb] of the whole segment).

    A piece whose primitives' pixel boxes add up to more than ``SPLIT_AREA`` times the cube's
    pixels is cut in two (up to ``depth`` more times): geometry close to a long segment sweeps
    across much of the cube, so its boxes are huge and occlusion bounds (the farthest depth a
    pixel's envelope reaches along the piece) stay far; halves sweep half as far. The union of
    the halves' sets is the set of the whole (exactness is per eye position)."""
    t0 = time.perf_counter()
    prim_src, prim_face, prim_box, prim_z, prim_flag = _collect_prims(
        geom, v0, dvec, rb, rots, res, near, jitter, batch, stats)
    t1 = time.perf_counter()
    if depth > 0 and len(prim_box):
        area = int(np.sum((prim_box[:, 1] - prim_box[:, 0] + 1).astype(np.int64)
                          * (prim_box[:, 3] - prim_box[:, 2] + 1)))
        if area > SPLIT_AREA * 6 * res * res:
            stats["box_seconds"] = stats.get("box_seconds", 0.0) + (t1 - t0)
            stats["splits"] = stats.get("splits", 0) + 1
            del prim_src, prim_face, prim_box, prim_z, prim_flag
            half = 0.5 * dvec
            tm = 0.5 * (ta + tb)
            for a, lo, hi in ((v0, ta, tm), (v0 + half, tm, tb)):
                checkpoint()
                _piece(geom, a, half, lo, hi, depth - 1, rb, rots, res, near, knots, jitter,
                       seed, batch, visible, stats, witness)
            return
    zkey, tile_start, items = _sort_and_bin(prim_face, prim_box, prim_z, res, near)
    t2 = time.perf_counter()
    tiles = np.flatnonzero(np.diff(tile_start) > 0).astype(np.int64)
    # Tiles are strided over several chunks per thread so busy screen regions spread out.
    nch = max(1, min(len(tiles), 8 * numba.get_num_threads()))
    counters = np.zeros((nch, 7), dtype=np.int64)
    counters[:, 6] = START_CAP
    wit = np.zeros((nch, geom.n_ids, 5)) if witness is not None else np.zeros((1, 0, 5))
    overflow = np.zeros(len(tiles), dtype=bool)
    # The envelope pass runs in groups of tiles with a checkpoint between them, so a cancelled
    # or late computation stops within a fraction of one segment's time.
    groups = max(1, min(TILE_GROUPS, len(tiles) // (4 * nch)))
    for sel in np.array_split(np.arange(len(tiles)), groups):
        if not len(sel):
            continue
        checkpoint()
        group_overflow = np.zeros(len(sel), dtype=bool)
        _resolve(tiles[sel], nch, tile_start, items, prim_src, prim_box, prim_z, zkey, prim_flag,
                 prim_face, geom.verts0, geom.verts1, geom.faces, geom.moving, geom.cl_start,
                 geom.cl_tris, geom.centers0, geom.centers1, geom.radii, geom.n_triangles, v0,
                 dvec, rots, res, near, knots, jitter, seed, visible,
                 group_overflow, counters, wit)
        overflow[sel] = group_overflow
    if overflow.any():
        raise RuntimeError(f"more than {MAX_CAP} visibility events at one pixel centre in "
                           f"{int(overflow.sum())} tiles; lower the resolution")
    t3 = time.perf_counter()
    if witness is not None:
        best = np.argmax(wit[:, :, 0], axis=0)
        cand = wit[best, np.arange(geom.n_ids)]
        # Piece times to segment times.
        cand[:, 0] *= tb - ta
        cand[:, 1] = ta + cand[:, 1] * (tb - ta)
        better = cand[:, 0] > witness[:, 0]
        witness[better] = cand[better]
    stats["box_seconds"] = stats.get("box_seconds", 0.0) + (t1 - t0)
    stats["bin_seconds"] = stats.get("bin_seconds", 0.0) + (t2 - t1)
    stats["envelope_seconds"] = stats.get("envelope_seconds", 0.0) + (t3 - t2)
    stats["tile_items"] = stats.get("tile_items", 0) + int(len(items))
    for k, name in enumerate(("pairs", "pieces", "items_processed", "items_culled",
                              "final_pieces", "envelope_grows")):
        stats[name] = stats.get(name, 0) + int(counters[:, k].sum())
    stats["max_cap"] = max(stats.get("max_cap", 0), int(counters[:, 6].max()))
    stats["face_runs"] = stats.get("face_runs", 0) + 6
