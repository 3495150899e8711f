"""The primitives a cell's COS pass works on, relative to the cell centre in float64.

Static triangles are full primitives (occludees and occluders, with welded vertex ids for
fusion). What moves (a triangle whose vertices change over the keyframes) and spheres are
*hulls*: the eight corners of a box that holds every position they take between the keyframes
(positions are piecewise linear in time, so the keyframe boxes' union bounds the sweep). Hulls
are occludees only: they are reported when any part of that box may be seen, and never hide
anything, which keeps both conservative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from visibility.scene import Scene
from visibility.scene_cache import per_scene
from visibility.topology import NEAR_CLEARANCE

#: Primitive kinds.
TRIANGLE = 0
HULL = 1


@dataclass
class Prims:
    """Primitive arrays of one cell.

    Attributes
    ----------
    pts : (P, 3) float64 points relative to the cell centre, metres.
    start : (n,) int64 first point of each primitive; ``npts`` (n,) int64 its point count
        (3 for a triangle, 8 for a hull).
    kind : (n,) int8, TRIANGLE or HULL.
    out_id : (n,) int64, the id reported: a triangle id, or ``n_triangles + sphere index``.
    vid : (n, 3) int64 welded vertex ids of a triangle's corners (-1 for hulls).
    scale : float, largest absolute world coordinate involved (rounding of the shift to the
        cell centre is a few ulps of it).
    """

    pts: np.ndarray
    start: np.ndarray
    npts: np.ndarray
    kind: np.ndarray
    out_id: np.ndarray
    vid: np.ndarray
    scale: float

    def __len__(self) -> int:
        return int(len(self.start))

    @property
    def plane_tol(self) -> float:
        """Distance (metres) within which the plane tests cannot tell a side: 1 nm plus 64
        ulps of ``scale``, the rounding of the shift to the cell centre."""
        return 1e-9 + 64.0 * float(np.spacing(max(self.scale, 1.0)))


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(k, 8, 3) corners of k boxes."""
    out = np.empty((len(lo), 8, 3))
    for c in range(8):
        for a in range(3):
            out[:, c, a] = hi[:, a] if (c >> a) & 1 else lo[:, a]
    return out


@dataclass(frozen=True)
class _Static:
    """A scene's valid triangles that do not move, gathered once per scene.

    ids : (n,) int64 triangle ids; faces : (n, 3) int64 their vertex rows; scale : the
    largest coordinate magnitude among their corners (0.0 when none); moving : (k,) int64
    ids of the valid triangles that move. (Their corners are gathered per cell: kept, they
    would triple a large scene's memory.)
    """

    ids: np.ndarray
    faces: np.ndarray
    scale: float
    moving: np.ndarray


def _gather_static(scene: Scene) -> _Static:
    valid = np.flatnonzero(scene.valid_faces)
    faces = scene.faces[valid].astype(np.int64)
    moving = np.zeros(len(valid), dtype=bool)
    if scene.states is not None and scene.states.shape[0] > 1:
        states = scene.states
        vmove = np.any(np.any(states != states[:1], axis=0), axis=1)  # (n_vertices,)
        moving = np.any(vmove[faces], axis=1)
    still = faces[~moving]
    used = np.unique(still)
    scale = float(np.max(np.abs(scene.vertices[used]))) if len(used) else 0.0
    return _Static(valid[~moving].astype(np.int64), still, scale,
                   valid[moving].astype(np.int64))


def _static_triangles(scene: Scene) -> _Static:
    """``_Static`` of ``scene``, cached per scene object: the gathers are a cell's largest
    fixed cost on a 100k-triangle scene (4x the gather of the corners itself)."""
    return per_scene(scene, "cos/static", _gather_static)[0]


def build_prims(scene: Scene, centre: np.ndarray, welded: np.ndarray,
                drop: np.ndarray | None = None) -> Prims:
    """Primitives of ``scene`` around ``centre`` (3,) metres, with welded vertex ids (n_vertices,).

    Degenerate faces (``scene.valid_faces`` False) are left out, and so are the triangles
    ``drop`` (m,) bool marks (ones no eye of the cell can see, ``topology.unseen_back_faces``).
    """
    c = np.asarray(centre, dtype=np.float64)
    m = scene.n_triangles
    st = _static_triangles(scene)
    if drop is None:
        stat, sf = st.ids, st.faces
    else:
        keep = ~drop[st.ids]
        stat, sf = st.ids[keep], st.faces[keep]
    scale = max(float(np.max(np.abs(c))) if c.size else 0.0, st.scale)
    n_stat = len(stat)
    hull_lo, hull_hi, hull_id = [], [], []
    mv = st.moving if drop is None else st.moving[~drop[st.moving]]
    if len(mv):
        corners = scene.states[:, scene.faces[mv].astype(np.int64)]  # (k, t, 3, 3)
        hull_lo.append(corners.min(axis=(0, 2)))
        hull_hi.append(corners.max(axis=(0, 2)))
        hull_id.append(mv.astype(np.int64))
    if scene.n_spheres:
        cen = scene.sphere_centers  # (k, s, 3)
        r = scene.sphere_radii[:, None]
        hull_lo.append(cen.min(axis=0) - r)
        hull_hi.append(cen.max(axis=0) + r)
        hull_id.append(m + np.arange(scene.n_spheres, dtype=np.int64))
    k = 0
    if hull_lo:
        lo = np.concatenate(hull_lo)
        hi = np.concatenate(hull_hi)
        ok = np.all(np.isfinite(lo) & np.isfinite(hi), axis=1)
        lo, hi, hid = lo[ok], hi[ok], np.concatenate(hull_id)[ok]
        k = len(lo)
        if k:
            scale = max(scale, float(np.max(np.abs(np.concatenate([lo, hi])))))
    # One pass writes the triangles' corners (relative to the centre) and welded ids: numpy's
    # gathers, casts and concatenations showed in a small cell's time on a 100k scene.
    base = 3 * n_stat
    pts = np.empty((base + 8 * k, 3))
    vids = np.empty((n_stat + k, 3), dtype=np.int64)
    _gather_triangles(scene.vertices, sf, welded, c, pts, vids)
    start = np.empty(n_stat + k, dtype=np.int64)
    start[:n_stat] = np.arange(n_stat, dtype=np.int64) * 3
    npts = np.full(n_stat + k, 3, dtype=np.int64)
    kind = np.zeros(n_stat + k, dtype=np.int8)
    out_id = stat
    if hull_lo:
        pts[base:] = (_box_corners(lo, hi) - c).reshape(-1, 3)
        start[n_stat:] = base + np.arange(k, dtype=np.int64) * 8
        npts[n_stat:] = 8
        kind[n_stat:] = 1
        vids[n_stat:] = -1
        out_id = np.concatenate([stat, hid])
    return Prims(pts, start, npts, kind, out_id, vids, scale)


@njit(cache=True, nogil=True, parallel=True)
def _gather_triangles(vertices, faces, welded, c, pts, vids):  # pragma: no cover - numba
    """pts[3 i + k] = vertices[faces[i, k]] - c and vids[i, k] = welded[faces[i, k]] for the
    triangles i of ``faces`` (n, 3)."""
    for i in prange(faces.shape[0]):
        for k in range(3):
            v = faces[i, k]
            for a in range(3):
                pts[3 * i + k, a] = np.float64(vertices[v, a]) - c[a]
            vids[i, k] = welded[v]


# ------------------------------------------------------------------------------ numba kernels
@njit(cache=True, nogil=True)
def _tri_box_overlap(a, b, c, half, tol):  # pragma: no cover - numba
    """Separating-axis test of a triangle (corners relative to the box centre) against the box
    [-half, half] grown by ``tol``: True unless an axis separates them (13 axes)."""
    hx, hy, hz = half[0] + tol, half[1] + tol, half[2] + tol
    # Box axes.
    for k in range(3):
        hk = hx if k == 0 else (hy if k == 1 else hz)
        if min(a[k], b[k], c[k]) > hk or max(a[k], b[k], c[k]) < -hk:
            return False
    e = np.empty((3, 3))
    for k in range(3):
        e[0, k] = b[k] - a[k]
        e[1, k] = c[k] - b[k]
        e[2, k] = a[k] - c[k]
    # Triangle normal.
    nx = e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1]
    ny = e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2]
    nz = e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]
    d = nx * a[0] + ny * a[1] + nz * a[2]
    r = hx * abs(nx) + hy * abs(ny) + hz * abs(nz)
    if abs(d) > r:
        return False
    # Edge x box-axis cross products.
    for i in range(3):
        for k in range(3):
            # axis = unit_k x e_i
            ax = 0.0
            ay = 0.0
            az = 0.0
            if k == 0:
                ay, az = -e[i, 2], e[i, 1]
            elif k == 1:
                ax, az = e[i, 2], -e[i, 0]
            else:
                ax, ay = -e[i, 1], e[i, 0]
            pa = ax * a[0] + ay * a[1] + az * a[2]
            pb = ax * b[0] + ay * b[1] + az * b[2]
            pc = ax * c[0] + ay * c[1] + az * c[2]
            rr = hx * abs(ax) + hy * abs(ay) + hz * abs(az)
            if min(pa, pb, pc) > rr or max(pa, pb, pc) < -rr:
                return False
    return True


@njit(cache=True, nogil=True, parallel=True)
def _inside_box(pts, start, npts, bounds, half, tol, plane_tol, out):  # pragma: no cover
    for p in prange(start.shape[0]):
        s = start[p]
        out[p] = False
        if npts[p] == 3:
            a = pts[s]
            b = pts[s + 1]
            c = pts[s + 2]
            if not _tri_box_overlap(a, b, c, half, tol):
                continue
            # A flat (or point) cell lying in the triangle's own plane sees it edge-on from
            # every eye: the projection has no area, so it is not visible.
            ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
            vx, vy, vz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
            nx = uy * vz - uz * vy
            ny = uz * vx - ux * vz
            nz = ux * vy - uy * vx
            nn = np.sqrt(nx * nx + ny * ny + nz * nz)
            on = True
            for k in range(8):
                cx = half[0] if k & 1 else -half[0]
                cy = half[1] if k & 2 else -half[1]
                cz = half[2] if k & 4 else -half[2]
                dist = nx * (cx - a[0]) + ny * (cy - a[1]) + nz * (cz - a[2])
                if abs(dist) > plane_tol * nn:
                    on = False
                    break
            out[p] = not on
        else:
            ok = True
            for k in range(3):
                if bounds[p, 0, k] > half[k] + tol or bounds[p, 1, k] < -half[k] - tol:
                    ok = False
            out[p] = ok


def inside_box(prims: Prims, half: np.ndarray, bounds: np.ndarray | None = None) -> np.ndarray:
    """(n,) bool: primitives that touch the cell box (centred, half sizes ``half`` (3,) metres).
    ``bounds``: their ``prim_bounds`` when the caller has them already.

    An eye inside the box may stand right next to such a primitive, so it is visible (the
    segment from an eye to the side plane it looks through lies in the box). The box is grown
    by a few ulps of the coordinates so rounding cannot drop a touching triangle.
    """
    out = np.zeros(len(prims), dtype=np.bool_)
    if len(prims):
        ulp = np.spacing(max(prims.scale, float(np.max(np.abs(half))), 1.0))
        if bounds is None:
            bounds = prim_bounds(prims)
        _inside_box(prims.pts, prims.start, prims.npts, bounds,
                    np.asarray(half, dtype=np.float64), 64.0 * ulp, 16.0 * ulp, out)
    return out


@njit(cache=True, nogil=True, parallel=True)
def _solid(pts, start, npts, grown, tol, out):  # pragma: no cover - numba
    for p in prange(start.shape[0]):
        s = start[p]
        out[p] = npts[p] == 3 and not _tri_box_overlap(pts[s], pts[s + 1], pts[s + 2], grown,
                                                        tol)


def solid_mask(prims: Prims, half: np.ndarray, clearance: float = NEAR_CLEARANCE
               ) -> np.ndarray:
    """(n,) uint8: 1 for the triangles that may occlude, those farther than ``clearance``
    metres from the cell box (centred, half sizes ``half`` (3,) metres) at every point.

    A client draws with a near plane (``raster.camera.DEFAULT_NEAR``; at most sqrt(3) times
    that along the ray in a 90 degree view, ``topology.NEAR_CLEARANCE``): an eye in the cell
    standing closer than that to a wall has the wall cut away and sees what lies behind it. A
    triangle meeting the box grown by ``clearance`` (a box, so a little more than the points
    that near) is therefore an occludee only. Hulls never occlude (0)."""
    out = np.zeros(len(prims), dtype=np.uint8)
    if len(prims):
        ulp = np.spacing(max(prims.scale, float(np.max(np.abs(half))), 1.0))
        grown = np.asarray(half, dtype=np.float64) + float(clearance)
        ok = np.zeros(len(prims), dtype=np.bool_)
        _solid(prims.pts, prims.start, prims.npts, grown, 64.0 * ulp, ok)
        out[ok] = 1
    return out


@njit(cache=True, nogil=True, parallel=True)
def _bounds(pts, start, npts, out):  # pragma: no cover - numba
    for p in prange(start.shape[0]):
        s = start[p]
        for k in range(3):
            lo = np.inf
            hi = -np.inf
            for i in range(npts[p]):
                lo = min(lo, pts[s + i, k])
                hi = max(hi, pts[s + i, k])
            out[p, 0, k] = lo
            out[p, 1, k] = hi


def prim_bounds(prims: Prims) -> np.ndarray:
    """(n, 2, 3) float64 bounding box [min, max] of each primitive, relative to the cell
    centre, metres."""
    out = np.empty((len(prims), 2, 3))
    if len(prims):
        _bounds(prims.pts, prims.start, prims.npts, out)
    return out


def box_gaps(prims: Prims, half: np.ndarray, bounds: np.ndarray | None = None) -> np.ndarray:
    """(n,) float64 distance (metres) from the cell box (centred, half sizes ``half``) to each
    primitive's bounding box (``bounds``: its ``prim_bounds``, computed when not given): no
    point of the primitive is nearer to the box."""
    b = prim_bounds(prims) if bounds is None else bounds
    out = np.empty(len(b))
    _gaps(np.ascontiguousarray(b), np.asarray(half, dtype=np.float64), out)
    return out


@njit(cache=True, nogil=True, parallel=True)
def _gaps(b, h, out):  # pragma: no cover - numba
    for p in prange(b.shape[0]):
        s = 0.0
        for k in range(3):
            g = max(0.0, max(b[p, 0, k] - h[k], -h[k] - b[p, 1, k]))
            s += g * g
        out[p] = np.sqrt(s)


def distance_order(prims: Prims, half: np.ndarray, bounds: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Primitive indices sorted by the distance from the cell box to each primitive's bounding
    box: the approximate front-to-back order of every per-pixel list (Sec. 5: sort once, then
    fill the lists in that order instead of sorting each list).

    Returns
    -------
    order : (n,) int64, nondecreasing in ``gap``.
    gap : (n,) float64 per primitive (``box_gaps``); the resolution's early-z cut relies on
        every list being nondecreasing in it.
    """
    gap = box_gaps(prims, half, bounds)
    return np.argsort(gap, kind="stable").astype(np.int64), gap


@njit(cache=True, nogil=True)
def face_reach(bounds, order, axes, upper, thresholds, out):  # pragma: no cover - numba
    """out[f, t]: whether primitive ``order[t]``'s box (``bounds`` (n, 2, 3), ``prim_bounds``)
    reaches threshold f (at most 8) along axis ``axes[f]`` (F,): its maximum at or beyond
    ``thresholds[f]`` where ``upper[f]``, its minimum at or before it otherwise. The boxes
    are read in their own order into a byte of bits per primitive, which ``order`` then
    gathers: gathering the boxes themselves in ``order`` (numpy's way, per face) missed the
    cache at every primitive."""
    bits = np.zeros(bounds.shape[0], dtype=np.uint8)
    for p in range(bounds.shape[0]):
        b = 0
        for f in range(axes.shape[0]):
            a = axes[f]
            if (bounds[p, 1, a] >= thresholds[f]) if upper[f] else \
                    (bounds[p, 0, a] <= thresholds[f]):
                b |= 1 << f
        bits[p] = b
    for t in range(order.shape[0]):
        b = bits[order[t]]
        for f in range(axes.shape[0]):
            out[f, t] = (b >> f) & 1 != 0


@njit(cache=True, nogil=True)
def run_boxes(pts, starts, m, leaf, corners):  # pragma: no cover - numba
    """Per run L of triangles [starts[L], starts[L + 1]) (the last ends at ``m``; triangle i's
    points are rows 3i..3i+2 of ``pts``): leaf[i] = L for its triangles, and the 8 corners
    of its box (rows 8L..8L+7 of ``corners``; corner c takes the maximum of axis k where bit k
    of c is set)."""
    n_runs = starts.shape[0]
    for r in range(n_runs):
        a = starts[r]
        b = starts[r + 1] if r + 1 < n_runs else m
        lo0 = lo1 = lo2 = np.inf
        hi0 = hi1 = hi2 = -np.inf
        for i in range(a, b):
            leaf[i] = r
            for v in range(3 * i, 3 * i + 3):
                lo0 = min(lo0, pts[v, 0])
                hi0 = max(hi0, pts[v, 0])
                lo1 = min(lo1, pts[v, 1])
                hi1 = max(hi1, pts[v, 1])
                lo2 = min(lo2, pts[v, 2])
                hi2 = max(hi2, pts[v, 2])
        for c in range(8):
            corners[8 * r + c, 0] = hi0 if c & 1 else lo0
            corners[8 * r + c, 1] = hi1 if c & 2 else lo1
            corners[8 * r + c, 2] = hi2 if c & 4 else lo2
