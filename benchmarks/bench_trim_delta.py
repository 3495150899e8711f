"""trim_regions past the paper's largest sphere: the benchmark's random cubes of the real scenes
at a chosen Δ (one sphere of that radius each), scored by independent rays.

``max_delta`` sets how many spheres cover a cell, so what a cell costs: a server's 1 m cell
(1 m across the ground, the grid's eye range high) takes 12 spheres at the paper's largest Δ,
0.3 m, and 4 at 0.41 m. Whether the method keeps the paper's bound (0.005 % of a frame's
pixels) with spheres of that size is what this measures, on the cubes
``bench_trim_regions``' random-cells table draws (same seed, same scenes and counts, cubes
whose circumscribed sphere is Δ): FN px is the most pixels of a frame showing a triangle the
PVS lacks (eyes in the cube's open space, ``RANDOM_FRAMES`` frames each).

Writes ``benchmarks/results/trim_delta_<Δ>.md`` (+ ``.json``), e.g. ``trim_delta_0.41.md``.
Usage:
``python -m benchmarks.bench_trim_delta --delta 0.41`` (about 10 minutes on 2 cores, the
kitchen's cubes most of it), ``--scenes lavaducts --cubes 2`` for a smoke run into ``--out``.
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

from benchmarks.bench_trim_regions import (
    RANDOM_CELLS,
    RANDOM_FRAMES,
    RESULTS,
    load,
    random_open_cubes,
)
from visibility.cores.base import get_core
from visibility.cores.trim_regions.quality import frame_errors
from visibility.viewcells import Viewcell

#: The paper's bound on a frame's false-negative pixels (Wonka et al. 2006's 0.005 %).
BOUND = 5e-5


def measure(delta: float, cells: dict[str, int]) -> list[dict[str, Any]]:
    """One row per random cube (``random_open_cubes``, ``cells`` cubes per scene) of Δ
    ``delta`` metres, computed with ``max_delta=delta`` (one sphere)."""
    core = get_core("trim_regions")
    params = core.make_params(max_delta=delta)
    rows = []
    for name, n in cells.items():
        scene = load(name)
        for k, (box, cast) in enumerate(random_open_cubes(scene, n, delta=delta)):
            pvs = core.compute(scene, Viewcell(box), params)
            e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
            rows.append({"scene": name, "cube": k,
                         "centre": (0.5 * (box[0] + box[1])).tolist(),
                         "spheres": int(pvs.stats["spheres"]), "seconds": pvs.seconds,
                         "pvs": len(pvs), "gt": e["gt"], "frames": len(cast.eyes),
                         "fn_pixels_max": e["fn_pixels_max"],
                         "fn_pixel_rate_max": e["fn_pixel_rate_max"]})
            print(f"{name} {k + 1}/{n}: {pvs.seconds:.2f} s, FN px {e['fn_pixels_max']}",
                  flush=True)
    return rows


def markdown(delta: float, rows: list[dict[str, Any]], argv: list[str], elapsed: float,
             loadavg: tuple[float, float]) -> str:
    """The results page: a row per scene, then the cubes over the bound."""
    out = ["# trim_regions: random cubes at one Δ", "",
           f"Command: `python -m benchmarks.bench_trim_delta {' '.join(argv)}`; "
           f"{os.cpu_count()} CPU cores, {elapsed:.0f} s in all; load average (1 min) "
           f"{loadavg[0]:.1f} at start, {loadavg[1]:.1f} at end.", "",
           f"Cubes of Δ {delta} m (one sphere each, `max_delta={delta}`) at the seeded random "
           "places of `bench_trim_regions`' random-cells table, each judged on "
           f"{RANDOM_FRAMES} frames of Embree rays from eyes in its open space. Over: cubes "
           "with a frame above the paper's 0.005 % (19.7 px of a 6 x 256² frame).", "",
           "| scene | cubes | over the bound | FN px max | FN px max, median | "
           "PVS / GT, median | s, median |", "|---|---|---|---|---|---|---|"]
    for name in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == name]
        over = sum(r["fn_pixel_rate_max"] > BOUND for r in rs)
        out.append(f"| {name} | {len(rs)} | {over} | {max(r['fn_pixels_max'] for r in rs)} | "
                   f"{np.median([r['fn_pixels_max'] for r in rs]):.0f} | "
                   f"{np.median([r['pvs'] / max(r['gt'], 1) for r in rs]):.2f} | "
                   f"{np.median([r['seconds'] for r in rs]):.2f} |")
    over = [r for r in rows if r["fn_pixel_rate_max"] > BOUND]
    out += ["", "Over the bound: " + (", ".join(
        f"{r['scene']} cube {r['cube']} at {np.round(r['centre'], 3).tolist()} "
        f"({r['fn_pixels_max']} px)" for r in over) or "none") + ".", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--delta", type=float, required=True, help="sphere radius Δ, metres")
    ap.add_argument("--scenes", default=",".join(RANDOM_CELLS),
                    help="comma-separated real scenes (default: the random-cells table's)")
    ap.add_argument("--cubes", type=int, default=0,
                    help="cubes per scene (default: the random-cells table's counts)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    if not args.delta > 0:
        ap.error("--delta must be positive")
    names = [s for s in args.scenes.split(",") if s]
    unknown = [s for s in names if s not in RANDOM_CELLS]
    if unknown:
        ap.error(f"unknown scenes {unknown}; known: {sorted(RANDOM_CELLS)}")
    cells = {s: args.cubes or RANDOM_CELLS[s] for s in names}
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    rows = measure(args.delta, cells)
    elapsed = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"trim_delta_{args.delta:g}"
    (args.out / f"{stem}.json").write_text(json.dumps(
        {"delta": args.delta, "rows": rows, "seconds": elapsed,
         "load": [load0, os.getloadavg()[0]]}, indent=1))
    text = markdown(args.delta, rows, argv, elapsed, (load0, os.getloadavg()[0]))
    (args.out / f"{stem}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
