"""Rendering through the scene hierarchy: frustum and hierarchical occlusion culling.

The same images as ``visibility.raster.triangles`` (bit for bit: the depth test keeps the
nearest surface and, on ties, the smaller id, whatever the drawing order), at a cost that
follows what a view sees rather than the whole scene. The hierarchy (``hierarchy.Hierarchy``)
is walked front to back in batches: nodes are taken nearest box first (a priority queue), so
occluders are drawn before what they hide; each batch's leaves are rasterized by the shared
kernels, the depth pyramid (``pyramid``) is rebuilt, and the walk goes on testing nodes against
it. A node is skipped when, in every view whose frustum it meets, its box lies entirely behind
what is drawn: its nearest depth is farther than the farthest depth drawn anywhere under its
projected pixel-centre rectangle. A box that reaches behind the near plane is never skipped, so
nothing near the eye is culled.

Why nothing the full render draws is lost: a triangle inside a skipped box has, at every pixel
centre it could cover, a depth no nearer than the box's nearest corner, which is farther (by a
relative margin that covers rounding) than what that pixel already holds; it would lose the
depth test there.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit, prange

from visibility.raster.hierarchy import Hierarchy
from visibility.raster.pyramid import PyramidLayout, rect_min, update_pyramid
from visibility.raster.triangles import (
    _REC,
    BAND_SHIFT,
    _centre_range,
    _finish,
    _raster,
    _render_views_on,
    _scratch,
    _setup,
    _split_views,
    out_depth,
    out_ids,
    raster_workers,
    views_covered,
)

#: Relative depth margin of the occlusion test: a box must lie this much farther than what a
#: pixel holds to be skipped (rounding of the triangle's depth plane is far below it).
DEPTH_MARGIN = 1e-6
#: Triangles in the first batch (drawn before any test can skip anything) and the most per
#: batch; batches double in between, so the pyramid is fresh where it culls most.
FIRST_BATCH = 1024
MAX_BATCH = 1 << 13

#: The hierarchy as the walk reads it.
Tree = namedtuple("Tree", "boxes order leaf slots")
#: A set of views sharing an eye: rotations (F, 3, 3), image size, tangents, near plane; and
#: each rotation as a signed permutation of ``base``'s axes (rots[k][r] = signs[k, r] *
#: base[axes[k, r]]), so a point goes to ``base``'s frame once for all views.
Views = namedtuple("Views", "eye rots width height tan_x tan_y near base axes signs")


def _as_permutations(rots: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axes (F, 3) int64, signs (F, 3) float64) with rots[k] = signs[k][:, None] *
    base[axes[k]], exactly; ValueError when a view is not so aligned with ``base``."""
    rel = rots @ base.T
    axes = np.argmax(np.abs(rel), axis=2)
    signs = np.sign(np.take_along_axis(rel, axes[..., None], axis=2)[..., 0])
    if not np.array_equal(signs[..., None] * base[axes], rots):
        raise ValueError("every view must be a signed permutation of the base rotation")
    return axes.astype(np.int64), signs.astype(np.float64)
#: A depth pyramid: level 0, the views' inverse depths (F, H, W); the levels above in flat
#: storage (F, size); their layout.
Pyramid = namedtuple("Pyramid", "invd hz heights widths offsets")


@njit(cache=True, nogil=True, inline="always")
def _pick(c0, c1, c2, axis):  # pragma: no cover - numba
    return c0 if axis == 0 else (c1 if axis == 1 else c2)


@njit(cache=True, nogil=True, inline="always")
def _box_corner(q, o0, o1, o2, x0, x1, x2, y0, y1, y2, z0, z1, z2):  # pragma: no cover - numba
    """Corner q (bits: +x, +y, +z edge) of a box given by a corner o and its edge vectors."""
    c0, c1, c2 = o0, o1, o2
    if q & 1:
        c0, c1, c2 = c0 + x0, c1 + x1, c2 + x2
    if q & 2:
        c0, c1, c2 = c0 + y0, c1 + y1, c2 + y2
    if q & 4:
        c0, c1, c2 = c0 + z0, c1 + z1, c2 + z2
    return c0, c1, c2


@njit(cache=True, nogil=True, inline="always")
def _plane_max(a, b, c, d):  # pragma: no cover - numba
    """Largest value over a box of an affine function worth ``a`` at a corner and changing
    by ``b``, ``c``, ``d`` along its three edges; and a bound on its rounding."""
    return a + max(b, 0.0) + max(c, 0.0) + max(d, 0.0), \
        1e-9 * (abs(a) + abs(b) + abs(c) + abs(d))


@njit(cache=True, nogil=True)
def _box_hidden(boxes, node, views, pyr):  # pragma: no cover - numba
    """Whether every pixel centre node's box may cover, in every view, already holds
    something nearer than the box's nearest point.

    The box goes to the frame of ``views.base`` once, as a corner o and three edge vectors;
    each view's camera coordinates are a signed permutation of those (``views.axes``,
    ``views.signs``). A frustum plane's value is affine over the box, so whether the box lies
    outside it, and its nearest depth, come from those four vectors without its corners
    (branch-free); only views the box meets project its corners."""
    eye, base, axes, signs = views.eye, views.base, views.axes, views.signs
    tan_x, tan_y, near = views.tan_x, views.tan_y, views.near
    hw = 0.5 * views.width
    hh = 0.5 * views.height
    dx = boxes[node, 1, 0] - boxes[node, 0, 0]
    dy = boxes[node, 1, 1] - boxes[node, 0, 1]
    dz = boxes[node, 1, 2] - boxes[node, 0, 2]
    ox, oy, oz = boxes[node, 0, 0] - eye[0], boxes[node, 0, 1] - eye[1], boxes[node, 0, 2] - eye[2]
    o0 = base[0, 0] * ox + base[0, 1] * oy + base[0, 2] * oz
    o1 = base[1, 0] * ox + base[1, 1] * oy + base[1, 2] * oz
    o2 = base[2, 0] * ox + base[2, 1] * oy + base[2, 2] * oz
    x0, x1, x2 = base[0, 0] * dx, base[1, 0] * dx, base[2, 0] * dx
    y0, y1, y2 = base[0, 1] * dy, base[1, 1] * dy, base[2, 1] * dy
    z0, z1, z2 = base[0, 2] * dz, base[1, 2] * dz, base[2, 2] * dz
    for k in range(axes.shape[0]):
        ax, ay, aw = axes[k, 0], axes[k, 1], axes[k, 2]
        sx_, sy_, sw_ = signs[k, 0], signs[k, 1], -signs[k, 2]
        # (x, y, w) in view k of the corner and of the three edges.
        ox_, oy_, ow_ = sx_ * _pick(o0, o1, o2, ax), sy_ * _pick(o0, o1, o2, ay), \
            sw_ * _pick(o0, o1, o2, aw)
        ex, ey, ew = sx_ * _pick(x0, x1, x2, ax), sy_ * _pick(x0, x1, x2, ay), \
            sw_ * _pick(x0, x1, x2, aw)
        fx, fy, fw = sx_ * _pick(y0, y1, y2, ax), sy_ * _pick(y0, y1, y2, ay), \
            sw_ * _pick(y0, y1, y2, aw)
        gx, gy, gw = sx_ * _pick(z0, z1, z2, ax), sy_ * _pick(z0, z1, z2, ay), \
            sw_ * _pick(z0, z1, z2, aw)
        # Outside the frustum: wholly on the outer side of one of its side planes. The near
        # plane needs no test: a box reaching in front of it is "behind" and kept below.
        out = False
        for sgn in (1.0, -1.0):
            m, tol = _plane_max(ow_ * tan_x - sgn * ox_, ew * tan_x - sgn * ex,
                                fw * tan_x - sgn * fx, gw * tan_x - sgn * gx)
            out |= m < -tol
            m, tol = _plane_max(ow_ * tan_y - sgn * oy_, ew * tan_y - sgn * ey,
                                fw * tan_y - sgn * fy, gw * tan_y - sgn * gy)
            out |= m < -tol
        m, tol = _plane_max(ow_ - near, ew, fw, gw)
        out |= m < -tol
        if out:
            continue
        zmin = ow_ + min(ew, 0.0) + min(fw, 0.0) + min(gw, 0.0)
        if zmin < near * (1.0 + 1e-9) + 1e-9 * (abs(ow_) + abs(ew) + abs(fw) + abs(gw)):
            return False  # reaches the near plane (or the eye): never culled
        sx0, sx1, sy0, sy1 = np.inf, -np.inf, np.inf, -np.inf
        for q in range(8):
            px, py, w = _box_corner(q, ox_, oy_, ow_, ex, ey, ew, fx, fy, fw, gx, gy, gw)
            sx = (px / (w * tan_x) + 1.0) * hw
            sy = (1.0 - py / (w * tan_y)) * hh
            sx0, sx1 = min(sx0, sx), max(sx1, sx)
            sy0, sy1 = min(sy0, sy), max(sy1, sy)
        px0, px1 = _centre_range(sx0, sx1, views.width)
        py0, py1 = _centre_range(sy0, sy1, views.height)
        if px0 > px1 or py0 > py1:
            continue  # between pixel centres: covers none
        m = rect_min(pyr.invd, pyr.hz, k, pyr.heights, pyr.widths, pyr.offsets, px0, px1,
                     py0, py1)
        if not m > (1.0 / zmin) * (1.0 + DEPTH_MARGIN):
            return False
    return True


@njit(cache=True, nogil=True, inline="always")
def _box_distance2(boxes, node, eye):  # pragma: no cover - numba
    """Squared distance from ``eye`` to node's box (0 inside)."""
    d = 0.0
    for a in range(3):
        g = max(boxes[node, 0, a] - eye[a], eye[a] - boxes[node, 1, a], 0.0)
        d += g * g
    return d


@njit(cache=True, nogil=True, inline="always")
def _push(heap_key, heap_node, size, key, node):  # pragma: no cover - numba
    """Insert (key, node) into the binary min-heap of ``size`` entries; the new size."""
    i = size
    while i > 0:
        parent = (i - 1) >> 1
        if heap_key[parent] <= key:
            break
        heap_key[i] = heap_key[parent]
        heap_node[i] = heap_node[parent]
        i = parent
    heap_key[i] = key
    heap_node[i] = node
    return size + 1


@njit(cache=True, nogil=True, inline="always")
def _pop(heap_key, heap_node, size):  # pragma: no cover - numba
    """Remove the smallest entry of the heap; (its node, the new size)."""
    top = heap_node[0]
    size -= 1
    key, node = heap_key[size], heap_node[size]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and heap_key[c + 1] < heap_key[c]:
            c += 1
        if key <= heap_key[c]:
            break
        heap_key[i] = heap_key[c]
        heap_node[i] = heap_node[c]
        i = c
    heap_key[i] = key
    heap_node[i] = node
    return top, size


@njit(cache=True, nogil=True)
def _walk(tree, views, pyr, mask, done, front, size, out, budget,
          counts):  # pragma: no cover - numba
    """Take nodes nearest first (``front``: a min-heap of (squared box distance, node) pairs of
    ``size`` entries) until ``budget`` triangles are listed in ``out`` or none is left; hidden
    nodes are dropped, a leaf's triangles (those ``mask`` keeps, by their positions in leaf
    order) listed unless ``done`` marks the leaf, an inner node's children queued. Returns
    (triangles listed, heap size).
    ``counts``: nodes tested, nodes hidden, leaves drawn."""
    boxes, order = tree.boxes, tree.order
    heap_key, heap_node = front
    eye = views.eye
    n_tri = order.shape[0]
    n = 0
    while size > 0 and n < budget:
        node, size = _pop(heap_key, heap_node, size)
        counts[0] += 1
        if _box_hidden(boxes, node, views, pyr):
            counts[1] += 1
            continue
        if node >= tree.slots:
            if done[node - tree.slots]:
                continue  # drawn first, from the previous view's leaves (``Coherence``)
            counts[2] += 1
            s = (node - tree.slots) * tree.leaf
            for t in range(s, min(s + tree.leaf, n_tri)):
                if mask[order[t]]:
                    out[n] = t  # a position in leaf order (``Hierarchy.faces``)
                    n += 1
            continue
        for ch in (2 * node, 2 * node + 1):
            if boxes[ch, 0, 0] <= boxes[ch, 1, 0]:  # not an empty slot
                size = _push(heap_key, heap_node, size, _box_distance2(boxes, ch, eye), ch)
    return n, size


@njit(cache=True, nogil=True)
def _leaf_positions(leaves, tree, mask, done, out):  # pragma: no cover - numba
    """List in ``out`` the positions (leaf order) of the triangles of ``leaves`` that ``mask``
    keeps, marking those leaves in ``done``; returns how many."""
    n = 0
    n_tri = tree.order.shape[0]
    for j in leaves:
        if j < 0 or j >= done.shape[0] or done[j]:
            continue
        done[j] = 1
        s = j * tree.leaf
        for t in range(s, min(s + tree.leaf, n_tri)):
            if mask[tree.order[t]]:
                out[n] = t
                n += 1
    return n


@njit(cache=True, nogil=True)
def _seen_leaves(idbuf, ids_to_leaf, mark):  # pragma: no cover - numba
    """Mark the leaf of every face id in ``idbuf`` (flat)."""
    for p in range(idbuf.shape[0]):
        i = idbuf[p]
        if i >= 0:
            leaf = ids_to_leaf[i]
            if leaf >= 0:
                mark[leaf] = 1


#: Culling pays while a view draws at most this share of the tree's triangles: past it the
#: walk and the per-triangle tests cost more than drawing every triangle does (where the
#: crossing lies: ``python -m benchmarks.bench_culling``, docs/culling.md).
PAYS_UP_TO = 0.08
#: A scene whose runs found culling not paying still tries it on every this-many-th run.
RETRY_EVERY = 8


class Coherence:
    """A run of views from nearby eyes (the cubemaps of one cell): what the previous view saw
    (the leaves its image holds) is drawn first by the next, so its depth pyramid is nearly
    whole before the walk starts and the walk skips most of the scene (two-pass occlusion
    culling: last frame's visible set, then the rest tested against it).

    It also decides whether culling pays for the run: ``hierarchy_for(h)`` gives ``h`` until
    a view draws more than ``PAYS_UP_TO`` of the tree's triangles, then None (draw every
    face: the same images, cheaper there). What runs on a scene found is remembered with the
    hierarchy, so later runs on a scene where culling does not pay start without it (trying it
    again every ``RETRY_EVERY`` runs)."""

    def __init__(self) -> None:
        self.leaves: np.ndarray | None = None
        self.off = False
        self._opened: Hierarchy | None = None

    def hierarchy_for(self, hierarchy: Hierarchy | None) -> Hierarchy | None:
        """``hierarchy`` while culling pays for this run, else None."""
        if hierarchy is None or self.off:
            return None
        if self._opened is not hierarchy:
            self._opened = hierarchy
            st = hierarchy.stats
            st["runs"] = st.get("runs", 0) + 1
            if not st.get("pays", True) and st["runs"] % RETRY_EVERY:
                self.off = True
                return None
        return hierarchy

    def drew(self, hierarchy: Hierarchy, triangles: int) -> None:
        """A view of the run drew ``triangles`` through ``hierarchy``."""
        pays = triangles <= PAYS_UP_TO * max(len(hierarchy.order), 1)
        hierarchy.stats["pays"] = pays
        if not pays:
            self.off = True


@njit(cache=True, nogil=True, inline="always")
def _home(v, eye, i, views, cube):  # pragma: no cover - numba
    """(view, screen x, screen y, depth) of vertex i: the view whose frustum holds it (-1 none,
    -2 not finite), as ``triangles._home_views`` decides it: for a cube, the face of the
    dominant axis in ``views.base``'s frame, else view 0."""
    base, axes, signs = views.base, views.axes, views.signs
    x, y, z = v[i, 0] - eye[0], v[i, 1] - eye[1], v[i, 2] - eye[2]
    c0 = base[0, 0] * x + base[0, 1] * y + base[0, 2] * z
    c1 = base[1, 0] * x + base[1, 1] * y + base[1, 2] * z
    c2 = base[2, 0] * x + base[2, 1] * y + base[2, 2] * z
    if not np.isfinite(c0 + c1 + c2):
        return -2, 0.0, 0.0, 0.0
    k = 0
    if cube:
        a0, a1, a2 = abs(c0), abs(c1), abs(c2)
        if a0 >= a1 and a0 >= a2:
            k = 0 if c0 >= 0 else 1
        elif a1 >= a2:
            k = 2 if c1 >= 0 else 3
        else:
            k = 4 if c2 >= 0 else 5
    # The view's coordinates: a signed permutation of the base frame's (``Views``).
    a, b, d = axes[k, 0], axes[k, 1], axes[k, 2]
    px = signs[k, 0] * (c0 if a == 0 else (c1 if a == 1 else c2))
    py = signs[k, 1] * (c0 if b == 0 else (c1 if b == 1 else c2))
    w = -signs[k, 2] * (c0 if d == 0 else (c1 if d == 1 else c2))
    tan_x, tan_y = views.tan_x, views.tan_y
    if w >= views.near and abs(px) <= w * tan_x and abs(py) <= w * tan_y:
        return (k, (px / (w * tan_x) + 1.0) * 0.5 * views.width,
                (1.0 - py / (w * tan_y)) * 0.5 * views.height, w)
    return -1, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True, parallel=True)
def _bin(v, faces, sel, views, pyr, cube, out, box):  # pragma: no cover - numba
    """``triangles._cull`` for a selection, each face's corners placed on the fly: bit k of
    ``out[t]`` when face ``sel[t]`` may cover a pixel centre of view k, and its pixel box
    when its corners share a view (``box[t, 0] = -1``: left to ``_setup``). A face inside one
    view whose box lies behind what the pyramid holds (as ``_box_hidden`` judges boxes) gets
    no bit. Returns the faces so hidden."""
    n = v.shape[0]
    eye, rots = views.eye, views.rots
    width, height = views.width, views.height
    tan_x, tan_y, near = views.tan_x, views.tan_y, views.near
    hidden = 0
    for t in prange(sel.shape[0]):
        out[t] = 0
        box[t, 0] = -1
        f = sel[t]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        if i0 < 0 or i1 < 0 or i2 < 0 or i0 >= n or i1 >= n or i2 >= n:
            continue
        h0, x0, y0, w0 = _home(v, eye, i0, views, cube)
        h1, x1, y1, w1 = _home(v, eye, i1, views, cube)
        h2, x2, y2, w2 = _home(v, eye, i2, views, cube)
        if h0 == -2 or h1 == -2 or h2 == -2:
            continue
        if h0 >= 0 and h0 == h1 and h0 == h2:
            px0, px1 = _centre_range(min(x0, x1, x2), max(x0, x1, x2), width)
            py0, py1 = _centre_range(min(y0, y1, y2), max(y0, y1, y2), height)
            if px0 <= px1 and py0 <= py1:
                # Depth is affine over the triangle: its nearest point is a corner.
                m = rect_min(pyr.invd, pyr.hz, h0, pyr.heights, pyr.widths, pyr.offsets, px0,
                             px1, py0, py1)
                if m > (1.0 / min(w0, w1, w2)) * (1.0 + DEPTH_MARGIN):
                    hidden += 1
                    continue
                out[t] = 1 << h0
                box[t, 0] = px0
                box[t, 1] = px1
                box[t, 2] = py0
                box[t, 3] = py1
            continue
        out[t] = views_covered(v, eye, i0, i1, i2, rots, width, height, tan_x, tan_y, near)
    return hidden


def _draw(v, faces, sel, ids, views, pyr, base, invd, idbuf, counts, n_workers, dirty,
          merge=False):
    """Rasterize faces ``sel`` into every view's ``invd`` and ``idbuf``, but those the pyramid
    already hides; ``dirty`` (F, 4) gets each view's drawn pixel box [x0, x1, y0, y1] (x0 > x1:
    none), or grows by it with ``merge``. Returns the faces the pyramid hid."""
    n_views = len(views.rots)
    cube = base is not None
    bits = _scratch("cull_bits", len(sel), np.uint8)
    box = _scratch("cull_box", (len(sel), 4), np.int32)
    hidden = _bin(v, faces, sel, views, pyr, cube, bits, box)
    offsets, order = _split_views(bits, n_views)
    if not merge:
        dirty[:] = (1 << 30, -1, 1 << 30, -1)
    for k in range(n_views):
        idx = order[offsets[k]: offsets[k + 1]]
        if len(idx) == 0:
            continue
        bounds = _scratch("cull_bounds", (len(idx), 4), np.int32)
        rec = _scratch("cull_rec", (len(idx), _REC), np.float64)
        _setup(v, views.eye, faces, sel, idx, box, ids, views.rots, k, views.width,
               views.height, views.tan_x, views.tan_y, views.near, bounds, rec)
        _raster(rec, bounds, views.width, views.near, BAND_SHIFT, n_workers, invd[k],
                idbuf[k], counts)
        drawn = bounds[bounds[:, 0] <= bounds[:, 1]]
        if len(drawn):
            dirty[k] = (min(dirty[k, 0], drawn[:, 0].min()), max(dirty[k, 1], drawn[:, 1].max()),
                        min(dirty[k, 2], drawn[:, 2].min()), max(dirty[k, 3], drawn[:, 3].max()))
    return hidden


def _leaves_seen(idbuf: np.ndarray, hierarchy: Hierarchy) -> np.ndarray:
    """The hierarchy's leaves holding a face of ``idbuf`` (face rows; -1 empty), sorted."""
    mark = np.zeros(hierarchy.n_leaf_slots, dtype=np.uint8)
    _seen_leaves(idbuf.reshape(-1), hierarchy.leaf_of, mark)
    return np.flatnonzero(mark)


def render_views_culled(v: np.ndarray, eye: np.ndarray, faces: np.ndarray,
                        hierarchy: Hierarchy, mask: np.ndarray, ids: np.ndarray,
                        rots: np.ndarray, base: np.ndarray | None, width: int, height: int,
                        tan_x: float, tan_y: float, near: float, stats: dict | None,
                        want_depth: bool = True, always: np.ndarray | None = None,
                        coherence: Coherence | None = None,
                        buffers: tuple[np.ndarray | None, np.ndarray] | None = None,
                        ) -> tuple[np.ndarray | None, np.ndarray]:
    """Depth (F, H, W) float32 and ids (F, H, W) int32 of F views sharing ``eye``, drawing only
    what the hierarchy's culling keeps: identical to ``triangles._render_views`` on the
    faces of ``mask``.

    A render that has drawn more than ``PAYS_UP_TO`` of the tree's triangles and has more
    to walk gives culling up and draws every face of ``mask`` (the same images: a view into
    clutter sees most of what its frustum holds, and each batch's walk, binning and pyramid
    then cost more than the drawing they spare); ``stats`` gains ``gave_up``.

    ``mask``: (m,) bool, faces to draw (checked inputs: ``triangles._check_inputs``);
    ``always``: int64 face ids drawn without culling (moving faces, which the hierarchy does not
    hold), in the first batch; ``coherence`` (ids must be the faces' rows): the leaves the
    previous view saw go in the first batch too, and it gets this view's; ``buffers``: (F, H, W)
    depth (or None) and id buffers to write into (``render.render_ids``). ``stats`` gains
    ``triangles`` (drawn), ``pixels``, ``pixel_tests``, ``band_pairs`` as the full render
    reports them, and ``nodes_tested``, ``nodes_hidden``, ``leaves_drawn``,
    ``triangles_hidden`` (in drawn leaves, hidden one by one), ``batches``, ``seeded``
    (triangles drawn first from the previous view's leaves).
    """
    n_views = len(rots)
    rots = np.ascontiguousarray(rots, dtype=np.float64)
    frame = rots[0] if base is None else np.ascontiguousarray(base, dtype=np.float64)
    axes, signs = _as_permutations(rots, frame)
    views = Views(np.ascontiguousarray(eye, dtype=np.float64), rots, int(width), int(height),
                  float(tan_x), float(tan_y), float(near), frame, axes, signs)
    tree = Tree(hierarchy.boxes, hierarchy.order, int(hierarchy.leaf_size),
                int(hierarchy.n_leaf_slots))
    layout = PyramidLayout.of(height, width)
    invd = _scratch("cull_invd", (n_views, height, width), np.float64)
    invd.fill(0.0)
    pyr = Pyramid(invd, layout.empty(n_views), layout.heights, layout.widths, layout.offsets)
    idbuf = out_ids(buffers, n_views, height, width)
    n_workers = raster_workers(height)
    counts = np.zeros((n_workers, 2), dtype=np.int64)
    walk = np.zeros(3, dtype=np.int64)
    # The walk's front: a min-heap by box distance, at most one entry per node.
    front = (np.empty(len(hierarchy.boxes)), np.empty(len(hierarchy.boxes), dtype=np.int64))
    sp = 0
    if hierarchy.boxes[1, 0, 0] <= hierarchy.boxes[1, 1, 0]:
        sp = _push(front[0], front[1], 0, 0.0, 1)
    out = np.empty(MAX_BATCH + tree.leaf, dtype=np.int64)
    budget, drawn, batches, hidden, walk_seeded = FIRST_BATCH, 0, 0, 0, 0
    dirty = np.zeros((n_views, 4), dtype=np.int64)
    extra = np.zeros(0, np.int64) if always is None else np.asarray(always, np.int64)
    # The tree's triangles are drawn from its leaf-ordered copy; their ids are the rows of
    # the scene's faces they stand for.
    tree_ids = hierarchy.order if len(ids) == 0 else ids[hierarchy.order]
    done = np.zeros(tree.slots, dtype=np.uint8)
    n_tree = len(hierarchy.order)
    if coherence is not None and coherence.leaves is not None and len(coherence.leaves):
        seeded = np.empty(len(coherence.leaves) * tree.leaf, dtype=np.int64)
        k = _leaf_positions(np.asarray(coherence.leaves, np.int64), tree, mask, done, seeded)
        if k:
            # Drawn before the walk, as one batch: a whole pyramid to test the rest against.
            drawn += k
            hidden += _draw(hierarchy.vertices, hierarchy.faces, seeded[:k], tree_ids, views,
                            pyr, base, invd, idbuf, counts, n_workers, dirty)
            update_pyramid(invd, pyr.heights, pyr.widths, pyr.offsets, pyr.hz, dirty)
            batches += 1
            walk_seeded = k
    while sp > 0 or (batches == 0 and len(extra)):
        n, sp = _walk(tree, views, pyr, mask, done, front, sp, out, budget, walk)
        first = batches == 0
        if first and len(extra):
            drawn += len(extra)
            hidden += _draw(v, faces, extra, ids, views, pyr, base, invd, idbuf, counts,
                            n_workers, dirty)
        batches += 1
        if n:
            drawn += n
            hidden += _draw(hierarchy.vertices, hierarchy.faces, out[:n], tree_ids, views, pyr,
                            base, invd, idbuf, counts, n_workers, dirty,
                            merge=first and len(extra) > 0)
        if sp > 0 and drawn - hidden > PAYS_UP_TO * n_tree:
            # Culling no longer pays (``PAYS_UP_TO``): a view into clutter draws most of what
            # its frustum holds, and batch after batch the walk, the binning and the pyramid
            # cost more than drawing every face of the mask once does: the same images.
            if stats is not None:
                for key, val in (("nodes_tested", int(walk[0])), ("nodes_hidden", int(walk[1])),
                                 ("leaves_drawn", int(walk[2])), ("batches", batches),
                                 ("seeded", walk_seeded), ("gave_up", 1)):
                    stats[key] = stats.get(key, 0) + int(val)
            sel = np.flatnonzero(mask).astype(np.int64)
            depth, idbuf = _render_views_on(v, eye, faces, sel, ids, rots, base, width, height,
                                            tan_x, tan_y, near, stats, want_depth, buffers)
            if coherence is not None and len(ids) == 0:
                coherence.leaves = _leaves_seen(idbuf, hierarchy)
                coherence.drew(hierarchy, drawn - hidden)
            return depth, idbuf
        if sp > 0 and (n or (first and len(extra))):
            update_pyramid(invd, pyr.heights, pyr.widths, pyr.offsets, pyr.hz, dirty)
        budget = min(2 * budget, MAX_BATCH)
    if coherence is not None and len(ids) == 0:
        coherence.leaves = _leaves_seen(idbuf, hierarchy)
        coherence.drew(hierarchy, drawn - hidden)
    depth = None
    if want_depth:
        depth = out_depth(buffers, n_views, height, width)
        _finish(invd, idbuf, depth)
    if stats is not None:
        for key, val in (("triangles", drawn - hidden), ("triangles_hidden", hidden),
                         ("pixels", n_views * width * height),
                         ("pixel_tests", int(counts[:, 0].sum())),
                         ("band_pairs", int(counts[:, 1].sum())),
                         ("nodes_tested", int(walk[0])), ("nodes_hidden", int(walk[1])),
                         ("leaves_drawn", int(walk[2])), ("batches", batches),
                         ("seeded", walk_seeded)):
            stats[key] = stats.get(key, 0) + int(val)
    return depth, idbuf

