"""Where a person can walk inside one viewcell, at sub-cell resolution, and view segments there.

``visibility.walkable`` finds walkable ground at cell resolution (a cell is walkable when most of
its 3 x 3 samples agree on a floor). Inside such a cell there can still be walls, counters and
closed solids: a viewcell's rectangle sides can run right through them, and an eye walking those
sides sees what only the inside of a wall sees. This module samples a cell's XZ rectangle on a
finer lattice (``step`` metres) and keeps the points where a standing person fits:

- the vertical line from ``body_height`` below the cell's lowest eye up to its highest eye
  crosses no triangle (no table top, shelf, ceiling or floor slab in the way), and
- the point is not inside a closed solid: the first surface straight above faces up, i.e. the
  line leaves a solid through its top (counter-clockwise winding unless
  ``scene.meta["winding"] == "cw"``), and
- the point is not outside the scene's rooms: of ``WRAP_RAYS`` level rays at the middle eye
  height, fewer than ``WRAP_HITS`` meet a surface within ``WRAP_REACH``, or fewer than
  ``ray_reference.INSIDE_SHARE`` of those meet its back (a game level's void beside its
  walls, which face into its rooms, sees their backs or nothing; a street sees facades, a
  room its walls).

A viewcell's box is one floor level (its Y range is the eye range above that floor), so the
open part of each level a grid column holds comes from that level's own cell.

``walk_segments`` turns the open part into view segments: the outline of each connected open
region, one lattice step in from its edge where the region is large enough (marching squares,
simplified), at the eye heights, cut wherever a segment comes within ``CLEARANCE`` of geometry
to its side or meets it (a wall thinner than the lattice step), ``MARGIN`` short of it. No
returned segment crosses a triangle of the scene.
Conventions: Y-up, right-handed, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from visibility.exact_grid import build_grid, grid_first_hits, ray_triangle
from visibility.raster.hierarchy import candidates_in_box, ready_hierarchy
from visibility.ray_reference import INSIDE_SHARE, back_hits, front_normals
from visibility.scene import Scene
from visibility.walkable import bin_of, bin_triangles

#: Lattice step inside a cell (metres).
STEP = 0.2
#: Most lattice points along a side: a larger cell gets a coarser lattice (a 1 km cell at 0.2 m
#: would test 25M points where its cubemaps cost far less).
MAX_LATTICE = 256
#: How far below the lowest eye the body must be clear, as a share of the scene's lowest eye
#: height above its floor (``meta["eye_range"][0]``, 1.5 m unless a scene says otherwise):
#: knees to eyes, 1 m at 1.5 m, so that table tops and counters block a standing place while
#: seats and low kerbs do not. A share, not metres: in a scene whose eyes stand 1 m above the
#: floor (a game level's units) a 1 m body reached the floor itself and found no open floor.
BODY_SHARE = 2.0 / 3.0
#: The lowest eye height above the floor when a scene does not give one (metres).
EYE_LOW = 1.5
#: Segments stop this far short of a triangle they would meet (metres).
MARGIN = 0.1
#: Segments keep this far from geometry to either side (metres). The visibility cubemap's near
#: plane is 0.05 m away, 0.087 m at its corners: an eye nearer a wall than that sees through it.
CLEARANCE = 0.1
#: Open regions smaller than this are dropped (square metres): gaps between chair legs.
MIN_REGION_AREA = 0.25
#: Level rays per open lattice point that tell the scene's void from its rooms (``_outside``).
WRAP_RAYS = 16
#: How far those rays look for a surface (metres).
WRAP_REACH = 10.0
#: Share of the rays that must meet a surface for the point to be judged at all: beside a
#: level's flat outer wall a quarter of them meet its back within ``WRAP_REACH``.
WRAP_HITS = 0.25
#: Most outline vertices per region and eye height: the outline is simplified (coarser
#: tolerance) until it fits, since each segment costs a full cubemap pass.
MAX_SIDES = 8


@njit(cache=True, nogil=True, inline="always")
def _meet(px, py, pz, dx, dy, dz, tris, i):  # pragma: no cover - numba
    """Parameter t of segment p + t d, t in [0, 1], where it meets triangle ``i`` of ``tris``
    (m, 3, 3) (Moller-Trumbore, both faces: ``ray_reference``'s), or -1.0 where it does not."""
    t = ray_triangle(tris, i, px, py, pz, dx, dy, dz)
    return t if 0.0 <= t <= 1.0 else -1.0


@njit(cache=True, nogil=True)
def _hits_along(p, q, tris, out_t):  # pragma: no cover - numba
    """Parameters t in [0, 1] where segment p->q meets triangles (Moller-Trumbore, both faces);
    returns how many were written to ``out_t`` and the normal-Y sign of the nearest hit."""
    n = 0
    best = np.inf
    best_ny = 0.0
    for i in range(tris.shape[0]):
        t = _meet(p[0], p[1], p[2], q[0] - p[0], q[1] - p[1], q[2] - p[2], tris, i)
        if t < 0.0:
            continue
        if n < out_t.shape[0]:
            out_t[n] = t
            n += 1
        if t < best:
            best = t
            best_ny = _normal_y(tris, i)
    return n, best_ny


@njit(cache=True, nogil=True, inline="always")
def _normal_y(tris, i):  # pragma: no cover - numba
    """Y of triangle ``i``'s (unnormalised) normal (e1 x e2)."""
    e1x, e1z = tris[i, 1, 0] - tris[i, 0, 0], tris[i, 1, 2] - tris[i, 0, 2]
    e2x, e2z = tris[i, 2, 0] - tris[i, 0, 0], tris[i, 2, 2] - tris[i, 0, 2]
    return e1z * e2x - e1x * e2z


@njit(parallel=True, cache=True, nogil=True)
def _open_points(px, pz, y_lo, y_hi, y_top, tris, sign, grid, x0, z0, size, nx,
                 nz):  # pragma: no cover - numba
    """(n,) bool: the vertical line y_lo..y_hi at each point meets no triangle and the first
    surface above y_hi (up to y_top) does not face down into the point (inside a solid).
    ``grid`` (start, items): ``tris`` by XZ cell (``XZGrid``: x0, z0, size, nx, nz); a
    point tests only its cell's triangles, in ascending order as a full scan would."""
    start, items = grid
    n = px.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for s in prange(n):
        x, z = px[s], pz[s]
        cell = bin_of(x, x0, size, nx) * nz + bin_of(z, z0, size, nz)
        blocked = False
        best = np.inf
        best_ny = 0.0
        hits = 0
        for k in range(start[cell], start[cell + 1]):
            i = items[k]
            if _meet(x, y_lo, z, 0.0, y_hi - y_lo, 0.0, tris, i) >= 0.0:
                blocked = True
                break
            t = _meet(x, y_hi, z, 0.0, y_top - y_hi, 0.0, tris, i)
            if t >= 0.0:
                hits += 1
                if t < best:
                    best = t
                    best_ny = _normal_y(tris, i)
        if blocked:
            continue
        # Going up, leaving through a surface whose outward normal points up means inside.
        out[s] = not (hits > 0 and sign * best_ny > 0.0)
    return out


@njit(cache=True, nogil=True)
def _clear_samples(p, d, ts, keep, side, tris, grid, x0, z0, size, nx,
                   nz):  # pragma: no cover - numba
    """Clear ``keep[i]`` where the horizontal line through p + ts[i] d from -``side`` to
    +``side`` (3,) meets a triangle of ``tris``; ``grid`` as for ``_open_points``."""
    start, items = grid
    for j in range(ts.shape[0]):
        if not keep[j]:
            continue
        cx = p[0] + ts[j] * d[0]
        cy = p[1] + ts[j] * d[1]
        cz = p[2] + ts[j] * d[2]
        ax, az = cx - side[0], cz - side[2]
        bx, bz = cx + side[0], cz + side[2]
        a0, a1 = bin_of(min(ax, bx), x0, size, nx), bin_of(max(ax, bx), x0, size, nx)
        b0, b1 = bin_of(min(az, bz), z0, size, nz), bin_of(max(az, bz), z0, size, nz)
        hit = False
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                cell = a * nz + b
                for k in range(start[cell], start[cell + 1]):
                    if _meet(ax, cy - side[1], az, 2.0 * side[0], 2.0 * side[1], 2.0 * side[2],
                             tris, items[k]) >= 0.0:
                        hit = True
                        break
                if hit:
                    break
            if hit:
                break
        if hit:
            keep[j] = False


class XZGrid:
    """Triangles (m, 3, 3) binned by the cells of an XZ grid over a box (2, 3), about
    ``size`` metres square (at most ``MAX_LATTICE`` a side): point and line queries read only
    the triangles whose XZ bounds reach their cells, so a cell's walk costs what lies near
    each query, not every triangle near the cell times every query."""

    def __init__(self, tris: np.ndarray, box: np.ndarray, size: float) -> None:
        span = float(max(box[1, 0] - box[0, 0], box[1, 2] - box[0, 2], size))
        self.size = max(float(size), span / MAX_LATTICE)
        self.x0 = float(box[0, 0])
        self.z0 = float(box[0, 2])
        self.nx = max(1, int(math.ceil((box[1, 0] - box[0, 0]) / self.size)))
        self.nz = max(1, int(math.ceil((box[1, 2] - box[0, 2]) / self.size)))
        xz = tris[:, :, [0, 2]]
        # A hair wider than the bounds: a point on a triangle's edge must find it.
        pad = 1e-9 * (1.0 + np.abs(xz).max(axis=(1, 2)))[:, None] if len(tris) else 0.0
        self.csr = bin_triangles(np.ascontiguousarray(xz.min(axis=1) - pad),
                                 np.ascontiguousarray(xz.max(axis=1) + pad),
                                 np.array([self.x0, self.z0]), self.size, self.nx, self.nz)

    def args(self) -> tuple:
        """What the kernels take after ``tris``: (grid, x0, z0, size, nx, nz)."""
        return self.csr, self.x0, self.z0, self.size, self.nx, self.nz


@dataclass(frozen=True)
class CellWalk:
    """The open part of a cell: ``open`` (nx, nz) bool on lattice points ``xs`` (nx,) and
    ``zs`` (nz,) metres; ``box`` (2, 3) the cell box it was computed for."""

    box: np.ndarray
    xs: np.ndarray
    zs: np.ndarray
    open: np.ndarray

    @property
    def open_area(self) -> float:
        """Open floor area in square metres (lattice points times the lattice cell area)."""
        dx = self.xs[1] - self.xs[0] if len(self.xs) > 1 else 0.0
        dz = self.zs[1] - self.zs[0] if len(self.zs) > 1 else 0.0
        return float(self.open.sum() * dx * dz)


@njit(cache=True, nogil=True)
def _meeting(vertices, faces, valid, ids, lo, hi, out):  # pragma: no cover - numba
    """Valid faces among ``ids`` (all faces when ``ids`` is empty) whose bounds meet the closed
    box [lo, hi]; written to ``out``, their count returned."""
    n = len(ids) if len(ids) else len(faces)
    k = 0
    for i in range(n):
        t = ids[i] if len(ids) else i
        if not valid[t]:
            continue
        ok = True
        for a in range(3):
            x0 = vertices[faces[t, 0], a]
            x1 = vertices[faces[t, 1], a]
            x2 = vertices[faces[t, 2], a]
            if max(x0, x1, x2) < lo[a] or min(x0, x1, x2) > hi[a]:
                ok = False
                break
        if ok:
            out[k] = t
            k += 1
    return k


def _near_triangles(scene: Scene, box: np.ndarray, pad: float, y_lo: float) -> np.ndarray:
    """(m, 3, 3) float64 valid triangles whose bounds overlap the box's XZ rectangle (padded)
    and reach above ``y_lo``. With the scene's hierarchy built (``ready_hierarchy``, never
    waited for) only the leaves near the box are read: a cell's walk then costs what lies near
    it, not the whole scene (a full scan gathered every triangle of a 1M scene, 137 MiB, per
    cell)."""
    lo = np.array([box[0, 0] - pad, y_lo, box[0, 2] - pad])
    hi = np.array([box[1, 0] + pad, np.inf, box[1, 2] + pad])
    h = ready_hierarchy(scene)
    if h is not None and h.n_faces == len(scene.faces):
        ids = candidates_in_box(h, lo, hi)
        if not len(ids):
            return np.zeros((0, 3, 3))
    else:
        ids = np.zeros(0, dtype=np.int64)
    out = np.empty(len(ids) if len(ids) else len(scene.faces), dtype=np.int64)
    k = _meeting(scene.vertices, scene.faces, scene.valid_faces, ids, lo, hi, out)
    return np.ascontiguousarray(scene.vertices[scene.faces[np.sort(out[:k])]], dtype=np.float64)


def _check_box(box: np.ndarray) -> np.ndarray:
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
        raise ValueError(f"box must be finite with max >= min, got {b.tolist()}")
    return b


def body_height(scene: Scene) -> float:
    """Metres below the lowest eye that must be clear for a person to stand (``BODY_SHARE``
    of the scene's lowest eye height above its floor)."""
    eye_range = scene.meta.get("eye_range") or (EYE_LOW,)
    return BODY_SHARE * float(eye_range[0])


def cell_walk(scene: Scene, box: np.ndarray, step: float = STEP,
              body: float | None = None) -> CellWalk:
    """Open floor inside a cell box (2, 3) on a lattice of about ``step`` metres (see the
    module docstring for what counts as open); ``body`` metres below the lowest eye must be
    clear (default ``body_height``)."""
    b = _check_box(box)
    body = body_height(scene) if body is None else float(body)
    if not step > 0 or not body >= 0:
        raise ValueError(f"step must be > 0 and body >= 0, got {step}, {body}")
    step = lattice_step(b, step)
    nx = max(2, int(math.ceil((b[1, 0] - b[0, 0]) / step)) + 1)
    nz = max(2, int(math.ceil((b[1, 2] - b[0, 2]) / step)) + 1)
    xs = np.linspace(b[0, 0], b[1, 0], nx)
    zs = np.linspace(b[0, 2], b[1, 2], nz)
    y_lo = b[0, 1] - body
    tris = _near_triangles(scene, b, step, y_lo)
    top = float(tris[:, :, 1].max()) + 1.0 if len(tris) else b[1, 1] + 1.0
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    sign = -1.0 if scene.meta.get("winding") == "cw" else 1.0
    if len(tris):
        grid = XZGrid(tris, b, step)
        ok = _open_points(gx.ravel(), gz.ravel(), y_lo, b[1, 1], max(top, b[1, 1] + 1e-6),
                          tris, sign, *grid.args())
    else:
        ok = np.ones(gx.size, dtype=bool)
    ok &= ~_outside(scene, b, gx.ravel(), gz.ravel(), ok)
    return CellWalk(b, xs, zs, ok.reshape(nx, nz))


def _outside(scene: Scene, b: np.ndarray, px: np.ndarray, pz: np.ndarray,
             ok: np.ndarray) -> np.ndarray:
    """(n,) bool over lattice points (px, pz): those of ``ok`` that stand outside the scene's
    rooms, in a game level's void (module docstring): at least ``WRAP_HITS`` of ``WRAP_RAYS``
    level rays at the box's middle eye height meet a surface within ``WRAP_REACH`` metres, and
    at least ``INSIDE_SHARE`` of those meet its back (fronts by the scene's winding, as the
    reference's open-space test reads them: ``ray_reference.back_hits``). The vertical tests
    cannot tell such a place from a street of a city without terrain: nothing above or below
    either. Exact float64 rays through the triangles near the box (``exact_grid``)."""
    out = np.zeros(len(px), dtype=bool)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return out
    y = 0.5 * (b[0, 1] + b[1, 1])
    tris = _near_triangles(scene, b, WRAP_REACH, y)
    tris = tris[tris[:, :, 1].min(axis=1) <= y]
    if not len(tris):
        return out
    a = (np.arange(WRAP_RAYS) + 0.5) * (2.0 * np.pi / WRAP_RAYS)
    d = np.stack([np.cos(a), np.zeros(WRAP_RAYS), np.sin(a)], axis=1)
    orig = np.repeat(np.stack([px[idx], np.full(len(idx), y), pz[idx]], axis=1), WRAP_RAYS,
                     axis=0)
    dirs = np.ascontiguousarray(np.tile(d, (len(idx), 1)))
    hid = np.empty(len(orig), dtype=np.int64)
    ht = np.empty(len(orig))
    grid_first_hits(tris, build_grid(tris.min(axis=1), tris.max(axis=1)), orig, dirs,
                    np.zeros(len(orig)), hid, ht)
    hid[ht > WRAP_REACH] = -1
    back = back_hits(dirs, hid, front_normals(tris, scene))
    hits = (hid >= 0).reshape(-1, WRAP_RAYS).sum(axis=1)
    backs = back.reshape(-1, WRAP_RAYS).sum(axis=1)
    out[idx] = (hits >= WRAP_HITS * WRAP_RAYS) & (backs >= INSIDE_SHARE * hits)
    return out


def open_eyes(scene: Scene, box: np.ndarray, n: int, rng: np.random.Generator,
              clearance: float = CLEARANCE, step: float = STEP) -> np.ndarray:
    """(k, 3) float64 eyes where a person can stand in a cell box (2, 3): open lattice points of
    its floor (``cell_walk``) at a uniform height in the box's eye range, kept only when no
    triangle lies within ``clearance`` metres (an eye nearer a wall than the clients' near
    plane sees through it). ``n`` are drawn; k < n where fewer candidates qualify (k = 0 when
    the cell has no open floor). Metres, Y-up."""
    from trimesh.triangles import closest_point

    b = _check_box(box)
    walk = cell_walk(scene, b, step)
    ii, kk = np.nonzero(walk.open)
    if not len(ii) or n <= 0:
        return np.zeros((0, 3))
    # Twice the candidates asked for: some fall within the clearance of a wall or a solid.
    m = 2 * int(n)
    pick = rng.integers(0, len(ii), size=m)
    eyes = np.stack([walk.xs[ii[pick]], rng.uniform(b[0, 1], b[1, 1], m), walk.zs[kk[pick]]],
                    axis=1)
    tris = _near_triangles(scene, b, clearance, b[0, 1] - clearance)
    keep = np.ones(m, dtype=bool)
    if len(tris):
        lo = tris.min(axis=1)
        hi = tris.max(axis=1)
        for i, e in enumerate(eyes):
            near = np.all((lo <= e + clearance) & (hi >= e - clearance), axis=1)
            if near.any():
                cand = tris[near]
                cp = closest_point(cand, np.broadcast_to(e, (len(cand), 3)))
                keep[i] = float(np.min(np.linalg.norm(cp - e, axis=1))) >= clearance
    return eyes[keep][: int(n)]


def lattice_step(box: np.ndarray, step: float = STEP) -> float:
    """The lattice step (metres) used for a cell box (2, 3): ``step``, or coarser so that no
    side holds more than ``MAX_LATTICE`` points."""
    side = float(max(box[1, 0] - box[0, 0], box[1, 2] - box[0, 2]))
    return max(step, side / (MAX_LATTICE - 1))


def _outlines(walk: CellWalk) -> list[np.ndarray]:
    """Closed XZ outlines (k, 2) of the open regions, each region's simplified to at most
    MAX_SIDES vertices, in metres."""
    from scipy import ndimage
    from skimage.measure import approximate_polygon, find_contours

    xs, zs = walk.xs, walk.zs
    dx, dz = xs[1] - xs[0], zs[1] - zs[0]
    labels, n = ndimage.label(walk.open)
    out = []
    for k in range(1, n + 1):
        region = labels == k
        if region.sum() * dx * dz < MIN_REGION_AREA:
            continue
        # Level 0.75 puts the outline a quarter step from the open samples toward the closed.
        # One sample in from the edge, where there is room, keeps the outline off the walls.
        inner = ndimage.binary_erosion(region, border_value=1)  # not off the cell's own sides
        if inner.sum() * dx * dz >= MIN_REGION_AREA:
            region = inner
        img = np.pad(region.astype(np.float64), 1)
        contours = find_contours(img, 0.75)
        if not contours:
            continue
        c = max(contours, key=len) - 1.0  # the outer outline; holes are seen from it
        tol = 0.5
        poly = approximate_polygon(c, tol)
        while len(poly) - 1 > MAX_SIDES and tol < max(img.shape):
            tol *= 1.5
            poly = approximate_polygon(c, tol)
        xz = np.stack([xs[0] + poly[:, 0] * dx, zs[0] + poly[:, 1] * dz], axis=1)
        xz[:, 0] = np.clip(xz[:, 0], xs[0], xs[-1])
        xz[:, 1] = np.clip(xz[:, 1], zs[0], zs[-1])
        out.append(xz)
    return out


def clear_pieces(p: np.ndarray, q: np.ndarray, tris: np.ndarray, clearance: float = CLEARANCE,
                 margin: float = MARGIN, grid: XZGrid | None = None
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pieces of segment p->q (3,) metres that keep ``clearance`` metres horizontally from every
    triangle of ``tris`` (m, 3, 3) and stop ``margin`` metres short of one they would meet.

    The segment is sampled every ``clearance / 2`` metres; a sample is kept when the horizontal
    line across the segment through it, ``clearance`` to each side, meets no triangle and no
    crossing of the segment itself lies within ``margin``; pieces join consecutive kept
    samples. ``grid``: ``tris`` binned (``XZGrid``) when the caller has them so, for many
    segments.
    """
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    d = q - p
    length = float(np.linalg.norm(d))
    if length == 0.0 or len(tris) == 0:
        return [(p, q)] if length > 0.0 else []
    buf = np.empty(4096)
    n, _ = _hits_along(p, q, tris, buf)
    cuts = np.sort(buf[:n])
    side = np.array([-d[2], 0.0, d[0]])
    side_len = float(np.linalg.norm(side))
    side = side / side_len * clearance if side_len > 0 else np.array([clearance, 0.0, 0.0])
    m = max(2, int(math.ceil(length / (0.5 * clearance))) + 1)
    ts = np.linspace(0.0, 1.0, m)
    keep = np.ones(m, dtype=bool)
    if n:
        keep &= np.abs(ts[:, None] - cuts[None, :]).min(axis=1) * length >= margin
    if grid is None:
        both = np.stack([np.minimum(p, q), np.maximum(p, q)])
        grid = XZGrid(tris, both, max(clearance, length / (MAX_LATTICE - 1)))
    _clear_samples(p, d, ts, keep, side, tris, *grid.args())
    out = []
    i = 0
    while i < m:
        if not keep[i]:
            i += 1
            continue
        j = i
        while j + 1 < m and keep[j + 1]:
            j += 1
        if j > i:
            out.append((p + ts[i] * d, p + ts[j] * d))
        i = j + 1
    return out


def walk_segments(scene: Scene, box: np.ndarray, heights: list[float], step: float = STEP,
                  body: float | None = None) -> np.ndarray:
    """(k, 2, 3) view segments around the open part of a cell at the given eye heights (metres),
    none meeting a triangle of the scene; (0, 2, 3) when the cell has no open part."""
    walk = cell_walk(scene, box, step, body)
    b = walk.box
    step = lattice_step(b, step)
    tris = _near_triangles(scene, b, step + MARGIN + CLEARANCE, min(heights) - CLEARANCE)
    grid = XZGrid(tris, b, max(4.0 * CLEARANCE, step))
    segs = []
    for xz in _outlines(walk):
        for y in heights:
            for i in range(len(xz) - 1):
                p = np.array([xz[i, 0], y, xz[i, 1]])
                q = np.array([xz[i + 1, 0], y, xz[i + 1, 1]])
                segs.extend(clear_pieces(p, q, tris, grid=grid))
    if not segs:
        return np.zeros((0, 2, 3))
    return np.array([[a, c] for a, c in segs])
