"""A scene's geometry as the from-segment kernels read it: ``SegmentGeometry`` per state
interval, with its triangles cut into spatial clusters (``build_clusters``), cached per scene
(``scene_geometries``).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from visibility.cores.from_segment.groups import GeometryArrays
from visibility.scene import Scene
from visibility.scene_cache import Build

#: Triangles per spatial cluster (unit of the box pass and of tile-level culling).
CLUSTER = 32

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@dataclass(eq=False)
class SegmentGeometry:
    """The geometry of one state interval, as the kernels read it.

    Attributes
    ----------
    verts0, verts1 : (n, 3) float64 vertex positions at the interval's start and end (the same
        array for a static scene), metres.
    faces : (m, 3) int32.
    tri_sel : (k,) int64 ids of the triangles that take part (valid faces).
    moving : (m,) bool, triangles whose corners move in this interval.
    centers0, centers1 : (s, 3) float64 sphere centres at start and end; radii : (s,) float64.
    sphere_sel : (q,) int64 ids of the spheres that take part.
    cl_start, cl_tris : spatial clusters of the selected triangles: cluster c holds
        ``cl_tris[cl_start[c]:cl_start[c + 1]]`` (CLUSTER triangles, Morton order of centroids).
    cl_lo, cl_hi : (c, 3) float64 bounding box of each cluster over both positions.
    """

    verts0: np.ndarray
    verts1: np.ndarray
    faces: np.ndarray
    tri_sel: np.ndarray
    moving: np.ndarray
    centers0: np.ndarray
    centers1: np.ndarray
    radii: np.ndarray
    sphere_sel: np.ndarray
    cl_start: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    cl_tris: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    cl_lo: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cl_hi: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def n_triangles(self) -> int:
        return int(len(self.faces))

    def arrays(self) -> GeometryArrays:
        """The arrays the kernels read, as one named group."""
        return GeometryArrays(self.verts0, self.verts1, self.faces, self.moving, self.cl_start,
                              self.cl_tris, self.centers0, self.centers1, self.radii,
                              self.n_triangles, self.cl_lo, self.cl_hi)

    @property
    def n_ids(self) -> int:
        """Length of the visibility mask: triangles, then spheres."""
        return int(len(self.faces) + len(self.radii))


def _part1by2(x: np.ndarray) -> np.ndarray:
    x = x & np.uint64(0x3FF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x30000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x300F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x9249249)
    return x


def build_clusters(vertices: np.ndarray, faces: np.ndarray,
                   tri_sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cl_start (c + 1,), cl_tris (k,)): the selected triangles in Morton order of their
    centroids, cut into clusters of CLUSTER consecutive triangles."""
    k = len(tri_sel)
    if k == 0:
        return np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    f = faces[tri_sel]
    cent = vertices[f[:, 0]] + vertices[f[:, 1]] + vertices[f[:, 2]]
    lo = cent.min(axis=0)
    span = np.maximum(cent.max(axis=0) - lo, 1e-300)
    q = np.clip((cent - lo) / span * 1023.0, 0, 1023).astype(np.uint64)
    code = _part1by2(q[:, 0]) | (_part1by2(q[:, 1]) << np.uint64(1)) | (
        _part1by2(q[:, 2]) << np.uint64(2))
    cl_tris = tri_sel[np.argsort(code, kind="stable")].astype(np.int64)
    cl_start = np.append(np.arange(0, k, CLUSTER, dtype=np.int64), k)
    return cl_start, cl_tris


@njit(**_JIT)
def _cluster_bounds(verts0, verts1, faces, cl_start, cl_tris):  # pragma: no cover - numba
    """(c, 3) min and max corner of each cluster over both vertex positions."""
    nc = cl_start.shape[0] - 1
    lo = np.empty((nc, 3))
    hi = np.empty((nc, 3))
    for c in range(nc):
        for r in range(3):
            lo[c, r] = np.inf
            hi[c, r] = -np.inf
        for k in range(cl_start[c], cl_start[c + 1]):
            t = cl_tris[k]
            for j in range(3):
                vi = faces[t, j]
                for r in range(3):
                    a = verts0[vi, r]
                    b = verts1[vi, r]
                    lo[c, r] = min(lo[c, r], min(a, b))
                    hi[c, r] = max(hi[c, r], max(a, b))
    return lo, hi


_GEOMETRY_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _signature(scene: Scene) -> tuple:
    arrays = (scene.vertices, scene.faces, scene.states, scene.sphere_centers, scene.sphere_radii)
    return tuple((id(a), None if a is None else a.shape) for a in arrays)


def scene_geometries(scene: Scene) -> list[SegmentGeometry]:
    """One ``SegmentGeometry`` per consecutive pair of the scene's states (one for a static
    scene). Triangles use ``scene.valid_faces``; spheres need finite centres and radius > 0.

    Cached per scene (weakly; rebuilt if its arrays are replaced): clusters are built once.
    Scenes are treated as immutable: arrays changed in place are not noticed.
    """
    sig = _signature(scene)
    hit = _GEOMETRY_CACHE.get(scene)
    if hit is not None and hit[0] == sig:
        return hit[1]
    faces = np.ascontiguousarray(scene.faces, dtype=np.int32)
    tri_sel = np.flatnonzero(scene.valid_faces).astype(np.int64)
    m = len(faces)
    if scene.states is not None and scene.states.shape[0] > 1:
        tri_states = [np.ascontiguousarray(s) for s in scene.states]
    else:
        base = scene.vertices if scene.states is None else scene.states[0]
        tri_states = [np.ascontiguousarray(base, dtype=np.float64)]
    if scene.n_spheres:
        radii = np.ascontiguousarray(scene.sphere_radii, dtype=np.float64)
        cs = [np.ascontiguousarray(c) for c in scene.sphere_centers]
        finite = np.all(np.isfinite(scene.sphere_centers), axis=(0, 2))
        ok = finite & np.isfinite(radii) & (radii > 0)
        sphere_sel = np.flatnonzero(ok).astype(np.int64)
    else:
        radii = np.zeros(0)
        cs = [np.zeros((0, 3))]
        sphere_sel = np.zeros(0, dtype=np.int64)
    cl_start, cl_tris = build_clusters(tri_states[0], faces, tri_sel)
    pairs = max(len(tri_states), len(cs)) - 1
    out = []
    for p in range(max(pairs, 1)):
        a = tri_states[min(p, len(tri_states) - 1)]
        b = tri_states[min(p + 1, len(tri_states) - 1)]
        if a is b:
            moving = np.zeros(m, dtype=bool)
        else:
            vm = np.any(a != b, axis=1)
            moving = vm[faces].any(axis=1) if m else np.zeros(0, dtype=bool)
        lo, hi = _cluster_bounds(a, b, faces, cl_start, cl_tris)
        out.append(SegmentGeometry(
            verts0=a, verts1=b, faces=faces, tri_sel=tri_sel, moving=moving,
            centers0=cs[min(p, len(cs) - 1)], centers1=cs[min(p + 1, len(cs) - 1)], radii=radii,
            sphere_sel=sphere_sel, cl_start=cl_start, cl_tris=cl_tris, cl_lo=lo, cl_hi=hi))
    _GEOMETRY_CACHE[scene] = (sig, out)
    return out


#: The clusters as a per-scene build (``Core.scene_builds``): a server makes them when the
#: scene loads, not on a walker's first request.
GEOMETRY_BUILD = Build("from_segment/clusters", scene_geometries)
