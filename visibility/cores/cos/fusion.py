"""Edge adjacency for occluder fusion (paper Sec. 4.3): weld vertices by exact position.

Two triangles share an edge in the COS exactly when they share it in world space, so a triangle
soup fuses where its triangles touch once equal positions get one id. Welding is exact (bitwise
equal float64 coordinates): a tolerance would fuse triangles across a hairline gap, and a ray
through that gap would then count as blocked (a false negative).
"""

from __future__ import annotations

import numpy as np

from visibility.scene import Scene
from visibility.scene_cache import per_scene
from visibility.topology import scene_welded_ids


def _open_edges(scene: Scene) -> tuple[np.ndarray, np.ndarray, int]:
    """The scene's edges as welded-id pairs (valid faces only, corner k -> k + 1, (3m, 2)),
    which of them belong to one triangle only, and how many distinct edges there are; built
    once per scene for both shares."""
    return per_scene(scene, "cos/open_edges", _build_open_edges)[0]


def _build_open_edges(scene: Scene) -> tuple[np.ndarray, np.ndarray, int]:
    ids, _ = scene_welded_ids(scene)
    f = ids[np.asarray(scene.faces)[np.asarray(scene.valid_faces)]]
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    if len(e) == 0:
        return e, np.zeros(0, dtype=bool), 0
    _, inv, counts = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True,
                               return_counts=True)
    return e, counts[inv.ravel()] == 1, len(counts)


def open_edge_share(scene: Scene) -> float:
    """Share of the scene's edges (after welding, valid faces only) that belong to one triangle
    only: open borders and T-junctions, where occluders cannot fuse (a wall split at a
    T-junction keeps a silhouette across its face). 0 for a closed, welded mesh."""
    _, one, distinct = _open_edges(scene)
    # An open edge is used once, so its uses count the distinct open edges.
    return float(one.sum() / distinct) if distinct else 0.0


def t_junction_share(scene: Scene) -> float:
    """Share of the scene's open edges (``open_edge_share``) that run along another open edge
    held the opposite way, overlapping it on one line: T-junctions, where two triangles meet
    with no gap but share no vertex pair, so occluder fusion (welded edges) cannot join them
    and a silhouette stays across a continuous surface. Lines match when directions and feet
    agree to 1e-6 (relative to the scene's size); 0.0 when no edge is open."""
    e, one, _ = _open_edges(scene)
    e = e[one]
    if len(e) == 0:
        return 0.0
    ids, _ = scene_welded_ids(scene)
    rep = np.zeros(int(ids.max()) + 1, dtype=np.int64)
    rep[ids] = np.arange(len(ids))
    v = np.asarray(scene.vertices, dtype=np.float64)
    a, b = v[rep[e[:, 0]]], v[rep[e[:, 1]]]
    scale = max(float(np.abs(v).max()), 1.0)
    d = b - a
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # One direction per line: the largest component positive; the edge's sign says which way
    # it runs along it.
    big = np.argmax(np.abs(d), axis=1)
    sign = np.sign(d[np.arange(len(d)), big])
    d *= sign[:, None]
    ta = np.einsum("ij,ij->i", a, d)
    tb = np.einsum("ij,ij->i", b, d)
    foot = a - ta[:, None] * d
    key = np.concatenate([np.round(d * 1e6), np.round(foot / scale * 1e6)], axis=1)
    _, line = np.unique(key, axis=0, return_inverse=True)
    line = line.ravel()
    order = np.argsort(line, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(line[order]) != 0])
    ends = np.r_[starts[1:], len(order)]
    lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
    eps = 1e-9 * scale
    joined = np.zeros(len(e), dtype=bool)
    # Only lines holding two open edges or more can hold a T-junction.
    for k in np.flatnonzero(ends - starts >= 2):
        m = order[starts[k]:ends[k]]
        # Opposite ways and overlapping by more than rounding.
        opp = sign[m][:, None] != sign[m][None, :]
        over = (np.minimum(hi[m][:, None], hi[m][None, :])
                - np.maximum(lo[m][:, None], lo[m][None, :])) > eps
        joined[m] = (opp & over).any(axis=1)
    return float(joined.mean())
