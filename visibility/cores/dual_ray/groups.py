"""The named groups of arrays the shaft kernels take (``dual_space.nodes_visible``,
``dual_space.boxes_visible_among``) in place of long positional argument lists.

Plain ``NamedTuple`` s: numba passes them into nopython code as heterogeneous tuples. The
kernels unpack them before their parallel loops (numba loses writes made inside a prange body
through a named tuple's field, numba issue #7135).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Pieces(NamedTuple):
    """Fence pieces (``fences.Fences``): ``seg`` (k, 4) XZ end points, ``top`` and ``bot``
    (k, 2) the strip's top and bottom at both ends, ``lean`` (k, 2) how far the real wall
    strays from the piece, ``vid`` (k, 2) ids of the end points, metres."""

    seg: np.ndarray
    top: np.ndarray
    bot: np.ndarray
    lean: np.ndarray
    vid: np.ndarray


class PieceGrid(NamedTuple):
    """The XZ grid that finds pieces: corner ``lo`` (2,), cell side ``step``, cells ``n``
    (2,) along X and Z, CSR ``cell_start`` (nx * nz + 1,) and ``cell_items`` (piece ids per
    cell, highest top first)."""

    lo: np.ndarray
    step: float
    n: np.ndarray
    cell_start: np.ndarray
    cell_items: np.ndarray


class GroupLists(NamedTuple):
    """Occluder lists shared by groups of boxes: box i belongs to group ``group[i]``, whose
    pieces are ``ids[start[g]:start[g + 1]]`` when ``ok[g]`` (else the whole grid's)."""

    group: np.ndarray
    start: np.ndarray
    ids: np.ndarray
    ok: np.ndarray
