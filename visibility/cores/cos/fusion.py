"""Edge adjacency for occluder fusion (paper Sec. 4.3): weld vertices by exact position.

Two triangles share an edge in the COS exactly when they share it in world space, so a triangle
soup fuses where its triangles touch once equal positions get one id. Welding is exact (bitwise
equal float64 coordinates): a tolerance would fuse triangles across a hairline gap, and a ray
through that gap would then count as blocked (a false negative).
"""

from __future__ import annotations

import weakref

import numpy as np

from visibility.scene import Scene

_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def weld_vertices(vertices: np.ndarray) -> np.ndarray:
    """(n,) int64 id per vertex, equal for bitwise-equal positions.

    Parameters
    ----------
    vertices : (n, 3) float64 positions, metres.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    n = len(v)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    # -0.0 and 0.0 are the same point.
    v = v + 0.0
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    s = v[order]
    new = np.empty(n, dtype=bool)
    new[0] = True
    new[1:] = np.any(s[1:] != s[:-1], axis=1)
    ids = np.empty(n, dtype=np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids


def scene_welded_ids(scene: Scene) -> tuple[np.ndarray, float]:
    """Welded vertex ids of ``scene`` (rest positions), cached per scene object.

    Returns
    -------
    ids : (n_vertices,) int64.
    seconds : time spent welding now (0.0 on a cache hit).
    """
    import time

    hit = _CACHE.get(scene)
    if hit is not None and hit[0] == scene.n_vertices:
        return hit[1], 0.0
    t0 = time.perf_counter()
    ids = weld_vertices(scene.vertices)
    _CACHE[scene] = (scene.n_vertices, ids)
    return ids, time.perf_counter() - t0


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
