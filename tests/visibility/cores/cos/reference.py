"""Dense sampled references for the COS core's zero-false-negative checks.

``sample_pvs`` draws stratified eyes inside the box; a conservative core must also hold what is
seen from the box's boundary, so the reference here adds the 8 corners, 12 edge midpoints and 6
face centres (each with its own random cube orientation). Every triangle seen in at least one
sample counts.
"""

from __future__ import annotations

import numpy as np

from visibility.ground_truth import sample_pvs
from visibility.raster import render_cubemap_ids
from visibility.raster.camera import random_rotation
from visibility.scene import Scene
from visibility.viewcells import Viewcell


def boundary_points(box: np.ndarray) -> np.ndarray:
    """(26, 3) corners, edge midpoints and face centres of a box (2, 3)."""
    lo, hi = box
    mid = 0.5 * (lo + hi)
    out = []
    for i in (0, 1, 2):
        for j in (0, 1, 2):
            for k in (0, 1, 2):
                if (i, j, k) == (1, 1, 1):
                    continue
                pick = [(lo, mid, hi)[c] for c in (i, j, k)]
                out.append([pick[0][0], pick[1][1], pick[2][2]])
    return np.array(out)


def dense_reference(scene: Scene, box: np.ndarray, n_points: int = 256, resolution: int = 256,
                    seed: int = 0) -> np.ndarray:
    """Sorted ids of every triangle seen from ``n_points`` stratified eyes in the box and from
    its 26 boundary points, in random orientations, at ``resolution`` px per cube face."""
    gt = sample_pvs(scene, Viewcell(box), n_points=n_points, resolution=resolution, seed=seed)
    seen = np.zeros(scene.n_triangles, dtype=bool)
    seen[gt.triangle_ids] = True
    rng = np.random.default_rng(seed + 7919)
    for p in boundary_points(np.asarray(box, dtype=np.float64)):
        ids = render_cubemap_ids(scene.vertices, scene.faces, p, resolution, random_rotation(rng),
                                 face_mask=scene.valid_faces)
        seen[ids[ids >= 0]] = True
    return np.flatnonzero(seen)


def cell_around(scene: Scene, size: float, index: int = 0, height: float | None = None
                ) -> np.ndarray:
    """(2, 3) a cube cell of side ``size`` centred at eye height over the ``index``-th cell of
    the scene's default viewcell grid (cycled)."""
    from visibility.viewcells import ViewcellGrid

    grid = ViewcellGrid.for_scene(scene)
    c = grid.cell(index % len(grid)).center
    if height is not None:
        c = c.copy()
        c[1] = height
    return np.stack([c - 0.5 * size, c + 0.5 * size])
