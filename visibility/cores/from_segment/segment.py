"""Continuous from-segment visibility (Popescu et al. 2024, Alg. 1) on the six faces of a cubemap.

For a view segment v0 -> v1 (t in [0, 1]) and a cube orientation, every pixel of every face gets a
lower envelope over t of the depths of the primitives that cover its sample; the primitives owning
a piece of some envelope form the segment's visible set. A pixel's sample is its centre (the
paper) or, with ``jitter``, a fixed pseudo-random point of the pixel (``sample_offset``), so that
sub-pixel triangles sliding between two rows of centres still meet samples. Conventions are
``visibility.raster.camera``'s: a sample's ray is (ndc_x, ndc_y, -1) in camera space and depth is
``-z_cam``.

Static triangles (Eqs. 1-2) are in ``static``, moving triangles (Sec. 3.2) and spheres
(Sec. 3.3) in ``dynamic`` / ``spheres``. This module is the driver: ``segment_visible`` runs the
pipeline below over the parts, ``boxes`` (screen boxes, binning), ``envelope`` (per-pixel
envelopes), ``raster`` (tile resolution) and ``geometry`` (the scene's cached clusters).

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

import numba
import numpy as np

from visibility.cancel import checkpoint
from visibility.cores.from_segment.boxes import (
    _PERM,
    _SGN,
    _cluster_boxes,
    _expanded_area,
    _expanded_boxes,
    _sort_and_bin,
    _sphere_boxes,
    _split_clusters,
    _tile_ranges,
)
from visibility.cores.from_segment.envelope import MAX_CAP, START_CAP
from visibility.cores.from_segment.geometry import SegmentGeometry
from visibility.cores.from_segment.groups import (
    CubeFrame,
    PrimRows,
    Results,
    Sweep,
    TileWork,
)
from visibility.cores.from_segment.hull import HMAX, Hulls, no_hulls
from visibility.cores.from_segment.raster import (
    C_CYCLES,
    C_MAX_CAP,
    C_THREAD,
    COUNTERS,
    FOOTPRINT_CENTROID,
    FOOTPRINT_CORNERS,
    FOOTPRINT_OFF,
    _resolve,
)
from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations

#: A segment piece whose primitives' pixel boxes add up to more than this many times the cube's
#: pixels is cut in two, at most MAX_SPLIT_DEPTH times over (``_piece``). Open scenes sit far
#: below the threshold; a 4 m side through dense clutter far above it. Near the threshold a
#: piece's fixed costs weigh against its sweep, so the value matters little; far smaller cuts
#: too often. Since tiles whose primitives are all marked are skipped, a piece's later halves
#: cost less, and deep cuts repeat the set-up more than they save, hence few cuts by default
#: (figures: ``docs/cores/from_segment.md``).
SPLIT_AREA = 64
MAX_SPLIT_DEPTH = 2
#: Default clusters per batch of the box pass (bounds its scratch memory, ~100 bytes each).
DEFAULT_BATCH = 1 << 15
#: Most groups of tiles the envelope pass of one segment is split into, with a cancellation
#: checkpoint between groups (``visibility.cores.base.checkpoint``).
TILE_GROUPS = 16


def _box_area(box: np.ndarray) -> int:
    """Sum of the areas, in pixels, of (k, 4) inclusive pixel boxes (row0, row1, col0, col1)."""
    b = box.astype(np.int64)
    return int(np.sum((b[:, 1] - b[:, 0] + 1) * (b[:, 3] - b[:, 2] + 1)))


def _cluster_stage(geom, v0, dvec, rb, res, near, pad, batch) -> list[tuple]:
    """Per batch of the scene's clusters, ``_split_clusters``' answer for the segment: the
    clusters kept whole (ids, faces, boxes, depths, flags) and the (triangle, face) pairs of
    those expanded. Computed once per piece, for its area and then its primitives."""
    out = []
    nc = len(geom.cl_start) - 1
    for first in range(0, nc, batch):
        last = min(nc, first + batch)
        k = last - first
        cbox = np.empty((k, 6, 4), dtype=np.int32)
        cz = np.empty((k, 6))
        cflag = np.empty((k, 6), dtype=np.uint8)
        _cluster_boxes(geom.cl_lo[first:last], geom.cl_hi[first:last], v0, dvec, rb, _PERM, _SGN,
                       res, near, pad, cbox, cz, cflag)
        out.append(_split_clusters(geom.cl_start, geom.cl_tris, cbox, cz, cflag, first, res))
    return out


def _collect_prims(geom, v0, dvec, rb, rots, res, near, pad, batch, stats, area_only=False,
                   stage=None):
    """All (primitive, face) pairs that can touch a pixel sample of the segment's cubemap:
    whole clusters, triangles of expanded clusters, spheres (global ids n_tri + s), and the
    projected swept hulls of the triangles (``hull.Hulls``). With ``area_only``, just the sum
    of their pixel boxes' areas (int), at a fraction of the cost. ``stage``: the segment's
    ``_cluster_stage``, when the caller has it already."""
    parts = []
    area = 0
    hull_parts = []
    kept = 0
    expanded = 0
    if stage is None:
        stage = _cluster_stage(geom, v0, dvec, rb, res, near, pad, batch)
    for kc, kf, kb, kz, kfl, et, ef in stage:
        if area_only:
            area += _box_area(kb)
            if len(et):
                area += int(_expanded_area(geom.arrays(), et, ef, CubeFrame(
                    v0, dvec, rb, _PERM, _SGN, int(res), float(near), float(pad))))
            continue
        parts.append((kc, kf, kb, kz, kfl))
        kept += len(kc)
        if len(et):
            ebox = np.empty((len(et), 4), dtype=np.int32)
            ez = np.empty(len(et))
            efl = np.empty(len(et), dtype=np.uint8)
            ehull = Hulls(np.zeros(0, np.int32), np.empty((len(et), HMAX, 2), np.float32),
                          np.empty(len(et), np.int8))
            _expanded_boxes(geom.arrays(), et, ef,
                            CubeFrame(v0, dvec, rb, _PERM, _SGN, int(res), float(near),
                                      float(pad)), ebox, ez, efl, ehull)
            keep = efl != 0
            parts.append((et[keep].astype(np.int32), ef[keep].astype(np.int32), ebox[keep],
                          ez[keep], efl[keep]))
            # Only the hulls built are kept (most triangles' boxes are too small to get one):
            # rows for all would cost ~100 B per expanded triangle and face, and so would
            # copying them all before picking.
            built = keep & (ehull.count > 0)
            hull_parts.append((len(parts) - 1, ehull.pts[built], ehull.count[built],
                               built[keep]))
            expanded += int(keep.sum())
    if len(geom.sphere_sel):
        k = len(geom.sphere_sel)
        box = np.empty((k, 6, 4), dtype=np.int32)
        z = np.empty((k, 6))
        flag = np.empty((k, 6), dtype=np.uint8)
        _sphere_boxes(geom.centers0, geom.centers1, geom.radii, geom.sphere_sel, v0, dvec, rots,
                      res, near, pad, box, z, flag)
        si, sf = np.nonzero(flag)
        if area_only:
            return area + _box_area(box[si, sf])
        parts.append(((geom.sphere_sel[si] + geom.n_triangles).astype(np.int32),
                      sf.astype(np.int32), box[si, sf], z[si, sf], flag[si, sf]))
    if area_only:
        return area
    if not parts:
        parts.append((np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 4), np.int32),
                      np.zeros(0), np.zeros(0, np.uint8)))
    prim_src, prim_face, prim_box, prim_z, prim_flag = (
        np.ascontiguousarray(np.concatenate([p[i] for p in parts])) for i in range(5))
    hulls = no_hulls(len(prim_src))
    if hull_parts:
        starts = np.cumsum([0] + [len(p[0]) for p in parts])
        row = 0
        for k, pts, _, has in hull_parts:
            rows = np.full(len(has), -1, dtype=np.int32)
            rows[has] = np.arange(row, row + len(pts), dtype=np.int32)
            hulls.index[starts[k]:starts[k + 1]] = rows
            row += len(pts)
        hulls = Hulls(hulls.index, np.ascontiguousarray(np.concatenate([h[1] for h in hull_parts])),
                      np.ascontiguousarray(np.concatenate([h[2] for h in hull_parts])))
    stats["prims"] = stats.get("prims", 0) + len(prim_src)
    stats["cluster_prims"] = stats.get("cluster_prims", 0) + kept
    stats["triangle_prims"] = stats.get("triangle_prims", 0) + expanded
    return prim_src, prim_face, prim_box, prim_z, prim_flag, hulls


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
    envelope_cap: int = START_CAP,
    footprint: bool = False,
    corners: bool = False,
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
        Output-sensitive: a screen tile all of whose primitives are marked already (by earlier
        segments of the cell, or earlier tiles) is not resolved, nor, where a tile lists few
        unmarked ones, the pixels none of those can reach (``stats["tiles_known"]``,
        ``["pixels_known"]``); the mask comes out the same. Not with ``witness``.
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
    envelope_cap : envelope rows per pixel to start with, grown x4 as a pixel needs more (up to
        ``MAX_CAP``); the answer does not depend on it (a smaller one tests the growth).
    footprint : also mark a static triangle that holds no pixel sample anywhere on the
        segment when an extra sample at its centroid sees it (``raster._footprint_seen``;
        ``stats["footprint_seen"]``): sub-pixel triangles that slide between the samples.
        False marks what some pixel sample sees and nothing else (the paper's answer). Not
        with ``witness`` (the extra samples have no pixel to name).
    corners : with ``footprint``, also samples near each corner of such a triangle, and takes
        triangles whose pixel box holds closed pixels (a nearer surface in view all along the
        segment) beside open ones: slivers seen past a roof line.

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
    cap = int(envelope_cap)
    if not 1 <= cap <= MAX_CAP:
        raise ValueError(f"envelope_cap must be in [1, {MAX_CAP}], got {envelope_cap}")
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
    if footprint and witness is not None:
        raise ValueError("footprint marks primitives no sample witnesses: not with witness")
    mode = FOOTPRINT_OFF if not footprint else (
        FOOTPRINT_CORNERS if corners else FOOTPRINT_CENTROID)
    _piece(geom, v0, v1 - v0, 0.0, 1.0, cuts if splittable else 0, rb, rots, res,
           float(near), int(knots), jitter, int(seed), max(1, int(batch)), visible, stats,
           witness, cap=cap, footprint=mode)
    return visible


def _piece(geom, v0, dvec, ta, tb, depth, rb, rots, res, near, knots, jitter, seed, batch,
           visible, stats, witness, est=0.0, cap=START_CAP, footprint=FOOTPRINT_OFF):
    """Visible set of the eye walking v0 -> v0 + dvec (times [ta, tb] of the whole segment).

    A piece whose primitives' pixel boxes add up to more than ``SPLIT_AREA`` times the cube's
    pixels is cut in two (up to ``depth`` more times): geometry close to a long segment sweeps
    across much of the cube, so its boxes are huge and occlusion bounds (the farthest depth a
    pixel's envelope reaches along the piece) stay far; halves sweep half as far. The union of
    the halves' sets is the set of the whole (exactness is per eye position). ``est``: an
    estimate of the piece's area from its parent's (0: none); over the limit, the piece is cut
    without measuring. ``cap``: envelope rows per pixel to start with. ``footprint``: the
    footprint rule's mode (``raster.FOOTPRINT_OFF`` and the others)."""
    t0 = time.perf_counter()
    limit = SPLIT_AREA * 6 * res * res
    # Pixel boxes hold the pixels whose sample may meet a primitive; with the footprint rule,
    # every pixel its centroid crosses (at centres, a sub-pixel triangle's box may hold none).
    pad = max(jitter, 0.5) if footprint != FOOTPRINT_OFF else jitter
    # The decision needs only the boxes' areas (no hulls, nothing stored). Deciding whole
    # segments from a full collection instead (open scenes never cut them) wasted far more on
    # cluttered scenes, where they are cut, than it saved on open ones.
    area = est
    stage = None
    if depth > 0 and est <= limit:
        stage = _cluster_stage(geom, v0, dvec, rb, res, near, pad, batch)
        area = _collect_prims(geom, v0, dvec, rb, rots, res, near, pad, batch, stats,
                              area_only=True, stage=stage)
    if depth > 0 and area > limit:
        del stage  # the halves project their own; not held through the recursion
        stats["box_seconds"] = stats.get("box_seconds", 0.0) + (time.perf_counter() - t0)
        stats["splits"] = stats.get("splits", 0) + 1
        half = 0.5 * dvec
        tm = 0.5 * (ta + tb)
        # A half sweeps half as far in each image direction, so its boxes keep about a
        # quarter of the area or more: far enough over, it is cut without measuring (the
        # answer is the same either way; only the cost differs).
        for a, lo, hi in ((v0, ta, tm), (v0 + half, tm, tb)):
            checkpoint()
            _piece(geom, a, half, lo, hi, depth - 1, rb, rots, res, near, knots, jitter,
                   seed, batch, visible, stats, witness, 0.25 * area, cap, footprint)
        return
    prim_src, prim_face, prim_box, prim_z, prim_flag, hulls = _collect_prims(
        geom, v0, dvec, rb, rots, res, near, pad, batch, stats, stage=stage)
    del stage
    t1 = time.perf_counter()
    rstart, cols = _tile_ranges(prim_box, hulls, pad)
    zkey, tile_start, items = _sort_and_bin(prim_face, prim_box, prim_z, rstart, cols, res, near)
    del rstart, cols
    t2 = time.perf_counter()
    tiles = np.flatnonzero(np.diff(tile_start) > 0).astype(np.int64)
    # Tiles are strided over several chunks per thread so busy screen regions spread out.
    nch = max(1, min(len(tiles), 8 * numba.get_num_threads()))
    counters = np.zeros((nch, len(COUNTERS)), dtype=np.int64)
    counters[:, C_MAX_CAP] = cap
    busiest = 0
    wit = np.zeros((nch, geom.n_ids, 5)) if witness is not None else np.zeros((1, 0, 5))
    overflow = np.zeros(len(tiles), dtype=bool)
    # The envelope pass runs in groups of tiles with a checkpoint between them, so a cancelled
    # or late computation stops within a fraction of one segment's time.
    groups = max(1, min(TILE_GROUPS, len(tiles) // (4 * nch)))
    rows = PrimRows.of(prim_src, prim_box, prim_z, zkey, prim_flag, prim_face, hulls)
    sweep = Sweep(v0, dvec, rots, res, near, knots, jitter, seed, cap, np.int64(footprint), pad)
    garrays = geom.arrays()
    for sel in np.array_split(np.arange(len(tiles)), groups):
        if not len(sel):
            continue
        checkpoint()
        group_overflow = np.zeros(len(sel), dtype=bool)
        before = counters[:, C_CYCLES].copy()
        _resolve(TileWork(tiles[sel], nch, numba.get_num_threads(), tile_start, items), rows,
                 garrays, sweep, Results(visible, group_overflow, counters, wit))
        overflow[sel] = group_overflow
        # The busiest thread's cycles: against the mean, how well the chunks spread.
        per = np.bincount(counters[:, C_THREAD], weights=counters[:, C_CYCLES] - before)
        busiest += int(per.max())
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
    for k, name in enumerate(COUNTERS):
        if name not in ("max_cap", "thread"):
            stats[name] = stats.get(name, 0) + int(counters[:, k].sum())
    stats["max_cap"] = max(stats.get("max_cap", 0), int(counters[:, C_MAX_CAP].max()))
    stats["cycles_busiest_thread"] = stats.get("cycles_busiest_thread", 0) + busiest
    stats["face_runs"] = stats.get("face_runs", 0) + 6
