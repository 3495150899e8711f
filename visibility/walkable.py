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

import logging

import numpy as np
from numba import njit, prange
from scipy import ndimage

from visibility.scene import Scene, WalkArea

log = logging.getLogger(__name__)

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
#: Most grid columns (squares) the detection examines. Memory grows by about 1 kB a column
#: (local ground, per-cell levels, the connectivity graph), so 2^19 columns stay under ~500 MB;
#: the largest real scene (Lyon, 2.3 x 2.4 km at 4 m) needs 332 000. A wider scene gets coarser
#: squares (an integer multiple of the cell size, logged), never GBs.
MAX_WALK_COLUMNS = 1 << 19
#: Most coarsening of the squares (a multiple of the cell size) before detection refuses: past
#: it the squares (32 m at 4 m cells) no longer resolve streets or rooms.
MAX_COARSENING = 8
#: Most (triangle, bin) pairs in the triangle bins (8 bytes each, 64 MB): a triangle spanning
#: the whole scene sits in every bin, so a few huge triangles would fill memory; past this the
#: bins grow (the bins only speed up the ray casts, results do not depend on them).
MAX_BIN_ITEMS = 1 << 23
#: Vertical rays cast per pass (their hits, floors and ceilings are ~200 bytes a ray), so the
#: rays of a big scene never sit in memory all at once: 2^18 rays are ~50 MB.
RAYS_PER_PASS = 1 << 18


@njit(cache=True, nogil=True)
def bin_triangles(tri_min, tri_max, origin, bin_size, nbx, nbz):  # pragma: no cover - numba
    """Triangles binned by their 2-D boxes ``tri_min``, ``tri_max`` (m, 2) on a grid of
    ``nbx`` x ``nbz`` square bins of ``bin_size`` from ``origin`` (2,) (boxes past the grid,
    wholly or in part, go to its border bins, so a query clamped to the grid finds them):
    (starts (nbx nbz + 1,), items), bin i nbz + k holding ``items[starts[b]:starts[b + 1]]``,
    each bin's triangles in ascending order."""
    counts = np.zeros(nbx * nbz + 1, dtype=np.int64)
    m = tri_min.shape[0]
    for t in range(m):
        i0, i1, k0, k1 = _bin_range(tri_min, tri_max, t, origin, bin_size, nbx, nbz)
        for i in range(i0, i1 + 1):
            for k in range(k0, k1 + 1):
                counts[i * nbz + k + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    items = np.empty(starts[-1], dtype=np.int64)
    for t in range(m):
        i0, i1, k0, k1 = _bin_range(tri_min, tri_max, t, origin, bin_size, nbx, nbz)
        for i in range(i0, i1 + 1):
            for k in range(k0, k1 + 1):
                b = i * nbz + k
                items[fill[b]] = t
                fill[b] += 1
    return starts, items


@njit(cache=True, nogil=True, inline="always")
def bin_of(x, origin, bin_size, n):  # pragma: no cover - numba
    """The bin along one axis holding coordinate ``x``, clamped to [0, n - 1]."""
    return min(n - 1, max(0, int(np.floor((x - origin) / bin_size))))


@njit(cache=True, nogil=True, inline="always")
def _bin_range(tri_min, tri_max, t, origin, bin_size, nbx, nbz):  # pragma: no cover - numba
    """Bins (i0, i1, k0, k1), inclusive, that triangle t's box reaches."""
    return (bin_of(tri_min[t, 0], origin[0], bin_size, nbx),
            bin_of(tri_max[t, 0], origin[0], bin_size, nbx),
            bin_of(tri_min[t, 1], origin[1], bin_size, nbz),
            bin_of(tri_max[t, 1], origin[1], bin_size, nbz))


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


def _grid_shape(span: np.ndarray, cell_size: float, name: str) -> tuple[float, int, int]:
    """(square size, nx, nz) of the detection grid over an XZ ``span`` (metres): squares of
    ``cell_size``, or of the smallest integer multiple of it (up to MAX_COARSENING) that keeps
    the columns within MAX_WALK_COLUMNS. ValueError past that."""
    s = float(cell_size)
    if not (np.isfinite(s) and s > 0):
        raise ValueError(f"cell_size must be a positive number of metres, got {cell_size}")
    if not np.all(np.isfinite(span)):
        raise ValueError(f"scene {name!r}: its extent {span.tolist()} m is not finite")
    for f in range(1, MAX_COARSENING + 1):
        nx, nz = (max(1.0, float(np.ceil(w / (f * s)))) for w in span)
        if nx * nz <= MAX_WALK_COLUMNS:
            if f > 1:
                log.warning("scene %r spans %.0f x %.0f m: walk-area detection uses %.3g m "
                            "squares (%d x the cell size) to stay within MAX_WALK_COLUMNS = %d",
                            name, span[0], span[1], f * s, f, MAX_WALK_COLUMNS)
            return f * s, int(nx), int(nz)
    raise ValueError(
        f"scene {name!r} spans {span[0]:.0f} x {span[1]:.0f} m: walk-area detection at "
        f"{s:g} m squares would need more than MAX_WALK_COLUMNS = {MAX_WALK_COLUMNS} columns "
        f"even {MAX_COARSENING} times coarser; give a larger cell size or a sidecar walk area")


def _bins(xz_min: np.ndarray, xz_max: np.ndarray, origin: np.ndarray, s: float, nx: int,
          nz: int) -> tuple[float, int, int]:
    """(bin size, nbx, nbz): the squares themselves, or bins doubled in size until the
    (triangle, bin) pairs fit MAX_BIN_ITEMS (at most 64 doublings: then one bin holds all)."""
    size, nbx, nbz = s, nx, nz
    for _ in range(64):
        i0 = np.clip(np.floor((xz_min[:, 0] - origin[0]) / size), 0, nbx - 1)
        i1 = np.clip(np.floor((xz_max[:, 0] - origin[0]) / size), 0, nbx - 1)
        k0 = np.clip(np.floor((xz_min[:, 1] - origin[1]) / size), 0, nbz - 1)
        k1 = np.clip(np.floor((xz_max[:, 1] - origin[1]) / size), 0, nbz - 1)
        if float(np.sum((i1 - i0 + 1) * (k1 - k0 + 1))) <= MAX_BIN_ITEMS or nbx * nbz == 1:
            break
        size *= 2.0
        nbx, nbz = max(1, -(-nbx // 2)), max(1, -(-nbz // 2))
    return size, nbx, nbz


def detect_walk_area(
    scene: Scene,
    cell_size: float,
    eye_height: float = 1.7,
    eye_range: tuple[float, float] = (1.5, 1.9),
) -> WalkArea:
    """A WalkArea of cell-sized squares (with floor and ceiling heights) found from geometry.

    The squares lie on the lattice of ``cell_size`` anchored at the scene's XZ minimum, so a
    ``ViewcellGrid`` of the same size has one cell per square and level. A scene too wide for
    MAX_WALK_COLUMNS squares gets squares of a multiple of ``cell_size`` (still on the lattice;
    logged), or a ValueError naming the limit. Memory stays bounded: rays are cast
    RAYS_PER_PASS at a time and only each pass's per-square levels are kept.
    """
    valid = scene.valid_faces
    tris = scene.triangles()[valid]
    if len(tris) == 0:
        return WalkArea(np.zeros((0, 6)), eye_height=eye_height, eye_range=eye_range)
    b0 = tris.reshape(-1, 3).min(axis=0)
    b1 = tris.reshape(-1, 3).max(axis=0)
    origin = np.array([b0[0], b0[2]])
    with np.errstate(over="ignore"):
        span = np.array([b1[0] - b0[0], b1[2] - b0[2]])
    s, nx, nz = _grid_shape(span, cell_size, scene.name)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    ny = n[:, 1] / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    xz_min = np.stack([tris[:, :, 0].min(axis=1), tris[:, :, 2].min(axis=1)], axis=1)
    xz_max = np.stack([tris[:, :, 0].max(axis=1), tris[:, :, 2].max(axis=1)], axis=1)
    # Triangles facing sideways cannot hold a vertical line's hit worth keeping.
    flat = np.abs(ny) > 1e-6
    tris_f, ny_f = np.ascontiguousarray(tris[flat]), np.ascontiguousarray(ny[flat])
    bin_size, nbx, nbz = _bins(xz_min[flat], xz_max[flat], origin, s, nx, nz)
    starts, items = bin_triangles(xz_min[flat], xz_max[flat], origin, bin_size, nbx, nbz)
    ground = _local_ground(tris, origin, s, nx, nz).ravel()
    del n, xz_min, xz_max, flat

    # Quake levels wind their faces clockwise: their normals point away from the playable
    # space. Geometry alone cannot tell such a level from closed solids, so a hint says it.
    sign = -1.0 if str(scene.meta.get("winding", "ccw")).lower() == "cw" else 1.0
    ny_f = sign * ny_f
    k = SUBSAMPLES
    per = k * k
    sub = (np.arange(k) + 0.5) / k * s
    # Levels of each pass for both readings of the scene; which one holds is known only once
    # every ray is cast (most crossed columns ending at an up-facing surface: outdoors).
    indoor: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    outdoor_levels: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    crossed = up_top = 0
    step = max(1, RAYS_PER_PASS // per)
    for c0 in range(0, nx * nz, step):
        col = np.arange(c0, min(c0 + step, nx * nz))
        ci, ck = col // nz, col % nz
        shape = (len(col), k, k)
        px = np.broadcast_to(origin[0] + ci[:, None, None] * s + sub[None, :, None], shape)
        pz = np.broadcast_to(origin[1] + ck[:, None, None] * s + sub[None, None, :], shape)
        col_ground = np.repeat(ground[col], per)
        floors_y, ceil_y, count, top_ny, _ = _column_floors(
            px.ravel(), pz.ravel(), col_ground, tris_f, ny_f, starts, items, origin, bin_size,
            nbx, nbz, MAX_HITS, MAX_FLOORS, MIN_HEADROOM, UP_NY, ROOF_ABOVE_GROUND,
        )
        has = count > 0
        crossed += int(np.count_nonzero(has))
        up_top += int(np.count_nonzero(top_ny[has] > UP_NY))
        cell = np.repeat(col, per)
        ok = np.isfinite(floors_y)
        cells_f = np.broadcast_to(cell[:, None], ok.shape)[ok]
        yv, cv = floors_y[ok], ceil_y[ok]
        indoor.append(_levels(cells_f, yv, cv, per))
        # Outdoors, columns no surface crosses, inside the scene's footprint, are open ground.
        empty = (count == 0) & np.isfinite(col_ground)
        outdoor_levels.append(_levels(np.concatenate([cells_f, cell[empty]]),
                                      np.concatenate([yv, col_ground[empty]]),
                                      np.concatenate([cv, np.full(int(empty.sum()), np.inf)]),
                                      per))
    outdoor = crossed > 0 and up_top / crossed > 0.5
    chosen = outdoor_levels if outdoor else indoor
    cells_a, floors_a, ceils_a = (np.concatenate([c[j] for c in chosen]) for j in range(3))
    rects = _rects(cells_a, floors_a, ceils_a, nz, origin, s)
    return WalkArea(rects, eye_height=eye_height, eye_range=eye_range)


def _levels(cell_idx: np.ndarray, yv: np.ndarray, cv: np.ndarray,
            per: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group sample floors (square index, floor y, ceiling y per floor found) into per-square
    levels and keep those most of the square's ``per`` samples agree on. Returns the kept
    (square, mean floor, lowest ceiling), sorted by square then floor."""
    if len(yv) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
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
    return cells_a[keep].astype(np.int64), floors_a[keep], ceils_a[keep]


def _rects(cells_a: np.ndarray, floors_a: np.ndarray, ceils_a: np.ndarray, nz: int,
           origin: np.ndarray, s: float) -> np.ndarray:
    """(w, 6) rects of the levels in connected regions large enough (``_large_regions``)."""
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
