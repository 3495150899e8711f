"""A 2.5D city: a street grid, blocks of extruded buildings, a tessellated ground plane.

Every occluder is a vertical extrusion of a convex footprint standing on the ground or on a roof
(towers in tiers, rooftop plant), so the city is a height field (``meta["is_2_5d"] = True``).
The request is met by the number of blocks (more triangles: a larger city), the facade detail
(more triangles: finer facade grids with window bands) and, last, the ground tessellation.
"""

from __future__ import annotations

import numpy as np

from visibility.generators._mesh import (
    MeshParts,
    SolidBatch,
    Solids,
    check_request,
    fit_plan,
    grid_xz,
    rect_profile,
    shade_by_normal,
    solids_count,
    solids_mesh_parts,
    subdivide,
    vary,
)
from visibility.scene import Scene, WalkArea

DEFAULT_TRIANGLES = 100_000
STREET_WIDTH = (10.0, 16.0)
BLOCK_SIZE = (55.0, 95.0)
#: Setback of every building from its block's edge: keeps 4 m viewcells centred on a street
#: (they reach 2 m past its edge) out of the buildings.
SIDEWALK = (2.6, 4.0)
OUTSKIRTS = 40.0
#: Share of the budget the ground takes, and the tile sizes it may use (metres).
GROUND_SHARE = 0.12
GROUND_STEP = (0.75, 40.0)

WALL_COLORS = np.array([[205, 190, 160], [170, 165, 160], [160, 90, 70], [200, 200, 195],
                        [140, 135, 125], [215, 175, 130], [120, 130, 145]], dtype=np.float64)
WINDOW_COLOR = np.array([70, 95, 125], dtype=np.float64)
ROOF_COLOR = np.array([95, 92, 90], dtype=np.float64)
PLANT_COLOR = np.array([150, 150, 155], dtype=np.float64)
ASPHALT = np.array([70, 72, 76], dtype=np.float64)
PAVEMENT = np.array([165, 160, 150], dtype=np.float64)
GRASS = np.array([95, 130, 70], dtype=np.float64)

# Solid tags (how a solid is coloured).
_TAG_BODY, _TAG_PLANT = 0, 1


def _detail(triangles: int) -> float:
    return float(np.clip(np.sqrt(triangles / 1e5), 0.3, 6.0))


def _layout(nbx: int, nbz: int, rng: np.random.Generator):
    """Street and block coordinates: edges alternate street, block, street ... along X and Z."""

    def axis(nb):
        streets = rng.uniform(*STREET_WIDTH, size=nb + 1)
        blocks = rng.uniform(*BLOCK_SIZE, size=nb)
        widths = np.empty(2 * nb + 1)
        widths[0::2], widths[1::2] = streets, blocks
        edges = np.concatenate([[0.0], np.cumsum(widths)])
        return edges - edges[-1] / 2

    return axis(nbx), axis(nbz)


def _cuts(lo: np.ndarray, hi: np.ndarray, n: np.ndarray, rng: np.random.Generator):
    """Jittered cut positions splitting each [lo_i, hi_i] into n_i pieces, flattened.

    Returns (cuts, offset of interval i's first cut); interval i has n_i + 1 cuts.
    """
    off = np.concatenate([[0], np.cumsum(n + 1)[:-1]])
    owner = np.repeat(np.arange(len(n)), n + 1)
    j = np.arange(int((n + 1).sum())) - off[owner]
    width = (hi - lo)[owner] / n[owner]
    inner = (j > 0) & (j < n[owner])
    cuts = lo[owner] + j * width + np.where(inner, rng.uniform(-0.2, 0.2, len(j)) * width, 0.0)
    return cuts, off


def _plan(nbx: int, nbz: int, detail: float, seed: int) -> tuple[Solids, dict]:
    """Buildings of an nbx x nbz block city as a Solids batch, plus the layout."""
    rng = np.random.default_rng([seed, nbx, nbz, 0xC17])
    xe, ze = _layout(nbx, nbz, rng)
    half = max(xe[-1], ze[-1])
    rows_per_floor = 1 if detail < 1.8 else 2

    # Blocks, then a jittered grid of lots in each.
    bi, bk = (a.ravel() for a in np.meshgrid(np.arange(nbx), np.arange(nbz), indexing="ij"))
    sw = rng.uniform(*SIDEWALK, size=len(bi))
    bx0, bx1 = xe[2 * bi + 1] + sw, xe[2 * bi + 2] - sw
    bz0, bz1 = ze[2 * bk + 1] + sw, ze[2 * bk + 2] - sw
    nlx = np.maximum(1, np.rint((bx1 - bx0) / rng.uniform(16, 30, len(bi)))).astype(np.int64)
    nlz = np.maximum(1, np.rint((bz1 - bz0) / rng.uniform(16, 30, len(bi)))).astype(np.int64)
    cx, offx = _cuts(bx0, bx1, nlx, rng)
    cz, offz = _cuts(bz0, bz1, nlz, rng)
    nlot = nlx * nlz
    blk = np.repeat(np.arange(len(bi)), nlot)
    q = np.arange(int(nlot.sum())) - np.repeat(np.cumsum(nlot) - nlot, nlot)
    lj, ll = q // nlz[blk], q % nlz[blk]
    n = len(blk)
    inner_gap = rng.uniform(0.5, 2.0, (n, 4))
    edge_gap = rng.uniform(0.0, 1.5, (n, 4))
    first = np.stack([lj == 0, lj == nlx[blk] - 1, ll == 0, ll == nlz[blk] - 1], 1)
    gap = np.where(first, edge_gap, inner_gap)
    lx0 = cx[offx[blk] + lj] + gap[:, 0]
    lx1 = cx[offx[blk] + lj + 1] - gap[:, 1]
    lz0 = cz[offz[blk] + ll] + gap[:, 2]
    lz1 = cz[offz[blk] + ll + 1] - gap[:, 3]
    keep = (rng.random(n) >= 0.07) & (lx1 - lx0 >= 5) & (lz1 - lz0 >= 5)
    lx0, lx1, lz0, lz1 = lx0[keep], lx1[keep], lz0[keep], lz1[keep]
    n = len(lx0)

    # Per building: height (taller downtown), storey height, facade column width, type.
    mx, mz = (lx0 + lx1) / 2, (lz0 + lz1) / 2
    r = np.hypot(mx, mz) / half
    height = np.exp(rng.normal(np.log(14.0), 0.45, n)) * (1 + 3.0 * np.exp(-((r / 0.35) ** 2)))
    height = np.clip(height, 6.0, 220.0)
    fh = rng.uniform(3.0, 4.0, n)
    step = np.clip(4.5 / detail, 1.0, 9.0) * rng.uniform(0.8, 1.25, n)
    obj = np.arange(1, n + 1)  # object 0 is the ground
    u = rng.random(n)
    prism = (u < 0.2) & (height < 60)
    tower = ~prism & ((u < 0.5) | (height > 45))
    box = ~prism & ~tower

    batch = SolidBatch()
    xv, yv, zv = np.eye(3)

    def add(idx, profiles, ya, yb):
        nv = np.maximum(1, np.rint((yb - ya) / fh[idx])).astype(np.int64) * rows_per_floor
        org = np.zeros((len(idx), 3))
        org[:, 1] = ya
        batch.add(profiles, org, xv, zv, (yb - ya)[:, None] * yv, obj=obj[idx], step=step[idx],
                  nv=nv, cap1=True, tag=_TAG_BODY)

    top_rect = np.stack([lx0, lz0, lx1, lz1], 1)
    ids = np.flatnonzero(box)
    add(ids, rect_profile(lx0[ids], lz0[ids], lx1[ids], lz1[ids]), np.zeros(len(ids)), height[ids])
    top_rect[box] += [1.0, 1.0, -1.0, -1.0]

    # Prisms: convex polygons inscribed in the lot's ellipse, grouped by corner count.
    kk = rng.integers(5, 9, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    for k in range(5, 9):
        ids = np.flatnonzero(prism & (kk == k))
        if len(ids) == 0:
            continue
        ang = phase[ids, None] + np.linspace(0, 2 * np.pi, k, endpoint=False)[None]
        rx, rz = (lx1[ids] - lx0[ids]) / 2, (lz1[ids] - lz0[ids]) / 2
        poly = np.stack([mx[ids, None] + rx[:, None] * np.cos(ang),
                         mz[ids, None] + rz[:, None] * np.sin(ang)], axis=-1)
        add(ids, poly, np.zeros(len(ids)), height[ids])
    ids = np.flatnonzero(prism)
    rx, rz = (lx1[ids] - lx0[ids]) / 2, (lz1[ids] - lz0[ids]) / 2
    top_rect[ids] = np.stack([mx[ids] - 0.6 * rx, mz[ids] - 0.6 * rz, mx[ids] + 0.6 * rx,
                              mz[ids] + 0.6 * rz], 1)

    # Towers: 2 or 3 tiers, each set back from the one below.
    nt = rng.integers(2, 4, n)
    cut = np.sort(rng.uniform(0.35, 0.85, (n, 2)), axis=1)[:, ::-1]
    ys = np.stack([np.zeros(n), height * (1 - cut[:, 0]),
                   np.where(nt == 3, height * (1 - cut[:, 1]), height), height], 1)
    shrink = rng.uniform(0.08, 0.2, (n, 3, 2))
    rect = np.stack([lx0, lz0, lx1, lz1], 1)
    for t in range(3):
        if t:
            w, d = rect[:, 2] - rect[:, 0], rect[:, 3] - rect[:, 1]
            sx, sz = w * shrink[:, t, 0], d * shrink[:, t, 1]
            rect = rect + np.stack([sx, sz, -sx, -sz], 1)
        ids = np.flatnonzero(tower & (nt > t))
        add(ids, rect_profile(*rect[ids].T), ys[ids, t], ys[ids, t + 1])
        top = tower & (nt == t + 1)
        top_rect[top] = rect[top] + [1.0, 1.0, -1.0, -1.0]

    # Rooftop plant: boxes and octagonal tanks on the top tier.
    iw, idd = top_rect[:, 2] - top_rect[:, 0], top_rect[:, 3] - top_rect[:, 1]
    n_plant = np.minimum(6, rng.poisson(1.2 * min(detail, 3.0), n))
    n_plant[(iw < 3) | (idd < 3)] = 0
    own = np.repeat(np.arange(n), n_plant)
    m = len(own)
    w = 1.0 + rng.random(m) * (np.minimum(4.0, iw[own]) - 1.0)
    d = 1.0 + rng.random(m) * (np.minimum(4.0, idd[own]) - 1.0)
    px = top_rect[own, 0] + rng.random(m) * (iw[own] - w)
    pz = top_rect[own, 1] + rng.random(m) * (idd[own] - d)
    ph = rng.uniform(1.0, 3.5, m)
    tank = rng.random(m) < 0.3
    org = np.zeros((m, 3))
    org[:, 1] = height[own]
    sel = np.flatnonzero(~tank)
    batch.add(rect_profile(px[sel], pz[sel], px[sel] + w[sel], pz[sel] + d[sel]), org[sel], xv,
              zv, ph[sel, None] * yv, obj=obj[own[sel]], cap1=True, tag=_TAG_PLANT)
    sel = np.flatnonzero(tank)
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    rr = np.minimum(w[sel], d[sel]) / 2
    poly = np.stack([px[sel, None] + rr[:, None] * (1 + np.cos(ang)),
                     pz[sel, None] + rr[:, None] * (1 + np.sin(ang))], axis=-1)
    batch.add(poly, org[sel], xv, zv, ph[sel, None] * yv, obj=obj[own[sel]], cap1=True,
              tag=_TAG_PLANT)
    layout = {"x_edges": xe, "z_edges": ze, "buildings": n}
    return batch.freeze(), layout


def _ground_breaks(xe: np.ndarray, ze: np.ndarray):
    return (np.concatenate([[xe[0] - OUTSKIRTS], xe, [xe[-1] + OUTSKIRTS]]),
            np.concatenate([[ze[0] - OUTSKIRTS], ze, [ze[-1] + OUTSKIRTS]]))


def _fit(triangles: int, detail: float, seed: int):
    """(solids, layout, ground step) of the block grid that meets the request."""

    def make(nbx, nbz):
        solids, layout = _plan(nbx, nbz, detail, seed)
        bx, bz = _ground_breaks(layout["x_edges"], layout["z_edges"])
        return (solids, layout), int(solids_count(solids).sum()), bx, bz, 1

    guess = triangles * (1 - GROUND_SHARE) / (450.0 * detail * 9)
    (solids, layout), step, _ = fit_plan(triangles, make, guess, GROUND_SHARE, GROUND_STEP)
    return solids, layout, step


def generate(triangles: int | None = DEFAULT_TRIANGLES, seed: int = 0) -> Scene:
    """A 2.5D city of about ``triangles`` triangles (within +-20 % for 10k..several million).

    Parameters
    ----------
    triangles : the triangle budget (None: DEFAULT_TRIANGLES). More triangles make a larger
        city (more blocks) with more facade detail.
    seed : the random seed; the same (triangles, seed) gives bit-identical arrays.

    Returns
    -------
    Scene named "city": object 0 is the ground, each building (with its tiers and rooftop plant)
    is one object; the walk area is the streets (floor y = 0); ``meta["is_2_5d"]`` is True.
    """
    triangles = DEFAULT_TRIANGLES if triangles is None else triangles
    triangles, seed = check_request(triangles, seed)
    detail = _detail(triangles)
    solids, layout, step = _fit(triangles, detail, seed)
    xe, ze = layout["x_edges"], layout["z_edges"]
    rng = np.random.default_rng([seed, 0xC17C])
    parts = MeshParts()

    # Ground: asphalt streets, pavement blocks, grass outskirts; one object.
    bx, bz = _ground_breaks(xe, ze)
    gv, gf, gix, giz = grid_xz(subdivide(bx, step), subdivide(bz, step), 0.0)
    cxz = gv[gf].mean(axis=1)
    ix = np.searchsorted(xe, cxz[:, 0]) - 1
    iz = np.searchsorted(ze, cxz[:, 2]) - 1
    inside = (ix >= 0) & (ix < len(xe) - 1) & (iz >= 0) & (iz < len(ze) - 1)
    street = inside & ((ix % 2 == 0) | (iz % 2 == 0))
    base = np.where(street[:, None], ASPHALT, np.where(inside[:, None], PAVEMENT, GRASS))
    tile = np.where((gix + giz) % 2 == 0, 1.0, 0.94)[:, None]
    parts.add(gv, gf, 0, base * tile)
    del gv, gf, gix, giz, cxz, ix, iz, inside, street, base, tile

    # Buildings, coloured and stored piece by piece: the mesh's int64 per-face arrays and float
    # colours never exist for the whole city at once.
    n_obj = int(solids.obj.max()) + 1 if len(solids) else 1
    wall_pick = rng.integers(0, len(WALL_COLORS), size=n_obj)
    wall_rgb = vary(np.ones(3), rng, n_obj, 0.1) * WALL_COLORS[wall_pick]
    glass = rng.random(n_obj) < 0.15
    window_rgb = vary(WINDOW_COLOR, rng, n_obj, 0.15)
    roof_rgb = vary(ROOF_COLOR, rng, n_obj, 0.15)
    rows2 = detail >= 1.8
    for mesh in solids_mesh_parts(solids):
        obj = solids.obj[mesh.solid]
        tag = solids.tag[mesh.solid]
        window = (mesh.iu % 2 == 1) & ((mesh.iv % 2 == 1) if rows2 else True)
        window |= glass[obj] & (mesh.iu % 3 != 0)
        wall = mesh.kind == 0
        rgb = np.where((wall & window)[:, None], window_rgb[obj], wall_rgb[obj])
        rgb = np.where((mesh.kind != 0)[:, None], roof_rgb[obj], rgb)
        plant_rgb = PLANT_COLOR * (0.9 + 0.2 * (mesh.kind == 0))[:, None]
        rgb = np.where((tag == _TAG_PLANT)[:, None], plant_rgb, rgb)
        parts.add(mesh.verts, mesh.faces, obj, rgb)

    verts, faces, object_ids, colors = parts.build()
    colors = shade_by_normal(verts, faces, colors)
    rects = []
    for k in range(0, len(ze), 2):  # streets along X
        rects.append([xe[0], ze[k], xe[-1], ze[k + 1], 0.0])
    for i in range(0, len(xe), 2):  # streets along Z
        rects.append([xe[i], ze[0], xe[i + 1], ze[-1], 0.0])
    scene = Scene(
        vertices=verts, faces=faces, object_ids=object_ids, colors=colors, name="city",
        walk=WalkArea(rects=np.array(rects), eye_height=1.7, eye_range=(1.5, 1.9)),
        object_names=["ground"] + [f"building_{i}" for i in range(1, int(object_ids.max()) + 1)],
    )
    scene.meta.update({
        "generator": "city", "seed": seed, "requested_triangles": triangles,
        "is_2_5d": True, "blocks": [(len(xe) - 2) // 2, (len(ze) - 2) // 2],
        "buildings": int(layout["buildings"]), "detail": detail, "ground_step_m": float(step),
    })
    return scene
