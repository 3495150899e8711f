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

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from visibility.scene import Scene
from visibility.scene_cache import per_scene
from visibility.topology import weld_vertices

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
    cut : triangles cut.
    """

    scene: Scene
    source: np.ndarray | None
    cut: int


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
        return TSplit(scene, None, 0)
    v = np.asarray(scene.vertices, dtype=np.float64)
    f = np.asarray(scene.faces, dtype=np.int64)
    valid = np.asarray(scene.valid_faces, dtype=bool)
    ids = weld_vertices(v)
    fv = np.flatnonzero(valid)
    # Each valid face's three edges, undirected by welded ids, found once each.
    corners = f[fv]
    fe = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2).reshape(-1, 2)
    wid = ids[fe]
    lo = np.minimum(wid[:, 0], wid[:, 1])
    hi = np.maximum(wid[:, 0], wid[:, 1])
    key, first, inv = np.unique(lo * (int(ids.max()) + 1) + hi, return_index=True,
                                return_inverse=True)
    undirected = fe[first]
    # A seam fusion cannot cross: an open edge (one triangle holds it) with the end of
    # another open edge on it. A corner touching an edge two triangles share (a building's
    # corner on a roof's ridge) leaves no silhouette to close, and cutting there only adds
    # triangles.
    open_edge = np.bincount(inv, minlength=len(undirected)) == 1
    ends = np.zeros(int(ids.max()) + 1, dtype=bool)
    ends[ids[undirected[open_edge]].ravel()] = True
    rows = np.flatnonzero(open_edge)
    e, point, t = edge_points(v, undirected[rows], ids, ends)
    e = rows[e]
    keep = _along(v, ids, undirected, open_edge, e, point)
    e, point, t = e[keep], point[keep], t[keep]
    if len(e) == 0:
        return TSplit(scene, None, 0)
    starts = np.searchsorted(e, np.arange(len(undirected) + 1))
    # Per face edge (3 per valid face): its points, in the face edge's own direction.
    fe_edge = inv.reshape(-1, 3)
    has = (starts[fe_edge + 1] - starts[fe_edge]).sum(axis=1) > 0
    if has.sum() < MIN_CUT_SHARE * len(fv):
        return TSplit(scene, None, 0)
    new_v = [v]
    nv = len(v)
    faces = [f[~np.isin(np.arange(len(f)), fv[has])]]
    src = [np.flatnonzero(~np.isin(np.arange(len(f)), fv[has]))]
    out_f: list[list[int]] = []
    out_s: list[int] = []
    cents = []
    for row in np.flatnonzero(has):
        tri = corners[row]
        poly: list[int] = []
        for k in range(3):
            ue = fe_edge[row, k]
            poly.append(int(tri[k]))
            s0, s1 = starts[ue], starts[ue + 1]
            if s1 == s0:
                continue
            pts = point[s0:s1]
            # The undirected edge runs from ``undirected[ue, 0]``; reverse when this face's
            # edge runs the other way.
            if ids[undirected[ue, 0]] != ids[tri[k]]:
                pts = pts[::-1]
            poly.extend(int(x) for x in pts)
        c = nv + len(cents)
        cents.append(v[tri].mean(axis=0))
        face_id = int(fv[row])
        for j in range(len(poly)):
            out_f.append([poly[j], poly[(j + 1) % len(poly)], c])
            out_s.append(face_id)
    new_v.append(np.asarray(cents).reshape(-1, 3))
    faces.append(np.asarray(out_f, dtype=np.int64).reshape(-1, 3))
    src.append(np.asarray(out_s, dtype=np.int64))
    faces_all = np.concatenate(faces)
    src_all = np.concatenate(src)
    cut = Scene(vertices=np.concatenate(new_v), faces=faces_all,
                object_ids=np.asarray(scene.object_ids)[src_all],
                colors=np.asarray(scene.colors)[src_all], name=scene.name,
                sphere_centers=scene.sphere_centers, sphere_radii=scene.sphere_radii,
                sphere_colors=scene.sphere_colors, walk=scene.walk,
                object_names=scene.object_names, meta=dict(scene.meta))
    return TSplit(cut, src_all, int(has.sum()))


def scene_t_split(scene: Scene) -> tuple[TSplit, float]:
    """``split_t_junctions`` cached per scene object; (split, seconds spent now)."""
    import time

    t0 = time.perf_counter()
    split, built = per_scene(scene, "topology/tsplit", split_t_junctions)
    return split, (time.perf_counter() - t0) if built else 0.0
