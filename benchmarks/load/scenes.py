"""The scene a load run serves, loaded here exactly as the server loads it, and the walkers'
walkthroughs over it.

A scene is named as the server names it: a file of the scenes folder (by stem) or a generator
(sized by ``--triangles``). The folder follows ``pvs serve``'s rule (``pvs_cli.serve_settings``:
``--scenes``, else ``PVS_SCENES_DIR``, else ``../shared/scenes`` when present) and the scene is
loaded through the server's own catalogue (``server.catalog.SceneCatalog``), so file units are
scaled by the sidecar's ``"scale"`` (lavaducts is in Quake units), hints apply, and the grid is
the one the server builds (``check_served`` compares it with the running server's).

Walks (``plan_walks``) are ``client.walkthrough.generate_walkthrough`` random walks over the grid;
a walk with a pose off the ground (``benchmarks.load.ground``: inside a building, in no cell, or
the eye too high or low over the ground) is drawn again with another seed.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from benchmarks.load.ground import ground_check
from client.walkthrough import Walkthrough, generate_walkthrough
from server.catalog import LoadedScene, SceneCatalog, UnknownSceneError
from server.settings import Settings
from visibility.generators import available_generators

#: Seed offset between a walker's successive draws (larger than any walker count, so no two
#: walkers of a run share a seed).
WALK_SEED_STRIDE = 1_000_003
#: Size of a generated scene when ``--triangles`` is not given.
DEFAULT_TRIANGLES = 20_000
#: Most draws per walker before its walk is kept off the ground (and counted so).
MAX_WALK_DRAWS = 50


@dataclass
class BenchScene:
    """The scene of a load run as the server serves it.

    Attributes
    ----------
    name : the catalogue name the walkers ask for.
    kind : "file" or "generated".
    loaded : the scene and its viewcell grid (``server.catalog.LoadedScene``).
    scenes_dir : the scenes folder the server is given (None: none).
    generated : ``PVS_GENERATED`` for the server ({name: triangles} or {}).
    env : the ``PVS_*`` environment the server starts with (cell size, generated scene).
    """

    name: str
    kind: str
    loaded: LoadedScene
    scenes_dir: Path | None
    generated: dict[str, int] = field(default_factory=dict)
    env: dict[str, str] = field(default_factory=dict)

    @property
    def triangles(self) -> int:
        """Triangles of the scene (rows of its face array)."""
        return int(self.loaded.scene.n_triangles)

    @property
    def cells(self) -> int:
        """Viewcells of its grid."""
        return len(self.loaded.grid)

    @property
    def cell_size(self) -> float:
        """Side of its viewcells, metres."""
        return float(self.loaded.grid.cell_size)

    def describe(self) -> dict:
        """JSON-friendly: name, kind, source (file name or generator), triangles, cells."""
        return {"scene": self.name, "scene_kind": self.kind,
                "scene_source": self.loaded.info.get("source"), "triangles": self.triangles,
                "cells": self.cells, "cell_size": self.cell_size}


def load_bench_scene(name: str, triangles: int | None, scenes: str | None,
                     cell_size: float | None, workers: int = 2) -> BenchScene:
    """Load scene ``name`` as ``pvs serve`` would serve it: a file of the scenes folder, else a
    generator sized ``triangles`` (default ``DEFAULT_TRIANGLES``). SystemExit naming what is
    served when it is neither, or when ``triangles`` is given for a file scene."""
    from pvs_cli import serve_settings

    is_generator = name in available_generators()
    size = DEFAULT_TRIANGLES if triangles is None else int(triangles)
    env = {k: v for k, v in os.environ.items() if k.startswith("PVS_")}
    if is_generator:
        env["PVS_GENERATED"] = f"{name}={size}"
    else:
        env["PVS_GENERATED"] = ""
    if cell_size is not None:
        env["PVS_CELL_SIZE"] = repr(float(cell_size))
    ns = argparse.Namespace(host="127.0.0.1", port=0, core=None, cell_size=None,
                            workers=workers, scenes=scenes)
    try:
        settings: Settings = serve_settings(ns, env)
    except ValueError as exc:
        raise SystemExit(f"bench_load: {exc}") from None
    catalog = SceneCatalog(settings)
    try:
        loaded = catalog.get(name)
    except UnknownSceneError:
        raise SystemExit(
            f"bench_load: no scene {name!r}: not a generator ({', '.join(available_generators())}"
            f") nor a file of the scenes folder {settings.scenes_dir} "
            f"({', '.join(n for n in catalog.names() if n != name) or 'none'})") from None
    if loaded.kind == "file" and triangles is not None:
        raise SystemExit(f"bench_load: --triangles sizes a generated scene; {name!r} is a file "
                         f"of {settings.scenes_dir}")
    return BenchScene(name, loaded.kind, loaded, settings.scenes_dir, dict(settings.generated),
                      env)


def check_served(url: str, bs: BenchScene, timeout: float = 900.0) -> None:
    """Have the server at ``url`` load the scene (``GET /scenes/{name}``: a file scene's parse
    and walk-area detection happen before the walkers come, not in their first cell) and check
    that its grid is ours; RuntimeError when it is not."""
    r = httpx.get(f"{url}/scenes/{bs.name}", timeout=timeout)
    r.raise_for_status()
    info = r.json()
    grid = info.get("grid", {})
    ours = bs.loaded.grid.to_dict()
    if (info.get("triangles"), grid.get("cells"), grid.get("cell_size")) != (
            bs.triangles, ours["cells"], ours["cell_size"]):
        raise RuntimeError(
            f"the server's {bs.name!r} ({info.get('triangles')} triangles, {grid.get('cells')} "
            f"cells of {grid.get('cell_size')} m) is not the benchmark's ({bs.triangles} "
            f"triangles, {ours['cells']} cells of {ours['cell_size']} m)")


@dataclass
class WalkPlan:
    """Every walker's walkthrough, drawn once: walker i walks ``walks[i]`` in every run.

    ``draws`` : how many walks were drawn per walker (1: the first was on the ground);
    ``ground`` : ``ground_check`` of each kept walk (without its per-pose array).
    """

    walks: list[Walkthrough]
    draws: list[int]
    ground: list[dict]

    def summary(self, n: int) -> dict:
        """The first ``n`` walkers' walks: poses, redrawn walks, poses still off the ground,
        inside a solid, and the eye height's range over the ground, metres."""
        g = self.ground[:n]
        lo = [x["eye_height_min_m"] for x in g if x["eye_height_min_m"] is not None]
        hi = [x["eye_height_max_m"] for x in g if x["eye_height_max_m"] is not None]
        return {"poses": sum(x["poses"] for x in g),
                "walks_redrawn": sum(1 for d in self.draws[:n] if d > 1),
                "draws": sum(self.draws[:n]),
                "poses_off_ground": sum(x["off_ground"] for x in g),
                "poses_inside": sum(x["inside"] for x in g),
                "poses_no_surface_below": sum(x["no_surface_below"] for x in g),
                "eye_height_min_m": min(lo) if lo else None,
                "eye_height_max_m": max(hi) if hi else None}

    def cells(self, n: int) -> set[int]:
        """The cells the first ``n`` walkers' poses fall in."""
        grid_cells: set[int] = set()
        for w in self.walks[:n]:
            grid_cells.update(int(c) for c in w.meta.get("cells", []) if c is not None)
        return grid_cells


def plan_walks(bs: BenchScene, walkers: int, duration: float, speed: float, fps: float,
               seed: int) -> WalkPlan:
    """``walkers`` walks on ``bs``: walker i first draws seed ``seed + i``, then
    ``+ WALK_SEED_STRIDE`` per draw, until a walk has every pose on the ground (at most
    ``MAX_WALK_DRAWS``; then the walk with the fewest poses off the ground is kept, and the
    summary counts them). Each walk's ``meta["cells"]`` holds its poses' cells."""
    grid, scene = bs.loaded.grid, bs.loaded.scene
    walks, draws, ground = [], [], []
    for i in range(walkers):
        best = None
        for k in range(MAX_WALK_DRAWS):
            w = generate_walkthrough(grid, duration=duration, speed=speed, fps=fps,
                                     seed=seed + i + k * WALK_SEED_STRIDE)
            g = ground_check(scene, grid, w.positions)
            g.pop("ok")
            if best is None or g["off_ground"] < best[1]["off_ground"]:
                best = (w, g, k + 1)
            if g["off_ground"] == 0:
                break
        w, g, _ = best
        w.meta["cells"] = [grid.cell_of(p) for p in w.positions]
        walks.append(w)
        draws.append(k + 1)
        ground.append(g)
    return WalkPlan(walks, draws, ground)


def warm_cells(bs: BenchScene, plan: WalkPlan, walkers: int) -> list[int]:
    """The cells a warm server computes before its walkers come: every cell the first
    ``walkers`` walks pass through and their neighbours (the server prefetches neighbours), or
    every cell of the grid when that is no more."""
    grid = bs.loaded.grid
    cells = plan.cells(walkers)
    around = set(cells)
    for c in cells:
        around.update(grid.neighbours(c))
    if len(around) >= len(grid):
        return list(range(len(grid)))
    return sorted(around)


def walk_velocities(w: Walkthrough) -> np.ndarray:
    """(n, 3) velocity of each pose, m/s (central differences; zeros for a single pose)."""
    if len(w.t) > 1:
        return np.gradient(w.positions, w.t, axis=0)
    return np.zeros_like(w.positions)
