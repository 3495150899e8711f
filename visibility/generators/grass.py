"""A meadow: a gently rolling terrain mesh covered by thin grass blades (tiny triangles).

Each blade is three triangles (a bent strip: two at the base, one at the tip), 1-2.5 cm wide
and 15-60 cm tall, standing at a random spot with a random heading and lean. The field grows with
the triangle budget at a fixed blade density; ``generate_swaying`` animates the same meadow with
per-vertex keyframes (blades bend in a travelling wind gust; the terrain stays put).
The walk area is the field, one rectangle per 4 m tile at the tile's highest ground.
"""

from __future__ import annotations

import numpy as np

from visibility.generators._mesh import check_request, grid_xz, to_rgb, vary
from visibility.scene import Scene, WalkArea

DEFAULT_TRIANGLES = 200_000
#: Blades per square metre (the field's side follows from the budget).
DENSITY = 120.0
#: Share of the budget spent on the terrain mesh.
TERRAIN_SHARE = 0.03
#: Terrain relief amplitude, metres.
RELIEF = 0.25
#: Side of a walk tile (one viewcell), metres.
TILE = 4.0
BLADE_HEIGHT = (0.15, 0.6)
BLADE_WIDTH = (0.01, 0.025)
#: Object granularity: blades are grouped into square patches of this side, metres.
PATCH = 2.0
#: Speed of the gust front in ``generate_swaying``, m/s.
GUST_SPEED = 3.0
GREEN = np.array([80.0, 150.0, 55.0])
SOIL = np.array([110.0, 90.0, 60.0])


def _height(x: np.ndarray, z: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """Terrain height (metres) at (x, z): a few smooth waves."""
    return RELIEF * (0.5 * np.sin(0.21 * x + phase[0]) * np.cos(0.17 * z + phase[1])
                     + 0.3 * np.sin(0.05 * x + 0.07 * z + phase[2])
                     + 0.2 * np.cos(0.33 * z - 0.11 * x + phase[3]))


def _plan(triangles: int) -> tuple[int, int, int, float]:
    """(terrain cells per side, three-triangle blades, one-triangle blades, field side m)."""
    g = max(4, int(np.sqrt(TERRAIN_SHARE * triangles / 2.0)))
    rest = triangles - 2 * g * g
    blades, singles = divmod(rest, 3)
    side = TILE * max(2, int(np.ceil(np.sqrt((blades + singles) / DENSITY) / TILE)))
    return g, blades, singles, side


def _build(triangles: int, seed: int):
    """Rest-state arrays plus what the animation needs: (verts, faces, obj, rgb, walk rects,
    blade base points (b, 3), per-vertex height fraction (n,), per-vertex blade index (n,),
    blade heights (b,), meta)."""
    rng = np.random.default_rng(seed)
    g, blades, singles, side = _plan(triangles)
    phase = rng.uniform(0, 2 * np.pi, 4)
    # Terrain.
    edges = np.linspace(0.0, side, g + 1)
    tv, tf, _, _ = grid_xz(edges, edges, 0.0)
    tv[:, 1] = _height(tv[:, 0], tv[:, 2], phase)
    t_rgb = vary(SOIL, rng, len(tf), 0.08)
    # Blades: 5 vertices, 3 triangles each; "singles" are one-triangle blades (budget remainder).
    nb = blades + singles
    px = rng.uniform(0.0, side, nb)
    pz = rng.uniform(0.0, side, nb)
    py = _height(px, pz, phase) - 0.01
    h = rng.uniform(*BLADE_HEIGHT, nb)
    w = rng.uniform(*BLADE_WIDTH, nb)
    heading = rng.uniform(0.0, np.pi, nb)
    lean = rng.uniform(0.0, 0.3, nb) * h
    sx, sz = np.cos(heading), np.sin(heading)
    # Lean out of the blade's plane so the strip is visibly bent.
    lx, lz = -sz * lean, sx * lean
    frac = np.array([0.0, 0.0, 0.55, 0.55, 1.0])
    half = np.array([-0.5, 0.5, -0.35, 0.35, 0.0])
    bend = frac ** 2
    bx = px[:, None] + half[None] * w[:, None] * sx[:, None] + bend[None] * lx[:, None]
    bz = pz[:, None] + half[None] * w[:, None] * sz[:, None] + bend[None] * lz[:, None]
    by = py[:, None] + frac[None] * h[:, None]
    bv = np.stack([bx, by, bz], axis=2).reshape(-1, 3)
    base = len(tv) + 5 * np.arange(nb)[:, None]
    strip = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4]])
    bf = (base[:blades, None, :] + strip[None]).reshape(-1, 3)
    # A one-triangle blade: base left, base right, tip.
    sf = base[blades:] + np.array([[0, 1, 4]])
    faces = np.concatenate([tf, bf, sf]).astype(np.int64)
    verts = np.concatenate([tv, bv])
    patches = int(np.ceil(side / PATCH))
    patch = (np.minimum(px // PATCH, patches - 1) * patches
             + np.minimum(pz // PATCH, patches - 1)).astype(np.int64) + 1
    obj = np.concatenate([np.zeros(len(tf), dtype=np.int64), np.repeat(patch[:blades], 3),
                          patch[blades:]])
    blade_rgb = vary(GREEN, rng, nb, 0.18)
    rgb = np.concatenate([t_rgb, np.repeat(blade_rgb[:blades], 3, axis=0), blade_rgb[blades:]])
    # Walk tiles at their highest ground, so eye heights clear every hill.
    nt = int(round(side / TILE))
    rects = []
    for i in range(nt):
        for k in range(nt):
            xs = np.linspace(i * TILE, (i + 1) * TILE, 9)
            zs = np.linspace(k * TILE, (k + 1) * TILE, 9)
            xx, zz = np.meshgrid(xs, zs)
            top = float(_height(xx, zz, phase).max())
            rects.append([i * TILE, k * TILE, (i + 1) * TILE, (k + 1) * TILE, top])
    vfrac = np.concatenate([np.zeros(len(tv)), np.tile(frac, nb)])
    vblade = np.concatenate([np.full(len(tv), -1), np.repeat(np.arange(nb), 5)])
    meta = {"blades": int(nb), "field_side_m": float(side), "terrain_cells": int(g),
            "terrain_triangles": int(len(tf)), "blade_triangles": int(len(bf) + len(sf)),
            # The walker wades through the meadow: triangles from this id on (the blades) stand
            # in the walk area by design; the terrain before them leaves it open.
            "walk_through_from": int(len(tf))}
    return (verts, faces, obj, to_rgb(rgb), np.array(rects), np.stack([px, py, pz], axis=1),
            vfrac, vblade, h, meta)


def generate(triangles: int | None = None, seed: int = 0) -> Scene:
    """A static meadow of exactly ``triangles`` triangles (default 200,000).

    Raises ValueError for budgets outside the generators' range or a negative seed.
    """
    triangles, seed = check_request(DEFAULT_TRIANGLES if triangles is None else triangles, seed)
    verts, faces, obj, rgb, rects, _, _, _, _, meta = _build(triangles, seed)
    scene = Scene(vertices=verts, faces=faces, object_ids=obj, colors=rgb, name="grass",
                  walk=WalkArea(rects=rects, eye_height=1.7, eye_range=(1.5, 1.9)))
    scene.meta.update({"generator": "grass", "seed": seed, "requested_triangles": triangles,
                       "is_2_5d": False, **meta})
    return scene


def generate_swaying(triangles: int | None = None, seed: int = 0, states: int = 10,
                     dt: float = 0.1, gust: float = 0.35) -> Scene:
    """The meadow of ``generate`` animated by ``states`` keyframes ``dt`` seconds apart.

    A wind gust travels across the field along +X; each blade vertex is displaced horizontally by
    ``gust * blade height * (height fraction)^2`` times a travelling wave (tips move most, bases
    not at all). The terrain does not move. Vertices move linearly between keyframes.
    """
    triangles, seed = check_request(DEFAULT_TRIANGLES if triangles is None else triangles, seed)
    if isinstance(states, bool) or not isinstance(states, (int, np.integer)) or not (
            2 <= int(states) <= 1000):
        raise ValueError(f"states must be an integer in [2, 1000], got {states!r}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    if not (np.isfinite(gust) and 0 <= gust <= 2):
        raise ValueError(f"gust must be in [0, 2], got {gust!r}")
    verts, faces, obj, rgb, rects, base, vfrac, vblade, h, meta = _build(triangles, seed)
    rng = np.random.default_rng(seed + 1)
    nb = len(base)
    wind = np.array([1.0, 0.0, 0.25]) / np.linalg.norm([1.0, 0.0, 0.25])
    blade_phase = rng.uniform(0, 2 * np.pi, nb)
    k = int(states)
    times = np.arange(k) * float(dt)
    moving = vblade >= 0
    bi = vblade[moving]
    amp = gust * h[bi] * vfrac[moving] ** 2
    out = np.repeat(verts[None], k, axis=0)
    span = meta["field_side_m"] + 8.0
    for s, t in enumerate(times):
        # A gentle per-blade sway plus a gust front crossing the field at GUST_SPEED.
        front = (GUST_SPEED * t) % span - 4.0
        wave = 0.6 * np.sin(2.0 * np.pi * 0.8 * t + blade_phase[bi]) + 0.8 * np.exp(
            -((base[bi, 0] - front) ** 2) / 8.0)
        disp = (amp * wave)[:, None] * wind[None]
        out[s, moving] = verts[moving] + disp
    scene = Scene(vertices=out[0], faces=faces, object_ids=obj, colors=rgb,
                  name="swaying_grass", states=out, state_times=times,
                  walk=WalkArea(rects=rects, eye_height=1.7, eye_range=(1.5, 1.9)))
    scene.meta.update({"generator": "swaying_grass", "seed": seed,
                       "requested_triangles": triangles, "is_2_5d": False, "states": k,
                       "dt": float(dt), "gust": float(gust), **meta})
    return scene
