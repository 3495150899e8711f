"""The stiff and extreme cases in one small scene, far from the origin.

The walk area is two 4 m viewcells side by side (local X 0..8, Z 0..4, floor 0). Around it each
case is one object; ``meta["cases"]`` maps its name to its triangle ids and
``meta["case_purpose"]`` says what it tests:

- ``ground``: the tessellated ground plane;
- ``wall`` and ``hidden``: a closed box behind a tall wall, invisible from the walk area;
- ``visible``: a triangle in plain view of every point of the walk area;
- ``slivers``: triangles with aspect ratio 1e6;
- ``zero_area``, ``repeated_index``, ``non_finite``: degenerate faces (counted in
  ``scene.degenerate_report``, kept out of ``scene.valid_faces``);
- ``edge_on``: triangles whose plane contains an edge segment of a viewcell at eye height;
- ``eye_plane``: horizontal triangles at the bottom, middle and top of the eye range;
- ``coplanar``: overlapping triangles in one plane, one an exact duplicate;
- ``intersecting``: pairs of triangles that cross each other;
- ``huge``: a triangle 12 km across, larger than any view.

Everything, walk rects included, is moved by ``offset`` (default 1e5 m in X and Z) to test
precision. The rest of the budget is clutter: small random triangles away from the cases'
lines of sight (``meta["clutter_range"]`` is its [start, stop) of triangle ids).
"""

from __future__ import annotations

import numpy as np

from visibility.generators._mesh import (
    MeshParts,
    box_mesh,
    check_request,
    grid_xz,
    shade_by_normal,
    vary,
)
from visibility.scene import Scene, WalkArea

DEFAULT_TRIANGLES = 10_000
DEFAULT_OFFSET = 1e5
#: The walk rectangle in local coordinates: two 4 m cells.
WALK = (0.0, 0.0, 8.0, 4.0)
EYE_RANGE = (1.5, 1.9)
EYE_HEIGHT = 1.7
GROUND = (-40.0, -40.0, 48.0, 44.0)
#: No clutter in this box (local X, Z): it holds the walk area, every case and their views.
QUIET = (-17.0, -15.0, 23.0, 8.5)

PURPOSE = {
    "ground": "tessellated ground plane under everything",
    "wall": "tall wall (closed box) that hides the 'hidden' box",
    "hidden": "closed box behind the wall: must be invisible from the walk area",
    "visible": "triangle in plain view of every point of the walk area",
    "slivers": "triangles of aspect ratio 1e6 (one horizontal at eye height)",
    "zero_area": "faces with collinear or coincident vertices (degenerate: zero area)",
    "repeated_index": "faces repeating a vertex index (degenerate)",
    "non_finite": "faces using NaN or infinite vertices (degenerate)",
    "edge_on": "triangles whose plane contains a viewcell edge segment at eye height",
    "eye_plane": "horizontal triangles at the bottom, middle and top of the eye range",
    "coplanar": "overlapping coplanar triangles, one an exact duplicate of another",
    "intersecting": "pairs of triangles crossing each other",
    "huge": "a triangle 12 km across, larger than the whole view",
}

COLORS = {
    "ground": (120, 120, 115), "wall": (170, 80, 60), "hidden": (255, 0, 255),
    "visible": (0, 230, 60), "slivers": (250, 220, 0), "zero_area": (255, 255, 255),
    "repeated_index": (255, 255, 255), "non_finite": (255, 255, 255), "edge_on": (0, 220, 230),
    "eye_plane": (255, 140, 0), "coplanar": (220, 30, 30), "intersecting": (140, 60, 200),
    "huge": (150, 180, 220),
}


def _offset_vector(offset) -> np.ndarray:
    off = np.asarray(offset, dtype=np.float64)
    if off.ndim == 0:
        off = np.array([float(off), 0.0, float(off)])
    if off.shape != (3,) or not np.all(np.isfinite(off)):
        raise ValueError(f"offset must be a finite number or 3 numbers, got {offset!r}")
    return off


def _tris(*corners) -> tuple[np.ndarray, np.ndarray]:
    """Separate triangles from (3, 3) corner lists: (verts, faces)."""
    v = np.asarray(corners, dtype=np.float64).reshape(-1, 3)
    return v, np.arange(len(v)).reshape(-1, 3)


def _slivers(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Eight slivers of length 2-3 m and width length * 1e-6 west of the walk area."""
    n = 7
    d = rng.normal(size=(n, 3))
    d[:, 1] *= 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = np.cross(d, rng.normal(size=(n, 3)))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    length = rng.uniform(2.0, 3.0, n)
    c = np.stack([rng.uniform(-10, -6, n), rng.uniform(1.4, 2.2, n), rng.uniform(2.5, 4.5, n)], 1)
    a = c - d * length[:, None] / 2
    b = c + d * length[:, None] / 2
    apex = c + w * (length * 1e-6)[:, None]
    v = np.stack([a, b, apex], 1)
    # One along Z, horizontal at eye height: edge-on to the eye and a sliver at once.
    extra = np.array([[[-5.0, EYE_HEIGHT, 1.0], [-5.0, EYE_HEIGHT, 5.0],
                       [-5.0 + 4e-6, EYE_HEIGHT, 3.0]]])
    v = np.concatenate([v, extra]).reshape(-1, 3)
    return v, np.arange(len(v)).reshape(-1, 3)


def _clutter(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n small random triangles outside QUIET, in front of the wall, none degenerate."""
    out: list[np.ndarray] = []
    have = 0
    while have < n:
        m = 2 * (n - have) + 64
        c = np.stack([rng.uniform(GROUND[0], GROUND[2], m), rng.uniform(0.5, 8.0, m),
                      rng.uniform(GROUND[1], QUIET[3], m)], 1)
        size = rng.uniform(0.3, 2.0, m)
        corners = c[:, None] + rng.uniform(-0.5, 0.5, (m, 3, 3)) * size[:, None, None]
        x, y, z = (corners[:, :, k] for k in range(3))
        lo = [np.minimum(np.minimum(q[:, 0], q[:, 1]), q[:, 2]) for q in (x, y, z)]
        hi = [np.maximum(np.maximum(q[:, 0], q[:, 1]), q[:, 2]) for q in (x, y, z)]
        quiet = (hi[0] > QUIET[0]) & (lo[0] < QUIET[2]) & (hi[2] > QUIET[1]) & (lo[2] < QUIET[3])
        inside = (lo[0] > GROUND[0]) & (hi[0] < GROUND[2]) & (lo[2] > GROUND[1]) & (
            hi[2] < QUIET[3]) & (lo[1] > 0.05)
        e1 = [q[:, 1] - q[:, 0] for q in (x, y, z)]
        e2 = [q[:, 2] - q[:, 0] for q in (x, y, z)]
        area2 = ((e1[1] * e2[2] - e1[2] * e2[1]) ** 2 + (e1[2] * e2[0] - e1[0] * e2[2]) ** 2
                 + (e1[0] * e2[1] - e1[1] * e2[0]) ** 2)
        good = corners[~quiet & inside & (area2 > (0.02 * size**2) ** 2)]
        out.append(good[: n - have])
        have += len(out[-1])
    v = np.concatenate(out).reshape(-1, 3)
    return v, np.arange(len(v)).reshape(-1, 3)


def generate(triangles: int | None = DEFAULT_TRIANGLES, seed: int = 0,
             offset: float | tuple[float, float, float] = DEFAULT_OFFSET) -> Scene:
    """The stress scene: every stiff case once plus clutter up to ``triangles`` (exact for any
    budget of at least 1000; the cases alone take about 300 triangles).

    Parameters
    ----------
    triangles : the triangle budget (None: DEFAULT_TRIANGLES).
    seed : the random seed (slivers' orientation, clutter); same seed, bit-identical arrays.
    offset : metres added to every vertex and walk rect: a number (applied to X and Z) or
        an (x, y, z) triple.

    Returns
    -------
    Scene named "stress" with ``meta["cases"]`` ({name: [triangle ids]}), ``meta["case_purpose"]``,
    ``meta["case_objects"]`` ({name: object id}), ``meta["clutter_range"]``, ``meta["offset"]``,
    ``meta["cells"]`` (the two 4 m viewcell boxes, (2, 2, 3) nested lists, metres).
    """
    triangles = DEFAULT_TRIANGLES if triangles is None else triangles
    triangles, seed = check_request(triangles, seed)
    off = _offset_vector(offset)
    rng = np.random.default_rng([seed, 0x57E5])
    parts = MeshParts()
    cases: dict[str, list[int]] = {}
    objects: dict[str, int] = {}

    def add(name, verts, faces, rgb=None):
        obj = len(objects)
        objects[name] = obj
        color = np.asarray(COLORS[name] if rgb is None else rgb, dtype=np.float64)
        ids = parts.add(verts, faces, obj, color)
        cases[name] = ids.tolist()

    gv, gf, gix, giz = grid_xz(np.linspace(GROUND[0], GROUND[2], 12),
                               np.linspace(GROUND[1], GROUND[3], 12), 0.0)
    objects["ground"] = 0
    cases["ground"] = parts.add(gv, gf, 0, np.where(((gix + giz) % 2 == 0)[:, None],
                                                   COLORS["ground"], (100, 100, 96))).tolist()
    wv, wf, _, _ = box_mesh([-30.0, 0.0, 10.0], [38.0, 12.0, 10.4])
    add("wall", wv, wf)
    hv, hf, _, _ = box_mesh([3.5, 0.05, 12.0], [4.5, 1.0, 13.0])
    add("hidden", hv, hf)
    add("visible", *_tris([2.5, 0.5, -6.0], [5.5, 0.5, -6.0], [4.0, 3.0, -6.0]))
    add("slivers", *_slivers(rng))
    # Degenerate faces: exact in float64 even after the offset (integer steps along axes or
    # the diagonal, coincident points).
    zv = np.array([[-3, 1, -9], [-2, 1, -9], [-1, 1, -9],      # collinear along X
                   [-3, 1, -10], [-3, 2, -10], [-3, 3, -10],    # collinear along Y
                   [-2, 2, -11], [-1, 3, -10], [0, 4, -9],      # collinear along a diagonal
                   [1, 1, -9], [1, 1, -9], [1, 1, -9]], float)  # three coincident points
    add("zero_area", zv, np.arange(12).reshape(4, 3))
    rv = np.array([[2, 1, -9], [3, 1, -9], [2, 2, -9]], float)
    add("repeated_index", rv, np.array([[0, 0, 1], [0, 1, 1], [0, 1, 0], [2, 2, 2]]))
    nv = np.array([[4, 1, -9], [5, 1, -9], [np.nan, 2, -9], [np.inf, 1, -9], [4, -np.inf, -9],
                   [5, 2, np.nan]], float)
    add("non_finite", nv, np.array([[0, 1, 2], [0, 3, 1], [4, 1, 0], [2, 3, 5]]))
    theta = np.radians(30.0)
    tilt = np.array([0.0, np.sin(theta), np.cos(theta)])
    edge_on = [
        # Plane z = 0 holds the cells' south side; the triangle lies west of the walk area.
        [[-6.0, 0.5, 0.0], [-1.0, 0.5, 0.0], [-3.0, 3.0, 0.0]],
        # Plane x = 8 holds the east side of the second cell.
        [[8.0, 0.5, 5.0], [8.0, 0.5, 9.0], [8.0, 3.0, 7.0]],
        # Plane x = 4 holds the edge shared by the two cells.
        [[4.0, 0.5, 5.0], [4.0, 0.5, 8.0], [4.0, 2.5, 6.5]],
        # A plane through the north side at eye height, tilted 30 degrees up.
        [np.array([1.0, EYE_HEIGHT, 4.0]) + 3 * tilt, np.array([7.0, EYE_HEIGHT, 4.0]) + 3 * tilt,
         np.array([4.0, EYE_HEIGHT, 4.0]) + 6 * tilt],
        # A vertical plane through the cells' north-west vertical edge (x = 0, z = 4).
        [[-2.0, 0.5, 6.0], [-5.0, 0.5, 9.0], [-3.5, 3.0, 7.5]],
    ]
    add("edge_on", *_tris(*edge_on))
    add("eye_plane", *_tris(
        [10.0, EYE_RANGE[0], -1.0], [10.0, EYE_RANGE[0], 5.0], [16.0, EYE_RANGE[0], 2.0],
        [10.0, EYE_HEIGHT, -1.0], [16.0, EYE_HEIGHT, 2.0], [10.0, EYE_HEIGHT, 5.0],
        [10.0, EYE_RANGE[1], -1.0], [10.0, EYE_RANGE[1], 5.0], [16.0, EYE_RANGE[1], 2.0]))
    cop = _tris([-3.0, 0.5, -5.0], [1.0, 0.5, -5.0], [-1.0, 3.0, -5.0],
                [-2.5, 1.0, -5.0], [0.5, 1.0, -5.0], [-1.0, 3.5, -5.0],
                [-3.0, 0.5, -5.0], [1.0, 0.5, -5.0], [-1.0, 3.0, -5.0])
    add("coplanar", *cop, rgb=[COLORS["coplanar"], (30, 30, 220), (30, 200, 200)])
    add("intersecting", *_tris(
        [7.0, 0.5, -4.5], [11.0, 0.5, -4.5], [9.0, 3.0, -4.5],
        [9.0, 0.5, -6.0], [9.0, 0.5, -3.0], [9.0, 3.2, -4.5],
        [12.0, 0.3, -8.0], [16.0, 0.3, -8.0], [14.0, 2.5, -7.0],
        [12.0, 2.5, -8.0], [16.0, 2.5, -8.0], [14.0, 0.2, -7.2]),
        rgb=[COLORS["intersecting"], (20, 160, 140), COLORS["intersecting"], (20, 160, 140)])
    r = 6000.0
    add("huge", *_tris([4.0 - r, 40.0, 2.0 - r * 0.577], [4.0, 40.0, 2.0 + r * 1.155],
                       [4.0 + r, 40.0, 2.0 - r * 0.577]))
    base = parts.n_faces
    n_clutter = max(0, triangles - base)
    cv, cf = _clutter(n_clutter, rng)
    first = len(objects)
    clutter_obj = first + np.arange(len(cf)) // 64
    parts.add(cv, cf, clutter_obj, vary(np.array([150.0, 150.0, 150.0]), rng, len(cf), 0.3))

    verts, faces, object_ids, colors = parts.build()
    colors = shade_by_normal(verts, faces, colors)
    verts = verts + off
    x0, z0, x1, z1 = WALK
    rects = np.array([[x0 + off[0], z0 + off[2], x1 + off[0], z1 + off[2], off[1]]])
    cells = [[[x0 + 4 * i + off[0], off[1] + EYE_RANGE[0], z0 + off[2]],
              [x0 + 4 * (i + 1) + off[0], off[1] + EYE_RANGE[1], z1 + off[2]]] for i in range(2)]
    scene = Scene(vertices=verts, faces=faces, object_ids=object_ids, colors=colors,
                  name="stress",
                  walk=WalkArea(rects=rects, eye_height=EYE_HEIGHT, eye_range=EYE_RANGE),
                  object_names=list(objects) + [f"clutter_{i}" for i in
                                                range(int(object_ids.max()) + 1 - first)])
    scene.meta.update({
        "generator": "stress", "seed": seed, "requested_triangles": triangles, "is_2_5d": False,
        "cases": cases, "case_purpose": dict(PURPOSE), "case_objects": objects,
        "clutter_range": [base, base + len(cf)], "offset": off.tolist(), "cells": cells,
    })
    return scene
