"""Topology of a triangle soup: which corners are one point, which triangles share an edge,
and which parts of the scene are closed surfaces.

Vertices are welded by exact position (bitwise equal float64 coordinates): a tolerance would
join triangles across a hairline gap, and a ray through that gap would then count as blocked.
Edges with one triangle (a border) or more than two (non-manifold) are kept apart from the
two-triangle edges the cores fuse or read silhouettes from.

A *closed part* (``closed_components``) is a set of triangles joined through edges of exactly
two triangles that hold them in opposite directions, with no other edge: a watertight,
consistently wound surface. ``closed_parts`` adds its orientation (the sign of its enclosed
volume) and box, and ``unseen_back_faces`` uses them: from an eye outside a closed surface,
a ray that meets one of its triangles from the inside has crossed the surface before, so a
triangle whose outer side faces away from every eye of a cell is never seen from that cell.
A closed part that passes through itself has no outer side for every triangle (it is inside
out in places); there the winding number on each side of the triangles no other crosses
(``winding.front_windings``) says which side is hidden: one where it is not 0.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
from numba import njit, parallel_chunksize, prange

from visibility.raster.camera import DEFAULT_NEAR
from visibility.scene import Scene, moving_faces
from visibility.scene_cache import Build, Persist, load_npz, per_scene, save_npz
from visibility.winding import UNDECIDED, front_windings


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

    t0 = time.perf_counter()
    ids, built = per_scene(scene, "topology/welded", lambda s: weld_vertices(s.vertices))
    return ids, (time.perf_counter() - t0) if built else 0.0


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


def build_edges(vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray,
                weld: np.ndarray | None = None) -> Edges:
    """Edges of the triangles ``ids`` of ``faces`` (m, 3) over ``vertices`` (n, 3) float64;
    ``weld`` (n,) the vertices' welded ids when already known (``weld_vertices``)."""
    ids = np.asarray(ids, dtype=np.int64)
    if not len(ids):
        z = np.zeros((0, 2), dtype=np.int64)
        return Edges(z, z.copy(), z.copy(), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))
    if weld is None:
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


def connected_pieces(faces: np.ndarray, ids: np.ndarray, weld: np.ndarray,
                     n_triangles: int) -> np.ndarray:
    """(n_triangles,) int64 label of the connected piece of each triangle of ``ids`` (rows of
    ``faces`` (m, 3)): triangles joined through corners at one position (``weld``: welded
    vertex ids, ``weld_vertices``); -1 for the triangles not in ``ids``. Looser than a closed
    part: any shared corner joins, whatever the edges (trim_regions' trims validate only the
    intervals of their own edge's piece)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    label = np.full(n_triangles, -1, dtype=np.int64)
    if not len(ids):
        return label
    w = weld[faces[ids].astype(np.int64)]
    n = int(weld.max()) + 1
    a = np.concatenate([w[:, 0], w[:, 1]])
    b = np.concatenate([w[:, 1], w[:, 2]])
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    label[ids] = comp[w[:, 0]]
    return label


#: A closed part's orientation is trusted when its signed volume (about its box centre) is at
#: least this share of the volume its triangles' cones enclose unsigned: a zero-volume part (a
#: sheet closed by a reversed copy of itself) has no outside to speak of.
ORIENTED_SHARE = 1e-6
#: A part closer to the cell than this (metres) keeps its back faces: a camera's near plane
#: (``raster.camera.DEFAULT_NEAR`` along the axis of a 90 degree view, up to sqrt(3) times
#: that off it) can cut its front away and show its inside.
NEAR_CLEARANCE = float(np.sqrt(3.0)) * DEFAULT_NEAR
#: Triangles with twice their area under this share of their longest edge squared (an aspect
#: of about 10^6) are never taken for unseen: their normal is too rounded to trust.
NEEDLE = 1e-6


@dataclass
class ClosedParts:
    """The closed parts of a scene's static triangles (``closed_components``).

    Attributes
    ----------
    edges : the static valid triangles' edges (``build_edges``).
    label : (m,) int64 the closed part of each triangle, -1 for triangles in none.
    outward : (m,) int8 +1 where a triangle's winding normal (counter-clockwise corners, right
        hand) points out of its closed part, -1 where it points in, 0 for triangles of no
        closed part or of a part whose volume is too small to tell (``ORIENTED_SHARE``).
    box : (p, 2, 3) float64 each part's bounding box [min, max], metres (world frame).
    oriented : (k,) int64 the triangles with ``outward`` != 0 whose normal can be trusted (not
        needles, ``NEEDLE``): the candidates of ``unseen_back_faces``.
    normal : (k, 3) float64 their outer unit normals; ``offset`` (k,) normal . corner, metres.
    wound : (j,) int64 triangles of parts that pass through themselves (no ``outward``), which
        no other triangle crosses and whose front side's winding number ``wfront`` (j,) int32
        is known (``winding.front_windings``; the back's is one more); ``wnormal`` (j, 3)
        their right-hand unit normals and ``woffset`` (j,) normal . corner, metres.
    """

    edges: Edges
    label: np.ndarray
    outward: np.ndarray
    box: np.ndarray
    oriented: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    wound: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    wfront: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    wnormal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    woffset: np.ndarray = field(default_factory=lambda: np.zeros(0))


#: Triangles are shrunk towards their centroids by this share before the crossing test, so that
#: neighbours meeting along a shared edge or corner do not count as crossing.
SHRINK = 1e-5


@njit(cache=True, inline="always")
def _orient2(ax, ay, bx, by, cx, cy):  # pragma: no cover - numba
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@njit(cache=True, nogil=True)
def _coplanar_meets(p, q, t, n):  # pragma: no cover - numba
    """Whether segment [p, q], lying in the plane of triangle t (normal n), meets it: in 2D,
    dropping the normal's largest axis. Touching counts as meeting."""
    k = np.argmax(np.abs(n))
    i = (k + 1) % 3
    j = (k + 2) % 3
    px, py, qx, qy = p[i], p[j], q[i], q[j]
    sgn = 1.0 if _orient2(t[0, i], t[0, j], t[1, i], t[1, j], t[2, i], t[2, j]) > 0 else -1.0
    for e in (p, q):
        inside = True
        for c in range(3):
            a = t[c]
            b = t[(c + 1) % 3]
            if sgn * _orient2(a[i], a[j], b[i], b[j], e[i], e[j]) < 0.0:
                inside = False
        if inside:
            return True
    for c in range(3):
        a = t[c]
        b = t[(c + 1) % 3]
        o1 = _orient2(px, py, qx, qy, a[i], a[j])
        o2 = _orient2(px, py, qx, qy, b[i], b[j])
        o3 = _orient2(a[i], a[j], b[i], b[j], px, py)
        o4 = _orient2(a[i], a[j], b[i], b[j], qx, qy)
        if o1 * o2 <= 0.0 and o3 * o4 <= 0.0:
            return True
    return False


@njit(cache=True, inline="always")
def _segment_meets(p, q, t):  # pragma: no cover - numba
    """Whether segment [p, q] (3,) meets triangle t (3, 3); a segment (nearly) in the
    triangle's plane counts as meeting (the caller takes that for a crossing: conservative)."""
    e1 = t[1] - t[0]
    e2 = t[2] - t[0]
    d = q - p
    h = np.cross(d, e2)
    det = np.dot(e1, h)
    scale = np.sqrt(np.dot(e1, e1) * np.dot(e2, e2) * np.dot(d, d))
    if abs(det) <= 1e-12 * scale:
        n = np.cross(e1, e2)
        nn = np.sqrt(np.dot(n, n))
        dp = abs(np.dot(n, p - t[0]))
        dq = abs(np.dot(n, q - t[0]))
        if max(dp, dq) > 1e-9 * nn * np.sqrt(np.dot(d, d) + np.dot(e1, e1)):
            return False  # parallel to the plane, off it
        return _coplanar_meets(p, q, t, n)
    f = 1.0 / det
    sv = p - t[0]
    u = f * np.dot(sv, h)
    if u < -1e-12 or u > 1.0 + 1e-12:
        return False
    qv = np.cross(sv, e1)
    v = f * np.dot(d, qv)
    if v < -1e-12 or u + v > 1.0 + 1e-12:
        return False
    w = f * np.dot(e2, qv)
    return -1e-12 <= w <= 1.0 + 1e-12


@njit(cache=True, inline="always")
def _cross(a, b):  # pragma: no cover - numba
    """Whether triangles a and b (3, 3), shrunk, meet: an edge of one meets the other."""
    for i in range(3):
        if _segment_meets(a[i], a[(i + 1) % 3], b):
            return True
        if _segment_meets(b[i], b[(i + 1) % 3], a):
            return True
    return False


@njit(cache=True, nogil=True, parallel=True)
def _crossings(tris, lo, hi, start, axis, parts, every, out, flag):  # pragma: no cover - numba
    """Crossing triangles of the parts ``parts``. Part k holds rows start[k] to start[k + 1]
    of the shrunk triangles ``tris`` (n, 3, 3), sorted by their lower bound along the part's
    longest axis ``axis[k]``; ``lo``, ``hi`` (n, 3) their boxes. out[k] = True when two of
    its triangles cross; with ``every``, flag[i] = True for each triangle another crosses
    (else the part's sweep stops at its first crossing). Parts run in parallel (each writes
    only its own out[k] and its own rows of ``flag``): callers list them largest first and
    run it with a chunk size of 1 (``_sweep_parts``), so no thread is left the big ones."""
    for kk in prange(parts.shape[0]):
        k = parts[kk]
        ax = axis[k]
        for i in range(start[k], start[k + 1]):
            for j in range(i + 1, start[k + 1]):
                if lo[j, ax] > hi[i, ax]:
                    break
                if (lo[j, 0] > hi[i, 0] or hi[j, 0] < lo[i, 0] or lo[j, 1] > hi[i, 1]
                        or hi[j, 1] < lo[i, 1] or lo[j, 2] > hi[i, 2] or hi[j, 2] < lo[i, 2]):
                    continue
                if _cross(tris[i], tris[j]):
                    out[k] = True
                    if not every:
                        break
                    flag[i] = True
                    flag[j] = True
            if out[k] and not every:
                break


def _sweep(tris: np.ndarray, label: np.ndarray, p: int) -> tuple:
    """The crossing tests' layout: triangles shrunk (``SHRINK``), grouped by part and sorted
    along each part's longest axis; (shrunk sorted triangles, their lo and hi (n, 3), part
    start rows (p + 1,), axis per part (p,), the sort order)."""
    c = tris.mean(axis=1, keepdims=True)
    t = c + (tris - c) * (1.0 - SHRINK)
    lo = t.min(axis=1)
    hi = t.max(axis=1)
    ext = np.zeros((p, 3))
    for a in range(3):
        top = np.full(p, -np.inf)
        bot = np.full(p, np.inf)
        np.maximum.at(top, label, hi[:, a])
        np.minimum.at(bot, label, lo[:, a])
        ext[:, a] = top - bot
    axis = np.argmax(ext, axis=1).astype(np.int64)
    order = np.lexsort((lo[np.arange(len(t)), axis[label]], label))
    start = np.searchsorted(label[order], np.arange(p + 1)).astype(np.int64)
    return (np.ascontiguousarray(t[order]), np.ascontiguousarray(lo[order]),
            np.ascontiguousarray(hi[order]), start, axis, order)


def self_crossing_parts(tris: np.ndarray, label: np.ndarray, p: int) -> np.ndarray:
    """(p,) bool, True for the parts some two of whose triangles cross or overlap (beyond the
    edges and corners they share).

    Parameters
    ----------
    tris : (k, 3, 3) float64 triangles, metres; ``label`` (k,) int64 their part in [0, p).
    """
    if not len(tris):
        return np.zeros(p, dtype=bool)
    return _crossing_parts(_sweep(tris, label, p), p)


def _sweep_parts(layout: tuple, parts: np.ndarray, every: bool, out: np.ndarray,
                 flag: np.ndarray) -> None:
    """``_crossings`` over ``parts`` (int64 ids), largest first, one part per thread at a time:
    part sizes vary a hundredfold, and a sweep's work grows faster than its size."""
    t, lo, hi, start, axis, _ = layout
    size = start[parts + 1] - start[parts]
    ordered = np.ascontiguousarray(parts[np.argsort(-size, kind="stable")], dtype=np.int64)
    with parallel_chunksize(1):
        _crossings(t, lo, hi, start, axis, ordered, every, out, flag)


def _crossing_parts(layout: tuple, p: int) -> np.ndarray:
    """``self_crossing_parts`` on a ``_sweep`` layout."""
    out = np.zeros(p, dtype=bool)
    _sweep_parts(layout, np.arange(p, dtype=np.int64), False, out, np.zeros(0, dtype=np.bool_))
    return out


def _crossed(layout: tuple, p: int, parts: np.ndarray) -> np.ndarray:
    """(k,) bool in the triangles' own order: those of the parts ``parts`` (int64 ids) that
    another triangle of their part crosses or overlaps, on a ``_sweep`` layout (as
    ``self_crossing_parts`` tests)."""
    t, _, _, _, _, order = layout
    flag = np.zeros(len(t), dtype=bool)
    if len(parts):
        _sweep_parts(layout, np.asarray(parts, dtype=np.int64), True,
                     np.zeros(p, dtype=np.bool_), flag)
    out = np.zeros(len(t), dtype=bool)
    out[order] = flag
    return out


def _wound_sides(tri: np.ndarray, lab: np.ndarray, p: int, layout: tuple,
                 crossing: np.ndarray, n: np.ndarray, norm: np.ndarray,
                 needle: np.ndarray) -> tuple:
    """Of the parts ``crossing`` (p,) bool (they pass through themselves), the triangles no
    other crosses, not needles, whose front winding ``winding.front_windings`` can count:
    (rows of ``tri``, front windings, right-hand unit normals, offsets). ``layout`` is the
    parts' ``_sweep``; ``n``, ``norm`` the triangles' right-hand normals and their lengths."""
    if not crossing.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros((0, 3)), \
            np.zeros(0)
    # Every triangle of those parts blocks the rays; only the uncrossed ones are counted for.
    rows = np.flatnonzero(crossing[lab])
    todo = ~_crossed(layout, p, np.flatnonzero(crossing))[rows] & ~needle[rows]
    wf = front_windings(tri[rows], lab[rows], todo)
    ok = todo & (wf != UNDECIDED)
    rows = rows[ok]
    unit = n[rows] / norm[rows, None]
    return rows, wf[ok], unit, np.einsum("ij,ij->i", unit, tri[rows, 0])


def build_closed_parts(scene: Scene) -> ClosedParts:
    """Closed parts of ``scene``'s valid static triangles (a part touching a moving triangle
    has a border there and is not closed), with their orientation and boxes."""
    m = scene.n_triangles
    static = np.flatnonzero(scene.valid_faces & ~moving_faces(scene)).astype(np.int64)
    edges = build_edges(scene.vertices, scene.faces, static, scene_welded_ids(scene)[0])
    label = closed_components(edges, m)
    outward = np.zeros(m, dtype=np.int8)
    inpart = np.flatnonzero(label >= 0)
    if not len(inpart):
        return ClosedParts(edges, label, outward, np.zeros((0, 2, 3)),
                           np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0))
    # Compact labels 0..p-1.
    uniq, lab = np.unique(label[inpart], return_inverse=True)
    label[inpart] = lab
    p = len(uniq)
    tri = scene.vertices[scene.faces[inpart].astype(np.int64)]  # (k, 3, 3)
    box = np.empty((p, 2, 3))
    for a in range(3):
        box[:, 0, a] = np.full(p, np.inf)
        box[:, 1, a] = np.full(p, -np.inf)
        np.minimum.at(box[:, 0, a], lab, tri[:, :, a].min(axis=1))
        np.maximum.at(box[:, 1, a], lab, tri[:, :, a].max(axis=1))
    # Six times the signed volume of each triangle's cone from the part's box centre.
    rel = tri - (0.5 * (box[lab, 0] + box[lab, 1]))[:, None, :]
    cone = np.einsum("ij,ij->i", rel[:, 0], np.cross(rel[:, 1], rel[:, 2]))
    vol = np.bincount(lab, weights=cone, minlength=p)
    mag = np.bincount(lab, weights=np.abs(cone), minlength=p)
    sign = np.where(np.abs(vol) > ORIENTED_SHARE * mag, np.sign(vol), 0.0).astype(np.int8)
    # A surface that passes through itself can be inside out in places (an inner piece
    # wound against the rest): its volume's sign says nothing there.
    layout = _sweep(tri, lab, p)
    crossing = _crossing_parts(layout, p)
    sign[crossing] = 0
    outward[inpart] = sign[lab]
    # Outer unit normals of the oriented triangles; a needle's normal is rounding: left out.
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    long2 = np.max(np.sum((tri - np.roll(tri, 1, axis=1)) ** 2, axis=2), axis=1)
    norm = np.linalg.norm(n, axis=1)
    needle = ~(norm > NEEDLE * long2)
    keep = (outward[inpart] != 0) & ~needle
    # Parts that pass through themselves have no outside for every triangle: the winding
    # number on each side of those no other triangle crosses says which side is hidden.
    wrows, wfront, wnormal, woffset = _wound_sides(tri, lab, p, layout, crossing, n, norm,
                                                   needle)
    n = n[keep] * (outward[inpart][keep] / norm[keep])[:, None]
    return ClosedParts(edges, label, outward, box, inpart[keep], n,
                       np.einsum("ij,ij->i", n, tri[keep, 0]), inpart[wrows], wfront,
                       wnormal, woffset)


#: The per-scene cache's name for the closed parts (``visibility.scene_cache``).
CLOSED_KIND = "topology/closed_parts"
#: Their format on disk: a file of another format is built again, never read.
CLOSED_FORMAT = "closed-parts-1"


def save_closed_parts(parts: ClosedParts, path: str | Path) -> None:
    """Write ``parts`` to ``path`` (``.npz``, ``scene_cache.save_npz``)."""
    arrays = {f"edges_{f.name}": getattr(parts.edges, f.name) for f in fields(Edges)}
    arrays.update({f.name: getattr(parts, f.name) for f in fields(ClosedParts)
                   if f.name != "edges"})
    save_npz(path, format=np.array(CLOSED_FORMAT), **arrays)


def load_closed_parts(path: str | Path, scene: Scene) -> ClosedParts | None:
    """The closed parts saved at ``path`` for ``scene``; None when missing, of another format,
    of another triangle count, or holding ids outside the scene's arrays."""
    m, n = scene.n_triangles, scene.n_vertices
    try:
        z = load_npz(path)
        if str(z.pop("format")) != CLOSED_FORMAT:
            return None
        a = {k: np.ascontiguousarray(v) for k, v in z.items()}
        edges = Edges(**{f.name: a.pop(f"edges_{f.name}") for f in fields(Edges)})
        parts = ClosedParts(edges=edges, **a)
    except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile):
        return None
    if len(parts.label) != m or len(parts.outward) != m:
        return None
    # Vertex rows and triangle ids (-1 where an edge or a triangle has none) in range.
    for ids, top in ((edges.vert, n), (edges.opp, n), (edges.face, m), (parts.oriented, m),
                     (parts.wound, m)):
        if len(ids) and (ids.min() < -1 or ids.max() >= top):
            return None
    if len(parts.label) and parts.label.max() >= len(parts.box):
        return None
    return parts


#: The closed parts on disk, by the scene's content hash (``scene_cache.set_store``): on the
#: 1M-triangle kitchen they take seconds to build, a restart reads them instead.
CLOSED_PERSIST: Persist[ClosedParts] = Persist(save=save_closed_parts, load=load_closed_parts,
                                               version=CLOSED_FORMAT)
#: The closed parts as one of a scene's background builds (``Core.scene_builds``).
CLOSED_BUILD = Build(CLOSED_KIND, build_closed_parts, CLOSED_PERSIST)


def closed_parts(scene: Scene) -> tuple[ClosedParts, bool]:
    """The cached ``ClosedParts`` of ``scene`` (read from the store when kept there) and
    whether this call built them."""
    return per_scene(scene, CLOSED_KIND, build_closed_parts, CLOSED_PERSIST)


@njit(cache=True, nogil=True, parallel=True)
def _behind_cell(oriented, label, apart, normal, offset, lo, hi, tol,
                 out):  # pragma: no cover - numba
    """out[t] = True for each oriented triangle t (``oriented`` (k,), its outer plane
    ``normal`` (k, 3) and ``offset`` (k,)) of a part ``apart`` from the cell [lo, hi] whose
    plane has the whole cell more than ``tol`` behind it: the cell corner farthest along the
    outer normal decides."""
    for i in prange(oriented.shape[0]):
        t = oriented[i]
        if not apart[label[t]]:
            continue
        ahead = -offset[i]
        s = 0.0
        for a in range(3):
            s += normal[i, a] * (hi[a] if normal[i, a] > 0.0 else lo[a])
        if s + ahead < -tol:
            out[t] = True


def cell_tolerance(box: np.ndarray) -> float:
    """Metres by which a cell ``box`` (2, 3) must clear what is tested against it: 1 nm plus
    64 ulps of its largest coordinate (the rounding of a frame shifted to the cell)."""
    return 1e-9 + 64.0 * float(np.spacing(max(float(np.max(np.abs(box))), 1.0)))


def parts_apart(parts: ClosedParts, box: np.ndarray, tol: float | None = None) -> np.ndarray:
    """(p,) bool, True for the closed parts whose box lies more than ``NEAR_CLEARANCE`` plus
    ``tol`` (default ``cell_tolerance``) from the cell ``box`` (2, 3) along some axis: every
    eye of the cell stands outside them."""
    lo = np.asarray(box[0], dtype=np.float64)
    hi = np.asarray(box[1], dtype=np.float64)
    gap = (cell_tolerance(box) if tol is None else tol) + NEAR_CLEARANCE
    pb = parts.box
    return np.any((pb[:, 0] > hi + gap) | (pb[:, 1] < lo - gap), axis=1)


def unseen_back_faces(scene: Scene, box: np.ndarray, tol: float | None = None) -> np.ndarray:
    """Triangles that no eye in ``box`` can see: the triangles of oriented closed parts whose
    box lies more than ``NEAR_CLEARANCE`` from the cell's, with every corner of the cell
    strictly behind their outer side.

    An eye outside a closed, consistently wound surface (outside its box) that looks at one of
    its triangles from the inside looks along a ray that entered the surface before: the
    surface hides the triangle there. That needs the surface's inside to be inside
    everywhere; parts that pass through themselves can be inside out in places, and are left
    unoriented (``self_crossing_parts``).

    Parameters
    ----------
    box : (2, 3) float64 the cell [min, max], metres.
    tol : distance (metres) by which the cell must clear a part's box and lie behind a
        triangle's plane; by default 1 nm plus 64 ulps of the box's largest coordinate (the
        rounding of a frame shifted to the cell).

    Returns
    -------
    (m,) bool, True for the triangles never seen from the cell.
    """
    parts, _ = closed_parts(scene)
    out = np.zeros(scene.n_triangles, dtype=bool)
    if not len(parts.oriented) and not len(parts.wound):
        return out
    lo = np.asarray(box[0], dtype=np.float64)
    hi = np.asarray(box[1], dtype=np.float64)
    if tol is None:
        tol = cell_tolerance(box)
    apart = parts_apart(parts, box, tol)
    # One pass over the oriented triangles (numpy's temporaries over a million of them cost
    # more than the test).
    _behind_cell(parts.oriented, parts.label, apart, parts.normal, parts.offset, lo, hi,
                 float(tol), out)
    # Triangles of parts that pass through themselves: hidden on a side where the winding
    # number is not 0, for an eye outside the part's box (where it is 0), so when the whole
    # cell lies on that side.
    selw = apart[parts.label[parts.wound]]
    n = parts.wnormal[selw]
    top = np.einsum("ij,ij->i", n, np.where(n > 0.0, hi, lo)) - parts.woffset[selw]
    bot = np.einsum("ij,ij->i", n, np.where(n > 0.0, lo, hi)) - parts.woffset[selw]
    wf = parts.wfront[selw]
    hidden = ((top < -tol) & (wf + 1 != 0)) | ((bot > tol) & (wf != 0))
    out[parts.wound[selw][hidden]] = True
    return out
