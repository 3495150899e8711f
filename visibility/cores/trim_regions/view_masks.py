"""What one view of a sphere draws: the triangles of its drawn octree leaves, their facing in
scene ids and the edges they hold (P1), in single passes that release the GIL (views run on
threads, ``pipeline``). Triangle ids are row indices of the scene's face array."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def drawn_rows(drawn, item_leaf, item_rows, need):  # pragma: no cover - numba
    """Mark ``need`` (s,) bool (cleared here) for the static rows ``item_rows`` (k,) of the
    octree items whose leaf ``item_leaf`` (k,) is ``drawn`` (leaves,) bool; -1 rows skipped."""
    need[:] = False
    for j in range(item_leaf.shape[0]):
        r = item_rows[j]
        if r >= 0 and drawn[item_leaf[j]]:
            need[r] = True


@njit(cache=True, nogil=True)
def drawn_edges(static, need, facing, ambiguous, ambiguous_code, edge_face, facing_of,
                edge_on):  # pragma: no cover - numba
    """Scene-wide facing and the edges a view tests as silhouettes.

    static : (s,) int64 triangle ids of the static rows; need, facing : (s,) the rows drawn
    and their facing (``raster.setup_triangles``). ambiguous : (a,) int64 triangle ids whose
    plane passes through the sphere, given ``ambiguous_code``. edge_face : (E, 2) int64 the
    triangles of each edge (-1: none). Out: ``facing_of`` (m,) int8 per triangle id (0 where
    not static), ``edge_on`` (E,) bool, an edge with a drawn triangle."""
    facing_of[:] = 0
    drawn_id = np.zeros(facing_of.shape[0], dtype=np.bool_)
    for i in range(static.shape[0]):
        facing_of[static[i]] = facing[i]
        if need[i]:
            drawn_id[static[i]] = True
    for i in range(ambiguous.shape[0]):
        facing_of[ambiguous[i]] = ambiguous_code
    for k in range(edge_face.shape[0]):
        f0 = edge_face[k, 0]
        f1 = edge_face[k, 1]
        edge_on[k] = (f0 >= 0 and drawn_id[f0]) or (f1 >= 0 and drawn_id[f1])


@njit(cache=True, nogil=True)
def drawn_instances(drawn, item_leaf, item_rows, tri_items, npoly, near, layer, out_item,
                    out_layer):  # pragma: no cover - numba
    """The octree items a view rasterizes, in one pass: those whose leaf is ``drawn``, whose
    static row ``item_rows`` has a polygon (``npoly`` > 0 after the near clip) and whose
    triangle ``tri_items`` is not ``near`` the sphere (never an occluder for it). Writes their
    indices (ascending) to ``out_item`` and their leaves' ``layer`` to ``out_layer``, both
    (k,) int64; returns how many."""
    n = 0
    for j in range(item_leaf.shape[0]):
        leaf = item_leaf[j]
        r = item_rows[j]
        if drawn[leaf] and r >= 0 and npoly[r] > 0 and near[tri_items[j]] == 0:
            out_item[n] = j
            out_layer[n] = layer[leaf]
            n += 1
    return n
