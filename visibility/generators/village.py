"""A village (not 2.5D): narrow jogging streets, houses with overhanging upper storeys and
gable roofs, arches spanning streets, trees with trunk and canopy.

Streets run on a jittered grid: every street segment between two crossings has its own offset
and width, so streets jog at each crossing (the crossing itself is a small square). Houses line
the blocks, their upper storeys overhang the street (above head height), some street segments
pass under a stone arch, and trees fill courtyards, parks and the countryside around.
The request is met by the number of blocks, the detail (wall, roof and canopy tessellation)
and, last, the ground tessellation.
"""

from __future__ import annotations

import numpy as np

from visibility.generators._mesh import (
    MeshParts,
    SolidBatch,
    Solids,
    blob_mesh,
    check_request,
    fit_plan,
    grid_xz,
    rect_profile,
    shade_by_normal,
    solid_caps,
    solids_count,
    solids_mesh_parts,
    subdivide,
    vary,
)
from visibility.scene import Scene, WalkArea

DEFAULT_TRIANGLES = 100_000
BLOCK_SIZE = (24.0, 40.0)
STREET_WIDTH = (3.5, 6.0)
#: Largest sideways offset of a street segment from its grid line (metres).
JITTER = 1.2
#: Clearance between a street (or square) and the houses beside it (metres).
MARGIN = 0.3
OUTSKIRTS = 30.0
GROUND_SHARE = 0.1
GROUND_STEP = (0.4, 30.0)

PLASTER = np.array([[235, 228, 210], [225, 200, 150], [215, 170, 140], [200, 205, 210],
                    [230, 215, 185], [190, 160, 120]], dtype=np.float64)
TIMBER = np.array([90, 60, 40], dtype=np.float64)
WINDOW = np.array([60, 75, 95], dtype=np.float64)
DOOR = np.array([105, 65, 35], dtype=np.float64)
ROOFS = np.array([[170, 80, 55], [120, 60, 50], [95, 95, 105], [150, 100, 70]], dtype=np.float64)
STONE = np.array([165, 155, 140], dtype=np.float64)
BARK = np.array([95, 70, 50], dtype=np.float64)
LEAVES = np.array([70, 120, 55], dtype=np.float64)
COBBLE = np.array([130, 120, 110], dtype=np.float64)
GRASS = np.array([105, 140, 75], dtype=np.float64)

_TAG_LOWER, _TAG_UPPER, _TAG_ROOF, _TAG_CHIMNEY, _TAG_TRUNK, _TAG_ARCH = range(6)


def _detail(triangles: int) -> dict:
    d = float(np.clip(np.sqrt(triangles / 1e5), 0.3, 6.0))
    return {
        "detail": d,
        "wall_step": float(np.clip(2.2 / d**0.6, 0.35, 5.0)),
        "rows": 1 if d < 1.5 else (2 if d < 4 else 3),
        "canopy_level": 0 if d < 0.45 else (1 if d < 1.3 else (2 if d < 3.5 else 3)),
        "arch_points": int(8 + 4 * round(d)),
    }


def _streets(nbx: int, nbz: int, rng: np.random.Generator) -> dict:
    """Street segments, crossing squares and blocks of a jittered nbx x nbz grid."""
    X = np.concatenate([[0.0], np.cumsum(rng.uniform(*BLOCK_SIZE, nbx) + 5.0)])
    Z = np.concatenate([[0.0], np.cumsum(rng.uniform(*BLOCK_SIZE, nbz) + 5.0)])
    X, Z = X - X[-1] / 2, Z - Z[-1] / 2
    vw = rng.uniform(*STREET_WIDTH, (nbx + 1, nbz))
    vx0 = X[:, None] + rng.uniform(-JITTER, JITTER, (nbx + 1, nbz)) - vw / 2
    vx1 = vx0 + vw
    hw = rng.uniform(*STREET_WIDTH, (nbz + 1, nbx))
    hz0 = Z[:, None] + rng.uniform(-JITTER, JITTER, (nbz + 1, nbx)) - hw / 2
    hz1 = hz0 + hw

    def pad(a, fill):  # pad the last axis with one fill column on each side
        return np.pad(a, ((0, 0), (1, 1)), constant_values=fill)

    # Crossing squares: the box around the ends of the segments meeting there.
    px0 = np.minimum(pad(vx0, np.inf)[:, :-1], pad(vx0, np.inf)[:, 1:])  # (nbx+1, nbz+1)
    px1 = np.maximum(pad(vx1, -np.inf)[:, :-1], pad(vx1, -np.inf)[:, 1:])
    pz0 = np.minimum(pad(hz0, np.inf)[:, :-1], pad(hz0, np.inf)[:, 1:]).T
    pz1 = np.maximum(pad(hz1, -np.inf)[:, :-1], pad(hz1, -np.inf)[:, 1:]).T
    # Segments run from square to square.
    vz0, vz1 = pz1[:, :-1], pz0[:, 1:]  # (nbx+1, nbz)
    hx0, hx1 = px1[:-1, :].T, px0[1:, :].T  # (nbz+1, nbx)
    return {"X": X, "Z": Z, "v": np.stack([vx0, vz0, vx1, vz1], -1),
            "h": np.stack([hx0, hz0, hx1, hz1], -1), "p": np.stack([px0, pz0, px1, pz1], -1)}


def _lots(a0, a1, rng):
    """Lots along rows [a0_r, a1_r]: returns (row, start, end); 5.5-10 m wide, the last one
    stretched to the row's end or closing it when at least 4.5 m remain."""
    n = len(a0)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    m = int(np.ceil(np.max(a1 - a0) / 5.5)) + 1
    w = rng.uniform(5.5, 10.0, (n, m))
    ends = a0[:, None] + np.cumsum(w, axis=1)
    starts = np.concatenate([a0[:, None], ends[:, :-1]], axis=1)
    full = ends <= a1[:, None]
    nfull = full.sum(axis=1)
    last = np.where(nfull > 0, ends[np.arange(n), np.maximum(nfull - 1, 0)], a0)
    rem = a1 - last
    extra = rem >= 4.5
    ends = np.where(full, ends, np.nan)
    stretch = ~extra & (nfull > 0)
    ends[np.flatnonzero(stretch), nfull[stretch] - 1] = a1[stretch]
    row, col = np.nonzero(np.isfinite(ends))
    s, e = starts[row, col], ends[row, col]
    xr = np.flatnonzero(extra)
    row = np.concatenate([row, xr])
    s = np.concatenate([s, last[xr]])
    e = np.concatenate([e, a1[xr]])
    order = np.lexsort((s, row))
    return row[order], s[order], e[order]


def _trim_houses(rects: np.ndarray, walk: np.ndarray, axis: np.ndarray):
    """Shrink house footprints (x0, z0, x1, z1) off every walk rect (plus MARGIN); return the
    kept mask. Each overlap is cut on the side that loses the least area; a house left
    narrower than 4 m or shallower than 3.5 m is dropped."""
    w = walk + np.array([-MARGIN, -MARGIN, MARGIN, MARGIN])
    keep = np.ones(len(rects), bool)
    over = ((rects[:, None, 0] < w[None, :, 2]) & (rects[:, None, 2] > w[None, :, 0])
            & (rects[:, None, 1] < w[None, :, 3]) & (rects[:, None, 3] > w[None, :, 1]))
    for h, r in zip(*np.nonzero(over), strict=True):
        x0, z0, x1, z1 = rects[h].tolist()
        if x1 <= x0 or z1 <= z0:
            continue
        wx0, wz0, wx1, wz1 = w[r].tolist()
        if not (x0 < wx1 and x1 > wx0 and z0 < wz1 and z1 > wz0):
            continue
        options = [(wx1 - x0) * (z1 - z0), (x1 - wx0) * (z1 - z0),
                   (wz1 - z0) * (x1 - x0), (z1 - wz0) * (x1 - x0)]
        best = int(np.argmin(options))
        if best == 0:
            x0 = wx1
        elif best == 1:
            x1 = wx0
        elif best == 2:
            z0 = wz1
        else:
            z1 = wz0
        rects[h] = (x0, z0, x1, z1)
    along = np.where(axis == 0, rects[:, 2] - rects[:, 0], rects[:, 3] - rects[:, 1])
    across = np.where(axis == 0, rects[:, 3] - rects[:, 1], rects[:, 2] - rects[:, 0])
    keep &= (along >= 4.0) & (across >= 3.5)
    return keep


def _arch_profile(r: float, spring: float, pier: float, crown: float, n_arc: int):
    """(2N, 2) closed arch profile (outer chain then inner chain reversed) in (across, up)
    metres around the street centre, and its (4(N-1), 3) cap triangulation."""
    R, top = r + pier, spring + r + crown
    corner = np.arctan2(top - spring, R)
    theta = np.unique(np.concatenate([np.linspace(np.pi, 0, n_arc), [corner, np.pi - corner]]))
    theta = theta[::-1]
    inner = np.stack([r * np.cos(theta), spring + r * np.sin(theta)], 1)
    # Where the ray from the arc centre at angle theta meets the outer rectangle.
    c, s = np.cos(theta), np.sin(theta)
    with np.errstate(divide="ignore"):
        t_side = np.where(np.abs(c) > 1e-12, R / np.abs(c), np.inf)
        t_top = np.where(s > 1e-12, (top - spring) / s, np.inf)
    t = np.minimum(t_side, t_top)
    outer = np.stack([c * t, spring + s * t], 1)
    outer[np.abs(outer[:, 0] - R) < 1e-9, 0] = R
    outer[np.abs(outer[:, 0] + R) < 1e-9, 0] = -R
    inner = np.concatenate([[[-r, 0.0]], inner, [[r, 0.0]]])
    outer = np.concatenate([[[-R, 0.0]], outer, [[R, 0.0]]])
    n = len(inner)
    prof = np.concatenate([outer, inner[::-1]])
    o = np.arange(n)
    i = 2 * n - 1 - o
    tri = np.concatenate([np.stack([i[:-1], i[1:], o[1:]], 1),
                          np.stack([i[:-1], o[1:], o[:-1]], 1)])
    return prof, tri


def _plan(nbx: int, nbz: int, opts: dict, seed: int):
    rng = np.random.default_rng([seed, nbx, nbz, 0x71A])
    st = _streets(nbx, nbz, rng)
    v, h, p = st["v"], st["h"], st["p"]
    walk = np.concatenate([v.reshape(-1, 4), h.reshape(-1, 4), p.reshape(-1, 4)])
    batch = SolidBatch()
    yv = np.array([0.0, 1.0, 0.0])
    ax_vec = np.eye(3)[[0, 2]]  # row axis 0 runs along X, 1 along Z
    obj_next = 1  # object 0 is the ground

    # Arches: on inner street segments of 16 m or more, at the segment's middle.
    arches = []  # (axis of street, along centre, across centre, half width)
    for axis, seg, inner_lines in ((0, h, range(1, nbz)), (1, v, range(1, nbx))):
        for line in inner_lines:
            for j in range(seg.shape[1]):
                x0, z0, x1, z1 = seg[line, j]
                length = (x1 - x0) if axis == 0 else (z1 - z0)
                if length >= 16 and rng.random() < 0.3:
                    along = (x0 + x1) / 2 if axis == 0 else (z0 + z1) / 2
                    across = (z0 + z1) / 2 if axis == 0 else (x0 + x1) / 2
                    half = (z1 - z0) / 2 if axis == 0 else (x1 - x0) / 2
                    arches.append((axis, along, across, half, rng.uniform(0.9, 1.5)))
    arches_a = np.array(arches, dtype=np.float64).reshape(-1, 5)

    # Blocks: parks or rings of houses; rows along each side, cut around arch piers.
    bi, bk = (a.ravel() for a in np.meshgrid(np.arange(nbx), np.arange(nbz), indexing="ij"))
    bx0, bx1 = v[bi, bk, 2] + MARGIN, v[bi + 1, bk, 0] - MARGIN
    bz0, bz1 = h[bk, bi, 3] + MARGIN, h[bk + 1, bi, 1] - MARGIN
    park = rng.random(len(bi)) < 0.12
    depth = np.minimum(rng.uniform(7.0, 10.0, len(bi)),
                       (np.minimum(bx1 - bx0, bz1 - bz0) - 4.0) / 2)
    park |= depth < 4.0
    rows = []  # along0, along1, across0, across1, axis, street side (-1 at across0, +1 at a1)
    for b in np.flatnonzero(~park):
        d = depth[b]
        rows.append((bx0[b], bx1[b], bz0[b], bz0[b] + d, 0, -1))
        rows.append((bx0[b], bx1[b], bz1[b] - d, bz1[b], 0, 1))
        if bz1[b] - bz0[b] - 2 * d > 5.0:
            rows.append((bz0[b] + d + 0.3, bz1[b] - d - 0.3, bx0[b], bx0[b] + d, 1, -1))
            rows.append((bz0[b] + d + 0.3, bz1[b] - d - 0.3, bx1[b] - d, bx1[b], 1, 1))
    rows_a = np.array(rows, dtype=np.float64).reshape(-1, 6)
    # Cut rows around arches whose street runs along them (the pier stands in the row).
    for axis, along, across, half, thick in arches_a:
        near = ((rows_a[:, 4] == axis) & (rows_a[:, 0] < along + thick)
                & (rows_a[:, 1] > along - thick)
                & (np.minimum(np.abs(rows_a[:, 2] - across), np.abs(rows_a[:, 3] - across))
                   < half + 3.0))
        cut = np.flatnonzero(near)
        if len(cut):
            left, right = rows_a[cut].copy(), rows_a[cut].copy()
            left[:, 1] = along - thick / 2 - 0.4
            right[:, 0] = along + thick / 2 + 0.4
            rows_a = np.concatenate([np.delete(rows_a, cut, axis=0), left, right])
    row, s0, s1 = _lots(rows_a[:, 0], rows_a[:, 1], rng)
    s0, s1 = s0 + 0.15, s1 - 0.15
    ok = s1 - s0 >= 4.0
    row, s0, s1 = row[ok], s0[ok], s1[ok]
    axis = rows_a[row, 4].astype(np.int64)
    side = rows_a[row, 5]
    c0, c1 = rows_a[row, 2], rows_a[row, 3]
    rect = np.where((axis == 0)[:, None], np.stack([s0, c0, s1, c1], 1),
                    np.stack([c0, s0, c1, s1], 1))
    keep = _trim_houses(rect, walk, axis)
    rect, axis, side = rect[keep], axis[keep], side[keep]
    n = len(rect)

    # Houses: lower storey, wider upper storey (overhanging the street), gable roof, chimney.
    house_obj = obj_next + np.arange(n)
    obj_next += n
    h1 = rng.uniform(2.7, 3.2, n)
    h2 = rng.uniform(2.5, 3.0, n) * np.where(rng.random(n) < 0.2, 2, 1)
    over = rng.uniform(0.4, 0.9, n)
    pitch = np.radians(rng.uniform(30, 45, n))
    rows_n = opts["rows"]
    step = opts["wall_step"]
    zero = np.zeros((n, 3))
    batch.add(rect_profile(*rect.T), zero, np.eye(3)[0], np.eye(3)[2], h1[:, None] * yv,
              obj=house_obj, step=step, nv=rows_n, cap0=False, cap1=False, tag=_TAG_LOWER)
    up = rect.copy()
    k = np.where(axis == 0, 1, 0) + np.where(side > 0, 2, 0)  # which coordinate grows
    up[np.arange(n), k] += np.where(side > 0, over, -over)
    org = zero.copy()
    org[:, 1] = h1
    nv2 = rows_n * np.where(h2 > 4, 2, 1)
    batch.add(rect_profile(*up.T), org, np.eye(3)[0], np.eye(3)[2], h2[:, None] * yv,
              obj=house_obj, step=step, nv=nv2, cap0=True, cap1=False, tag=_TAG_UPPER)
    # Roof: a triangular profile across the row swept along it.
    a0 = np.where(axis == 0, up[:, 1], up[:, 0])
    a1 = np.where(axis == 0, up[:, 3], up[:, 2])
    l0 = np.where(axis == 0, up[:, 0], up[:, 1])
    l1 = np.where(axis == 0, up[:, 2], up[:, 3])
    eave = 0.3
    rise = ((a1 - a0) / 2 + eave) * np.tan(pitch)
    prof = np.stack([np.stack([a0 - eave, np.zeros(n)], 1), np.stack([a1 + eave, np.zeros(n)], 1),
                     np.stack([(a0 + a1) / 2, rise], 1)], axis=1)
    base = h1 + h2
    across_vec = ax_vec[1 - axis]
    along_vec = ax_vec[axis]
    org = along_vec * l0[:, None] + yv * base[:, None]
    roof_step = step * 1.2
    batch.add(prof, org, across_vec, yv, along_vec * (l1 - l0)[:, None], obj=house_obj,
              step=roof_step, nv=np.maximum(1, np.rint((l1 - l0) / roof_step)).astype(np.int64),
              cap0=True, cap1=True, tag=_TAG_ROOF)
    ch = np.flatnonzero(rng.random(n) < 0.35)
    if len(ch):
        al = l0[ch] + 0.5 + rng.random(len(ch)) * np.maximum(l1[ch] - l0[ch] - 1.6, 0)
        ac = a0[ch] + (a1[ch] - a0[ch]) * rng.choice([0.2, 0.7], len(ch))
        cx0 = np.where(axis[ch] == 0, al, ac)
        cz0 = np.where(axis[ch] == 0, ac, al)
        org = np.zeros((len(ch), 3))
        org[:, 1] = base[ch]
        batch.add(rect_profile(cx0, cz0, cx0 + 0.6, cz0 + 0.6), org, np.eye(3)[0], np.eye(3)[2],
                  (rise[ch] + 0.6)[:, None] * yv, obj=house_obj[ch], cap1=True, tag=_TAG_CHIMNEY)

    # Arches: the profile spans the street, swept along it by the arch's thickness.
    arch_ids = np.zeros(0, np.int64)
    arch_tri = np.zeros((0, 3), np.int64)
    if len(arches_a):
        na = len(arches_a)
        spring = rng.uniform(2.5, 3.2, na)
        crown = rng.uniform(0.5, 0.9, na)
        profs, tri = [], None
        for j in range(na):
            pr, tri = _arch_profile(arches_a[j, 3] + 0.25, spring[j], 0.9, crown[j],
                                    opts["arch_points"])
            profs.append(pr)
        aax = arches_a[:, 0].astype(np.int64)
        across_vec = ax_vec[1 - aax]
        along_vec = ax_vec[aax]
        org = (along_vec * (arches_a[:, 1] - arches_a[:, 4] / 2)[:, None]
               + across_vec * arches_a[:, 2:3])
        arch_ids = batch.add(np.stack(profs), org, across_vec, yv,
                             along_vec * arches_a[:, 4:5], obj=obj_next + np.arange(na),
                             step=step, nv=1, cap0=False, cap1=False, tag=_TAG_ARCH)
        arch_tri = tri
        obj_next += na

    # Trees: courtyards, parks and the countryside.
    regions = []  # x0, z0, x1, z1, fill probability
    for b in range(len(bi)):
        if park[b]:
            regions.append((bx0[b] + 0.5, bz0[b] + 0.5, bx1[b] - 0.5, bz1[b] - 0.5, 0.85))
        else:
            d = depth[b] + 0.8
            regions.append((bx0[b] + d, bz0[b] + d, bx1[b] - d, bz1[b] - d, 0.7))
    ext = np.array([walk[:, 0].min(), walk[:, 1].min(), walk[:, 2].max(), walk[:, 3].max()])
    o, g = OUTSKIRTS, 4.0
    regions += [(ext[0] - o, ext[1] - o, ext[2] + o, ext[1] - g, 0.3),
                (ext[0] - o, ext[3] + g, ext[2] + o, ext[3] + o, 0.3),
                (ext[0] - o, ext[1] - g, ext[0] - g, ext[3] + g, 0.3),
                (ext[2] + g, ext[1] - g, ext[2] + o, ext[3] + g, 0.3)]
    reg = np.array(regions, dtype=np.float64)
    spacing = rng.uniform(5.5, 8.0, len(reg))
    nx = np.floor((reg[:, 2] - reg[:, 0]) / spacing).clip(0).astype(np.int64)
    nz = np.floor((reg[:, 3] - reg[:, 1]) / spacing).clip(0).astype(np.int64)
    cnt = nx * nz
    rid = np.repeat(np.arange(len(reg)), cnt)
    q = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    cw = (reg[rid, 2] - reg[rid, 0]) / nx[rid]
    cd = (reg[rid, 3] - reg[rid, 1]) / nz[rid]
    room = np.minimum(cw, cd) / 2 - 0.2
    fill = (rng.random(len(rid)) < reg[rid, 4]) & (room >= 1.2 * 1.15)
    rc = 1.2 + rng.random(len(rid)) * (np.minimum(3.0, room / 1.15) - 1.2)
    jx = (rng.random(len(rid)) * 2 - 1) * np.maximum(cw / 2 - rc * 1.15, 0)
    jz = (rng.random(len(rid)) * 2 - 1) * np.maximum(cd / 2 - rc * 1.15, 0)
    tx = reg[rid, 0] + (q // nz[rid] + 0.5) * cw + jx
    tz = reg[rid, 1] + (q % nz[rid] + 0.5) * cd + jz
    # No canopy over a street or square (parks may touch a square's corner).
    wm = walk + np.array([-MARGIN, -MARGIN, MARGIN, MARGIN])
    reach = 1.15 * rc
    clash = ((tx - reach)[:, None] < wm[None, :, 2]) & ((tx + reach)[:, None] > wm[None, :, 0]) & (
        (tz - reach)[:, None] < wm[None, :, 3]) & ((tz + reach)[:, None] > wm[None, :, 1])
    fill &= ~clash.any(axis=1)
    tx, tz, rc = tx[fill], tz[fill], rc[fill]
    nt = len(tx)
    ry = rc * rng.uniform(0.8, 1.3, nt)
    trunk_h = np.maximum(rng.uniform(1.8, 3.2, nt), 0.6 * ry + 1.2)
    trunk_r = rng.uniform(0.15, 0.3, nt)
    ang = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    trunk = np.stack([tx[:, None] + trunk_r[:, None] * np.cos(ang),
                      tz[:, None] + trunk_r[:, None] * np.sin(ang)], axis=-1)
    tree_obj = obj_next + np.arange(nt)
    obj_next += nt
    batch.add(trunk, np.zeros((nt, 3)), np.eye(3)[0], np.eye(3)[2], trunk_h[:, None] * yv,
              obj=tree_obj, cap1=False, tag=_TAG_TRUNK)
    canopy = {"centers": np.stack([tx, trunk_h + 0.6 * ry, tz], 1),
              "radii": np.stack([rc, ry, rc * rng.uniform(0.85, 1.15, nt)], 1), "obj": tree_obj}
    solids = batch.freeze()
    fixed = int(solids_count(solids).sum()) + nt * 20 * 4 ** opts["canopy_level"]
    fixed += 2 * len(arch_ids) * len(arch_tri)
    # A uniform ground grid: breaks at every jogging street edge would cost far too many tiles.
    xb = np.array([ext[0] - o - 10, ext[2] + o + 10])
    zb = np.array([ext[1] - o - 10, ext[3] + o + 10])
    plan = {"solids": solids, "walk": walk, "arch_ids": arch_ids, "arch_tri": arch_tri,
            "canopy": canopy, "houses": n, "house_axis": axis, "house_side": side,
            "house_obj": house_obj, "trees": nt, "arches": len(arches_a), "blocks": (nbx, nbz),
            "parks": int(park.sum()), "ground_breaks": (xb, zb)}
    return plan, fixed, xb, zb, 1


def generate(triangles: int | None = DEFAULT_TRIANGLES, seed: int = 0) -> Scene:
    """A village of about ``triangles`` triangles (within +-20 % for 10k..several million).

    Parameters
    ----------
    triangles : the triangle budget (None: DEFAULT_TRIANGLES). More triangles make more blocks
        and finer walls, roofs and canopies.
    seed : the random seed; the same (triangles, seed) gives bit-identical arrays.

    Returns
    -------
    Scene named "village": object 0 is the ground, then one object per house (storeys, roof,
    chimney), per arch and per tree; the walk area is the streets and crossing squares (floor
    y = 0); ``meta["is_2_5d"]`` is False (overhangs, arches, canopies).
    """
    triangles = DEFAULT_TRIANGLES if triangles is None else triangles
    triangles, seed = check_request(triangles, seed)
    opts = _detail(triangles)
    guess = triangles * (1 - GROUND_SHARE) / (2100.0 * opts["detail"] ** 0.9)
    plan, step, _ = fit_plan(triangles, lambda a, b: _plan(a, b, opts, seed), guess,
                             GROUND_SHARE, GROUND_STEP)
    rng = np.random.default_rng([seed, 0x71AC])
    parts = MeshParts()
    walk = plan["walk"]

    # Ground: cobbles on the streets and squares, grass elsewhere.
    xb, zb = plan["ground_breaks"]
    xe, ze = subdivide(xb, step), subdivide(zb, step)
    gv, gf, gix, giz = grid_xz(xe, ze, 0.0)
    # Tiles whose centre lies on a street: one slice per walk rect of a (tiles x, tiles z) mask.
    xc, zc = (xe[1:] + xe[:-1]) / 2, (ze[1:] + ze[:-1]) / 2
    mask = np.zeros((len(xc), len(zc)), bool)
    i0, i1 = np.searchsorted(xc, walk[:, 0]), np.searchsorted(xc, walk[:, 2])
    k0, k1 = np.searchsorted(zc, walk[:, 1]), np.searchsorted(zc, walk[:, 3])
    for a, b, c, d in zip(i0, i1, k0, k1, strict=True):
        mask[a:b, c:d] = True
    on_street = mask[gix, giz]
    tile = np.where((gix + giz) % 2 == 0, 1.0, 0.93)[:, None]
    parts.add(gv, gf, 0, np.where(on_street[:, None], COBBLE, GRASS) * tile)

    del gv, gf, gix, giz, on_street, tile

    # Houses, chimneys, trunks, arch sides, coloured and stored piece by piece (the whole
    # mesh's int64 per-face arrays and float colours never exist at once).
    solids: Solids = plan["solids"]
    n_obj = int(solids.obj.max()) + 1 if len(solids) else 1
    plaster = PLASTER[rng.integers(0, len(PLASTER), n_obj)] * vary(np.ones(3), rng, n_obj, 0.08)
    roof = ROOFS[rng.integers(0, len(ROOFS), n_obj)] * vary(np.ones(3), rng, n_obj, 0.1)
    timbered = rng.random(n_obj) < 0.4
    stone = vary(STONE, rng, n_obj, 0.1)
    bark = vary(BARK, rng, n_obj, 0.1)
    for mesh in solids_mesh_parts(solids):
        obj = solids.obj[mesh.solid]
        tag = solids.tag[mesh.solid]
        wall = mesh.kind == 0
        nv = solids.nv[mesh.solid]
        window = wall & (mesh.iu % 2 == 1) & ((nv == 1) | (mesh.iv % 2 == 1))
        beam = wall & timbered[obj] & ((mesh.iu % 3 == 0) | (mesh.iv % 2 == 0))
        door = wall & (tag == _TAG_LOWER) & (mesh.iv == 0) & (mesh.iu == mesh.nu // 2)
        rgb = plaster[obj]
        rgb = np.where(((tag == _TAG_UPPER) & beam)[:, None], TIMBER, rgb)
        rgb = np.where(((tag <= _TAG_UPPER) & window)[:, None], WINDOW, rgb)
        rgb = np.where(((tag == _TAG_UPPER) & (mesh.kind == 2))[:, None], TIMBER, rgb)
        rgb = np.where(door[:, None], DOOR, rgb)
        rgb = np.where((tag == _TAG_ROOF)[:, None],
                       roof[obj] * np.where(mesh.kind == 0, 1.0, 0.8)[:, None], rgb)
        rgb = np.where((tag == _TAG_CHIMNEY)[:, None], 0.8 * roof[obj], rgb)
        rgb = np.where((tag == _TAG_ARCH)[:, None], stone[obj], rgb)
        rgb = np.where((tag == _TAG_TRUNK)[:, None], bark[obj], rgb)
        parts.add(mesh.verts, mesh.faces, obj, rgb)
    for at_end in (False, True):
        cv, cf, owner = solid_caps(solids, plan["arch_ids"], plan["arch_tri"], at_end)
        parts.add(cv, cf, solids.obj[owner], stone[solids.obj[owner]])

    # Canopies.
    cano = plan["canopy"]
    bv, bf, blob = blob_mesh(cano["centers"], cano["radii"], opts["canopy_level"], rng)
    leaves = vary(LEAVES, rng, len(cano["obj"]), 0.18)
    parts.add(bv, bf, cano["obj"][blob], leaves[blob])

    verts, faces, object_ids, colors = parts.build()
    colors = shade_by_normal(verts, faces, colors)
    rects = np.concatenate([walk, np.zeros((len(walk), 1))], axis=1)
    scene = Scene(
        vertices=verts, faces=faces, object_ids=object_ids, colors=colors, name="village",
        walk=WalkArea(rects=rects, eye_height=1.7, eye_range=(1.5, 1.9)),
    )
    scene.meta.update({
        "generator": "village", "seed": seed, "requested_triangles": triangles,
        "is_2_5d": False, "blocks": list(plan["blocks"]), "houses": int(plan["houses"]),
        "trees": int(plan["trees"]), "arches": int(plan["arches"]), "parks": plan["parks"],
        "detail": opts["detail"], "ground_step_m": float(step),
    })
    return scene
