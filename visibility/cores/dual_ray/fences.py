"""The occluders of a 2.5D scene as *fences*: vertical walls, each closed downwards.

A static wall triangle (``|n_y| <= WALL_NY``) occludes as its downward closure: everything under
its top edge over its XZ footprint, a vertical strip with a piecewise-linear top (the upper hull
of its corners). That closure is what the reduction to the ceiling plane needs (Observation 1
lifts a free segment upward; a set closed downwards cannot catch the lifted one unless it
caught the original). A wall of a 2.5D scene stands on the ground, so its closure adds only
the solid under it. Each triangle gives one or two *pieces*: an XZ segment ``p -> q`` with the
fence top ``yp -> yq`` linear along it.

What is not a wall (roofs, terrain, trees, street furniture), moving triangles and walls thinner
than ``MIN_LENGTH`` never occlude: they are occludees only. Pieces over the same XZ segment (a
facade split into rows) keep the highest; pieces that continue each other along a line at the
same top (a facade split into columns) are merged, so a city's facades become a few pieces each.

Built once per scene (``scene_fences``), with a uniform XZ grid (``FenceGrid``) that lists the
pieces crossing each grid cell, for the shaft queries.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit

from visibility.cores.dual_ray.cache import per_scene
from visibility.scene import Scene

#: A triangle is a wall, an occluder, when its normal is within this of horizontal (|n_y|; 0.02
#: is 1.1 degrees). The 2.5D analysis takes walls up to 0.1; walls between the two are
#: occludees only here, since flattening them onto a vertical plane would move them.
WALL_NY = 0.02
#: Shortest fence piece kept, metres.
MIN_LENGTH = 1e-4
#: Rounding of end points and tops when pieces are compared (dedupe, merge), metres.
SNAP = 1e-3
#: Target pieces per grid cell of the query grid.
PIECES_PER_CELL = 4.0


@dataclass
class Fences:
    """Fence pieces and the grid that finds them.

    Attributes
    ----------
    seg : (k, 4) float64 XZ end points ``[px, pz, qx, qz]``, metres.
    top : (k, 2) float64 fence top at p and at q, metres.
    grid_lo : (2,) float64 XZ corner of the grid; ``grid_step`` its cell side; ``grid_n``
        (2,) int64 cells along X and Z.
    cell_start : (nx * nz + 1,) int64 CSR offsets; ``cell_items`` (k',) int64 piece ids per cell
        (a piece is listed in every cell its bounds overlap).
    walls : number of wall triangles the pieces come from.
    build_seconds : time the build took.
    """

    seg: np.ndarray
    top: np.ndarray
    grid_lo: np.ndarray
    grid_step: float
    grid_n: np.ndarray
    cell_start: np.ndarray
    cell_items: np.ndarray
    walls: int
    build_seconds: float

    def __len__(self) -> int:
        return int(len(self.seg))


@njit(cache=True, nogil=True)
def _pieces(tri, out_seg, out_top):  # pragma: no cover - numba
    """Upper-hull pieces of vertical triangles ``tri`` (t, 3, 3); returns the count written."""
    k = 0
    for t in range(tri.shape[0]):
        # Horizontal direction of the wall: the longest XZ extent between two corners.
        best = -1.0
        ia, ib = 0, 1
        for a in range(3):
            for b in range(a + 1, 3):
                dx = tri[t, b, 0] - tri[t, a, 0]
                dz = tri[t, b, 2] - tri[t, a, 2]
                d2 = dx * dx + dz * dz
                if d2 > best:
                    best = d2
                    ia, ib = a, b
        if best <= 0.0:
            continue
        ln = np.sqrt(best)
        ux = (tri[t, ib, 0] - tri[t, ia, 0]) / ln
        uz = (tri[t, ib, 2] - tri[t, ia, 2]) / ln
        ox, oz = tri[t, ia, 0], tri[t, ia, 2]
        us = np.empty(3)
        ys = np.empty(3)
        for c in range(3):
            us[c] = (tri[t, c, 0] - ox) * ux + (tri[t, c, 2] - oz) * uz
            ys[c] = tri[t, c, 1]
        # Sort the corners by u (ties: higher first, so the hull starts at the top).
        order = np.argsort(us - 1e-12 * ys)
        u0, u1, u2 = us[order[0]], us[order[1]], us[order[2]]
        y0, y1, y2 = ys[order[0]], ys[order[1]], ys[order[2]]
        # The middle corner is on the upper hull when it lies above the chord 0 -> 2.
        if u2 - u0 <= 0.0:
            continue
        chord = y0 + (y2 - y0) * (u1 - u0) / (u2 - u0)
        if u1 - u0 < 1e-12:
            # Vertical left edge: the top there is the higher of corners 0 and 1.
            ya = max(y0, y1)
            out_seg[k, 0] = ox + u0 * ux
            out_seg[k, 1] = oz + u0 * uz
            out_seg[k, 2] = ox + u2 * ux
            out_seg[k, 3] = oz + u2 * uz
            out_top[k, 0] = ya
            out_top[k, 1] = y2
            k += 1
        elif u2 - u1 < 1e-12:
            yb = max(y1, y2)
            out_seg[k, 0] = ox + u0 * ux
            out_seg[k, 1] = oz + u0 * uz
            out_seg[k, 2] = ox + u2 * ux
            out_seg[k, 3] = oz + u2 * uz
            out_top[k, 0] = y0
            out_top[k, 1] = yb
            k += 1
        elif y1 > chord:
            out_seg[k, 0] = ox + u0 * ux
            out_seg[k, 1] = oz + u0 * uz
            out_seg[k, 2] = ox + u1 * ux
            out_seg[k, 3] = oz + u1 * uz
            out_top[k, 0] = y0
            out_top[k, 1] = y1
            k += 1
            out_seg[k, 0] = ox + u1 * ux
            out_seg[k, 1] = oz + u1 * uz
            out_seg[k, 2] = ox + u2 * ux
            out_seg[k, 3] = oz + u2 * uz
            out_top[k, 0] = y1
            out_top[k, 1] = y2
            k += 1
        else:
            out_seg[k, 0] = ox + u0 * ux
            out_seg[k, 1] = oz + u0 * uz
            out_seg[k, 2] = ox + u2 * ux
            out_seg[k, 3] = oz + u2 * uz
            out_top[k, 0] = y0
            out_top[k, 1] = y2
            k += 1
    return k


@njit(cache=True, nogil=True)
def _merge_runs(seg, top, order, key_line, snap):  # pragma: no cover - numba
    """Merge pieces that continue each other: ``order`` sorts them by line and by start along
    it; consecutive pieces on one line (``key_line``) whose ends meet (within ``snap``) at the
    same top, with the same top slope, become one. Returns a keep mask (merged pieces are
    extended in place)."""
    n = len(order)
    keep = np.zeros(len(seg), dtype=np.bool_)
    i = 0
    while i < n:
        a = order[i]
        keep[a] = True
        j = i + 1
        while j < n:
            b = order[j]
            if key_line[b] != key_line[a]:
                break
            gap = abs(seg[b, 0] - seg[a, 2]) + abs(seg[b, 1] - seg[a, 3])
            if gap > snap or abs(top[b, 0] - top[a, 1]) > snap:
                break
            la = np.hypot(seg[a, 2] - seg[a, 0], seg[a, 3] - seg[a, 1])
            lb = np.hypot(seg[b, 2] - seg[b, 0], seg[b, 3] - seg[b, 1])
            if la <= 0.0 or lb <= 0.0:
                break
            sa = (top[a, 1] - top[a, 0]) / la
            sb = (top[b, 1] - top[b, 0]) / lb
            if abs(sa - sb) * (la + lb) > snap:
                break
            seg[a, 2] = seg[b, 2]
            seg[a, 3] = seg[b, 3]
            top[a, 1] = top[b, 1]
            j += 1
        i = j
    return keep


def _orient(seg: np.ndarray, top: np.ndarray) -> None:
    """Make every piece run in increasing x (then z), in place, so equal segments compare."""
    flip = (seg[:, 2] < seg[:, 0]) | ((seg[:, 2] == seg[:, 0]) & (seg[:, 3] < seg[:, 1]))
    seg[flip] = seg[flip][:, [2, 3, 0, 1]]
    top[flip] = top[flip][:, ::-1]


def wall_mask(scene: Scene, wall_ny: float = WALL_NY) -> np.ndarray:
    """(n_triangles,) bool: valid, static faces within ``wall_ny`` of vertical (occluders)."""
    m = scene.n_triangles
    out = np.zeros(m, dtype=bool)
    valid = np.flatnonzero(scene.valid_faces)
    if len(valid) == 0:
        return out
    f = scene.faces[valid]
    if scene.states is not None and scene.states.shape[0] > 1:
        st = scene.states
        vmove = np.any(np.any(st != st[:1], axis=0), axis=1)
        static = ~np.any(vmove[f], axis=1)
    else:
        static = np.ones(len(valid), dtype=bool)
    tri = scene.vertices[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ny = np.divide(np.abs(n[:, 1]), norm, out=np.ones(len(n)), where=norm > 0)
    out[valid] = static & (ny <= wall_ny) & np.all(np.isfinite(tri), axis=(1, 2))
    return out


def build_fences(scene: Scene) -> Fences:
    """Fence pieces of ``scene``'s walls, deduplicated and merged, with their query grid."""
    t0 = time.perf_counter()
    walls = np.flatnonzero(wall_mask(scene))
    tri = np.ascontiguousarray(scene.vertices[scene.faces[walls]], dtype=np.float64)
    seg = np.empty((2 * len(tri), 4))
    top = np.empty((2 * len(tri), 2))
    k = _pieces(tri, seg, top) if len(tri) else 0
    seg, top = seg[:k], top[:k]
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    ok = length >= MIN_LENGTH
    seg, top = seg[ok], top[ok]
    _orient(seg, top)
    if len(seg):
        # Same XZ segment (a facade in rows): keep the piece with the highest lower top. Any
        # subset of the occluders is conservative; this one drops only what a kept piece
        # covers when the two tops are parallel, as in a facade grid.
        q = np.round(seg / SNAP).astype(np.int64)
        order = np.lexsort((-np.minimum(top[:, 0], top[:, 1]), q[:, 3], q[:, 2], q[:, 1],
                            q[:, 0]))
        qs = q[order]
        first = np.ones(len(order), dtype=bool)
        first[1:] = np.any(qs[1:] != qs[:-1], axis=1)
        pick = order[first]
        seg, top = np.ascontiguousarray(seg[pick]), np.ascontiguousarray(top[pick])
        # Runs along one line (a facade in columns): merge.
        d = seg[:, 2:] - seg[:, :2]
        ln = np.hypot(d[:, 0], d[:, 1])
        ang = np.round(np.arctan2(d[:, 1], d[:, 0]) / 1e-6).astype(np.int64)
        nx, nz = -d[:, 1] / ln, d[:, 0] / ln
        off = np.round((seg[:, 0] * nx + seg[:, 1] * nz) / SNAP).astype(np.int64)
        _, key_line = np.unique(np.stack([ang, off], axis=1), axis=0, return_inverse=True)
        key_line = key_line.reshape(-1).astype(np.int64)
        along = seg[:, 0] * (d[:, 0] / ln) + seg[:, 1] * (d[:, 1] / ln)
        order = np.lexsort((along, key_line)).astype(np.int64)
        keep = _merge_runs(seg, top, order, key_line, SNAP)
        seg, top = np.ascontiguousarray(seg[keep]), np.ascontiguousarray(top[keep])
    grid = _grid(seg)
    return Fences(seg, top, *grid, walls=len(walls), build_seconds=time.perf_counter() - t0)


@njit(cache=True, nogil=True)
def _fill_grid(seg, x0, z0, step, nx, nz, counts, start, items, mode):  # pragma: no cover
    for i in range(seg.shape[0]):
        i0 = min(max(int((min(seg[i, 0], seg[i, 2]) - x0) / step), 0), nx - 1)
        i1 = min(max(int((max(seg[i, 0], seg[i, 2]) - x0) / step), 0), nx - 1)
        j0 = min(max(int((min(seg[i, 1], seg[i, 3]) - z0) / step), 0), nz - 1)
        j1 = min(max(int((max(seg[i, 1], seg[i, 3]) - z0) / step), 0), nz - 1)
        for a in range(i0, i1 + 1):
            for b in range(j0, j1 + 1):
                c = a * nz + b
                if mode == 0:
                    counts[c] += 1
                else:
                    items[start[c] + counts[c]] = i
                    counts[c] += 1


def _grid(seg: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """Uniform XZ grid over the pieces: (lo, step, (nx, nz), cell_start, cell_items)."""
    if len(seg) == 0:
        return (np.zeros(2), 1.0, np.array([1, 1], dtype=np.int64), np.zeros(2, np.int64),
                np.zeros(0, np.int64))
    lo = np.array([min(seg[:, 0].min(), seg[:, 2].min()), min(seg[:, 1].min(), seg[:, 3].min())])
    hi = np.array([max(seg[:, 0].max(), seg[:, 2].max()), max(seg[:, 1].max(), seg[:, 3].max())])
    ext = np.maximum(hi - lo, 1e-3)
    step = float(np.sqrt(ext[0] * ext[1] * PIECES_PER_CELL / len(seg)))
    step = max(step, float(ext.max()) / 2048.0, 1e-3)
    n = np.minimum(np.ceil(ext / step).astype(np.int64) + 1, 4096)
    counts = np.zeros(int(n[0] * n[1]), dtype=np.int64)
    dummy = np.zeros(1, dtype=np.int64)
    _fill_grid(seg, lo[0], lo[1], step, int(n[0]), int(n[1]), counts, dummy, dummy, 0)
    start = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    items = np.empty(int(start[-1]), dtype=np.int64)
    counts[:] = 0
    _fill_grid(seg, lo[0], lo[1], step, int(n[0]), int(n[1]), counts, start, items, 1)
    return lo, step, n, start, items


def scene_fences(scene: Scene) -> tuple[Fences, float]:
    """The scene's fences, built on first use and cached with the scene.

    Returns
    -------
    fences : the ``Fences``.
    seconds : build time spent by this call (0.0 from the cache).
    """
    fences, built = per_scene(scene, "fences", build_fences)
    return fences, (fences.build_seconds if built else 0.0)
