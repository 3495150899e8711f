"""``pvs bench``: error against run time for every registered core, side by side, on the same cells.

The matrix is every core of ``visibility.cores.base.available_cores()`` (plus the Embree ray-caster
peer of ``benchmarks.peers``) x its accuracy knob x cell sizes x scenes. Per point: seconds (median
of repeats, min, max), peak memory, PVS size (% of the scene's valid triangles), FN and FP rates
against a dense sampled ground truth (cached on disk, ``benchmarks.gt_cache``), and frame metrics
(mean and worst ε, mean PSNR and SSIM) over a fixed set of views inside the cell, rendered with
``client.render.OffscreenRenderer`` (PVS subset against the full scene).

Peak memory is measured twice in one untimed run before the timed repeats: the peak of the
allocations tracemalloc sees (Python objects and numpy arrays, including memory the allocator
reuses) and the rise of the process's peak resident set (``VmHWM``, reset by writing 5 to
/proc/self/clear_refs) over its resident set at the start (sees numba and GL allocations too, but
not pages the process already held).

Scenes with spheres get sphere FN/FP too (``PVS.sphere_ids`` against ``GroundTruth.sphere_ids``);
a core or peer that reports no sphere ids reads "n/a".

A core's knob and its levels are its own declaration (``Core.knob``, ``Core.knob_levels``): a new
core joins with no change here.

Usage: ``pvs bench --quick`` (minutes), ``pvs bench --preset medium`` (the published
BENCHMARKS.md, about half an hour on 2 cores), ``pvs bench --preset full``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

from client.metrics import PSNR_CAP_DB  # noqa: E402
from visibility.cancel import CancelToken  # noqa: E402
from visibility.viewcells import spread_evenly  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENES = REPO.parent / "shared" / "scenes"
RESULTS_DIR = REPO / "benchmarks" / "results"

#: Viewpoint counts of the ray-caster peer (ascending cost). A core's knob and its levels are
#: its own declaration (``Core.knob``, ``Core.knob_levels``); a preset's ``knob_levels`` may
#: replace the levels of a knob by name for a cheaper run.
PEER_LEVELS: list[int] = [8, 32, 128]

#: Every generator except ``stress`` (a test scene: a few hundred stiff-case triangles plus random
#: clutter, whose known answers ``visibility.cores.checks`` checks), at two sizes.
#: For ``spheres`` the size is the sphere count. Meadows and moving scenes are smaller: there
#: everything is visible and ``from_segment`` resolves every triangle at every pixel it
#: sweeps, per keyframe interval (BENCHMARKS.md has its times).
GENERATOR_SCENES_MEDIUM = [
    "city:20000", "city:100000", "village:20000", "village:100000", "rooms:20000",
    "rooms:100000", "grass:2000", "grass:10000", "swaying_grass:1000", "swaying_grass:2000",
    "spheres:50", "spheres:200",
]

# Presets: ``peer_repeats`` is the repeats of the equal-time / equal-completeness peer points
# (their time is the reference's by construction, or set by a deterministic sample count);
# ``peer_cap`` is (seconds, factor) of the equal-completeness cap.
PRESETS: dict[str, dict[str, Any]] = {
    "quick": {
        "scenes": ["rooms:5000"], "cell_sizes": [None], "cells": 1, "repeats": 1,
        "peer_repeats": 1, "levels": 2, "gt_points": 32, "gt_resolution": 64, "views": 2,
        "view_size": 64, "resolution": 64, "peer_cap": [10.0, 10.0],
        "knob_levels": {"samples": [4, 16], "resolution": [32, 64], "runs": [1, 2],
                        "delta": [0.5, 0.25]},
    },
    "medium": {
        "scenes": GENERATOR_SCENES_MEDIUM + ["real"],
        "cell_sizes": [None, "x2"], "cells": 1, "repeats": 3, "peer_repeats": 1, "levels": 2,
        "gt_points": 256, "gt_resolution": 128, "views": 4, "view_size": 96, "resolution": 64,
        "peer_cap": [20.0, 3.0],
        "knob_levels": {"samples": [8, 32], "resolution": [32, 64], "runs": [1, 2]},
    },
    "full": {
        "scenes": ["city:100000", "village:100000", "rooms:100000", "city:1000000",
                   "village:1000000", "rooms:1000000", "grass:200000", "grass:1000000",
                   "swaying_grass:100000", "swaying_grass:500000", "spheres:2000",
                   "spheres:20000", "real"],
        "cell_sizes": [None, "x2"], "cells": 4, "repeats": 3, "peer_repeats": 3, "levels": 3,
        "gt_points": 1024, "gt_resolution": 512, "views": 8, "view_size": 256,
        "resolution": 256, "peer_cap": [60.0, 50.0], "knob_levels": {},
    },
}


# --------------------------------------------------------------------------- measurements
def _status_kib(field: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def measure_peak(fn, traced: bool = True):
    """Run ``fn()``; return (its result, RSS peak rise MiB or None, traced peak MiB or None).

    RSS: ``VmHWM`` after the run minus ``VmRSS`` before it, with ``VmHWM`` reset through
    /proc/self/clear_refs (None where that is impossible); it sees every allocation (numba, GL)
    but only as far as it needs pages the process did not hold already. Traced: the peak of
    tracemalloc's count during the run (numpy arrays and Python objects, reused memory
    included; not numba's own allocations), None when ``traced`` is false or tracing was
    already on. tracemalloc slows allocation, so callers do not time this run.
    """
    import tracemalloc

    try:
        Path("/proc/self/clear_refs").write_text("5")
        base = _status_kib("VmRSS")
    except OSError:
        base = None
    started = traced and not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    try:
        out = fn()
        traced_mib = tracemalloc.get_traced_memory()[1] / 2**20 if started else None
    finally:
        if started:
            tracemalloc.stop()
    peak = _status_kib("VmHWM")
    rss = None if base is None or peak is None else max(0.0, (peak - base) / 1024.0)
    return out, rss, traced_mib


def _load() -> str:
    try:
        return f"{os.getloadavg()[0]:.1f}"
    except OSError:
        return "?"


def machine_description() -> str:
    """One paragraph naming the CPU, cores, memory, OS and library versions."""
    import numba

    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = _meminfo_gib()
    return (f"{cpu}, {os.cpu_count()} logical cores, {mem} GiB RAM, {gpu_description()} (cores "
            f"run on the CPU; frames with Mesa OSMesa); {platform.system()} {platform.release()}; "
            f"Python {platform.python_version()}, numpy {np.__version__}, "
            f"numba {numba.__version__}")


def gpu_description() -> str:
    """The GPUs ``nvidia-smi`` lists ("GPU: name, memory; ..."), or "no GPU" when it is absent
    or lists none."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return "no GPU"
    try:
        out = subprocess.run([exe, "--query-gpu=name,memory.total", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return "no GPU (nvidia-smi present but failed)"
    gpus = [ln.strip() for ln in out.splitlines() if ln.strip()]
    return "GPU: " + "; ".join(gpus) if gpus else "no GPU"


def last_batch_share(rec: dict) -> float | None:
    """Share of a ground truth's triangles that its last batch of viewpoints added (0 =
    saturated at that density), from the ``convergence`` record of ``sample_pvs``."""
    conv = rec.get("convergence") or []
    if not conv or conv[-1][1] <= 0:
        return None
    return conv[-1][2] / conv[-1][1]


def _meminfo_gib() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return f"{int(line.split()[1]) / 2**20:.0f}"
    except OSError:
        pass
    return "?"


# --------------------------------------------------------------------------- matrix pieces
def knob_levels(core, preset_levels: dict[str, list[Any]], count: int) -> list[Any]:
    """The first ``count`` levels of a core's declared knob (``[None]`` without a knob): the
    preset's levels for that knob name when it names them, else the core's own."""
    if core.knob is None:
        return [None]
    return list(preset_levels.get(core.knob) or core.knob_levels)[:count]


def load_scenes(specs: list[str]) -> list[tuple[str, Any]]:
    """(label, loader) pairs for ``name:triangles`` generator specs, ``real`` (every scene in
    ../shared/scenes/) and paths to scene files. Loaders are called lazily, one scene at a time."""
    out: list[tuple[str, Any]] = []
    for spec in specs:
        if spec == "real":
            for p in sorted(SHARED_SCENES.glob("*.glb")):
                out.append((p.stem, _file_loader(p)))
        elif Path(spec).suffix and Path(spec).exists():
            out.append((Path(spec).stem, _file_loader(Path(spec))))
        else:
            name, _, tri = spec.partition(":")
            triangles = int(float(tri)) if tri else None
            label = f"{name}_{_short(triangles)}" if triangles else name
            out.append((label, _gen_loader(name, triangles)))
    return out


def _short(n: int) -> str:
    if n < 1000:
        return str(n)  # sphere counts: 50 and 200 must not both read "0k"
    return f"{n // 1_000_000}M" if n % 1_000_000 == 0 else f"{n // 1000}k"


def _file_loader(path: Path):
    def load():
        from visibility.loaders import load_scene

        return load_scene(path)

    return load


def _gen_loader(name: str, triangles: int | None):
    def load():
        from visibility.generators import make_scene

        return make_scene(name, triangles=triangles)

    return load


def pick_cells(grid, k: int, scene=None) -> list[int]:
    """``k`` cell ids spread evenly over the grid's id order (deterministic).

    With ``scene``, only cells whose centre lies inside the scene's bounding box (X and Z) are
    candidates when there are any: a grid over a scene without a walk area (kitchen) overhangs
    it, and a cell mostly outside the room measures little.
    """
    n = len(grid)
    if n == 0:
        return []
    ids = np.arange(n)
    if scene is not None:
        valid = scene.vertices[np.unique(scene.faces[scene.valid_faces])]
        if len(valid):
            lo, hi = valid.min(axis=0), valid.max(axis=0)
            c = np.array([np.asarray(grid.cell(int(i)).box).mean(axis=0) for i in ids])
            inside = ((c[:, 0] >= lo[0]) & (c[:, 0] <= hi[0]) & (c[:, 2] >= lo[2])
                      & (c[:, 2] <= hi[2]))
            if inside.any():
                ids = ids[inside]
    return spread_evenly(ids, k) or [int(ids[0])]


#: Candidate eyes per kept view, and the id-buffer size used to score their directions.
VIEW_CANDIDATES = 3
VIEW_SCORE_RESOLUTION = 32
#: Pitch of every view (radians, down): horizon a little above the centre.
VIEW_PITCH = -0.15


def view_set(scene, cell, n: int, seed: int = 777) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` fixed (eye, forward) views inside a cell, each looking where geometry is.

    ``VIEW_CANDIDATES * n`` stratified eyes in the cell each get four horizontal directions (a
    cube turned by a random yaw, ``render_cubemap_ids`` at ``VIEW_SCORE_RESOLUTION`` px, rest
    state); a direction scores the number of distinct triangles its face shows (ties: more
    pixels covered). Each eye keeps
    its best direction and the ``n`` best eyes are kept, so no view stares into the void (an
    eye outside a room looks at its outside wall rather than away from it). Deterministic.
    """
    from visibility.ground_truth import sample_points
    from visibility.raster import render_cubemap_ids

    rng = np.random.default_rng(seed)
    eyes = sample_points(cell.box, VIEW_CANDIDATES * n, rng)
    # The four cube faces whose forward is horizontal (+X, -X, +Z, -Z in cube coordinates).
    horizontal = [k for k in range(6) if abs(_CUBE_FORWARD[k][1]) < 0.5]
    picks = []
    for eye in eyes:
        yaw = rng.uniform(0.0, 2 * np.pi)
        c, sn = np.cos(yaw), np.sin(yaw)
        base = np.array([[c, 0.0, -sn], [0.0, 1.0, 0.0], [sn, 0.0, c]])  # world-to-cube
        ids = render_cubemap_ids(scene.vertices, scene.faces, eye, VIEW_SCORE_RESOLUTION, base,
                                 face_mask=scene.valid_faces)
        # Distinct triangles, ties broken by the share of pixels covered.
        scores = [len(np.unique(ids[k][ids[k] >= 0])) + float(np.mean(ids[k] >= 0)) / 2
                  for k in horizontal]
        best = horizontal[int(np.argmax(scores))]
        fwd = base.T @ _CUBE_FORWARD[best]  # the face's forward in world coordinates
        fwd = np.array([fwd[0] * np.cos(VIEW_PITCH), np.sin(VIEW_PITCH),
                        fwd[2] * np.cos(VIEW_PITCH)])
        picks.append((max(scores), eye, fwd))
    order = sorted(range(len(picks)), key=lambda i: -picks[i][0])[:n]
    return [(picks[i][1], picks[i][2]) for i in sorted(order)]


def _cube_forward() -> np.ndarray:
    from visibility.raster.camera import cube_face_rotations

    return -cube_face_rotations()[:, 2, :]  # rows are right, up, back


_CUBE_FORWARD = _cube_forward()


def pvs_geometry(scene, ids, sphere_ids) -> tuple[np.ndarray, np.ndarray]:
    """Triangles and colours of a PVS for the renderer (rest state), its spheres as icospheres
    (none when ``sphere_ids`` is None: the core reports no spheres)."""
    from client.render import scene_sphere_centers, sphere_triangles

    ids = np.asarray(ids, dtype=np.int64)
    tris, cols = scene.triangles(ids), scene.colors[ids]
    if scene.n_spheres and sphere_ids is not None and len(sphere_ids):
        s = np.asarray(sphere_ids, dtype=np.int64)
        st, sc = sphere_triangles(scene_sphere_centers(scene, None)[s], scene.sphere_radii[s],
                                  scene.sphere_colors[s])
        tris, cols = np.concatenate([tris, st]), np.concatenate([cols, sc])
    return tris, cols


def frame_summary(renderer, scene, ids, views, gt_frames, key,
                  sphere_ids=None) -> dict[str, float]:
    """Mean and worst ε, mean PSNR (capped) and mean SSIM of the PVS frames over the views."""
    from client.metrics import capped_psnr, frame_metrics

    tris, cols = pvs_geometry(scene, ids, sphere_ids)
    eps, ps, ss = [], [], []
    for k, ((eye, fwd), gt) in enumerate(zip(views, gt_frames, strict=True)):
        fr = renderer.render(tris, cols, eye, fwd, key="bench_pvs", version=(key, k))
        m = frame_metrics(fr, gt)
        eps.append(m["epsilon"])
        ps.append(m["psnr"])
        ss.append(m["ssim"])
    renderer.drop("bench_pvs")
    return {"eps_mean": float(np.mean(eps)), "eps_worst": float(np.max(eps)),
            "psnr_mean": float(np.mean(capped_psnr(np.array(ps)))), "ssim_mean": float(np.mean(ss))}


# --------------------------------------------------------------------------- running
def run_matrix(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    """Run the whole matrix described by ``cfg``; return one row per (scene, cell, core, level)."""
    from benchmarks import peers
    from benchmarks.gt_cache import cached_ground_truth, scene_fingerprint
    from client.render import OffscreenRenderer
    from visibility.cores.base import available_cores, get_core
    from visibility.ground_truth import fn_fp_rates
    from visibility.viewcells import ViewcellGrid

    cores = cfg["cores"] or available_cores()
    levels_by_knob = _levels_by_knob(cfg)
    use_peer = cfg["peer"] and peers.available()
    if cfg["peer"] and not use_peer:
        log("embreex is not installed: the ray-caster peer is skipped")
    rows: list[dict[str, Any]] = []
    renderer = OffscreenRenderer(cfg["view_size"], cfg["view_size"], yfov_deg=90.0)
    try:
        for label, load in load_scenes(cfg["scenes"]):
            t0 = time.perf_counter()
            try:
                scene = load()
            except (ValueError, KeyError, OSError) as exc:
                # An hour-long run goes on without the scene and the report says so.
                log(f"[{label}] NOT measured: it failed to load: {exc}")
                cfg.setdefault("load_errors", []).append(f"{label}: {exc}")
                continue
            fp = scene_fingerprint(scene)
            n_valid = max(1, int(scene.valid_faces.sum()))
            # A core made for other scenes (2.5D only) is refused once, with its reason.
            fitting = []
            for name in cores:
                fit = get_core(name).fit(scene)
                if fit.ok:
                    fitting.append(name)
                else:
                    rows.append({"scene": label, "triangles": scene.n_triangles,
                                 "spheres": scene.n_spheres, "cell_size": None, "cell": None,
                                 "core": name, "knob": "-", "level": None,
                                 "refused": fit.why})
                    log(f"[{label}] {name} does not fit: {fit.why}")
            if not fitting:
                continue
            log(f"[{label}] {scene.n_triangles} triangles, loaded in "
                f"{time.perf_counter() - t0:.1f} s")
            for cs in cfg["cell_sizes"]:
                grid = ViewcellGrid.for_scene(scene, None)
                if cs == "x2":
                    grid = ViewcellGrid.for_scene(scene, 2 * grid.cell_size)
                elif cs is not None:
                    grid = ViewcellGrid.for_scene(scene, float(cs))
                for cid in pick_cells(grid, cfg["cells"], scene):
                    cell = grid.cell(cid)
                    base = {"scene": label, "triangles": scene.n_triangles,
                            "spheres": scene.n_spheres,
                            "cell_size": float(grid.cell_size), "cell": cid}
                    gt_ids, gt_rec = cached_ground_truth(
                        scene, cell, cfg["gt_points"], cfg["gt_resolution"],
                        cache_dir=cfg["cache_dir"], fingerprint=fp)
                    gt_spheres = gt_rec["sphere_ids"]
                    share = last_batch_share(gt_rec)
                    log(f"  cell {cid} ({grid.cell_size:g} m): ground truth {len(gt_ids)} "
                        f"triangles, {len(gt_spheres)} spheres, last batch added "
                        f"{_fmt(None if share is None else 100 * share, '.2f')} % "
                        f"({'cached' if gt_rec['cached'] else 'computed'} "
                        f"{gt_rec['seconds']:.1f} s)")
                    views = view_set(scene, cell, cfg["views"])
                    gt_frames = [renderer.render_scene(scene, e, f) for e, f in views]
                    jobs = _jobs(fitting, levels_by_knob, cfg, use_peer)
                    for job in jobs:
                        row = dict(base, gt_triangles=int(len(gt_ids)),
                                   gt_spheres=int(len(gt_spheres)), gt_last_batch=share,
                                   gt_seconds=gt_rec["seconds"], **job["row"])
                        reps = cfg["repeats"] if job["kind"] in ("core", "peer") else cfg.get(
                            "peer_repeats", cfg["repeats"])
                        try:
                            res = _run_point(job, scene, cell, reps, rows, label, cid, gt_ids,
                                             cfg.get("peer_cap"), float(grid.cell_size))
                        except Exception as exc:  # a failing core is a finding, not a stop
                            row["error"] = f"{type(exc).__name__}: {exc}"
                            log(f"    {row['core']} {row['knob']}={row['level']}: {row['error']}")
                            rows.append(row)
                            continue
                        if res is None:
                            continue
                        ids, sids, secs, peak, traced, extra = res
                        fn, fp_rate = fn_fp_rates(ids, gt_ids)
                        row.update(seconds_median=float(np.median(secs)),
                                   seconds_min=float(np.min(secs)),
                                   seconds_max=float(np.max(secs)), repeats=len(secs),
                                   peak_mib=peak, peak_traced_mib=traced,
                                   pvs=int(len(ids)), pvs_pct=100.0 * len(ids) / n_valid,
                                   fn=fn, fp=fp_rate, **extra)
                        if scene.n_spheres:
                            # None: the core or peer reports no spheres ("n/a", not 100 % FN).
                            sfn, sfp = (None, None) if sids is None else fn_fp_rates(
                                sids, gt_spheres)
                            row.update(sphere_fn=sfn, sphere_fp=sfp,
                                       pvs_spheres=None if sids is None else int(len(sids)))
                        row.update(frame_summary(renderer, scene, ids, views, gt_frames,
                                                 (row["core"], row["level"], cid), sids))
                        rows.append(row)
                        log(f"    {row['core']:>14} {row['knob']}={row['level']!s:<6} "
                            f"{row['seconds_median']:8.3f} s  FN {100 * fn:6.2f}%  "
                            f"FP {100 * fp_rate:6.2f}%  eps {row['eps_mean']:.3f}%")
            renderer.drop("__scene_static__")
            renderer.drop("__scene_dynamic__")
            del scene
    finally:
        renderer.close()
    return rows


def _jobs(cores, levels_by_knob, cfg, use_peer) -> list[dict[str, Any]]:
    from visibility.cores.base import get_core

    jobs = []
    for name in cores:
        core = get_core(name)
        knob = core.knob
        for lv in knob_levels(core, levels_by_knob, cfg["levels"]):
            jobs.append({"kind": "core", "core": core, "knob": knob, "level": lv,
                         "row": {"core": name, "knob": knob or "-", "level": lv}})
    if use_peer:
        from benchmarks import peers

        for lv in levels_by_knob["samples"][: cfg["levels"]]:
            jobs.append({"kind": "peer", "level": lv,
                         "row": {"core": peers.NAME, "knob": "samples", "level": lv}})
    ref = cfg.get("reference")
    if ref and ref in cores:
        # Both from-point peers against the reference core's most accurate level: equal time
        # (its median seconds as a budget) and equal completeness (until they have found as
        # much of the ground truth as it did).
        engines = [("raster", "sampling")] + ([("embree", peers_name())] if use_peer else [])
        for engine, label in engines:
            jobs.append({"kind": "equal_time", "engine": engine, "ref": ref,
                         "row": {"core": label, "knob": "budget", "level": ref}})
            jobs.append({"kind": "equal_completeness", "engine": engine, "ref": ref,
                         "row": {"core": label, "knob": "completeness", "level": ref}})
    return jobs


def merge_rows(old: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows of an earlier run with a new run's rows merged in: a new row replaces an old one
    of the same point (scene, cell size, cell, core, knob, level) and otherwise follows the old
    rows of its cell, so each scene's table keeps its cells together. A core's old rows on a
    scene and cell size where the new run measured it on other cells are dropped: the grid's
    cells changed, and the command now picks the new ones."""
    def key(r):
        return (r["scene"], r["cell_size"], r["cell"], r["core"], r["knob"], str(r["level"]))

    def cell(r):
        return (r["scene"], r["cell_size"], r["cell"])

    measured: dict[tuple, set] = {}
    for r in new:
        measured.setdefault((r["scene"], r["cell_size"], r["core"]), set()).add(r["cell"])
    old = [r for r in old
           if r["cell"] in measured.get((r["scene"], r["cell_size"], r["core"]), {r["cell"]})]
    fresh = {key(r): r for r in new}
    out = [fresh.pop(key(r), r) for r in old]
    for r in new:
        if key(r) in fresh:
            last = max((i for i, o in enumerate(out) if cell(o) == cell(r)), default=None)
            if last is None:
                out.append(r)
            else:
                out.insert(last + 1, r)
            fresh.pop(key(r))
    return out


def peers_name() -> str:
    from benchmarks import peers

    return peers.NAME


#: Most viewpoints a from-point peer may use for an equal-time or equal-completeness point.
MAX_PEER_SAMPLES = 100_000
#: An equal-completeness peer stops after max(PEER_CAP_SECONDS, PEER_CAP_FACTOR x the reference
#: core's time) and is reported as not having reached the target.
PEER_CAP_SECONDS = 60.0
PEER_CAP_FACTOR = 50.0


def _run_point(job, scene, cell, repeats, rows, label, cid, gt_ids=None, peer_cap=None,
               size=None):
    """(triangle ids, sphere ids or None, seconds per repeat, RSS peak MiB, traced peak MiB,
    extra row fields) of one matrix point, or None when its reference row is missing.

    Core and fixed-sample peer points: one untimed run measures memory (``measure_peak``; it
    also warms per-scene caches), then ``repeats`` timed runs. Equal-time and
    equal-completeness peer points: ``repeats`` timed runs, the first also measuring the RSS
    peak (tracemalloc would slow the peer and change how many viewpoints fit the budget).
    """
    from benchmarks import peers

    cap_s, cap_f = peer_cap or (PEER_CAP_SECONDS, PEER_CAP_FACTOR)

    cfg_res = _run_point.resolution
    if job["kind"] == "core":
        core = job["core"]
        ok, why = core.supports(scene)
        if not ok:
            raise RuntimeError(f"unsupported: {why}")
        over = {}
        if job["knob"] != "resolution":
            over["resolution"] = cfg_res
        if job["level"] is not None:
            over[job["knob"]] = job["level"]
        params = core.make_params(**over)
        deadline = _run_point.deadline

        def once():
            # Under the benchmark's deadline, if any: a point that runs past it is a finding
            # (the row says so), not an hour of the run.
            return core.compute(scene, cell, params,
                                token=CancelToken.after(deadline) if deadline else None)
    elif job["kind"] == "peer":
        def once():
            return peers.from_point_pvs(scene, cell, "embree", job["level"], cfg_res)
    else:
        ref = [r for r in rows if r["scene"] == label and r["cell"] == cid
               and r["cell_size"] == size
               and r["core"] == job["ref"] and "seconds_median" in r]
        if not ref:
            return None
        ref = ref[-1]  # the most accurate level
        kw: dict[str, Any] = {"samples": MAX_PEER_SAMPLES}
        if job["kind"] == "equal_time":
            kw["time_budget"] = ref["seconds_median"]
        else:
            kw.update(target_ids=gt_ids, target_share=1.0 - ref["fn"],
                      time_budget=max(cap_s, cap_f * ref["seconds_median"]))
            job["row"]["cap_seconds"] = max(cap_s, cap_f * ref["seconds_median"])
            job["row"]["target_pct"] = 100.0 * (1.0 - ref["fn"])

        def once():
            return peers.from_point_pvs(scene, cell, job["engine"], resolution=cfg_res, **kw)
    secs, out, peak, traced, extra = [], None, None, None, {}
    if job["kind"] in ("core", "peer"):
        t0 = time.perf_counter()
        _, peak, traced = measure_peak(once, traced=True)
        if time.perf_counter() - t0 > SLOW_POINT_SECONDS:
            repeats = 1  # one timed run is enough to say a point takes this long
    for r in range(max(1, repeats)):
        t0 = time.perf_counter()
        if r == 0 and peak is None:
            out, peak, _ = measure_peak(once, traced=False)
        else:
            out = once()
        secs.append(time.perf_counter() - t0)
        if job["kind"] != "core":
            extra = {"peer_samples": out.stats.get("samples")}
            if "target_pct" in job["row"]:
                extra["reached"] = bool(out.stats.get("reached"))
                extra["target_pct"] = job["row"]["target_pct"]
    sphere_ids = getattr(out, "sphere_ids", None)  # peers and sphere-blind cores: None
    return out.triangle_ids, sphere_ids, secs, peak, traced, extra


_run_point.resolution = 128
_run_point.deadline = None
#: A core point whose untimed first run takes longer than this is timed once, not ``repeats``
#: times.
SLOW_POINT_SECONDS = 10.0


# --------------------------------------------------------------------------- output
def _fmt(v, spec=".3f", none="–"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return format(v, spec)


def scene_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of one scene's rows; scenes with spheres get sphere FN/FP columns."""
    spheres = any(r.get("spheres") for r in rows)
    cols = ["cell (size m)", "core", "knob", "seconds median (min–max)",
            "peak MiB traced / RSS", "PVS %", "FN %", "FP %"]
    if spheres:
        cols += ["sphere FN %", "sphere FP %"]
    cols += ["ε mean %", "ε worst %", "PSNR dB", "SSIM"]
    head = "| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|\n"
    lines = []
    for r in rows:
        cell = f"{r['cell']} ({r['cell_size']:g})"
        knob = f"{r['knob']}={r['level']}"
        if "error" in r:
            lines.append(f"| {cell} | {r['core']} | {knob} | error: {r['error']} |"
                         + " |" * (len(cols) - 4))
            continue
        if r["knob"] == "budget":
            knob = f"equal time to {r['level']}"
        elif r["knob"] == "completeness":
            knob = f"equal completeness to {r['level']} ({_fmt(r.get('target_pct'), '.1f')} %)"
            if not r.get("reached", True):
                knob += f", NOT reached in {_fmt(r.get('cap_seconds'), '.0f')} s"
        if r.get("peer_samples") is not None:
            knob += f" ({r['peer_samples']} pts)"
        secs = f"{_fmt(r['seconds_median'])} ({_fmt(r['seconds_min'])}–{_fmt(r['seconds_max'])})"
        if r.get("repeats", 0) == 1:
            secs = f"{_fmt(r['seconds_median'])} (1 run)"
        cells = [cell, r["core"], knob, secs,
                 f"{_fmt(r.get('peak_traced_mib'), '.0f')} / {_fmt(r['peak_mib'], '.0f')}",
                 _fmt(r["pvs_pct"], ".2f"), _fmt(100 * r["fn"], ".2f"), _fmt(100 * r["fp"], ".2f")]
        if spheres:
            for k in ("sphere_fn", "sphere_fp"):
                v = r.get(k)
                cells.append("n/a" if v is None else _fmt(100 * v, ".2f"))
        cells += [_fmt(r["eps_mean"], ".3f"), _fmt(r["eps_worst"], ".3f"),
                  _fmt(r["psnr_mean"], ".1f"), _fmt(r["ssim_mean"], ".4f")]
        lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def ground_truth_lines(rows: list[dict[str, Any]], cfg: dict[str, Any]) -> str:
    """One line per cell of a scene: its ground truth's size, cost and saturation."""
    out, seen = [], set()
    for r in rows:
        key = (r["cell"], r["cell_size"])
        if key in seen or "gt_triangles" not in r:
            continue
        seen.add(key)
        sph = f", {r['gt_spheres']} of {r['spheres']} spheres" if r.get("spheres") else ""
        share = r.get("gt_last_batch")
        out.append(f"- cell {r['cell']} ({r['cell_size']:g} m): ground truth {r['gt_triangles']} "
                   f"triangles{sph} from {cfg['gt_points']} points at {cfg['gt_resolution']} px "
                   f"in {_fmt(r.get('gt_seconds'), '.1f')} s; its last batch of 8 points added "
                   f"{_fmt(None if share is None else 100 * share, '.2f')} % of them")
    return "\n".join(out) + "\n"


def plot_scene(rows: list[dict[str, Any]], title: str, path: Path) -> None:
    """Error-against-time PNG: FN rate and mean ε against median seconds, one curve per core."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    good = [r for r in rows if "error" not in r and r["knob"] not in ("budget", "completeness")]
    for core in sorted({r["core"] for r in good}):
        rs = [r for r in good if r["core"] == core]
        levels = sorted({str(r["level"]) for r in rs}, key=lambda s: (len(s), s))
        # One point per level: the mean over cells, so the curve is the cost/error trade-off.
        xs, fns, eps = [], [], []
        for lv in levels:
            sel = [r for r in rs if str(r["level"]) == lv]
            xs.append(np.mean([r["seconds_median"] for r in sel]))
            fns.append(100 * np.mean([r["fn"] for r in sel]))
            eps.append(np.mean([r["eps_mean"] for r in sel]))
        order = np.argsort(xs)
        for ax, ys in ((axes[0], fns), (axes[1], eps)):
            ax.plot(np.array(xs)[order], np.array(ys)[order], "o-", label=core)
    for knob, mark in (("budget", "k*"), ("completeness", "kD")):
        for r in (r for r in rows if r.get("knob") == knob and "error" not in r):
            axes[0].plot([r["seconds_median"]], [100 * r["fn"]], mark, ms=8)
            axes[1].plot([r["seconds_median"]], [r["eps_mean"]], mark, ms=8)
    for ax, lab in ((axes[0], "FN rate (% of ground truth)"), (axes[1], "mean ε (% of pixels)")):
        ax.set_xscale("log")
        ax.set_xlabel("seconds per cell (median)")
        ax.set_ylabel(lab)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{title}: error against run time (mean over cells; ★ peer at equal time, "
                 "◆ at equal completeness)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_outputs(rows, cfg, command: str, wall: float, out_md: Path, results_dir: Path) -> None:
    """Per-scene markdown tables and plots in ``results_dir``; the combined report at ``out_md``."""
    results_dir.mkdir(parents=True, exist_ok=True)
    tag = cfg["preset"]
    (results_dir / f"bench_{tag}.json").write_text(json.dumps(
        {"command": command, "config": {k: v for k, v in cfg.items() if k != "cache_dir"},
         "rows": rows}, indent=1, default=str))
    runs = cfg.get("runs") or [{"command": command, "wall_s": wall,
                                "load_start": cfg["load_start"], "load_end": _load()}]
    run_lines = []
    for run in runs:
        took = "" if run.get("wall_s") is None else f", wall time {run['wall_s'] / 60:.1f} min"
        load = "" if run.get("load_start") is None else (
            f", load average (1 min) at start {run['load_start']}"
            + (f", at end {run['load_end']}" if run.get("load_end") else ""))
        run_lines.append(f"`{run['command']}`{took}{load}")
    parts = [
        "# Benchmarks: error against run time, every core on the same cells\n",
        ("Command: " if len(runs) == 1 else "Commands (the later runs' rows merged into the "
         "first's tables with `--merge`): ") + "; ".join(run_lines) + f".  \nPreset `{tag}`.  \n"
        + (f"Machine: {machine_description()}" if len(runs) == 1 else
         f"Machine of the last run: {machine_description()} (the earlier runs' machines are "
         "not recorded and may differ)") + ". Other jobs shared the cores: times are wall "
        "times under that load.\n",
        method_paragraph(cfg),
        *([f"Scenes NOT measured (they failed to load): {'; '.join(cfg['load_errors'])}.\n"]
          if cfg.get("load_errors") else []),
        "Other measurements, each with its own command and machine: the from-segment paper's "
        "experiments ([benchmarks/results/from_segment.md](benchmarks/results/from_segment.md), "
        "`python -m benchmarks.bench_segment`) and the server under 5 to 50 concurrent "
        "clients, cold and warm cache ([benchmarks/results/load.md](benchmarks/results/load.md)"
        ", `python -m benchmarks.bench_load`; `from_segment`: "
        "[benchmarks/results/load_from_segment.md](benchmarks/results/load_from_segment.md), "
        "`python -m benchmarks.bench_load --core from_segment --name load_from_segment`; "
        "these and the abuse runs predate progressive streams: add `--no-progressive` to "
        "reproduce them). "
        "Under abuse (50 and 20 walkers with and without a client flooding expensive requests: "
        "[benchmarks/results/load_abuse.md](benchmarks/results/load_abuse.md), "
        "[benchmarks/results/load_abuse_20.md](benchmarks/results/load_abuse_20.md), "
        "`python -m benchmarks.bench_load --clients 50 --hostile --name load_abuse`), the cost "
        "of stopping a computation, checkpoints against a killed worker process "
        "([benchmarks/results/cancel.md](benchmarks/results/cancel.md), "
        "`python -m benchmarks.bench_cancel`), the cores' cost estimates against measurements "
        "([benchmarks/results/admission.md](benchmarks/results/admission.md), "
        "`python -m benchmarks.bench_admission`). With progressive streams (a first answer "
        "at once, refined in place), 20 walkers on a cold cache "
        "([benchmarks/results/load_progressive_from_segment.md]"
        "(benchmarks/results/load_progressive_from_segment.md), `python -m "
        "benchmarks.bench_load --clients 20 --cache cold --core from_segment --name "
        "load_progressive_from_segment`; [benchmarks/results/load_progressive_sampling.md]"
        "(benchmarks/results/load_progressive_sampling.md), the same with `--core sampling "
        "--name load_progressive_sampling`). `from_segment` and `sampling` on cells of the "
        "real scenes scored by ray casting ([benchmarks/results/real_cells.md]"
        "(benchmarks/results/real_cells.md), `python -m benchmarks.bench_real_cells`). The "
        "`cos` core's own experiments (the "
        "paper's speed cells, FP per cell size: [benchmarks/results/cos.md]"
        "(benchmarks/results/cos.md), `python -m benchmarks.bench_cos`) and the small cells "
        "(5-30 cm) where `cos`, `trim_regions`, `from_segment` and `sampling` meet "
        "([benchmarks/results/small_cells.md](benchmarks/results/small_cells.md), "
        "`python -m benchmarks.bench_small_cells`). The `dual_ray` core's experiments (the "
        "paper's Table 1 grid, its speed targets: [benchmarks/results/dual_ray.md]"
        "(benchmarks/results/dual_ray.md), `python -m benchmarks.bench_dual_ray`) and the big "
        "cells (25, 100 and 300 m) of the 100k city and Lyon where it should win, beside "
        "`from_segment`, `sampling` and the ray-casting peer "
        "([benchmarks/results/big_cells.md](benchmarks/results/big_cells.md), `pvs bench "
        "--preset medium --scenes city:100000 ../shared/scenes/lyon_vilo3d.glb --cell-sizes 25 "
        "100 300 --cores dual_ray from_segment sampling --point-deadline 120 --out "
        "benchmarks/results/big_cells.md --results-dir benchmarks/results/big_cells`). The "
        "`trim_regions` core's experiments (time per phase against Δ, false-negative pixels, "
        "side by side with `cos`: [benchmarks/results/trim_regions.md]"
        "(benchmarks/results/trim_regions.md), `python -m benchmarks.bench_trim_regions`).\n",
    ]
    for label in dict.fromkeys(r["scene"] for r in rows):
        refused = [r for r in rows if r["scene"] == label and "refused" in r]
        srows = [r for r in rows if r["scene"] == label and "refused" not in r]
        note = "".join(f"Not run here: `{r['core']}` does not fit this scene ({r['refused']}).\n\n"
                       for r in refused)
        if not srows:
            parts.append(f"## {label} ({refused[0]['triangles']} triangles)\n\n{note}")
            continue
        table = scene_table(srows)
        png = results_dir / f"{tag}_{label}.png"
        plot_scene(srows, label, png)
        (results_dir / f"{tag}_{label}.md").write_text(f"## {label}\n\n{table}")
        rel = os.path.relpath(png, out_md.parent)
        sph = f", {srows[0]['spheres']} spheres" if srows[0].get("spheres") else ""
        parts.append(f"## {label} ({srows[0]['triangles']} triangles{sph})\n\n"
                     f"{ground_truth_lines(srows, cfg)}\n{note}{table}\n![{label}]({rel})\n")
    out_md.parent.mkdir(parents=True, exist_ok=True)
    out_md.write_text("\n".join(parts))


def method_paragraph(cfg: dict[str, Any]) -> str:
    """The report's method paragraph: what was run, with which knob levels, and why."""
    levels = _levels_by_knob(cfg)
    knobs = ", ".join(f"`{c}` {c_knob} {lv}" for c, c_knob, lv in _core_levels(cfg))
    cap_s, cap_f = cfg.get("peer_cap") or (PEER_CAP_SECONDS, PEER_CAP_FACTOR)
    top = top_core_resolution(cfg)
    return (
        "Method: scenes are every generator but `stress` (a test scene of stiff cases, checked "
        "with known answers by the stiff suite) at two sizes (for `spheres` the size is the "
        "sphere count), and every scene in `../shared/scenes/`. Per scene and cell size "
        f"({', '.join('default' if c is None else str(c) for c in cfg['cell_sizes'])}; `x2` = "
        f"twice the default side), {cfg['cells']} cell(s) picked evenly over the viewcell grid "
        "(`ViewcellGrid.for_scene`). Knob levels per core (each core declares its knob): "
        f"{knobs}; cores whose knob is not `resolution` run at "
        f"{cfg['resolution']} px. Ground truth: `sample_pvs` with {cfg['gt_points']} points at "
        f"{cfg['gt_resolution']} px ({cfg['gt_resolution'] / top:g}x the finest core resolution, "
        f"{top} px, and {cfg['gt_points'] / max(1, max(levels.get('samples', [1]))):g}x the "
        "most samples), triangles and spheres (spheres render and occlude), cached in "
        "`benchmarks/results/cache/`; each scene lists per cell the share of its triangles the "
        "last batch of 8 points added, so a reader sees how far from saturation it is (a "
        "sampled ground truth only misses, so FN is a lower bound and part of a conservative "
        "core's FP is truly visible). FN = share of the ground truth missing from the PVS; FP = "
        "share of the PVS not in the ground truth; for spheres the same over sphere ids "
        "(`PVS.sphere_ids`), n/a for a core or peer that reports none. Seconds: median "
        f"(min–max) of {cfg['repeats']} timed repeats in one process after a warm-up compile "
        "and an untimed memory run; the equal-time and equal-completeness peer points run "
        f"{cfg.get('peer_repeats', cfg['repeats'])} time(s) (equal time is the reference's "
        "time by construction; equal completeness stops at a deterministic viewpoint count). "
        "Peak MiB traced / RSS, from the untimed run: the peak of tracemalloc's count (numpy "
        "arrays and Python objects, reused memory included; not numba's internal allocations) "
        "and the rise of VmHWM (reset via /proc/self/clear_refs) over VmRSS (everything, but "
        "only pages the process did not already hold); the equal-time/completeness points give "
        "RSS only. Frames: "
        f"{cfg['views']} fixed views at {cfg['view_size']}² px, 90° fov, from eyes inside the "
        f"cell, each looking the horizontal way (pitched {VIEW_PITCH:g} rad) that shows the most "
        f"distinct triangles, the best {cfg['views']} of {VIEW_CANDIDATES * cfg['views']} "
        "candidate eyes; PVS subset (its spheres included) against the full scene at rest "
        "(`client.metrics.frame_metrics`; an identical frame's PSNR counts as "
        f"{PSNR_CAP_DB:g} dB"
        + ("; rows of merged runs made before that rule show 100 dB, the cap then"
           if len(cfg.get("runs") or []) > 1 else "") + "). Peer `embree_rays`: Embree "
        "(embreex via trimesh) rays through cube pixel centres from the same stratified points "
        "as `sampling` (neither peer draws spheres). "
        f"Peers against `{cfg.get('reference')}` at its most accurate level: both from-point "
        "methods (`sampling`, our rasterizer, and `embree_rays`) add viewpoints one at a time "
        "until they have used its median time (equal time) or found as large a share of the "
        f"ground truth as it did (equal completeness; capped at max({cap_s:g} s, {cap_f:g}x its "
        "time), marked NOT reached otherwise). "
        + (f"A core point still running after {cfg['point_deadline']:g} s was stopped (its row "
           "says so), and one whose first run took over "
           f"{SLOW_POINT_SECONDS:g} s was timed once. " if cfg.get("point_deadline") else "")
        + "Levels and sizes are chosen so the medium preset "
        "takes about half an hour on 2 cores: two levels per knob show the slope of each "
        "error-against-time curve, the ground truth is the dominant fixed cost per cell.\n")


def _levels_by_knob(cfg: dict[str, Any]) -> dict[str, list[Any]]:
    return {"samples": PEER_LEVELS, **cfg.get("knob_levels", {})}


def _core_levels(cfg: dict[str, Any]) -> list[tuple[str, str, list[Any]]]:
    """(core, knob, levels) of every core the run measures."""
    from visibility.cores.base import available_cores, get_core

    out = []
    known = available_cores()
    for name in cfg["cores"] or known:
        if name not in known:  # reported by ``main`` as an unknown core
            continue
        core = get_core(name)
        out.append((name, core.knob or "-",
                    knob_levels(core, _levels_by_knob(cfg), int(cfg["levels"]))))
    return out


def top_core_resolution(cfg: dict[str, Any]) -> int:
    """The finest cubemap resolution any core runs at in ``cfg`` (px)."""
    res = [int(cfg["resolution"])]
    for _, knob, levels in _core_levels(cfg):
        if knob == "resolution":
            res += [int(v) for v in levels]
    return max(res)


# --------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pvs bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default="medium")
    p.add_argument("--quick", action="store_true", help="the 'quick' preset (a few minutes)")
    p.add_argument("--scenes", nargs="+", help="name:triangles, 'real', or scene file paths")
    p.add_argument("--cores", nargs="+", help="cores to run (default: every registered core)")
    p.add_argument("--cell-sizes", nargs="+", help="metres, 'default' or 'x2'")
    p.add_argument("--cells", type=int, help="cells per scene and cell size")
    p.add_argument("--repeats", type=int)
    p.add_argument("--levels", type=int, help="knob levels per core")
    p.add_argument("--gt-points", type=int)
    p.add_argument("--gt-resolution", type=int)
    p.add_argument("--views", type=int)
    p.add_argument("--view-size", type=int)
    p.add_argument("--resolution", type=int, help="resolution of cores whose knob is not it")
    p.add_argument("--no-peer", action="store_true", help="skip the Embree ray-caster peer")
    # The peers reproduce the from-segment paper's comparison (Sec. 4.5): named on purpose.
    p.add_argument("--reference", default="from_segment",
                   help="core the from-point peers get equal time and equal completeness "
                        "against ('none' to skip)")
    p.add_argument("--out", type=Path, default=None, help="report (default BENCHMARKS.md)")
    p.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    p.add_argument("--cache-dir", type=Path, default=None)
    p.add_argument("--point-deadline", type=float, default=None,
                   help="seconds a core point may run before it is stopped and reported as "
                        "over the deadline (default: none)")
    p.add_argument("--report-only", action="store_true",
                   help="run nothing: rewrite the report from RESULTS_DIR/bench_PRESET.json")
    p.add_argument("--merge", action="store_true",
                   help="keep the rows of the last run of this preset (RESULTS_DIR/"
                        "bench_PRESET.json) that this run does not measure again, and write "
                        "the report from both (e.g. a new core added to the published tables)")
    return p


def config_from_args(args: argparse.Namespace) -> dict[str, Any]:
    preset = "quick" if args.quick else args.preset
    cfg = dict(PRESETS[preset])
    cfg["knob_levels"] = dict(cfg.get("knob_levels", {}))
    cfg["preset"] = preset
    for k in ("scenes", "cells", "repeats", "levels", "gt_points", "gt_resolution", "views",
              "view_size", "resolution"):
        v = getattr(args, k)
        if v is not None:
            cfg[k] = v
    if args.cell_sizes:
        cfg["cell_sizes"] = [None if c == "default" else (c if c == "x2" else float(c))
                             for c in args.cell_sizes]
    cfg["cores"] = args.cores
    cfg["peer"] = not args.no_peer
    cfg["reference"] = None if args.reference == "none" else args.reference
    cfg["cache_dir"] = str(args.cache_dir) if args.cache_dir else None
    for k in ("cells", "repeats", "levels", "gt_points", "gt_resolution", "views", "view_size",
              "resolution"):
        if int(cfg[k]) < 1:
            raise ValueError(f"--{k.replace('_', '-')} must be >= 1, got {cfg[k]}")
    if args.repeats is not None:
        cfg["peer_repeats"] = min(int(cfg.get("peer_repeats", cfg["repeats"])), cfg["repeats"])
    # A ground truth coarser than a core would count the core's extra detail as FP.
    top = top_core_resolution(cfg)
    if int(cfg["gt_resolution"]) < top:
        raise ValueError(f"--gt-resolution must be at least the finest core resolution ({top} "
                         f"px), got {cfg['gt_resolution']}")
    return cfg


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark matrix; write the report and results. Returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        print(f"pvs bench: {exc}", file=sys.stderr)
        return 2
    from visibility.cores.base import available_cores

    unknown = set(cfg["cores"] or []) - set(available_cores())
    if unknown:
        print(f"pvs bench: unknown cores {sorted(unknown)}; available: {available_cores()}",
              file=sys.stderr)
        return 2
    out_md = args.out or (REPO / "BENCHMARKS.md")
    if args.report_only:
        path = args.results_dir / f"bench_{cfg['preset']}.json"
        if not path.is_file():
            print(f"pvs bench: --report-only needs the results of a run: {path} is missing",
                  file=sys.stderr)
            return 2
        saved = json.loads(path.read_text())
        scfg = saved["config"]
        runs = scfg.get("runs") or [{"command": saved["command"]}]
        write_outputs(saved["rows"], scfg, runs[-1]["command"], runs[-1].get("wall_s") or 0.0,
                      out_md, args.results_dir)
        print(f"wrote {out_md} from {args.results_dir}")
        return 0
    command = "pvs bench " + shlex.join(argv)
    _run_point.resolution = int(cfg["resolution"])
    _run_point.deadline = args.point_deadline
    if args.point_deadline:
        cfg["point_deadline"] = float(args.point_deadline)
    cfg["load_start"] = _load()
    t0 = time.perf_counter()
    _warm_up(cfg)
    rows = run_matrix(cfg, log=lambda s: print(s, flush=True))
    wall = time.perf_counter() - t0
    if args.merge:
        prev_path = args.results_dir / f"bench_{cfg['preset']}.json"
        if prev_path.exists():
            prev = json.loads(prev_path.read_text())
            rows = merge_rows(prev["rows"], rows)
            pc = prev.get("config", {})
            cfg["runs"] = pc.get("runs") or [{"command": prev["command"],
                                              "load_start": pc.get("load_start")}]
            # The report describes the merged tables: every core in them, the earlier run's
            # peers and reference.
            ran = {r["core"] for r in rows}
            cfg["cores"] = [c for c in available_cores() if c in ran] or None
            if cfg["cores"] is not None and set(cfg["cores"]) == set(available_cores()):
                cfg["cores"] = None
            for k in ("peer", "reference"):
                if k in pc:
                    cfg[k] = pc[k]
            if pc.get("point_deadline"):
                cfg["point_deadline"] = pc["point_deadline"]
    cfg.setdefault("runs", [])
    cfg["runs"] = [*cfg["runs"], {"command": command, "wall_s": wall,
                                  "load_start": cfg["load_start"], "load_end": _load()}]
    write_outputs(rows, cfg, command, wall, out_md, args.results_dir)
    print(f"wrote {out_md} and {args.results_dir}")
    return 0


def _warm_up(cfg) -> None:
    """Compile every core's numba kernels on a tiny scene, so the first timed point is fair."""
    from benchmarks import peers
    from visibility.cores.base import available_cores, get_core

    scene, cell = _tiny_scene_and_cell()
    for name in cfg["cores"] or available_cores():
        core = get_core(name)
        core.compute(scene, cell, core.make_params(resolution=16))
    if cfg["peer"] and peers.available():
        peers.embree_pvs(scene, cell, samples=1, resolution=8)


def _tiny_scene_and_cell():
    from visibility.scene import Scene
    from visibility.viewcells import Viewcell

    tris = np.array([[(-1, 0, -5), (1, 0, -5), (0, 2, -5)], [(-4, 0, -8), (4, 0, -8), (0, 4, -8)]],
                    dtype=np.float64)
    scene = Scene(tris.reshape(-1, 3), np.arange(6).reshape(-1, 3), name="warmup")
    return scene, Viewcell(np.array([[-0.5, 1.5, -0.5], [0.5, 1.9, 0.5]]))


if __name__ == "__main__":
    raise SystemExit(main())
