"""The named groups of arrays the ``cos`` kernels take (``lists.fill_lists``,
``resolve.resolve_tiles``) in place of long positional argument lists.

Plain ``NamedTuple`` s: numba passes them into nopython code as heterogeneous tuples, and the
kernels unpack them once at the top.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class PrimArrays(NamedTuple):
    """The primitives (``prims.Prims``) as the kernels read them.

    pts : (P, 3) float64 corner points, metres, cell-centred; primitive p's are
        ``pts[start[p]:start[p] + npts[p]]``.
    start, npts : (n,) int64.
    kind : (n,) int8, 0 for a triangle (the others are hulls: occludees only).
    vid : (n, 3) int64 welded vertex ids (fusion along shared edges).
    solid : (n,) uint8, whether the primitive may occlude (``prims.solid_mask``).
    gap : (n,) float64 distance from the cell box to the primitive's bounding box, metres.
    leaf : (n,) int64 the primitive's leaf, a run of consecutive triangle ids (-1: none);
        leaf_pts : (8 L, 3) float64 the leaves' box corners, cell-centred
        (``core._leaf_boxes``).
    """

    pts: np.ndarray
    start: np.ndarray
    npts: np.ndarray
    kind: np.ndarray
    vid: np.ndarray
    solid: np.ndarray
    gap: np.ndarray
    leaf: np.ndarray
    leaf_pts: np.ndarray


class Screen(NamedTuple):
    """One view's camera and pixel grid (``planes.View``).

    origin, perm, sign : the side plane's frame (cell-centred, axis permutation and signs).
    corners : (4, 3) the camera rectangle in the view's frame.
    nx, ny : pixels across and down; x_lo, y_lo : the grid's lower corner on the image plane;
    pw : pixel width (image-plane units); plane_tol : the plane tests' tolerance, metres.
    relaxed : whether an occludee may take the relaxed cover test (``resolve._covers_q``)
        where the strict one finds no group hiding it.
    fuse : whether separate groups may hide an occludee together where none does alone
        (``resolve._fused_hide``).
    refine : levels of 2 x 2 sub-pixels an occludee no group hides over the whole pixel is
        tested at (``resolve._refined_hide``; 0: none).
    leaf_list : pixels listing at least this many entries test the leaf box of an occludee
        once it is hidden (``resolve._leaf_hidden``; 0: none).
    """

    origin: np.ndarray
    perm: np.ndarray
    sign: np.ndarray
    corners: np.ndarray
    nx: int
    ny: int
    x_lo: float
    y_lo: float
    pw: float
    plane_tol: float
    relaxed: bool
    fuse: bool
    refine: int
    leaf_list: int


class TileLists(NamedTuple):
    """Per-pixel lists of a run of screen tiles [tile0, tile1).

    entries : (E,) int32 items of their tile (indices into its part of ``items``); pixel
        ``loc`` of tile ``tile`` holds ``entries[pstart[i]:pstart[i] + pcount[i]]``,
        i = (tile - tile0) tsz^2 + loc.
    torder : (tile1 - tile0,) int64 the order tiles are taken in (balances the threads).
    tiles_x : tiles across; tsz : pixels across a tile.
    shares : how many threads ``torder`` was dealt to (``core._balanced_order``): its
        contiguous shares, in that number, carry a like mix of costs.
    items, ioff : (I,) int32 primitive ids of the tiles' items, tile ``tile``'s at
        ``items[ioff[tile]:ioff[tile + 1]]`` (``ioff`` indexed by tile, over all tiles of the
        view), in front-to-back order: the entries name items of their tile, so that what
        the tile's pixels share (the items' edge adjacency) is worked out once per tile.
    block : (tiles,) int64 pixels per side of a tile's samples, indexed by tile like ``ioff``:
        1 samples every pixel; b > 1 one sample per b x b pixels, at their centre with a
        half-width of b / 2 pixels (its directions hold all of theirs), its list at
        ``loc = r tsz + c`` for the sample in row r and column c of the tile's samples; an
        entry its test leaves unhidden is tested again at sub-samples down to single pixels
        (``resolve._refined_hide``).
    """

    entries: np.ndarray
    pstart: np.ndarray
    pcount: np.ndarray
    tile0: int
    tile1: int
    torder: np.ndarray
    tiles_x: int
    tsz: int
    shares: int
    items: np.ndarray
    ioff: np.ndarray
    block: np.ndarray


class Marks(NamedTuple):
    """What a resolution reads and writes per primitive and per tile.

    known : (n,) uint8 primitives already known visible (tested no more, still occluders).
    vis : (n,) uint8 set to 1 for each primitive found visible.
    hid : (E,) uint8 set to 1 at each entry found hidden (the coarse pass), or (0,): not kept.
    counters : (tiles, N_COUNTERS) int64 work per tile (``resolve.resolve_tiles``).
    stop : (1,) uint8 the computation's stop flag (``visibility.cancel.stop_flag``).
    """

    known: np.ndarray
    vis: np.ndarray
    hid: np.ndarray
    counters: np.ndarray
    stop: np.ndarray


class EdgePool(NamedTuple):
    """The active (silhouette) edges of a pixel's occluder groups (``resolve.resolve_tiles``),
    each group's in one contiguous block, so that the cover tests, which walk a group's
    silhouette, read memory in order rather than chasing a list.

    geo : (room, 6) float64 per record: the edge's COS end points (ax, ay, bx, by) and their
        depths (wa, wb), copied from the occluder triangle (its own arrays are read at random).
    node : (room,) int64 the edge's node 3 q + e (edge e of occluder triangle q); -1 in a record
        no block holds (left behind when a block moved, or by an edge fused away).
    pos : (3 lmax,) int64 the record of node.
    start, length, cap : (lmax,) int64 per group: its block's first record, records used (its
        active edges, in any order), records reserved.
    top : (1,) int64 the first free record.
    """

    geo: np.ndarray
    node: np.ndarray
    pos: np.ndarray
    start: np.ndarray
    length: np.ndarray
    cap: np.ndarray
    top: np.ndarray


class ShareScratch(NamedTuple):
    """The scratch arrays of one share of ``resolve.resolve_tiles`` (``resolve._share_scratch``),
    sized for the share's longest pixel list ``lmax``, its longest tile ``tmax`` (entries) and
    its tile of most items ``imax``.

    cam : a primitive's points in the view's frame (``load_prim``); qv, qr: their projection
        (``project``); rv, rr: the pixel's region of eye offsets (``lists.region_at``).
    kx, ky : the occludee's region K (``region_polygon``); tx_, ty_: its scratch; rx, ry: the
        pixel's whole offset region; kb, rb: their geometry (``_k_box``); knx, kny, klo, khi
        and rnx, rny, rlo, rhi: their edge normals and extents.
    qctx : the occludee's context for ``_covers_q``; rpoly (MAX_POLY, 6), rpb (7,): the camera
        rectangle's image in the cameras' frame (x, y, edge normal x, y, extent lo, hi per
        vertex) and its axes (``polygon_axes``); ws, wpt: the relaxed cover test's scratch.
    ov, ow, owr, oid, oact, oplane, ouse, obb : occluder triangles (lmax rows): COS corners
        (counter-clockwise), depths, depth range, welded ids, active edges, plane, whether the
        whole camera rectangle lies on one side of that plane (the plane test applies), COS
        box.
    grp, nxt, head, tail, gsize, gbb, gwlo, gwhi, gcov, alive, gdorm : groups (id = their first
        triangle): members, size, COS box, depth range, coverall, alive, dormant (only hidden
        triangles: never tested against).
    edges : the groups' active edges (``EdgePool``).
    live, lpos, covl, cpos, cand : the live list (groups not coverall, oldest first; dead
        entries have lpos -1 until it is compacted), the unordered list of coverall groups and
        their positions, candidate groups.
    gslot, sg, shead, pool, pdep, fslot, sfr, dom : depth grids of groups of ``GRID_MIN``
        triangles or more (slots of sg, shead in the frame of depth sfr over the domain dom:
        x0, x1, y0, y1, cells per metre in x and y; member list nodes in pool; free slots).
    thash, eslot, eready, sstate, enext : fusion along shared edges: the tile's hash of
        undirected welded edges (tile stamp, lower id, higher id, edge slot), each item's three
        edge slots (-1: none) and the tile they were made for (at its first insertion there),
        per edge slot the pixel's stamp and its newest occluder edge 3 q + e, chained newest
        first through enext.
    tseen, tset : primitives found visible at an earlier pixel of the tile (a bit each), and
        the ids set, cleared after the tile.
    work : (N_WORK,) int64 per-tile counters the helpers add to (``resolve.N_WORK``).
    opart : (lmax, 3) int64 per occluder edge, the edge 3 r + f it was fused with (-1: none).
    obad, part, pbb, pwlo, pwhi : a group's part in front of the occludee
        (``resolve._front_part``, separate groups only): the triangles left out, the part's
        silhouette as a one-block ``EdgePool`` (group 0), its COS box and depth range.
    """

    cam: np.ndarray
    qv: np.ndarray
    qr: np.ndarray
    rv: np.ndarray
    rr: np.ndarray
    kx: np.ndarray
    ky: np.ndarray
    tx_: np.ndarray
    ty_: np.ndarray
    rx: np.ndarray
    ry: np.ndarray
    kb: np.ndarray
    qctx: np.ndarray
    rpoly: np.ndarray
    rpb: np.ndarray
    ws: np.ndarray
    wpt: np.ndarray
    knx: np.ndarray
    kny: np.ndarray
    klo: np.ndarray
    khi: np.ndarray
    rb: np.ndarray
    rnx: np.ndarray
    rny: np.ndarray
    rlo: np.ndarray
    rhi: np.ndarray
    ov: np.ndarray
    ow: np.ndarray
    owr: np.ndarray
    oid: np.ndarray
    oact: np.ndarray
    oplane: np.ndarray
    ouse: np.ndarray
    obb: np.ndarray
    grp: np.ndarray
    nxt: np.ndarray
    head: np.ndarray
    tail: np.ndarray
    gsize: np.ndarray
    gbb: np.ndarray
    gwlo: np.ndarray
    gwhi: np.ndarray
    gcov: np.ndarray
    alive: np.ndarray
    gdorm: np.ndarray
    edges: EdgePool
    live: np.ndarray
    lpos: np.ndarray
    covl: np.ndarray
    cand: np.ndarray
    cpos: np.ndarray
    gslot: np.ndarray
    sg: np.ndarray
    shead: np.ndarray
    pool: np.ndarray
    pdep: np.ndarray
    fslot: np.ndarray
    sfr: np.ndarray
    dom: np.ndarray
    thash: np.ndarray
    eslot: np.ndarray
    eready: np.ndarray
    sstate: np.ndarray
    enext: np.ndarray
    tseen: np.ndarray
    tset: np.ndarray
    work: np.ndarray
    opart: np.ndarray
    obad: np.ndarray
    part: EdgePool
    pbb: np.ndarray
    pwlo: np.ndarray
    pwhi: np.ndarray
