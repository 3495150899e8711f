"""Which primitives a view can list: the scene hierarchy's leaves that meet the view's rays.

A view's rays leave every camera position c on its rectangle with a direction whose tangents
(u, v) lie in the image window, at depths w >= c_w. Each window side bounds them by one plane
in camera space (for the left side: x - a w >= min over the corners of c_x - a c_w), so a node
box wholly beyond one of those planes, or behind every camera position, holds nothing a ray of
the view meets: its triangles get empty footprints (``lists.footprints``) and are never
projected. The window is widened by ``MARGIN_PIXELS`` against the half-pixel growth of the
footprints and rounding. The walk is over ``visibility.raster.hierarchy`` (the one tree every
core that culls shares); primitives outside the tree (moving triangles, spheres) are always
kept.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from visibility.cores.cos.prims import TRIANGLE, Prims
from visibility.raster.hierarchy import Hierarchy

#: Pixels by which the image window is widened for the cull.
MARGIN_PIXELS = 2.0


class Tree(NamedTuple):
    """The kernels' view of the scene hierarchy and of where its triangles sit in a cell's
    front-to-back order.

    boxes : (2 * slots, 2, 3) float64 node boxes, world metres, heap order.
    order : (t,) int32 triangle ids in leaf order; ``leaf_size`` triangles a leaf.
    pos_of_tri : (n_faces,) int64 position in the cell's ``order`` of each triangle's
        primitive (-1: none, e.g. an unseen back face).
    loose_pos : (k,) int64 positions of the primitives the tree does not hold.
    shift : (3,) float64 the cell centre, world metres (primitive points are relative to it).
    """

    boxes: np.ndarray
    order: np.ndarray
    leaf_size: int
    pos_of_tri: np.ndarray
    loose_pos: np.ndarray
    shift: np.ndarray


def cell_tree(h: Hierarchy, prims: Prims, order: np.ndarray, n_triangles: int,
              centre: np.ndarray) -> Tree:
    """The ``Tree`` of a cell whose primitives ``prims`` are taken in ``order`` (n,) (positions
    t hold primitive order[t]); ``n_triangles`` is the scene's face count."""
    n = len(order)
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n, dtype=np.int64)
    out = prims.out_id
    tri = (prims.kind == TRIANGLE) & (out < n_triangles)
    in_tree = np.zeros(n, dtype=bool)
    in_tree[tri] = h.leaf_of[out[tri]] >= 0
    pos_of_tri = np.full(h.n_faces, -1, dtype=np.int64)
    pos_of_tri[out[in_tree]] = pos[in_tree]
    loose_pos = np.sort(pos[~in_tree])
    return Tree(h.boxes, h.order, int(h.leaf_size), pos_of_tri, loose_pos,
                np.asarray(centre, dtype=np.float64))


def view_planes(corners: np.ndarray, x_lo: float, y_lo: float, nx: int, ny: int, pw: float,
                tol: float) -> np.ndarray:
    """(5, 4) half-spaces a * x + b * y + c * w >= d (camera space, metres) holding every
    point a ray of the view meets: the four window sides (widened by ``MARGIN_PIXELS``) and
    w >= the nearest camera depth; each loosened by ``tol`` metres."""
    m = MARGIN_PIXELS * pw
    a_lo, a_hi = x_lo - m, x_lo + nx * pw + m
    b_lo, b_hi = y_lo - m, y_lo + ny * pw + m
    cx, cy, cw = corners[:, 0], corners[:, 1], corners[:, 2]
    return np.array([
        [1.0, 0.0, -a_lo, float((cx - a_lo * cw).min()) - tol],
        [-1.0, 0.0, a_hi, float(-(cx - a_hi * cw).max()) - tol],
        [0.0, 1.0, -b_lo, float((cy - b_lo * cw).min()) - tol],
        [0.0, -1.0, b_hi, float(-(cy - b_hi * cw).max()) - tol],
        [0.0, 0.0, 1.0, float(cw.min()) - tol],
    ])


@njit(cache=True, nogil=True)
def _outside(boxes, node, shift, origin, perm, sign, planes):  # pragma: no cover - numba
    """Whether node's box lies wholly outside one of ``planes`` (camera space)."""
    lo = np.empty(3)
    hi = np.empty(3)
    for k in range(3):
        a = perm[k]
        p0 = sign[k] * (boxes[node, 0, a] - shift[a] - origin[a])
        p1 = sign[k] * (boxes[node, 1, a] - shift[a] - origin[a])
        lo[k] = min(p0, p1)
        hi[k] = max(p0, p1)
    if not lo[0] <= hi[0]:
        return True  # an empty node
    for f in range(planes.shape[0]):
        best = 0.0
        for k in range(3):
            c = planes[f, k]
            best += c * (hi[k] if c > 0.0 else lo[k])
        if best < planes[f, 3]:
            return True
    return False


@njit(cache=True, nogil=True)
def view_positions(tree, keep, origin, perm, sign, planes, out):  # pragma: no cover - numba
    """Write to ``out`` the positions t with ``keep[t]`` whose primitive the view's rays may
    meet (``Tree`` leaves not culled by ``planes``, and every loose primitive); returns how
    many. ``out`` must hold len(keep)."""
    boxes, order, leaf_size, pos_of_tri, loose_pos, shift = tree
    slots = boxes.shape[0] // 2
    n = 0
    stack = np.empty(64, dtype=np.int64)
    top = 0
    stack[0] = 1
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        if _outside(boxes, node, shift, origin, perm, sign, planes):
            continue
        if node < slots:
            stack[top] = 2 * node
            stack[top + 1] = 2 * node + 1
            top += 2
            continue
        leaf = node - slots
        for i in range(leaf * leaf_size, min((leaf + 1) * leaf_size, order.shape[0])):
            t = pos_of_tri[order[i]]
            if t >= 0 and keep[t]:
                out[n] = t
                n += 1
    for i in range(loose_pos.shape[0]):
        t = loose_pos[i]
        if keep[t]:
            out[n] = t
            n += 1
    return n


@njit(cache=True, nogil=True, parallel=True)
def views_positions(tree, keep, keep_of, origins, perms, signs, planes, off, out,
                    counts):  # pragma: no cover - numba
    """``view_positions`` for V views at once, in parallel: view v's positions, increasing,
    go to ``out[off[v]:off[v] + counts[v]]``. keep (F, n) bool per side plane, keep_of (V,)
    the plane of each view, origins (V, 3), perms (V, 3), signs (V, 3), planes (V, 5, 4);
    off (V + 1,) prefix sums of each view's kept positions, out (off[V],) int32, counts (V,)."""
    n = keep.shape[1]
    for v in prange(counts.shape[0]):
        seg = out[off[v]:off[v + 1]]
        k = view_positions(tree, keep[keep_of[v]], origins[v], perms[v], signs[v], planes[v],
                           seg)
        # The walk yields leaves in tree order; the lists need front-to-back order: a sort,
        # or marks read back in order where that reads fewer items than the sort compares.
        if k * np.log2(max(k, 2)) < n:
            seg[:k].sort()
        else:
            mark = np.zeros(n, dtype=np.bool_)
            for i in range(k):
                mark[seg[i]] = True
            j = 0
            for t in range(n):
                if mark[t]:
                    seg[j] = t
                    j += 1
        counts[v] = k
