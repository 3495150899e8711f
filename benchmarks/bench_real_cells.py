"""``from_segment`` against ``sampling`` on the real scenes, scored by dense ray casting.

For each real scene in ``../shared/scenes/`` a seeded walk (``client.walkthrough.
generate_walkthrough``, the scene's own grid) picks the cells it stands in at a third and at
two thirds of its length, as a user's walk would. The reference of a cell is independent of
both cores' rasterizer: Intel Embree rays (``benchmarks.peers.embree_views``) through the pixel
centres of randomly turned cubes from ``POINTS`` eyes where a person can stand in the cell
(``cell_eyes``: its open floor, ``visibility.cell_walk``, at the eye heights, 0.1 m clear of
geometry, as from_segment's segments are; the whole box for a cell with no open floor),
``RAYS`` rays per face side; a triangle counts as visible when at least ``MIN_HITS`` rays hit
it first (a one-ray hit is as likely a numerical grazing as a sight). Each cell is then solved
by ``from_segment`` at its defaults, by ``sampling`` at its defaults, and by ``sampling`` given
``from_segment``'s time (equal time: viewpoints added until that time is spent,
``peers.from_point_pvs`` with our rasterizer). The table gives the share of the reference each
missed, the PVS size, the seconds, and the frames: ``FRAMES`` views from where a person can
stand in the cell (``frame_views``: eyes as the reference's, a random yaw and pitch), at
``from_segment``'s own resolution, drawn from the PVS against the full scene (ε, PSNR, SSIM;
with 64 frames a 0 means that no pixel of any of them differs), plus the size in pixels of
what was missed (the median projected area, at the reference's resolution, of the missed
triangles from the cell's centre). The frames' rays pass by triangles smaller than their
spacing, so each answer is also scored against the reference grown by rays from such eyes
aimed at every triangle some answer on the cell holds (``aimed_reference``,
``visibility.ray_aimed``). Before its cells, each scene gets the per-scene builds a server
makes when it loads a scene (``prepare``), untimed.

Writes ``benchmarks/results/real_cells.md`` and ``.json``; prints as it goes.

Usage::

    python -m benchmarks.bench_real_cells            # every real scene, 2 cells each
    python -m benchmarks.bench_real_cells --quick    # lavaducts, 1 cell, a lighter reference
    python -m benchmarks.bench_real_cells --scenes lyon_vilo3d lavaducts \
        --fs-variants resolution=512 --out benchmarks/results/real_cells_512.md
    python -m benchmarks.bench_real_cells --fs-variants jitter=0 cuts=0   # what each buys
    python -m benchmarks.bench_real_cells --scenes lyon_vilo3d --where  # misses: from where
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_matrix import (
    SHARED_SCENES,
    frame_summary,
    machine_description,
)
from benchmarks.common import aimed_total
from benchmarks.peers import embree_views, from_point_pvs
from visibility.ground_truth import sample_points
from visibility.raster.camera import random_rotation

ROOT = Path(__file__).resolve().parents[1]

RESULTS = ROOT / "benchmarks" / "results"
#: Reference: points per cell, rays per cube face side, first hits a triangle needs.
POINTS = 64
RAYS = 183
MIN_HITS = 3
#: A core run stopped after this many seconds (its row says so): the server's own deadline
#: (``server.settings``' ``compute_deadline``), so a row says whether a walker would get it.
DEADLINE = 300.0
#: from_segment's phases and work counters kept per row (``core.FromSegmentCore`` stats):
#: where the time of a cell went and how much it walked and drew.
WORK = ("walk", "segments", "runs", "box_seconds", "bin_seconds", "envelope_seconds",
        "pairs", "setups", "final_pieces")
#: Rays aimed at the answers (``visibility.ray_aimed``): per candidate in the first round, and
#: at most, doubled while ``AIM_BUDGET`` rays at every candidate would not be passed.
AIM_RAYS = 16
AIM_MOST = 65536
AIM_BUDGET = 600_000_000
#: Frames per cell, and the largest pitch of their forward direction (degrees).
FRAMES = 64
MAX_PITCH = 30.0


def cell_eyes(scene, cell, n: int, rng: np.random.Generator) -> tuple[np.ndarray, bool]:
    """(n, 3) eyes where a person can stand in the cell (``cell_walk.open_eyes``: its open
    floor, clear of geometry by the segments' clearance), repeated to n where fewer qualify;
    a cell with no open floor gets ``n`` stratified points of its whole box instead. Returns
    the eyes and whether they came from open floor."""
    from visibility.cell_walk import open_eyes

    eyes = open_eyes(scene, np.asarray(cell.box, dtype=np.float64), n, rng)
    if not len(eyes):
        return sample_points(cell.box, n, rng), False
    return eyes[np.arange(n) % len(eyes)], True


def reference(scene, cell, points: int, rays: int, seed: int) -> tuple[np.ndarray, float]:
    """Triangles first-hit by at least ``MIN_HITS`` Embree rays from ``points`` eyes where a
    person can stand in the cell (``cell_eyes``; module docstring), and the seconds it took."""
    t0 = time.perf_counter()
    valid = np.flatnonzero(scene.valid_faces)
    view = embree_views(scene, valid, cell, rays)
    rng = np.random.default_rng(seed)
    hits = np.zeros(scene.n_triangles, dtype=np.int64)
    for eye in cell_eyes(scene, cell, points, rng)[0]:
        hits += np.bincount(view(eye, random_rotation(rng)), minlength=scene.n_triangles)
    return np.flatnonzero(hits >= MIN_HITS).astype(np.int32), time.perf_counter() - t0


def frame_views(scene, cell, n: int, seed: int) -> tuple[list[tuple[np.ndarray, np.ndarray]],
                                                           bool]:
    """``n`` (eye, forward) views where a person can stand in the cell (``cell_eyes``), forward
    at a uniform yaw and a pitch within ``MAX_PITCH`` degrees. Returns the views and whether
    the cell had open floor."""
    rng = np.random.default_rng(seed)
    eyes, has_open = cell_eyes(scene, cell, n, rng)
    yaw = rng.uniform(0.0, 2.0 * np.pi, n)
    pitch = np.radians(rng.uniform(-MAX_PITCH, MAX_PITCH, n))
    fwd = np.stack([np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)],
                   axis=1)
    return list(zip(eyes, fwd, strict=True)), has_open


def aimed_reference(scene, cell, candidates: np.ndarray, known: np.ndarray, seed: int
                    ) -> tuple[Any, float]:
    """Rays aimed at ``candidates`` (the union of the answers on the cell) from eyes where a
    person can stand in it (``cell_eyes``), ``known`` (the frames' reference) counted as seen:
    ``AIM_RAYS`` per candidate, doubled up to ``AIM_MOST`` within ``AIM_BUDGET``
    (``ray_aimed.aimed_seen``). Returns the sample and its seconds."""
    from visibility.ray_aimed import aimed_seen

    most = AIM_RAYS
    while most * 2 <= AIM_MOST and most * 2 * len(candidates) <= AIM_BUDGET:
        most *= 2
    t0 = time.perf_counter()
    got = aimed_seen(scene, np.asarray(cell.box, dtype=np.float64), candidates, known=known,
                     rays=AIM_RAYS, most=most, seed=seed,
                     eyes=lambda n, rng: cell_eyes(scene, cell, n, rng)[0])
    return got, time.perf_counter() - t0


def parse_variant(text: str) -> dict[str, Any]:
    """``"jitter=0,cuts=0"`` -> {"jitter": 0, "cuts": 0}: core parameters to try besides the
    defaults, read as ``pvs --param`` reads them (``pvs_cli.parse_params``; the core's
    ``make_params`` checks names and ranges)."""
    from pvs_cli import parse_params

    return parse_params([t.strip() for t in text.split(",") if t.strip()])


def prepare(scene) -> float:
    """Build now what a server builds when a scene loads (``server.scene_builds``): the
    spatial hierarchy and the per-scene structures of the cores measured here, so that no
    cell's time includes them. Returns the seconds."""
    from visibility.cores.base import get_core
    from visibility.raster import hierarchy
    from visibility.scene_cache import per_scene

    t0 = time.perf_counter()
    builds = [hierarchy.BUILD] if scene.n_triangles >= hierarchy.MIN_TRIANGLES else []
    for name in ("from_segment", "sampling"):
        builds += get_core(name).scene_builds(scene)
    for b in builds:
        per_scene(scene, b.kind, b.build, b.persist)
    return time.perf_counter() - t0


def walk_cells(scene, seed: int, k: int) -> list[int]:
    """The cells a seeded walk through the scene's grid stands in at 1/(k+1) ... k/(k+1) of it."""
    from client.walkthrough import generate_walkthrough
    from visibility.viewcells import ViewcellGrid

    grid = ViewcellGrid.for_scene(scene)
    walk = generate_walkthrough(grid, duration=30.0, seed=seed)
    n = len(walk.positions)
    out = []
    for j in range(1, k + 1):
        c = grid.cell_of(walk.positions[(j * n) // (k + 1)])
        if c is not None and c not in out:
            out.append(int(c))
    return out


def missed_pixels(scene, ids: np.ndarray, eye: np.ndarray, rays: int) -> float:
    """Median projected area (pixels of a 90 degree face ``rays`` wide) of triangles ``ids``
    seen from ``eye``: their area over the squared distance, in units of one pixel's solid
    angle at the face centre."""
    if not len(ids):
        return 0.0
    tri = scene.triangles(ids)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d2 = np.sum((tri.mean(axis=1) - eye) ** 2, axis=1)
    pixel = (2.0 / rays) ** 2  # solid angle of one pixel at the centre of a 90 degree face
    return float(np.median(area / np.maximum(d2, 1e-12) / pixel))


def run(cfg: dict[str, Any], log=print) -> list[dict[str, Any]]:
    from client.render import OffscreenRenderer
    from visibility.cancel import CancelToken, ComputationCancelled
    from visibility.cores.base import get_core
    from visibility.ground_truth import fn_fp_rates
    from visibility.loaders import load_scene
    from visibility.viewcells import ViewcellGrid

    renderer = OffscreenRenderer(cfg["frame_px"], cfg["frame_px"], yfov_deg=90.0)
    rows: list[dict[str, Any]] = []
    # Compile the kernels once, on a small scene: no real scene's first run pays for it.
    from visibility.generators import make_scene

    small = make_scene("rooms", triangles=2_000)
    small_grid = ViewcellGrid.for_scene(small)
    for name in ("from_segment", "sampling"):
        get_core(name).compute(small, small_grid.cell(0))
    try:
        sources = [(path, None) for path in cfg["scenes"]] + [
            (name, int(n)) for name, n in cfg.get("generated", [])]
        for source, n in sources:
            if n is None:
                scene = load_scene(source)
                scene_label = scene.name
            else:
                scene = make_scene(source, triangles=n)
                scene_label = f"{source} {n // 1000}k (generated)"
            grid = ViewcellGrid.for_scene(scene)
            log(f"[{scene_label}] per-scene builds in {prepare(scene):.1f} s (untimed)")
            for cell_id in walk_cells(scene, cfg["seed"], cfg["cells"]):
                cell = grid.cell(cell_id)
                ref, ref_s = reference(scene, cell, cfg["points"], cfg["rays"], cfg["seed"])
                views, has_open = frame_views(scene, cell, cfg["frames"], cfg["seed"] + cell_id)
                gt = [renderer.render_scene(scene, e, f) for e, f in views]
                centre = np.asarray(cell.box).mean(axis=0)
                log(f"[{scene_label}] cell {cell_id} ({grid.cell_size:g} m): reference "
                    f"{len(ref)} triangles from {cfg['points']} points x 6 x {cfg['rays']}^2 "
                    f"rays in {ref_s:.1f} s")
                base = {"scene": scene_label, "triangles": scene.n_triangles, "cell": cell_id,
                        "cell_size": grid.cell_size, "reference": int(len(ref)),
                        "reference_seconds": ref_s, "open_floor": has_open}
                fs_seconds = None
                first = len(rows)
                answers = []
                walked = []  # the from_segment parameters of each answer (None: another core)
                runs = [("from_segment (defaults)", "from_segment", {}),
                        ("sampling (defaults)", "sampling", {})]
                runs += [(f"from_segment ({text})", "from_segment", parse_variant(text))
                         for text in cfg.get("fs_variants", [])]
                for label, name, params in runs:
                    core = get_core(name)
                    try:
                        pvs = core.compute(scene, cell, core.make_params(**params),
                                           token=CancelToken.after(DEADLINE))
                    except ComputationCancelled:
                        rows.append({**base, "method": label, "error": f"past {DEADLINE:g} s"})
                        continue
                    if name == "from_segment" and not params:
                        fs_seconds = pvs.seconds
                    rows.append(_row(base, label, pvs.triangle_ids, pvs.seconds, ref, scene,
                                     renderer, views, gt, centre, cfg, fn_fp_rates))
                    if name == "from_segment":
                        rows[-1]["work"] = {k: pvs.stats[k] for k in WORK if k in pvs.stats}
                    answers.append(pvs.triangle_ids)
                    walked.append(core.make_params(**params) if name == "from_segment" else None)
                    log(_line(rows[-1]))
                if fs_seconds is not None:
                    peer = from_point_pvs(scene, cell, "raster", samples=100_000,
                                          resolution=get_core("sampling").make_params()
                                          .resolution, seed=cfg["seed"] + 1,
                                          time_budget=fs_seconds)
                    rows.append(_row(base, f"sampling at equal time ({peer.stats['samples']} "
                                     "points)", peer.triangle_ids, peer.seconds, ref, scene,
                                     renderer, views, gt, centre, cfg, fn_fp_rates))
                    answers.append(peer.triangle_ids)
                    walked.append(None)
                    log(_line(rows[-1]))
                seen = _score_aimed(rows[first:], answers, scene, cell, ref,
                                    cfg["seed"] + cell_id, log)
                if cfg.get("where") and seen is not None:
                    scored = [r for r in rows[first:] if "error" not in r]
                    for r, ids, fs in zip(scored, answers, walked, strict=True):
                        if fs is not None:
                            r["aimed_missed_where"] = where_seen(
                                scene, cell, np.setdiff1d(seen, ids), fs, cfg["seed"] + cell_id)
                            log(f"    {r['method']:38s} its aimed misses seen from: "
                                f"{_where(r['aimed_missed_where'])}")
    finally:
        renderer.close()
    return rows


def _score_aimed(rows, answers, scene, cell, ref, seed, log) -> np.ndarray | None:
    """Each row's answer against the frames' reference grown by rays aimed at the union of
    the answers (``aimed_reference``): ``aimed`` seen in all, ``aimed_fn`` the share of it
    the answer lacks, ``pvs_over_aimed``. Returns the grown reference's ids (None: no
    answer)."""
    scored = [r for r in rows if "error" not in r]
    if not answers:
        return None
    got, secs = aimed_reference(scene, cell, np.unique(np.concatenate(answers)), ref, seed)
    seen = np.union1d(ref, got.ids)
    log(f"    rays aimed at the answers: {len(seen)} seen ({got.rays_per_candidate} rays per "
        f"candidate, {'converged' if got.converged else 'not converged'}, last doubling "
        f"+{100 * got.added_last:.2f} %) in {secs:.1f} s")
    centre = np.asarray(cell.box, dtype=np.float64).mean(axis=0)
    for r, ids in zip(scored, answers, strict=True):
        missed = np.setdiff1d(seen, ids)
        r.update(aimed=int(len(seen)), aimed_converged=bool(got.converged),
                 aimed_rays=got.rays_per_candidate, aimed_added_last=got.added_last,
                 aimed_seconds=secs, aimed_fn=float(len(missed) / max(1, len(seen))),
                 aimed_missed_px=missed_pixels(scene, missed, centre, RAYS),
                 pvs_over_aimed=float(len(ids) / max(1, len(seen))))
        log(f"    {r['method']:38s} against them: FN {100 * r['aimed_fn']:.2f} %, PVS "
            f"{r['pvs_over_aimed']:.2f}x")
    return seen


#: Rays per missed triangle and eye set in ``where_seen``.
WHERE_RAYS = 4096


def where_seen(scene, cell, missed: np.ndarray, params, seed: int) -> dict[str, int]:
    """Where from_segment's misses ``missed`` (triangle ids) are seen from, each counted once,
    in this order (``visibility.ray_aimed.seen_from``, ``WHERE_RAYS`` float64 rays per
    triangle and eye set): ``segments``, points of the segments the core walked with
    ``params`` (the pixel samples passed it by: a sampling miss); ``outline``, the same
    outline at any height of the cell's eye range (the eye levels passed it by); ``inside``,
    eyes on the open floor within it (``cell_eyes``); ``none``, none of these rays."""
    from visibility.cores.from_segment.core import view_segments
    from visibility.ray_aimed import seen_from

    box = np.asarray(cell.box, dtype=np.float64)
    rng = np.random.default_rng(seed)
    segs, _ = view_segments(scene, box, params.eye_levels, params.walk)
    s = segs[rng.integers(0, len(segs), WHERE_RAYS)]
    on = s[:, 0] + rng.random(WHERE_RAYS)[:, None] * (s[:, 1] - s[:, 0])
    around = on.copy()
    around[:, 1] = rng.uniform(box[0, 1], box[1, 1], WHERE_RAYS)
    inside = cell_eyes(scene, cell, 512, rng)[0]
    first = seen_from(scene, missed, [on, around, inside], rays=WHERE_RAYS, seed=seed)
    out = {name: int(np.count_nonzero(first == k))
           for k, name in enumerate(("segments", "outline", "inside"))}
    out["none"] = int(np.count_nonzero(first < 0))
    return out


def _where(w: dict[str, int]) -> str:
    return (f"{w['segments']} the walked segments, {w['outline']} only their outline at other "
            f"heights, {w['inside']} only eyes inside it, {w['none']} none of the rays")


def parse_generated(text: str) -> tuple[str, int]:
    """``NAME:TRIANGLES`` of a generated scene (a key of ``visibility.generators.GENERATORS``)
    as (name, triangles); a clear error otherwise."""
    from visibility.generators import GENERATORS

    name, _, n = text.partition(":")
    if name not in GENERATORS or not n.isdigit() or int(n) <= 0:
        raise SystemExit(f"--generated takes NAME:TRIANGLES with NAME one of "
                         f"{sorted(GENERATORS)}, got {text!r}")
    return name, int(n)


def _row(base, label, ids, seconds, ref, scene, renderer, views, gt, centre, cfg,
         fn_fp_rates) -> dict[str, Any]:
    fn, fp = fn_fp_rates(ids, ref)
    missed = np.setdiff1d(ref, ids)
    frames = frame_summary(renderer, scene, ids, views, gt, key=label)
    return {**base, "method": label, "seconds": float(seconds), "pvs": int(len(ids)),
            "fn": fn, "fp": fp, "missed": int(len(missed)),
            "missed_median_px": missed_pixels(scene, missed, centre, cfg["rays"]), **frames}


def _line(r: dict[str, Any]) -> str:
    return (f"    {r['method']:38s} {r['seconds']:7.2f} s  PVS {r['pvs']:7d}  FN "
            f"{100 * r['fn']:6.2f} % ({r['missed']} missed, median {r['missed_median_px']:.2f}"
            f" px)  eps {r['eps_mean']:.3f} % (worst {r['eps_worst']:.3f} %)")


def report(rows: list[dict[str, Any]], cfg: dict[str, Any], command: str, wall: float) -> str:
    load = os.getloadavg()[0]
    lines = ["# from_segment and sampling on the real scenes, against dense ray casting", "",
             f"Command: `{command}`, wall time {wall / 60:.1f} min, load average (1 min) at "
             f"the end {load:.1f}.  ",
             f"Machine: {machine_description()}", "",
             f"Per scene, the cells a seeded walk (seed {cfg['seed']}) stands in; reference: "
             f"triangles first-hit by at least {MIN_HITS} Embree rays from {cfg['points']} "
             f"eyes x 6 x {cfg['rays']}^2 rays, the eyes on the cell's open floor 0.1 m clear "
             "of geometry (module docstring of `benchmarks/bench_real_cells.py`). FN = share of "
             "the reference missed; FP = share "
             "of the PVS the rays did not see; missed px = median projected size of the missed "
             "triangles from the cell centre, in pixels of a 90 degree face as wide as the "
             f"reference's; frames: {cfg['frames']} views from such eyes (random yaw, pitch "
             f"within {MAX_PITCH:g} degrees; * a cell with no open floor: eyes in its whole "
             f"box) at {cfg['frame_px']} px, PVS against the full "
             "scene. Aimed: the reference grown by rays from such eyes aimed at random "
             "points of every triangle some answer on the cell holds (`ray_aimed.aimed_seen`: "
             f"{AIM_RAYS} rays per triangle, doubled until a doubling adds under 0.1 % or "
             f"{AIM_MOST} rays, or {AIM_BUDGET:,} rays at all of them, would be passed; "
             "rays per triangle in brackets, * not converged), each seen triangle confirmed "
             "by a float64 cast: a lower bound on what eyes of the cell see, so PVS / aimed "
             "is an upper bound; FN aimed = share of it the answer lacks, px their median "
             "projected size as for missed px.", "",
             "| scene | cell (m) | reference | method | s | PVS | FN % | missed px | FP % | "
             "ε mean % | ε worst % | PSNR dB | SSIM | aimed | FN aimed % | px | PVS / aimed |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['cell']} ({r['cell_size']:g}) | {r['reference']}"
                         f" | {r['method']} | {r['error']} | | | | | | | | | | | | |")
            continue
        lines.append(
            f"| {r['scene']} | {r['cell']} ({r['cell_size']:g}){_star(r)} | {r['reference']} | "
            f"{r['method']} | {r['seconds']:.2f} | {r['pvs']} | {100 * r['fn']:.2f} | "
            f"{r['missed_median_px']:.2f} | {100 * r['fp']:.1f} | {r['eps_mean']:.3f} | "
            f"{r['eps_worst']:.3f} | {r['psnr_mean']:.1f} | {r['ssim_mean']:.4f} | "
            f"{_aimed(r)} |")
    work = [r for r in rows if "work" in r]
    if work:
        lines += ["", "`from_segment`'s phases and work (its stats): the segments it walked "
                  "(how: the open floor's outline, or the rectangle), runs of turned cubes, "
                  "seconds collecting the primitives' boxes, binning them into tiles and in "
                  "the envelope pass, (primitive, pixel) pairs drawn, primitives set up, and "
                  "envelope pieces at the end.", "",
                  "| scene | cell (m) | method | walk | segments | runs | box s | bin s | "
                  "envelope s | pairs | setups | pieces |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in work:
            w = r["work"]
            lines.append(
                f"| {r['scene']} | {r['cell']} ({r['cell_size']:g}) | {r['method']} | "
                f"{w.get('walk', '')} | {w.get('segments', 0)} | {w.get('runs', 0)} | "
                f"{w.get('box_seconds', 0.0):.2f} | {w.get('bin_seconds', 0.0):.2f} | "
                f"{w.get('envelope_seconds', 0.0):.2f} | {w.get('pairs', 0):,} | "
                f"{w.get('setups', 0):,} | {w.get('final_pieces', 0):,} |")
    where = [r for r in rows if "aimed_missed_where" in r]
    if where:
        lines += ["", "Where the aimed misses are seen from (`--where`: "
                  f"{WHERE_RAYS} float64 rays per missed triangle from points of the segments "
                  "the core walked, then from the same outline at random heights of the eye "
                  "range, then from eyes on the open floor inside it; each counted at the "
                  "first that sees it):", ""]
        lines += [f"- {r['scene']}, cell {r['cell']}, {r['method']}: "
                  f"{sum(r['aimed_missed_where'].values())} missed; "
                  f"{_where(r['aimed_missed_where'])}" for r in where]
    return "\n".join(lines) + "\n"


def _aimed(r: dict[str, Any]) -> str:
    if "aimed" not in r:
        return "– | – | – | –"
    return (f"{aimed_total(r['aimed'], r['aimed_rays'], r['aimed_converged'])} | "
            f"{100 * r['aimed_fn']:.2f} | {r['aimed_missed_px']:.2f} | "
            f"{r['pvs_over_aimed']:.2f}")


def _star(r: dict[str, Any]) -> str:
    return "" if r.get("open_floor", True) else " *"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="lavaducts, 1 cell, lighter reference")
    ap.add_argument("--cells", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scenes", nargs="*", help="real scene names (default: every one; the "
                    "flag alone: none, for --generated only)")
    ap.add_argument("--generated", nargs="*", default=[], metavar="NAME:TRIANGLES",
                    help="generated scenes to add (visibility.generators), e.g. city:1000000")
    ap.add_argument("--fs-variants", nargs="*", default=[], metavar="KEY=VALUE[,KEY=VALUE]",
                    help="from_segment also with these parameters, e.g. jitter=0 cuts=0")
    ap.add_argument("--frames", type=int, default=FRAMES, help="frames per cell")
    ap.add_argument("--frame-px", type=int, default=None,
                    help="frame size in pixels (default: from_segment's resolution)")
    ap.add_argument("--where", action="store_true",
                    help="say where each from_segment answer's aimed misses are seen from: "
                    "the walked segments, their outline at other heights, or only inside")
    ap.add_argument("--out", type=Path, default=RESULTS / "real_cells.md")
    args = ap.parse_args(argv)
    scenes = sorted(str(p) for p in SHARED_SCENES.glob("*.glb")
                    if not args.scenes or p.stem in args.scenes)
    if args.scenes is not None and not args.scenes:
        scenes = []
    generated = [parse_generated(g) for g in args.generated]
    cfg = {"scenes": scenes, "generated": generated, "cells": args.cells,
           "seed": args.seed, "points": POINTS, "rays": RAYS, "fs_variants": args.fs_variants,
           "frames": args.frames, "where": args.where,
           "frame_px": args.frame_px or _from_segment_resolution()}
    if args.quick:
        cfg.update(scenes=[s for s in scenes if "lavaducts" in s], cells=1, points=16, rays=96,
                   frames=min(args.frames, 8))
    command = "python -m benchmarks.bench_real_cells " + " ".join(
        argv if argv is not None else sys.argv[1:])
    t0 = time.perf_counter()
    rows = run(cfg)
    text = report(rows, cfg, command.strip(), time.perf_counter() - t0)
    args.out.write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps({"command": command, "config": cfg,
                                                          "rows": rows}, indent=1))
    print(text)
    return 0


def _from_segment_resolution() -> int:
    from visibility.cores.base import get_core

    return int(get_core("from_segment").make_params().resolution)


if __name__ == "__main__":
    raise SystemExit(main())
