"""The exact planar test (Koltun et al. 2001, Sec. 5.1) and the rasterized test's
overestimation as Table 1 defines it.

Exact: the union of the occluding segments' dual regions (each a trapeze or a double triangle
in the unit square: ``f0 * f1 <= 0``, ``dual_space.region``) is taken away from the square,
region by region, as convex polygons (each region is two convex parts, each two half-planes
within the square; taking a convex part away from a convex piece leaves at most two convex
pieces); the cell and the node see each other iff some area of the square stays uncovered.
Pure numpy (shapely, which the issue suggests, is not among the installed packages). A set of
measure zero left uncovered (two regions that touch) is not visibility.

Overestimation (Table 1): over a set of target boxes, P_E is the footprint area the exact test
finds occluded and P_C the area the rasterized test does; the rasterized test is conservative
(it never calls occluded what the exact one calls visible), so P_C <= P_E and the
overestimation is ``(P_E - P_C) / P_E`` in percent. Like the paper's, it does not depend on the
model's depth complexity. Targets here: every kd leaf of the scene (tested directly, not through
the hierarchy, so both tests see the same leaves), weighted by its XZ footprint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from visibility.cores.dual_ray.dual_space import (
    occluders,
    raster_visible,
    shaft_frame,
    shaft_regions,
)
from visibility.cores.dual_ray.fences import Fences, scene_fences
from visibility.cores.dual_ray.kdtree import scene_kdtree
from visibility.scene import Scene

#: Uncovered area of the unit square (dual ray space) below which the exact test says hidden.
AREA_TOL = 1e-12


def _clip(poly: np.ndarray, c: float, a: float, b: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of convex polygon ``poly`` (k, 2) where c + a x + b y <= 0."""
    if len(poly) == 0:
        return poly
    f = c + a * poly[:, 0] + b * poly[:, 1]
    if np.all(f <= 0):
        return poly
    if np.all(f >= 0):
        return poly[:0]
    out = []
    k = len(poly)
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        fp, fq = f[i], f[(i + 1) % k]
        if fp <= 0:
            out.append(p)
        if (fp < 0 < fq) or (fq < 0 < fp):
            t = fp / (fp - fq)
            out.append(p + t * (q - p))
    return np.array(out).reshape(-1, 2)


def _area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def uncovered(regs: np.ndarray) -> list[np.ndarray]:
    """What of the unit square the dual regions ``regs`` (n, 6) leave uncovered, as convex
    polygons (each (k, 2)) of area above ``AREA_TOL``."""
    pieces = [_SQUARE]
    for c0, a0, b0, c1, a1, b1 in regs:
        # The region's two convex parts, each {g <= 0, h <= 0}: f0 <= 0 <= f1 and
        # f1 <= 0 <= f0.
        for g, h in (((c0, a0, b0), (-c1, -a1, -b1)), ((-c0, -a0, -b0), (c1, a1, b1))):
            out = []
            for p in pieces:
                # p minus {g <= 0, h <= 0} = (p and g > 0) + (p and g <= 0 and h > 0).
                keep = _clip(p, -g[0], -g[1], -g[2])
                if _area(keep) > AREA_TOL:
                    out.append(keep)
                rest = _clip(_clip(p, *g), -h[0], -h[1], -h[2])
                if _area(rest) > AREA_TOL:
                    out.append(rest)
            pieces = out
            if not pieces:
                return pieces
    return pieces


def exact_visible(regs: np.ndarray) -> bool:
    """Whether the union of the dual regions ``regs`` (n, 6) leaves part of the unit square
    uncovered (more than ``AREA_TOL``): the exact planar answer."""
    return bool(uncovered(regs))


def shaft_visible_exact(alo: np.ndarray, ahi: np.ndarray, blo: np.ndarray, bhi: np.ndarray,
                        fences: Fences) -> bool:
    """The exact test of box B (3,) [min], (3,) [max] against box A among ``fences``."""
    frame = shaft_frame(alo, ahi, blo, bhi)
    if frame[13] == 0.0:
        return True
    regs, _, _ = shaft_regions(frame, fences.seg, fences.top, fences.bot, fences.lean,
                               fences.grid_lo,
                               fences.grid_step, fences.grid_n, fences.cell_start,
                               fences.cell_items)
    return exact_visible(regs)


@dataclass
class Overestimation:
    """Table 1's measure for one cell: ``percent[r]`` at each resolution r, from the occluded
    footprint areas ``exact_area`` (P_E) and ``raster_area[r]`` (P_C), m^2, over ``targets``
    kd leaves; ``unsound`` counts leaves the raster called occluded and the exact test visible
    (0 for a conservative raster)."""

    percent: dict[int, float]
    exact_area: float
    raster_area: dict[int, float]
    targets: int
    unsound: int


def overestimation(scene: Scene, box: np.ndarray, resolutions: list[int], coarse: int = 16,
                   sample: int | None = None, seed: int = 0) -> Overestimation:
    """Table 1's overestimation of the rasterized test against the exact one for cell ``box``
    (2, 3) over the kd leaves of ``scene`` with a shaft (module docstring): all of them, or a
    random ``sample`` of that many (``seed``), which keeps the exact test's cost bounded on big
    scenes."""
    tree, _ = scene_kdtree(scene)
    fences, _ = scene_fences(scene)
    alo = np.ascontiguousarray(box[0], dtype=np.float64)
    ahi = np.ascontiguousarray(box[1], dtype=np.float64)
    leaves = np.flatnonzero((tree.child[:, 0] < 0)
                            & (tree.item_start[1:] > tree.item_start[:-1]))
    if sample is not None and len(leaves) > sample:
        leaves = np.sort(np.random.default_rng(seed).choice(leaves, sample, replace=False))
    p_e = 0.0
    p_c = {int(r): 0.0 for r in resolutions}
    unsound = 0
    n = 0
    for leaf in leaves:
        blo, bhi = tree.lo[leaf], tree.hi[leaf]
        frame = shaft_frame(alo, ahi, blo, bhi)
        if frame[13] == 0.0:
            continue
        n += 1
        area = float((bhi[0] - blo[0]) * (bhi[2] - blo[2]))
        regs, segs, ids = shaft_regions(frame, fences.seg, fences.top, fences.bot, fences.lean,
                                        fences.grid_lo, fences.grid_step, fences.grid_n,
                                        fences.cell_start, fences.cell_items)
        vf, vstart = occluders(frame, segs, ids, fences.vid)
        ex = exact_visible(regs)
        if not ex:
            p_e += area
        for r in resolutions:
            vis, _ = raster_visible(vf, vstart, int(r), int(coarse))
            if not vis:
                p_c[int(r)] += area
                if ex:
                    unsound += 1
    pct = {r: (100.0 * (p_e - a) / p_e if p_e > 0 else 0.0) for r, a in p_c.items()}
    return Overestimation(pct, p_e, p_c, n, unsound)
