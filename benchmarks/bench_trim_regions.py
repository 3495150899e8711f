"""The trim region core against its paper (Voglreiter et al. 2023): time per phase (Fig. 13),
k-buffer memory and trim-sequence length (Table 2), false-negative pixels and primitive rates
(Fig. 16, Table 3), PVS size and tightness (Fig. 15), and side by side with ``cos`` and
``sampling`` on equal small cells, every error judged by independent rays
(``visibility.ray_frames``).

- Speed: the 100k ``village`` and the 1M ``kitchen`` at the default resolution, one sphere of
  Δ in {0.05, 0.1, 0.2, 0.3} m and the default ``max_delta`` (0.41 m) at a walkable cell's
  centre: best of 2 runs after a warm-up (the per-scene octree is built once and reported
  apart), seconds per phase P0-P4.
- Quality: generated scenes (20k rooms, village, city) and the real ones of ../shared/scenes,
  two cells each at every Δ, at the defaults (the method alone) and with the sampling add-on
  (``gather_eyes=8``) and with ``small="centres"`` (the paper's pixel centres): frames from
  ``--frames`` eyes with random cube orientations inside the sphere's cube cell, 256 px per face
  (``trim_regions.quality``).
- Box cells: 1 m and 4 m cells of the 100k city and a 1 m cell of lavaducts, as cubes and as
  the server's cells (the grid's eye range high), at the defaults (many spheres each) and the
  cubes covered by fewer, larger spheres, scored by ray frames.
- Leaf size: ``max_prims`` (most triangles per octree leaf) 256, 1024 and 4096 on a 0.2 m
  sphere of the village, Lyon and the kitchen: layers peeled, time per phase and the PVS, to
  see whether larger leaves (fewer layers, as the paper's 6-14) pay.
- Side by side: ``cos`` and ``sampling`` at their defaults on the same cube cells of the 20k
  scenes and lavaducts, and how much of trim_regions' answer is provably unseen: triangles
  ``cos`` (conservative)
  leaves out of the PVS of the box holding every sphere trim_regions answers for, so no eye of
  those spheres sees them; all three also against the frames' ground truth grown by rays
  aimed at every triangle of their answers (``--side-aim-most``).

Writes ``benchmarks/results/trim_regions.md`` (+ ``.json``, ``.png``). Usage:
``python -m benchmarks.bench_trim_regions`` (about 20 minutes on 2 cores), ``--quick`` for a
smoke run into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("MPLBACKEND", "Agg")


import numpy as np

from benchmarks.bench_matrix import SHARED_SCENES
from benchmarks.common import aimed_total
from visibility.cores.base import get_core
from visibility.cores.trim_regions.core import DEFAULT_MAX_DELTA
from visibility.cores.trim_regions.frustum import cover_box
from visibility.cores.trim_regions.pipeline import GATHER_EYES, PHASES
from visibility.cores.trim_regions.quality import FRAME_NEAR, frame_errors
from visibility.cores.trim_regions.warm import WARM
from visibility.generators import make_scene
from visibility.ray_aimed import aimed_seen
from visibility.ray_frames import first_open_cell, ray_frames, seen_ids
from visibility.scene import Scene
from visibility.viewcells import Viewcell, ViewcellGrid

ROOT = Path(__file__).resolve().parents[1]

RESULTS = ROOT / "benchmarks" / "results"
DELTAS = (0.05, 0.1, 0.2, 0.3, DEFAULT_MAX_DELTA)
#: The speed table's sphere radii: ``DELTAS`` and the issue's 0.3 m cube (its circumscribed
#: sphere, Δ = 0.15 √3 m), the aim's cell on the kitchen.
SPEED_DELTAS = tuple(sorted(DELTAS + (round(0.15 * 3 ** 0.5, 3),)))
#: The paper's frame times on an RTX 4090 (Sec. 6.2, Fig. 13): 16-22 ms.
PAPER_MS = (16.0, 22.0)


def load(name: str, triangles: int | None = None) -> Scene:
    """A generated scene (``triangles``) or a real one from ../shared/scenes."""
    if triangles:
        return make_scene(name, triangles=triangles)
    from visibility.loaders import load_scene

    return load_scene(SHARED_SCENES / f"{name}.glb")


def sphere_cell(scene: Scene, delta: float, which: int) -> np.ndarray:
    """(2, 3) the cube whose circumscribed sphere has radius ``delta`` around the centre of a
    grid cell of the scene (``which``: 0 the middle one, 1 one a third in; each the first
    from there whose centre stands in open space, ``ray_frames.first_open_cell``)."""
    grid = ViewcellGrid.for_scene(scene)
    c = grid.cell(first_open_cell(scene, grid, len(grid) // 2 if which == 0
                                  else len(grid) // 3)).center
    h = delta / np.sqrt(3.0)
    return np.stack([c - h, c + h])


def timed(core: Any, scene: Scene, box: np.ndarray,
          **params: Any) -> tuple[Any, Any, float]:
    """(best of 2 runs, the first run that built the octree and compiled, cold seconds).
    The 2 runs follow one another at once, as a walker's cells do, so they find the per-view
    buffers warm (``trim_regions.warm``); the cold seconds time one run after they were
    released."""
    p = core.make_params(**params)
    first = core.compute(scene, Viewcell(box), p)
    runs = [core.compute(scene, Viewcell(box), p) for _ in range(2)]
    WARM.release()
    cold = core.compute(scene, Viewcell(box), p).seconds
    return min(runs, key=lambda r: r.seconds), first, cold


def speed(quick: bool) -> list[dict[str, Any]]:
    core = get_core("trim_regions")
    sampling = get_core("sampling")
    rows = []
    cases = [("village", 20_000 if quick else 100_000)] + ([] if quick else [("kitchen", None)])
    for name, n in cases:
        scene = load(name, n)
        for delta in SPEED_DELTAS:
            box = sphere_cell(scene, delta, 0)
            pvs, first, cold = timed(core, scene, box, max_delta=delta)
            # ``sampling`` at its defaults on the same cube, for scale (best of 2 likewise).
            beside, _, _ = timed(sampling, scene, box)
            st = pvs.stats
            rows.append({"scene": name, "triangles": scene.n_triangles, "delta": delta,
                         "seconds": pvs.seconds, "cold_seconds": cold,
                         "sampling_seconds": beside.seconds, "sampling_pvs": len(beside),
                         **{k: st[k] for k in PHASES},
                         "layers": st["layers"], "pvs": len(pvs),
                         "octree_leaves": st["octree_leaves"],
                         "octree_build_seconds": _build_seconds(core, scene),
                         "active_pixels": st["active_pixels"],
                         "mean_sequence_length": st["mean_sequence_length"],
                         "kbuffer_allocated_mb": st["kbuffer_allocated_bytes"] / 2**20,
                         "kbuffer_used_mb": st["kbuffer_used_bytes"] / 2**20,
                         "overflow_pixels": st["overflow_pixels"],
                         "deterministic": bool(np.array_equal(first.triangle_ids,
                                                              pvs.triangle_ids))})
            print(f"speed {name} Δ={delta}: {pvs.seconds:.2f} s", flush=True)
    return rows


#: Box cells the cell table times (scene, generated triangles or None for a real scene, metres
#: on a side): the issue's 1 m aim and the server's 4 m cells on the 100k city, each covered by
#: many spheres at the defaults, and a 1 m cell of lavaducts, where larger spheres miss more.
CELL_CASES = (("city", 100_000, (1.0, 4.0)), ("lavaducts", None, (1.0,)))
#: Spheres per axis the cell table tries beside the default cover (``max_delta``): 2 (eight
#: spheres) and 1 (one sphere around the whole box).
CELL_SPLITS = (2, 1)


def box_cells(quick: bool, frames: int) -> list[dict[str, Any]]:
    """Seconds per phase, spheres, views, PVS and false-negative pixels of box cells
    (``CELL_CASES``: the grid's middle cell in open space) at the defaults and covered by
    fewer, larger spheres (``CELL_SPLITS``), one run after a warm-up each, scored on the same
    ray frames (eyes in the box, ``ray_frames``)."""
    if quick:
        return []
    core = get_core("trim_regions")
    rows = []
    for name, tri, sides in CELL_CASES:
        rows += _box_cells(core, name, load(name, tri), sides, frames)
    return rows


def _box_cells(core: Any, name: str, scene: Scene, sides: tuple[float, ...],
               frames: int) -> list[dict[str, Any]]:
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(first_open_cell(scene, grid, len(grid) // 2))
    c = cell.center
    # The server's cells of that side: the side across the ground, the grid's eye range high.
    eye_range = float(cell.box[1][1] - cell.box[0][1])
    rows = []
    for side in sides:
        for shape, height in (("cube", side), ("cell", eye_range)):
            half = 0.5 * np.array([side, height, side])
            box = np.stack([c - half, c + half])
            cast = ray_frames(scene, box, frames, 256, seed=1, near=FRAME_NEAR)
            # The radius of n x n x n spheres covering the cube (nudged up against rounding).
            half_diag = 0.5 * float(np.linalg.norm(box[1] - box[0]))
            variants = [("default", {})] + ([] if shape == "cell" else [
                (f"{n ** 3} sphere" + ("s" if n > 1 else ""),
                 {"max_delta": half_diag / n * (1 + 1e-9)}) for n in CELL_SPLITS])
            for label, kw in variants:
                p = core.make_params(**kw)
                core.compute(scene, Viewcell(box), p)
                pvs = core.compute(scene, Viewcell(box), p)
                st = pvs.stats
                e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
                e.pop("missed")
                rows.append({"scene": name, "triangles": scene.n_triangles, "side": side,
                             "height": height, "shape": shape,
                             "cover": label, "seconds": pvs.seconds, "spheres": st["spheres"],
                             "views": st["views"], "delta": st["delta"], "pvs": len(pvs),
                             **{k: st[k] for k in PHASES}, "gt": e["gt"],
                             "fn_pixels_max": e["fn_pixels_max"],
                             "fn_pixel_rate_max": e["fn_pixel_rate_max"], "fn": e["fn"]})
                print(f"cell {name} {side} x {height:g} m, {label}: {pvs.seconds:.2f} s, "
                      f"{st['spheres']} sphere(s), FN px {e['fn_pixels_max']}", flush=True)
    return rows


#: Leaf sizes the leaf-size table compares (``max_prims``; 256 is the default).
LEAF_SIZES = (256, 1024, 4096)


def _cast(casts: dict, name: str, scene: Scene, box: np.ndarray, frames: int,
          keep: bool) -> Any:
    """The quality frames of ``box`` (``ray_frames``, seed 1), cast once: taken from
    ``casts`` when there, else cast, and kept there for a later table (``keep``) or handed
    over (the last user: frames of a large scene weigh tens of megabytes)."""
    key = (name, scene.n_triangles, np.asarray(box, float).tobytes(), frames)
    cast = casts.pop(key, None)
    if cast is None:
        cast = ray_frames(scene, box, frames, 256, seed=1, near=FRAME_NEAR)
    if keep:
        casts[key] = cast
    return cast


def leaf_sizes(quick: bool, frames: int, casts: dict | None = None) -> list[dict[str, Any]]:
    """Layers, seconds per phase, PVS and the worst frame's missed pixels at each of
    ``LEAF_SIZES`` on one 0.2 m sphere per scene (best of 2 after a warm-up that builds that
    octree), scored on the frames the quality table casts for that cell (``casts``, shared
    with ``quality``)."""
    casts = {} if casts is None else casts
    core = get_core("trim_regions")
    cases = [("village", 20_000 if quick else 100_000)] + (
        [] if quick else [("lyon_vilo3d", None), ("kitchen", None)])
    rows = []
    for name, n in cases:
        scene = load(name, n)
        box = sphere_cell(scene, 0.2, 0)
        cast = _cast(casts, name, scene, box, frames, keep=True)
        for mp in LEAF_SIZES:
            pvs, _, _ = timed(core, scene, box, max_delta=0.2, max_prims=mp)
            st = pvs.stats
            e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
            rows.append({"scene": name, "max_prims": mp, "seconds": pvs.seconds,
                         "layers": st["layers"], "pvs": len(pvs), "gt": e["gt"],
                         "fn_pixels_max": e["fn_pixels_max"],
                         **{k: st[k] for k in PHASES}})
            print(f"leaves {name} max_prims={mp}: {pvs.seconds:.2f} s, {st['layers']} layers, "
                  f"FN px {e['fn_pixels_max']}", flush=True)
    return rows


def _build_seconds(core: Any, scene: Scene) -> float:
    """The octree and edge build of ``scene`` timed alone (a fresh build)."""
    from visibility.cores.trim_regions.cache import build_scene_data

    return build_scene_data(scene).build_seconds


#: Rays aimed at each triangle of the answer the frames did not show (``aimed_ground_truth``):
#: in the first round, and at most in all.
AIM_RAYS = 16
AIM_MOST = 256
#: At most, on the side-by-side cells (a few thousand triangles each).
SIDE_AIM_MOST = 1024


def aimed_ground_truth(scene: Scene, box: np.ndarray, pvs_ids: np.ndarray, cast: Any,
                       most: int) -> dict[str, Any]:
    """The frames' ground truth grown by rays aimed at the answer's other triangles
    (``visibility.ray_aimed``, eyes in the cube, the frames' near plane): its size, the rays
    per triangle cast, what the last doubling added, and the triangles seen that the answer
    lacks (float64-confirmed)."""
    t0 = time.perf_counter()
    got = aimed_seen(scene, box, pvs_ids, known=seen_ids(cast), rays=min(AIM_RAYS, most),
                     most=most, seed=3, near=FRAME_NEAR)
    return {"gt_aimed": got.total, "aimed_rays": got.rays_per_candidate,
            "aimed_most": int(most), "aimed_added_last": got.added_last,
            "aimed_converged": bool(got.converged),
            "aimed_missed": int(len(np.setdiff1d(got.ids, pvs_ids))),
            "aimed_seconds": time.perf_counter() - t0}


def quality(quick: bool, frames: int, casts: dict | None = None,
            aim_most: int = AIM_MOST) -> list[dict[str, Any]]:
    """Each cell's frames cast once (``ray_frames``; those ``leaf_sizes`` cast are taken from
    ``casts``), scoring the core at its defaults and with the sampling add-on
    (``gather_eyes``: eyes of the cell sampled into the answer); the defaults' answer also
    against the frames' ground truth grown by aimed rays (``aimed_ground_truth``; 0: not)."""
    core = get_core("trim_regions")
    n = 5_000 if quick else 20_000
    cases: list[tuple[str, Any, tuple[float, ...]]] = [
        (g, n, (0.05, 0.2) if quick else DELTAS) for g in ("rooms", "village", "city")]
    if not quick:
        cases += [(r, None, DELTAS) for r in ("lavaducts", "lyon_vilo3d", "denhaag")]
        cases += [("kitchen", None, DELTAS)]
    rows = []
    for name, tri, deltas in cases:
        scene = load(name, tri)
        for which in (0, 1):
            for delta in deltas:
                box = sphere_cell(scene, delta, which)
                pvs = core.compute(scene, Viewcell(box), core.make_params(max_delta=delta))
                gathered = core.compute(scene, Viewcell(box),
                                     core.make_params(max_delta=delta, gather_eyes=GATHER_EYES))
                centres = core.compute(scene, Viewcell(box),
                                       core.make_params(max_delta=delta, small="centres"))
                cast = _cast({} if casts is None else casts, name, scene, box, frames,
                             keep=False)
                e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
                e0 = frame_errors(scene, gathered.triangle_ids, box, frames=cast)
                e1 = frame_errors(scene, centres.triangle_ids, box, frames=cast)
                e.pop("missed")
                aim = (aimed_ground_truth(scene, box, pvs.triangle_ids, cast, aim_most)
                       if aim_most > 0 else {})
                rows.append({**aim, "scene": name, "cell": which, "delta": delta,
                             "triangles": scene.n_triangles, "seconds": pvs.seconds,
                             "active_pixels": pvs.stats["active_pixels"],
                             "mean_sequence_length": pvs.stats["mean_sequence_length"],
                             "kbuffer_used_mb": pvs.stats["kbuffer_used_bytes"] / 2**20,
                             "overflow_pixels": pvs.stats["overflow_pixels"],
                             "dropped_eyes": cast.dropped, **e,
                             "gather_seconds": gathered.seconds, "gather_pvs": e0["pvs"],
                             "gather_fn_pixels_max": e0["fn_pixels_max"],
                             "gather_fn_pixel_rate_max": e0["fn_pixel_rate_max"],
                             "gather_fn": e0["fn"],
                             "centres_seconds": centres.seconds, "centres_pvs": e1["pvs"],
                             "centres_fn_pixels_max": e1["fn_pixels_max"],
                             "centres_fn_pixel_rate_max": e1["fn_pixel_rate_max"],
                             "centres_fn": e1["fn"]})
                print(f"quality {name} cell {which} Δ={delta}: FN px {e['fn_pixels_max']} "
                      f"(with the add-on {e0['fn_pixels_max']}, centres "
                      f"{e1['fn_pixels_max']}), PVS/GT "
                      f"{e['pvs'] / max(e['gt'], 1):.2f}"
                      + (f", with aimed rays {e['pvs'] / max(aim['gt_aimed'], 1):.2f}"
                         if aim else ""), flush=True)
    return rows


#: Random cubes per real scene (``random_cells``) and the frames each is judged on.
RANDOM_CELLS = {"lavaducts": 30, "denhaag": 20, "lyon_vilo3d": 20, "kitchen": 10}
RANDOM_FRAMES = 8


def random_open_cubes(scene: Scene, n: int, frames: int = RANDOM_FRAMES, seed: int = 0,
                      delta: float = DEFAULT_MAX_DELTA) -> list[tuple[np.ndarray, Any]]:
    """``n`` cubes whose circumscribed sphere is ``delta`` metres (box (2, 3) [min, max]) at
    seeded random places of the scene's grid cells, each with its ``frames`` ray frames (seed
    1, ``ray_frames``); a cube none of whose eyes stands in open space is drawn again."""
    grid = ViewcellGrid.for_scene(scene)
    rng = np.random.default_rng(seed)
    h = delta / np.sqrt(3.0)
    out = []
    while len(out) < n:
        cell = grid.cell(int(rng.integers(len(grid))))
        c = cell.box[0] + rng.random(3) * (cell.box[1] - cell.box[0])
        box = np.stack([c - h, c + h])
        cast = ray_frames(scene, box, frames, 256, seed=1, near=FRAME_NEAR)
        if len(cast.eyes):
            out.append((box, cast))
    return out


def random_cells(quick: bool) -> list[dict[str, Any]]:
    """Cubes of Δ ``DEFAULT_MAX_DELTA`` (the largest one sphere covers at the core's defaults) at
    seeded random places of each real scene's grid cells, those with an eye in open space
    (``random_open_cubes``), each scored on ``RANDOM_FRAMES`` frames: walls and clutter run
    through many of them, as they do through a walker's cells, where the quality table's two
    cells per scene sit in open space."""
    if quick:
        return []
    core = get_core("trim_regions")
    rows = []
    for name, n in RANDOM_CELLS.items():
        scene = load(name)
        for k, (box, cast) in enumerate(random_open_cubes(scene, n)):
            pvs = core.compute(scene, Viewcell(box), core.make_params())
            e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
            rows.append({"scene": name, "centre": (0.5 * (box[0] + box[1])).tolist(),
                         "seconds": pvs.seconds, "pvs": len(pvs), "gt": e["gt"],
                         "frames": len(cast.eyes), "fn_pixels_max": e["fn_pixels_max"],
                         "fn_pixel_rate_max": e["fn_pixel_rate_max"], "fn": e["fn"]})
            print(f"random {name} {k + 1}/{n}: {pvs.seconds:.2f} s, FN px "
                  f"{e['fn_pixels_max']}", flush=True)
    return rows


#: The side-by-side table's cores, each at its defaults.
SIDE_CORES = ("trim_regions", "cos", "sampling")


def side_by_side(quick: bool, frames: int, aim_most: int = SIDE_AIM_MOST
                 ) -> list[dict[str, Any]]:
    """trim_regions, cos and sampling on the same cube cells (5-30 cm) of the 20k scenes and
    lavaducts, scored on the same frames of independent rays, and against those grown by
    rays aimed at every triangle of the three answers (``_side_aimed``; ``aim_most`` 0:
    not)."""
    n = 5_000 if quick else 20_000
    cases: list[tuple[str, Any]] = [(g, n) for g in ("rooms", "village", "city")]
    if not quick:
        cases.append(("lavaducts", None))
    sizes = (0.05, 0.3) if quick else (0.05, 0.1, 0.2, 0.3)
    rows = []
    for name, tri in cases:
        scene = load(name, tri)
        grid = ViewcellGrid.for_scene(scene)
        c = grid.cell(first_open_cell(scene, grid, len(grid) // 2)).center
        for size in sizes:
            box = np.stack([c - size / 2, c + size / 2])
            cast = ray_frames(scene, box, frames, 256, seed=2, near=FRAME_NEAR)
            answers = []
            for core_name in SIDE_CORES:
                core = get_core(core_name)
                pvs, _, _ = timed(core, scene, box)
                answers.append(pvs.triangle_ids)
                e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
                rows.append({"scene": name, "size": size, "core": core_name,
                             "seconds": pvs.seconds, "pvs": e["pvs"], "gt": e["gt"],
                             "pvs_share": e["pvs"] / scene.n_triangles,
                             "gt_share": e["gt"] / scene.n_triangles,
                             "fn_pixels_max": e["fn_pixels_max"], "fn": e["fn"], "fp": e["fp"],
                             "proven_unseen": (proven_unseen(scene, box, pvs.triangle_ids, core)
                                               if core_name == "trim_regions" else None)})
                print(f"side {name} {size} {core_name}: {pvs.seconds:.2f} s, PVS/GT "
                      f"{e['pvs'] / max(e['gt'], 1):.2f}", flush=True)
            if aim_most > 0:
                _side_aimed(rows[-len(answers):], answers, scene, box, cast, aim_most)
    return rows


def _side_aimed(rows: list[dict[str, Any]], answers: list[np.ndarray], scene: Scene,
                box: np.ndarray, cast: Any, most: int) -> None:
    """The side-by-side rows of one cell scored against the frames' ground truth grown by
    rays aimed at every triangle some core's answer holds (``visibility.ray_aimed``, eyes in
    the cube, the frames' near plane): ``gt_aimed``, and ``fn_aimed`` the triangles seen that
    the answer lacks (float64-confirmed)."""
    t0 = time.perf_counter()
    frames_seen = seen_ids(cast)
    got = aimed_seen(scene, box, np.unique(np.concatenate(answers)), known=frames_seen,
                     rays=min(AIM_RAYS, most), most=most, seed=3, near=FRAME_NEAR)
    seen = np.union1d(frames_seen, got.ids)
    for r, ids in zip(rows, answers, strict=True):
        r.update(gt_aimed=int(len(seen)), aimed_rays=got.rays_per_candidate,
                 aimed_converged=bool(got.converged),
                 fn_aimed=int(len(np.setdiff1d(seen, ids))),
                 aimed_seconds=time.perf_counter() - t0)


def proven_unseen(scene: Scene, box: np.ndarray, ids: np.ndarray, trim: Any) -> int:
    """How many of trim_regions' ``ids`` for the cube ``box`` no eye of its covering spheres
    can see: those ``cos`` (conservative: every triangle any eye of its box sees) leaves out
    of the PVS of the box around all the spheres (at the default ``max_delta``)."""
    centres, delta = cover_box(box, trim.make_params().max_delta)
    around = np.stack([centres.min(axis=0) - delta, centres.max(axis=0) + delta])
    cos = get_core("cos")
    seen = cos.compute(scene, Viewcell(around), cos.make_params()).triangle_ids
    return int(len(np.setdiff1d(ids, seen)))


def wall_phases(row: dict[str, Any]) -> list[float]:
    """A speed row's phase seconds (thread seconds summed over views that run at once)
    scaled to add up to its wall seconds: each phase's share of the thread time."""
    thread = [float(row[p]) for p in PHASES]
    total = sum(thread)
    return [row["seconds"] * t / total if total > 0 else 0.0 for t in thread]


def plot(speed_rows: list[dict[str, Any]], quality_rows: list[dict[str, Any]],
         path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    labels = [f"{r['scene']}\nΔ={r['delta']}" for r in speed_rows]
    bottom = np.zeros(len(speed_rows))
    split = np.array([wall_phases(r) for r in speed_rows]).reshape(len(speed_rows), len(PHASES))
    for i, ph in enumerate(PHASES):
        v = split[:, i]
        a.bar(range(len(v)), v, bottom=bottom, label=ph)
        bottom += v
    a.set_xticks(range(len(labels)), labels, fontsize=7)
    a.set_ylabel("wall seconds, split by thread time (2 CPU cores)")
    a.set_title("time per phase (Fig. 13)")
    a.legend(fontsize=7)
    for name in dict.fromkeys(r["scene"] for r in quality_rows):
        rs = [r for r in quality_rows if r["scene"] == name and r["cell"] == 0]
        b.plot([100 * r["delta"] for r in rs], [r["fn_pixels_mean"] for r in rs], "o-",
               label=name)
    b.axhline(5e-5 * 6 * 256 * 256, color="k", ls="--", lw=0.8, label="0.005 % of a frame")
    b.set_xlabel("Δ (cm)")
    b.set_ylabel("mean FN pixels per 6 x 256² frame")
    b.set_title("false-negative pixels (Fig. 16)")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _side_aimed_cells(r: dict[str, Any]) -> str:
    if "gt_aimed" not in r:
        return "– | – | –"
    return (f"{aimed_total(r['gt_aimed'], r['aimed_rays'], r['aimed_converged'])} | "
            f"{r['pvs'] / max(r['gt_aimed'], 1):.2f} | {r['fn_aimed']}")


def _unseen_cell(r: dict[str, Any]) -> str:
    """The side-by-side table's proven-unseen cell: count and share of the PVS (– for cos)."""
    if r.get("proven_unseen") is None:
        return "–"
    return f"{r['proven_unseen']:,} ({100 * r['proven_unseen'] / max(r['pvs'], 1):.0f} %)"


def markdown(speed_rows, quality_rows, side_rows, frames, elapsed, argv, loads,
             leaf_rows=(), cell_rows=(), random_rows=()) -> str:
    cmd = " ".join(["python -m benchmarks.bench_trim_regions", *argv])
    out = ["# trim_regions: speed, memory and error against the paper", "",
           f"Command: `{cmd}`; {platform.processor() or platform.machine()}, {os.cpu_count()} "
           f"CPU cores, {elapsed:.0f} s in all; load average (1 min) {loads[0]:.1f} at start, "
           f"{loads[1]:.1f} at end (another engineer's jobs may share the cores: wall times "
           "under that load).", "", "![phases and FN pixels](trim_regions.png)", "",
           "## Speed (Fig. 13, Table 2)", "",
           "One sphere of radius Δ at a walkable cell's centre, default resolution (256 px per "
           "cube face, 6 faces), best of 2 after a warm-up; P0 octree layers, P1 geometry "
           "(projection, silhouettes, trim quads), P2 rasterization into the k-buffers, P3 "
           "resolve, P4 gather (occludee footprints, hulls); the octree is built once per "
           "scene. The views run two at a time (one per core), so the phases' thread seconds "
           "add up to more than the wall time: each phase column is its share of the thread "
           "time times the wall time. Ratio: our seconds over the paper's 16-22 ms on an "
           "RTX 4090. The timed runs follow one another, as a walker's cells do, and reuse "
           "the per-view buffers the run before left (kept 5 s, `trim_regions.warm`); cold s: "
           "one run after they were released (the first cell after a pause pays their page "
           "faults). Sampling: the `sampling` core at its defaults on the same cube in the same "
           "run (best of 2 after a warm-up), its seconds and PVS, for scale.", "",
           "| scene | triangles | Δ m | s | cold s | P0 | P1 | P2 | P3 | P4 | × paper | layers "
           "| PVS | sampling s | sampling PVS | active px | seq. length | k-buffer MB alloc / "
           "used | overflow px | octree leaves / build s |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in speed_rows:
        ratio = f"{1000 * r['seconds'] / PAPER_MS[1]:.0f}-{1000 * r['seconds'] / PAPER_MS[0]:.0f}"
        out.append(f"| {r['scene']} | {r['triangles']:,} | {r['delta']} | {r['seconds']:.2f} | "
                   f"{r['cold_seconds']:.2f} | " + " | ".join(f"{v:.2f}" for v in wall_phases(r))
                   + f" | {ratio} | {r['layers']} | {r['pvs']:,} | {r['sampling_seconds']:.2f} | "
                   f"{r['sampling_pvs']:,} | {r['active_pixels']:,} | "
                   f"{r['mean_sequence_length']:.1f} | {r['kbuffer_allocated_mb']:.0f} / "
                   f"{r['kbuffer_used_mb']:.1f} | {r['overflow_pixels']} | "
                   f"{r['octree_leaves']} / {r['octree_build_seconds']:.1f} |")
    if cell_rows:
        out += ["", "## Box cells", "",
                "Box cells at the grid's middle cell (the 100k city; a 1 m cell of lavaducts), "
                "each side as a cube and as the server's cell (the side across the ground, the "
                "grid's eye range high): the core at its defaults (the fewest spheres of at "
                f"most `max_delta` {DEFAULT_MAX_DELTA} m: more for a larger box, up to 27, "
                "then larger ones) and "
                "the cubes covered by 8 and by 1 larger spheres (`max_delta` the half "
                "diagonal of the box over 2 and 1), one run after a warm-up each. FN px: the "
                f"most pixels of a frame showing a triangle the PVS lacks, over {frames} frames "
                "from eyes in the box (as the quality table below; the paper's bound is 19.7 "
                "px); FN: missed / GT triangles. The aim for the 1 m cell is 2 s.", "",
                "| scene | cell m | cover | spheres | Δ m | views | s | P0 | P1 | P2 | P3 | P4 "
                "| PVS | GT | FN px max | FN px % max | FN |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in cell_rows:
            dims = f"{r['side']:g} x {r.get('height', r['side']):g} x {r['side']:g}"
            out.append(f"| {r['scene']} | {dims} | {r['cover']} | {r['spheres']} | "
                       f"{r['delta']:.2f} | {r['views']} | {r['seconds']:.2f} | "
                       + " | ".join(f"{v:.2f}" for v in wall_phases(r))
                       + f" | {r['pvs']:,} | {r['gt']:,} | {r['fn_pixels_max']} | "
                       f"{100 * r['fn_pixel_rate_max']:.4f} | {r['fn']:.3f} |")
    if leaf_rows:
        out += ["", "## Leaf size", "",
                "One sphere of Δ 0.2 m at the grid's middle cell, default resolution, best of 2 "
                "after a warm-up that builds the octree; `max_prims` is the most triangles an "
                "octree leaf holds (the default 256). Layers: summed over the 6 views; phases as "
                "in the speed table; GT and FN px max as in the quality table below, on the "
                "frames it casts for the same cell.", "",
                "| scene | max_prims | layers | s | P0 | P1 | P2 | P3 | P4 | PVS | GT | "
                "FN px max |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in leaf_rows:
            out.append(f"| {r['scene']} | {r['max_prims']} | {r['layers']} | "
                       f"{r['seconds']:.2f} | " + " | ".join(f"{v:.2f}" for v in wall_phases(r))
                       + f" | {r['pvs']:,} | {r['gt']:,} | {r['fn_pixels_max']} |")
    out += ["", "## Error and tightness (Fig. 15-16, Table 3)", "",
            f"Two cells per scene (the grid's middle cell and one a third in), the cube whose "
            f"circumscribed sphere is Δ; frames: {frames} eyes stratified in the cube (those "
            "inside geometry dropped) with random cube orientations, 256 px per face "
            "(393,216 px per frame; the paper's bound of 0.005 % is 19.7 px), one ray through "
            "a random point of each pixel cast by Embree, independently of our rasterizer "
            "(`visibility/ray_frames.py`), each missed pixel cast again in float64 before it "
            "counts. FN px: the pixels of a frame whose nearest triangle is missing from the "
            "PVS (max and mean over frames). GT: every triangle the frames show. FN = "
            "missed / GT, FP = (PVS - GT) / GT as Table 3 and Fig. 15 define them; * without "
            "unreliable triangles (an edge under one pixel from the cell's centre). The "
            "defaults are the method alone, small and thin triangles behind trimmed occluders "
            "tested at every pixel they touch (`small=\"conservative\"`). Add-on: the same "
            f"cell with the sampling add-on (`gather_eyes={GATHER_EYES}`: eyes stratified in "
            "the cell sampled into the answer), scored on the same frames. Centres: the "
            "method with `small=\"centres\"` (the paper: those triangles tested at pixel "
            "centres only), on the same frames.", "",
            "| scene | cell | Δ m | s | PVS | GT | PVS / GT | FN px max | FN px mean | FN px % "
            "max | FN | FN* | FP | FP* | active px | seq. length | overflow px | add-on: s | "
            "PVS | FN px max | FN | centres: s | PVS | FN px max | FN |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
            "---|---|---|---|---|"]
    for r in quality_rows:
        out.append(f"| {r['scene']} | {r['cell']} | {r['delta']} | {r['seconds']:.2f} | "
                   f"{r['pvs']:,} | {r['gt']:,} | {r['pvs'] / max(r['gt'], 1):.2f} | "
                   f"{r['fn_pixels_max']} | {r['fn_pixels_mean']:.1f} | "
                   f"{100 * r['fn_pixel_rate_max']:.4f} | {r['fn']:.3f} | {r['fn_star']:.3f} | "
                   f"{r['fp']:.2f} | {r['fp_star']:.2f} | {r['active_pixels']:,} | "
                   f"{r['mean_sequence_length']:.1f} | {r['overflow_pixels']} | "
                   f"{r['gather_seconds']:.2f} | {r['gather_pvs']:,} | "
                   f"{r['gather_fn_pixels_max']} | {r['gather_fn']:.3f} | "
                   f"{r['centres_seconds']:.2f} | {r['centres_pvs']:,} | "
                   f"{r['centres_fn_pixels_max']} | {r['centres_fn']:.3f} |")
    for key, mode in (("fn_pixel_rate_max", "at the defaults (the method alone)"),
                      ("gather_fn_pixel_rate_max", "with the sampling add-on"),
                      ("centres_fn_pixel_rate_max", "with `small=\"centres\"`")):
        over = [r for r in quality_rows if r[key] > 5e-5]
        out += ["", f"Frames above the paper's 0.005 % {mode}: {len(over)} of "
                f"{len(quality_rows)} cells: " + (", ".join(
                    f"{r['scene']} cell {r['cell']} Δ={r['delta']} ({100 * r[key]:.4f} %)"
                    for r in over) or "none") + "."]
    out.append("")
    aimed = [r for r in quality_rows if "gt_aimed" in r]
    if aimed:
        out += ["### Against rays aimed at the answer", "",
                "The frames' rays pass by triangles smaller than their pixels, so their ground "
                "truth undercounts what the cell's eyes see. Here it is grown by rays aimed at "
                "the other triangles of the answer at the defaults (`visibility/ray_aimed.py`: "
                "from random eyes in the cube's open space to random points of each, the "
                "frames' near plane, whatever a ray meets first counts as seen once a float64 "
                f"cast agrees), {AIM_RAYS} per triangle, doubled until a doubling adds under "
                f"0.1 % or {aimed[0]['aimed_most']} are cast. FN aimed: triangles they see that "
                "the answer lacks.", "",
                "| scene | cell | Δ m | PVS | GT | GT with aimed rays | rays per triangle | "
                "last doubling | PVS / GT | PVS / GT with aimed rays | FN aimed | s |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in aimed:
            out.append(f"| {r['scene']} | {r['cell']} | {r['delta']} | {r['pvs']:,} | "
                       f"{r['gt']:,} | {r['gt_aimed']:,} | {r['aimed_rays']:,} | "
                       f"+{100 * r['aimed_added_last']:.2f} % | "
                       f"{r['pvs'] / max(r['gt'], 1):.2f} | "
                       f"{r['pvs'] / max(r['gt_aimed'], 1):.2f} | {r['aimed_missed']} | "
                       f"{r['aimed_seconds']:.1f} |")
        out.append("")
    if random_rows:
        out += ["## Random cells", "",
                f"Cubes of Δ {DEFAULT_MAX_DELTA} m (the core's defaults: the largest one sphere "
                "covers) at seeded random places of each real "
                "scene's grid cells, those with an eye in open space, each judged as above on "
                f"{RANDOM_FRAMES} frames: walls and clutter run through many of them, as "
                "through a walker's cells. Over: cells with a frame above the paper's 19.7 px.",
                "", "| scene | cells | over the bound | FN px max | FN px max, median | "
                "PVS / GT, median | s, median |", "|---|---|---|---|---|---|---|"]
        for name in dict.fromkeys(r["scene"] for r in random_rows):
            rs = [r for r in random_rows if r["scene"] == name]
            over = sum(r["fn_pixel_rate_max"] > 5e-5 for r in rs)
            out.append(f"| {name} | {len(rs)} | {over} | "
                       f"{max(r['fn_pixels_max'] for r in rs)} | "
                       f"{np.median([r['fn_pixels_max'] for r in rs]):.0f} | "
                       f"{np.median([r['pvs'] / max(r['gt'], 1) for r in rs]):.2f} | "
                       f"{np.median([r['seconds'] for r in rs]):.2f} |")
        out.append("")
    out += ["## Side by side with cos and sampling on equal cube cells", "",
            "The same cube cell of each size at the grid's middle cell; each core at its "
            f"defaults (trim_regions covers the cube with spheres of at most {DEFAULT_MAX_DELTA} "
            "m: one sphere "
            "here), all three scored on the same frames of independent rays. PVS and GT as "
            "shares of the scene; FN px as above. Proven unseen: "
            "triangles of trim_regions' answer that cos (conservative) leaves out of the PVS "
            "of the box holding its spheres, so no eye trim_regions answers for sees them. "
            "GT aimed: the frames' GT grown by rays from eyes in the cube aimed at every "
            "triangle of the three answers (as in the table above; rays per triangle in "
            "brackets, * not converged): a lower bound on what the cube's eyes see, so PVS / "
            "GT aimed is an upper bound; FN aimed: triangles those rays see that the answer "
            "lacks.", "",
            "| scene | cell | core | s | PVS | GT | PVS % | GT % | PVS / GT | FN px max | FN | "
            "proven unseen | GT aimed | PVS / GT aimed | FN aimed |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in side_rows:
        out.append(f"| {r['scene']} | {100 * r['size']:.0f} cm | {r['core']} | "
                   f"{r['seconds']:.2f} | {r['pvs']:,} | {r['gt']:,} | "
                   f"{100 * r['pvs_share']:.1f} | {100 * r['gt_share']:.1f} | "
                   f"{r['pvs'] / max(r['gt'], 1):.2f} | {r['fn_pixels_max']} | {r['fn']:.3f} | "
                   + _unseen_cell(r) + " | " + _side_aimed_cells(r) + " |")
    trims = [r for r in side_rows if r.get("proven_unseen") is not None]
    if trims:
        shares = [100 * r["proven_unseen"] / max(r["pvs"], 1) for r in trims]
        out += ["", f"Provably unseen: {min(shares):.0f}-{max(shares):.0f} % of trim_regions' "
                "answer on these cells. The method walks each ray from v* alone and reports "
                "what lies past the umbra of a trimmed silhouette; it fuses no occluders "
                "across rays, as cos does per pixel, so a triangle that other occluders hide "
                "from every eye can stay in its answer."]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20k village, 5k scenes, few frames")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--aim-most", type=int, default=AIM_MOST,
                    help="most rays aimed at each triangle of an answer (0: none)")
    ap.add_argument("--side-aim-most", type=int, default=SIDE_AIM_MOST,
                    help="most rays aimed at each triangle of the side-by-side answers "
                    "(0: none)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    frames = 4 if args.quick else args.frames
    speed_rows = speed(args.quick)
    # The leaf table's cells are quality cells too: their frames are cast once.
    casts: dict = {}
    leaf_rows = leaf_sizes(args.quick, frames, casts)
    cell_rows = box_cells(args.quick, frames)
    quality_rows = quality(args.quick, frames, casts,
                           min(args.aim_most, AIM_RAYS) if args.quick else args.aim_most)
    casts.clear()
    random_rows = random_cells(args.quick)
    side_rows = side_by_side(args.quick, frames,
                             min(args.side_aim_most, AIM_RAYS) if args.quick
                             else args.side_aim_most)
    elapsed = time.perf_counter() - t0
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "trim_regions.json").write_text(json.dumps(
        {"speed": speed_rows, "leaf_sizes": leaf_rows, "box_cells": cell_rows,
         "quality": quality_rows, "random_cells": random_rows,
         "side_by_side": side_rows,
         "frames": frames, "seconds": elapsed, "load": [load0, os.getloadavg()[0]]},
        indent=1))
    plot(speed_rows, quality_rows, out / "trim_regions.png")
    (out / "trim_regions.md").write_text(markdown(
        speed_rows, quality_rows, side_rows, frames, elapsed, argv,
        (load0, os.getloadavg()[0]), leaf_rows, cell_rows, random_rows))
    print((out / "trim_regions.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
