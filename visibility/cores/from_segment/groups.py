"""The named groups of arrays the envelope pass takes (``raster._resolve``, ``raster._raster``)
in place of long positional argument lists.

Plain ``NamedTuple`` s: numba passes them into nopython code as heterogeneous tuples, and the
kernels unpack them once at the top.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from visibility.cores.from_segment.hull import Hulls


class CubeFrame(NamedTuple):
    """The cube the box pass projects into: the segment's start ``v0`` (3,) and displacement
    ``dvec`` (3,), metres; the cube's base rotation ``rb`` (3, 3); per face the axis
    permutation ``perm`` and signs ``sgn`` (``boxes._PERM``, ``boxes._SGN``); ``res`` pixels
    across a face; the ``near`` plane, metres; ``pad`` pixels of sample offset to allow for."""

    v0: np.ndarray
    dvec: np.ndarray
    rb: np.ndarray
    perm: np.ndarray
    sgn: np.ndarray
    res: int
    near: float
    pad: float


class TileWork(NamedTuple):
    """The tiles of one group of the envelope pass and their primitive lists.

    tiles : (k,) int64 tile ids (face-major, ``boxes.TILE`` x ``TILE`` pixels) to resolve.
    n_chunks : the tiles are strided over this many chunks (``tiles[c::n_chunks]``).
    n_workers : threads taking chunks.
    tile_start : (T + 1,) int64 CSR offsets of each tile's list into ``tile_items``.
    tile_items : (E,) int64 primitive rows (``PrimRows``), front to back per tile.
    """

    tiles: np.ndarray
    n_chunks: int
    n_workers: int
    tile_start: np.ndarray
    tile_items: np.ndarray


class PrimRows(NamedTuple):
    """The segment's (primitive, face) rows (``segment._collect_prims``).

    src : (n,) int32 triangle id, cluster id (``FLAG_CLUSTER``) or ``n_tri + sphere``.
    box : (n, 4) int32 pixel box (row0, row1, col0, col1) on its face.
    z : (n,) float64 smallest depth along the segment, metres.
    zkey : (n,) float64 the depth its tile lists are sorted by.
    flag : (n,) uint8 ``boxes.FLAG_*``.
    face : (n,) int32 cube face.
    hull_index, hull_pts, hull_count : the projected swept hulls of some rows, the fields of a
        ``hull.Hulls`` (flat here: numba's parallel loops take no tuple inside a tuple).
    """

    src: np.ndarray
    box: np.ndarray
    z: np.ndarray
    zkey: np.ndarray
    flag: np.ndarray
    face: np.ndarray
    hull_index: np.ndarray
    hull_pts: np.ndarray
    hull_count: np.ndarray

    @classmethod
    def of(cls, src: np.ndarray, box: np.ndarray, z: np.ndarray, zkey: np.ndarray,
           flag: np.ndarray, face: np.ndarray, hulls: Hulls) -> PrimRows:
        """The rows, with their ``hulls`` spread into the flat fields."""
        return cls(src, box, z, zkey, flag, face, hulls.index, hulls.pts, hulls.count)


class GeometryArrays(NamedTuple):
    """``geometry.SegmentGeometry`` as the kernels read it (``SegmentGeometry.arrays``: its
    attributes of the same names; ``c0``, ``c1``: the sphere centres; ``n_tri``: the face
    count; ``cl_lo``, ``cl_hi``: the clusters' boxes over both positions)."""

    verts0: np.ndarray
    verts1: np.ndarray
    faces: np.ndarray
    moving: np.ndarray
    cl_start: np.ndarray
    cl_tris: np.ndarray
    c0: np.ndarray
    c1: np.ndarray
    radii: np.ndarray
    n_tri: int
    cl_lo: np.ndarray
    cl_hi: np.ndarray


class Sweep(NamedTuple):
    """The moving cube and its pixel samples.

    v0 : (3,) float64 the segment's start, metres; dvec : (3,) its displacement.
    rots : (6, 3, 3) world-to-face rotations.
    res : pixels across a face; near : near plane, metres.
    knots : moving primitives' depth chords are at most 1 / knots long in t.
    jitter : samples' offset from pixel centres, pixels (``raster.sample_offset``).
    seed : the jitter pattern.
    cap : envelope rows per pixel to start with (grown x4 as needed, ``raster._grown``).
    footprint : the footprint rule's mode (``raster.FOOTPRINT_OFF``: only what a pixel
        sample sees, the paper; ``FOOTPRINT_CENTROID``: a static triangle that holds no pixel
        sample along the segment gets an extra sample at its centroid,
        ``raster._footprint_seen``; ``FOOTPRINT_CORNERS``: near its corners too, and for
        triangles passing closed pixels by).
    pad : how far off a pixel's centre, in pixels, a primitive's box and spans reach
        (``jitter``, or half a pixel with the footprint rule).
    """

    v0: np.ndarray
    dvec: np.ndarray
    rots: np.ndarray
    res: int
    near: float
    knots: int
    jitter: float
    seed: int
    cap: int
    footprint: int
    pad: float


class Results(NamedTuple):
    """What the envelope pass writes.

    visible : (n_ids,) bool, primitives owning a piece of some envelope.
    overflow : (k,) bool per tile of ``TileWork.tiles``: its envelopes outgrew ``MAX_CAP``.
    counters : (n_chunks, len(raster.COUNTERS)) int64 work counters per chunk.
    witness : (n_chunks, n_ids, 5) float64 per chunk, or (1, 0, 5) for none.
    """

    visible: np.ndarray
    overflow: np.ndarray
    counters: np.ndarray
    witness: np.ndarray


class PieceScratch(NamedTuple):
    """Scratch of one primitive's cover test at one pixel: its depth pieces (t0, t1, z0, z1)
    and the moving and sphere covers' breakpoints and stack (``dynamic``, ``spheres``); and
    ``at`` (4,) int64: the row, column and piece where a draw stopped for want of envelope
    room, and 1 in ``at[3]`` while the next draw of the primitive resumes there
    (``raster._raster``)."""

    t0: np.ndarray
    t1: np.ndarray
    z0: np.ndarray
    z1: np.ndarray
    brk: np.ndarray
    stk: np.ndarray
    at: np.ndarray


class TilePixels(NamedTuple):
    """The current tile's pixels: rows from ``r0`` and columns from ``cl0``, ``tw`` wide,
    ``npx`` in all (row-major), ``step`` NDC units a pixel; per pixel its envelope's piece
    count ``cnt`` and bound ``bound`` (``envelope.pixel_bound``) and its sample's offset
    (``jx``, ``jy``) NDC units from its centre."""

    r0: int
    cl0: int
    tw: int
    npx: int
    step: float
    cnt: np.ndarray
    bound: np.ndarray
    jx: np.ndarray
    jy: np.ndarray


class ChunkScratch(NamedTuple):
    """The arrays one chunk of ``raster._resolve`` owns (``raster._chunk_scratch``), borrowed
    by ``raster._resolve_chunk``: per pixel of a tile its piece count ``cnt`` (int64),
    ``bound`` and sample offsets ``jx``, ``jy``; one primitive's set-up ``coef`` (40,),
    camera-space corners ``P``, velocities ``U``, world corners ``W`` (3, 3), the face
    rotation ``R`` (3, 3), the eye's motion ``dc`` (3,), a sphere's centre ``cen`` and velocity
    ``vel`` (3,), a pixel box ``bx`` (4,) int64, row spans ``span`` (TILE, 2) int64, a cluster
    triangle's swept hull scratch ``c_uv`` (6, 2), ``c_scratch`` (14, 2), ``c_pts`` (1, HMAX,
    2) float32; the row spans' columns ``ext`` (TILE, 2) float64 (``hull.hull_rows``); and the
    cover test's ``piece`` (``PieceScratch``)."""

    cnt: np.ndarray
    bound: np.ndarray
    jx: np.ndarray
    jy: np.ndarray
    coef: np.ndarray
    P: np.ndarray
    U: np.ndarray
    W: np.ndarray
    R: np.ndarray
    dc: np.ndarray
    cen: np.ndarray
    vel: np.ndarray
    bx: np.ndarray
    span: np.ndarray
    c_uv: np.ndarray
    c_scratch: np.ndarray
    c_pts: np.ndarray
    ext: np.ndarray
    piece: PieceScratch
