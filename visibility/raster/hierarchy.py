"""The scene's spatial hierarchy: a bounding-volume tree over its static triangles.

Built once per scene (``scene_hierarchy``), shared by every path that rasterizes the scene
(``visibility.raster.culling``) and offered to the cores. Triangles are sorted along a Morton
curve of their centroids and cut into leaves of ``leaf_size`` consecutive triangles; the tree
over the leaves is implicit (a complete binary tree in heap order: node ``i`` has children
``2i`` and ``2i + 1``, leaf ``j`` is node ``n_leaf_slots + j``), so it stores no pointers, only
one float64 box per node and the triangle order (about 4 bytes a triangle plus 48 bytes a node),
and a copy of the tree's triangles in leaf order with their corners in first-use order (12
bytes a triangle and 24 a vertex): a view's walk then reads memory in the order it draws, which
on scenes of tens of millions of triangles is most of the cost of drawing.

Boxes are float64 and built from the float64 vertices with min/max (no rounding), so a box holds
its triangles exactly, whatever the coordinate offset (georeferenced scenes keep their
precision). Moving triangles (``visibility.scene.moving_faces``) are left out: their positions
change with time, so the renderer draws them without culling.
"""

from __future__ import annotations

import threading
import time
import weakref
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit, prange

from visibility.scene import Scene, moving_faces
from visibility.scene_cache import (
    Build,
    Persist,
    build_in_background,
    in_progress,
    load_npz,
    peek,
    per_scene,
    save_npz,
)

#: Triangles per leaf: smaller leaves cull tighter and cost more node tests.
LEAF_SIZE = 16
#: Bits per axis of the Morton code (3 x 21 = 63 bits).
MORTON_BITS = 21
#: Format tag of saved hierarchies; another tag (an older build) is rebuilt, never read.
FORMAT = "bvh-1"


@dataclass(frozen=True)
class Hierarchy:
    """A bounding-volume tree over a scene's static valid triangles.

    Attributes
    ----------
    order : (t,) int32 triangle ids (rows of the scene's face array) in leaf order.
    boxes : (2 * n_leaf_slots, 2, 3) float64 node boxes [min, max], metres, in heap order
        (index 0 unused); empty nodes have min > max.
    leaf_size : triangles per leaf (the last leaf may hold fewer).
    n_faces : rows of the face array it was built for (a guard against another scene's faces).
    loose : (l,) int32 drawable faces left out of the tree (moving ones): drawn unculled.
    faces : (t, 3) int32 the faces of ``order``, in that order, indexing ``vertices``.
    vertices : (u, 3) float64 their corners, metres, in first-use order (static: the tree
        holds no moving face).
    seconds : build time.
    """

    order: np.ndarray
    boxes: np.ndarray
    leaf_size: int
    n_faces: int
    loose: np.ndarray
    faces: np.ndarray
    vertices: np.ndarray
    seconds: float = 0.0
    #: (k,) int64 indices into the scene's vertices (static ones) and (k, 3) their positions:
    #: what a render checks its vertices against (``matches``).
    probe_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    probe_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: (n_faces,) int32 leaf of each face (-1: not in the tree).
    leaf_of: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    def __post_init__(self) -> None:
        if len(self.leaf_of) != self.n_faces:
            lo = np.full(self.n_faces, -1, dtype=np.int32)
            lo[self.order] = np.arange(len(self.order), dtype=np.int32) // self.leaf_size
            object.__setattr__(self, "leaf_of", lo)
    stats: dict = field(default_factory=dict)

    def matches(self, vertices: np.ndarray) -> bool:
        """Whether ``vertices`` (n, 3) hold the positions it was built from, judged at a few
        static vertices spread over the tree (exactly): another frame or scene fails."""
        v = np.asarray(vertices)
        if len(self.probe_ids) and (v.ndim != 2 or len(v) <= int(self.probe_ids.max())):
            return False
        return bool(np.array_equal(v[self.probe_ids], self.probe_xyz))

    @property
    def n_leaves(self) -> int:
        return (len(self.order) + self.leaf_size - 1) // self.leaf_size

    @property
    def n_leaf_slots(self) -> int:
        return len(self.boxes) // 2

    @property
    def nbytes(self) -> int:
        return int(self.order.nbytes + self.boxes.nbytes + self.loose.nbytes
                   + self.faces.nbytes + self.vertices.nbytes + self.leaf_of.nbytes)

    def save(self, path: str | Path) -> None:
        """Write to ``path`` (``.npz``, ``scene_cache.save_npz``)."""
        save_npz(path, format=np.array(FORMAT), order=self.order, boxes=self.boxes,
                 leaf_size=np.array(self.leaf_size), n_faces=np.array(self.n_faces),
                 loose=self.loose)

    @classmethod
    def load(cls, path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Hierarchy | None:
        """The hierarchy saved at ``path`` for the scene of ``vertices`` (n, 3) and ``faces``
        (m, 3); None when missing, of another format or another face count, or malformed.
        The leaf-ordered copy is rebuilt from the scene's arrays, not stored."""
        n_faces = len(faces)
        try:
            z = load_npz(path)
            if str(z["format"]) != FORMAT or int(z["n_faces"]) != n_faces:
                return None
            order = np.ascontiguousarray(z["order"], dtype=np.int32)
            boxes = np.ascontiguousarray(z["boxes"], dtype=np.float64)
            loose = np.ascontiguousarray(z["loose"], dtype=np.int32)
            leaf = int(z["leaf_size"])
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
            return None
        slots = len(boxes) // 2
        if (boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or slots & (slots - 1) or leaf < 1
                or len(order) > slots * leaf
                or any(len(a) and (a.min() < 0 or a.max() >= n_faces) for a in (order, loose))):
            return None
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        lf, lv, probes = _local_copy(v, np.ascontiguousarray(faces, dtype=np.int32), order)
        return cls(order, boxes, leaf, n_faces, loose, lf, lv, seconds=0.0,
                   stats={"loaded": True}, probe_ids=probes, probe_xyz=v[probes].copy())


# --------------------------------------------------------------------------------- build
@njit(cache=True, nogil=True)
def _spread(x):  # pragma: no cover - numba
    """The low 21 bits of x spread to every third bit."""
    x = x & 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    x = (x | (x << 2)) & 0x1249249249249249
    return x


@njit(cache=True, nogil=True, parallel=True)
def _morton(v, faces, ids, lo, scale, codes):  # pragma: no cover - numba
    """Morton code of each listed face's centroid, quantized over [lo, lo + 1/scale]."""
    top = (1 << MORTON_BITS) - 1
    for t in prange(ids.shape[0]):
        f = ids[t]
        q = np.zeros(3, dtype=np.int64)
        for a in range(3):
            c = (v[faces[f, 0], a] + v[faces[f, 1], a] + v[faces[f, 2], a]) / 3.0
            x = (c - lo[a]) * scale[a]
            q[a] = min(max(np.int64(x), 0), top)
        codes[t] = (_spread(np.uint64(q[0])) << np.uint64(2)) | \
            (_spread(np.uint64(q[1])) << np.uint64(1)) | _spread(np.uint64(q[2]))


@njit(cache=True, nogil=True, parallel=True)
def _leaf_boxes(v, faces, order, leaf, slots, boxes):  # pragma: no cover - numba
    """Boxes of the leaves (nodes slots .. 2 slots - 1): min/max over their triangles' corners."""
    n = order.shape[0]
    for j in prange(slots):
        node = slots + j
        for a in range(3):
            boxes[node, 0, a] = np.inf
            boxes[node, 1, a] = -np.inf
        s = j * leaf
        e = min(s + leaf, n)
        for t in range(s, e):
            f = order[t]
            for c in range(3):
                i = faces[f, c]
                for a in range(3):
                    x = v[i, a]
                    if x < boxes[node, 0, a]:
                        boxes[node, 0, a] = x
                    if x > boxes[node, 1, a]:
                        boxes[node, 1, a] = x


@njit(cache=True, nogil=True)
def _first_use(faces, order, n_vertices, local_faces, remap):  # pragma: no cover - numba
    """``local_faces`` = faces[order] renumbered by first use of each vertex; ``remap`` (n,)
    int32 must be -1 on entry. Returns the old vertex ids in their new order."""
    used = np.empty(min(3 * order.shape[0], n_vertices), dtype=np.int64)
    n = 0
    for t in range(order.shape[0]):
        f = order[t]
        for c in range(3):
            i = faces[f, c]
            if remap[i] < 0:
                remap[i] = n
                used[n] = i
                n += 1
            local_faces[t, c] = remap[i]
    return used[:n]


#: Vertices ``Hierarchy.matches`` checks.
PROBES = 16


def _local_copy(v: np.ndarray, f: np.ndarray, order: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(faces[order] renumbered, the vertices they use in first-use order, probe vertex ids:
    ``PROBES`` of those spread over the order)."""
    local = np.empty((len(order), 3), dtype=np.int32)
    remap = np.full(len(v), -1, dtype=np.int32)
    used = _first_use(f, order, len(v), local, remap)
    probes = used[np.linspace(0, len(used) - 1, min(PROBES, len(used))).astype(np.int64)]
    return local, np.ascontiguousarray(v[used]), probes.astype(np.int64)


@njit(cache=True, nogil=True)
def _inner_boxes(boxes, slots):  # pragma: no cover - numba
    """Each inner node's box: the union of its children's."""
    for node in range(slots - 1, 0, -1):
        for a in range(3):
            boxes[node, 0, a] = min(boxes[2 * node, 0, a], boxes[2 * node + 1, 0, a])
            boxes[node, 1, a] = max(boxes[2 * node, 1, a], boxes[2 * node + 1, 1, a])


@njit(cache=True, nogil=True)
def _leaves_in_box(boxes, lo, hi, out):  # pragma: no cover - numba
    """Leaves (0-based) whose node box meets the closed box [lo, hi] (3,) into ``out``;
    returns their count. Empty nodes (min > max) meet nothing."""
    slots = len(boxes) // 2
    stack = np.empty(2 * 64 + 2, dtype=np.int64)
    stack[0] = 1
    top = 1
    k = 0
    while top > 0:
        top -= 1
        node = stack[top]
        if (boxes[node, 0, 0] > hi[0] or boxes[node, 1, 0] < lo[0]
                or boxes[node, 0, 1] > hi[1] or boxes[node, 1, 1] < lo[1]
                or boxes[node, 0, 2] > hi[2] or boxes[node, 1, 2] < lo[2]):
            continue
        if node >= slots:
            out[k] = node - slots
            k += 1
        else:
            stack[top] = 2 * node
            stack[top + 1] = 2 * node + 1
            top += 2
    return k


def candidates_in_box(h: Hierarchy, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(k,) int64 triangle ids that may meet the closed box [lo, hi] (3,) metres (infinite
    bounds allowed): the tree's triangles in leaves whose box meets it, a superset of those
    whose own bounds do, and every loose (moving) face. Work grows with the leaves met, not
    with the scene."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    leaves = np.empty(max(h.n_leaves, 1), dtype=np.int64)
    n = _leaves_in_box(h.boxes, lo, hi, leaves)
    slots = (leaves[:n, None] * h.leaf_size + np.arange(h.leaf_size)).ravel()
    ids = h.order[slots[slots < len(h.order)]].astype(np.int64)
    return np.concatenate([ids, h.loose.astype(np.int64)]) if len(h.loose) else ids


def drawable_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) bool: faces the rasterizer may draw (indices in range, finite corners)."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    ok = np.all((f >= 0) & (f < len(v)), axis=1)
    finite = np.all(np.isfinite(v), axis=1)
    ok[ok] = np.all(finite[f[ok]], axis=1)
    return ok


def build_hierarchy(vertices: np.ndarray, faces: np.ndarray,
                    static: np.ndarray | None = None,
                    leaf_size: int = LEAF_SIZE) -> Hierarchy:
    """The bounding-volume tree over the drawable faces (``drawable_faces``) that ``static``
    marks; the other drawable faces are kept as ``loose`` (drawn without culling).

    Parameters
    ----------
    vertices : (n, 3) float64 positions, metres (the positions of the static faces).
    faces : (m, 3) int32 vertex indices.
    static : (m,) bool, faces whose positions never change (None: all).
    leaf_size : triangles per leaf.
    """
    t0 = time.perf_counter()
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"vertices and faces must be (n, 3), got {v.shape} and {f.shape}")
    draw = drawable_faces(v, f)
    if static is not None:
        static = np.asarray(static, dtype=bool)
        if static.shape != (len(f),):
            raise ValueError(f"static must be ({len(f)},) bool, got {static.shape}")
    if int(leaf_size) < 1:
        raise ValueError(f"leaf_size must be >= 1, got {leaf_size}")
    leaf = int(leaf_size)
    loose = np.zeros(0, np.int32) if static is None else \
        np.flatnonzero(draw & ~static).astype(np.int32)
    ids = np.flatnonzero(draw if static is None else draw & static).astype(np.int32)
    n_leaves = max(1, -(-len(ids) // leaf))
    slots = 1 << int(np.ceil(np.log2(n_leaves))) if n_leaves > 1 else 1
    if len(ids):
        used = v[np.unique(f[ids[:: max(1, len(ids) // 200_000)]].ravel())]
        lo, hi = used.min(axis=0), used.max(axis=0)
        # Centroids beyond the sampled bounds clamp to the curve's ends: order only, never
        # correctness, depends on the codes.
        scale = ((1 << MORTON_BITS) - 1) / np.maximum(hi - lo, 1e-12)
        codes = np.empty(len(ids), dtype=np.uint64)
        _morton(v, f, ids, lo, scale, codes)
        order = ids[np.argsort(codes, kind="stable")]
        del codes
    else:
        order = ids
    boxes = np.empty((2 * slots, 2, 3), dtype=np.float64)
    boxes[0] = np.array([[np.inf] * 3, [-np.inf] * 3])
    _leaf_boxes(v, f, order, leaf, slots, boxes)
    _inner_boxes(boxes, slots)
    order = order.astype(np.int32)
    lf, lv, probes = _local_copy(v, f, order)
    return Hierarchy(order, boxes, leaf, len(f), loose, lf, lv,
                     seconds=time.perf_counter() - t0, probe_ids=probes,
                     probe_xyz=v[probes].copy())


# --------------------------------------------------------------------------------- per scene
#: The per-scene cache's name for the hierarchy (``visibility.scene_cache``).
KIND = "raster/hierarchy"
#: Scenes below this many triangles are drawn whole: a view of them costs less than the walk.
MIN_TRIANGLES = 50_000


def _build_for(scene: Scene) -> Hierarchy:
    return build_hierarchy(scene.vertices, scene.faces, static=~moving_faces(scene))


#: The hierarchy on disk, by the scene's content hash (``scene_cache.set_store``).
PERSIST: Persist[Hierarchy] = Persist(save=lambda h, p: h.save(p),
                                      load=lambda p, s: Hierarchy.load(p, s.vertices, s.faces),
                                      version=FORMAT)
#: The hierarchy as one of a scene's background builds (``scene_cache.build_in_background``).
BUILD = Build(KIND, _build_for, PERSIST)

_started: weakref.WeakSet[Scene] = weakref.WeakSet()
_started_lock = threading.Lock()


def scene_hierarchy(scene: Scene) -> Hierarchy:
    """The hierarchy of ``scene``'s static triangles, built (or read from the store) now if
    it is not there yet."""
    return per_scene(scene, KIND, _build_for, PERSIST)[0]


def ready_hierarchy(scene: Scene, start: bool = True) -> Hierarchy | None:
    """The hierarchy of ``scene`` if it is built, else None, never waiting: with ``start``, a
    background build begins for a scene of at least ``MIN_TRIANGLES`` triangles (once), so
    later calls find it."""
    h = peek(scene, KIND)
    if h is not None or not start or scene.n_triangles < MIN_TRIANGLES:
        return h
    with _started_lock:
        if scene in _started or in_progress(scene, KIND):
            return None
        _started.add(scene)
    build_in_background(scene, [BUILD])
    return None
