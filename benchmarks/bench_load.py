"""Load benchmark: N concurrent protocol clients walking a served scene against a real server.

Starts ``python -m pvs_cli serve`` on a free loopback port (configured through ``PVS_*``
environment variables) serving ``--scene``: a generated scene (``--triangles``) or a file of the
scenes folder (``--scenes``, else ``pvs serve``'s default, ``../shared/scenes``), loaded here
through the server's own catalogue so the benchmark's grid is the server's
(``benchmarks.load.scenes``). Then runs N asyncio walkers (``benchmarks.load.walkers``), each
replaying its own walkthrough at real-time pacing; walks are drawn once, on the ground
(``benchmarks.load.ground``: never inside a building, in a cell, the eye at walking height over
the ground; a walk that is not is drawn again), walker i walking the same walk in every run.

One run per worker count (``--workers 1,2``), cache state and walker count (``--clients
5,20,50``): cold (a fresh server per run, every PVS computed while the walkers walk: the
computing capacity) and warm (one server per worker count whose memory cache holds the PVS of
every cell the walks pass through and their neighbours, computed over HTTP before the walkers
come, as an edge server started from its disk cache: the streaming capacity).

Per run (``benchmarks.load.summary``): frames by the answer their cell held when drawn (each
of ``protocol.messages.ANSWERS``, then stalled) and the core's own share; stalls (frames whose
cell was not complete one frame interval after the pose was sent; the first cell of each
walker, waited for before its clock starts, is not counted); frame delivery latency
p50/p95/p99/max (never-delivered frames counting as the latest); the image error of sampled
frames per answer, per walker then over walkers (ε mean and worst, PSNR, SSIM:
``benchmarks.load.frames``); triangles per walker; computations and computations per second;
the server's CPU and peak RSS; bytes; duplicates and client errors. Over all runs: the capacity
per worker count (most walkers with no stall, per worker and per CPU core; computations per
second).

Abuse mode (``--hostile``, ``benchmarks.load.hostile``): each run twice on the same settings,
without and with a hostile client flooding expensive HTTP PVS requests from another loopback
address; a walker then waits ``--first-cell-timeout`` (30 s) for its first cell and walks anyway.
Its own run mode and file (``--name load_abuse``).

With ``--replicas N`` (N > 1) every run starts a fresh ``redis-server`` and N servers sharing it
(``PVS_CACHE``); the walkers go to them in turn, counters, CPU and RSS are summed over them.

Writes ``OUT/NAME.md`` (command and machine on top), ``OUT/NAME.png`` and ``OUT/NAME.json``
(``--out``, default ``benchmarks/results``; ``--name``, default ``load``).

Usage::

    python -m benchmarks.bench_load                  # village 20k: 5, 20, 50 walkers, cold, warm
    python -m benchmarks.bench_load --scene village --triangles 100000 --workers 1,2
    python -m benchmarks.bench_load --scene lyon_vilo3d --clients 20 --cache cold
    python -m benchmarks.bench_load --scene lavaducts --scenes ../shared/scenes --quick
    python -m benchmarks.bench_load --hostile --name load_abuse  # 50 walkers, with/without flood
    python -m benchmarks.bench_load --replicas 2 --name load_redis  # 2 servers share Redis
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.common import command_line, cpu_seconds, machine
from benchmarks.load.frames import FRAME_SIZE, eps_by_answer, score_samples
from benchmarks.load.hostile import (
    HOSTILE_ADDRESS,
    HOSTILE_PARAMS,
    HOSTILE_STATUSES,
    hostile_answers_text,
    hostile_box,
    hostile_client,
    hostile_flood,
)
from benchmarks.load.report import (
    abuse_table,
    capacity_lines,
    load_table,
    rerender,
    run_lines,
    write_outputs,
)
from benchmarks.load.scenes import BenchScene, WalkPlan, load_bench_scene, plan_walks, warm_cells
from benchmarks.load.servers import (
    COUNTERS,
    REDIS_HITS,
    Served,
    compile_kernels,
    serving,
    warm_up,
)
from benchmarks.load.summary import latency_summary, summarise
from benchmarks.load.walkers import run_clients
from server.settings import Settings

# Re-exported: the tests use the hostile parts and the percentiles by these names, and
# bench_redis imports ``machine`` from here.
__all__ = ["HOSTILE_ADDRESS", "HOSTILE_PARAMS", "HOSTILE_STATUSES", "hostile_answers_text",
           "hostile_box", "hostile_flood", "latency_summary", "machine", "main"]

ROOT = Path(__file__).resolve().parents[1]
#: Every ``SAMPLE_EVERY``-th frame of each answer of each walker is drawn after the run.
SAMPLE_EVERY = 5


def measure(served: Served, args: argparse.Namespace, bs: BenchScene, plan: WalkPlan,
            clients: int, cache: str, workers: int, hostile: bool | None = None) -> dict:
    """One run of ``clients`` walkers (the plan's first ones) against ``served``; its summary.
    ``hostile`` True: while the hostile client floods the server; False: a run of the abuse
    mode without it; None: a run of the default mode (no hostile fields)."""
    before = served.counters()
    cpu0, own0 = sum(cpu_seconds(p) for p in served.pids), time.process_time()
    flood = (hostile_client(served.urls[0], bs.name, args.core, args.hostile_params,
                            bs.loaded.grid.boxes, args.hostile_concurrency,
                            args.hostile_timeout, args.hostile_pause, args.seed)
             if hostile else contextlib.nullcontext({}))
    with flood as counts:
        stats, peak_rss, wall = asyncio.run(run_clients(
            served.urls, served.pids, bs.name, args.core, args.params, plan.walks[:clients],
            budget=args.budget, progressive=args.progressive,
            first_cell_timeout=args.first_cell_timeout, grace=args.grace, fps=args.fps,
            sample_every=args.sample_every))
    server_cpu = sum(cpu_seconds(p) for p in served.pids) - cpu0
    client_cpu = time.process_time() - own0
    after = served.counters()
    m = {k: after[k] - before[k] for k in COUNTERS}
    run = {"clients": clients, "cache": cache, "workers": workers, **bs.describe(),
           "core": args.core, "params": args.params, "progressive": args.progressive,
           "walk_seconds": args.duration, "speed": args.speed, "fps": args.fps,
           "grace_seconds": args.grace, "first_cell_timeout": args.first_cell_timeout,
           "walks": plan.summary(clients), "frame_size": FRAME_SIZE,
           "sample_every": args.sample_every}
    if args.replicas > 1:
        run.update(replicas=args.replicas)
    r = summarise(run, stats, m, peak_rss, wall, server_cpu, client_cpu)
    if args.replicas > 1:
        r["redis_hits"] = m[REDIS_HITS]
    r["eps_by_answer"] = eps_by_answer(score_samples(bs.loaded.scene,
                                                     [s.samples for s in stats]))
    if hostile is not None:
        r["hostile"] = hostile
    if hostile:
        r.update(hostile_answers=counts, hostile_params=args.hostile_params,
                 hostile_concurrency=args.hostile_concurrency,
                 hostile_timeout=args.hostile_timeout, hostile_pause=args.hostile_pause,
                 hostile_address=HOSTILE_ADDRESS)
    return r


def _int_list(text: str, what: str, ap: argparse.ArgumentParser) -> list[int]:
    try:
        vals = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        ap.error(f"{what} takes a comma-separated list of positive integers, got {text!r}")
    if not vals or min(vals) < 1:
        ap.error(f"{what} takes a comma-separated list of positive integers, got {text!r}")
    return vals


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line (see the module docstring); exits with a message on bad values."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", default=None,
                    help="concurrent walkers, a comma-separated list: one run per count "
                         "(default 5,20,50; with --hostile 50)")
    ap.add_argument("--workers", default="1,2",
                    help="server workers, a comma-separated list: the runs once per count "
                         "(default 1,2)")
    ap.add_argument("--duration", type=float, default=20.0, help="walk length, seconds")
    ap.add_argument("--speed", type=float, default=1.4, help="walking speed, m/s")
    ap.add_argument("--fps", type=float, default=10.0, help="poses per second")
    ap.add_argument("--scene", default="village",
                    help="a scene the server serves: a generator or a file of --scenes")
    ap.add_argument("--triangles", type=int, default=None,
                    help="size of a generated scene (default 20000); not for file scenes")
    ap.add_argument("--scenes", default=None,
                    help="folder of scene files (default as pvs serve: PVS_SCENES_DIR, else "
                         "../shared/scenes)")
    ap.add_argument("--cell-size", type=float, default=None,
                    help="viewcell size, metres (default the scene's own, else 4)")
    ap.add_argument("--core", default=Settings.model_fields["core"].default,
                    help="core the server computes with (default: the server settings' default)")
    ap.add_argument("--params", default="{}",
                    help="core parameters, JSON (default: the core's defaults)")
    ap.add_argument("--budget", type=int, default=None, help="client triangle budget")
    ap.add_argument("--replicas", type=int, default=1,
                    help="server processes sharing one fresh redis-server (PVS_CACHE); the "
                         "walkers are spread over them in turn (default 1: no Redis)")
    ap.add_argument("--progressive", action=argparse.BooleanOptionalAction, default=None,
                    help="ask for progressive streams (or not); default: the server's")
    ap.add_argument("--seed", type=int, default=0, help="walker i's walk starts at seed + i")
    ap.add_argument("--grace", type=float, default=10.0,
                    help="seconds after its walk a walker still waits for stalled frames' cells")
    ap.add_argument("--cache", default="cold,warm",
                    help="cold (a fresh server per run), warm (one server with the walks' "
                         "cells computed before the walkers come), or both")
    ap.add_argument("--sample-every", type=int, default=SAMPLE_EVERY,
                    help="draw every N-th frame of each answer of each walker for the image "
                         "error (0: none)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results",
                    help="folder for NAME.md, NAME.png and NAME.json")
    ap.add_argument("--name", default="load",
                    help="file stem of the outputs (e.g. load_lyon for another scene)")
    ap.add_argument("--no-files", action="store_true", help="print only")
    ap.add_argument("--no-warmup", action="store_true",
                    help="do not compile the kernels before the runs (known compiled: the "
                         "first cells of a run pay what is missing)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke: the first walker count (at most 5), 6 s walks, cold cache, "
                         "the first worker count")
    ap.add_argument("--hostile", action="store_true",
                    help="abuse mode: every run twice, without and with a hostile client "
                         "flooding expensive HTTP PVS requests (see the module docstring)")
    ap.add_argument("--hostile-concurrency", type=int, default=16,
                    help="the hostile client's requests in flight at once")
    ap.add_argument("--hostile-params", default=None,
                    help="core parameters of the hostile requests, JSON (default: "
                         "HOSTILE_PARAMS for the core, else resolution 2048)")
    ap.add_argument("--hostile-timeout", type=float, default=10.0,
                    help="seconds the hostile client waits for an answer before it sends "
                         "another request in its place")
    ap.add_argument("--hostile-pause", type=float, default=0.05,
                    help="seconds the hostile client waits after a refusal or a 429/503")
    ap.add_argument("--first-cell-timeout", type=float, default=None,
                    help="seconds a walker waits for its first cell before it walks anyway "
                         "(default 300; with --hostile 30)")
    ap.add_argument("--rerender", type=Path, metavar="JSON",
                    help="rewrite the tables and plot of a measured run from its JSON, "
                         "measuring nothing")
    args = ap.parse_args(argv)
    if args.rerender:
        return args
    if args.clients is None:
        args.clients = "50" if args.hostile else "5,20,50"
    args.counts = _int_list(args.clients, "--clients", ap)
    args.worker_counts = _int_list(args.workers, "--workers", ap)
    args.caches = [x.strip() for x in args.cache.split(",") if x.strip()]
    if not args.caches or set(args.caches) - {"cold", "warm"}:
        ap.error("--cache takes cold and/or warm")
    if args.first_cell_timeout is None:
        args.first_cell_timeout = 30.0 if args.hostile else 300.0
    for flag, v in (("--duration", args.duration), ("--speed", args.speed),
                    ("--fps", args.fps), ("--grace", args.grace)):
        if not (np.isfinite(v) and v > 0) and not (flag == "--speed" and v == 0):
            ap.error(f"{flag} takes a positive number, got {v}")
    if args.sample_every < 0 or args.replicas < 1:
        ap.error("--sample-every takes 0 or more, --replicas 1 or more")
    if args.hostile_concurrency < 1 or args.hostile_timeout <= 0:
        ap.error("--hostile-concurrency takes a positive count, --hostile-timeout seconds > 0")
    try:
        args.params = json.loads(args.params)
        args.hostile_params = (json.loads(args.hostile_params) if args.hostile_params else
                               HOSTILE_PARAMS.get(args.core, {"resolution": 2048}))
    except json.JSONDecodeError as exc:
        ap.error(f"--params and --hostile-params take JSON objects: {exc}")
    if not isinstance(args.params, dict) or not isinstance(args.hostile_params, dict):
        ap.error("--params and --hostile-params take JSON objects")
    if args.quick:
        args.counts = [min(args.counts[0], 5)]
        args.duration = min(args.duration, 6.0)
        args.caches = ["cold"]
        args.worker_counts = args.worker_counts[:1]
    return args


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (see the module docstring); 0 when done."""
    args = parse_args(argv)
    if args.rerender:
        rerender(args.rerender)
        return 0
    command = command_line("benchmarks.bench_load", argv)
    where = machine()
    print("command: " + command)
    print("machine: " + where)
    # Kernels missing from the numba cache compile inside the server at its first cells, so
    # they are compiled first: the runs measure serving, not compiling.
    where += ("; kernels not compiled before the runs (--no-warmup)" if args.no_warmup else
              f"; kernels compiled before the runs (`pvs warmup`): {compile_kernels():.0f} s")
    print(where.rsplit("; ", 1)[1])
    bs = load_bench_scene(args.scene, args.triangles, args.scenes, args.cell_size)
    plan = plan_walks(bs, max(args.counts), args.duration, args.speed, args.fps, args.seed)
    walks = plan.summary(max(args.counts))
    print(f"scene {bs.name} ({bs.kind}): {bs.triangles} triangles, {bs.cells} cells of "
          f"{bs.cell_size:g} m; walks: {json.dumps(walks)}")
    runs: list[dict] = []

    def report(r: dict) -> None:
        print("\n".join(run_lines(r)))
        print("json: " + json.dumps({k: v for k, v in r.items()
                                     if k not in ("latencies_s", "triangles_per_walker")}))
        runs.append(r)

    def warmed(served: Served, workers: int) -> dict:
        cells = warm_cells(bs, plan, max(args.counts))
        secs = asyncio.run(warm_up(served.urls[0], bs.name, args.core, args.params, cells,
                                   workers))
        print(f"warm-up: {len(cells)} cells computed in {secs:.1f} s")
        return {"warm_up_seconds": secs, "warm_cells": len(cells)}

    for workers in args.worker_counts:
        if args.hostile:
            # Pairs: the same run without, then with the hostile client.
            for cache in args.caches:
                for n in args.counts:
                    if cache == "cold":
                        for hostile in (False, True):
                            with serving(bs, args.core, workers, args.replicas) as served:
                                report(measure(served, args, bs, plan, n, "cold", workers,
                                               hostile))
                        continue
                    with serving(bs, args.core, workers, args.replicas) as served:
                        w = warmed(served, workers)
                        for hostile in (False, True):
                            report({**measure(served, args, bs, plan, n, "warm", workers,
                                              hostile), **w})
            continue
        if "cold" in args.caches:
            for n in args.counts:
                with serving(bs, args.core, workers, args.replicas) as served:
                    report(measure(served, args, bs, plan, n, "cold", workers))
        if "warm" in args.caches:
            with serving(bs, args.core, workers, args.replicas) as served:
                w = warmed(served, workers)
                for n in args.counts:
                    report({**measure(served, args, bs, plan, n, "warm", workers), **w})
    print("\n".join(abuse_table(runs) if args.hostile
                    else capacity_lines(runs) + [""] + load_table(runs)))
    if not args.no_files:
        write_outputs(args.out, args.name, command, where, runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
