"""An indoor level: a grid of rooms with thick walls, floors and ceilings, joined by doors.

Occlusion is strong: from a room one sees other rooms only through door openings. Every room
connects to the rest (a random spanning tree of doors plus extra doors). Furniture stands along
the walls (cabinets, bookshelves full of books, desks, potted plants) and a lamp hangs from each
ceiling; the walk area is each room's free floor plus the door passages, so it stays clear of
furniture and walls. ``floors=2`` stacks a second storey at +3.5 m.
The request is met by the number of rooms, the furniture detail (books, plant tessellation)
and, last, the floor and ceiling tiling.
"""

from __future__ import annotations

import numpy as np

from visibility.generators._mesh import (
    MeshParts,
    blob_mesh,
    box_mesh,
    check_request,
    fit_plan,
    grid_xz,
    shade_by_normal,
    subdivide,
    vary,
)
from visibility.scene import Scene, WalkArea

DEFAULT_TRIANGLES = 100_000
WALL = 0.2            # wall thickness, metres
ROOM_PITCH = (4.8, 8.0)
STOREY = 3.0          # floor to ceiling
LEVEL_PITCH = 3.5     # floor to floor
DOOR_HEIGHT = 2.1
DOOR_WIDTH = (0.9, 1.2)
BAND = (0.45, 0.65)   # depth of the furniture band along a wall
ROOF = 0.3
GRID_SHARE = 0.12
GRID_STEP = (0.15, 8.0)

WALL_COLORS = np.array([[230, 225, 215], [210, 220, 230], [235, 220, 190], [215, 230, 210],
                        [240, 210, 200]], dtype=np.float64)
FLOOR_COLORS = np.array([[160, 110, 70], [190, 150, 100], [120, 120, 130], [175, 160, 150],
                         [100, 70, 50]], dtype=np.float64)
CEILING = np.array([245, 243, 238], dtype=np.float64)
WOOD = np.array([[150, 100, 60], [200, 170, 120], [110, 75, 45], [235, 235, 230]], np.float64)
BOOKS = np.array([[180, 40, 40], [40, 80, 160], [40, 130, 70], [200, 170, 50], [90, 50, 110],
                  [220, 220, 210], [30, 30, 35]], dtype=np.float64)
LEAF = np.array([60, 130, 60], dtype=np.float64)
POT = np.array([170, 90, 60], dtype=np.float64)
LAMP = np.array([255, 240, 200], dtype=np.float64)
SCREEN = np.array([25, 25, 30], dtype=np.float64)
ROOF_COLOR = np.array([120, 115, 110], dtype=np.float64)

_CABINET, _SHELF, _DESK, _PLANT = range(4)


def _detail(triangles: int) -> dict:
    d = float(np.clip(np.sqrt(triangles / 1e5), 0.3, 6.0))
    return {"detail": d, "book_fill": float(np.clip(0.3 * d, 0.08, 1.0)),
            "plant_level": 1 if d < 2 else 2}


class _Boxes:
    """Collects boxes (lo, hi) with an object id, a colour and whether they need a bottom
    (boxes standing on a floor or a shelf board leave their hidden bottom out)."""

    def __init__(self) -> None:
        self.cols: dict[str, list[np.ndarray]] = {"lo": [], "hi": [], "obj": [], "rgb": [],
                                                  "bottom": []}

    def add(self, lo, hi, obj, rgb, bottom: bool = False) -> None:
        lo = np.asarray(lo, np.float64).reshape(-1, 3)
        n = len(lo)
        c = self.cols
        c["lo"].append(lo)
        c["hi"].append(np.asarray(hi, np.float64).reshape(-1, 3))
        c["obj"].append(np.broadcast_to(np.asarray(obj, np.int64), (n,)))
        c["rgb"].append(np.broadcast_to(np.asarray(rgb, np.float64), (n, 3)))
        c["bottom"].append(np.full(n, bool(bottom)))

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.concatenate(v) for k, v in self.cols.items()}


def _local_to_world(side, a0, a1, e0, e1, y0, y1, room_box):
    """World boxes from boxes in a wall's frame: ``a`` along the wall, ``e`` out of it.

    side 0: wall at z = iz0; 1: x = ix0; 2: z = iz1; 3: x = ix1. room_box (n, 4) is the room
    interior (ix0, iz0, ix1, iz1). Returns (lo, hi) (n, 3).
    """
    ix0, iz0, ix1, iz1 = room_box.T
    lo = np.empty((len(a0), 3))
    hi = np.empty((len(a0), 3))
    lo[:, 1], hi[:, 1] = y0, y1
    along_x = (side == 0) | (side == 2)
    wall = np.select([side == 0, side == 1, side == 2], [iz0, ix0, iz1], ix1)
    sign = np.where(side < 2, 1.0, -1.0)
    ea, eb = wall + sign * e0, wall + sign * e1
    emin, emax = np.minimum(ea, eb), np.maximum(ea, eb)
    lo[:, 0] = np.where(along_x, a0, emin)
    hi[:, 0] = np.where(along_x, a1, emax)
    lo[:, 2] = np.where(along_x, emin, a0)
    hi[:, 2] = np.where(along_x, emax, a1)
    return lo, hi


class _Placer:
    """Adds furniture boxes given in their wall's frame (see ``_local_to_world``), heights
    above the storey's floor ``fy``."""

    def __init__(self, boxes: _Boxes, side, room_box, item_obj, fy: float) -> None:
        self.boxes, self.side, self.room_box, self.item_obj, self.fy = (
            boxes, side, room_box, item_obj, fy)

    def __call__(self, sel, a0, a1, e0, e1, y0, y1, rgb, bottom: bool = False) -> None:
        lo, hi = _local_to_world(self.side[sel], a0, a1, e0, e1, self.fy + y0, self.fy + y1,
                                 self.room_box[sel])
        self.boxes.add(lo, hi, self.item_obj[sel], rgb, bottom)


def _plan(nx: int, nz: int, floors: int, opts: dict, seed: int):
    rng = np.random.default_rng([seed, nx, nz, floors, 0x5005])
    X = np.concatenate([[0.0], np.cumsum(rng.uniform(*ROOM_PITCH, nx))])
    Z = np.concatenate([[0.0], np.cumsum(rng.uniform(*ROOM_PITCH, nz))])
    X, Z = X - X[-1] / 2, Z - Z[-1] / 2
    h = WALL / 2
    boxes = _Boxes()
    blobs = []  # (centres, radii, obj, colours)
    walk = []
    obj = 1  # object 0 is the roof
    ri, rk = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij"))
    nroom = len(ri)
    interior = np.stack([X[ri] + h, Z[rk] + h, X[ri + 1] - h, Z[rk + 1] - h], 1)
    wall_rgb = WALL_COLORS[rng.integers(0, len(WALL_COLORS), 4096)] * vary(np.ones(3), rng, 4096,
                                                                            0.05)
    for level in range(floors):
        fy = LEVEL_PITCH * level
        cy = fy + STOREY
        # Doors: a random spanning tree (each room opens west or south) plus extra doors.
        # door_x[i, k]: door in the wall at X[i] between rooms (i-1, k) and (i, k); door_z alike.
        pick_west = rng.random((nx, nz)) < 0.5
        door_x = np.zeros((nx + 1, nz), bool)
        door_z = np.zeros((nx, nz + 1), bool)
        ii, kk = np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij")
        west = (ii > 0) & ((kk == 0) | pick_west)
        south = (kk > 0) & ~west
        door_x[1:nx][west[1:]] = True
        door_z[:, 1:nz][south[:, 1:]] = True
        door_x[1:nx] |= rng.random((nx - 1, nz)) < 0.3
        door_z[:, 1:nz] |= rng.random((nx, nz - 1)) < 0.3
        dwx = rng.uniform(*DOOR_WIDTH, (nx + 1, nz))
        dwz = rng.uniform(*DOOR_WIDTH, (nx, nz + 1))
        margin = BAND[1] + 0.4
        # Door start along the wall, inside the room span with room for corner furniture.
        dx0 = Z[:-1][None] + h + margin + rng.random((nx + 1, nz)) * (
            np.diff(Z)[None] - WALL - 2 * margin - dwx)
        dz0 = X[:-1][:, None] + h + margin + rng.random((nx, nz + 1)) * (
            np.diff(X)[:, None] - WALL - 2 * margin - dwz)

        # Walls along X (at Z[k]): one piece per room column, owning the junction to its west.
        top_outer = fy + (LEVEL_PITCH if level < floors - 1 else STOREY + ROOF)
        for k in range(nz + 1):
            for i in range(nx):
                x0 = X[i] - h
                x1 = X[i + 1] - h if i < nx - 1 else X[i + 1] + h
                outer = k in (0, nz)
                ytop = top_outer if outer else cy
                if door_z[i, k]:
                    d0, d1 = dz0[i, k], dz0[i, k] + dwz[i, k]
                    lo = [[x0, fy, Z[k] - h], [d1, fy, Z[k] - h], [d0, fy + DOOR_HEIGHT, Z[k] - h]]
                    hi = [[d0, ytop, Z[k] + h], [x1, ytop, Z[k] + h], [d1, ytop, Z[k] + h]]
                else:
                    lo, hi = [[x0, fy, Z[k] - h]], [[x1, ytop, Z[k] + h]]
                for j in range(len(lo)):  # the third piece is a lintel: its bottom shows
                    boxes.add(lo[j], hi[j], obj, wall_rgb[obj % 4096], bottom=j == 2)
                    obj += 1
        # Walls along Z (at X[i]): between the junctions.
        for i in range(nx + 1):
            for k in range(nz):
                z0, z1 = Z[k] + h, Z[k + 1] - h
                outer = i in (0, nx)
                ytop = top_outer if outer else cy
                if door_x[i, k]:
                    d0, d1 = dx0[i, k], dx0[i, k] + dwx[i, k]
                    lo = [[X[i] - h, fy, z0], [X[i] - h, fy, d1], [X[i] - h, fy + DOOR_HEIGHT, d0]]
                    hi = [[X[i] + h, ytop, d0], [X[i] + h, ytop, z1], [X[i] + h, ytop, d1]]
                else:
                    lo, hi = [[X[i] - h, fy, z0]], [[X[i] + h, ytop, z1]]
                for j in range(len(lo)):  # the third piece is a lintel: its bottom shows
                    boxes.add(lo[j], hi[j], obj, wall_rgb[obj % 4096], bottom=j == 2)
                    obj += 1

        # Furniture bands: which sides of each room hold furniture, and their door gaps.
        depth = rng.uniform(*BAND, nroom)
        furnished = rng.random((nroom, 4)) < 0.55
        # Door spans on each side (side 0: wall Z[k], 1: X[i], 2: Z[k+1], 3: X[i+1]).
        has = np.stack([door_z[ri, rk], door_x[ri, rk], door_z[ri, rk + 1], door_x[ri + 1, rk]], 1)
        d_start = np.stack([dz0[ri, rk], dx0[ri, rk], dz0[ri, rk + 1], dx0[ri + 1, rk]], 1)
        d_width = np.stack([dwz[ri, rk], dwx[ri, rk], dwz[ri, rk + 1], dwx[ri + 1, rk]], 1)
        # Items packed along every furnished side, dropping those that block a door.
        s_room, s_side = np.nonzero(furnished)
        ib = interior[s_room]
        d = depth[s_room]
        along_x = (s_side == 0) | (s_side == 2)
        a_lo = np.where(along_x, ib[:, 0] + d + 0.05, ib[:, 1])
        a_hi = np.where(along_x, ib[:, 2] - d - 0.05, ib[:, 3])
        m = int(np.ceil(ROOM_PITCH[1] / 0.55)) + 1
        width = rng.uniform(0.5, 1.6, (len(s_room), m))
        gap = rng.uniform(0.05, 0.6, (len(s_room), m))
        end = a_lo[:, None] + np.cumsum(width + gap, axis=1)
        start = end - width
        ok = end <= a_hi[:, None]
        ds, dw = d_start[s_room, s_side], d_width[s_room, s_side]
        blocked = has[s_room, s_side][:, None] & (start < (ds + dw + 0.3)[:, None]) & (
            end > (ds - 0.3)[:, None])
        ok &= ~blocked
        si, col = np.nonzero(ok)
        it_room, it_side = s_room[si], s_side[si]
        a0, a1 = start[si, col], end[si, col]
        dep = d[si] - rng.uniform(0.0, 0.08, len(si))
        kind = rng.choice(4, size=len(si), p=[0.35, 0.3, 0.2, 0.15])
        nit = len(si)
        item_obj = obj + np.arange(nit)
        obj += nit
        rbox = interior[it_room]
        wood = WOOD[rng.integers(0, len(WOOD), nit)] * vary(np.ones(3), rng, nit, 0.08)
        zero, one = np.zeros(nit), np.ones(nit)

        put = _Placer(boxes, it_side, rbox, item_obj, fy)

        # Cabinets.
        c = np.flatnonzero(kind == _CABINET)
        ch = rng.uniform(0.7, 2.1, len(c))
        put(c, a0[c], a1[c], zero[c], dep[c], zero[c], ch, wood[c])
        # Desks: top, four legs, sometimes a screen.
        c = np.flatnonzero(kind == _DESK)
        put(c, a0[c], a1[c], zero[c], dep[c], 0.72 * one[c], 0.76 * one[c], wood[c], True)
        for la, le in ((0, 0), (1, 0), (0, 1), (1, 1)):
            xa = np.where(la == 0, a0[c] + 0.02, a1[c] - 0.07)
            xe = np.where(le == 0, 0.02 * one[c], dep[c] - 0.07)
            put(c, xa, xa + 0.05, xe, xe + 0.05, zero[c], 0.72 * one[c], 0.8 * wood[c])
        scr = c[rng.random(len(c)) < 0.5]
        mid = (a0[scr] + a1[scr]) / 2
        put(scr, mid - 0.25, mid + 0.25, 0.05 * one[scr], 0.09 * one[scr], 0.76 * one[scr],
            1.1 * one[scr], SCREEN)
        # Bookshelves: sides, top, base, back, boards and rows of books.
        c = np.flatnonzero(kind == _SHELF)
        sh = rng.uniform(1.2, 2.0, len(c))
        put(c, a0[c], a0[c] + 0.03, zero[c], dep[c], zero[c], sh, wood[c])
        put(c, a1[c] - 0.03, a1[c], zero[c], dep[c], zero[c], sh, wood[c])
        put(c, a0[c], a1[c], zero[c], dep[c], sh - 0.03, sh, wood[c], True)
        put(c, a0[c] + 0.03, a1[c] - 0.03, zero[c], dep[c], zero[c], 0.08 * one[c], wood[c])
        put(c, a0[c] + 0.03, a1[c] - 0.03, zero[c], 0.02 * one[c], 0.08 * one[c], sh - 0.03,
            0.85 * wood[c], True)
        nb = np.maximum(0, np.floor((sh - 0.11) / 0.35)).astype(np.int64)  # shelf rows
        row_item = np.repeat(c, nb)
        row_j = np.arange(int(nb.sum())) - np.repeat(np.cumsum(nb) - nb, nb)
        row_h = np.repeat((sh - 0.11) / np.maximum(nb, 1), nb)
        y_row = 0.08 + row_j * row_h
        board = y_row > 0.08
        bsel = row_item[board]
        put(bsel, a0[bsel] + 0.03, a1[bsel] - 0.03, 0.02 * np.ones(len(bsel)), dep[bsel],
            y_row[board], y_row[board] + 0.02, wood[bsel], True)
        y_base = np.where(board, y_row + 0.02, y_row)
        filled = rng.random(len(row_item)) < opts["book_fill"]
        row_item, y_base, row_h = row_item[filled], y_base[filled], row_h[filled]
        bw = rng.uniform(0.025, 0.05, len(row_item))
        inner = a1[row_item] - a0[row_item] - 0.06
        nbook = np.floor(inner / bw).astype(np.int64)
        b_item = np.repeat(row_item, nbook)
        bj = np.arange(int(nbook.sum())) - np.repeat(np.cumsum(nbook) - nbook, nbook)
        b_w = np.repeat(bw, nbook)
        b_a0 = a0[b_item] + 0.03 + bj * b_w + 0.002
        b_h = np.repeat(row_h - 0.05, nbook) * rng.uniform(0.55, 1.0, len(b_item))
        b_y = np.repeat(y_base, nbook)
        b_d = dep[b_item] * rng.uniform(0.6, 0.9, len(b_item))
        b_rgb = BOOKS[rng.integers(0, len(BOOKS), len(b_item))] * vary(np.ones(3), rng,
                                                                         len(b_item), 0.1)
        put(b_item, b_a0, b_a0 + b_w - 0.004, 0.03 * np.ones(len(b_item)), b_d, b_y, b_y + b_h,
            b_rgb)
        # Potted plants: a pot and a leafy blob kept inside the band.
        c = np.flatnonzero(kind == _PLANT)
        mid = (a0[c] + a1[c]) / 2
        em = dep[c] / 2
        put(c, mid - 0.15, mid + 0.15, em - 0.15, em + 0.15, zero[c], 0.35 * one[c], POT)
        r = np.minimum(rng.uniform(0.2, 0.3, len(c)), (dep[c] / 2 - 0.03) / 1.15)
        lo, hi = _local_to_world(it_side[c], mid - r, mid + r, em - r, em + r,
                                 fy + 0.35 + 0.8 * r, fy + 0.35 + 0.8 * r, rbox[c])
        blobs.append(((lo + hi) / 2, np.stack([r, 1.2 * r, r], 1), item_obj[c],
                      vary(LEAF, rng, len(c), 0.15)))
        # Ceiling lamps.
        cxz = (interior[:, :2] + interior[:, 2:]) / 2
        lo = np.stack([cxz[:, 0] - 0.2, np.full(nroom, cy - 0.15), cxz[:, 1] - 0.2], 1)
        hi = np.stack([cxz[:, 0] + 0.2, np.full(nroom, cy), cxz[:, 1] + 0.2], 1)
        boxes.add(lo, hi, obj + np.arange(nroom), LAMP, bottom=True)
        obj += nroom

        # Walk area: each room's floor minus its furniture bands, and the door passages.
        band = furnished * (depth[:, None] + 0.05)
        rect = interior + np.stack([band[:, 1], band[:, 0], -band[:, 3], -band[:, 2]], 1)
        walk.append(np.column_stack([rect, np.full(nroom, fy), np.full(nroom, cy)]))
        rect_of = rect.reshape(nx, nz, 4)
        for i, k in zip(*np.nonzero(door_x), strict=True):
            a, b = rect_of[i - 1, k], rect_of[i, k]
            walk.append([[a[2], dx0[i, k] + 0.05, b[0], dx0[i, k] + dwx[i, k] - 0.05, fy,
                          fy + DOOR_HEIGHT]])
        for i, k in zip(*np.nonzero(door_z), strict=True):
            a, b = rect_of[i, k - 1], rect_of[i, k]
            walk.append([[dz0[i, k] + 0.05, a[3], dz0[i, k] + dwz[i, k] - 0.05, b[1], fy,
                          fy + DOOR_HEIGHT]])

    box = boxes.arrays()
    n_leaf = sum(len(b[0]) for b in blobs) * 20 * 4 ** opts["plant_level"]
    fixed = int(np.where(box["bottom"], 12, 10).sum()) + n_leaf + 2  # + the roof
    xb = np.concatenate([X - h, X + h])
    zb = np.concatenate([Z - h, Z + h])
    plan = {"X": X, "Z": Z, "boxes": box, "blobs": blobs,
            "walk": np.concatenate([np.asarray(w, np.float64).reshape(-1, 6) for w in walk]),
            "rooms": nroom * floors, "n_obj": obj, "grid": (nx, nz)}
    return plan, fixed, xb, zb, 2 * floors


def generate(triangles: int | None = DEFAULT_TRIANGLES, seed: int = 0, floors: int = 1) -> Scene:
    """An indoor level of about ``triangles`` triangles (within +-20 % for 10k..several million).

    Parameters
    ----------
    triangles : the triangle budget (None: DEFAULT_TRIANGLES). More triangles make more rooms
        and fuller bookshelves.
    seed : the random seed; the same (triangles, seed, floors) gives bit-identical arrays.
    floors : 1 or 2 storeys (the second's floor at +3.5 m).

    Returns
    -------
    Scene named "rooms": object 0 is the roof; each wall piece, room floor, room ceiling,
    furniture item (with its books) and lamp is one object. The walk area is the free floor
    of every room (ceiling 3 m above it) and the door passages (ceiling at the 2.1 m lintel).
    """
    triangles = DEFAULT_TRIANGLES if triangles is None else triangles
    triangles, seed = check_request(triangles, seed)
    if isinstance(floors, bool) or floors not in (1, 2):
        raise ValueError(f"floors must be 1 or 2, got {floors!r}")
    opts = _detail(triangles)
    guess = triangles * (1 - GRID_SHARE) / (900.0 * opts["detail"] ** 0.8) / floors
    plan, step, _ = fit_plan(triangles, lambda a, b: _plan(a, b, floors, opts, seed), guess,
                             GRID_SHARE, GRID_STEP)
    rng = np.random.default_rng([seed, floors, 0x5006])
    X, Z = plan["X"], plan["Z"]
    nx, nz = plan["grid"]
    h = WALL / 2
    parts = MeshParts()
    # Roof over everything.
    top = LEVEL_PITCH * (floors - 1) + STOREY + ROOF
    rv, rf, _, _ = grid_xz([X[0] - h, X[-1] + h], [Z[0] - h, Z[-1] + h], top)
    parts.add(rv, rf, 0, ROOF_COLOR)
    # Floors and ceilings: one object per room each.
    first = plan["n_obj"]
    n_rooms = nx * nz * floors
    xe, ze = subdivide(np.concatenate([X - h, X + h]), step), subdivide(
        np.concatenate([Z - h, Z + h]), step)
    floor_rgb = FLOOR_COLORS[rng.integers(0, len(FLOOR_COLORS), n_rooms)] * vary(
        np.ones(3), rng, n_rooms, 0.06)
    ceil_rgb = vary(CEILING, rng, n_rooms, 0.03)
    for level in range(floors):
        fy = LEVEL_PITCH * level
        for y, up in ((fy, True), (fy + STOREY, False)):
            gv, gf, gix, giz = grid_xz(xe, ze, y, up=up)
            c = gv[gf].mean(axis=1)
            ri = np.clip(np.searchsorted(X, c[:, 0]) - 1, 0, nx - 1)
            rk = np.clip(np.searchsorted(Z, c[:, 2]) - 1, 0, nz - 1)
            room = level * nx * nz + ri * nz + rk
            tile = np.where((gix + giz) % 2 == 0, 1.0, 0.92)[:, None]
            rgb = floor_rgb[room] * tile if up else ceil_rgb[room]
            parts.add(gv, gf, first + room + (0 if up else n_rooms), rgb)
    # Walls, furniture, books, lamps.
    box = plan["boxes"]
    for bottom in (True, False):
        sel = np.flatnonzero(box["bottom"] == bottom)
        bv, bf, bid, _ = box_mesh(box["lo"][sel], box["hi"][sel], bottom=bottom)
        parts.add(bv, bf, box["obj"][sel][bid], box["rgb"][sel][bid])
    for centers, radii, bo, rgb in plan["blobs"]:
        lv, lf, li = blob_mesh(centers, radii, opts["plant_level"], rng)
        parts.add(lv, lf, bo[li], rgb[li])

    verts, faces, object_ids, colors = parts.build()
    colors = shade_by_normal(verts, faces, colors)
    scene = Scene(vertices=verts, faces=faces, object_ids=object_ids, colors=colors, name="rooms",
                  walk=WalkArea(rects=plan["walk"], eye_height=1.7, eye_range=(1.5, 1.9)))
    scene.meta.update({
        "generator": "rooms", "seed": seed, "requested_triangles": triangles,
        "is_2_5d": False, "floors": floors, "rooms": int(plan["rooms"]), "grid": [nx, nz],
        "detail": opts["detail"], "tile_step_m": float(step),
        "storey_height_m": STOREY, "level_pitch_m": LEVEL_PITCH,
    })
    return scene
