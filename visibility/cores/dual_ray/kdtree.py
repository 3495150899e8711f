"""The kd-tree the dual-ray core traverses: a 2D (XZ) kd-tree over the scene's triangles.

The occluders are 2.5D, so cell-to-node visibility depends on a node's footprint and top
height only (``dual_space``); splitting in Y would add nodes without adding occlusion. A
triangle sits in every leaf whose XZ region its bounds overlap, so a node's box (its region
clipped to its triangles' bounds, their full height range) holds every part of its triangles
that lies in its region. Moving triangles take part over the bounds of every keyframe (their
sweep: positions are piecewise linear in time), spheres are left to the caller.

Built once per scene (``scene_kdtree``, cached with the scene).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from visibility.cores.dual_ray.cache import per_scene
from visibility.scene import Scene

#: Most triangles a leaf holds before it is split (more leaves: finer PVS, more tests).
LEAF_SIZE = 48
#: Deepest split; leaves stop here whatever they hold.
MAX_DEPTH = 28
#: A split whose children hold together more than this share of the parent's triangles (large
#: triangles straddling it) is not made.
MAX_DUPLICATION = 1.7


@dataclass
class KdTree:
    """A 2D kd-tree over triangle bounds.

    Attributes
    ----------
    lo, hi : (n_nodes, 3) float64 node boxes [min, max], metres (tight on the node's triangles,
        clipped in X and Z to the node's region).
    child : (n_nodes, 2) int64 children, -1 for a leaf.
    depth : (n_nodes,) int64.
    item_start : (n_nodes + 1,) int64 CSR offsets into ``items`` (leaves only; inner nodes
        hold an empty range).
    items : (k,) int64 triangle ids of the leaves, a triangle in every leaf it overlaps.
    tri_lo, tri_hi : (n_triangles, 3) float64 bounds of every triangle (swept for moving ones;
        NaN for invalid faces, which are in no leaf).
    build_seconds : time the build took.
    """

    lo: np.ndarray
    hi: np.ndarray
    child: np.ndarray
    depth: np.ndarray
    item_start: np.ndarray
    items: np.ndarray
    tri_lo: np.ndarray
    tri_hi: np.ndarray
    build_seconds: float

    @property
    def n_nodes(self) -> int:
        return int(len(self.lo))

    @property
    def n_leaves(self) -> int:
        return int(np.count_nonzero(self.child[:, 0] < 0))

    def leaf_items(self, node: int) -> np.ndarray:
        """Triangle ids of leaf ``node``."""
        return self.items[self.item_start[node]:self.item_start[node + 1]]


def triangle_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (n_triangles, 3) float64 bounds of every face over every keyframe; NaN rows for
    invalid faces."""
    m = scene.n_triangles
    lo = np.full((m, 3), np.nan)
    hi = np.full((m, 3), np.nan)
    valid = np.flatnonzero(scene.valid_faces)
    if len(valid) == 0:
        return lo, hi
    f = scene.faces[valid]
    if scene.states is not None and scene.states.shape[0] > 1:
        pts = scene.states[:, f]  # (k, t, 3, 3)
        lo[valid] = pts.min(axis=(0, 2))
        hi[valid] = pts.max(axis=(0, 2))
    else:
        pts = scene.vertices[f]
        lo[valid] = pts.min(axis=1)
        hi[valid] = pts.max(axis=1)
    # A moving face's keyframes may hold non-finite positions the rest pose does not.
    bad = ~(np.all(np.isfinite(lo), axis=1) & np.all(np.isfinite(hi), axis=1))
    lo[bad] = np.nan
    hi[bad] = np.nan
    return lo, hi


def build_kdtree(scene: Scene, leaf_size: int = LEAF_SIZE) -> KdTree:
    """Build the kd-tree of ``scene`` (module docstring). O(n log n) numpy work per level."""
    t0 = time.perf_counter()
    tlo, thi = triangle_bounds(scene)
    ids = np.flatnonzero(np.all(np.isfinite(tlo), axis=1)).astype(np.int64)
    lo_l: list[np.ndarray] = []
    hi_l: list[np.ndarray] = []
    child_l: list[list[int]] = []
    depth_l: list[int] = []
    leaf_of: list[np.ndarray | None] = []
    cx = 0.5 * (tlo[:, 0] + thi[:, 0])
    cz = 0.5 * (tlo[:, 2] + thi[:, 2])
    # Stack of (triangle ids, region lo xz, region hi xz, depth, parent slot).
    if len(ids):
        region = (np.array([tlo[ids, 0].min(), tlo[ids, 2].min()]),
                  np.array([thi[ids, 0].max(), thi[ids, 2].max()]))
    else:
        region = (np.zeros(2), np.zeros(2))
    stack: list[tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int]] = [
        (ids, region[0], region[1], 0, -1, 0)]
    while stack:
        idx, rlo, rhi, depth, parent, side = stack.pop()
        node = len(lo_l)
        if parent >= 0:
            child_l[parent][side] = node
        if len(idx):
            blo = np.array([max(tlo[idx, 0].min(), rlo[0]), tlo[idx, 1].min(),
                            max(tlo[idx, 2].min(), rlo[1])])
            bhi = np.array([min(thi[idx, 0].max(), rhi[0]), thi[idx, 1].max(),
                            min(thi[idx, 2].max(), rhi[1])])
        else:
            blo = np.array([rlo[0], 0.0, rlo[1]])
            bhi = np.array([rhi[0], 0.0, rhi[1]])
        lo_l.append(blo)
        hi_l.append(bhi)
        child_l.append([-1, -1])
        depth_l.append(depth)
        leaf_of.append(idx)
        if len(idx) <= leaf_size or depth >= MAX_DEPTH:
            continue
        ext = bhi[[0, 2]] - blo[[0, 2]]
        axis = 0 if ext[0] >= ext[1] else 1
        col = 0 if axis == 0 else 2
        c = cx[idx] if axis == 0 else cz[idx]
        pos = float(np.median(c))
        a_lo, a_hi = float(blo[col]), float(bhi[col])
        if not (a_lo < pos < a_hi):
            pos = 0.5 * (a_lo + a_hi)
            if not (a_lo < pos < a_hi):
                continue
        left = idx[tlo[idx, col] <= pos]
        right = idx[thi[idx, col] >= pos]
        if len(left) + len(right) > MAX_DUPLICATION * len(idx) or \
                len(left) == len(idx) or len(right) == len(idx):
            continue
        leaf_of[node] = None
        llo, lhi = blo[[0, 2]].copy(), bhi[[0, 2]].copy()
        lhi[axis] = pos
        rlo2, rhi2 = blo[[0, 2]].copy(), bhi[[0, 2]].copy()
        rlo2[axis] = pos
        stack.append((right, rlo2, rhi2, depth + 1, node, 1))
        stack.append((left, llo, lhi, depth + 1, node, 0))
    n = len(lo_l)
    counts = np.array([0 if leaf_of[i] is None else len(leaf_of[i]) for i in range(n)],
                      dtype=np.int64)
    start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    items = (np.concatenate([a for a in leaf_of if a is not None]).astype(np.int64)
             if n else np.zeros(0, np.int64))
    return KdTree(np.array(lo_l).reshape(-1, 3), np.array(hi_l).reshape(-1, 3),
                  np.array(child_l, dtype=np.int64).reshape(-1, 2),
                  np.array(depth_l, dtype=np.int64), start, items, tlo, thi,
                  time.perf_counter() - t0)


def scene_kdtree(scene: Scene) -> tuple[KdTree, float]:
    """The scene's kd-tree, built on first use and cached with the scene.

    Returns
    -------
    tree : the ``KdTree``.
    seconds : build time spent by this call (0.0 when it came from the cache).
    """
    tree, built = per_scene(scene, "kdtree", build_kdtree)
    return tree, (tree.build_seconds if built else 0.0)
