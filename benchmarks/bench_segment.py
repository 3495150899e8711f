"""The ``from_segment`` core measured the way its paper does (Popescu et al. 2024, Sec. 4.4-4.5).

Four parts, each printed as a table and written to ``benchmarks/results/from_segment.md`` with
PNG plots and the raw numbers (``from_segment.json``):

``scenes``  per scene and cell: seconds, PVS size (% of the scene's valid triangles), FN and FP
            against a dense sampled ground truth (``benchmarks.gt_cache``), over face resolutions
            x jitter runs (the paper's accuracy knobs); spheres are counted separately.
``segment`` Sec. 4.5.1: one from-segment pass on a view segment against from-point sampling of
            the same segment (same cube orientation and face resolution, viewpoints in van der
            Corput order so every prefix is spread along the segment). The dense ground truth is
            the union of all from-point views. Reported: completeness against points and against
            seconds, and the ratio of the time from-point sampling needs to reach from-segment's
            completeness to from-segment's time (the target: >= 99.5 % at >= 20x).
``cell``    Sec. 4.5.2: from-segment with 1, 2, 4, 8 jittered runs on the cell's perimeter
            against from-point sampling at random points of the cell (random cube each), both
            against the cell's dense ground truth: equal time and equal completeness.
``grass``   cells of ``grass`` at 100k triangles (everything visible) at the core's defaults and
            other cut depths.
``kitchen`` a 4 m cell of the 1M-triangle kitchen, the same way (one run each: minutes).
``city1m``  one 4 x 4 m cell of ``city`` at 1M triangles at 256^2 per face (what the server's
            prefetch budget depends on): median seconds, the phases, peak memory.

Usage: ``python -m benchmarks.bench_segment`` (the standard run, about half an hour on 2 cores),
``--quick`` (a smoke run in a minute or two), ``--parts segment cell`` to run some parts only.
Times are wall seconds after a warm-up compile, on the machine described at the top of the report.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from benchmarks.bench_matrix import (  # noqa: E402
    _load,
    load_scenes,
    machine_description,
    measure_peak,
    pick_cells,
)
from benchmarks.gt_cache import cached_ground_truth  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
PARTS = ("scenes", "segment", "cell", "rect", "orient", "city1m", "grass", "kitchen")
#: The issue's target for the segment experiment.
TARGET_COMPLETENESS = 0.995
TARGET_RATIO = 20.0

PRESETS: dict[str, dict[str, Any]] = {
    "quick": {
        "scenes": ["city:20000", "spheres:300"], "resolutions": [32, 64], "runs": [1, 2],
        "cells": 1, "gt_points": 32, "gt_resolution": 64,
        "segment_scenes": ["city:20000"], "segment_resolution": 64, "segment_points": 256,
        "cell_scenes": ["city:20000"], "cell_resolution": 64, "cell_runs": [1, 2],
        "cell_points": 64, "rect_scenes": ["city:20000"], "orient_scenes": ["city:20000"],
        "first_orientation": "axis", "city1m_triangles": 100_000,
        "city1m_cells": 1, "repeats": 1, "grass_triangles": 10_000, "grass_cells": 1,
        "max_seconds": 20, "part_resolution": 256,
    },
    "standard": {
        "scenes": ["city:100000", "city:1000000", "village:100000", "grass:200000",
                   "swaying_grass:100000", "spheres:2000", "real"],
        "resolutions": [128, 256, 512], "runs": [1, 2, 4, 8], "cells": 1,
        "gt_points": 256, "gt_resolution": 512,
        "segment_scenes": ["city:100000", "village:100000"], "segment_resolution": 256,
        "segment_points": 4096,
        "cell_scenes": ["city:100000", "grass:200000"], "cell_resolution": 256,
        "cell_runs": [1, 2, 4, 8], "cell_points": 2048,
        "rect_scenes": ["city:100000", "village:100000"],
        "orient_scenes": ["city:100000", "village:100000", "rooms:100000", "real"],
        "first_orientation": "axis", "city1m_triangles": 1_000_000,
        "city1m_cells": 3, "repeats": 3, "max_seconds": 90, "grass_triangles": 100_000,
        "grass_cells": 2, "part_resolution": 256,
    },
}


# --------------------------------------------------------------------------- helpers
def van_der_corput(n: int) -> np.ndarray:
    """(n,) the base-2 van der Corput sequence 0, 1/2, 1/4, 3/4, ...: every prefix is spread
    evenly over [0, 1)."""
    out = np.zeros(n)
    for k in range(n):
        x, denom, i = 0.0, 1.0, k
        while i:
            denom *= 2.0
            x += (i & 1) / denom
            i >>= 1
        out[k] = x
    return out


def _core():
    from visibility.cores.base import get_core

    return get_core("from_segment")


def _warm_up() -> None:
    """Compile the kernels (from-segment, rasterizer, sphere buffers) on a tiny scene."""
    from visibility.raster import render_cubemap
    from visibility.raster.spheres import draw_spheres_cubemap
    from visibility.scene import Scene
    from visibility.viewcells import Viewcell

    tris = np.array([[(-1, 0, -5), (1, 0, -5), (0, 2, -5)]], dtype=np.float64)
    scene = Scene(tris.reshape(-1, 3), np.arange(3).reshape(-1, 3), name="warmup",
                  sphere_centers=np.array([[[0.0, 1.0, -3.0]], [[0.5, 1.0, -3.0]]]),
                  sphere_radii=np.array([0.5]))
    cell = Viewcell(np.array([[-0.5, 1.5, -0.5], [0.5, 1.9, 0.5]]))
    core = _core()
    core.compute(scene, cell, core.make_params(resolution=16))
    d, i = render_cubemap(scene.vertices, scene.faces, np.zeros(3), 16)
    draw_spheres_cubemap(scene.sphere_centers[0], scene.sphere_radii, np.zeros(3), d, i)


def _share(a: np.ndarray, ref: np.ndarray) -> float:
    """|a ∩ ref| / |ref| for sorted unique id arrays (1 for an empty reference)."""
    return 1.0 if len(ref) == 0 else len(np.intersect1d(a, ref, assume_unique=True)) / len(ref)


def _fn_fp(ids: np.ndarray, ref: np.ndarray) -> tuple[float | None, float | None]:
    from visibility.ground_truth import fn_fp_rates

    if len(ref) == 0 and len(ids) == 0:
        return None, None
    return fn_fp_rates(ids, ref)


def _time_to_reach(curve_hits: np.ndarray, curve_sec: np.ndarray, need: int) -> tuple[int, float]:
    """(points, seconds) at which a cumulative hit curve first reaches ``need``; (-1, inf) when
    it never does."""
    k = int(np.searchsorted(curve_hits, need, side="left"))
    if k >= len(curve_hits):
        return -1, float("inf")
    return k + 1, float(curve_sec[k])


def _reached_at_time(curve_hits: np.ndarray, curve_sec: np.ndarray, seconds: float) -> tuple[
        int, int]:
    """(points, hits) of a cumulative curve within ``seconds`` (0, 0 when not even one)."""
    k = int(np.searchsorted(curve_sec, seconds, side="right"))
    return (k, int(curve_hits[k - 1])) if k else (0, 0)


def from_point_curve(scene, points: np.ndarray, rotations: list[np.ndarray | None],
                     resolution: int, reference: np.ndarray | None = None,
                     progress: str | None = None) -> dict[str, np.ndarray]:
    """From-point sampling, one cubemap per viewpoint, with its cumulative curve.

    Returns ``seen`` (m,) bool, ``seconds`` (n,) cumulative render-and-union wall time (the
    bookkeeping of the curve itself is not counted), ``found`` (n,) triangles seen so far and,
    with a ``reference`` (sorted ids), ``hits`` (n,) of them seen so far.
    """
    from tqdm import tqdm

    from visibility.raster import render_cubemap_ids

    m = scene.n_triangles
    seen = np.zeros(m, dtype=bool)
    ref = None
    if reference is not None:
        ref = np.zeros(m, dtype=bool)
        ref[np.asarray(reference, dtype=np.int64)] = True
    n = len(points)
    secs, found, hits = np.zeros(n), np.zeros(n, np.int64), np.zeros(n, np.int64)
    total = 0.0
    n_found = n_hits = 0
    mask = scene.valid_faces
    for k in tqdm(range(n), desc=progress or "from-point", unit="view", leave=False,
                  disable=progress is None, mininterval=2.0):
        t0 = time.perf_counter()
        ids = render_cubemap_ids(scene.vertices, scene.faces, points[k], resolution, rotations[k],
                                 face_mask=mask)
        hit = np.unique(ids[ids >= 0])
        new = hit[~seen[hit]]
        seen[new] = True
        total += time.perf_counter() - t0
        n_found += len(new)
        if ref is not None:
            n_hits += int(np.count_nonzero(ref[new]))
        secs[k], found[k], hits[k] = total, n_found, n_hits
    out = {"seen": seen, "seconds": secs, "found": found}
    if ref is not None:
        out["hits"] = hits
    return out


def _timed(fn, repeats: int) -> tuple[Any, list[float]]:
    out, secs = None, []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        secs.append(time.perf_counter() - t0)
    return out, secs


# --------------------------------------------------------------------------- parts
def part_scenes(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Seconds, PVS %, FN and FP against the dense ground truth per scene x res x runs."""
    from visibility.viewcells import ViewcellGrid

    core = _core()
    rows: list[dict[str, Any]] = []
    for label, loader in load_scenes(cfg["scenes"]):
        scene = loader()
        grid = ViewcellGrid.for_scene(scene)
        n_valid = int(np.count_nonzero(scene.valid_faces))
        for cid in pick_cells(grid, cfg["cells"]):
            cell = grid.cell(cid)
            gt, rec = _ground_truth(scene, cell, cfg, log, label)
            sph_gt = rec.get("sphere_ids")
            base = None  # (resolution, seconds of one run) measured last
            for res in sorted(cfg["resolutions"]):
                for runs in sorted(cfg["runs"]):
                    if base is not None:
                        guess = base[1] * (res / base[0]) ** 2 * runs
                        if guess > cfg["max_seconds"]:
                            log(f"  {label:>16} res {res:>4} runs {runs}: skipped, projected "
                                f"{guess:.0f} s > {cfg['max_seconds']} s")
                            rows.append({"scene": label, "triangles": scene.n_triangles,
                                         "cell": cid, "resolution": res, "runs": runs,
                                         "skipped": guess})
                            continue
                    params = core.make_params(resolution=res, runs=runs,
                                              first_orientation=cfg["first_orientation"])
                    pvs, secs = _timed(
                        lambda s=scene, c=cell, p=params: core.compute(s, c, p), 1)
                    # Seconds per run grow faster than linearly on dense scenes (longer
                    # interval lists), so project from the worst point measured at this res.
                    per_run = secs[0] / runs
                    if base is not None and base[0] == res:
                        per_run = max(per_run, base[1])
                    base = (res, per_run)
                    fn, fp = _fn_fp(pvs.triangle_ids, gt)
                    row = {"scene": label, "triangles": scene.n_triangles, "cell": cid,
                           "resolution": res, "runs": runs, "seconds": secs[0],
                           "pvs": len(pvs), "pvs_pct": 100.0 * len(pvs) / max(n_valid, 1),
                           "gt": int(len(gt)), "fn": fn, "fp": fp,
                           "gt_last_new": rec.get("last_new_share")}
                    if scene.n_spheres:
                        sfn, sfp = _fn_fp(pvs.sphere_ids, np.asarray(sph_gt, dtype=np.int32))
                        row.update({"spheres": scene.n_spheres, "sphere_pvs": len(pvs.sphere_ids),
                                    "sphere_fn": sfn, "sphere_fp": sfp})
                    rows.append(row)
                    log(_scene_line(row))
    return rows


def _ground_truth(scene, cell, cfg, log, label) -> tuple[np.ndarray, dict]:
    """The cell's dense ground truth (cached) and its record; spheres, when the scene has them,
    are sampled too (not cached: the cache holds triangle ids)."""
    t0 = time.perf_counter()
    if scene.n_spheres:
        from visibility.ground_truth import sample_pvs

        g = sample_pvs(scene, cell, cfg["gt_points"], cfg["gt_resolution"], seed=12345)
        rec = {"seconds": g.seconds, "convergence": g.convergence,
               "sphere_ids": g.sphere_ids.tolist()}
        gt = g.triangle_ids
    else:
        gt, rec = cached_ground_truth(scene, cell, cfg["gt_points"], cfg["gt_resolution"])
    conv = rec.get("convergence") or []
    if len(conv) >= 2 and conv[-1][1]:
        rec["last_new_share"] = conv[-1][2] / conv[-1][1]
    log(f"  [{label}] ground truth: {len(gt)} triangles from {cfg['gt_points']} points at "
        f"{cfg['gt_resolution']} px ({time.perf_counter() - t0:.1f} s"
        f"{', cached' if rec.get('cached') else ''}; last batch added "
        f"{100 * rec.get('last_new_share', float('nan')):.2f} %)")
    return gt, rec


def _scene_line(r: dict[str, Any]) -> str:
    s = (f"  {r['scene']:>16} cell {r['cell']:>5} res {r['resolution']:>4} runs {r['runs']} "
         f"{r['seconds']:8.3f} s  PVS {r['pvs_pct']:6.2f} %  FN {_pct(r['fn'])}  FP "
         f"{_pct(r['fp'])}")
    if "spheres" in r:
        s += f"  spheres FN {_pct(r['sphere_fn'])} FP {_pct(r['sphere_fp'])}"
    return s


def _pct(x: float | None) -> str:
    return "   n/a" if x is None else f"{100 * x:6.2f} %"


def part_segment(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Sec. 4.5.1: one from-segment pass against from-point sampling along the same segment."""
    from visibility.cores.from_segment import cell_segments
    from visibility.viewcells import ViewcellGrid

    core = _core()
    res, n = int(cfg["segment_resolution"]), int(cfg["segment_points"])
    out = []
    for label, loader in load_scenes(cfg["segment_scenes"]):
        scene = loader()
        grid = ViewcellGrid.for_scene(scene)
        cid = pick_cells(grid, 1)[0]
        p, q = cell_segments(grid.cell(cid).box, eye_levels=1)[0]
        # Pixel centres (jitter 0), as in the paper: the from-point views it is compared with
        # sample the centres, so an exact pass holds all they see.
        params = core.make_params(resolution=res, runs=1, jitter=0.0,
                                  first_orientation=cfg["first_orientation"])
        fs, secs = _timed(lambda s=scene, a=p, b=q, pr=params: core.compute_segment(s, a, b, pr),
                          cfg["repeats"])
        t_fs = float(np.median(secs))
        pts = p + van_der_corput(n)[:, None] * (q - p)
        curve = from_point_curve(scene, pts, [None] * n, res, progress=f"{label} segment")
        gt = np.flatnonzero(curve["seen"]).astype(np.int32)
        fs_ids = fs.triangle_ids
        comp = _share(fs_ids, gt)
        union = np.union1d(gt, fs_ids)
        need = int(np.ceil(comp * len(gt) - 1e-9))
        n_eq, t_eq = _time_to_reach(curve["found"], curve["seconds"], need)
        k_t, found_t = _reached_at_time(curve["found"], curve["seconds"], t_fs)
        row = {
            "scene": label, "triangles": scene.n_triangles, "cell": cid,
            "segment": [p.tolist(), q.tolist()], "resolution": res, "points": n,
            "fs_seconds": t_fs, "fs_seconds_all": secs, "fs_found": int(len(fs_ids)),
            "gt": int(len(gt)), "fs_completeness": comp,
            "fs_outside_gt": int(len(fs_ids) - round(comp * len(gt))),
            "union": int(len(union)),
            "fp_seconds_per_view": float(curve["seconds"][-1] / n),
            "fp_seconds_all": float(curve["seconds"][-1]),
            "equal_quality_points": n_eq, "equal_quality_seconds": t_eq,
            "ratio": t_eq / t_fs if np.isfinite(t_eq) else None,
            "equal_time_points": k_t, "equal_time_completeness": found_t / max(len(gt), 1),
            "curve_points": _log_samples(n),
        }
        idx = np.asarray(row["curve_points"]) - 1
        row["curve_completeness"] = (curve["found"][idx] / max(len(gt), 1)).tolist()
        row["curve_union_completeness"] = (curve["found"][idx] / max(len(union), 1)).tolist()
        row["curve_seconds"] = curve["seconds"][idx].tolist()
        row["meets_target"] = bool(comp >= TARGET_COMPLETENESS and row["ratio"] is not None
                                   and row["ratio"] >= TARGET_RATIO)
        out.append(row)
        log(f"  [{label}] segment {np.round(p, 2).tolist()} -> {np.round(q, 2).tolist()} at "
            f"{res}^2: from-segment {t_fs:.3f} s, {comp:.2%} of the dense ground truth ({n} "
            f"views, {len(gt)} triangles; it also finds {row['fs_outside_gt']} the views miss). "
            f"From-point needs {n_eq if n_eq > 0 else f'> {n}'} views, "
            f"{t_eq:.2f} s, for the same share: {_ratio(row['ratio'])}; in equal time it reaches "
            f"{row['equal_time_completeness']:.2%} ({k_t} views)")
    return out


def _ratio(r: float | None) -> str:
    return "not reached" if r is None else f"{r:.1f}x"


def _log_samples(n: int) -> list[int]:
    """Distinct integers 1..n spaced evenly in log scale (always holding n)."""
    return sorted({int(round(x)) for x in np.geomspace(1, n, 60)} | {n})


def part_rect(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Sec. 4.5.2 on the paper's own region: a view rectangle (the cell's XZ square at mid eye
    height), so from-segment walks 4 segments and from-point samples the same rectangle."""
    return part_cell(cfg, log, flat=True)


def part_cell(cfg: dict[str, Any], log=print, flat: bool = False) -> list[dict[str, Any]]:
    """Sec. 4.5.2: jittered from-segment runs on the perimeter against from-point sampling in
    the cell (``flat``: in the view rectangle at the cell's mid eye height, as the paper does).

    Both methods only report triangles seen at some pixel centre from some point of the cell,
    so everything either finds is visible: their union with the dense ground truth is the best
    known visible set ("known"), and completeness is measured against it (as the paper's Figs.
    8-9 count visible triangles found) as well as against the sampled ground truth alone.
    """
    from visibility.ground_truth import sample_points
    from visibility.raster.camera import random_rotation
    from visibility.viewcells import Viewcell, ViewcellGrid

    core = _core()
    res, n = int(cfg["cell_resolution"]), int(cfg["cell_points"])
    out = []
    for label, loader in load_scenes(cfg["rect_scenes" if flat else "cell_scenes"]):
        scene = loader()
        grid = ViewcellGrid.for_scene(scene)
        cid = pick_cells(grid, 1)[0]
        cell = grid.cell(cid)
        if flat:
            box = np.array(cell.box, dtype=np.float64)
            box[:, 1] = box[:, 1].mean()
            cell = Viewcell(box, cid)
        gt, _ = _ground_truth(scene, cell, cfg, log, label)
        fs_rows, fs_sets = [], []
        for runs in cfg["cell_runs"]:
            params = core.make_params(resolution=res, runs=runs,
                                      first_orientation=cfg["first_orientation"])
            pvs, secs = _timed(lambda s=scene, c=cell, p=params: core.compute(s, c, p), 1)
            fs_sets.append(pvs.triangle_ids)
            fs_rows.append({"runs": runs, "seconds": secs[0], "found": len(pvs),
                            "gt_share": _share(pvs.triangle_ids, gt)})
        rng = np.random.default_rng(2024)
        pts = sample_points(cell.box, n, rng)
        rots = [random_rotation(rng) for _ in range(n)]
        curve = from_point_curve(scene, pts, rots, res, reference=gt, progress=f"{label} cell")
        known = gt
        for ids in [*fs_sets, np.flatnonzero(curve["seen"])]:
            known = np.union1d(known, ids)
        nk = max(len(known), 1)
        for r in fs_rows:
            r["completeness"] = r["found"] / nk
            need = int(r["found"])
            r["eq_quality_points"], r["eq_quality_seconds"] = _time_to_reach(
                curve["found"], curve["seconds"], need)
            r["eq_quality_ratio"] = (r["eq_quality_seconds"] / r["seconds"]
                                     if np.isfinite(r["eq_quality_seconds"]) else None)
            k, found = _reached_at_time(curve["found"], curve["seconds"], r["seconds"])
            r["eq_time_points"], r["eq_time_completeness"] = k, found / nk
            r["eq_time_gt_share"] = (int(curve["hits"][k - 1]) if k else 0) / max(len(gt), 1)
        idx = np.asarray(_log_samples(n)) - 1
        row = {"scene": label, "triangles": scene.n_triangles, "cell": cid, "resolution": res,
               "box": cell.box.tolist(), "flat": flat, "gt": int(len(gt)),
               "known": int(len(known)), "gt_points": cfg["gt_points"],
               "gt_resolution": cfg["gt_resolution"], "fs": fs_rows, "fp_points": n,
               "fp_completeness": float(curve["found"][-1] / nk),
               "fp_gt_share": float(curve["hits"][-1] / max(len(gt), 1)),
               "fp_seconds": float(curve["seconds"][-1]),
               "curve_points": (idx + 1).tolist(),
               "curve_completeness": (curve["found"][idx] / nk).tolist(),
               "curve_seconds": curve["seconds"][idx].tolist()}
        out.append(row)
        for r in fs_rows:
            log(f"  [{label}] cell {cid}: from-segment x{r['runs']} {r['seconds']:.2f} s finds "
                f"{r['found']} ({r['completeness']:.2%} of {nk} known visible, "
                f"{r['gt_share']:.2%} of the ground truth); from-point in equal time "
                f"{r['eq_time_completeness']:.2%} ({r['eq_time_points']} views); for as many "
                f"{r['eq_quality_points'] if r['eq_quality_points'] > 0 else f'> {n}'} views "
                f"{r['eq_quality_seconds']:.2f} s ({_ratio(r['eq_quality_ratio'])})")
    return out


def part_orient(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """FN, FP and seconds of 1 and 2 runs with the first cube axis-aligned (the paper) and
    oblique (the core's default), per scene cell, against the dense ground truth."""
    from visibility.viewcells import ViewcellGrid

    core = _core()
    rows = []
    for label, loader in load_scenes(cfg["orient_scenes"]):
        scene = loader()
        if scene.n_triangles > 500_000:
            log(f"  [{label}] skipped: {scene.n_triangles} triangles (this part stays short)")
            continue
        grid = ViewcellGrid.for_scene(scene)
        cid = pick_cells(grid, 1)[0]
        cell = grid.cell(cid)
        gt, _ = _ground_truth(scene, cell, cfg, log, label)
        for runs in (1, 2):
            for first in ("axis", "oblique"):
                params = core.make_params(resolution=_part_res(cfg), runs=runs,
                                          first_orientation=first)
                pvs, secs = _timed(lambda s=scene, c=cell, p=params: core.compute(s, c, p), 1)
                fn, fp = _fn_fp(pvs.triangle_ids, gt)
                rows.append({"scene": label, "cell": cid, "runs": runs, "first": first,
                             "seconds": secs[0], "fn": fn, "fp": fp, "gt": int(len(gt))})
                log(f"  [{label}] runs {runs} first {first:>7}: {secs[0]:.2f} s FN "
                    f"{_pct(fn)} FP {_pct(fp)}")
    return rows


def _md_orient(rows, cfg) -> str:
    s = ["## First orientation: axis-aligned against oblique cubes\n",
         f"One cell per scene at {_part_res(cfg)} px, 3 eye levels, the dense ground truth of "
         "the per-scene "
         f"part ({cfg['gt_points']} points at {cfg['gt_resolution']} px). Long thin features "
         "parallel to a side (ledges, kerbs, roof lines) project to bands that slide along "
         "themselves as the eye moves; an axis-aligned cube on an axis-aligned scene can hold "
         "such a band between two pixel rows for the whole side, an oblique cube cannot. The "
         "core's default is oblique; the other parts of this report use the paper's "
         "axis-aligned first cube.\n",
         "| scene | cell | runs | axis s | axis FN % | axis FP % | oblique s | oblique FN % "
         "| oblique FP % |", "|---|---|---|---|---|---|---|---|---|"]
    by = {(r["scene"], r["runs"], r["first"]): r for r in rows}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for runs in (1, 2):
            a, o = by.get((scene, runs, "axis")), by.get((scene, runs, "oblique"))
            if a is None or o is None:
                continue
            s.append(f"| {scene} | {a['cell']} | {runs} | {a['seconds']:.2f} | "
                     f"{100 * a['fn']:.2f} | {100 * a['fp']:.2f} | {o['seconds']:.2f} | "
                     f"{100 * o['fn']:.2f} | {100 * o['fp']:.2f} |")
    return "\n".join(s) + "\n"


def part_city1m(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Seconds for one 4 x 4 m cell of city at 1M triangles at 256^2 per face, and its phases."""
    from visibility.generators import make_scene
    from visibility.viewcells import ViewcellGrid

    tri = int(cfg["city1m_triangles"])
    t0 = time.perf_counter()
    scene = make_scene("city", triangles=tri)
    log(f"  city {scene.n_triangles} triangles generated in {time.perf_counter() - t0:.1f} s")
    grid = ViewcellGrid.for_scene(scene, cell_size=4.0)
    res = _part_res(cfg)
    return _cell_rows(scene, grid, pick_cells(grid, cfg["city1m_cells"]),
                      [{"eye_levels": 3, "resolution": res}, {"eye_levels": 1, "resolution": res}],
                      cfg["repeats"], "city 1M", log)


#: Cut depths measured beside the default on scenes with near clutter (``grass``, ``kitchen``).
CUT_VARIANTS = [{}, {"cuts": 0}, {"cuts": 6}]


def _part_res(cfg: dict[str, Any]) -> int:
    """Pixels per cube face of the orient, city1m, grass and kitchen parts (the core's 256 px
    unless the preset says otherwise: the smoke test runs them small)."""
    return int(cfg.get("part_resolution", 256))


def part_grass(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Seconds for cells of ``grass`` (everything visible: the envelopes are the answer) at the
    core's defaults and other cut depths, and of ``swaying_grass`` (the same meadow moving
    along the segment) at the defaults, and the phases."""
    from visibility.generators import make_scene
    from visibility.viewcells import ViewcellGrid

    tri = int(cfg["grass_triangles"])
    rows = []
    # The swaying meadow moves, and moving geometry is never cut: the defaults only.
    for name, variants in (("grass", CUT_VARIANTS), ("swaying_grass", [{}])):
        scene = make_scene(name, triangles=tri)
        grid = ViewcellGrid.for_scene(scene)
        variants = [{"resolution": _part_res(cfg), **v} for v in variants]
        rows += _cell_rows(scene, grid, pick_cells(grid, cfg["grass_cells"], scene), variants,
                           cfg["repeats"], name, log)
    return rows


def part_kitchen(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Seconds for a 4 m cell of the 1M-triangle kitchen (``../shared/scenes``) at the core's
    defaults and other cut depths, one run each (minutes per run)."""
    from benchmarks.bench_matrix import SHARED_SCENES
    from visibility.loaders import load_scene
    from visibility.viewcells import ViewcellGrid

    path = SHARED_SCENES / "kitchen.glb"
    if not path.is_file():
        log(f"  no {path}: kitchen part skipped")
        return []
    scene = load_scene(path)
    grid = ViewcellGrid.for_scene(scene)
    cells = pick_cells(grid, 1, scene)
    core = _core()
    # Untimed: builds the scene's clusters, which the timed rows would otherwise include.
    core.compute(scene, grid.cell(cells[0]), core.make_params(resolution=16))
    variants = [{"resolution": _part_res(cfg), **v} for v in CUT_VARIANTS]
    return _cell_rows(scene, grid, cells, variants, 1, "kitchen", log, first_run=False)


def _cell_rows(scene, grid, cells, variants, repeats, label, log,
               first_run: bool = True) -> list[dict[str, Any]]:
    """One row per cell and parameter variant (``variants``: overrides of the core's defaults
    and of 256 px): median seconds of ``repeats`` runs, phases, counters, PVS size and, with
    ``first_run``, the memory of an untimed first run; then a row of ``sampling`` at its
    defaults on the same cell (after an untimed run), for scale."""
    from visibility.cores.base import get_core

    core = _core()
    sampling = get_core("sampling")
    rows = []
    for cid in cells:
        cell = grid.cell(cid)
        for over in variants:
            params = core.make_params(**{"resolution": 256, **over})
            peak = traced = None
            if first_run:
                # Untimed first run: cluster build and first touch; it also measures memory
                # (RSS rise, which sees numba's arrays, and tracemalloc's peak, which sees
                # numpy's; the later runs reuse pages, so their RSS rise says nothing).
                _, peak, traced = measure_peak(lambda c=cell, p=params: core.compute(scene, c, p))
            stats_all, secs = [], []
            for _k in range(repeats):
                pvs = core.compute(scene, cell, params)
                secs.append(pvs.seconds)
                stats_all.append(pvs.stats)
            med = int(np.argsort(secs)[len(secs) // 2])
            st = stats_all[med]
            row = {"scene": label, "cell": cid, "core": "from_segment",
                   "box": np.asarray(cell.box).tolist(),
                   "eye_levels": params.eye_levels, "cuts": params.cuts,
                   "first_orientation": params.first_orientation,
                   "segments": st.get("segments"), "seconds": float(np.median(secs)),
                   "seconds_all": secs, "peak_mib": peak, "traced_mib": traced, "pvs": len(pvs),
                   "pvs_pct": 100.0 * len(pvs) / scene.n_triangles,
                   "phases": {k: float(st.get(k, 0.0)) for k in
                              ("box_seconds", "bin_seconds", "envelope_seconds",
                               "setup_seconds")},
                   "counters": {k: v for k, v in st.items() if isinstance(v, int | np.integer)
                                and not k.endswith("seconds")}}
            rows.append(row)
            ph = row["phases"]
            c = row["counters"]
            log(f"  {label} cell {cid} (eye levels {params.eye_levels}, cuts {params.cuts}, "
                f"{row['segments']} segments, {c.get('splits', 0)} splits): "
                f"{row['seconds']:.2f} s median of {len(secs)} (box {ph['box_seconds']:.2f}, "
                f"bin {ph['bin_seconds']:.2f}, envelope {ph['envelope_seconds']:.2f}, setup "
                f"{ph['setup_seconds']:.2f}); envelope pixel pairs {c.get('pairs', 0)}, tile "
                f"items {c.get('tile_items', 0)}, tiles skipped as known "
                f"{c.get('tiles_known', 0)} of {c.get('tiles', 0)}; PVS {len(pvs)} "
                f"({row['pvs_pct']:.2f} %); first run RSS rise "
                f"{'?' if peak is None else f'{peak:.0f}'} MiB, traced peak "
                f"{'?' if traced is None else f'{traced:.0f}'} MiB")
        sp = sampling.make_params()
        sampling.compute(scene, cell, sp)
        runs = [sampling.compute(scene, cell, sp) for _k in range(repeats)]
        secs = [r.seconds for r in runs]
        pvs = runs[int(np.argsort(secs)[len(secs) // 2])]
        rows.append({"scene": label, "cell": cid, "core": "sampling", "seconds_all": secs,
                     "seconds": float(np.median(secs)), "pvs": len(pvs),
                     "pvs_pct": 100.0 * len(pvs) / scene.n_triangles, "phases": {},
                     "counters": {}, "peak_mib": None, "traced_mib": None})
        log(f"  {label} cell {cid} sampling (defaults): {rows[-1]['seconds']:.2f} s median of "
            f"{len(secs)}; PVS {len(pvs)} ({rows[-1]['pvs_pct']:.2f} %)")
    return rows


# --------------------------------------------------------------------------- report
def _f(x: Any, spec: str = ".3f") -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return format(x, spec)


def write_report(results: dict[str, Any], cfg: dict[str, Any], command: str, wall: float,
                 out_dir: Path, merge: bool = False) -> Path:
    """Markdown tables, PNG plots and the raw JSON under ``out_dir``; returns the .md path.

    Each part keeps its own provenance (command, wall time, load average at its start and end),
    so with ``merge`` the parts of this run replace the same parts of the report already there
    (same preset) and the others stay: a timing part can be rerun alone on a quiet machine.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    tag = "" if cfg["preset"] == "standard" else f"_{cfg['preset']}"
    raw_path = out_dir / f"from_segment{tag}.json"
    parts: dict[str, Any] = {}
    if merge and raw_path.is_file():
        try:
            parts = json.loads(raw_path.read_text()).get("parts", {})
        except (OSError, ValueError):
            parts = {}
    meta = {"command": command, "wall_seconds": wall, "load_start": cfg["load_start"],
            "load_end": _load(), "machine": machine_description(), "config": cfg}
    for name, rows in results.items():
        parts[name] = {"meta": meta, "rows": rows}
    raw_path.write_text(json.dumps({"preset": cfg["preset"], "parts": parts}, indent=1,
                                   default=_jsonable))
    md = ["# `from_segment` benchmarks (Popescu et al. 2024, Sec. 4.4-4.5)\n",
          f"Preset `{cfg['preset']}`. Each part says the command that measured it, its wall "
          "time and the load average (1 min) at its start and end; times are wall seconds "
          "on that machine under that load. The paper's experiments (per scene, one segment, "
          "a cell, the view rectangle) use the paper's axis-aligned first cube; the core's "
          "default first cube is oblique (see 'First orientation'), and the 1M-city timing runs "
          "the core as the server does.\n"]
    writers = {"city1m": lambda rows, c: _md_city1m(rows, c),
               "grass": lambda rows, c: _md_grass(rows, c),
               "kitchen": lambda rows, c: _md_kitchen(rows, c),
               "segment": lambda rows, c: _md_segment(rows, out_dir, tag),
               "cell": lambda rows, c: _md_cell(rows, c, out_dir, tag),
               "rect": lambda rows, c: _md_cell(rows, c, out_dir, tag, flat=True),
               "orient": lambda rows, c: _md_orient(rows, c),
               "scenes": lambda rows, c: _md_scenes(rows, c, out_dir, tag)}
    for name in PARTS:
        if name not in parts:
            continue
        m = parts[name]["meta"]
        body = writers[name](parts[name]["rows"], m["config"])
        head, _, rest = body.partition("\n")
        md.append(f"{head}\n\nCommand: `{m['command']}` (part wall time "
                  f"{m['wall_seconds'] / 60:.1f} min).  \nMachine: {m['machine']}. Load average "
                  f"at start {m['load_start']}, at end {m['load_end']}.\n{rest}")
    path = out_dir / f"from_segment{tag}.md"
    path.write_text("\n".join(md))
    return path


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


#: How the timed cell parts (``_cell_rows``) measure, for their reports.
_REPEATS_NOTE = (
    "Median of repeats after one untimed run (cluster build, first touch) that measures memory: "
    "its RSS rise (numba's arrays included; pages already held do not count) and tracemalloc's "
    "peak (numpy arrays and Python objects). ")
_LEVELS_NOTE = (
    "Eye levels 3 is the default (sides at the bottom, middle and top of the eye-height range: "
    "12 segments x 6 faces); 1 walks the sides at mid height only. ")


def _md_city1m(rows, cfg) -> str:
    return _md_cells(
        rows, f"One 4 x 4 m cell of `city` at {cfg['city1m_triangles']:,} triangles, "
        f"{_part_res(cfg)}² per face",
        "The server's prefetch budget: at 1.4 m/s a walker crosses a 4 m cell in about 2.9 s. "
        + _REPEATS_NOTE + _LEVELS_NOTE)


def _md_grass(rows, cfg) -> str:
    return _md_cells(
        rows, f"Cells of `grass` at {cfg['grass_triangles']:,} triangles, {_part_res(cfg)}² per "
        "face",
        "A meadow where every blade is seen, still (`grass`) and swaying as the eye walks "
        "(`swaying_grass`: moving triangles, never cut): the envelopes are the answer, and the "
        "segments "
        "after the first find little new (`tiles_known`: screen tiles whose primitives were all "
        "marked visible already, not resolved). Cut depths beside the default (`cuts`: sides "
        "halved where near geometry sweeps the cube; splits: halvings made). " + _REPEATS_NOTE)


def _md_kitchen(rows, cfg) -> str:
    return _md_cells(
        rows, f"A 4 m cell of the 1M-triangle kitchen, {_part_res(cfg)}² per face",
        "Dense clutter along every side: the case `cuts` was made for. One timed run per row "
        "(the rows take minutes), after an untimed run at 16 px that builds the scene's "
        "clusters; no memory figures. ")


def _md_cells(rows, title, lead) -> str:
    s = [f"## {title}\n",
         lead + "The core's default parameters otherwise (first cube "
         f"{rows[0].get('first_orientation', 'axis') if rows else '?'}), as the server runs "
         "it.\n",
         "| scene | cell | core | eye levels | cuts (splits) | segments | seconds median (all) "
         "| box | bin | envelope | setup | PVS | PVS % | pixel pairs | tiles skipped as known "
         "| first-run RSS rise MiB | traced peak MiB |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ph = r["phases"]
        c = r["counters"]
        known = (f"{c['tiles_known']:,} of {c['tiles']:,}" if "tiles_known" in c else "–")
        cuts = f"{r['cuts']} ({c.get('splits', 0)})" if "cuts" in r else "–"
        pairs = f"{c['pairs']:,}" if "pairs" in c else "–"
        s.append(f"| {r.get('scene', '–')} | {r['cell']} | {r.get('core', 'from_segment')} | "
                 f"{r.get('eye_levels', '–')} | {cuts} | {r.get('segments', '–')} | "
                 f"{r['seconds']:.2f} ({', '.join(f'{x:.2f}' for x in r['seconds_all'])}) | "
                 + " | ".join(_f(ph.get(k), ".2f") for k in
                              ("box_seconds", "bin_seconds", "envelope_seconds",
                               "setup_seconds"))
                 + f" | {r['pvs']:,} | {r['pvs_pct']:.2f} | "
                 f"{pairs} | {known} | "
                 f"{_f(r['peak_mib'], '.0f')} | {_f(r.get('traced_mib'), '.0f')} |")
    return "\n".join(s) + "\n"


def _md_segment(rows, out_dir: Path, tag: str) -> str:
    png = out_dir / f"from_segment_segment{tag}.png"
    _plot_curves(rows, png, "segment")
    s = ["## One segment: from-segment against from-point sampling (Sec. 4.5.1)\n",
         "One side of a cell at mid eye height; both methods use the axis-aligned cube at the "
         "same face resolution. From-point views are placed along the segment in van der Corput "
         "order (every prefix evenly spread); the dense ground truth is the union of all of them. "
         f"Target: from-segment reaches ≥ {TARGET_COMPLETENESS:.1%} of it at least "
         f"{TARGET_RATIO:g}x faster than from-point sampling reaches the same share.\n",
         "| scene | res | from-segment s | its share of dense GT | found outside GT | GT views "
         "(s) | from-point views for equal share | their s | ratio | from-point share in "
         "equal time | target met |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s.append(f"| {r['scene']} | {r['resolution']} | {r['fs_seconds']:.3f} | "
                 f"{r['fs_completeness']:.2%} | {r['fs_outside_gt']} | {r['points']} "
                 f"({r['fp_seconds_all']:.1f}) | "
                 f"{r['equal_quality_points'] if r['equal_quality_points'] > 0 else 'not reached'}"
                 f" | {_f(r['equal_quality_seconds'], '.2f')} | {_ratio(r['ratio'])} | "
                 f"{r['equal_time_completeness']:.2%} ({r['equal_time_points']} views) | "
                 f"{'yes' if r['meets_target'] else 'no'} |")
    rel = png.name
    return "\n".join(s) + f"\n\n![segment experiment]({rel})\n"


def _md_cell(rows, cfg, out_dir: Path, tag: str, flat: bool = False) -> str:
    png = out_dir / f"from_segment_{'rect' if flat else 'cell'}{tag}.png"
    _plot_curves(rows, png, "cell")
    if flat:
        head = ("## The paper's view rectangle: jittered from-segment runs against from-point "
                "sampling (Sec. 4.5.2)\n")
        where = ("The region is the cell's XZ square at its mid eye height (a view rectangle, "
                 "as in the paper): from-segment walks its 4 sides with `runs` cube "
                 "orientations (identity, then random); from-point renders one random cube from "
                 "each of stratified random points of the rectangle; the ground truth samples "
                 "the rectangle too.")
    else:
        head = "## A cell: jittered from-segment runs against from-point sampling (Sec. 4.5.2)\n"
        where = ("From-segment walks the cell's perimeter (3 eye levels) with `runs` cube "
                 "orientations (identity, then random); from-point renders one random cube "
                 "from each of stratified random points of the cell.")
    s = [head, where + " Both at the resolution in the table, both report only "
         "triangles seen at some pixel centre, so everything found is visible: completeness is "
         "the share of the *known visible* set (the union of both methods' finds and the dense "
         f"ground truth, {cfg['gt_points']} points at {cfg['gt_resolution']} px), as the paper "
         "counts visible triangles found (Figs. 8-9); the share of the sampled ground truth "
         "alone is given too. 'For as many' = the from-point time to find as many visible "
         "triangles as from-segment did.\n",
         "| scene | res | runs | from-segment s | found | share of known | share of GT | "
         "from-point share of known in equal time (views) | from-point s for as many (views) "
         "| ratio |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for r in row["fs"]:
            eqp = r["eq_quality_points"]
            s.append(f"| {row['scene']} | {row['resolution']} | {r['runs']} | "
                     f"{r['seconds']:.2f} | {r['found']} | {r['completeness']:.2%} | "
                     f"{r['gt_share']:.2%} | "
                     f"{r['eq_time_completeness']:.2%} ({r['eq_time_points']}) | "
                     f"{_f(r['eq_quality_seconds'], '.2f')} "
                     f"({eqp if eqp > 0 else 'not reached in ' + str(row['fp_points'])}) | "
                     f"{_ratio(r['eq_quality_ratio'])} |")
        s.append(f"| {row['scene']} | | from-point, all {row['fp_points']} views | "
                 f"{row['fp_seconds']:.2f} | | {row['fp_completeness']:.2%} | "
                 f"{row['fp_gt_share']:.2%} | | | |")
    return "\n".join(s) + f"\n\n![cell experiment]({png.name})\n"


def _md_scenes(rows, cfg, out_dir: Path, tag: str) -> str:
    png = out_dir / f"from_segment_scenes{tag}.png"
    _plot_scenes(rows, png)
    s = ["## Per scene: error against run time over resolution and jitter runs\n",
         f"One cell per scene (`pick_cells`), ground truth {cfg['gt_points']} points at "
         f"{cfg['gt_resolution']} px ('GT last batch' = share of the ground truth its last batch "
         "of 8 views added: how far from saturation it is). FN = share of the ground truth "
         "missing from the PVS, FP = share of the PVS outside it (a sampled ground truth misses "
         "slivers, so part of FP is truly visible). One timed run per point after warm-up; a point "
         "whose time, projected from the points measured before it (x4 per resolution doubling, "
         "x runs), "
         f"exceeds {cfg['max_seconds']} s is skipped and says so.\n",
         "| scene | triangles | cell | res | runs | seconds | PVS % | FN % | FP % | GT size | "
         "GT last batch | spheres FN % | spheres FP % |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r:
            s.append(f"| {r['scene']} | {r['triangles']} | {r['cell']} | {r['resolution']} | "
                     f"{r['runs']} | skipped: projected {r['skipped']:.0f} s > "
                     f"{cfg['max_seconds']} s | | | | | | | |")
            continue
        s.append(f"| {r['scene']} | {r['triangles']} | {r['cell']} | {r['resolution']} | "
                 f"{r['runs']} | {r['seconds']:.3f} | {r['pvs_pct']:.2f} | "
                 f"{_f(_x100(r['fn']), '.2f')} | {_f(_x100(r['fp']), '.2f')} | {r['gt']} | "
                 f"{_f(_x100(r.get('gt_last_new')), '.2f')} % | "
                 f"{_f(_x100(r.get('sphere_fn')), '.2f')} | "
                 f"{_f(_x100(r.get('sphere_fp')), '.2f')} |")
    return "\n".join(s) + f"\n\n![per scene]({png.name})\n"


def _x100(x):
    return None if x is None else 100.0 * x


def _plot_curves(rows, path: Path, kind: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 3.6 * len(rows)), squeeze=False)
    for ax_row, r in zip(axes, rows, strict=True):
        a, b = ax_row
        a.semilogx(r["curve_points"], np.asarray(r["curve_completeness"]) * 100, "-",
                   label="from-point sampling")
        b.semilogx(r["curve_seconds"], np.asarray(r["curve_completeness"]) * 100, "-",
                   label="from-point sampling")
        if kind == "segment":
            a.axhline(r["fs_completeness"] * 100, color="C3", ls="--",
                      label=f"from-segment (1 run, {r['fs_seconds']:.2f} s)")
            b.plot([r["fs_seconds"]], [r["fs_completeness"] * 100], "o", color="C3",
                   label="from-segment")
            a.set_xlabel("from-point views along the segment")
        else:
            fs = r["fs"]
            a.plot([x["runs"] for x in fs], [x["completeness"] * 100 for x in fs], "o-",
                   color="C3", label="from-segment (runs on the perimeter)")
            b.plot([x["seconds"] for x in fs], [x["completeness"] * 100 for x in fs], "o-",
                   color="C3", label="from-segment")
            a.set_xlabel("runs (from-point: views; from-segment: cube orientations)")
        b.set_xlabel("seconds")
        for ax in (a, b):
            ax.set_ylabel("% of dense ground truth" if kind == "segment"
                          else "% of known visible triangles")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8, loc="lower right")
        a.set_title(f"{r['scene']} ({r['triangles']} tris), {r['resolution']}² per face")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_scenes(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, ax = plt.subplots(figsize=(9, 5.5))
    for k, name in enumerate(scenes):
        sr = [r for r in rows if r["scene"] == name and r.get("fn") is not None]
        for res in sorted({r["resolution"] for r in sr}):
            pts = sorted((r["seconds"], 100 * r["fn"]) for r in sr if r["resolution"] == res)
            if pts:
                x, y = zip(*pts, strict=True)
                ax.loglog(x, np.maximum(y, 1e-3), "o-", color=f"C{k % 10}",
                          alpha=0.4 + 0.6 * res / max(r["resolution"] for r in sr),
                          label=f"{name} @{res}")
    ax.set_xlabel("seconds per cell")
    ax.set_ylabel("FN % against the dense ground truth")
    ax.set_title("from_segment: error against run time (points along a line: 1, 2, 4, 8 runs)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_segment",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="a smoke run (a minute or two)")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    p.add_argument("--scenes", nargs="+", help="scenes of the 'scenes' part (name:triangles, "
                   "'real', or files)")
    p.add_argument("--out", type=Path, default=RESULTS_DIR, help="results folder")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the chosen parts, print their tables, write the report. Returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    preset = "quick" if args.quick else "standard"
    cfg = dict(PRESETS[preset], preset=preset, load_start=_load())
    if args.scenes:
        cfg["scenes"] = args.scenes
    command = "python -m benchmarks.bench_segment " + shlex.join(argv)
    print(f"{command}\n{machine_description()}", flush=True)
    t0 = time.perf_counter()
    _warm_up()
    log = lambda s: print(s, flush=True)  # noqa: E731
    runners = {"city1m": part_city1m, "grass": part_grass, "kitchen": part_kitchen,
               "segment": part_segment,
               "cell": part_cell, "rect": part_rect, "orient": part_orient,
               "scenes": part_scenes}
    path = None
    for part in PARTS:
        if part in args.parts:
            print(f"== {part}", flush=True)
            cfg["load_start"] = _load()
            p0 = time.perf_counter()
            rows = runners[part](cfg, log)
            # Written after every part: a long run stopped half-way keeps what it measured.
            path = write_report({part: rows}, cfg, command, time.perf_counter() - p0, args.out,
                                merge=True)
    print(f"wrote {path} in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
