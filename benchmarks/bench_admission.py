"""The cores' cost estimates (``Core.estimate_cost``, what admission control prices a request
by) against what the computations measure: seconds and peak memory, per core, scene and
resolution.

Each computation runs on the middle cell of its scene's viewcell grid (4 m cells), in a fresh
process of its own after a warm-up compile at 16 px; memory is the process's peak resident
size during the run (the kernel's high-water mark, reset just before it through
``/proc/self/clear_refs``) less its resident size before, numba's allocations included. The
ratio columns say how far the model is off: the
server corrects seconds per scene once a computation has run (``server.admission``), memory
is refused on the estimate alone.

Writes ``benchmarks/results/admission.md`` (+ ``.json``). Usage:
``python -m benchmarks.bench_admission`` (about 5 minutes on 2 cores, the kitchen's
from_segment cell at 64 px the longest), ``--quick`` for a smoke run into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from benchmarks.bench_matrix import SHARED_SCENES, measure_peak
from visibility.cores.base import get_core
from visibility.generators import make_scene
from visibility.viewcells import ViewcellGrid

ROOT = Path(__file__).resolve().parents[1]

RESULTS = ROOT / "benchmarks" / "results"
#: (scene, core, resolutions) measured by the full run.
CASES = (
    ("village 20k", "sampling", (128, 512)),
    ("village 20k", "from_segment", (128, 256, 512)),
    ("village 20k", "cos", (64, 128)),
    ("city 100k", "sampling", (128, 512)),
    ("city 100k", "from_segment", (128, 256)),
    ("city 100k", "cos", (64, 128)),
    ("kitchen", "sampling", (128,)),
    ("kitchen", "from_segment", (64,)),
)


def peak_rise(fn) -> tuple[Any, float, int]:
    """``fn()``, its wall seconds and its peak resident size above the size before it, bytes
    (``benchmarks.bench_matrix.measure_peak``: VmHWM reset through /proc/self/clear_refs)."""
    t0 = time.perf_counter()
    out, rise_mib, _ = measure_peak(fn, traced=False)
    return out, time.perf_counter() - t0, int((rise_mib or 0.0) * 2**20)


def load(label: str):
    if label == "kitchen":
        from visibility.loaders import load_scene

        return load_scene(SHARED_SCENES / "kitchen.glb")
    name, size = label.split()
    return make_scene(name, triangles=int(size.rstrip("k")) * 1000)


def measure(label: str, core_name: str, resolution: int) -> dict:
    """One row, computed in the calling process (run it in a fresh one)."""
    sc = load(label)
    grid = ViewcellGrid.for_scene(sc)
    cell = grid.cell(len(grid) // 2)
    core = get_core(core_name)
    core.compute(sc, cell, core.make_params(resolution=16))  # compile, build caches
    params = core.make_params(resolution=resolution)
    est = core.estimate_cost(sc, cell, params)
    _, seconds, rise = peak_rise(lambda: core.compute(sc, cell, params))
    return {"scene": label, "core": core_name, "resolution": resolution,
            "triangles": sc.n_triangles, "estimated_s": est.seconds,
            "measured_s": seconds, "estimated_bytes": int(est.peak_bytes),
            "measured_bytes": int(rise)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one small scene, one low resolution")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    cases = ((("village 2k", c, (32,)) for c in ("sampling", "from_segment", "cos"))
             if args.quick else CASES)
    load0, t_all = os.getloadavg()[0], time.perf_counter()
    rows = []
    ctx = multiprocessing.get_context("spawn")
    for label, core_name, resolutions in cases:
        if label == "kitchen" and not (SHARED_SCENES / "kitchen.glb").exists():
            print("kitchen.glb not found: skipped")
            continue
        for r in resolutions:
            # A fresh process per row: pages an earlier run freed would hide this one's rise.
            with ProcessPoolExecutor(1, mp_context=ctx) as pool:
                row = pool.submit(measure, label, core_name, r).result()
            rows.append(row)
            print(f"{label:12s} {core_name:12s} R={r:4d}  est {row['estimated_s']:8.2f} s  "
                  f"measured {row['measured_s']:8.2f} s  "
                  f"est {row['estimated_bytes'] / 2**20:8.0f} MiB  "
                  f"rise {row['measured_bytes'] / 2**20:7.0f} MiB", flush=True)
    elapsed = time.perf_counter() - t_all
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "admission.json").write_text(json.dumps({"rows": rows, "seconds": elapsed}, indent=1))
    lines = ["# Cost estimates against measurements", "",
             f"Command: `python -m benchmarks.bench_admission {' '.join(argv)}`; "
             f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
             f"{elapsed:.0f} s; load average (1 min) {load0:.1f} at start, "
             f"{os.getloadavg()[0]:.1f} at end.", "",
             "Middle cell (4 m) of each scene's grid, each row in a fresh process; RSS rise: "
             "peak resident size during the run less the size before it. "
             "Ratio: measured / estimated.", "",
             "| scene | core | R | estimated s | measured s | ratio | estimated MiB | "
             "RSS rise MiB | ratio |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ts = r["measured_s"] / max(r["estimated_s"], 1e-9)
        tb = r["measured_bytes"] / max(r["estimated_bytes"], 1)
        lines.append(f"| {r['scene']} | {r['core']} | {r['resolution']} | "
                     f"{r['estimated_s']:.2f} | {r['measured_s']:.2f} | {ts:.2f} | "
                     f"{r['estimated_bytes'] / 2**20:.0f} | {r['measured_bytes'] / 2**20:.0f} | "
                     f"{tb:.2f} |")
    (out / "admission.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'admission.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
