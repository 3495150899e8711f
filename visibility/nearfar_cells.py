"""Which viewcells need a far cubemap, decided for all cells at once.

``visibility.nearfar.needs_cubemap`` answers one cell centre O with a pass over every face. A
server that reports, per scene, how many cells have static geometry beyond r2 asks it for every
cell; this module answers all centres together instead. A cell needs a cubemap when some valid
static face has a corner at horizontal distance ρ >= r2 from O, i.e. when the farthest static
corner is at least r2 away. The farthest point of a set from O is a vertex of the set's convex
hull (ρ is convex), so the (usually few dozen) hull corners of the static corners in the XZ plane
stand for all of them: an (n cells x h hull corners) distance table, no per-face work per cell.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from visibility.scene import Scene


def static_corners_xz(scene: Scene) -> np.ndarray:
    """(k, 2) float64 unique XZ positions (metres) of the corners of the scene's valid static
    faces: the faces ``visibility.nearfar.split_ids`` may bake (a face with a corner that moves
    between keyframes is dynamic and never baked)."""
    faces = scene.faces[scene.valid_faces]
    if scene.states is not None and scene.states.shape[0] > 1:
        moving = np.any(scene.states != scene.states[:1], axis=(0, 2))
        faces = faces[~np.any(moving[faces], axis=1)]
    if not len(faces):
        return np.zeros((0, 2))
    used = np.unique(faces.reshape(-1))
    return np.unique(scene.vertices[used][:, [0, 2]], axis=0)


def hull_corners_xz(points: np.ndarray) -> np.ndarray:
    """The rows of ``points`` (k, 2) on their convex hull: every farthest point from any centre
    is among them. Degenerate sets (fewer than 3 points, all on a line) are returned whole or
    reduced with a joggled hull, whose vertices are still rows of ``points``."""
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
