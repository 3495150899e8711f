"""What the trim region core keeps per scene (paper Sec. 5.1: the octree is created once when
the scene loads): the static triangles, their edges and the octree, built on first use and kept
while the scene lives (``visibility.scene_cache.per_scene``: weak keys, one build per scene)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from visibility.cores.trim_regions.octree import MAX_DEPTH, Octree, build_octree
from visibility.scene import Scene, moving_faces
from visibility.scene_cache import per_scene
from visibility.topology import (
    Edges,
    closed_parts,
    connected_pieces,
    parts_apart,
    scene_welded_ids,
)


@dataclass
class SceneData:
    """Per-scene structures.

    Attributes
    ----------
    static : (s,) int64 ids of the valid triangles that never move (occluders and occludees).
    moving : (d,) int64 ids of the valid triangles whose vertices change between keyframes
        (occludees only, tested as swept boxes).
    static_mask : (m,) bool, True for the static triangles.
    faces : (m, 3) int64 copy of the scene's faces.
    edges : the static triangles' edges.
    closed : (m,) int64 label of the closed, consistently wound part each triangle belongs to,
        -1 for the rest (``topology.closed_components``).
    piece : (m,) int64 the connected piece of each static triangle
        (``topology.connected_pieces``),
        -1 for the rest: a trim validates only intervals of its own edge's piece.
    octree : the static triangles' octree.
    normals : (s, 3) float64 unit normals of the static triangles (rows follow ``static``).
    plane : (s,) float64 their planes' offsets, normal . corner, metres (world frame).
    normal_of : (m, 3) float64 the unit normal of each triangle id (zero but for the static
        ones).
    build_seconds : time the build took, seconds.
    """

    static: np.ndarray
    moving: np.ndarray
    static_mask: np.ndarray
    faces: np.ndarray
    edges: Edges
    closed: np.ndarray
    piece: np.ndarray
    octree: Octree
    normals: np.ndarray
    plane: np.ndarray
    normal_of: np.ndarray
    build_seconds: float


def build_scene_data(scene: Scene, max_prims: int = 256) -> SceneData:
    """Edges and octree of ``scene``'s static triangles (see ``SceneData``)."""
    import time

    t0 = time.perf_counter()
    valid = scene.valid_faces.copy()
    moving = moving_faces(scene) & valid
    static = np.flatnonzero(valid & ~moving).astype(np.int64)
    tris = scene.vertices[scene.faces[static].astype(np.int64)]
    octree = build_octree(tris.min(axis=1) if len(static) else np.zeros((0, 3)),
                          tris.max(axis=1) if len(static) else np.zeros((0, 3)),
                          static, max_prims, MAX_DEPTH)
    parts, _ = closed_parts(scene)
    piece = connected_pieces(scene.faces, static, scene_welded_ids(scene)[0],
                             scene.n_triangles)
    mask = np.zeros(scene.n_triangles, dtype=bool)
    mask[static] = True
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]) if len(static) \
        else np.zeros((0, 3))
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    plane = np.einsum("ij,ij->i", normals, tris[:, 0]) if len(static) else np.zeros(0)
    normal_of = np.zeros((scene.n_triangles, 3))
    normal_of[static] = normals
    return SceneData(static, np.flatnonzero(moving).astype(np.int64), mask,
                     np.ascontiguousarray(scene.faces.astype(np.int64)), parts.edges,
                     parts.label, piece, octree, normals, plane, normal_of,
                     time.perf_counter() - t0)


def scene_data(scene: Scene, max_prims: int = 256) -> tuple[SceneData, bool]:
    """The cached ``SceneData`` of ``scene`` for ``max_prims`` per node, and whether this call
    built it."""
    return per_scene(scene, f"trim_regions/{max_prims}",
                     lambda s: build_scene_data(s, max_prims))


def faced_out_for(scene: Scene, data: SceneData, box: np.ndarray) -> SceneData:
    """``data`` for the cell ``box`` (2, 3): the triangles of closed parts wound inside out
    (``topology.ClosedParts.outward`` -1) turned to face out (``faces``, ``normal_of``,
    ``normals`` and ``plane``) when the cell stands clear of the part's box
    (``topology.parts_apart``, as ``topology.unseen_back_faces`` decides it); ``data``
    itself when none is.

    From outside a closed surface a ray enters it where it meets a face's outer side first,
    whatever the face's winding, and leaves it through the inner side of another: the
    k-buffer's front and back faces must say so, or the seal of a pixel falls on the far
    side of an inside-out board, behind the trims of its near side, and hides what eyes of
    the sphere see past the board's edge. A part around the cell (a room modelled as an
    inward-facing box) keeps its winding: its eyes see its inner side."""
    parts, _ = closed_parts(scene)
    inside_out = parts.outward == -1
    if not inside_out.any():
        return data
    apart = parts_apart(parts, box)
    flip = np.zeros(len(inside_out), dtype=bool)
    flip[inside_out] = apart[parts.label[inside_out]]
    if not flip.any():
        return data
    faces = data.faces.copy()
    faces[flip] = faces[flip][:, [0, 2, 1]]
    normal_of = data.normal_of.copy()
    normal_of[flip] *= -1.0
    rows = flip[data.static]
    normals = data.normals.copy()
    normals[rows] *= -1.0
    plane = data.plane.copy()
    plane[rows] *= -1.0
    return replace(data, faces=faces, normal_of=normal_of, normals=normals, plane=plane)
