"""Which viewcells need a far cubemap, decided for all cells at once, and which cells share one.

``visibility.nearfar.needs_cubemap`` answers one cell centre O with a pass over every face. A
server that reports, per scene, how many cells have static geometry beyond r2 asks it for every
cell; this module answers all centres together instead. A cell needs a cubemap when some valid
static face has a corner at horizontal distance ρ >= r2 from O, i.e. when the farthest static
corner is at least r2 away. The farthest point of a set from O is a vertex of the set's convex
hull (ρ is convex), so the (usually few dozen) hull corners of the static corners in the XZ plane
stand for all of them: an (n cells x h hull corners) distance table, no per-face work per cell.

``cubemap_anchors`` groups cells into blocks that share one cubemap: the near-far paper's
morph exists so that a cubemap stays usable while the eye walks tens of metres from its centre
O; with one cubemap per small cell the eye never gets far from O, and every cell costs a bake
and a download.
"""

from __future__ import annotations

import numpy as np

from visibility.scene import Scene, moving_faces
from visibility.viewcells import ViewcellGrid


def static_corners_xz(scene: Scene) -> np.ndarray:
    """(k, 2) float64 unique XZ positions (metres) of the corners of the scene's valid static
    faces: the faces ``visibility.nearfar.split_ids`` may bake (a face with a corner that moves
    between keyframes is dynamic and never baked)."""
    faces = scene.faces[scene.valid_faces & ~moving_faces(scene)]
    if not len(faces):
        return np.zeros((0, 2))
    used = np.unique(faces.reshape(-1))
    return np.unique(scene.vertices[used][:, [0, 2]], axis=0)


def hull_corners_xz(points: np.ndarray) -> np.ndarray:
    """The rows of ``points`` (k, 2) on their convex hull: every farthest point from any centre
    is among them. Degenerate sets (fewer than 3 points, all on a line) are returned whole or
    reduced with a joggled hull, whose vertices are still rows of ``points``."""
    # Imported here, not with the module: scipy.spatial weighs on every server's start-up,
    # and most never reach this (a near-far cell whose corners are more than 16 points).
    from scipy.spatial import ConvexHull, QhullError

    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(p) <= 16:
        return p
    try:
        return p[ConvexHull(p).vertices]
    except QhullError:
        # Collinear or coincident points: a joggled hull still names the extreme ones.
        return p[ConvexHull(p, qhull_options="QJ").vertices]


def farthest_static_distance(scene: Scene, centers: np.ndarray) -> np.ndarray:
    """(n,) float64 largest horizontal distance ρ (metres) from each of ``centers`` (n, 3) to a
    corner of a valid static face; -inf for a scene without static faces."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    hull = hull_corners_xz(static_corners_xz(scene))
    if not len(hull):
        return np.full(len(c), -np.inf)
    out = np.empty(len(c))
    # Rows in blocks keep the (cells x hull corners) table small for huge grids.
    for i in range(0, len(c), 4096):
        blk = c[i:i + 4096]
        rho = np.hypot(hull[None, :, 0] - blk[:, None, 0], hull[None, :, 1] - blk[:, None, 2])
        out[i:i + 4096] = rho.max(axis=1)
    return out


def cells_needing_cubemap(scene: Scene, centers: np.ndarray, r2: float) -> np.ndarray:
    """(n,) bool: whether ``visibility.nearfar.needs_cubemap`` holds for each cubemap centre of
    ``centers`` (n, 3) with far radius ``r2`` (metres): some static corner at ρ >= r2."""
    return farthest_static_distance(scene, centers) >= float(r2)


def cubemap_anchors(grid: ViewcellGrid, block: int) -> np.ndarray:
    """(cells,) int64: for each cell, the cell whose centre is the cubemap centre O it shares.

    Cells are grouped by ``block`` x ``block`` grid columns and by level (the cell's rank among
    the levels of its column, lowest first, so floors of a building stay apart); each group's
    anchor is its member nearest the members' mean centre, so O always lies in a walkable cell
    (free space at eye height), never inside a building an L-shaped group wraps around. With
    ``block`` 1 every cell is its own anchor. The anchor's own split and cubemap are the
    group's, so a server caches them per anchor cell exactly as per cell.
    """
    n = len(grid)
    block = int(block)
    if block < 1:
        raise ValueError(f"block must be a positive number of cells, got {block}")
    if block == 1 or n == 0:
        return np.arange(n, dtype=np.int64)
    ij = np.asarray(grid.ij, dtype=np.int64)
    # Rank of each cell among the levels of its column (floors ascending).
    order = np.lexsort((grid.floor, ij[:, 1], ij[:, 0]))
    col = ij[order]
    first = np.ones(n, dtype=bool)
    first[1:] = np.any(col[1:] != col[:-1], axis=1)
    starts = np.maximum.accumulate(np.where(first, np.arange(n), 0))
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n) - starts
    keys = np.stack([ij[:, 0] // block, ij[:, 1] // block, rank], axis=1)
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = group.reshape(-1)
    centres = grid.boxes.mean(axis=1)
    n_groups = int(group.max()) + 1
    counts = np.bincount(group, minlength=n_groups).astype(np.float64)
    mean = np.stack([np.bincount(group, centres[:, a], n_groups) for a in range(3)], axis=1)
    mean /= counts[:, None]
    dist = np.sum((centres - mean[group]) ** 2, axis=1)
    # Per group the nearest member (ties: the lowest id), found with one sort.
    by = np.lexsort((np.arange(n), dist, group))
    lead = np.ones(n, dtype=bool)
    lead[1:] = group[by[1:]] != group[by[:-1]]
    anchor_of_group = np.empty(n_groups, dtype=np.int64)
    anchor_of_group[group[by[lead]]] = by[lead]
    return anchor_of_group[group]
