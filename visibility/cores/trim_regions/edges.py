"""Edge adjacency of a triangle soup (paper Sec. 3.6: silhouettes are the edges between front
and back faces; the only thing the method needs of the scene's topology).

Vertices are welded by exact position first (``cos.fusion.weld_vertices``), so a soup whose
triangles merely touch still shares its edges. An edge with one triangle (a border) or more
than two (non-manifold) is always a silhouette candidate: trimming there is conservative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visibility.cores.cos.fusion import weld_vertices


@dataclass
class Edges:
    """Unique edges of a set of triangles.

    Attributes
    ----------
    vert : (E, 2) int64 vertex rows (of the scene's vertex array) of the two end points.
    face : (E, 2) int64 the adjacent triangles' ids (-1 where the edge has only one).
    opp : (E, 2) int64 vertex row of each adjacent triangle's corner off the edge (-1: none).
    many : (E,) bool, True for non-manifold edges (three or more triangles): trimmed on both
        sides.
    paired : (E,) bool, True for an edge of exactly two triangles that hold it in opposite
        directions (consistently wound there).
    """

    vert: np.ndarray
    face: np.ndarray
    opp: np.ndarray
    many: np.ndarray
    paired: np.ndarray

    def __len__(self) -> int:
        return int(len(self.vert))


def build_edges(vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray) -> Edges:
    """Edges of the triangles ``ids`` of ``faces`` (m, 3) over ``vertices`` (n, 3) float64."""
    ids = np.asarray(ids, dtype=np.int64)
    if not len(ids):
        z = np.zeros((0, 2), dtype=np.int64)
        return Edges(z, z.copy(), z.copy(), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))
    weld = weld_vertices(vertices)
    f = faces[ids].astype(np.int64)
    w = weld[f]
    # Half-edges k -> k+1 of each triangle, the opposite corner k+2.
    a = np.concatenate([w[:, 0], w[:, 1], w[:, 2]])
    b = np.concatenate([w[:, 1], w[:, 2], w[:, 0]])
    va = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    vb = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    vo = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    tri = np.tile(ids, 3)
    lo = np.minimum(a, b)
    hi = np.maximum(a, b)
    order = np.lexsort((hi, lo))
    lo, hi = lo[order], hi[order]
    new = np.ones(len(lo), dtype=bool)
    new[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    first = np.flatnonzero(new)
    count = np.diff(np.append(first, len(lo)))
    n_e = len(first)
    face = np.full((n_e, 2), -1, dtype=np.int64)
    opp = np.full((n_e, 2), -1, dtype=np.int64)
    face[:, 0] = tri[order][first]
    opp[:, 0] = vo[order][first]
    two = count >= 2
    face[two, 1] = tri[order][first[two] + 1]
    opp[two, 1] = vo[order][first[two] + 1]
    vert = np.stack([va[order][first], vb[order][first]], axis=1)
    start = a[order]
    paired = count == 2
    paired[two] &= start[first[two]] != start[first[two] + 1]
    return Edges(vert, face, opp, count > 2, paired)


def closed_components(edges: Edges, n_triangles: int) -> np.ndarray:
    """Closed, consistently wound parts of the scene (trim_regions' back-face rule).

    A part is a set of triangles connected through paired edges (``Edges.paired``); it is
    closed when none of its triangles has an edge that is a border, non-manifold or held in
    the same direction by its two triangles. From an eye outside such a part, every ray meets
    one of its front faces before any of its back faces, so a back face of it is never seen.

    Returns
    -------
    (n_triangles,) int64: the part's label for the triangles of closed parts, -1 elsewhere
    (and for triangles without edges).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    label = np.full(n_triangles, -1, dtype=np.int64)
    if not len(edges):
        return label
    pe = edges.face[edges.paired]
    graph = coo_matrix((np.ones(len(pe)), (pe[:, 0], pe[:, 1])),
                       shape=(n_triangles, n_triangles))
    _, comp = connected_components(graph, directed=False)
    has = np.zeros(n_triangles, dtype=bool)
    bad = np.zeros(n_triangles, dtype=bool)
    for k in range(2):
        f = edges.face[:, k]
        ok = f >= 0
        has[f[ok]] = True
        bad[f[ok & ~edges.paired]] = True
    bad_comp = np.zeros(int(comp.max()) + 1, dtype=bool)
    bad_comp[comp[bad]] = True
    closed = has & ~bad_comp[comp]
    label[closed] = comp[closed]
    return label
