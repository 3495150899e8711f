"""Edge adjacency for occluder fusion (paper Sec. 4.3): weld vertices by exact position.

Two triangles share an edge in the COS exactly when they share it in world space, so a triangle
soup fuses where its triangles touch once equal positions get one id. Welding is exact (bitwise
equal float64 coordinates): a tolerance would fuse triangles across a hairline gap, and a ray
through that gap would then count as blocked (a false negative).
"""

from __future__ import annotations

import numpy as np

from visibility.scene import Scene
from visibility.topology import scene_welded_ids


def open_edge_share(scene: Scene) -> float:
    """Share of the scene's edges (after welding, valid faces only) that belong to one triangle
    only: open borders and T-junctions, where occluders cannot fuse (a wall split at a
    T-junction keeps a silhouette across its face). 0 for a closed, welded mesh."""
    ids, _ = scene_welded_ids(scene)
    f = ids[np.asarray(scene.faces)[np.asarray(scene.valid_faces)]]
    if len(f) == 0:
        return 0.0
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return float(np.mean(counts == 1))
