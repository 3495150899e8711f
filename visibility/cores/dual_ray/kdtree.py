"""The kd-tree the dual-ray core traverses, over the scene's triangles.

Cell-to-node visibility depends on a node's footprint, top and bottom (``dual_space``): a lower
top is a lower ceiling, so tall nodes are split in Y too (heights weigh double when the axis
is chosen). A triangle sits in every leaf whose region its bounds overlap, so a node's box (its
region clipped to its triangles' bounds) holds every part of its triangles that lies in its
region. Moving triangles take part over the bounds of every keyframe (their
sweep: positions are piecewise linear in time), spheres are left to the caller.

Built once per scene (``scene_kdtree``, cached with the scene).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from visibility.scene import Scene
from visibility.scene_cache import per_scene

#: Most triangles a leaf holds before it is split (more leaves: finer PVS, more tests).
LEAF_SIZE = 48
#: Deepest split; leaves stop here whatever they hold.
MAX_DEPTH = 28
#: Weight of a node's height against its width when the split axis is chosen.
Y_WEIGHT = 2.0
#: A split whose children hold together more than this share of the parent's triangles (large
#: triangles straddling it) is not made.
MAX_DUPLICATION = 1.7


@dataclass
class KdTree:
    """A kd-tree over triangle bounds.

    Attributes
    ----------
    lo, hi : (n_nodes, 3) float64 node boxes [min, max], metres (tight on the node's triangles,
        clipped to the node's region).
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
    centre = 0.5 * (tlo + thi)
    if len(ids):
        region = (tlo[ids].min(axis=0), thi[ids].max(axis=0))
    else:
        region = (np.zeros(3), np.zeros(3))
    # Stack of (triangle ids, region lo, region hi, depth, parent, side).
    stack: list[tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int]] = [
        (ids, region[0], region[1], 0, -1, 0)]
    while stack:
        idx, rlo, rhi, depth, parent, side = stack.pop()
        node = len(lo_l)
        if parent >= 0:
            child_l[parent][side] = node
        if len(idx):
            blo = np.maximum(tlo[idx].min(axis=0), rlo)
            bhi = np.minimum(thi[idx].max(axis=0), rhi)
        else:
            blo, bhi = rlo.copy(), rlo.copy()
        lo_l.append(blo)
        hi_l.append(bhi)
        child_l.append([-1, -1])
        depth_l.append(depth)
        leaf_of.append(idx)
        if len(idx) <= leaf_size or depth >= MAX_DEPTH:
            continue
        # Split the longest side; heights count double: a lower box has a lower ceiling
        # (``dual_space``), so splitting tall nodes in Y pays in occlusion.
        ext = (bhi - blo) * np.array([1.0, Y_WEIGHT, 1.0])
        for axis in np.argsort(-ext):
            pos = float(np.median(centre[idx, axis]))
            a_lo, a_hi = float(blo[axis]), float(bhi[axis])
            if not (a_lo < pos < a_hi):
                pos = 0.5 * (a_lo + a_hi)
                if not (a_lo < pos < a_hi):
                    continue
            left = idx[tlo[idx, axis] <= pos]
            right = idx[thi[idx, axis] >= pos]
            if len(left) + len(right) > MAX_DUPLICATION * len(idx) or \
                    len(left) == len(idx) or len(right) == len(idx):
                continue
            leaf_of[node] = None
            llo, lhi = blo.copy(), bhi.copy()
            lhi[axis] = pos
            rlo2, rhi2 = blo.copy(), bhi.copy()
            rlo2[axis] = pos
            stack.append((right, rlo2, rhi2, depth + 1, node, 1))
            stack.append((left, llo, lhi, depth + 1, node, 0))
            break
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
