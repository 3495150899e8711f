"""Whether walkthrough poses stand on the ground in the open: vertical lines through the eyes
against the scene's triangles.

A pose is *inside* when the first surface above its eye faces up: the eye is inside a closed
solid (a building of a city scene, where streets are where buildings are not), as the walk-area
detection reads geometry (``visibility.walkable``; a scene whose ``meta["winding"]`` is ``"cw"``
has its normals flipped). Its *eye height* is its height above the highest surface crossed
below it or, where none is (a city model without terrain), above the floor of its viewcell (the
detection's local ground). Y-up, metres.
"""

from __future__ import annotations

import numpy as np

from visibility.scene import Scene
from visibility.viewcells import MAX_STEP, ViewcellGrid
from visibility.walkable import UP_NY

#: Side of the XZ bins the triangles are sorted into before the line tests, metres.
BIN_SIZE = 8.0


def vertical_hits(tris: np.ndarray, points: np.ndarray, bin_size: float = BIN_SIZE
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crossings of the vertical lines through ``points`` ((p, 3), metres) with ``tris``
    ((m, 3, 3), metres): (point index (h,), triangle row of ``tris`` (h,), crossing height
    (h,)), every pair once. Triangles vertical in XZ (walls) are never crossed."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0 or len(tris) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    xz = tris[:, :, [0, 2]]
    lo, hi = xz.min(axis=1), xz.max(axis=1)
    origin = points[:, [0, 2]].min(axis=0) - bin_size
    span = points[:, [0, 2]].max(axis=0) + bin_size - origin
    nb = np.maximum(1, np.ceil(span / bin_size).astype(np.int64) + 1)
    # Only triangles over some point's bin can be crossed.
    pb = np.floor((points[:, [0, 2]] - origin) / bin_size).astype(np.int64)
    pkey = pb[:, 0] * nb[1] + pb[:, 1]
    b0 = np.clip(np.floor((lo - origin) / bin_size), -1, nb).astype(np.int64)
    b1 = np.clip(np.floor((hi - origin) / bin_size), -1, nb).astype(np.int64)
    keep = np.all((b1 >= 0) & (b0 <= nb - 1), axis=1)
    t_ids = np.flatnonzero(keep)
    b0, b1 = np.maximum(b0[keep], 0), np.minimum(b1[keep], nb - 1)
    ni, nk = b1[:, 0] - b0[:, 0] + 1, b1[:, 1] - b0[:, 1] + 1
    per = ni * nk
    tri = np.repeat(t_ids, per)
    o = np.arange(int(per.sum())) - np.repeat(np.cumsum(per) - per, per)
    r = np.repeat(np.arange(len(t_ids)), per)
    key = (b0[r, 0] + o // nk[r]) * nb[1] + b0[r, 1] + o % nk[r]
    wanted = np.isin(key, pkey)
    key, tri = key[wanted], tri[wanted]
    order = np.argsort(key, kind="stable")
    key, tri = key[order], tri[order]
    start = np.searchsorted(key, pkey, side="left")
    count = np.searchsorted(key, pkey, side="right") - start
    pi = np.repeat(np.arange(len(points)), count)
    oo = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    ti = tri[np.repeat(start, count) + oo]
    # Signed areas in XZ: the point is inside when all three agree in sign.
    a = xz[ti] - points[pi][:, None, [0, 2]]
    w0 = a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0]
    w1 = a[:, 2, 0] * a[:, 0, 1] - a[:, 2, 1] * a[:, 0, 0]
    w2 = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    area = w0 + w1 + w2
    inside = (np.abs(area) > 1e-12) & (
        ((w0 >= 0) & (w1 >= 0) & (w2 >= 0)) | ((w0 <= 0) & (w1 <= 0) & (w2 <= 0)))
    pi, ti = pi[inside], ti[inside]
    w = np.stack([w0[inside], w1[inside], w2[inside]], axis=1) / area[inside][:, None]
    y = np.sum(w * tris[ti, :, 1], axis=1)
    return pi, ti, y


def ground_check(scene: Scene, grid: ViewcellGrid, positions: np.ndarray) -> dict:
    """How the eye ``positions`` ((p, 3), metres) stand. Per pose: ``inside`` when the first
    surface above the eye faces up (the eye is inside a closed solid: a building, as the
    walk-area detection reads it), ``roofed`` when any surface is above it, ``outside_cells``
    when no viewcell holds it, and its eye height over the ground (the highest surface below
    the eye, else its cell's floor). ``off_ground`` counts poses inside, outside the cells or
    whose eye height lies outside the grid's eye range widened by ``MAX_STEP`` (a walk
    interpolates the eye between cells whose floors differ by up to that). Returns the counts,
    a bool (p,) ``ok`` array, and the eye height's min / max over the poses that are not
    inside (metres)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(positions)
    valid = scene.valid_faces
    tris = scene.triangles()[valid]
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    sign = -1.0 if str(scene.meta.get("winding", "ccw")).lower() == "cw" else 1.0
    up = sign * nrm[:, 1] / np.maximum(np.linalg.norm(nrm, axis=1), 1e-300) > UP_NY
    pi, ti, y = vertical_hits(tris, positions)
    eye = positions[pi, 1]
    above = y > eye
    # The first surface above each eye: the lowest crossing above it.
    first = np.full(n, np.inf)
    np.minimum.at(first, pi[above], y[above])
    first_up = np.zeros(n, dtype=bool)
    at_first = above & (y == first[pi])
    first_up[pi[at_first & up[ti]]] = True
    below = np.full(n, -np.inf)
    np.maximum.at(below, pi[~above], y[~above])
    cells = [grid.cell_of(p) for p in positions]
    outside = np.array([c is None for c in cells], dtype=bool)
    floor = np.array([grid.floor[c] if c is not None else np.nan for c in cells])
    bare = ~np.isfinite(below)
    height = positions[:, 1] - np.where(bare, floor, below)
    lo, hi = grid.walk.eye_range
    with np.errstate(invalid="ignore"):
        low_high = ~((height >= lo - MAX_STEP) & (height <= hi + MAX_STEP))
    ok = ~(first_up | outside | low_high)
    shown = ~first_up & np.isfinite(height)
    return {
        "poses": int(n),
        "inside": int(np.count_nonzero(first_up)),
        "roofed": int(np.count_nonzero(np.isfinite(first))),
        "outside_cells": int(np.count_nonzero(outside)),
        "no_surface_below": int(np.count_nonzero(bare)),
        "off_ground": int(np.count_nonzero(~ok)),
        "eye_height_min_m": float(height[shown].min()) if shown.any() else None,
        "eye_height_max_m": float(height[shown].max()) if shown.any() else None,
        "ok": ok,
    }
