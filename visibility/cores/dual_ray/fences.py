"""The occluders of a 2.5D scene as wall *strips* (fence pieces).

A static wall triangle (``|n_y| <= WALL_NY``) is cut, along its horizontal direction u, at its
middle corner into (at most) two pieces; over each, its vertical section is a strip whose
bottom and top are linear in u. A piece is an XZ segment ``p -> q`` with the strip's bottom and
top at both ends. Pieces over the same XZ segment whose strips touch stack into one (a quad's
two triangles, a facade's rows: contiguity is checked at both ends, which suffices since the
gap between a convex bottom and a concave top is concave); pieces that continue each other
along a line with the same bottom and top merge (a facade's columns). So a city's facades
become a few strips each, every one inside the walls it comes from.

A wall that leans (its top is off its foot's vertical plane by more than ``JOIN``) is not
flattened onto a vertical plane, which would move it, possibly across a slit next to it: its
pieces are its section at mid-height, parametrized along the wall's horizontal direction, with
``lean`` = (how far the real wall strays from that vertical plane over the piece's heights,
metres; how fast it strays, metres per metre of height). They neither stack nor merge, and
each shaft shrinks them (``dual_space.cut_piece``) by how far along a ray of that shaft the
real wall can be from where the ray crosses the piece.

What is not a wall (roofs, terrain, trees, street furniture), moving triangles and walls
tilted past ``WALL_NY`` never occlude: they are occludees only.

Built once per scene (``scene_fences``), with a uniform XZ grid that lists the pieces crossing
each grid cell, for the shaft queries.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from numba import njit

from visibility.cores.dual_ray.groups import PieceGrid, Pieces
from visibility.scene import Scene
from visibility.scene_cache import per_scene
from visibility.topology import NEAR_CLEARANCE

#: A triangle is a wall, an occluder, when its normal is within this of horizontal (|n_y|; 0.02
#: is 1.1 degrees). The 2.5D analysis takes walls up to 0.1; walls between the two are
#: occludees only here, since flattening them onto a vertical plane would move them.
WALL_NY = 0.02
#: Shortest fence piece kept, metres.
MIN_LENGTH = 1e-4
#: Rounding of end points when pieces are compared (same XZ segment), metres.
SNAP = 1e-3
#: Largest mismatch of end points or heights (metres) at which pieces still join; joined
#: strips shrink by it, so they stay inside the walls they come from.
JOIN = 1e-6
#: Target pieces per grid cell of the query grid.
PIECES_PER_CELL = 4.0


@dataclass
class Fences:
    """Fence pieces and the grid that finds them.

    Attributes
    ----------
    seg : (k, 4) float64 XZ end points ``[px, pz, qx, qz]``, metres.
    top, bot : (k, 2) float64 the strip's top and bottom at p and at q, metres.
    lean : (k, 2) float64 per piece: the most the real wall strays horizontally from the
        piece's vertical plane at any height of the strip (metres), and its stray per metre of
        height; (0, 0) for the walls taken as vertical.
    vid : (k, 2) int64 ids of p and q: equal ids, the same XZ point exactly (pieces that meet
        there join into one occluder in a shaft where both reach it, ``dual_space.occluders``).
    grid_lo : (2,) float64 XZ corner of the grid; ``grid_step`` its cell side; ``grid_n``
        (2,) int64 cells along X and Z.
    cell_start : (nx * nz + 1,) int64 CSR offsets; ``cell_items`` (k',) int64 piece ids per cell
        (highest top first)
        (a piece is listed in every cell its bounds overlap).
    walls : number of wall triangles the pieces come from.
    build_seconds : time the build took.
    """

    seg: np.ndarray
    top: np.ndarray
    bot: np.ndarray
    lean: np.ndarray
    vid: np.ndarray
    grid_lo: np.ndarray
    grid_step: float
    grid_n: np.ndarray
    cell_start: np.ndarray
    cell_items: np.ndarray
    walls: int
    build_seconds: float

    def __len__(self) -> int:
        return int(len(self.seg))

    @property
    def pieces(self) -> Pieces:
        """The pieces as the shaft kernels take them."""
        return Pieces(self.seg, self.top, self.bot, self.lean, self.vid)

    @property
    def grid(self) -> PieceGrid:
        """The grid as the shaft kernels take it."""
        return PieceGrid(self.grid_lo, float(self.grid_step), self.grid_n, self.cell_start,
                         self.cell_items)


@njit(cache=True, nogil=True)
def _span_at(us, ys, u):  # pragma: no cover - numba
    """(lowest, highest) height of the triangle with corners (us, ys) in its plane at ``u``."""
    lo = np.inf
    hi = -np.inf
    for a in range(3):
        b = (a + 1) % 3
        ua, ub = us[a], us[b]
        if ua > ub:
            ua, ub = ub, ua
        if u < ua - 1e-12 or u > ub + 1e-12:
            continue
        if ub - ua <= 1e-12:
            y0, y1 = ys[a], ys[b]
            lo = min(lo, y0, y1)
            hi = max(hi, y0, y1)
        else:
            w = (u - us[a]) / (us[b] - us[a])
            w = min(max(w, 0.0), 1.0)
            y = ys[a] + w * (ys[b] - ys[a])
            lo = min(lo, y)
            hi = max(hi, y)
    return lo, hi


@njit(cache=True, nogil=True)
def _pieces(tri, out_seg, out_top, out_bot, out_lean):  # pragma: no cover - numba
    """Pieces of wall triangles ``tri`` (t, 3, 3): over each of the two u-intervals between
    its corners (u along the wall), the triangle's section is a strip whose bottom and top are
    linear. Returns the count written.

    A vertical triangle (one that strays at most ``JOIN`` from a vertical plane) is taken on
    the line through its two corners farthest apart in XZ, lean (0, 0). A leaning one is taken
    in the frame of its plane: u along its horizontal direction, the piece on the vertical
    plane through its section at mid-height; each (u, height) of the strip is a point of the
    triangle, which lies within ``lean[0]`` of the strip horizontally (``_lean_frame``)."""
    k = 0
    us = np.empty(3)
    ys = np.empty(3)
    for t in range(tri.shape[0]):
        ok, ox, oz, ux, uz, lam, slope = _lean_frame(tri[t])
        if not ok:
            continue
        for c in range(3):
            us[c] = (tri[t, c, 0] - ox) * ux + (tri[t, c, 2] - oz) * uz
            ys[c] = tri[t, c, 1]
        su = np.sort(us)
        for q in range(2):
            u0, u1 = su[q], su[q + 1]
            if u1 - u0 <= 1e-9:
                continue
            lo0, hi0 = _span_at(us, ys, u0)
            lo1, hi1 = _span_at(us, ys, u1)
            if not (hi0 >= lo0 and hi1 >= lo1):
                continue
            out_seg[k, 0] = ox + u0 * ux
            out_seg[k, 1] = oz + u0 * uz
            out_seg[k, 2] = ox + u1 * ux
            out_seg[k, 3] = oz + u1 * uz
            out_top[k, 0] = hi0
            out_top[k, 1] = hi1
            out_bot[k, 0] = lo0
            out_bot[k, 1] = lo1
            out_lean[k, 0] = lam
            out_lean[k, 1] = slope
            k += 1
    return k


@njit(cache=True, nogil=True)
def _lean_frame(t):  # pragma: no cover - numba
    """The frame of a wall triangle t (3, 3) for ``_pieces``: (ok, origin x, origin z, unit
    direction x, z along the wall, lean in metres, lean per metre of height).

    The plane n . p = d has, at height y, its horizontal section on the line
    h . (x, z) = (d - n_y y) / |n_h| (h the unit horizontal normal): it moves by
    |n_y| / |n_h| per metre of height. From the section at mid-height, the triangle strays at
    most that times half its height."""
    ex, ey, ez = t[1, 0] - t[0, 0], t[1, 1] - t[0, 1], t[1, 2] - t[0, 2]
    fx, fy, fz = t[2, 0] - t[0, 0], t[2, 1] - t[0, 1], t[2, 2] - t[0, 2]
    nx = ey * fz - ez * fy
    ny = ez * fx - ex * fz
    nz = ex * fy - ey * fx
    nh = np.sqrt(nx * nx + nz * nz)
    y0 = min(t[0, 1], t[1, 1], t[2, 1])
    y1 = max(t[0, 1], t[1, 1], t[2, 1])
    slope = abs(ny) / nh if nh > 0.0 else np.inf
    lam = 0.5 * (y1 - y0) * slope
    if not lam > JOIN:
        # Vertical: the line through the two corners farthest apart in XZ.
        best = -1.0
        ia, ib = 0, 1
        for a in range(3):
            for b in range(a + 1, 3):
                dx = t[b, 0] - t[a, 0]
                dz = t[b, 2] - t[a, 2]
                d2 = dx * dx + dz * dz
                if d2 > best:
                    best = d2
                    ia, ib = a, b
        if best <= 0.0:
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        ln = np.sqrt(best)
        return (True, t[ia, 0], t[ia, 2], (t[ib, 0] - t[ia, 0]) / ln,
                (t[ib, 2] - t[ia, 2]) / ln, 0.0, 0.0)
    hx, hz = nx / nh, nz / nh
    # The section at mid-height: its offset along h from corner 0's.
    ym = 0.5 * (y0 + y1)
    shift = -(ny / nh) * (ym - t[0, 1])
    return True, t[0, 0] + shift * hx, t[0, 2] + shift * hz, -hz, hx, lam, slope


@njit(cache=True, nogil=True)
def _stack(order, grp, top, bot, keep, tol):  # pragma: no cover - numba
    """Within each group of pieces over one XZ segment (``grp``, ``order`` sorting by group
    and bottom), join the strips that touch or overlap into one (bottom of the first, the
    higher top) while they stay contiguous at both ends: the gap between a convex bottom and a
    concave top is concave, so checking the ends suffices. Joined pieces are dropped from
    ``keep``; the first of each run holds the union."""
    n = len(order)
    i = 0
    while i < n:
        a = order[i]
        keep[a] = True
        j = i + 1
        while j < n:
            b = order[j]
            if grp[b] != grp[a]:
                break
            if bot[b, 0] > top[a, 0] + tol or bot[b, 1] > top[a, 1] + tol:
                break
            if top[b, 0] >= top[a, 0] and top[b, 1] >= top[a, 1]:
                top[a, 0] = top[b, 0]
                top[a, 1] = top[b, 1]
            elif not (top[b, 0] <= top[a, 0] and top[b, 1] <= top[a, 1]):
                # Crossing tops: either alone is inside the union; keep the higher on average.
                if top[b, 0] + top[b, 1] > top[a, 0] + top[a, 1]:
                    top[a, 0] = top[b, 0]
                    top[a, 1] = top[b, 1]
            j += 1
        i = j


@njit(cache=True, nogil=True)
def _merge_runs(seg, top, bot, order, key_line, snap):  # pragma: no cover - numba
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
        merged = False
        j = i + 1
        while j < n:
            b = order[j]
            if key_line[b] != key_line[a]:
                break
            gap = abs(seg[b, 0] - seg[a, 2]) + abs(seg[b, 1] - seg[a, 3])
            if gap > snap or abs(top[b, 0] - top[a, 1]) > snap or \
                    abs(bot[b, 0] - bot[a, 1]) > snap:
                break
            la = np.hypot(seg[a, 2] - seg[a, 0], seg[a, 3] - seg[a, 1])
            lb = np.hypot(seg[b, 2] - seg[b, 0], seg[b, 3] - seg[b, 1])
            if la <= 0.0 or lb <= 0.0:
                break
            sa = (top[a, 1] - top[a, 0]) / la
            sb = (top[b, 1] - top[b, 0]) / lb
            ba = (bot[a, 1] - bot[a, 0]) / la
            bb = (bot[b, 1] - bot[b, 0]) / lb
            if abs(sa - sb) * (la + lb) > snap or abs(ba - bb) * (la + lb) > snap:
                break
            # The joint's heights are taken inside both pieces' (within snap): lower top,
            # higher bottom, so the merged strip stays inside the two.
            seg[a, 2] = seg[b, 2]
            seg[a, 3] = seg[b, 3]
            top[a, 1] = top[b, 1]
            bot[a, 1] = bot[b, 1]
            merged = True
            j += 1
        if merged:
            # Heights matched within ``snap`` only: shrink the strip by it to stay inside.
            top[a, 0] -= snap
            top[a, 1] -= snap
            bot[a, 0] += snap
            bot[a, 1] += snap
        i = j
    return keep


def _orient(seg: np.ndarray, top: np.ndarray, bot: np.ndarray) -> None:
    """Make every piece run in increasing x (then z), in place, so equal segments compare."""
    flip = (seg[:, 2] < seg[:, 0]) | ((seg[:, 2] == seg[:, 0]) & (seg[:, 3] < seg[:, 1]))
    seg[flip] = seg[flip][:, [2, 3, 0, 1]]
    top[flip] = top[flip][:, ::-1]
    bot[flip] = bot[flip][:, ::-1]


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
    """Fence pieces of ``scene``'s walls, stacked and merged, with their query grid."""
    t0 = time.perf_counter()
    walls = np.flatnonzero(wall_mask(scene))
    tri = np.ascontiguousarray(scene.vertices[scene.faces[walls]], dtype=np.float64)
    seg = np.empty((2 * len(tri), 4))
    top = np.empty((2 * len(tri), 2))
    bot = np.empty((2 * len(tri), 2))
    lean = np.empty((2 * len(tri), 2))
    k = _pieces(tri, seg, top, bot, lean) if len(tri) else 0
    seg, top, bot, lean = seg[:k], top[:k], bot[:k], lean[:k]
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    ok = length >= MIN_LENGTH
    seg, top, bot, lean = seg[ok], top[ok], bot[ok], lean[ok]
    _orient(seg, top, bot)
    if len(seg):
        # Pieces over one XZ segment (a facade's rows, a quad's two triangles) stack into one
        # strip where they are contiguous. Segments compare after rounding to SNAP; the
        # stacked strip keeps the first piece's exact end points. Leaning pieces stay alone
        # (each its own group and line): their strips are not where their walls are.
        leaning = np.flatnonzero(lean[:, 0] > 0.0)
        q = np.round(seg / SNAP).astype(np.int64)
        _, grp = np.unique(q, axis=0, return_inverse=True)
        grp = grp.reshape(-1).astype(np.int64)
        grp[leaning] = grp.max() + 1 + np.arange(len(leaning))
        order = np.lexsort((bot[:, 0] + bot[:, 1], grp)).astype(np.int64)
        keep = np.zeros(len(seg), dtype=bool)
        seg, top, bot = (np.ascontiguousarray(a) for a in (seg, top, bot))
        _stack(order, grp, top, bot, keep, JOIN)
        seg, top, bot, lean = (np.ascontiguousarray(a[keep]) for a in (seg, top, bot, lean))
        leaning = np.flatnonzero(lean[:, 0] > 0.0)
        # Runs along one line (a facade in columns): merge.
        d = seg[:, 2:] - seg[:, :2]
        ln = np.hypot(d[:, 0], d[:, 1])
        ang = np.round(np.arctan2(d[:, 1], d[:, 0]) / 1e-6).astype(np.int64)
        nx, nz = -d[:, 1] / ln, d[:, 0] / ln
        off = np.round((seg[:, 0] * nx + seg[:, 1] * nz) / SNAP).astype(np.int64)
        _, key_line = np.unique(np.stack([ang, off], axis=1), axis=0, return_inverse=True)
        key_line = key_line.reshape(-1).astype(np.int64)
        key_line[leaning] = key_line.max() + 1 + np.arange(len(leaning))
        along = seg[:, 0] * (d[:, 0] / ln) + seg[:, 1] * (d[:, 1] / ln)
        order = np.lexsort((along, key_line)).astype(np.int64)
        keep = _merge_runs(seg, top, bot, order, key_line, JOIN)
        seg, top, bot, lean = (np.ascontiguousarray(a[keep]) for a in (seg, top, bot, lean))
    grid = _grid(seg, top)
    if len(seg):
        ends = np.concatenate([seg[:, :2], seg[:, 2:]])
        _, inv = np.unique(ends, axis=0, return_inverse=True)
        vid = np.ascontiguousarray(inv.reshape(-1).reshape(2, -1).T).astype(np.int64)
    else:
        vid = np.zeros((0, 2), dtype=np.int64)
    return Fences(seg, top, bot, np.ascontiguousarray(lean), vid, *grid, walls=len(walls),
                  build_seconds=time.perf_counter() - t0)


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


def _grid(seg: np.ndarray, top: np.ndarray
          ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """Uniform XZ grid over the pieces (k, 4) with their tops (k, 2): (lo, step, (nx, nz),
    cell_start, cell_items), each cell's items highest top first."""
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
    # Each cell's pieces highest top first: a shaft query stops at the first piece under its
    # ceiling there (``dual_space._gather``).
    cell = np.repeat(np.arange(len(counts)), np.diff(start))
    items = items[np.lexsort((-np.maximum(top[items, 0], top[items, 1]), cell))]
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


def near_pieces(fences: Fences, alo: np.ndarray, ahi: np.ndarray,
                clearance: float = NEAR_CLEARANCE) -> np.ndarray:
    """(k,) bool: the pieces that come within ``clearance`` metres of the cell box
    [``alo``, ``ahi``] (each (3,) metres), tested against the box grown by it (a box, so a
    little more than the points that near): a client in the cell standing that close to such
    a wall has its near plane (``topology.NEAR_CLEARANCE``) cut it away and sees behind it.

    Separating axes in XZ (x, z and the piece's normal) and the height ranges."""
    if len(fences) == 0:
        return np.zeros(0, dtype=bool)
    c = float(clearance)
    lo = np.asarray(alo, dtype=np.float64) - c
    hi = np.asarray(ahi, dtype=np.float64) + c
    seg = fences.seg
    px, pz, qx, qz = seg[:, 0], seg[:, 1], seg[:, 2], seg[:, 3]
    apart = (np.maximum(px, qx) < lo[0]) | (np.minimum(px, qx) > hi[0])
    apart |= (np.maximum(pz, qz) < lo[2]) | (np.minimum(pz, qz) > hi[2])
    apart |= (np.maximum(fences.top[:, 0], fences.top[:, 1]) < lo[1])
    apart |= (np.minimum(fences.bot[:, 0], fences.bot[:, 1]) > hi[1])
    # The piece's normal in XZ: the rectangle's corners all on one side of its line.
    nx, nz = pz - qz, qx - px
    d = nx * px + nz * pz
    cx = np.stack([lo[0], hi[0], hi[0], lo[0]])
    cz = np.stack([lo[2], lo[2], hi[2], hi[2]])
    side = nx[:, None] * cx[None, :] + nz[:, None] * cz[None, :] - d[:, None]
    apart |= np.all(side > 0.0, axis=1) | np.all(side < 0.0, axis=1)
    return ~apart


def cell_fences(fences: Fences, drop: np.ndarray) -> Fences:
    """``fences`` with the pieces ``drop`` (k,) bool made unable to occlude: their bottoms
    raised far above any shaft's floor, so ``dual_space.cut_piece`` keeps none of them (their
    tops, and so the grid's highest-top-first order, stay as they are)."""
    bot = fences.bot.copy()
    bot[drop] = 1e300
    return dataclasses.replace(fences, bot=bot)
