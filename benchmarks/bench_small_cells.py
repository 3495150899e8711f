"""Small cells (5, 10, 20, 30 cm), where ``cos``, ``from_segment`` and ``sampling`` meet on equal
cells: error against time, per scene and cell size.

The camera offset space paper works with cells of this size; the server's default grid uses
4 m. Here every core gets the same cube cells at eye height over the same grid cells of each
scene (``cell_around``), generated (20k-triangle rooms, village, city) and real
(``../shared/scenes``: lavaducts, denhaag), and is scored against one dense sampled reference
per cell (every triangle seen from ``--points`` stratified eyes in the box and its 26 boundary
points, 256 px per cube face). FN: reference triangles missing from the PVS (count and share);
FP: share of the PVS the reference did not see; seconds: best of 2 runs after a warm-up
compile; RSS rise: VmHWM over VmRSS of the untimed first run (numba's allocations included).

Writes ``benchmarks/results/small_cells.md`` (+ ``.json``, ``.png``: FN against seconds per
core). Usage: ``python -m benchmarks.bench_small_cells`` (about 8 minutes on 2 cores),
``--quick`` for a smoke run into ``--out``.
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
from tqdm import tqdm

from benchmarks.bench_matrix import SHARED_SCENES, measure_peak
from visibility.cores.base import get_core
from visibility.generators import make_scene
from visibility.ground_truth import cell_around, dense_reference, fn_fp_rates
from visibility.viewcells import Viewcell

ROOT = Path(__file__).resolve().parents[1]

RESULTS = ROOT / "benchmarks" / "results"
SIZES = (0.05, 0.1, 0.2, 0.3)
#: Each core at its default parameters and at the resolution the cos paper compares at.
#: cos also at 32 px (what a walker in 0.3 m cells can afford online on 2 cores) and 512 px
#: (what resolution buys back of its overestimation).
CORES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("cos", {}),
    ("cos", {"resolution": 32}),
    ("cos", {"resolution": 512}),
    ("from_segment", {}),
    ("from_segment", {"resolution": 512}),
    ("sampling", {}),
    ("sampling", {"samples": 128}),
    ("trim_regions", {}),
)


#: The smoke run's cores: one setting each, the cheapest.
QUICK_CORES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("cos", {"resolution": 32}), ("from_segment", {}), ("sampling", {}), ("trim_regions", {}))


def scenes(quick: bool) -> list[tuple[str, Any]]:
    """(label, Scene) of the scenes measured."""
    n = 5_000 if quick else 20_000
    out = [(f"{name} {n // 1000}k", make_scene(name, triangles=n))
           for name in ("rooms", "village", "city")]
    if not quick:
        from visibility.loaders import load_scene

        for name in ("lavaducts", "denhaag"):
            path = SHARED_SCENES / f"{name}.glb"
            if path.exists():
                out.append((name, load_scene(path)))
    return out


def measure(label: str, scene: Any, size: float, points: int, cores) -> list[dict[str, Any]]:
    """Every core on one cube cell of ``size`` metres over the scene's first grid cell."""
    from visibility.cores.cos.fusion import open_edge_share

    box = cell_around(scene, size, 0)
    ref = dense_reference(scene, box, n_points=points, resolution=256)
    open_edges = open_edge_share(scene)
    rows = []
    for name, params in cores:
        core = get_core(name)
        p = core.make_params(**params)
        first, rss, _ = measure_peak(lambda c=core, p=p: c.compute(scene, Viewcell(box), p),
                                     traced=False)
        best = min((first, core.compute(scene, Viewcell(box), p)), key=lambda x: x.seconds)
        fn, fp = fn_fp_rates(best.triangle_ids, ref)
        missed = int(len(np.setdiff1d(ref, best.triangle_ids)))
        # Where the extra triangles lie: distance from the cell's centre to their centroids.
        extra = np.setdiff1d(best.triangle_ids, ref)
        dist = np.linalg.norm(scene.vertices[scene.faces[extra]].mean(axis=1)
                              - box.mean(axis=0), axis=1) if len(extra) else np.zeros(0)
        fp_dist = [float(q) for q in np.quantile(dist, (0.1, 0.5, 0.9))] if len(dist) else None
        rows.append({"fp_distance_m": fp_dist, "open_edges": open_edges, "scene": label,
                     "size": size, "core": name, "params": params,
                     "label": name + (" " + ",".join(f"{k}={v}" for k, v in params.items())
                                      if params else ""),
                     "seconds": best.seconds, "pvs": len(best), "reference": int(len(ref)),
                     "fn": fn, "fn_count": missed, "fp": fp, "rss_mib": rss or 0.0,
                     "triangles": scene.n_triangles})
    return rows


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for label in dict.fromkeys(r["label"] for r in rows):
        pts = [(r["seconds"], 100 * r["fn"]) for r in rows if r["label"] == label]
        x, y = zip(*pts, strict=True)
        ax.scatter(x, y, label=label, s=18)
    ax.set_xscale("log")
    ax.set_xlabel("seconds per cell (2 CPU cores)")
    ax.set_ylabel("FN % against the dense reference")
    ax.set_title("5-30 cm cells: error against time, every scene and size")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(rows, points, elapsed, argv, load) -> str:
    cmd = " ".join(["python -m benchmarks.bench_small_cells", *argv])
    cores = ", ".join(dict.fromkeys(r["label"].split(" ")[0] for r in rows))
    out = [f"# Small cells: {cores} on equal cells", "",
           f"Command: `{cmd}`; {platform.processor() or platform.machine()}, {os.cpu_count()} "
           f"CPU cores, {elapsed:.0f} s in all; load average (1 min) {load[0]:.1f} at start, "
           f"{load[1]:.1f} at end (other jobs shared the cores: wall times under that load).",
           "",
           f"Per scene and size, one cube cell at eye height over the scene's first grid cell; "
           f"reference: every triangle seen from {points} stratified eyes in the box and its 26 "
           "boundary points at 256 px per face. FN: reference triangles missing (count, share); "
           "FP: share of the PVS the reference did not see (a sampled reference misses, so part "
           "of a conservative core's FP is truly visible); seconds: best of 2 after a warm-up; "
           "RSS rise of the first run; FP distance: from the cell's centre to the centroids "
           "of the triangles the reference did not see (quantiles).", "",
           "Open edges (after welding vertices, the share of edges that belong to one "
           "triangle only: open borders and T-junctions, where cos cannot fuse occluders): "
           + ", ".join(f"{r['scene']} {100 * r['open_edges']:.1f} %"
                       for r in {r["scene"]: r for r in rows if "open_edges" in r}.values())
           + ".", "",
           "![FN against seconds](small_cells.png)", "",
           "| scene | cell | core | s | PVS | ref | FN | FN % | FP % | FP distance m "
           "(10 / 50 / 90 %) | RSS rise MiB |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = r.get("fp_distance_m")
        dist = "–" if not d else " / ".join(f"{x:.0f}" if x >= 10 else f"{x:.1f}" for x in d)
        out.append(f"| {r['scene']} | {100 * r['size']:.0f} cm | {r['label']} | "
                   f"{r['seconds']:.3f} | {r['pvs']:,} | {r['reference']:,} | {r['fn_count']} | "
                   f"{100 * r['fn']:.2f} | {100 * r['fp']:.1f} | {dist} | "
                   f"{r['rss_mib']:.0f} |")
    out += ["", "## Per core, over every cell", "",
            "| core | cells | median s | max s | cells with a miss | mean FN % | mean FP % |",
            "|---|---|---|---|---|---|---|"]
    for label in dict.fromkeys(r["label"] for r in rows):
        rs = [r for r in rows if r["label"] == label]
        s = np.array([r["seconds"] for r in rs])
        out.append(f"| {label} | {len(rs)} | {np.median(s):.3f} | {s.max():.3f} | "
                   f"{sum(r['fn_count'] > 0 for r in rs)} | "
                   f"{100 * np.mean([r['fn'] for r in rs]):.2f} | "
                   f"{100 * np.mean([r['fp'] for r in rs]):.1f} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5k scenes, two sizes, few points")
    ap.add_argument("--points", type=int, default=256)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    points = 16 if args.quick else args.points
    sizes = (0.05, 0.3) if args.quick else SIZES
    cores = QUICK_CORES if args.quick else CORES
    warm = make_scene("city", triangles=2000)
    for name, params in cores:  # compile every kernel before the clock matters
        core = get_core(name)
        core.compute(warm, Viewcell(cell_around(warm, 0.3, 0)),
                     core.make_params(**{**params, "resolution": 16}))
    rows: list[dict[str, Any]] = []
    jobs = [(label, sc, size) for label, sc in scenes(args.quick) for size in sizes]
    for label, sc, size in tqdm(jobs, desc="cells", unit="cell"):
        rows += measure(label, sc, size, points, cores)
    elapsed = time.perf_counter() - t0
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "small_cells.json").write_text(json.dumps(
        {"rows": rows, "points": points, "seconds": elapsed}, indent=1))
    plot(rows, out / "small_cells.png")
    (out / "small_cells.md").write_text(
        markdown(rows, points, elapsed, argv, (load0, os.getloadavg()[0])))
    print((out / "small_cells.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
