"""Bouncing spheres: thousands of balls dropped onto a ground plane, keyframed over many states.

After the paper's *Bouncing Spheres* (Popescu et al. 2024, Fig. 3): every sphere falls from its own
height, bounces with its own restitution and comes to rest on the ground by the last state. Each
sphere owns one column of a square grid (column side > its diameter) and only moves vertically, so
spheres never intersect. Spheres are first-class primitives (``Scene.sphere_centers`` (k, s, 3),
``sphere_radii``); the ground is a small triangle grid. The walk area is the whole field.
"""

from __future__ import annotations

import numpy as np

from visibility.generators._mesh import check_request, grid_xz, to_rgb, vary
from visibility.scene import Scene, WalkArea

DEFAULT_SPHERES = 2_000
DEFAULT_STATES = 25
RADIUS = (0.2, 0.5)
DROP_HEIGHT = (0.5, 8.0)
RESTITUTION = (0.45, 0.7)
GRAVITY = 9.81
#: Gap between neighbouring columns, metres.
GAP = 0.4
#: Share of the grid columns that hold a sphere.
FILL = 0.55
GROUND_RGB = np.array([120.0, 120.0, 110.0])


def _bounce(h0: np.ndarray, e: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(len(times), s) height of the lowest point above the ground for balls dropped at rest from
    h0 (metres) with restitution e, at the given times (seconds); exact piecewise parabolas."""
    out = np.zeros((len(times), len(h0)))
    v = np.sqrt(2.0 * GRAVITY * h0)  # speed at the first impact
    t_hit = np.sqrt(2.0 * h0 / GRAVITY)
    for k, t in enumerate(times):
        falling = t < t_hit
        y = np.where(falling, h0 - 0.5 * GRAVITY * t * t, 0.0)
        # After the first impact: flights of duration 2 v_n / g with v_n = e^n v.
        tau = t - t_hit
        vn = v * e
        left = np.where(falling, 0.0, tau)
        for _ in range(60):
            flight = 2.0 * vn / GRAVITY
            inside = (left < flight) & (left >= 0) & ~falling
            y = np.where(inside, vn * left - 0.5 * GRAVITY * left * left, y)
            left = np.where(inside | falling, -1.0, left - flight)
            vn = vn * e
        out[k] = np.maximum(y, 0.0)
    return out


def generate(triangles: int | None = None, seed: int = 0, spheres: int | None = None,
             states: int = DEFAULT_STATES) -> Scene:
    """``spheres`` bouncing spheres (default: ``triangles`` when given, else 2,000) over
    ``states`` keyframes; the ground adds a few hundred triangles.

    ``triangles`` is what the generator registry passes as this scene's size, so it is taken as
    the sphere count. Raises ValueError for counts outside [1, 10^6], states outside [1, 1000]
    or a negative seed.
    """
    count = spheres if spheres is not None else (
        DEFAULT_SPHERES if triangles is None else triangles)
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not (
            1 <= int(count) <= 1_000_000):
        raise ValueError(f"spheres must be an integer in [1, 1000000], got {count!r}")
    if isinstance(states, bool) or not isinstance(states, (int, np.integer)) or not (
            1 <= int(states) <= 1000):
        raise ValueError(f"states must be an integer in [1, 1000], got {states!r}")
    _, seed = check_request(1000, seed)
    n = int(count)
    k = int(states)
    rng = np.random.default_rng(seed)
    pitch = 2.0 * RADIUS[1] + GAP
    cols = int(np.ceil(np.sqrt(n / FILL)))
    side = cols * pitch
    cells = rng.choice(cols * cols, size=n, replace=False)
    ci, ck = np.divmod(cells, cols)
    r = rng.uniform(*RADIUS, n)
    slack = 0.5 * pitch - r
    cx = (ci + 0.5) * pitch + rng.uniform(-1, 1, n) * slack
    cz = (ck + 0.5) * pitch + rng.uniform(-1, 1, n) * slack
    h0 = rng.uniform(*DROP_HEIGHT, n)
    e = rng.uniform(*RESTITUTION, n)
    # Long enough for the slowest ball to settle (geometric series of flight times, 1 mm).
    settle = np.sqrt(2.0 * h0 / GRAVITY) * (1.0 + 2.0 * e / (1.0 - e))
    times = np.linspace(0.0, float(settle.max()) * 1.05, k) if k > 1 else np.zeros(1)
    lift = _bounce(h0, e, times)
    centers = np.empty((k, n, 3))
    centers[:, :, 0] = cx
    centers[:, :, 2] = cz
    centers[:, :, 1] = r[None] + lift
    if k > 1:
        centers[-1, :, 1] = r  # at rest on the ground
    # Ground: a 16 x 16 grid of cells, slightly larger than the field.
    edges = np.linspace(-2.0, side + 2.0, 17)
    gv, gf, _, _ = grid_xz(edges, edges, 0.0)
    colors = to_rgb(vary(GROUND_RGB, rng, len(gf), 0.06))
    sphere_rgb = to_rgb(rng.uniform(40, 255, (n, 3)))
    scene = Scene(vertices=gv, faces=gf, colors=colors, name="spheres",
                  sphere_centers=centers, sphere_radii=r, sphere_colors=sphere_rgb,
                  walk=WalkArea(rects=np.array([[0.0, 0.0, side, side, 0.0]]), eye_height=1.7,
                                eye_range=(1.5, 1.9)))
    scene.meta.update({"generator": "spheres", "seed": seed, "spheres": n, "states": k,
                       "sphere_times": times.tolist(), "field_side_m": float(side),
                       "is_2_5d": False})
    return scene
