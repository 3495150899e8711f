"""What a scene's geometry says about itself: is it 2.5D (a height field plus vertical walls)?

A 2.5D core (heightfield occluders, e.g. the dual-ray core) is right only where every occluder is
a column standing on the ground: seen from above, each (x, z) has open air above one top surface
and none below it. This module decides that from the triangles alone, so real city tiles are
recognised without a sidecar, and reports why.

Method (Y-up, metres; the scene's rest pose, valid faces only):

* Near-vertical triangles (``|n_y| <= wall_ny``) are *walls*: they never break a height field.
* Every other triangle is point-sampled at the centres of a regular XZ grid (cell size chosen
  from the projected area so the sample count stays bounded; each sample stands for one cell's
  area). Its height and its facing (the sign of ``n_y``; a sidecar's ``"winding": "cw"`` flips
  it) are kept per grid column.
* In each column the samples are sorted by height. A pair of consecutive surfaces with an
  up-facing one below and a down-facing one above, more than ``clearance`` apart, bounds open
  space under a surface: an overhang, an arch, a canopy, a ceiling, a floor under another
  floor. Such a column is *violating*. Surfaces touching within ``clearance`` (a building's
  ground face on the terrain, a roof under rooftop plant) and solids without a bottom face (the
  next surface above faces up) bound no open space, and the underside of the lowest layer faces
  only the void beneath the scene.
* The scene is 2.5D when the violating share of the occupied footprint is at most
  ``max_violating_share`` and its top surfaces face up (topmost surfaces that face down are
  ceilings over everything: an interior, or inverted winding).

Limit: facing is what tells a solid's inside from open air, so a single-sided surface floating
face-up over the ground (a tilted grass blade, a one-sided canopy plane) reads as the top of a
solid column. Scenes built that way state ``is_2_5d`` in their meta (the generators do).

The scene's own ``meta["is_2_5d"]`` (a generator's, or a sidecar's) overrides the analysis; see
``scene_is_2_5d``, which also caches the geometry's answer per scene object.
"""

from __future__ import annotations

import threading
import time
import weakref
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numba import njit

from visibility.scene import Scene

#: Triangles with ``|n_y|`` at most this (within ~5.7 degrees of vertical) are walls.
WALL_NY = 0.1
#: Open space thinner than this (metres) between two surfaces is not counted: modelling slop
#: between a building's ground face and the terrain, not a place to see into.
CLEARANCE = 0.5
#: The largest share of the occupied footprint that may lie under an overhang for a 2.5D scene.
MAX_VIOLATING_SHARE = 0.02
#: Bounds on the grid samples (4 bytes each) and cells (14 bytes each); the cell size follows
#: from them (about 0.3 m on a 1 km^2 city tile), so memory stays under ~80 MB at any size.
MAX_SAMPLES = 4_000_000
MAX_CELLS = 4_000_000


@dataclass(frozen=True)
class HeightFieldAnalysis:
    """The outcome of ``analyse_2_5d``: the decision, why, and the measurements behind it.

    Shares are of the occupied footprint (grid cells holding some non-wall surface) except
    ``wall_area_share`` (of the total triangle area) and ``top_up_share`` (of the top surfaces'
    sampled footprint).
    """

    is_2_5d: bool
    reason: str
    violating_share: float = 0.0
    wall_area_share: float = 0.0
    top_up_share: float = 1.0
    occupied_cells: int = 0
    violating_cells: int = 0
    samples: int = 0
    cell_size: float = 0.0
    seconds: float = 0.0
    source: str = "geometry"
    #: Where the first overhang was found: (x, z) of the column's centre and the open space's
    #: bottom and top heights, metres; None when there is none.
    first_overhang: tuple[float, float, float, float] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly fields."""
        return asdict(self)


@njit(cache=True, nogil=True)
def _count_samples(ax, az, bx, bz, cx, cz, x0, z0, s, nx, nz, counts):  # pragma: no cover
    """Per grid cell, how many triangles (XZ projections) contain its centre."""
    for t in range(len(ax)):
        # Modes typed int64 (np.int64, not literals 0 and 1): a literal compiles its own
        # specialization of _cover.
        _cover(t, ax, az, bx, bz, cx, cz, x0, z0, s, nx, nz, counts, counts, np.int64(0))


@njit(cache=True, nogil=True)
def _cover(t, ax, az, bx, bz, cx, cz, x0, z0, s, nx, nz, counts, out_tri, mode):  # pragma: no cover
    """Visit the cell centres inside triangle t's XZ projection. mode 0: count per cell; mode 1:
    write t at the cell's next free slot (``counts`` holds the slots, advanced here)."""
    i0 = max(int(np.floor((min(ax[t], bx[t], cx[t]) - x0) / s - 0.5)), 0)
    i1 = min(int(np.ceil((max(ax[t], bx[t], cx[t]) - x0) / s - 0.5)), nx - 1)
    j0 = max(int(np.floor((min(az[t], bz[t], cz[t]) - z0) / s - 0.5)), 0)
    j1 = min(int(np.ceil((max(az[t], bz[t], cz[t]) - z0) / s - 0.5)), nz - 1)
    det = (bx[t] - ax[t]) * (cz[t] - az[t]) - (bz[t] - az[t]) * (cx[t] - ax[t])
    if det == 0.0:
        return
    sg = 1.0 if det > 0 else -1.0
    for i in range(i0, i1 + 1):
        px = x0 + (i + 0.5) * s
        for j in range(j0, j1 + 1):
            pz = z0 + (j + 0.5) * s
            # Edge functions with the triangle's own orientation; a centre on an edge counts for
            # both neighbours, which only adds a coincident sample (harmless for the rule).
            e0 = sg * ((bx[t] - ax[t]) * (pz - az[t]) - (bz[t] - az[t]) * (px - ax[t]))
            e1 = sg * ((cx[t] - bx[t]) * (pz - bz[t]) - (cz[t] - bz[t]) * (px - bx[t]))
            e2 = sg * ((ax[t] - cx[t]) * (pz - cz[t]) - (az[t] - cz[t]) * (px - cx[t]))
            if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                c = i * nz + j
                if mode == 0:
                    counts[c] += 1
                else:
                    out_tri[counts[c]] = t
                    counts[c] += 1


@njit(cache=True, nogil=True)
def _fill_samples(ax, az, bx, bz, cx, cz, x0, z0, s, nx, nz, slots, out_tri):  # pragma: no cover
    for t in range(len(ax)):
        _cover(t, ax, az, bx, bz, cx, cz, x0, z0, s, nx, nz, slots, out_tri, np.int64(1))


@njit(cache=True, nogil=True)
def _classify_columns(start, tri, plane, up, x0, z0, s, nz, clearance, top_tol):  # pragma: no cover
    """Per occupied column: (violating, top faces up). ``plane[t] = (a, b, c)`` gives the height
    of triangle t at (x, z) as a*x + b*z + c; ``up[t]`` its facing."""
    n_cells = len(start) - 1
    violating = np.zeros(n_cells, dtype=np.bool_)
    top_up = np.zeros(n_cells, dtype=np.int8)  # 1 up, -1 down, 0 empty
    hs = np.empty(256, dtype=np.float64)
    fs = np.empty(256, dtype=np.bool_)
    for c in range(n_cells):
        a, b = start[c], start[c + 1]
        k = b - a
        if k == 0:
            continue
        if k > len(hs):
            hs = np.empty(2 * k, dtype=np.float64)
            fs = np.empty(2 * k, dtype=np.bool_)
        px = x0 + (c // nz + 0.5) * s
        pz = z0 + (c % nz + 0.5) * s
        for m in range(k):
            t = tri[a + m]
            hs[m] = plane[t, 0] * px + plane[t, 1] * pz + plane[t, 2]
            fs[m] = up[t]
        # Insertion sort by height (columns hold a handful of layers).
        for m in range(1, k):
            h, f = hs[m], fs[m]
            q = m - 1
            while q >= 0 and hs[q] > h:
                hs[q + 1] = hs[q]
                fs[q + 1] = fs[q]
                q -= 1
            hs[q + 1] = h
            fs[q + 1] = f
        # The top surface's facing: any up-facing sample within top_tol of the highest.
        top = -1
        for m in range(k - 1, -1, -1):
            if hs[m] < hs[k - 1] - top_tol:
                break
            if fs[m]:
                top = 1
                break
        top_up[c] = top
        for m in range(k - 1):
            if fs[m] and not fs[m + 1] and hs[m + 1] - hs[m] > clearance:
                violating[c] = True
                break
    return violating, top_up


def analyse_2_5d(
    scene: Scene,
    *,
    wall_ny: float = WALL_NY,
    clearance: float = CLEARANCE,
    max_violating_share: float = MAX_VIOLATING_SHARE,
    max_samples: int = MAX_SAMPLES,
) -> HeightFieldAnalysis:
    """Decide from the geometry alone whether ``scene`` is 2.5D (module docstring: method).

    ``wall_ny``: |n_y| bound of walls; ``clearance``: metres of open space that count;
    ``max_violating_share``: the share of the footprint allowed under overhangs;
    ``max_samples``: grid sample budget. Ignores ``meta``; O(triangles + samples).
    """
    t0 = time.perf_counter()
    valid = scene.valid_faces
    if not valid.any():
        return HeightFieldAnalysis(False, "no valid triangles", seconds=time.perf_counter() - t0)
    tri = scene.vertices[scene.faces[valid]]  # (m, 3, 3)
    # Relative to a corner keeps far-from-origin scenes (1e5 m offsets) precise.
    origin = tri[0, 0].copy()
    tri = tri - origin
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ny = np.divide(n[:, 1], norm, out=np.zeros(len(n)), where=norm > 0)
    if str(scene.meta.get("winding", "ccw")).lower() == "cw":
        ny = -ny
    wall = np.abs(ny) <= wall_ny
    wall_share = float(norm[wall].sum() / max(norm.sum(), 1e-300))
    flat = tri[~wall]
    if len(flat) == 0:
        return HeightFieldAnalysis(True, "only vertical walls: a height field of extrusions",
                            wall_area_share=wall_share, seconds=time.perf_counter() - t0)
    # Plane of each non-wall triangle as y = a*x + b*z + c (exists: n_y != 0).
    nf = n[~wall]
    pa, pb = -nf[:, 0] / nf[:, 1], -nf[:, 2] / nf[:, 1]
    pc = flat[:, 0, 1] - pa * flat[:, 0, 0] - pb * flat[:, 0, 2]
    plane = np.ascontiguousarray(np.stack([pa, pb, pc], axis=1))
    up = ny[~wall] > 0
    projected = float(np.abs(nf[:, 1]).sum() / 2.0)
    lo = flat[:, :, [0, 2]].reshape(-1, 2).min(axis=0)
    hi = flat[:, :, [0, 2]].reshape(-1, 2).max(axis=0)
    bbox_area = float(max(hi[0] - lo[0], 1e-6) * max(hi[1] - lo[1], 1e-6))
    s = max(np.sqrt(projected / max_samples), np.sqrt(bbox_area / MAX_CELLS), 1e-6)
    nx = int(np.ceil((hi[0] - lo[0]) / s)) + 1
    nz = int(np.ceil((hi[1] - lo[1]) / s)) + 1
    cols = [np.ascontiguousarray(flat[:, k, d]) for k in range(3) for d in (0, 2)]
    args = (*cols, float(lo[0]), float(lo[1]), float(s), nx, nz)
    counts = np.zeros(nx * nz, dtype=np.int32)
    _count_samples(*args, counts)
    start = np.zeros(nx * nz + 1, dtype=np.int32)
    np.cumsum(counts, out=start[1:])
    del counts
    samples = int(start[-1])
    slots = start[:-1].copy()
    tri_of = np.empty(samples, dtype=np.int32)
    _fill_samples(*args, slots, tri_of)
    violating, top = _classify_columns(start, tri_of, plane, up, float(lo[0]), float(lo[1]),
                                       float(s), nz, float(clearance), float(clearance))
    occupied = int(np.count_nonzero(top))
    n_viol = int(np.count_nonzero(violating))
    first = _first_overhang(violating, start, tri_of, plane, up, float(lo[0]), float(lo[1]),
                            float(s), nz, float(clearance), origin)
    share = n_viol / occupied if occupied else 0.0
    top_up = float(np.count_nonzero(top > 0) / occupied) if occupied else 1.0
    stats = dict(violating_share=share, wall_area_share=wall_share, top_up_share=top_up,
                 occupied_cells=occupied, violating_cells=n_viol, samples=samples,
                 cell_size=float(s), seconds=time.perf_counter() - t0, first_overhang=first)
    if top_up < 0.5:
        why = (f"its topmost surfaces face down over {1 - top_up:.0%} of the footprint: "
               "ceilings over everything (an interior) or inverted winding")
        return HeightFieldAnalysis(False, why, **stats)
    if share > max_violating_share:
        x, z, y0, y1 = first  # type: ignore[misc]
        why = (f"{share:.1%} of the footprint lies under an overhang (open space under a "
               f"surface; the limit is {max_violating_share:.0%}); the first found at x = "
               f"{x:.1f}, z = {z:.1f} m: open from y = {y0:.1f} to {y1:.1f} m")
        return HeightFieldAnalysis(False, why, **stats)
    why = (f"a height field plus walls: {share:.2%} of the footprint under an overhang (limit "
           f"{max_violating_share:.0%}), {wall_share:.0%} of the area in walls")
    return HeightFieldAnalysis(True, why, **stats)


def _first_overhang(violating: np.ndarray, start: np.ndarray, tri_of: np.ndarray,
                    plane: np.ndarray, up: np.ndarray, x0: float, z0: float, s: float, nz: int,
                    clearance: float, origin: np.ndarray
                    ) -> tuple[float, float, float, float] | None:
    """(x, z, bottom, top) in world metres of the open space of the first violating column,
    or None."""
    hit = np.flatnonzero(violating)
    if len(hit) == 0:
        return None
    c = int(hit[0])
    px, pz = x0 + (c // nz + 0.5) * s, z0 + (c % nz + 0.5) * s
    t = tri_of[start[c]:start[c + 1]]
    h = plane[t, 0] * px + plane[t, 1] * pz + plane[t, 2]
    order = np.argsort(h, kind="stable")
    h, f = h[order], up[t][order]
    for m in range(len(h) - 1):
        if f[m] and not f[m + 1] and h[m + 1] - h[m] > clearance:
            return (float(px + origin[0]), float(pz + origin[2]), float(h[m] + origin[1]),
                    float(h[m + 1] + origin[1]))
    return (float(px + origin[0]), float(pz + origin[2]), float(h[0] + origin[1]),
            float(h[-1] + origin[1]))


def stated_2_5d(scene: Scene) -> HeightFieldAnalysis | None:
    """The answer ``scene.meta["is_2_5d"]`` states (a generator's or a sidecar's), or None when
    the meta states none (absent or null)."""
    stated = scene.meta.get("is_2_5d")
    if stated is None:
        return None
    who = "generator" if "generator" in scene.meta else "sidecar"
    return HeightFieldAnalysis(bool(stated), f"stated by the scene's {who} (meta['is_2_5d'])",
                               source="meta")


def is_2_5d(scene: Scene) -> tuple[bool, dict[str, Any]]:
    """(whether ``scene`` is 2.5D, the analysis as a dict with a ``reason`` and a ``source``,
    "meta" or "geometry"): the scene's ``meta["is_2_5d"]`` when it states one, else
    ``analyse_2_5d``. Computes afresh; servers use ``scene_is_2_5d``."""
    result = stated_2_5d(scene) or analyse_2_5d(scene)
    return result.is_2_5d, result.as_dict()


# The geometry's answer per scene object; weak keys, so an unloaded scene takes its entry along.
_CACHE: weakref.WeakKeyDictionary[Scene, HeightFieldAnalysis] = weakref.WeakKeyDictionary()
_CACHE_LOCK = threading.Lock()
# One lock per scene being analysed, so concurrent first calls analyse it once, not N times.
_PENDING: weakref.WeakKeyDictionary[Scene, threading.Lock] = weakref.WeakKeyDictionary()


def scene_is_2_5d(scene: Scene) -> tuple[bool, dict[str, Any]]:
    """``is_2_5d`` with the geometry analysed once per scene object (on first use; kept while the
    scene lives). The meta is read on every call, so a meta set later still overrides.
    Thread-safe; returns a fresh dict."""
    stated = stated_2_5d(scene)
    if stated is not None:
        return stated.is_2_5d, stated.as_dict()
    with _CACHE_LOCK:
        hit = _CACHE.get(scene)
        lock = None if hit is not None else _PENDING.setdefault(scene, threading.Lock())
    if hit is None:
        with lock:
            with _CACHE_LOCK:
                hit = _CACHE.get(scene)
            if hit is None:
                hit = analyse_2_5d(scene)
                with _CACHE_LOCK:
                    _CACHE[scene] = hit
                    _PENDING.pop(scene, None)
    return hit.is_2_5d, hit.as_dict()
