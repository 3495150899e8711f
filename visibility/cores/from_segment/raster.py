"""Rasterization and resolution of a view segment's tiles: each pixel's sample
(``sample_offset``), each primitive's coverage composited into the envelopes of the pixels of a
tile (``_raster``), the tiles resolved in parallel with occlusion culling (``_resolve``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.borrow import NO_REFCOUNT, borrow, keep_alive
from visibility.cores.from_segment.boxes import (
    FLAG_CLUSTER,
    FLAG_MOVING,
    FLAG_SLOW,
    FLAG_SPHERE,
    TILE,
)
from visibility.cores.from_segment.dynamic import moving_cover, moving_setup
from visibility.cores.from_segment.envelope import (
    EPS_LEN,
    MAX_CAP,
    _grow,
    envelope_insert,
    hides_over,
    pixel_bound,
)
from visibility.cores.from_segment.groups import (
    ChunkScratch,
    GeometryArrays,
    PieceScratch,
    PrimRows,
    Results,
    Sweep,
    TilePixels,
    TileWork,
)
from visibility.cores.from_segment.hull import HMAX, Hulls, hull_rows, store_hull
from visibility.cores.from_segment.spheres import sphere_cover, sphere_setup
from visibility.cores.from_segment.static import static_cover, static_setup
from visibility.cycles import cycles as _cycles
from visibility.exact_grid import ray_triangle
from visibility.raster.face_pixels import pixel_range
from visibility.shares import run_shares, take_next

#: A tile whose entries not yet marked visible are at most one in KNOWN_SHARE resolves only
#: the pixels those can reach (finding the pixels costs a pass over their spans).
KNOWN_SHARE = 8
#: A primitive whose box holds at most this many pixels of a tile is scanned over its box: its
#: hull (a convex hull of six points for a cluster's triangle, a pass over the hull's edges
#: for the others) costs more than the cover tests it could spare there.
SMALL_BOX = 8
#: Tiles listing more primitives than this (clutter) get no footprint rule
#: (``_footprint_seen``): each of its rays walks the list.
FOOTPRINT_MAX_ITEMS = 2048
#: The footprint rule's modes (``Sweep.footprint``): off (the pixel samples alone), a sample
#: at the centroid of a triangle no pixel sample meets and whose box holds no closed pixel,
#: or also near its corners, and for triangles whose box holds closed pixels beside open ones.
FOOTPRINT_OFF, FOOTPRINT_CENTROID, FOOTPRINT_CORNERS = 0, 1, 2
#: How far a corner's point lies towards the centroid (a share of the way).
CORNER_INSET = 0.1
#: What ``_point_seen`` found for a point, in rising order of what it learnt.
OUTSIDE, SKIPPED, BLOCKED, SEEN = 0, 1, 2, 3
#: One pixel pair in TIME_STRIDE is timed by step (cover test, then the envelope's insertions):
#: two counter reads at every pair would cost a sizeable share of a meadow's time.
TIME_STRIDE = 16

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Helpers called per primitive, tile or row that allocate nothing: no reference counting.
_JIT_NO_NRT = dict(_JIT, **NO_REFCOUNT)
_JIT_INLINE_HELPER = dict(_JIT, inline="always")

#: Columns of ``_resolve``'s counters (one row per chunk), summed into the segment's stats under
#: these names except ``max_cap`` (a maximum) and ``thread`` (the worker, one per thread, that ran
#: the chunk last). pairs: (pixel, primitive) cover tests; pieces: chords passed to the envelope;
#: inserts: those that changed it; insert_scan: the envelope's length at each chord (what a linear
#: insertion would read; the bisection reads its log); setups: triangle or sphere set-ups; items /
#: items_culled: tile list entries processed / skipped by the tile's bound; final_pieces: envelope
#: rows at the end; cycles*: CPU cycle counter, whole chunks and split into primitive set-up (and
#: culling), rasterization (cover tests and inserts) and per-tile work; pairs_uncovered /
#: pairs_behind: pairs whose pixel sample the primitive never covers along the segment / covers only
#: behind the pixel's closed envelope (the pairs' waste, by cause: a loose span or a missing depth
#: bound); cluster_pairs(_uncovered): those of cluster triangles; insert_moved: rows after an
#: insert's chord that a change of the envelope's length moved along its sorted array (the part of
#: linear insertion a search cannot save); bound_scans: inserts after which the pixel's occlusion
#: bound was read again (a gap filled, or a rewritten row as deep as the bound); tiles_known: tiles
#: skipped because every primitive they list was already marked visible (their envelopes would add
#: nothing to the answer); pixels_known: pixels of tiles listing few primitives not yet marked
#: (``KNOWN_SHARE``) that none of those can reach, skipped for the same reason; items_behind_new:
#: list entries of such tiles not drawn, beyond the farthest point any of those reaches
#: (``_far_new``); cycles_cover / cycles_insert: the CPU cycles of the pairs' cover tests and of
#: their chords' insertions into the envelopes (bound reads included), estimated from one pair
#: in TIME_STRIDE (the chunk's running count of pairs), times TIME_STRIDE; footprint_seen:
#: primitives holding no sample that the footprint rule marked (``_footprint_seen``; two
#: tiles may both mark one); pixels_passed: pixels of a primitive's rows passed by without a
#: cover test, its nearest depth beyond their bound (a primitive beyond the bound of every
#: pixel of its box is passed by whole, before its set-up, and its box's pixels counted);
#: footprint_candidates: triangles the rule tested (per tile); cycles_footprint: the CPU
#: cycles of the rule's tests (its rays, part of cycles_tile); prims_passed: primitives so
#: passed by whole (per tile; a cluster counts once, and a cluster's triangle so passed once).
COUNTERS = ("pairs", "pieces", "items_processed", "items_culled", "final_pieces",
            "envelope_grows", "max_cap", "inserts", "insert_scan", "setups", "tiles", "cycles",
            "cycles_setup", "cycles_raster", "cycles_tile", "thread", "pairs_uncovered",
            "pairs_behind", "cluster_pairs", "cluster_pairs_uncovered", "insert_moved",
            "bound_scans", "tiles_known", "pixels_known", "items_behind_new", "cycles_cover",
            "cycles_insert", "footprint_seen", "pixels_passed", "footprint_candidates",
            "cycles_footprint", "prims_passed")
(C_PAIRS, C_PIECES, C_ITEMS, C_CULLED, C_FINAL, C_GROWS, C_MAX_CAP, C_INSERTS, C_INSERT_SCAN,
 C_SETUPS, C_TILES, C_CYCLES, C_CYCLES_SETUP, C_CYCLES_RASTER, C_CYCLES_TILE,
 C_THREAD, C_UNCOVERED, C_BEHIND, C_CLUSTER_PAIRS, C_CLUSTER_UNCOVERED,
 C_INSERT_MOVED, C_BOUND_SCANS, C_KNOWN, C_PX_KNOWN, C_BEHIND_NEW, C_CYCLES_COVER,
 C_CYCLES_INSERT, C_FOOTPRINT, C_PASSED, C_FP_CAND, C_CYCLES_FOOTPRINT,
 C_PRIMS_PASSED) = range(len(COUNTERS))


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


# ------------------------------------------------------------------------------ tile resolution
@njit(**_JIT_NO_NRT)
def _row_spans(hulls, p, ia, ib, ja, jb, r0, pad, span, ext):
    """Columns of primitive p to visit in tile rows [ia, ib] (clamped to [ja, jb]): where its
    hull (``hull.Hulls``) can hold a sample up to ``pad`` pixels off centre, or all of [ja, jb]
    when it has none. Writes span[i - r0] = (j0, j1), empty when j0 > j1; ``ext`` (TILE, 2)
    float64 is scratch."""
    # The hull's row and vertex count as int64 (the arrays hold int32 and int8), as
    # _front_spans passes them: _hull_spans and hull_rows compile once.
    h = np.int64(hulls.index[p])
    m = np.int64(hulls.count[h]) if h >= 0 else np.int64(0)
    _hull_spans(hulls.pts, h, m, ia, ib, ja, jb, r0, pad, span, ext)


@njit(**_JIT_INLINE_HELPER)
def _box_behind(bound, z, ia, ib, ja, jb, r0, cl0, tw):  # pragma: no cover - numba
    """Whether depth ``z`` lies at or beyond the occlusion bound of every pixel of tile rows
    [ia, ib], columns [ja, jb] (``bound`` per tile pixel, rows ``tw`` wide from row ``r0``,
    column ``cl0``): ``_raster`` would pass a primitive nearest at ``z`` by at each of them.
    Stops at the first pixel open before ``z``, so a primitive in view pays a read or two."""
    for i in range(ia, ib + 1):
        base = (i - r0) * tw - cl0
        for j in range(ja, jb + 1):
            if z < bound[base + j]:
                return False
    return True


@njit(**_JIT_INLINE_HELPER)
def _box_passed(bound, z, ia, ib, ja, jb, r0, cl0, tw, work):  # pragma: no cover - numba
    """``_box_behind``, and when it holds the box's pixels and one primitive counted as passed
    by whole (``work``)."""
    if not _box_behind(bound, z, ia, ib, ja, jb, r0, cl0, tw):
        return False
    work[C_PASSED] += (ib - ia + 1) * (jb - ja + 1)
    work[C_PRIMS_PASSED] += 1
    return True


@njit(**_JIT_INLINE_HELPER)
def _prim_behind(prim_box, pr, z, r0, r1, cl0, cl1, tw, bound, work):  # pragma: no cover
    """``_box_passed`` over primitive ``pr``'s pixel box within the tile (rows [r0, r1),
    columns [cl0, cl1)); False for a box that misses the tile."""
    ia = max(prim_box[pr, 0], r0)
    ib = min(prim_box[pr, 1], r1 - 1)
    ja = max(prim_box[pr, 2], cl0)
    jb = min(prim_box[pr, 3], cl1 - 1)
    return ia <= ib and ja <= jb and _box_passed(bound, z, ia, ib, ja, jb, r0, cl0, tw, work)


@njit(**_JIT_NO_NRT)
def _box_spans(ia, ib, ja, jb, r0, span):
    """span[i - r0] = (ja, jb) for the rows ia <= i <= ib: the whole box, no hull."""
    for i in range(ia, ib + 1):
        span[i - r0, 0] = ja
        span[i - r0, 1] = jb


@njit(**_JIT_NO_NRT)
def _hull_spans(pts, h, m, ia, ib, ja, jb, r0, pad, span, ext):
    """span[i - r0] = the columns of [ja, jb] in tile row i (ia <= i <= ib) whose sample, up to
    ``pad`` pixels off centre, can fall inside the stored hull ``pts[h, :m]`` (``hull_cols``,
    all rows in one pass: ``hull_rows``, its columns in ``ext``); all of [ja, jb] when m is 0
    (no hull)."""
    if m > 0:
        hull_rows(pts, h, m, ia, ib, pad, r0, ext)
    for i in range(ia, ib + 1):
        j0 = ja
        j1 = jb
        if m > 0:
            if ext[i - r0, 0] <= ext[i - r0, 1]:
                j0 = max(j0, int(ext[i - r0, 0]))
                j1 = min(j1, int(ext[i - r0, 1]))
            else:
                j0 = 1
                j1 = 0
        span[i - r0, 0] = j0
        span[i - r0, 1] = j1


@njit(**_JIT)
def _first_from(env, px, cnt, t):
    """Index of the first of pixel px's ``cnt`` envelope rows starting at or after ``t``."""
    lo = 0
    hi = cnt
    while lo < hi:
        mid = (lo + hi) >> 1
        if env[px, mid, 0] < t:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(**_JIT_NO_NRT)
def _front_spans(P, U, res, ia, ib, ja, jb, r0, pad, span, uv, scratch, pts, ext):
    """``_row_spans`` for a triangle whose six swept points (``_cam_corners``' P, P + U) are
    all in front of the near plane (``_front_box``): the projected triangle at every point of
    the segment lies in the convex hull of their projections, so per row only the columns
    that hull can reach are visited, not the whole box [ja, jb]. ``uv`` (6, 2), ``scratch``
    (14, 2) and ``pts`` (1, HMAX, 2) float32 are scratch (``hull.store_hull``), as is ``ext``
    (TILE, 2) (``hull.hull_rows``)."""
    for c in range(3):
        for e in range(2):
            d = -(P[c, 2] + e * U[c, 2])
            uv[2 * c + e, 0] = (P[c, 0] + e * U[c, 0]) / d
            uv[2 * c + e, 1] = (P[c, 1] + e * U[c, 1]) / d
    # Typed int64, not literals, as boxes and _row_spans pass theirs: one compile of
    # store_hull (and convex_hull) and of _hull_spans.
    k = np.int64(0)
    m = store_hull(uv, np.int64(6), res, scratch, pts, k)
    _hull_spans(pts, k, m, ia, ib, ja, jb, r0, pad, span, ext)


@njit(**_JIT_INLINE_HELPER)
def _cam_corners(R, verts0, verts1, faces, t, v0, dc, P, U, W):
    """Camera-space corners P of triangle t at t = 0 (relative to the eye), their velocities U
    relative to the moving eye, and the world corners W (for canonical edge order). One formula
    for every caller, so shared edges stay bit-identical. Inlined: it runs once per triangle
    and tile (a cluster's triangles in every tile its box reaches), and a call passes its
    nine arrays by value."""
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


@njit(**_JIT_NO_NRT)
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


@njit(**_JIT_INLINE_HELPER)
def _clip_half(lo, hi, a, b):
    """[lo, hi] intersected with {t : a + b t >= 0}."""
    if b > 0.0:
        lo = max(lo, -a / b)
    elif b < 0.0:
        hi = min(hi, -a / b)
    elif a < 0.0:
        hi = lo - 1.0
    return lo, hi


@njit(**_JIT_INLINE_HELPER)
def _tri_hit(P, U, t, x, y, near, wt, tq):  # pragma: no cover - numba
    """Whether the triangle with camera-space corners P + t U (3, 3) meets the ray (x, y, -1)
    from the eye at a depth in [near, wt) (the ray's own parameter is the depth; ``tq`` (1, 3,
    3) scratch for ``exact_grid.ray_triangle``)."""
    for c in range(3):
        for r in range(3):
            tq[0, c, r] = P[c, r] + t * U[c, r]
    d = ray_triangle(tq, 0, 0.0, 0.0, 0.0, x, y, -1.0)
    return near <= d < wt


@njit(**_JIT_INLINE_HELPER)
def _slab(o, d, inv, lo, hi, s0, s1):  # pragma: no cover - numba
    """[s0, s1] narrowed to the ray parameters at which o + s d (``inv`` = 1 / d) lies in the
    slab [lo, hi] of one axis; ``ok`` False once the interval is empty beyond a relative slack
    (a box flat on one axis has its two slabs at one depth, and a miss here would let a
    hidden triangle through; the reciprocal's rounding lies far inside it)."""
    if d == 0.0:
        return s0, s1, lo <= o <= hi
    u = (lo - o) * inv
    v = (hi - o) * inv
    if u > v:
        u, v = v, u
    s0 = max(s0, u)
    s1 = min(s1, v)
    return s0, s1, not s0 > s1 + 1e-9 * (abs(s0) + abs(s1)) + 1e-300


@njit(**_JIT_INLINE_HELPER)
def _world_ray(ox, oy, oz, dx, dy, dz):  # pragma: no cover - numba
    """The ray o + s d as the box tests read it: (ox, oy, oz, dx, dy, dz) and d's reciprocals
    (0 for a zero component, which ``_slab`` tests apart)."""
    return (ox, oy, oz, dx, dy, dz, 1.0 / dx if dx != 0.0 else 0.0,
            1.0 / dy if dy != 0.0 else 0.0, 1.0 / dz if dz != 0.0 else 0.0)


@njit(**_JIT_INLINE_HELPER)
def _ray_meets_bounds(ray, lx, ly, lz, hx, hy, hz, near, wt):  # pragma: no cover - numba
    """Whether the ray (``_world_ray``) may meet the box [lx, hx] x [ly, hy] x [lz, hz] at a
    parameter s in [near, wt) (``_slab`` per axis)."""
    ox, oy, oz, dx, dy, dz, ix, iy, iz = ray
    s0, s1, ok = _slab(ox, dx, ix, lx, hx, near, wt)
    if ok:
        s0, s1, ok = _slab(oy, dy, iy, ly, hy, s0, s1)
    if ok:
        s0, s1, ok = _slab(oz, dz, iz, lz, hz, s0, s1)
    return ok


@njit(**_JIT_INLINE_HELPER)
def _ray_meets_box(ray, lo, hi, c, near, wt):  # pragma: no cover - numba
    """Whether the ray (``_world_ray``), s in [near, wt), may meet box c of ``lo``, ``hi``
    (k, 3)."""
    return _ray_meets_bounds(ray, lo[c, 0], lo[c, 1], lo[c, 2], hi[c, 0], hi[c, 1], hi[c, 2],
                             near, wt)


@njit(**_JIT_INLINE_HELPER)
def _ray_meets_tri_box(ray, verts0, verts1, faces, tri, moves, near,
                       wt):  # pragma: no cover - numba
    """Whether the ray (``_world_ray``), s in [near, wt), may meet the box of triangle ``tri``
    over both of its positions (the first alone when ``moves`` is False: the two are the
    same): a point of the triangle at any time lies in it, so a ray that misses it misses the
    triangle, and the exact test (``_tri_hit``, a rotation and a ray-triangle test) is
    spared. A ray meets few of the triangles whose cluster's box it meets."""
    a0 = faces[tri, 0]
    a1 = faces[tri, 1]
    a2 = faces[tri, 2]
    lx, hx = _tri_extent(verts0, verts1, a0, a1, a2, 0, moves)
    ly, hy = _tri_extent(verts0, verts1, a0, a1, a2, 1, moves)
    lz, hz = _tri_extent(verts0, verts1, a0, a1, a2, 2, moves)
    return _ray_meets_bounds(ray, lx, ly, lz, hx, hy, hz, near, wt)


@njit(**_JIT_INLINE_HELPER)
def _tri_extent(verts0, verts1, a0, a1, a2, a, moves):  # pragma: no cover - numba
    """(min, max) along axis a of corners a0, a1, a2 in ``verts0`` and, if it ``moves``,
    ``verts1``."""
    lo = min(verts0[a0, a], min(verts0[a1, a], verts0[a2, a]))
    hi = max(verts0[a0, a], max(verts0[a1, a], verts0[a2, a]))
    if moves:
        lo = min(lo, min(verts1[a0, a], min(verts1[a1, a], verts1[a2, a])))
        hi = max(hi, max(verts1[a0, a], max(verts1[a1, a], verts1[a2, a])))
    return lo, hi


@njit(**_JIT_NO_NRT)
def _sphere_hit(sp, x, y, t, wt, geom, frame):  # pragma: no cover - numba
    """Whether sphere ``sp`` meets the ray (x, y, -1) of the eye at time t at a depth in
    [near, wt) (``_ray_blocked``'s arguments)."""
    verts0, verts1, faces, moving, cl_start, cl_tris, c0, c1, radii, n_tri, cl_lo, cl_hi = geom
    R, dc, v0, dvec, near = frame
    # Centre relative to the eye at t, in the face's frame; the ray's depth is its own
    # parameter s (r = (x, y, -1)).
    bx = 0.0
    cc = 0.0
    for r in range(3):
        w = 0.0
        for c in range(3):
            w += R[r, c] * (c0[sp, c] + t * (c1[sp, c] - c0[sp, c]) - v0[c] - t * dvec[c])
        rr = x if r == 0 else (y if r == 1 else -1.0)
        bx += rr * w
        cc += w * w
    a = x * x + y * y + 1.0
    disc = bx * bx - a * (cc - radii[sp] * radii[sp])
    if disc >= 0.0:
        sq = np.sqrt(disc)
        s1 = (bx - sq) / a
        s2 = (bx + sq) / a
        if s1 < wt and s2 >= near:
            return True
    return False


@njit(**_JIT_NO_NRT)
def _ray_blocked(x, y, t, wt, pi, pj, pid, i0, i1, tile_items, rows, geom, frame,
                 sc3):  # pragma: no cover - numba
    """Whether a primitive of the tile's list entries [i0, i1) other than ``pid`` meets the
    ray (x, y, -1) of the eye at time t at a depth in [near, wt); the ray lies in the square
    of pixel (pi, pj). ``rows``: (prim_src, prim_z, prim_zkey, prim_flag, prim_box);
    ``geom``: ``groups.GeometryArrays``; ``frame``: (R, dc, v0, dvec, near); ``sc3``: (P, U,
    W) (3, 3) and (1, 3, 3) scratch and ``last`` (2,) int64, the primitive that blocked the
    last ray (kind 1 triangle, 2 sphere, 0 none; its id), tried first: rays through the same
    sub-pixel triangle are nearly always blocked by the same thing, and any primitive that
    meets the ray blocks it, listed or not. The list runs front to back by key, so the walk
    stops at the first key at or beyond wt; a primitive whose pixel box, grown by a pixel,
    misses (pi, pj) cannot reach a point of that pixel's square."""
    prim_src, prim_z, prim_zkey, prim_flag, prim_box = rows
    verts0, verts1, faces, moving, cl_start, cl_tris, c0, c1, radii, n_tri, cl_lo, cl_hi = geom
    R, dc, v0, dvec, near = frame
    P, U, W, tq, last = sc3
    if last[0] == 1 and last[1] != pid:
        _cam_corners(R, verts0, verts1, faces, last[1], v0, dc, P, U, W)
        if _tri_hit(P, U, t, x, y, near, wt, tq):
            return True
    elif last[0] == 2 and _sphere_hit(last[1], x, y, t, wt, geom, frame):
        return True
    # The ray in world space: from the eye at t, along R^T (x, y, -1) (depth per unit).
    ox = v0[0] + t * dvec[0]
    oy = v0[1] + t * dvec[1]
    oz = v0[2] + t * dvec[2]
    dx = R[0, 0] * x + R[1, 0] * y - R[2, 0]
    dy = R[0, 1] * x + R[1, 1] * y - R[2, 1]
    dz = R[0, 2] * x + R[1, 2] * y - R[2, 2]
    ray = _world_ray(ox, oy, oz, dx, dy, dz)
    for it in range(i0, i1):
        pr = tile_items[it]
        if prim_zkey[pr] >= wt:
            break
        if (prim_z[pr] >= wt or pi < prim_box[pr, 0] - 1 or pi > prim_box[pr, 1] + 1
                or pj < prim_box[pr, 2] - 1 or pj > prim_box[pr, 3] + 1):
            continue
        src = np.int64(prim_src[pr])
        flag = prim_flag[pr]
        if flag & FLAG_CLUSTER:
            if not _ray_meets_box(ray, cl_lo, cl_hi, src, near, wt):
                continue
            for k in range(cl_start[src], cl_start[src + 1]):
                tri = cl_tris[k]
                if tri == pid or not _ray_meets_tri_box(ray, verts0, verts1, faces, tri,
                                                        moving[tri], near, wt):
                    continue
                _cam_corners(R, verts0, verts1, faces, tri, v0, dc, P, U, W)
                if _tri_hit(P, U, t, x, y, near, wt, tq):
                    last[0] = 1
                    last[1] = tri
                    return True
        elif flag & FLAG_SPHERE:
            if _sphere_hit(src - n_tri, x, y, t, wt, geom, frame):
                last[0] = 2
                last[1] = src - n_tri
                return True
        elif src != pid:
            _cam_corners(R, verts0, verts1, faces, src, v0, dc, P, U, W)
            if _tri_hit(P, U, t, x, y, near, wt, tq):
                last[0] = 1
                last[1] = src
                return True
    return False


@njit(**_JIT_NO_NRT)
def _footprint_seen(pix, env, ia, ib, ja, jb, pid, P, i0, i1, tile_items, rows, geom, frame,
                    sc3, corners):  # pragma: no cover - numba
    """Whether a static triangle ``pid`` that holds no pixel sample along the segment
    (camera-space corners ``P`` (3, 3) from the eye at t = 0) is seen by an extra sample at
    its own centroid, or, with ``corners``, near one of its corners (``_point_seen``: for
    each pixel of the tile's rows [ia, ib], columns [ja, jb], its box, that the point's image
    crosses, a ray through the point from the eye at the middle of the crossing). A found
    sample is an eye on the segment and a direction that see the triangle: the answer stays
    exact, at the pixel samples and these. Tiles listing more than ``FOOTPRINT_MAX_ITEMS``
    primitives collect no such triangles (the caller's choice). The corners are tried when
    the centroid's rays were cast and blocked, or it crossed none of the box's pixels (the
    triangle straddles tiles), not when the pre-test passed over every pixel it crossed.

    Why: a triangle far smaller than a pixel slides between the samples of a whole sweep and
    no sample sees it, though eyes on the segment do (a roof's detail hundreds of metres
    away); a sample placed on it decides. Its centroid may lie behind a nearer edge that
    leaves a corner in view (a sliver seen past a roof line)."""
    R, dc, v0, dvec, near = frame
    wn = min(-P[0, 2], min(-P[1, 2], -P[2, 2]))
    cx = (P[0, 0] + P[1, 0] + P[2, 0]) / 3.0
    cy = (P[0, 1] + P[1, 1] + P[2, 1]) / 3.0
    w0 = -(P[0, 2] + P[1, 2] + P[2, 2]) / 3.0
    for k in range(4 if corners else 1):
        if k == 0:
            x, y, w = cx, cy, w0
        else:
            # Inside the triangle, a tenth of the way from the corner to the centroid: a ray
            # through the corner itself would graze the neighbours sharing it.
            x = P[k - 1, 0] + CORNER_INSET * (cx - P[k - 1, 0])
            y = P[k - 1, 1] + CORNER_INSET * (cy - P[k - 1, 1])
            w = -P[k - 1, 2] + CORNER_INSET * (w0 + P[k - 1, 2])
        got = _point_seen(pix, env, ia, ib, ja, jb, pid, x, y, w, wn, i0, i1, tile_items, rows,
                          geom, frame, sc3)
        if got == SEEN:
            return True
        if k == 0 and got == SKIPPED:
            # Every pixel the centroid crossed shows something nearer all through: the
            # corners are not tried (in clutter they cost more than they find).
            break
    return False


@njit(**_JIT_NO_NRT)
def _point_seen(pix, env, ia, ib, ja, jb, pid, cx, cy, w0, wn, i0, i1, tile_items, rows,
                geom, frame, sc3):  # pragma: no cover - numba
    """Whether a point of triangle ``pid`` at (cx, cy, -w0) in the camera frame of the eye at
    t = 0 (its nearest corner at depth ``wn``) is seen by a ray through it from the eye at
    the middle of its crossing of some pixel of rows [ia, ib], columns [ja, jb], whose own
    envelope (``env``) does not stand nearer than the triangle all through that crossing
    (``envelope.hides_over``, a pre-test that spares the cast), meeting nothing of the tile's
    list (``_ray_blocked``) before it. The point moves by -t dc (depth w0 + t wd). Returns
    ``SEEN``, ``BLOCKED`` (rays cast, all blocked), ``SKIPPED`` (crossed pixels, every one
    passed over by the pre-test) or ``OUTSIDE`` (crossed none of them)."""
    r0, cl0, tw, npx, step, cnt, bound, jx, jy = pix
    R, dc, v0, dvec, near = frame
    wd = dc[2]
    if min(w0, w0 + wd) < near:
        return SKIPPED
    got = OUTSIDE
    for i in range(ia, ib + 1):
        ytop = 1.0 - i * step
        ybot = ytop - step
        for j in range(ja, jb + 1):
            xl = j * step - 1.0
            xr = xl + step
            # The image is inside the pixel's square while four linear forms in t are >= 0
            # (w > 0 on the segment).
            lo, hi = _clip_half(0.0, 1.0, cx - xl * w0, -dc[0] - xl * wd)
            lo, hi = _clip_half(lo, hi, xr * w0 - cx, xr * wd + dc[0])
            lo, hi = _clip_half(lo, hi, cy - ybot * w0, -dc[1] - ybot * wd)
            lo, hi = _clip_half(lo, hi, ytop * w0 - cy, ytop * wd + dc[1])
            if not hi >= lo:
                continue
            # The pixel's own sample sees something nearer than the triangle's nearest corner
            # all through the crossing: no ray is cast. The point could still show there;
            # skipped for the time a cast costs (it walks the tile's list).
            if hides_over(env, (i - r0) * tw + (j - cl0), cnt, lo, hi, wn, wd):
                got = max(got, SKIPPED)
                continue
            # One time per pixel crossed: more per crossing found no more on the Lyon tile.
            t = 0.5 * (lo + hi)
            w = w0 + t * wd
            if not _ray_blocked((cx - t * dc[0]) / w, (cy - t * dc[1]) / w, t, w, i, j, pid,
                                i0, i1, tile_items, rows, geom, frame, sc3):
                return SEEN
            got = BLOCKED
    return got


@njit(**_JIT_NO_NRT)
def _raster(kind, pid, slow, zpr, ia, ib, span, coef, pix, near, knots, env, eid, T, tid,
            sc, work):
    """Composite one set-up primitive (kind 0 static triangle, 1 moving triangle, 2 sphere,
    its set-up ``coef``, nearest depth ``zpr``) into the envelopes (``env``, ``eid``) of the
    pixels of rows [ia, ib] of the current tile (``groups.TilePixels``), row i's columns
    [span[i - r0, 0], span[i - r0, 1]] (``_row_spans``), sampled at their centres moved by
    (jx, jy)[pixel] NDC units (``sample_offset``). ``T``, ``tid`` (insertion) and ``sc``
    (``groups.PieceScratch``) are scratch. Adds its work to ``work`` (``COUNTERS``
    columns). Returns (pixels newly bounded, full): ``full`` when an envelope ran out of
    room, the primitive drawn up to the pixel and piece kept in ``sc.at``; the caller grows
    the storage (``_grown``) and calls again, which resumes there (so no chord is inserted
    twice). The arrays are never rebound here, so numba counts no references at each
    insertion."""
    r0, cl0, tw, npx, step, cnt, bound, jx, jy = pix
    pt0, pt1, pz0, pz1, brk, stk, at = sc
    # Resuming a draw cut short: skip what it already drew.
    ri = -1
    rj = 0
    rq = 0
    if at[3] == 1:
        ri = at[0]
        rj = at[1]
        rq = at[2]
        at[3] = 0
    closed = 0
    pairs = 0
    passed = 0
    uncovered = 0
    behind = 0
    moved = 0
    pieces = 0
    scan = 0
    ins = 0
    rescans = 0
    full = False
    cyc_cover = 0
    cyc_insert = 0
    pairs_before = work[C_PAIRS]
    for i in range(max(ia, ri), ib + 1):
        yc = 1.0 - (i + 0.5) * step
        j0 = span[i - r0, 0]
        if i == ri:
            j0 = rj
        for j in range(j0, span[i - r0, 1] + 1):
            q0 = rq if (i == ri and j == rj) else 0
            px = (i - r0) * tw + (j - cl0)
            bpx = bound[px]
            if zpr >= bpx:
                passed += 1
                continue
            x = (j + 0.5) * step - 1.0 + jx[px]
            y = yc + jy[px]
            timed = (pairs_before + pairs) % TIME_STRIDE == 0
            pairs += 1
            cc = _cycles() if timed else 0
            if kind == 0:
                ok, ts, tf, zs, zf = static_cover(coef, x, y, near, slow)
                if timed:
                    cyc_cover += _cycles() - cc
                if not ok:
                    uncovered += 1
                    continue
                if min(zs, zf) >= bpx:
                    behind += 1
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
            if timed:
                cc1 = _cycles()
                if kind != 0:
                    cyc_cover += cc1 - cc
                cc = cc1
            if npc == 0:
                uncovered += 1
            for q in range(q0, npc):
                if min(pz0[q], pz1[q]) >= bound[px]:
                    continue
                pieces += 1
                # What a linear insertion would read (bisection reads its log).
                scan += cnt[px]
                nn, changed, rebound = envelope_insert(env, eid, px, cnt[px], pt0[q], pt1[q],
                                                       pz0[q], pz1[q], pid, T, tid, bound[px])
                if nn < 0:
                    # Deep envelope: the caller grows the storage and resumes here.
                    at[0] = i
                    at[1] = j
                    at[2] = q
                    at[3] = 1
                    full = True
                    break
                if changed:
                    ins += 1
                    if nn != cnt[px]:
                        moved += nn - _first_from(env, px, nn, pt1[q])
                    cnt[px] = nn
                    if rebound:
                        rescans += 1
                        zb = pixel_bound(env, px, nn)
                        if zb < np.inf:
                            if bound[px] == np.inf:
                                closed += 1
                            bound[px] = zb
            if timed:
                cyc_insert += _cycles() - cc
            if full:
                break
        if full:
            break
    work[C_CYCLES_COVER] += TIME_STRIDE * cyc_cover
    work[C_CYCLES_INSERT] += TIME_STRIDE * cyc_insert
    work[C_PAIRS] += pairs
    work[C_PASSED] += passed
    work[C_UNCOVERED] += uncovered
    work[C_BEHIND] += behind
    work[C_INSERT_MOVED] += moved
    work[C_PIECES] += pieces
    work[C_INSERTS] += ins
    work[C_INSERT_SCAN] += scan
    work[C_BOUND_SCANS] += rescans
    return closed, full


@njit(**_JIT)
def _grown(env, eid, T, tid, cnt, npx, work):
    """The envelope storage grown x4 (``_grow``) and True, or the same and False at MAX_CAP."""
    if 4 * env.shape[1] > MAX_CAP:
        return env, eid, T, tid, False
    env2, eid2, T2, tid2 = _grow(env, eid, cnt, npx, 4 * env.shape[1])
    work[C_GROWS] += 1
    return env2, eid2, T2, tid2, True


def _resolve(job: TileWork, prims: PrimRows, geom: GeometryArrays, sweep: Sweep,
             out: Results) -> None:
    """Envelopes of the tiles of ``job`` (``groups.TileWork``) over the rows ``prims``
    (``groups.PrimRows``) of the geometry ``geom`` (``groups.GeometryArrays``) seen by the cube
    moving along ``sweep`` (``groups.Sweep``); marks visible primitives in ``out``
    (``groups.Results``; global ids: triangles, then n_tri + sphere). A tile whose envelopes
    outgrow MAX_CAP sets ``out.overflow``, marks nothing. Tiles are strided over chunks so
    that busy screen regions spread over the threads. A primitive with a hull
    (``hull.Hulls``) is scanned row by row over the columns its hull can reach (Alg. 1 line
    6), the others over their whole box.

    ``n_workers`` (the thread count) workers each take the next chunk as they finish one
    (``take_next``): tiles differ in work by orders of magnitude, and a static split of the
    chunks left one thread 24-34 % busier than the mean on the city1m cells. A chunk's tiles
    are fixed, so the result does not depend on which thread runs it. The workers are
    threads, not a prange loop: compiled into a parallel loop, the chunk's kernel was compiled
    twice (``visibility.shares``)."""
    nxt = np.zeros(1, dtype=np.int64)
    run_shares(_resolve_worker, max(1, min(job.n_chunks, job.n_workers)), job, prims, geom,
               sweep, out, nxt)


@njit(**_JIT)
def _resolve_worker(job, prims, geom, sweep, out, nxt, worker,
                    n_workers):  # pragma: no cover - numba
    """Worker ``worker`` of ``_resolve``'s ``n_workers``: the next chunk (``nxt``, shared by
    the workers) until none is left."""
    while True:
        ch = take_next(nxt)
        if ch >= job.n_chunks:
            break
        _resolve_chunk(ch, worker, job, prims, geom, sweep, out)


@njit(**_JIT)
def _count_new(i0, i1, tile_items, prim_src, prim_flag, cl_start, cl_tris, visible):
    """How many of tile list entries [i0, i1) hold a primitive not yet marked visible (a
    cluster: any of its triangles)."""
    n = 0
    for it in range(i0, i1):
        pr = tile_items[it]
        src = prim_src[pr]
        if prim_flag[pr] & FLAG_CLUSTER:
            for k in range(cl_start[src], cl_start[src + 1]):
                if not visible[cl_tris[k]]:
                    n += 1
                    break
        elif not visible[src]:
            n += 1
    return n


@njit(**_JIT)
def _far_new(i0, i1, tile_items, prim_src, prim_flag, cl_start, cl_tris, visible, R, dc, geom,
             v0, P, U, W):
    """Greatest depth that a primitive of tile list entries [i0, i1) not yet marked visible
    (a cluster: its triangles not yet marked) reaches anywhere along the segment: the depth of
    a moving point is linear in t, so a triangle's greatest depth is at a corner at t = 0 or
    1; a sphere's, its centre's plus its radius. A primitive that stays beyond it can hide
    none of them, nor change what they own of an envelope."""
    verts0, verts1, faces, _, _, _, c0, c1, radii, n_tri, _, _ = geom
    far = -np.inf
    for it in range(i0, i1):
        pr = tile_items[it]
        # int64 (prim_src is int32), as a cluster's triangle ids: _cam_corners compiles once.
        src = np.int64(prim_src[pr])
        flag = prim_flag[pr]
        if flag & FLAG_CLUSTER:
            for k in range(cl_start[src], cl_start[src + 1]):
                t = cl_tris[k]
                if not visible[t]:
                    _cam_corners(R, verts0, verts1, faces, t, v0, dc, P, U, W)
                    for c in range(3):
                        far = max(far, -P[c, 2], -(P[c, 2] + U[c, 2]))
        elif visible[src]:
            continue
        elif flag & FLAG_SPHERE:
            s = src - n_tri
            z0 = 0.0
            z1 = -dc[2]
            for r in range(3):
                z0 += R[2, r] * (c0[s, r] - v0[r])
                z1 += R[2, r] * (c1[s, r] - v0[r])
            far = max(far, -z0 + radii[s], -z1 + radii[s])
        else:
            _cam_corners(R, verts0, verts1, faces, src, v0, dc, P, U, W)
            for c in range(3):
                far = max(far, -P[c, 2], -(P[c, 2] + U[c, 2]))
    return far


@njit(**_JIT)
def _fp_push(fp, n, pid, ia, ib, ja, jb, P):
    """Row n of ``fp`` (grown x2 when full; returned) := a triangle the footprint rule tests
    once its tile's envelopes are whole: (id, ia, ib, ja, jb, corners P)."""
    if n >= fp.shape[0]:
        grown = np.empty((2 * fp.shape[0], fp.shape[1]))
        grown[:n] = fp[:n]
        fp = grown
    fp[n, 0] = pid
    fp[n, 1] = ia
    fp[n, 2] = ib
    fp[n, 3] = ja
    fp[n, 4] = jb
    for r in range(3):
        for c in range(3):
            fp[n, 5 + 3 * r + c] = P[r, c]
    return fp


@njit(**_JIT)
def _chunk_scratch(npx_max, maxp):
    """The scratch arrays of one chunk of ``_resolve`` (``groups.ChunkScratch``; owners,
    which ``_resolve_chunk`` borrows)."""
    return ChunkScratch(
        np.zeros(npx_max, dtype=np.int64), np.empty(npx_max), np.zeros(npx_max),
        np.zeros(npx_max), np.empty(40), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)),
        np.empty((3, 3)), np.empty(3), np.empty(3), np.empty(3), np.empty(4, dtype=np.int64),
        np.empty((TILE, 2), dtype=np.int64), np.empty((6, 2)), np.empty((14, 2)),
        np.empty((1, HMAX, 2), dtype=np.float32), np.empty((TILE, 2)),
        PieceScratch(np.empty(maxp), np.empty(maxp), np.empty(maxp), np.empty(maxp),
                     np.empty(48), np.empty((64, 4)), np.zeros(4, dtype=np.int64)))


@njit(**_JIT)
def _resolve_chunk(ch, worker, job, prims, geom, sweep, out):  # pragma: no cover - numba
    """Chunk ``ch`` of ``_resolve``, run by worker ``worker``."""
    # Everything the per-item and per-pixel helpers take is borrowed (``visibility.borrow``):
    # numba counts no references for it at each call, which on shared arrays the two threads
    # would fight over. The owners: the arguments, and the local ones kept alive at the end.
    tiles, n_chunks, _, tile_start, tile_items = job
    tiles = borrow(tiles)
    tile_start = borrow(tile_start)
    tile_items = borrow(tile_items)
    prim_src, prim_box, prim_z, prim_zkey, prim_flag, _, h_index, h_pts, h_count = prims
    prim_src = borrow(prim_src)
    prim_box = borrow(prim_box)
    prim_z = borrow(prim_z)
    prim_zkey = borrow(prim_zkey)
    prim_flag = borrow(prim_flag)
    hulls = Hulls(borrow(h_index), borrow(h_pts), borrow(h_count))
    verts0, verts1, faces, moving, cl_start, cl_tris, c0, c1, radii, n_tri, cl_lo, cl_hi = geom
    verts0 = borrow(verts0)
    verts1 = borrow(verts1)
    faces = borrow(faces)
    moving = borrow(moving)
    cl_start = borrow(cl_start)
    cl_tris = borrow(cl_tris)
    c0 = borrow(c0)
    c1 = borrow(c1)
    radii = borrow(radii)
    cl_lo = borrow(cl_lo)
    cl_hi = borrow(cl_hi)
    geom = (verts0, verts1, faces, moving, cl_start, cl_tris, c0, c1, radii, n_tri, cl_lo, cl_hi)
    v0, dvec, rots, res, near, knots, jitter, seed, cap, footprint, pad = sweep
    v0 = borrow(v0)
    dvec = borrow(dvec)
    rots = borrow(rots)
    visible, overflow, counters, witness = out
    visible = borrow(visible)
    overflow = borrow(overflow)
    witness = borrow(witness)
    ntx = (res + TILE - 1) // TILE
    per_face = ntx * ntx
    npx_max = TILE * TILE
    step = 2.0 / res
    maxp = 8 * (knots + 2) + 8
    want_witness = witness.shape[1] == visible.shape[0]
    # The envelopes' storage, grown in place (``_grow``): owners and borrowed views.
    env_o = np.empty((npx_max, cap, 4))
    eid_o = np.empty((npx_max, cap), dtype=np.int32)
    T_o = np.empty((2 * cap + 8, 4))  # insertion scratch
    tid_o = np.empty(2 * cap + 8, dtype=np.int32)
    env, eid, T, tid = borrow((env_o, eid_o, T_o, tid_o))
    own = _chunk_scratch(npx_max, maxp)
    # c_uv, c_scratch, c_pts: a cluster triangle's swept hull (``_front_spans``).
    (cnt, bound, jx, jy, coef, P, U, W, R, dc, cen, vel, bx, span, c_uv, c_scratch, c_pts,
     ext, sc) = borrow(own)
    # Triangles for the footprint rule (``_fp_push``), tested when their tile is done.
    fp_o = np.empty((64, 14))
    pf_o = np.empty((3, 3))
    pf = borrow(pf_o)
    tq_o = np.empty((1, 3, 3))
    tq = borrow(tq_o)
    last_o = np.zeros(2, dtype=np.int64)  # what blocked the rule's last ray
    last = borrow(last_o)
    nfp = np.int64(0)  # not a literal 0: ``_fp_push`` is compiled once
    fp_rows = (prim_src, prim_z, prim_zkey, prim_flag, prim_box)
    # A private row of counters, copied out at the end.
    work_o = np.zeros(counters.shape[1], dtype=np.int64)
    work = borrow(work_o)
    for k in range(counters.shape[1]):
        work[k] = counters[ch, k]
    cyc_setup = 0
    cyc_raster = 0
    cyc_tile = 0
    cyc_start = _cycles()
    for qi in range(ch, tiles.shape[0], n_chunks):
        work[C_TILES] += 1
        ct0 = _cycles()
        tile = tiles[qi]
        n_new = 0
        if not want_witness:
            n_new = _count_new(tile_start[tile], tile_start[tile + 1], tile_items, prim_src,
                               prim_flag, cl_start, cl_tris, visible)
            if n_new == 0:
                # The tile can only mark primitives already marked (by an earlier segment, face
                # or tile): its envelopes would change nothing in the answer.
                work[C_KNOWN] += 1
                cyc_tile += _cycles() - ct0
                continue
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
        # The footprint rule's rays walk the tile's list: not in clutter, where it is long.
        fp_tile = (footprint != FOOTPRINT_OFF
                   and tile_start[tile + 1] - tile_start[tile] <= FOOTPRINT_MAX_ITEMS)
        # With corners, a triangle may also pass closed pixels by, so long as it meets an open
        # one, and its corners are tried.
        fp_corners = footprint == FOOTPRINT_CORNERS
        if 0 < n_new and KNOWN_SHARE * n_new <= tile_start[tile + 1] - tile_start[tile]:
            # Few primitives not yet marked: only the pixels they can reach are resolved, the
            # others (bound -inf: every primitive passes them by) would mark nothing new.
            for p in range(npx):
                bound[p] = -np.inf
            for it in range(tile_start[tile], tile_start[tile + 1]):
                pr = tile_items[it]
                if _count_new(it, it + 1, tile_items, prim_src, prim_flag, cl_start, cl_tris,
                              visible) == 0:
                    continue
                ia = max(prim_box[pr, 0], r0)
                ib = min(prim_box[pr, 1], r1 - 1)
                ja = max(prim_box[pr, 2], cl0)
                jb = min(prim_box[pr, 3], cl1 - 1)
                if fp_tile and (ib - ia + 1) * (jb - ja + 1) <= SMALL_BOX:
                    # The footprint rule may read any pixel of a small box.
                    _box_spans(ia, ib, ja, jb, r0, span)
                else:
                    _row_spans(hulls, pr, ia, ib, ja, jb, r0, pad, span, ext)
                for i in range(ia, ib + 1):
                    for j in range(span[i - r0, 0], span[i - r0, 1] + 1):
                        bound[(i - r0) * tw + (j - cl0)] = np.inf
            open_px = 0
            for p in range(npx):
                if bound[p] == np.inf:
                    open_px += 1
            work[C_PX_KNOWN] += npx - open_px
        tbound = np.inf
        since = 0
        nfp = np.int64(0)
        for r in range(3):
            for c in range(3):
                R[r, c] = rots[f, r, c]
        for r in range(3):
            dc[r] = R[r, 0] * dvec[0] + R[r, 1] * dvec[1] + R[r, 2] * dvec[2]
        # With few primitives still to mark, what lies beyond all of them is not drawn.
        zlim = np.inf
        if 0 < n_new and KNOWN_SHARE * n_new <= tile_start[tile + 1] - tile_start[tile]:
            zlim = _far_new(tile_start[tile], tile_start[tile + 1], tile_items, prim_src,
                            prim_flag, cl_start, cl_tris, visible, R, dc, geom, v0, P, U, W)
        ovf = False
        pix = TilePixels(r0, cl0, tw, npx, step, cnt, bound, jx, jy)
        cyc_tile += _cycles() - ct0
        end = tile_start[tile + 1]
        for it in range(tile_start[tile], end):
            pr = tile_items[it]
            if prim_zkey[pr] >= tbound:
                work[C_CULLED] += end - it
                break
            if prim_zkey[pr] > zlim:
                work[C_BEHIND_NEW] += end - it
                break
            if prim_z[pr] >= tbound:
                work[C_CULLED] += 1
                continue
            if prim_z[pr] > zlim:
                work[C_BEHIND_NEW] += 1
                continue
            work[C_ITEMS] += 1
            # int64 (prim_src is int32), as a cluster's triangle ids: _raster and _cam_corners
            # compile once.
            src = np.int64(prim_src[pr])
            flag = prim_flag[pr]
            slow = (flag & FLAG_SLOW) != 0
            closed = 0
            cs0 = _cycles()
            if flag & FLAG_CLUSTER:
                # Closed nearer at every pixel of its box (a cluster's box holds its
                # triangles' boxes, its depth is at most theirs): no triangle is set up.
                behind = _prim_behind(prim_box, pr, prim_z[pr], r0, r1, cl0, cl1, tw, bound,
                                      work)
                stop = cl_start[src] if behind else cl_start[src + 1]
                for k in range(cl_start[src], stop):
                    t = cl_tris[k]
                    _cam_corners(R, verts0, verts1, faces, t, v0, dc, P, U, W)
                    ok, zt = _front_box(P, U, res, bx, pad)
                    if not ok or zt >= tbound:
                        continue
                    ia = max(bx[0], r0)
                    ib = min(bx[1], r1 - 1)
                    ja = max(bx[2], cl0)
                    jb = min(bx[3], cl1 - 1)
                    if ia > ib or ja > jb:
                        continue
                    if _box_passed(bound, zt, ia, ib, ja, jb, r0, cl0, tw, work):
                        continue  # closed nearer at every pixel of its box: no set-up, no draw
                    if (ib - ia + 1) * (jb - ja + 1) <= SMALL_BOX:
                        _box_spans(ia, ib, ja, jb, r0, span)
                    else:
                        _front_spans(P, U, res, ia, ib, ja, jb, r0, pad, span, c_uv,
                                     c_scratch, c_pts, ext)
                    if moving[t]:
                        moving_setup(P, U, W, coef)
                        kind = 1
                    else:
                        static_setup(P, W, dc, coef)
                        kind = 0
                    work[C_SETUPS] += 1
                    cs1 = _cycles()
                    p0 = work[C_PAIRS]
                    u0 = work[C_UNCOVERED]
                    s0 = work[C_PASSED]
                    nc = 0
                    while True:
                        # np.bool_, not a literal False: a literal compiles another
                        # specialization of _raster and of the cover tests it calls.
                        more, full = _raster(kind, t, np.bool_(False), zt, ia, ib, span, coef,
                                             pix, near, knots, env, eid, T, tid, sc, work)
                        nc += more
                        if not full:
                            break
                        # An envelope ran out of room: grow the storage, resume the draw.
                        env_o, eid_o, T_o, tid_o, grown = _grown(env_o, eid_o, T_o, tid_o,
                                                                 cnt, npx, work)
                        if not grown:
                            ovf = True
                            break
                        env, eid, T, tid = borrow((env_o, eid_o, T_o, tid_o))
                    cyc_raster += _cycles() - cs1
                    work[C_CLUSTER_PAIRS] += work[C_PAIRS] - p0
                    work[C_CLUSTER_UNCOVERED] += work[C_UNCOVERED] - u0
                    if (fp_tile and not ovf and not visible[t]
                            and (bx[1] - bx[0] + 1) * (bx[3] - bx[2] + 1) <= SMALL_BOX
                            and work[C_PAIRS] - p0 == work[C_UNCOVERED] - u0
                            and (work[C_PASSED] == s0 or (fp_corners and work[C_PAIRS] > p0))
                            and not moving[t]):
                        fp_o = _fp_push(fp_o, nfp, t, ia, ib, ja, jb, P)
                        nfp += 1
                    closed += nc
                    if ovf:
                        break
            elif _prim_behind(prim_box, pr, prim_z[pr], r0, r1, cl0, cl1, tw, bound, work):
                pass  # closed nearer at every pixel of its box: no set-up, no draw
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
                ia = max(prim_box[pr, 0], r0)
                ib = min(prim_box[pr, 1], r1 - 1)
                ja = max(prim_box[pr, 2], cl0)
                jb = min(prim_box[pr, 3], cl1 - 1)
                if (ib - ia + 1) * (jb - ja + 1) <= SMALL_BOX:
                    _box_spans(ia, ib, ja, jb, r0, span)
                else:
                    _row_spans(hulls, pr, ia, ib, ja, jb, r0, pad, span, ext)
                work[C_SETUPS] += 1
                cs1 = _cycles()
                p0 = work[C_PAIRS]
                u0 = work[C_UNCOVERED]
                s0 = work[C_PASSED]
                while True:
                    more, full = _raster(kind, src, slow, prim_z[pr], ia, ib, span, coef, pix,
                                         near, knots, env, eid, T, tid, sc, work)
                    closed += more
                    if not full:
                        break
                    env_o, eid_o, T_o, tid_o, grown = _grown(env_o, eid_o, T_o, tid_o, cnt,
                                                             npx, work)
                    if not grown:
                        ovf = True
                        break
                    env, eid, T, tid = borrow((env_o, eid_o, T_o, tid_o))
                cyc_raster += _cycles() - cs1
                if (fp_tile and not ovf and not visible[src]
                        and (prim_box[pr, 1] - prim_box[pr, 0] + 1)
                        * (prim_box[pr, 3] - prim_box[pr, 2] + 1) <= SMALL_BOX
                        and work[C_PAIRS] - p0 == work[C_UNCOVERED] - u0
                        and (work[C_PASSED] == s0 or (fp_corners and work[C_PAIRS] > p0))
                        and kind == 0):
                    fp_o = _fp_push(fp_o, nfp, src, ia, ib, ja, jb, P)
                    nfp += 1
            cyc_setup += _cycles() - cs0
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
            sc.at[3] = 0  # the draw cut short is not resumed
            continue
        ct0 = _cycles()
        # The envelopes are whole now: earlier, a triangle drawn before what hides it (a
        # cluster's triangles come in its own order) would find its pixels open.
        work[C_FP_CAND] += nfp
        for c in range(nfp):
            pid = np.int64(fp_o[c, 0])
            if visible[pid]:
                continue
            for r in range(3):
                for k in range(3):
                    pf[r, k] = fp_o[c, 5 + 3 * r + k]
            if _footprint_seen(pix, env, np.int64(fp_o[c, 1]), np.int64(fp_o[c, 2]),
                               np.int64(fp_o[c, 3]), np.int64(fp_o[c, 4]), pid, pf,
                               tile_start[tile], tile_start[tile + 1], tile_items, fp_rows,
                               geom, (R, dc, v0, dvec, near), (P, U, W, tq, last),
                               fp_corners):
                visible[pid] = True
                work[C_FOOTPRINT] += 1
        work[C_CYCLES_FOOTPRINT] += _cycles() - ct0
        for p in range(npx):
            work[C_FINAL] += cnt[p]
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
        cyc_tile += _cycles() - ct0
    work[C_MAX_CAP] = max(work[C_MAX_CAP], env.shape[1])
    work[C_CYCLES] += _cycles() - cyc_start
    work[C_CYCLES_SETUP] += cyc_setup - cyc_raster
    work[C_CYCLES_RASTER] += cyc_raster
    work[C_CYCLES_TILE] += cyc_tile
    work[C_THREAD] = worker
    for k in range(counters.shape[1]):
        counters[ch, k] = work[k]
    keep_alive(env_o)
    keep_alive(eid_o)
    keep_alive(T_o)
    keep_alive(tid_o)
    keep_alive(own)
    keep_alive(work_o)
    keep_alive(pf_o)
    keep_alive(tq_o)
    keep_alive(last_o)
