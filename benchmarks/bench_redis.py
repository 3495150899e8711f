"""Shared-cache benchmark: a PVS hit from Redis against hits from memory and from disk.

Starts its own ``redis-server`` on a free loopback port (``benchmarks.redis_process``: no
persistence, 256 MB ``maxmemory``, LRU) and a ``ComputeService`` with all three tiers (memory,
``cache_dir`` in a temporary folder, ``cache=redis://…``), computes the PVS of ``--cells``
cells spread evenly over the scene's grid (``viewcells.spread_evenly``), then measures, cell
after cell and tier after tier in turn, ``--repeats`` rounds:

- the tier alone: ``PVSCache.get`` (memory), ``DiskPVSCache.get`` (an ``.npz`` read and
  checked), ``SharedCache.get_pvs`` (a Redis GET over loopback, decoded and checked);
- through the service, as a request sees it: ``ComputeService.submit(...).result()`` with the
  memory cache holding the cell (memory), or emptied before each call and only the disk, or
  only Redis, behind it (the lookup then runs on the worker pool, as a real miss does);
- the value sizes: the raw ids (4 bytes each), the ``.npz`` file, the Redis value (int32 gaps
  under zlib level 1) and the same value without zlib, with the codec's encode and decode
  times, so the compression is justified by figures.

Prints the tables and writes ``OUT/NAME.md`` and ``OUT/NAME.json`` (``--out``, default
``benchmarks/results``; ``--name``, default ``redis``). Usage::

    python -m benchmarks.bench_redis                  # village 20k, 12 cells, sampling
    python -m benchmarks.bench_redis --quick --no-files   # smoke: rooms 4k, 4 cells
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from benchmarks.bench_load import machine
from benchmarks.redis_process import RedisProcess, available
from server.cache.codec import decode_pvs, encode_pvs
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.resolve import Resolver
from server.settings import Settings
from visibility.viewcells import spread_evenly

ROOT = Path(__file__).resolve().parents[1]


def timed(fn: Callable[[], object]) -> float:
    """Seconds ``fn()`` took; AssertionError when it answered None (a miss)."""
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    assert out is not None, "expected a hit"
    return dt


def summary(xs: list[float]) -> dict[str, float]:
    """Median, p95 (nearest rank) and mean of ``xs`` seconds."""
    s = sorted(xs)
    return {"n": len(s), "median_s": statistics.median(s),
            "p95_s": s[min(len(s) - 1, int(np.ceil(0.95 * len(s))) - 1)],
            "mean_s": statistics.fmean(s)}


def measure(args: argparse.Namespace) -> dict:
    redis = RedisProcess(maxmemory="256mb").start()
    tmp = tempfile.TemporaryDirectory(prefix="pvs-bench-redis-")
    settings = Settings(
        generated={args.scene: args.triangles}, scenes_dir=None, cell_size=args.cell_size,
        core=args.core, core_params=args.params, workers=args.workers,
        cache_dir=Path(tmp.name), cache=redis.url, calibrate=False, progressive=False,
        cache_bytes=1 << 30)
    service = ComputeService(SceneCatalog(settings), settings)
    try:
        loaded = service.catalog.get(args.scene)
        n = loaded.scene.n_triangles
        cells = spread_evenly(np.arange(len(loaded.grid)), args.cells)
        choice = Resolver(settings).resolve(args.core, args.params, loaded)
        core, params = choice.core, choice.params
        t0 = time.perf_counter()
        results = [service.submit(args.scene, core, params, cell=c) for c in cells]
        results = [f.result() for f in results]
        fill = time.perf_counter() - t0
        print(f"computed {len(cells)} cells in {fill:.1f} s "
              f"({sum(r.seconds for r in results):.1f} s of computation)")
        # One key for every tier; Redis stores it as its ``shared()`` string.
        keys = {c: service.key(args.scene, core, params, c) for c in cells}
        tiered = service.cache
        disk, shared, memory = tiered.disk, tiered.shared, tiered.memory
        tiers: dict[str, list[float]] = {k: [] for k in ("memory", "disk", "redis")}
        via: dict[str, list[float]] = {k: [] for k in ("memory", "disk", "redis")}

        def through(tier: str, cell: int) -> float:
            if tier != "memory":
                memory.clear()
            tiered.disk = disk if tier == "disk" else None
            tiered.shared = shared if tier == "redis" else None
            try:
                dt = timed(lambda: service.submit(args.scene, core, params, cell=cell).result())
            finally:
                tiered.disk, tiered.shared = disk, shared
            for c, r in zip(cells, results, strict=True):  # the memory tier as it was
                memory.put(keys[c], r.pvs)
            return dt

        for _ in range(args.repeats):
            for c in cells:
                k = keys[c]
                tiers["memory"].append(timed(lambda k=k: memory.get(k)))
                tiers["disk"].append(timed(lambda k=k: disk.get(k, n_triangles=n)))
                tiers["redis"].append(timed(lambda k=k: shared.get_pvs(k.shared(), n)))
                for tier in via:
                    via[tier].append(through(tier, c))
        sizes = []
        client = redis.client()
        for c, r in zip(cells, results, strict=True):
            rk = keys[c].shared()
            ids = r.pvs.triangle_ids
            value = client.get(rk)
            raw = encode_pvs(rk, r.pvs, n, compress=False)
            enc = [timed(lambda p=r.pvs, rk=rk: encode_pvs(rk, p, n)) for _ in range(20)]
            dec = [timed(lambda v=value, rk=rk: decode_pvs(rk, v, n)) for _ in range(20)]
            dec_raw = [timed(lambda v=raw, rk=rk: decode_pvs(rk, v, n)) for _ in range(20)]
            sizes.append({"cell": int(c), "ids": int(len(ids)), "raw_bytes": int(4 * len(ids)),
                          "npz_bytes": disk.path(keys[c]).stat().st_size,
                          "redis_bytes": len(value), "redis_raw_bytes": len(raw),
                          "encode_s": statistics.median(enc),
                          "decode_s": statistics.median(dec),
                          "decode_raw_s": statistics.median(dec_raw)})
        version = client.info().get("redis_version", "?")
        client.close()
        return {"redis_version": version, "scene": args.scene, "triangles": int(n),
                "cell_size": args.cell_size, "core": core.name, "params": params.as_dict(),
                "cells": [int(c) for c in cells],
                "repeats": args.repeats, "workers": args.workers, "fill_seconds": fill,
                "compute_seconds": [r.seconds for r in results],
                "tier": {k: summary(v) for k, v in tiers.items()},
                "service": {k: summary(v) for k, v in via.items()}, "sizes": sizes,
                "redis_stats": shared.stats()}
    finally:
        service.shutdown()
        redis.close()
        tmp.cleanup()


def tables(r: dict) -> list[str]:
    """The report's tables (markdown)."""
    def us(x: float) -> str:
        return f"{1e6 * x:,.0f}"

    comp = sorted(r["compute_seconds"])
    lines = ["| tier | alone: median µs | alone: p95 µs | through the service: median µs | "
             "through the service: p95 µs |", "|---|---|---|---|---|"]
    for tier in ("memory", "disk", "redis"):
        a, s = r["tier"][tier], r["service"][tier]
        lines.append(f"| {tier} | {us(a['median_s'])} | {us(a['p95_s'])} | "
                     f"{us(s['median_s'])} | {us(s['p95_s'])} |")
    lines += ["", f"A computation of these cells took {statistics.median(comp):.2f} s (median; "
              f"{comp[0]:.2f} to {comp[-1]:.2f} s).", "",
              "| cell | ids | raw ids bytes | .npz bytes | Redis value bytes | without zlib | "
              "encode µs | decode µs | decode without zlib µs |",
              "|---|---|---|---|---|---|---|---|---|"]
    for s in r["sizes"]:
        lines.append(f"| {s['cell']} | {s['ids']:,} | {s['raw_bytes']:,} | {s['npz_bytes']:,} | "
                     f"{s['redis_bytes']:,} | {s['redis_raw_bytes']:,} | {us(s['encode_s'])} | "
                     f"{us(s['decode_s'])} | {us(s['decode_raw_s'])} |")
    tot = {k: sum(s[k] for s in r["sizes"]) for k in ("raw_bytes", "npz_bytes", "redis_bytes",
                                                      "redis_raw_bytes")}
    lines.append(f"| all | {sum(s['ids'] for s in r['sizes']):,} | {tot['raw_bytes']:,} | "
                 f"{tot['npz_bytes']:,} | {tot['redis_bytes']:,} | {tot['redis_raw_bytes']:,} "
                 "| | | |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="village")
    ap.add_argument("--triangles", type=int, default=20_000)
    ap.add_argument("--cell-size", type=float, default=4.0)
    ap.add_argument("--core", default="sampling")
    ap.add_argument("--params", default="{}", help="core parameters, JSON")
    ap.add_argument("--cells", type=int, default=12)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--name", default="redis")
    ap.add_argument("--no-files", action="store_true", help="print only")
    ap.add_argument("--quick", action="store_true", help="rooms 4k, 4 cells, 5 repeats")
    args = ap.parse_args(argv)
    if args.quick:
        args.scene, args.triangles, args.cells, args.repeats = "rooms", 4000, 4, 5
    args.params = json.loads(args.params)
    if not available():
        raise SystemExit("redis-server is not installed (scripts/setup.sh installs it)")
    command = ("python -m benchmarks.bench_redis " + " ".join(
        argv if argv is not None else sys.argv[1:])).strip()
    where = machine()
    print("command: " + command)
    print("machine: " + where)
    r = measure(args)
    body = tables(r)
    print("\n".join(body))
    if args.no_files:
        return 0
    md = ["# Shared cache: Redis hits against memory and disk hits", "",
          f"command: `{command}`", "", f"machine: {where}", "",
          f"Scene `{r['scene']}` ({r['triangles']:,} triangles, {r['cell_size']:g} m cells), "
          f"core `{r['core']}` with `{json.dumps(r['params'])}`, {len(r['cells'])} cells, "
          f"{r['repeats']} rounds, {r['workers']} workers. redis-server {r['redis_version']} on "
          "loopback (no persistence). *Alone*: the tier's own lookup (memory LRU get; .npz read "
          "and checked; Redis GET, decoded and checked). *Through the service*: "
          "`ComputeService.submit(...).result()`; for disk and Redis the memory cache is "
          "emptied first and only that tier stands behind it, so the lookup runs on the "
          "worker pool as a real memory miss does.", "", *body, "",
          "Redis values are the id gaps of the sorted set, int32, under zlib level 1 "
          "(`server.cache.codec`).", ""]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text("\n".join(md))
    (args.out / f"{args.name}.json").write_text(json.dumps(
        {"command": command, "machine": where, **r}, indent=1))
    print(f"wrote {args.out / args.name}.md, .json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
