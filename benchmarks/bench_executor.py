"""Cells per second of ``pvs precompute`` on the local worker pool and on a Dask ``LocalCluster``
of worker processes on this machine, and the overhead per job of going through the cluster.

Both runs are ``server.precompute.precompute`` on a ``ComputeService`` (what ``pvs precompute``
does), same scene, cells, core and parameters, each into a fresh on-disk cache, after a warm-up
on other cells (numba loads its kernels: in this process for the local pool, in every worker
process for the cluster). Each is run twice: with the core's real parameters, and with "tiny"
jobs (the core at its cheapest: 1 viewpoint of 8 px) whose time is almost all overhead.

Honest about the machine: the cluster's workers share this machine's cores with the scheduler
and the server process, so on 2 cores it cannot be faster than the local pool; what it measures
is the price of a job's trip (scheduling, pickling the job and its answer, the polling wait).
``overhead per job`` is the server side's mean of (round trip less the core's own seconds) over
the run's jobs (``DaskExecutor.state()['overhead_ms']``).

Writes ``OUT/executor.md`` and ``OUT/executor.json``. Usage (about 3 minutes on 2 cores)::

    python -m benchmarks.bench_executor
    python -m benchmarks.bench_executor --cells 40 --out /tmp      # smoke
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_cancel import machine
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.precompute import precompute
from server.resolve import Resolver
from server.settings import Settings
from visibility.viewcells import spread_evenly

TINY = {"samples": 1, "batch": 1, "resolution": 8}


def _service(scene: str, triangles: int, folder: Path, executor: str, workers: int
             ) -> ComputeService:
    s = Settings(generated={scene: triangles}, cache_dir=folder, calibrate=False,
                 progressive=False, workers=workers, executor=executor, log_level="warning")
    return ComputeService(SceneCatalog(s), s)


def warm_up(scene: str, triangles: int, core: str, params: dict[str, Any], warm: list[int],
            executor: str, workers: int, folder: Path) -> None:
    """``precompute`` of the warm-up cells (numba loads its kernels where the jobs run)."""
    svc = _service(scene, triangles, folder, executor, workers)
    try:
        precompute(svc, scene, core, params, warm, progress=False)
    finally:
        svc.shutdown()


def run(scene: str, triangles: int, core: str, params: dict[str, Any], cells: list[int],
        executor: str, workers: int, folder: Path, tag: str) -> dict[str, Any]:
    """One measured ``precompute`` run into ``folder``: its numbers and ids."""
    out: dict[str, Any] = {"executor": "local" if executor == "local" else "dask", "tag": tag}
    svc = _service(scene, triangles, folder, executor, workers)
    try:
        t0 = time.perf_counter()
        report = precompute(svc, scene, core, params, cells, progress=False)
        wall = time.perf_counter() - t0
        choice = Resolver(svc.settings).named(core, params)
        ids = [svc.cache.get(svc.key(scene, choice.core, choice.params, cell)).triangle_ids
               for cell in cells]
        state = svc.executor.state()
        slots = svc.pool.workers
    finally:
        svc.shutdown()
    if report.failed:
        raise RuntimeError(f"{tag}: cells failed: {report.failed}")
    out.update(cells=len(cells), computed=report.computed, wall_s=wall,
               cells_per_s=report.computed / wall, compute_s=report.compute_seconds,
               core_s_per_cell=report.compute_seconds / max(1, report.computed),
               slots=slots, executor_state=state)
    return out | {"ids": ids}


def overlap(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two rows' cells/s ranges overlap."""
    (a0, a1), (b0, b1) = a["cells_per_s_range"], b["cells_per_s_range"]
    return a0 <= b1 and b0 <= a1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="village")
    ap.add_argument("--triangles", type=int, default=20_000)
    ap.add_argument("--core", default="sampling")
    ap.add_argument("--cells", type=int, default=120, help="cells per run (spread evenly)")
    ap.add_argument("--workers", type=int, default=2,
                    help="local pool threads, and cluster workers (one thread each)")
    ap.add_argument("--repeats", type=int, default=5,
                    help="measured runs per executor, interleaved (the fastest reported)")
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from distributed import LocalCluster

    from visibility.generators import make_scene
    from visibility.viewcells import ViewcellGrid

    m0, t_all = machine(), time.perf_counter()
    scene = make_scene(args.scene, triangles=args.triangles, seed=0)
    n = len(ViewcellGrid.for_scene(scene, Settings().cell_size_for(scene.meta.get("cell_size"))))
    cells = spread_evenly(np.arange(n), args.cells)
    warm = [c for c in spread_evenly(np.arange(n), args.cells + 6) if c not in set(cells)][:4]
    scene_bytes = len(pickle.dumps(scene, protocol=5))
    t0 = time.perf_counter()
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.ERROR)
    cluster_start = time.perf_counter() - t0
    dask = cluster.scheduler_address.replace("tcp://", "dask://")
    rows = []
    try:
        with tempfile.TemporaryDirectory() as d:
            tmp = Path(d)
            for label, params in (("real", {}), ("tiny", TINY)):
                for ex in ("local", dask):
                    warm_up(args.scene, args.triangles, args.core, params, warm, ex,
                            args.workers, tmp / f"warm-{label}-{len(rows)}")
                    rows.append({"label": label, "params": params, "runs": [],
                                 "executor": "local" if ex == "local" else "dask", "ex": ex})
                # Interleaved, so a change of the machine's load hits both alike.
                for i in range(args.repeats):
                    for row in rows[-2:]:
                        tag = f"{label}-{row['executor']}-{i}"
                        print(f"[bench_executor] {tag}: {len(cells)} cells", file=sys.stderr)
                        row["runs"].append(run(args.scene, args.triangles, args.core, params,
                                               cells, row["ex"], args.workers, tmp / tag, tag))
    finally:
        cluster.close()
    same = {}
    for label in ("real", "tiny"):
        a, b = (r for r in rows if r["label"] == label)
        same[label] = all(np.array_equal(x, y) for ra, rb in zip(a["runs"], b["runs"], strict=True)
                          for x, y in zip(ra["ids"], rb["ids"], strict=True))
    for r in rows:
        del r["ex"]
        for x in r["runs"]:
            del x["ids"]
        # The fastest run stands for the row: on a shared machine it is the one other jobs
        # disturbed least (the range shows the rest).
        r.update(min(r["runs"], key=lambda x: x["wall_s"]))
        r["cells_per_s_range"] = [min(x["cells_per_s"] for x in r["runs"]),
                                  max(x["cells_per_s"] for x in r["runs"])]
    result = {"command": "python -m benchmarks.bench_executor " + " ".join(argv or sys.argv[1:]),
              "machine": m0, "load_end": list(os.getloadavg()),
              "scene": args.scene, "triangles": int(scene.n_triangles), "grid_cells": n,
              "core": args.core, "workers": args.workers, "cluster_start_s": cluster_start,
              "scene_pickle_bytes": scene_bytes, "same_ids": same, "rows": rows,
              "wall_s": time.perf_counter() - t_all}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "executor.json").write_text(json.dumps(result, indent=1, default=float))
    (out / "executor.md").write_text(report(result))
    print(report(result))
    return 0


def report(r: dict[str, Any]) -> str:
    """The Markdown report of a result."""
    m = r["machine"]
    by = {(x["label"], x["executor"]): x for x in r["rows"]}
    lines = [
        "# Executor benchmark: `pvs precompute` on the local pool and on a Dask LocalCluster", "",
        f"command: `{r['command'].strip()}` ({r['wall_s']:.0f} s)", "",
        f"machine: {m['cpu']}, {m['cores']} logical cores, {m['mem_gib']:.1f} GiB RAM, "
        f"{m['os']}; Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}; load "
        f"average (1 min) {m['load'][0]:.1f} at start, {r['load_end'][0]:.1f} at end "
        "(the machine is shared: times are wall times under that load).", "",
        f"Scene `{r['scene']}` ({r['triangles']} triangles, {r['grid_cells']} cells of 4 m), "
        f"core `{r['core']}`; {r['rows'][0]['cells']} cells spread evenly over the grid, each "
        "run into a fresh on-disk cache after a 4-cell warm-up. Local: the priority pool with "
        f"{r['workers']} threads. Dask: `LocalCluster(n_workers={r['workers']}, "
        f"threads_per_worker=1, processes=True)` on this machine (started in "
        f"{r['cluster_start_s']:.1f} s), the server keeping one job per worker thread under "
        f"way; the scene (pickled {r['scene_pickle_bytes'] / 2**20:.1f} MiB) scattered to "
        "every worker once. \"real\": the core's default parameters; \"tiny\": "
        f"`{TINY}`, a job that costs almost nothing, so its time is the trip.", "",
        f"Each row: the fastest of {len(r['rows'][0]['runs'])} runs (local and Dask runs "
        "interleaved; on a shared machine the fastest is the one other jobs disturbed least), "
        "with the range of cells/s over the runs.", "",
        "| jobs | executor | cells | wall s | cells/s (range) | core s per cell "
        "| overhead per job ms | same ids as local |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (label, ex), x in by.items():
        oh = x["executor_state"].get("overhead_ms")
        lo, hi = x["cells_per_s_range"]
        lines.append(
            f"| {label} | {ex} | {x['computed']} | {x['wall_s']:.1f} | {x['cells_per_s']:.2f} "
            f"({lo:.2f}–{hi:.2f}) | {x['core_s_per_cell']:.3f} "
            f"| {'–' if oh is None else f'{oh:.1f}'} "
            f"| {'–' if ex == 'local' else ('yes' if r['same_ids'][label] else 'NO')} |")
    real_l, real_d = by[("real", "local")], by[("real", "dask")]
    tiny_l, tiny_d = by[("tiny", "local")], by[("tiny", "dask")]
    trip = real_d["executor_state"].get("overhead_ms") or 0.0
    lines += [
        "",
        "overhead per job: the server side's mean of (round trip less the core's own seconds) "
        "over the run's jobs: scheduling, shipping the job and its answer, unpickling. The "
        "0.1 s poll of a waiting job's deadline adds nothing to it: a finished job wakes its "
        "waiter at once.",
        "",
        f"Real jobs: {real_d['cells_per_s']:.2f} cells/s on the cluster against "
        f"{real_l['cells_per_s']:.2f} on the local pool "
        f"({real_d['cells_per_s'] / real_l['cells_per_s']:.2f}x); "
        + ("the ranges overlap, so this machine's load hides any difference. "
           if overlap(real_l, real_d) else "the ranges do not overlap. ")
        + f"The same {m['cores']} cores do the work either way, so the cluster adds no "
        "computing here; it trades a trip per job (about "
        f"{trip:.0f} ms, {100 * trip / 1e3 / real_l['core_s_per_cell']:.0f} % of a "
        f"{real_l['core_s_per_cell']:.2f} s job) against worker processes that each have "
        "their own interpreter lock, where the pool's threads share one for the Python "
        "between kernels (not measured apart here). Tiny jobs show the trip alone: "
        f"{tiny_d['cells_per_s']:.1f} against {tiny_l['cells_per_s']:.1f} cells/s, about "
        f"{tiny_d['executor_state'].get('overhead_ms') or 0:.0f} ms per job. A cluster pays "
        "off once its workers are other machines' cores: each adds its cells per second, "
        "less that trip per job (plus the network's round trip).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
