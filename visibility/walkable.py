"""Where people walk in a scene that does not say: floors and open ground found from geometry.

Vertical rays are cast through a lattice of sample points (3 x 3 per viewcell column) and their
hits sorted by height (normals follow the counter-clockwise rule unless the scene's
``meta["winding"]`` is ``"cw"``). A hit is a floor when
its surface faces up, there is head room above it, the first surface above it does not face up
(that would put the floor inside a closed solid), and it is not a rooftop (open to the sky yet
well above the local ground). In outdoor scenes without terrain (the city scenes: streets are
where buildings are not) columns that no surface crosses are ground at the local ground height.
A cell is walkable at a level when most of its samples agree on a floor there; isolated specks
(table tops) are dropped.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from scipy import ndimage

from visibility.scene import Scene, WalkArea

#: Samples per cell side.
SUBSAMPLES = 3
#: Most hits kept per vertical ray.
MAX_HITS = 64
#: Most floors kept per vertical ray.
MAX_FLOORS = 6
#: Least clear height above a floor for a walker (metres).
MIN_HEADROOM = 1.3
#: A surface faces up when its unit normal's Y exceeds this.
UP_NY = 0.5
#: An open-sky floor more than this above the local ground is a rooftop (metres).
ROOF_ABOVE_GROUND = 3.0
#: Radius over which the local ground height is the lowest geometry (metres).
GROUND_RADIUS = 40.0
#: Share of a cell's samples that must agree on a floor level.
MIN_COVERAGE = 0.5
#: Connected walkable regions smaller than this are dropped (square metres).
MIN_REGION_AREA = 8.0


@njit(cache=True, nogil=True)
def _bin_triangles(tri_min, tri_max, origin, bin_size, nbx, nbz):
    counts = np.zeros(nbx * nbz + 1, dtype=np.int64)
    m = tri_min.shape[0]
    for t in range(m):
        i0 = max(0, int(np.floor((tri_min[t, 0] - origin[0]) / bin_size)))
        i1 = min(nbx - 1, int(np.floor((tri_max[t, 0] - origin[0]) / bin_size)))
        k0 = max(0, int(np.floor((tri_min[t, 1] - origin[1]) / bin_size)))
        k1 = min(nbz - 1, int(np.floor((tri_max[t, 1] - origin[1]) / bin_size)))
        for i in range(i0, i1 + 1):
            for k in range(k0, k1 + 1):
                counts[i * nbz + k + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    items = np.empty(starts[-1], dtype=np.int64)
    for t in range(m):
        i0 = max(0, int(np.floor((tri_min[t, 0] - origin[0]) / bin_size)))
        i1 = min(nbx - 1, int(np.floor((tri_max[t, 0] - origin[0]) / bin_size)))
        k0 = max(0, int(np.floor((tri_min[t, 1] - origin[1]) / bin_size)))
        k1 = min(nbz - 1, int(np.floor((tri_max[t, 1] - origin[1]) / bin_size)))
        for i in range(i0, i1 + 1):
            for k in range(k0, k1 + 1):
                b = i * nbz + k
                items[fill[b]] = t
                fill[b] += 1
    return starts, items


@njit(cache=True, nogil=True, parallel=True)
def _column_floors(
    px,
    pz,
    ground,
    tris,
    ny,
    starts,
    items,
    origin,
    bin_size,
    nbx,
    nbz,
    max_hits,
    max_floors,
    min_headroom,
    up_ny,
    roof_above,
):
    """Floors along vertical lines at (px, pz): (floor y, ceiling y) pairs, the hit count and
    the normal-Y of the topmost surface, per line."""
    n = px.shape[0]
    floors = np.full((n, max_floors), np.nan)
    ceils = np.full((n, max_floors), np.nan)
    count = np.zeros(n, dtype=np.int64)
    top_ny = np.zeros(n)
    bottom_ny = np.zeros(n)
    nchunks = 64
    for ch in prange(nchunks):
        hy = np.empty(max_hits)
        hn = np.empty(max_hits)
        for s in range(ch * n // nchunks, (ch + 1) * n // nchunks):
            x = px[s]
            z = pz[s]
            i = int(np.floor((x - origin[0]) / bin_size))
            k = int(np.floor((z - origin[1]) / bin_size))
            if i < 0 or i >= nbx or k < 0 or k >= nbz:
                continue
            b = i * nbz + k
            c = 0
            for j in range(starts[b], starts[b + 1]):
                t = items[j]
                ax, az = tris[t, 0, 0] - x, tris[t, 0, 2] - z
                bx, bz = tris[t, 1, 0] - x, tris[t, 1, 2] - z
                cx, cz = tris[t, 2, 0] - x, tris[t, 2, 2] - z
                w0 = bx * cz - bz * cx
                w1 = cx * az - cz * ax
                w2 = ax * bz - az * bx
                area = w0 + w1 + w2
                if abs(area) < 1e-12:
                    continue  # vertical in XZ: a vertical line does not cross it
                if area > 0:
                    if w0 < 0 or w1 < 0 or w2 < 0:
                        continue
                elif w0 > 0 or w1 > 0 or w2 > 0:
                    continue
                y = (w0 * tris[t, 0, 1] + w1 * tris[t, 1, 1] + w2 * tris[t, 2, 1]) / area
                # Sorted insertion; past max_hits the highest hits are dropped.
                if c >= max_hits and y >= hy[max_hits - 1]:
                    continue
                pos = min(c, max_hits - 1)
                while pos > 0 and hy[pos - 1] > y:
                    hy[pos] = hy[pos - 1]
                    hn[pos] = hn[pos - 1]
                    pos -= 1
                hy[pos] = y
                hn[pos] = ny[t]
                if c < max_hits:
                    c += 1
            count[s] = c
            if c == 0:
                continue
            top_ny[s] = hn[c - 1]
            bottom_ny[s] = hn[0]
            f = 0
            for h in range(c):
                if hn[h] <= up_ny:
                    continue
                above = np.inf if h + 1 >= c else hy[h + 1]
                if above - hy[h] < min_headroom:
                    continue
                if h + 1 < c and hn[h + 1] > up_ny:
                    continue  # the next surface up faces up: this floor is inside a solid
                if h + 1 >= c and hy[h] > ground[s] + roof_above:
                    continue  # open to the sky, well above the local ground: a rooftop
                if f < max_floors:
                    floors[s, f] = hy[h]
                    ceils[s, f] = above
                    f += 1
    return floors, ceils, count, top_ny, bottom_ny


def _local_ground(
    tris: np.ndarray, origin: np.ndarray, size: float, nx: int, nz: int
) -> np.ndarray:
    """(nx, nz) lowest geometry height within GROUND_RADIUS of each column (inf where none)."""
    v = tris.reshape(-1, 3)
    i = np.clip(((v[:, 0] - origin[0]) // size).astype(np.int64), 0, nx - 1)
    k = np.clip(((v[:, 2] - origin[1]) // size).astype(np.int64), 0, nz - 1)
    low = np.full(nx * nz, np.inf)
    np.minimum.at(low, i * nz + k, v[:, 1])
    r = max(1, int(np.ceil(GROUND_RADIUS / size)))
    g = ndimage.minimum_filter(low.reshape(nx, nz), size=2 * r + 1, mode="nearest")
    missing = ~np.isfinite(g)
    if missing.any() and not missing.all():
        # Far from any geometry (the middle of a large roof or square): the nearest estimate.
        _, idx = ndimage.distance_transform_edt(missing, return_indices=True)
        g = g[idx[0], idx[1]]
    return g


def detect_walk_area(
    scene: Scene,
    cell_size: float,
    eye_height: float = 1.7,
    eye_range: tuple[float, float] = (1.5, 1.9),
) -> WalkArea:
    """A WalkArea of cell-sized squares (with floor and ceiling heights) found from geometry.

    The squares lie on the lattice of ``cell_size`` anchored at the scene's XZ minimum, so a
    ``ViewcellGrid`` of the same size has one cell per square and level.
    """
    valid = scene.valid_faces
    tris = scene.triangles()[valid]
    if len(tris) == 0:
        return WalkArea(np.zeros((0, 6)), eye_height=eye_height, eye_range=eye_range)
    b0 = tris.reshape(-1, 3).min(axis=0)
    b1 = tris.reshape(-1, 3).max(axis=0)
    origin = np.array([b0[0], b0[2]])
    s = float(cell_size)
    nx = max(1, int(np.ceil((b1[0] - b0[0]) / s)))
    nz = max(1, int(np.ceil((b1[2] - b0[2]) / s)))
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    ny = n[:, 1] / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    xz_min = np.stack([tris[:, :, 0].min(axis=1), tris[:, :, 2].min(axis=1)], axis=1)
    xz_max = np.stack([tris[:, :, 0].max(axis=1), tris[:, :, 2].max(axis=1)], axis=1)
    # Triangles facing sideways cannot hold a vertical line's hit worth keeping.
    flat = np.abs(ny) > 1e-6
    tris_f, ny_f = np.ascontiguousarray(tris[flat]), np.ascontiguousarray(ny[flat])
    starts, items = _bin_triangles(xz_min[flat], xz_max[flat], origin, s, nx, nz)

    k = SUBSAMPLES
    sub = (np.arange(k) + 0.5) / k * s
    ci, ck, si, sk = np.meshgrid(
        np.arange(nx), np.arange(nz), np.arange(k), np.arange(k), indexing="ij"
    )
    px = (origin[0] + ci * s + sub[si]).ravel()
    pz = (origin[1] + ck * s + sub[sk]).ravel()
    ground = _local_ground(tris, origin, s, nx, nz)
    col_ground = np.repeat(ground.ravel(), k * k)

    def cast(normal_y):
        return _column_floors(
            px,
            pz,
            col_ground,
            tris_f,
            normal_y,
            starts,
            items,
            origin,
            s,
            nx,
            nz,
            MAX_HITS,
            MAX_FLOORS,
            MIN_HEADROOM,
            UP_NY,
            ROOF_ABOVE_GROUND,
        )

    # Quake levels wind their faces clockwise: their normals point away from the playable
    # space. Geometry alone cannot tell such a level from closed solids, so a hint says it.
    sign = -1.0 if str(scene.meta.get("winding", "ccw")).lower() == "cw" else 1.0
    floors_y, ceil_y, count, top_ny, bottom_ny = cast(sign * ny_f)
    # Outdoor scenes: most crossed columns end at an up-facing top surface (roof, terrain).
    has = count > 0
    outdoor = bool(has.any() and np.mean(top_ny[has] > UP_NY) > 0.5)
    if outdoor:
        # Columns no surface crosses, inside the scene's footprint, are open ground.
        empty = (count == 0) & np.isfinite(col_ground)
        floors_y = np.concatenate([floors_y, np.where(empty, col_ground, np.nan)[:, None]], axis=1)
        ceil_y = np.concatenate([ceil_y, np.where(empty, np.inf, np.nan)[:, None]], axis=1)

    rects = _cells_from_samples(floors_y, ceil_y, nx, nz, k, origin, s)
    return WalkArea(rects, eye_height=eye_height, eye_range=eye_range)


def _cells_from_samples(floors_y, ceil_y, nx, nz, k, origin, s) -> np.ndarray:
    """Group sample floors into per-cell levels; keep levels most samples agree on and drop
    small disconnected regions. Returns (w, 6) rects."""
    per = k * k
    width = floors_y.shape[1]
    fy = floors_y.reshape(nx * nz, per * width)
    cy = ceil_y.reshape(nx * nz, per * width)
    ok = np.isfinite(fy)
    if not ok.any():
        return np.zeros((0, 6))
    cell_idx = np.broadcast_to(np.arange(nx * nz)[:, None], fy.shape)[ok]
    yv, cv = fy[ok], cy[ok]
    order = np.lexsort((yv, cell_idx))
    cell_idx, yv, cv = cell_idx[order], yv[order], cv[order]
    # A new level starts at a new cell or a jump of more than 0.5 m within the cell.
    new = np.ones(len(yv), dtype=bool)
    new[1:] = (cell_idx[1:] != cell_idx[:-1]) | (np.diff(yv) > 0.5)
    starts = np.nonzero(new)[0]
    support = np.diff(np.append(starts, len(yv)))
    cells_a = cell_idx[starts]
    floors_a = np.add.reduceat(yv, starts) / support
    ceils_a = np.minimum.reduceat(cv, starts)
    keep = support >= MIN_COVERAGE * per
    cells_a, floors_a, ceils_a = cells_a[keep], floors_a[keep], ceils_a[keep]
    if len(cells_a) == 0:
        return np.zeros((0, 6))
    keep = _large_regions(cells_a, floors_a, nz, s)
    cells_a, floors_a, ceils_a = cells_a[keep], floors_a[keep], ceils_a[keep]
    ci, ck = cells_a // nz, cells_a % nz
    x0 = origin[0] + ci * s
    z0 = origin[1] + ck * s
    return np.stack([x0, z0, x0 + s, z0 + s, floors_a, ceils_a], axis=1)


def _large_regions(cells: np.ndarray, floors: np.ndarray, nz: int, s: float) -> np.ndarray:
    """(w,) bool: cells in connected regions (8-neighbours, steps <= 1 m) of enough area.

    ``cells`` are column indices (i * nz + k), sorted; a column may repeat once per level."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    w = len(cells)
    ci, ck = cells // nz, cells % nz
    rows, cols = [], []
    max_levels = int(np.max(np.diff(np.flatnonzero(np.diff(np.r_[-1, cells, -2])))))
    for di, dk in ((1, -1), (1, 0), (1, 1), (0, 1)):
        ni, nk = ci + di, ck + dk
        inside = (nk >= 0) & (nk < nz)
        target = ni * nz + nk
        lo = np.searchsorted(cells, target, side="left")
        hi = np.searchsorted(cells, target, side="right")
        for j in range(max_levels):
            cand = lo + j
            ok = inside & (cand < hi)
            src = np.nonzero(ok)[0]
            dst = cand[ok]
            close = np.abs(floors[dst] - floors[src]) <= 1.0
            rows.append(src[close])
            cols.append(dst[close])
    r = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, dtype=np.int64)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(w, w))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    return sizes[labels] * s * s >= MIN_REGION_AREA
