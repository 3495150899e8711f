"""T-junctions: triangles cut where a corner of another triangle lies on one of their edges.

A seam where one triangle's edge runs along two edges of its neighbours, with the neighbours'
shared corner on the long edge (a T-junction: no vertex pair in common), is closed in exact
geometry. Occluder fusion joins triangles across shared welded edges only, so such a seam stays
on the silhouette of both sides and a surface split by it hides only what either part hides
alone (``cos``: a wall of a game level built of brushes, seen from a cell metres wide).
Cutting the long-edged triangle at the corners on its edges makes the seam a run of shared
edges: the polygon (its corners and, in order, the points on each edge) is fanned from its
centroid, so the pieces share their inner edges exactly and tile the triangle.

A point counts as lying on an edge when it is within ``TOL_ULPS`` units in the last place of
the coordinates' magnitude of the segment, strictly between its ends: rounding, not a gap. A
gap any wider (a slit between two walls) stays open: nothing is welded or moved.

Conventions: Y-up, right-handed, metres; triangle ids are row indices of ``scene.faces``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from visibility.scene import Scene
from visibility.scene_cache import per_scene
from visibility.topology import build_edges, scene_welded_ids

#: How far off an edge a corner may lie and count as on it: this many units in the last place
#: of the largest coordinate magnitude of the edge and the corner.
TOL_ULPS = 64.0
#: Fewer seamed triangles than this share of the valid ones are left as they are: the cut scene
#: is a scene of its own, whose hierarchy and closed parts are built again (a 1M-triangle
#: interior with a handful of seams would solve without its hierarchy for a while).
MIN_CUT_SHARE = 1e-3


@dataclass(frozen=True)
class TSplit:
    """A scene with its T-junctions cut.

    scene : the cut scene (the given one itself when it has none).
    source : (m',) int64 id of the original triangle each triangle of ``scene`` comes from
        (None when nothing was cut).
    """

    scene: Scene
    source: np.ndarray | None

    @property
    def cut(self) -> int:
        """Triangles of the original scene that were cut (each into 4 or more)."""
        if self.source is None:
            return 0
        return int(np.count_nonzero(np.bincount(self.source) > 1))


def edge_points(vertices: np.ndarray, edges: np.ndarray, ids: np.ndarray,
                among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Welded points lying on edges, strictly between their ends.

    Parameters
    ----------
    vertices : (n, 3) float64 positions, metres.
    edges : (e, 2) int64 vertex rows of each edge's ends.
    ids : (n,) int64 welded id per vertex (``topology.weld_vertices``).
    among : optional (ids.max() + 1,) bool, the welded points to look for (default all).

    Returns
    -------
    edge : (k,) int64 edge row of each find, sorted by edge, then by ``t``.
    point : (k,) int64 a vertex row of the point.
    t : (k,) float64 where along the edge it lies (0 at ``edges[:, 0]``, 1 at the other end).
    """
    v = np.asarray(vertices, dtype=np.float64)
    rep = np.zeros(int(ids.max()) + 1 if len(ids) else 0, dtype=np.int64)
    rep[ids] = np.arange(len(ids))
    uniq = rep if among is None else rep[np.flatnonzero(among)]  # a row per welded point
    pts = v[uniq]
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(edges) == 0 or len(pts) < 3:
        return empty
    a = v[edges[:, 0]]
    b = v[edges[:, 1]]
    d = b - a
    length = np.linalg.norm(d, axis=1)
    mag = np.maximum(np.abs(a).max(axis=1), np.abs(b).max(axis=1))
    tol = TOL_ULPS * np.spacing(np.maximum(mag, 1.0))
    tree = cKDTree(pts)
    near = tree.query_ball_point(0.5 * (a + b), 0.5 * length + tol, workers=-1,
                                 return_sorted=False)
    counts = np.fromiter((len(x) for x in near), dtype=np.int64, count=len(near))
    if counts.sum() == 0:
        return empty
    e = np.repeat(np.arange(len(edges)), counts)
    p = np.concatenate([np.asarray(x, dtype=np.int64) for x in near if len(x)])
    wa = ids[edges[e, 0]]
    wb = ids[edges[e, 1]]
    wp = ids[uniq[p]]
    keep = (wp != wa) & (wp != wb) & (length[e] > 0)
    e, p = e[keep], p[keep]
    x = pts[p]
    rel = x - a[e]
    t = np.einsum("ij,ij->i", rel, d[e]) / (length[e] ** 2)
    off = rel - t[:, None] * d[e]
    dist = np.linalg.norm(off, axis=1)
    lim = np.maximum(tol[e], TOL_ULPS * np.spacing(np.maximum(np.abs(x).max(axis=1), 1.0)))
    inside = (dist <= lim) & (t * length[e] > lim) & ((1.0 - t) * length[e] > lim)
    e, p, t = e[inside], p[inside], t[inside]
    order = np.lexsort((t, e))
    return e[order], uniq[p[order]], t[order]


def _along(v: np.ndarray, ids: np.ndarray, edges: np.ndarray, open_edge: np.ndarray,
           e: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(k,) bool per find of ``edge_points``: whether an open edge at the point runs along the
    edge it lies on (its other end on the same line): the seam of a T-junction. A corner that
    merely touches the edge from another direction (a pole's foot on a kerb) closes nothing."""
    oe = edges[open_edge]
    wa, wb = ids[oe[:, 0]], ids[oe[:, 1]]
    ends = np.concatenate([wa, wb])
    other = np.concatenate([oe[:, 1], oe[:, 0]])
    order = np.argsort(ends, kind="stable")
    ends, other = ends[order], other[order]
    wp = ids[point]
    lo = np.searchsorted(ends, wp, side="left")
    hi = np.searchsorted(ends, wp, side="right")
    deg = hi - lo
    find = np.repeat(np.arange(len(e)), deg)
    slot = np.arange(deg.sum()) - np.repeat(np.cumsum(deg) - deg, deg) + np.repeat(lo, deg)
    y = v[other[slot]]
    a = v[edges[e[find], 0]]
    d = v[edges[e[find], 1]] - a
    rel = y - a
    off = rel - (np.einsum("ij,ij->i", rel, d) / np.einsum("ij,ij->i", d, d))[:, None] * d
    mag = np.maximum(np.abs(a).max(axis=1), np.abs(y).max(axis=1))
    on_line = np.linalg.norm(off, axis=1) <= TOL_ULPS * np.spacing(np.maximum(mag, 1.0))
    out = np.zeros(len(e), dtype=bool)
    out[find[on_line]] = True
    return out


def split_t_junctions(scene: Scene) -> TSplit:
    """The scene with every valid static triangle cut at the welded corners that lie on its
    edges (module docstring); spheres, colours and objects carried over. A keyframed scene
    is returned whole: a corner on an edge at rest need not stay on it; so is one where fewer
    than ``MIN_CUT_SHARE`` of the valid triangles hold a seam."""
    if scene.states is not None and len(scene.states) > 1:
        return TSplit(scene, None)
    v = np.asarray(scene.vertices, dtype=np.float64)
    f = np.asarray(scene.faces, dtype=np.int64)
    ids, _ = scene_welded_ids(scene)
    fv = np.flatnonzero(np.asarray(scene.valid_faces, dtype=bool))
    edges = build_edges(v, f, fv, ids)
    # A seam fusion cannot cross: an open edge (one triangle holds it, in its own direction:
    # ``Edges.vert``) with the end of another open edge on it, running along it. A corner
    # touching an edge two triangles share (a building's corner on a roof's ridge) leaves no
    # silhouette to close, and cutting there only adds triangles.
    open_edge = edges.face[:, 1] < 0
    ends = np.zeros(int(ids.max()) + 1 if len(ids) else 0, dtype=bool)
    ends[ids[edges.vert[open_edge]].ravel()] = True
    rows = np.flatnonzero(open_edge)
    e, point, t = edge_points(v, edges.vert[rows], ids, ends)
    e = rows[e]
    keep = _along(v, ids, edges.vert, open_edge, e, point)
    e, point, t = e[keep], point[keep], t[keep]
    face = edges.face[e, 0]
    cut = np.unique(face)
    if len(cut) == 0 or len(cut) < MIN_CUT_SHARE * len(fv):
        return TSplit(scene, None)
    # Each cut triangle's outline: its corners at 0, 1, 2 and the points on its edge k at
    # k + t (t runs along the triangle's own direction of that edge), fanned from a new
    # vertex at its centroid.
    corner = f[cut]
    slot = np.searchsorted(cut, face)
    k = np.argmax(ids[corner[slot]] == ids[edges.vert[e, 0]][:, None], axis=1)
    owner = np.concatenate([np.repeat(np.arange(len(cut)), 3), slot])
    key = np.concatenate([np.tile([0.0, 1.0, 2.0], len(cut)), k + t])
    vert = np.concatenate([corner.ravel(), point])
    order = np.lexsort((key, owner))
    owner, vert = owner[order], vert[order]
    start = np.searchsorted(owner, np.arange(len(cut)))
    size = np.diff(np.append(start, len(owner)))
    nxt = np.arange(len(owner)) + 1
    last = start + size - 1
    nxt[last] = start
    fan = np.stack([vert, vert[nxt], len(v) + owner], axis=1)
    kept = np.setdiff1d(np.arange(len(f)), cut)
    src = np.concatenate([kept, cut[owner]])
    out = Scene(vertices=np.concatenate([v, v[corner].mean(axis=1)]),
                faces=np.concatenate([f[kept], fan]),
                object_ids=np.asarray(scene.object_ids)[src],
                colors=np.asarray(scene.colors)[src], name=scene.name,
                sphere_centers=scene.sphere_centers, sphere_radii=scene.sphere_radii,
                sphere_colors=scene.sphere_colors, walk=scene.walk,
                object_names=scene.object_names, meta=dict(scene.meta))
    return TSplit(out, src)


def scene_t_split(scene: Scene) -> tuple[TSplit, float]:
    """``split_t_junctions`` cached per scene object; (split, seconds spent now)."""
    t0 = time.perf_counter()
    split, built = per_scene(scene, "topology/tsplit", split_t_junctions)
    return split, (time.perf_counter() - t0) if built else 0.0
