"""Compile the numba kernels into their on-disk cache (``NUMBA_CACHE_DIR``) ahead of use.

Every kernel is compiled at its first call in a process and cached; a fresh machine (a CI run, a
new Docker image) pays that on its first cells instead of once. ``warm_up`` runs each core on
the inputs that reach its kernels (a small static city, rooms of ``BIG_TRIANGLES``, spheres,
a keyframed scene; ``Core.warm_params``) and the ground truth's rasterizer, split over a few
processes, since numba compiles on one thread. A kernel specialization no warm-up input reaches
(other array types, a path only large scenes take) compiles at its first real use instead.

A process still loads each kernel from that cache at its first call, a second or two per core
with the GIL taken in long slices: ``load_kernels`` does it
ahead of use in a serving process (``server.app``), so no walker waits on it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import numpy as np

log = logging.getLogger(__name__)

#: The built-in work split in two groups of about equal compile time, one process each:
#: cores by name, ``ground_truth`` (the sampled reference), ``rays`` (the float64 caster) and
#: ``topology`` (closed parts, self-crossing ones included: no small scene below has one).
GROUPS: tuple[tuple[str, ...], ...] = (
    ("cos", "dual_ray", "rays", "topology"),
    ("from_segment", "trim_regions", "sampling", "ground_truth"),
)


def groups() -> list[tuple[str, ...]]:
    """``GROUPS`` plus every other registered core (a plugin's), added to the first group."""
    from visibility.cores.base import available_cores

    known = {name for g in GROUPS for name in g}
    extra = tuple(n for n in available_cores() if n not in known)
    return [GROUPS[0] + extra, *GROUPS[1:]]


#: Triangles of the warm-up's large scene: at least ``raster.hierarchy.MIN_TRIANGLES``, from
#: which scenes take other kernels (the scene hierarchy, parallel rasterization).
BIG_TRIANGLES = 60_000


def _scenes(dynamic: bool = True) -> list[tuple]:
    """(scene, cell box) pairs reaching every kernel path: small static triangles, a large
    scene (its hierarchy and walk-area detection run here, ``_warm_large``; a cell with
    furniture on its floor), then (``dynamic``) spheres and keyframed motion."""
    from visibility.generators import make_scene
    from visibility.ground_truth import cell_around

    city = make_scene("city", triangles=2000)
    # Rooms: furniture and walls beside the cell, so a walk of its open floor meets them.
    big = make_scene("rooms", triangles=BIG_TRIANGLES)
    _warm_large(big)
    out = [(city, cell_around(city, 0.3, 0)), (big, cell_around(big, 1.0, 0))]
    if dynamic:
        for kind in ("spheres", "swaying_grass"):
            scene = make_scene(kind, triangles=1000)
            out.append((scene, cell_around(scene, 0.3, 0)))
    return out


def _warm_large(scene) -> None:
    """What a large scene reaches before any core runs: its hierarchy (built in the
    background when a server loads it) and the grid of a scene with no walk area of its own
    (a loaded file: the walk area is detected)."""
    from visibility.raster.hierarchy import scene_hierarchy
    from visibility.scene import Scene
    from visibility.viewcells import ViewcellGrid

    scene_hierarchy(scene)
    ViewcellGrid.for_scene(Scene(scene.vertices, scene.faces))


#: Cores whose kernels this process has loaded (``load_kernels``).
_loaded: set[str] = set()
_loading = threading.Lock()


def load_kernels(names: Iterable[str]) -> dict[str, Exception]:
    """Load the named cores' kernels into this process (from the numba cache, compiling what
    it lacks) by running each once on the static warm-up scenes (``_scenes``, made once per
    call; moving scenes' kernels load at their first use); names this process loaded before
    are skipped. Returns the names that failed, with their error: their kernels load at their
    first use instead."""
    with _loading:
        todo = tuple(dict.fromkeys(n for n in names if n not in _loaded))
        if not todo:
            return {}
        scenes = _scenes(dynamic=False)
        failed: dict[str, Exception] = {}
        for name in todo:
            try:
                _warm((name,), scenes)
            except Exception as exc:  # noqa: BLE001 - reported to the caller, never fatal
                failed[name] = exc
                continue
            _loaded.add(name)
        return failed


def _warm(names: tuple[str, ...], scenes: list | None = None) -> float:
    """Run the named cores (and ``ground_truth``, ``rays``) once per (scene, box) of
    ``scenes`` (default ``_scenes()``); seconds."""
    from visibility.cores.base import get_core
    from visibility.ground_truth import sample_pvs
    from visibility.viewcells import Viewcell

    t0 = time.perf_counter()
    frames_warm = False
    for scene, box in _scenes() if scenes is None else scenes:
        for name in names:
            if name == "ground_truth":
                sample_pvs(scene, Viewcell(box), n_points=2, resolution=16)
            elif name == "rays":
                from visibility.ray_reference import exact_first_hits

                tri = np.asarray(scene.vertices[scene.faces[:4]], dtype=np.float64)
                ids = np.full(1, -1, dtype=np.int64)
                exact_first_hits(tri, tri.min(axis=1), tri.max(axis=1), np.zeros((1, 3)),
                                 np.ones((1, 3)), np.zeros(1), ids, np.zeros(1))
                from visibility.exact_grid import build_grid, grid_first_hits

                grid = build_grid(tri.min(axis=1), tri.max(axis=1))
                grid_first_hits(tri, grid, np.zeros((1, 3)), np.ones((1, 3)), np.zeros(1), ids,
                                np.zeros(1))
                from visibility.ray_frames import cube_directions

                cube_directions(np.eye(3), 2, np.random.default_rng(0))
                if not scene.is_dynamic and not frames_warm:
                    # Its glue kernels' types do not depend on the scene: once will do.
                    frames_warm = _warm_ray_frames(scene, box)
            elif name == "topology":
                continue  # once, below: it needs no scene
            else:
                core = get_core(name)
                # The kernels' types do not depend on the values: the cheapest level will do.
                knob = {core.knob: min(core.knob_levels)} if core.knob else {}
                for extra in ({}, *core.warm_params):
                    try:
                        core.compute(scene, Viewcell(box), core.make_params(**knob, **extra))
                    except (ValueError, NotImplementedError) as e:
                        # A core that refuses an input (dual_ray and interiors) compiled what
                        # it met.
                        log.debug("%s refused %s: %s", name, scene.name, e)
    if "topology" in names:
        _warm_topology()
    return time.perf_counter() - t0


def _warm_ray_frames(scene, box: np.ndarray) -> bool:
    """The Embree reference's glue kernels (``ray_frames``, ``ray_reference``), where embreex
    is installed (the ``bench`` extra; without it nothing uses them). True: nothing left to
    compile."""
    try:
        import embreex  # noqa: F401
    except ImportError:
        return True
    from visibility.ray_frames import missed_pixels, ray_frames
    from visibility.ray_reference import ray_reference

    frames = ray_frames(scene, box, n_eyes=1, resolution=2)
    missed_pixels(scene, frames, np.zeros(0, dtype=np.int64))
    ray_reference(scene, box, n_eyes=1, n_dirs=4)
    return True


def _warm_topology() -> None:
    """Closed parts of a cube with a corner pulled through it (it passes through itself, so
    the crossing sweep and the winding counts run too)."""
    import trimesh

    from visibility.scene import Scene
    from visibility.topology import build_closed_parts

    cube = trimesh.creation.box()
    v = np.array(cube.vertices, dtype=np.float64)
    v[np.argmax(v.sum(axis=1))] = (-1.5, -1.5, -1.5)
    parts = build_closed_parts(Scene(v, np.asarray(cube.faces)))
    if not len(parts.wound):
        log.warning("warm-up: the cube with a corner pulled through counted no winding")


def warm_up(processes: int = 2) -> dict[str, float]:
    """Compile every core's kernels into the numba cache; seconds per group of cores.

    Returns {"cos+dual_ray": s, ...}; run once after install
    (``pvs warmup``)."""
    ctx = get_context("spawn")
    with ProcessPoolExecutor(max(1, processes), mp_context=ctx) as pool:
        futures = {"+".join(g): pool.submit(_warm, g) for g in groups()}
        return {k: f.result() for k, f in futures.items()}
