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
    """

    pts: np.ndarray
    start: np.ndarray
    npts: np.ndarray
    kind: np.ndarray
    vid: np.ndarray
    solid: np.ndarray
    gap: np.ndarray


class Screen(NamedTuple):
    """One view's camera and pixel grid (``planes.View``).

    origin, perm, sign : the side plane's frame (cell-centred, axis permutation and signs).
    corners : (4, 3) the camera rectangle in the view's frame.
    nx, ny : pixels across and down; x_lo, y_lo : the grid's lower corner on the image plane;
    pw : pixel width (image-plane units); plane_tol : the plane tests' tolerance, metres.
    relaxed : whether an occludee may take the relaxed cover test (``resolve._covers_q``)
        where the strict one finds no group hiding it.
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


class TileLists(NamedTuple):
    """Per-pixel lists of a run of screen tiles [tile0, tile1).

    entries : (E,) int32 primitive ids; pixel ``loc`` of tile ``tile`` holds
        ``entries[pstart[i]:pstart[i] + pcount[i]]``, i = (tile - tile0) tsz^2 + loc.
    torder : (tile1 - tile0,) int64 the order tiles are taken in (balances the threads).
    tiles_x : tiles across; tsz : pixels across a tile.
    shares : how many threads ``torder`` was dealt to (``core._balanced_order``): its
        contiguous shares, in that number, carry a like mix of costs.
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


class Marks(NamedTuple):
    """What a resolution reads and writes per primitive and per tile.

    known : (n,) uint8 primitives already known visible (tested no more, still occluders).
    vis : (n,) uint8 set to 1 for each primitive found visible.
    hid : (E,) uint8 set to 1 at each entry found hidden (the coarse pass), or (0,): not kept.
    counters : (tiles, 6) int64 work per tile (``resolve.resolve_tiles``).
    stop : (1,) uint8 the computation's stop flag (``visibility.cancel.stop_flag``).
    """

    known: np.ndarray
    vis: np.ndarray
    hid: np.ndarray
    counters: np.ndarray
    stop: np.ndarray
