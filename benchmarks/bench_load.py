"""Load benchmark: N concurrent protocol clients replaying walkthroughs against a real server.

Starts ``python -m pvs_cli serve`` on a free loopback port (configured through ``PVS_*``
environment variables), then runs N asyncio clients (``client.session.Session``: receiving and
accounting, not rendering), each replaying its own generated walkthrough
(``client.walkthrough.generate_walkthrough``) at real-time pacing. One run per client count
(``--clients 5,10,20,50``) and cache state: cold (a fresh server, every PVS computed while the
walkers walk: the computing capacity) and warm (every cell's PVS computed through the HTTP route
before the clients come, as an edge server started from its disk cache: the streaming
capacity). Prints a table per run and a capacity table of all runs, the command line on top:

- stalls: frames whose cell was not complete one frame interval after the pose was sent (the
  first cell of each client, waited for before its clock starts, is not counted); frames whose
  cell is still missing ``--grace`` seconds after the walk count as never delivered;
- frame delivery latency p50/p95: per frame, the time from sending its pose until the client
  holds the pose's cell complete (0 when it already did);
- bytes received by the clients and bytes sent according to the server's /metrics;
- server memory: the RSS of the server process (``/proc/PID/status``), peak over the run;
- duplicates (triangles received twice without a drop between: must be 0) and client errors.

The core runs at its default settings (``--params '{}'``) unless told otherwise. Where the time
goes is printed too: the server's CPU seconds (``/proc/PID/stat``), the computation seconds it
reports (``pvs_computation_seconds_sum``) and the clients' CPU seconds, against the wall time.

Abuse mode (``--hostile``): each run is made twice on the same settings, once as above and once
while a hostile client floods the server with expensive HTTP PVS requests (``POST
/scenes/{scene}/pvs``, every box different so nothing is shared through the cache, parameters
far above the defaults: ``HOSTILE_PARAMS``, ``--hostile-params``), ``--hostile-concurrency`` at
once, each abandoned after ``--hostile-timeout`` seconds and sent anew, reconnecting when
refused. It runs in its own process (its flood must not slow the walkers' own event loop) from
another loopback source address (``127.0.0.2``), so a per-client cap keyed by address applies to
it and not to the walkers. The abuse table puts each pair side by side: the walkers' stalls and
latency with and without it, the server's peak RSS and the hostile's answers by status (200,
422, 429, 503, other; refused connections, requests it gave up on, requests still unanswered
when it stopped). Cold pairs run on two fresh servers; a warm pair on one warmed server, the
hostile row last so the work it leaves queued cannot slow the row without it. A flooded server
may never compute a walker's first cell, so in this mode a walker waits ``--first-cell-timeout``
(30 s) for it and then walks anyway, its frames counted. Its own run mode, not part of the
default runs: the default runs measure capacity and are published as ``load.md``; the abuse
pairs double every run, last longer (the grace waits of a flooded server), and measure admission
control instead, so they go to their own file (``--name load_abuse``).

Writes the tables (command and machine on top) to ``OUT/NAME.md``, a PNG with the
frame-latency distributions and the stalled share against the client count to ``OUT/NAME.png``
and every number to ``OUT/NAME.json`` (``--out``, default ``benchmarks/results``; ``--name``,
default ``load``).

Usage::

    python -m benchmarks.bench_load              # 5, 10, 20, 50 clients, cold and warm, 20 s walks
    python -m benchmarks.bench_load --clients 50 --cache cold
    python -m benchmarks.bench_load --core from_segment --name load_from_segment
    python -m benchmarks.bench_load --quick      # 5 clients, 6 s walks, cold (smoke)
    python -m benchmarks.bench_load --hostile --name load_abuse  # 50 walkers, with/without flood
    python -m benchmarks.bench_load --hostile --quick --no-files  # the same, smoke
    python -m benchmarks.bench_load --replicas 2 --name load_redis  # 2 servers share Redis

With ``--replicas N`` (N > 1) every run starts a fresh ``redis-server`` and N server processes
sharing it (``PVS_CACHE``); the walkers go to them in turn, counters, CPU and RSS are summed
over them, and the warm-up computes through the first one only (the others find every cell in
Redis). The tables add the PVS answered from Redis.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing
import os
import platform
import random
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from client.session import Session, SessionError  # noqa: E402
from client.walkthrough import generate_walkthrough  # noqa: E402
from pvs_cli import wait_until_healthy  # noqa: E402
from server.settings import Settings  # noqa: E402
from visibility.generators import make_scene  # noqa: E402
from visibility.viewcells import ViewcellGrid  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_bytes(pid: int) -> int:
    """Resident set size of process ``pid``, bytes (0 when unreadable)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (``/proc/PID/stat``; NaN when unreadable)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def machine() -> str:
    """CPU model, logical cores, memory and OS of this machine, one line."""
    model = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
        mem = next(int(x.split()[1]) for x in Path("/proc/meminfo").read_text().splitlines()
                   if x.startswith("MemTotal:"))
        mem_s = f", {mem / 2**20:.1f} GiB RAM"
    except (OSError, StopIteration, ValueError):
        mem_s = ""
    return f"{model}, {os.cpu_count()} logical cores{mem_s}, {platform.platform()}"


def metric(text: str, name: str) -> float:
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[-1])
    return float("nan")


class ClientStats:
    def __init__(self) -> None:
        self.frames = 0
        self.stalls = 0
        self.latencies: list[float] = []
        self.bytes = 0
        self.duplicates = 0
        self.dropped = 0
        self.first_cell_timeouts = 0
        self.errors: list[str] = []
        #: Frames by the answer their cell held when drawn (``cell_begin.answer``: "first",
        #: "refined", "full"), "stalled" when it had none in time.
        self.answers: dict[str, int] = {}
        #: (eye, forward, ids held, answer) of some frames, drawn after the run (``frame_eps``).
        self.samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]] = []


#: Frames whose error is measured after the run: every SAMPLE_EVERY-th frame of the first
#: SAMPLE_CLIENTS walkers (the ids each held then are kept).
SAMPLE_CLIENTS = 4
SAMPLE_EVERY = 5


async def one_client(url: str, args: argparse.Namespace, grid: ViewcellGrid, seed: int,
                     stats: ClientStats, sample: bool = False) -> None:
    walk = generate_walkthrough(grid, duration=args.duration, speed=args.speed, fps=args.fps,
                                seed=seed)
    pos, t = walk.positions, walk.t
    vel = np.gradient(pos, t, axis=0) if len(t) > 1 else np.zeros_like(pos)
    pending: list[asyncio.Task] = []
    try:
        s = await Session.connect(url, args.scene, args.core, args.params, budget=args.budget,
                                  timeout=120, progressive=args.progressive)
    except (SessionError, OSError, TimeoutError) as exc:
        stats.errors.append(f"connect: {exc}")
        return
    try:
        first = grid.cell_of(pos[0])
        await s.send_pose(0, 0.0, pos[0], walk.forwards[0], vel[0])
        try:
            await s.wait_cell(first, args.first_cell_timeout)
        except TimeoutError:
            # A flooded server may never get to it: walk anyway, so the frames still count.
            stats.first_cell_timeouts += 1
        t0 = time.perf_counter()
        frame = 1.0 / args.fps

        async def late(cell: int, sent: float) -> None:
            try:
                await s.wait_cell(cell, None)
                stats.latencies.append(time.perf_counter() - sent)
            except SessionError:
                stats.latencies.append(float("inf"))

        for i in range(1, len(walk)):
            await asyncio.sleep(max(0.0, t0 + t[i] - t[0] - time.perf_counter()))
            sent = time.perf_counter()
            await s.send_pose(i, float(t[i]), pos[i], walk.forwards[i], vel[i])
            stats.frames += 1
            cell = grid.cell_of(pos[i])
            if s.is_complete(cell):
                stats.latencies.append(0.0)
            else:
                try:
                    await s.wait_cell(cell, frame)
                    stats.latencies.append(time.perf_counter() - sent)
                except TimeoutError:
                    stats.stalls += 1
                    pending.append(asyncio.create_task(late(cell, sent)))
            held = s.cells.get(cell)
            answer = (held.answer if held is not None else None) or "stalled"
            stats.answers[answer] = stats.answers.get(answer, 0) + 1
            if sample and i % SAMPLE_EVERY == 0 and answer != "stalled":
                stats.samples.append((pos[i].copy(), walk.forwards[i].copy(),
                                      s.store.ids.copy(), answer))
        if pending:
            # A cell the walker has left may never come (the server drops prefetch work no
            # walker is heading for): after a grace period it counts as never delivered.
            _, late_ones = await asyncio.wait(pending, timeout=args.grace)
            for task in late_ones:
                task.cancel()
            stats.latencies += [float("inf")] * len(late_ones)
    except SessionError as exc:
        stats.errors.append(str(exc))
    finally:
        stats.bytes = s.bytes_received
        stats.duplicates = s.duplicates
        stats.dropped = s.dropped
        stats.errors += [f"{e.code}: {e.message}" for e in s.errors]
        stats.errors += s.local_errors
        await s.close()


#: Expensive parameters of the hostile client's requests, per core (``--hostile-params``): far
#: above the defaults, within each parameter's declared range so they pass validation.
HOSTILE_PARAMS: dict[str, dict] = {"sampling": {"resolution": 2048, "samples": 100_000},
                                   "from_segment": {"resolution": 2048},
                                   "cos": {"resolution": 2048}}
#: The hostile client's source address: another loopback address than the walkers' 127.0.0.1.
HOSTILE_ADDRESS = "127.0.0.2"
#: The statuses the hostile's answers are counted by; anything else counts as "other".
HOSTILE_STATUSES = (200, 422, 429, 503)


def hostile_box(cells: np.ndarray, rng: random.Random) -> list[list[float]]:
    """A random box near a random cell of ``cells`` ((k, 2, 3) [min, max]): shifted by up to
    half the cell and shrunk by up to half, so no two requests ask the same question."""
    lo, hi = cells[rng.randrange(len(cells))]
    size = hi - lo
    shift = np.array([rng.uniform(-0.5, 0.5) for _ in range(3)]) * size * np.array([1, 0, 1])
    scale = rng.uniform(0.5, 1.0)
    centre = 0.5 * (lo + hi) + shift
    half = 0.5 * size * scale
    return [(centre - half).tolist(), (centre + half).tolist()]


async def hostile_flood(url: str, scene: str, core: str, params: dict, cells: np.ndarray,
                        concurrency: int, timeout: float, pause: float, seed: int,
                        stop: Callable[[], bool], started: Callable[[], None]) -> dict:
    """Flood ``POST /scenes/{scene}/pvs`` with expensive ad-hoc boxes from ``HOSTILE_ADDRESS``
    until ``stop()``: ``concurrency`` requests at once, each abandoned after ``timeout`` s and
    replaced by a new one; after a refused connection or a 429/503 a loop waits ``pause`` s
    and sends again. Returns the answers counted by status and what went unanswered."""
    counts: dict = {"sent": 0, **{str(c): 0 for c in HOSTILE_STATUSES}, "other": 0,
                    "refused": 0, "timeout": 0, "unfinished": 0, "other_statuses": {}}
    inflight = [0]
    rng = random.Random(seed)
    transport = httpx.AsyncHTTPTransport(local_address=HOSTILE_ADDRESS)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    async with httpx.AsyncClient(base_url=url, transport=transport, timeout=timeout,
                                 limits=limits) as http:
        async def loop() -> None:
            while True:
                body = {"box": hostile_box(cells, rng), "core": core, "params": params}
                counts["sent"] += 1
                inflight[0] += 1
                try:
                    r = await http.post(f"/scenes/{scene}/pvs", json=body)
                except httpx.TimeoutException:
                    counts["timeout"] += 1
                    continue
                except httpx.TransportError:
                    counts["refused"] += 1
                    await asyncio.sleep(pause)
                    continue
                finally:
                    inflight[0] -= 1
                if r.status_code in HOSTILE_STATUSES:
                    counts[str(r.status_code)] += 1
                else:
                    counts["other"] += 1
                    other = counts["other_statuses"]
                    other[str(r.status_code)] = other.get(str(r.status_code), 0) + 1
                if r.status_code in (429, 503):
                    await asyncio.sleep(pause)

        tasks = [asyncio.create_task(loop()) for _ in range(concurrency)]
        started()
        while not stop():
            await asyncio.sleep(0.1)
        counts["unfinished"] = inflight[0]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    return counts


def _hostile_main(url: str, scene: str, core: str, params: dict, cells: np.ndarray,
                  concurrency: int, timeout: float, pause: float, seed: int, stop_ev: object,
                  started_ev: object, out: object) -> None:
    """The hostile client's process: flood until ``stop_ev`` is set, put the counts on
    ``out``."""
    out.put(asyncio.run(hostile_flood(url, scene, core, params, cells, concurrency, timeout,
                                      pause, seed, stop_ev.is_set, started_ev.set)))


@contextlib.contextmanager
def hostile_client(url: str, args: argparse.Namespace, grid: ViewcellGrid) -> Iterator[dict]:
    """Run the hostile client (its own process, ``spawn``: this process runs threads) for the
    ``with`` block; the dict it yields holds its counts once the block has ended."""
    ctx = multiprocessing.get_context("spawn")
    stop_ev, started_ev, out = ctx.Event(), ctx.Event(), ctx.Queue()
    cells = np.stack([grid.cell(i).box for i in range(len(grid))])
    proc = ctx.Process(target=_hostile_main, daemon=True, args=(
        url, args.scene, args.core, args.hostile_params, cells, args.hostile_concurrency,
        args.hostile_timeout, args.hostile_pause, args.seed, stop_ev, started_ev, out))
    proc.start()
    counts: dict = {}
    try:
        if not started_ev.wait(120):
            raise RuntimeError("the hostile client did not start")
        yield counts
    finally:
        stop_ev.set()
        try:
            counts.update(out.get(timeout=60))
        except Exception as exc:  # a lost count must not lose the walkers' numbers
            counts["error"] = f"{type(exc).__name__}: {exc}"
        proc.join(10)
        if proc.is_alive():
            proc.kill()


async def run_clients(url: str | list[str], args: argparse.Namespace, clients: int,
                      grid: ViewcellGrid, pid: int | list[int]
                      ) -> tuple[list[ClientStats], int, float]:
    """The run's walkers (client i on replica i mod N when ``url`` lists several), their stats,
    the servers' peak RSS (summed over replicas) and the wall time."""
    stats = [ClientStats() for _ in range(clients)]
    urls, pids = as_list(url), as_list(pid)
    peak = [sum(rss_bytes(p) for p in pids)]

    async def sample_rss() -> None:
        while True:
            peak[0] = max(peak[0], sum(rss_bytes(p) for p in pids))
            await asyncio.sleep(0.25)

    sampler = asyncio.create_task(sample_rss())
    t0 = time.perf_counter()
    # Stagger the starts over a second, as real clients arrive.
    async def delayed(i: int) -> None:
        await asyncio.sleep(i / max(1, clients))
        await one_client(urls[i % len(urls)], args, grid, args.seed + i, stats[i],
                         sample=i < SAMPLE_CLIENTS)

    await asyncio.gather(*(delayed(i) for i in range(clients)))
    wall = time.perf_counter() - t0
    sampler.cancel()
    return stats, peak[0], wall


#: PVS answered from the shared Redis cache (``--replicas``; NaN without Redis).
REDIS_HITS = 'pvs_cache_tier_hits_total{kind="pvs",tier="redis"}'
#: Server counters the summary reports (``/metrics``), as differences over one run.
COUNTERS = ("pvs_bytes_sent_total", "pvs_computations_total", "pvs_stalls_total",
            "pvs_computation_seconds_sum", "pvs_cache_hits_total",
            "pvs_computations_shared_total", "pvs_prefetch_skipped_total",
            "pvs_prefetch_yields_total", "pvs_slow_clients_total", REDIS_HITS)


def counters(url: str | list[str]) -> dict[str, float]:
    """The server's ``COUNTERS`` now (summed over replicas)."""
    texts = [httpx.get(u + "/metrics", timeout=30).text for u in as_list(url)]
    return {k: sum(metric(t, k) for t in texts) for k in COUNTERS}


def summarise(args: argparse.Namespace, clients: int, cache: str, scene_triangles: int,
              cells: int, stats: list[ClientStats], peak_rss: int, wall: float,
              m: dict[str, float], server_cpu: float, client_cpu: float) -> dict:
    """Every number of one run (the JSON output; the table is made from it). ``cache`` is
    "cold" (a fresh server) or "warm" (every cell's PVS computed before the clients came);
    ``m`` the server's counters over the run."""
    lat = np.array([x for s in stats for x in s.latencies])
    finite = lat[np.isfinite(lat)]
    frames = sum(s.frames for s in stats)
    stalls = sum(s.stalls for s in stats)
    answers: dict[str, int] = {}
    for st in stats:
        for k, v in st.answers.items():
            answers[k] = answers.get(k, 0) + v
    return {
        "progressive": args.progressive, "frames_by_answer": answers,
        "first_answer_share": answers.get("first", 0) / max(1, frames),
        "clients": clients, "cache": cache, "scene": args.scene, "triangles": scene_triangles,
        "cells": cells, "core": args.core, "params": args.params, "workers": args.workers,
        "walk_seconds": args.duration, "speed": args.speed, "fps": args.fps,
        "frames": frames, "stalls": stalls, "stall_fraction": stalls / max(1, frames),
        "clients_with_stalls": sum(1 for s in stats if s.stalls),
        "stalls_per_client": [s.stalls for s in stats],
        **latency_summary(finite, int(np.sum(~np.isfinite(lat)))),
        "latencies_s": [round(float(x), 5) for x in finite],
        "frames_never_delivered": int(np.sum(~np.isfinite(lat))),
        "bytes_received": sum(s.bytes for s in stats),
        "bytes_sent": m["pvs_bytes_sent_total"],
        "computations": m["pvs_computations_total"],
        "computation_seconds": m["pvs_computation_seconds_sum"],
        "cache_hits": m["pvs_cache_hits_total"],
        "computations_shared": m["pvs_computations_shared_total"],
        "prefetch_skipped": m["pvs_prefetch_skipped_total"],
        "prefetch_yields": m["pvs_prefetch_yields_total"],
        "slow_clients": m["pvs_slow_clients_total"],
        **({"replicas": args.replicas, "redis_hits": m[REDIS_HITS]} if args.replicas > 1
           else {}),
        "server_stalls": m["pvs_stalls_total"],
        "server_rss_peak_bytes": peak_rss,
        "server_cpu_seconds": server_cpu, "client_cpu_seconds": client_cpu,
        "duplicates": sum(s.duplicates for s in stats),
        "dropped": sum(s.dropped for s in stats),
        "client_errors": sum(len(s.errors) for s in stats),
        "first_cell_timeouts": sum(s.first_cell_timeouts for s in stats),
        "errors_sample": [e for s in stats for e in s.errors][:5],
        "wall_seconds": wall, "cell_size": args.cell_size, "grace_seconds": args.grace,
        "first_cell_timeout": args.first_cell_timeout,
    }


def latency_summary(delivered: np.ndarray, never: int) -> dict:
    """p50/p95 (nearest rank) over every frame, a frame never delivered counting as later than
    any delivered one: None when the percentile falls on such a frame (printed "never"), or
    when there are no frames. ``latency_max_s`` is the largest delivered latency."""
    d = np.sort(np.asarray(delivered, dtype=float))
    n = len(d) + int(never)
    out: dict = {"latency_max_s": float(d[-1]) if len(d) else None}
    for q in (50, 95):
        rank = int(np.ceil(q / 100.0 * n)) - 1  # nearest rank, 0-based
        out[f"latency_p{q}_s"] = float(d[rank]) if 0 <= rank < len(d) else None
    return out


def table(r: dict) -> list[tuple[str, str]]:
    """The printed rows of summary ``r``."""
    def ms(x: float | None) -> str:
        return ("n/a" if not r["frames"] else "never") if x is None else f"{1e3 * x:.1f} ms"

    return [
        ("clients / cache", f"{r['clients']} / {r['cache']}"),
        ("scene / triangles / cells", f"{r['scene']} / {r['triangles']} / {r['cells']}"),
        ("core / params / workers", f"{r['core']} / {json.dumps(r['params'])} / {r['workers']}"),
        ("walk", f"{r['walk_seconds']:g} s at {r['speed']:g} m/s, {r['fps']:g} fps"),
        ("frames", f"{r['frames']}"),
        ("stalls", f"{r['stalls']} ({100.0 * r['stall_fraction']:.2f} %)"),
        ("progressive", "server default" if r.get("progressive") is None
         else ("on" if r["progressive"] else "off")),
        ("frames by answer", ", ".join(f"{k} {v}" for k, v in
                                       sorted((r.get("frames_by_answer") or {}).items()))),
        *((f"ε {a} (sampled frames)", f"{e['eps_mean']:.3f} % mean, {e['eps_worst']:.3f} % "
           f"worst, SSIM {e['ssim_mean']:.4f} ({e['frames']} frames)")
          for a, e in (r.get("frame_error_by_answer") or {}).items()),
        ("clients with stalls", f"{r['clients_with_stalls']}"),
        ("frame latency p50", ms(r["latency_p50_s"])),
        ("frame latency p95", ms(r["latency_p95_s"])),
        ("frame latency max (delivered)", ms(r["latency_max_s"])),
        ("frames never delivered", f"{r['frames_never_delivered']}"),
        ("bytes received (clients)", f"{r['bytes_received'] / 1e6:.2f} MB"),
        ("bytes sent (server metrics)", f"{r['bytes_sent'] / 1e6:.2f} MB"),
        ("PVS computations / cache hits", f"{r['computations']:.0f} / {r['cache_hits']:.0f}"),
        *((("replicas / PVS from Redis", f"{r['replicas']} / {r['redis_hits']:.0f}"),)
          if "replicas" in r else ()),
        ("joined in-flight / prefetch skipped",
         f"{r['computations_shared']:.0f} / {r['prefetch_skipped']:.0f}"),
        ("prefetch yields / slow clients",
         f"{r['prefetch_yields']:.0f} / {r['slow_clients']:.0f}"),
        ("server stalls (metrics)", f"{r['server_stalls']:.0f}"),
        ("server RSS peak", f"{r['server_rss_peak_bytes'] / 2**20:.1f} MiB"),
        ("computation seconds (server)", f"{r['computation_seconds']:.1f} s"),
        ("server CPU", f"{r['server_cpu_seconds']:.1f} s"),
        ("clients CPU (this process)", f"{r['client_cpu_seconds']:.1f} s"),
        ("duplicate triangles", f"{r['duplicates']}"),
        ("triangles dropped", f"{r['dropped']}"),
        ("client errors", f"{r['client_errors']}"),
        ("wall time", f"{r['wall_seconds']:.1f} s"),
    ] + hostile_rows(r)


def hostile_rows(r: dict) -> list[tuple[str, str]]:
    """The printed rows about the hostile client and late first cells (none for a run of the
    default mode, whose layout stays as it was)."""
    rows = []
    if "hostile" in r or r.get("first_cell_timeouts"):
        rows.append(("first cells late (walked anyway)", f"{r.get('first_cell_timeouts', 0)}"))
    if "hostile" in r:
        rows.append(("hostile client", "yes" if r["hostile"] else "no"))
    if r.get("hostile"):
        h = r["hostile_answers"]
        rows += [("hostile requests / concurrency / params",
                  f"{h.get('sent', 0)} / {r['hostile_concurrency']} / "
                  f"{json.dumps(r['hostile_params'])}"),
                 ("hostile answers", hostile_answers_text(h))]
    return rows


def hostile_answers_text(h: dict) -> str:
    """The hostile's answers by status, one line."""
    if "error" in h and "sent" not in h:
        return f"not counted: {h['error']}"
    bits = [f"{c}: {h.get(str(c), 0)}" for c in HOSTILE_STATUSES]
    other = h.get("other_statuses") or {}
    bits.append(f"other: {h.get('other', 0)}" + (f" ({json.dumps(other)})" if other else ""))
    bits += [f"refused: {h.get('refused', 0)}", f"gave up: {h.get('timeout', 0)}",
             f"unanswered at stop: {h.get('unfinished', 0)}"]
    return ", ".join(bits)


def plot(runs: list[dict], path: Path) -> None:
    """Frame-latency distribution (CDF) per run and stalled share of frames against the number
    of clients, cold and warm cache, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for r in runs:
        lat = np.sort(np.asarray(r["latencies_s"], dtype=float)) * 1e3
        label = f"{r['clients']} clients, {r['cache']}" + (", hostile" if r.get("hostile")
                                                           else "")
        if len(lat):
            # Never-delivered frames stay off the curve, so it ends below 1.
            n = len(lat) + r["frames_never_delivered"]
            a.plot(lat, np.arange(1, len(lat) + 1) / n, drawstyle="steps-post",
                   ls="-" if r["cache"] == "cold" else "--", label=label)
        elif r["frames"]:
            a.plot([], [], ls="none", label=label + ": no frame delivered")
    if runs:
        a.axvline(1e3 / runs[0]["fps"], color="grey", ls=":", label="one frame interval")
    a.set_xscale("symlog", linthresh=1.0)
    a.set_xlim(left=0.0)
    a.set_xlabel("frame delivery latency (ms, 0 when the cell was already there)")
    a.set_ylabel("fraction of frames")
    a.set_title("frame delivery latency")
    a.legend(loc="lower right", fontsize=7)
    if any(r.get("hostile") for r in runs):
        # Abuse mode: each pair side by side, without and with the hostile client.
        keys = list(dict.fromkeys((r["clients"], r["cache"]) for r in runs))
        x = np.arange(len(keys))
        for off, hostile, colour in ((-0.2, False, "C0"), (0.2, True, "C3")):
            vals = [next((100.0 * r["stall_fraction"] for r in runs
                          if (r["clients"], r["cache"]) == k
                          and bool(r.get("hostile")) == hostile), 0.0) for k in keys]
            b.bar(x + off, vals, 0.4, color=colour,
                  label="with the hostile client" if hostile else "without")
        b.set_xticks(x, [f"{n} clients\n{cache} cache" for n, cache in keys])
        b.set_ylabel("stalled frames (%)")
        b.set_title("stalls with and without a hostile client")
        b.legend()
    else:
        for cache, marker in (("cold", "o-"), ("warm", "s--")):
            rs = sorted((r for r in runs if r["cache"] == cache), key=lambda r: r["clients"])
            if rs:
                b.plot([r["clients"] for r in rs], [100.0 * r["stall_fraction"] for r in rs],
                       marker, label=f"{cache} cache")
        b.set_xlabel("concurrent clients")
        b.set_ylabel("stalled frames (%)")
        b.set_title("stalls against load")
        b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def capacity_table(runs: list[dict]) -> list[str]:
    """One markdown row per run: the load each run put on the server and how it held."""
    rows = ["| cache | clients | frames | stalls % | first-answer frames % | ε first / after "
            "% | clients with stalls | p50 ms | p95 ms | "
            "never delivered | computations | computation s | MB sent | server RSS peak MiB | "
            "wall s |", "|" + "---|" * 15]
    for r in runs:
        def ms(x: float | None, r: dict = r) -> str:
            return ("n/a" if not r["frames"] else "never") if x is None else f"{1e3 * x:.0f}"

        err = r.get("frame_error_by_answer") or {}
        eps = " / ".join("-" if a not in err else f"{err[a]['eps_mean']:.3f}"
                         for a in ("first", "refined" if "refined" in err else "full"))
        share = r.get("first_answer_share")
        rows.append(
            f"| {r['cache']} | {r['clients']} | {r['frames']} | {100 * r['stall_fraction']:.2f} "
            f"| {'-' if share is None else f'{100 * share:.1f}'} | {eps} "
            f"| {r['clients_with_stalls']} | {ms(r['latency_p50_s'])} | "
            f"{ms(r['latency_p95_s'])} | {r['frames_never_delivered']} | "
            f"{r['computations']:.0f} | {r['computation_seconds']:.1f} | "
            f"{r['bytes_sent'] / 1e6:.2f} | {r['server_rss_peak_bytes'] / 2**20:.0f} | "
            f"{r['wall_seconds']:.1f} |")
    return rows


def abuse_table(runs: list[dict]) -> list[str]:
    """One markdown row per run of the abuse mode: the walkers with and without the hostile
    client, and the hostile's answers by status."""
    head = ("| cache | clients | hostile | frames | stalls % | clients with stalls | p50 ms | "
            "p95 ms | never delivered | first cells late | server RSS peak MiB | hostile sent "
            "| " + " | ".join(str(c) for c in HOSTILE_STATUSES)
            + " | other | refused | gave up | unanswered at stop |")
    rows = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in runs:
        def ms(x: float | None, r: dict = r) -> str:
            return ("n/a" if not r["frames"] else "never") if x is None else f"{1e3 * x:.0f}"

        h = r.get("hostile_answers", {}) if r.get("hostile") else {}

        def n(key: str, h: dict = h, r: dict = r) -> str:
            return str(h.get(key, 0)) if r.get("hostile") else "–"

        rows.append(
            f"| {r['cache']} | {r['clients']} | {'yes' if r.get('hostile') else 'no'} | "
            f"{r['frames']} | {100 * r['stall_fraction']:.2f} | {r['clients_with_stalls']} | "
            f"{ms(r['latency_p50_s'])} | {ms(r['latency_p95_s'])} | "
            f"{r['frames_never_delivered']} | {r.get('first_cell_timeouts', 0)} | "
            f"{r['server_rss_peak_bytes'] / 2**20:.0f} | {n('sent')} | "
            + " | ".join(n(str(c)) for c in HOSTILE_STATUSES)
            + f" | {n('other')} | {n('refused')} | {n('timeout')} | {n('unfinished')} |")
    return rows


@contextlib.contextmanager
def serving(args: argparse.Namespace) -> Iterator[tuple[Any, Any]]:
    """A fresh ``pvs serve`` on a free loopback port, with the run's scene, core and workers:
    (base URL, process). Its caches start empty. With ``--replicas N`` > 1: a fresh
    ``redis-server`` (``tests.redis_process``) and N servers sharing it (``PVS_CACHE``):
    (their URLs, their processes)."""
    if args.replicas <= 1:
        with _serve_one(args) as served:
            yield served
        return
    from tests.redis_process import RedisProcess

    redis = RedisProcess(maxmemory="1gb").start()
    try:
        with contextlib.ExitStack() as stack:
            served = [stack.enter_context(_serve_one(args, {"PVS_CACHE": redis.url}))
                      for _ in range(args.replicas)]
            yield [u for u, _ in served], [p for _, p in served]
    finally:
        redis.close()


def as_list(x: Any) -> list:
    """``x`` when it is a list (replicas), else ``[x]``."""
    return x if isinstance(x, list) else [x]


@contextlib.contextmanager
def _serve_one(args: argparse.Namespace, extra_env: dict[str, str] | None = None
               ) -> Iterator[tuple[str, subprocess.Popen]]:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, PVS_GENERATED=f"{args.scene}={args.triangles}",
               PVS_CORE=args.core, PVS_WORKERS=str(args.workers), PVS_LOG_LEVEL="warning",
               PVS_CELL_SIZE=str(args.cell_size), PVS_WS_PING_INTERVAL="none",
               **(extra_env or {}))
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    cmd = [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--scenes", str(ROOT / "nonexistent-scenes-dir")]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        if not wait_until_healthy(url, proc):
            print(proc.stderr.read().decode()[-3000:] if proc.stderr else "")
            raise SystemExit("server did not start")
        yield url, proc
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


async def warm_up(url: str | list[str], args: argparse.Namespace, cells: int) -> float:
    """Compute every cell's PVS through the HTTP route (the walkers' cache keys: same scene,
    core and parameters), ``args.workers`` at a time; seconds taken. Not ``pvs precompute``:
    that fills an on-disk cache for a server yet to start, while this fills the memory cache
    of the server under test, so the warm rows measure streaming alone. With replicas, the
    first one computes; the others then find every cell in Redis."""
    url = as_list(url)[0]
    t0 = time.perf_counter()
    gate = asyncio.Semaphore(args.workers)
    query = {"core": args.core, **{k: json.dumps(v) if not isinstance(v, str) else v
                                   for k, v in args.params.items()}}
    async with httpx.AsyncClient(base_url=url, timeout=600) as http:
        async def one(cell: int) -> None:
            async with gate:
                r = await http.get(f"/scenes/{args.scene}/cells/{cell}/pvs", params=query)
                r.raise_for_status()

        await asyncio.gather(*(one(c) for c in range(cells)))
    return time.perf_counter() - t0


def measure(url: str, proc: subprocess.Popen, args: argparse.Namespace, clients: int,
            cache: str, scene_triangles: int, grid: ViewcellGrid,
            hostile: bool | None = None) -> dict:
    """One run of ``clients`` walkers against the server at ``url``; its summary. ``hostile``
    True: while the hostile client floods the server; False: a run of the abuse mode without
    it; None: a run of the default mode (no hostile fields)."""
    before = counters(url)
    pids = [p.pid for p in as_list(proc)]
    cpu0, own0 = sum(cpu_seconds(p) for p in pids), time.process_time()
    with hostile_client(as_list(url)[0], args, grid) if hostile else \
            contextlib.nullcontext({}) as flood:
        stats, peak_rss, wall = asyncio.run(run_clients(url, args, clients, grid, pids))
    server_cpu = sum(cpu_seconds(p) for p in pids) - cpu0
    client_cpu = time.process_time() - own0
    after = counters(url)
    m = {k: after[k] - before[k] for k in COUNTERS}
    r = summarise(args, clients, cache, scene_triangles, len(grid), stats, peak_rss, wall, m,
                  server_cpu, client_cpu)
    r["frame_error_by_answer"] = frame_eps(args, [x for st in stats for x in st.samples])
    if hostile is not None:
        r["hostile"] = hostile
    if hostile:
        r.update(hostile_answers=flood, hostile_params=args.hostile_params,
                 hostile_concurrency=args.hostile_concurrency,
                 hostile_timeout=args.hostile_timeout, hostile_pause=args.hostile_pause,
                 hostile_address=HOSTILE_ADDRESS)
    return r


def frame_eps(args: argparse.Namespace,
              samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]]) -> dict:
    """ε (mean, worst), PSNR and SSIM per answer of the sampled frames (``ClientStats.
    samples``): each drawn from the ids the walker held then against the full scene, at
    ``FRAME_SIZE`` px, 90 degree field of view, after the run (so drawing does not slow the
    walkers)."""
    if not samples:
        return {}
    from client.metrics import capped_psnr, frame_metrics
    from client.render import OffscreenRenderer

    scene = make_scene(args.scene, triangles=args.triangles, seed=0)
    renderer = OffscreenRenderer(FRAME_SIZE, FRAME_SIZE, yfov_deg=90.0)
    got: dict[str, list[dict]] = {}
    try:
        for eye, fwd, ids, answer in samples:
            ids = ids[scene.valid_faces[ids]] if len(ids) else ids
            fr = renderer.render(scene.triangles(ids), scene.colors[ids], eye, fwd)
            gt = renderer.render_scene(scene, eye, fwd)
            got.setdefault(answer, []).append(frame_metrics(fr, gt))
    finally:
        renderer.close()
    return {a: {"frames": len(ms), "eps_mean": float(np.mean([m["epsilon"] for m in ms])),
                "eps_worst": float(np.max([m["epsilon"] for m in ms])),
                "psnr_mean": float(np.mean(capped_psnr(np.array([m["psnr"] for m in ms])))),
                "ssim_mean": float(np.mean([m["ssim"] for m in ms]))}
            for a, ms in sorted(got.items())}


#: Side of the frames ``frame_eps`` draws, pixels.
FRAME_SIZE = 128


def run_lines(r: dict) -> list[str]:
    """The printed table of one run."""
    rows = table(r)
    w = max(len(k) for k, _ in rows)
    lines = ["-" * (w + 30), *(f"{k:<{w}}  {v}" for k, v in rows), "-" * (w + 30)]
    return lines + [f"error: {e}" for e in r["errors_sample"]]


def write_outputs(out: Path, name: str, command: str, where: str, runs: list[dict]) -> None:
    """``OUT/NAME.md`` (capacity table, plot, each run's table), ``NAME.png``, ``NAME.json``."""
    out.mkdir(parents=True, exist_ok=True)
    r0 = runs[0]
    warm = next((r["warm_up_seconds"] for r in runs if "warm_up_seconds" in r), None)
    details = [line for r in runs for line in (
        f"### {r['clients']} clients, {r['cache']} cache"
        + {True: ", hostile client", False: ", no hostile client"}.get(r.get("hostile"), ""),
        "", "```", *run_lines(r), "```", "")]
    abuse = []
    hostile = next((r for r in runs if r.get("hostile")), None)
    if hostile is not None:
        abuse = ["## Abuse: the walkers with and without a hostile client", "",
                 f"Each pair runs on the same settings; in the second row a hostile client "
                 f"floods `POST /scenes/{r0['scene']}/pvs` from {hostile['hostile_address']} "
                 f"with {hostile['hostile_concurrency']} requests at once, each a different "
                 f"box near a random cell, core `{r0['core']}` with parameters "
                 f"`{json.dumps(hostile['hostile_params'])}`, abandoned after "
                 f"{hostile['hostile_timeout']:g} s and sent anew, sent again "
                 "at once after an answer (after "
                 f"{hostile.get('hostile_pause', 0.05):g} s when refused or answered "
                 "429/503), from before the first walker connects until the last one is done. "
                 "Cold pairs: two fresh servers; warm pairs: one warmed server, the hostile row "
                 "second. First cells late: walkers whose first cell did not come within "
                 f"{r0.get('first_cell_timeout', 300):g} s and walked anyway (their frames "
                 "count). Hostile answers by status; refused: connections refused or reset; "
                 "gave up: no answer within its timeout; unanswered at stop: in flight when "
                 "the walkers were done.", "", *abuse_table(runs), ""]
    md = ["# Load benchmark", "", f"command: `{command}`", "", f"machine: {where}", "",
          f"Scene `{r0['scene']}` ({r0['triangles']} triangles, {r0['cells']} cells of "
          f"{r0.get('cell_size', 4.0):g} m), core `{r0['core']}` with parameters "
          f"`{json.dumps(r0['params'])}`, {r0['workers']} workers; every client walks "
          f"{r0['walk_seconds']:g} s at {r0['speed']:g} m/s sending {r0['fps']:g} poses/s. "
          "Cold: a fresh server per row, every PVS computed while the walkers walk. Warm: one "
          "server whose cache holds every cell's PVS before the clients come"
          + (f" (computed in {warm:.1f} s)" if warm is not None else "")
          + "; its rows run one after another on it. A stall is a frame whose cell was not "
          "complete one frame interval after its pose was sent; never delivered: still missing "
          f"{r0.get('grace_seconds', 10.0):g} s after the walk ended (the walker had left the "
          "cell). Latency percentiles are over every frame (nearest rank), a never-delivered "
          "frame counting as the latest: 'never' when the percentile falls on one.", "",
          *(capacity_table(runs) + [""] if hostile is None else []), *abuse,
          f"![latency and stalls]({name}.png)", "",
          "## Each run", "", *details]
    (out / f"{name}.md").write_text("\n".join(md))
    (out / f"{name}.json").write_text(json.dumps(
        {"command": command, "machine": where, "runs": runs}, indent=1))
    plot(runs, out / f"{name}.png")
    print(f"wrote {out / name}.md, .png, .json")


def rerender(path: Path) -> None:
    """Rewrite ``path`` (a NAME.json of a measured run) and its .md/.png with the current
    summary and layout: the latency summary is recomputed from the stored latencies and
    never-delivered counts; nothing is measured again, command and machine stay the run's."""
    data = json.loads(path.read_text())
    for r in data["runs"]:
        r.update(latency_summary(np.asarray(r["latencies_s"], dtype=float),
                                 r["frames_never_delivered"]))
    write_outputs(path.parent, path.stem, data["command"], data["machine"], data["runs"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", default=None,
                    help="concurrent clients, a comma-separated list: one run per count "
                         "(default 5,10,20,50; with --hostile 50)")
    ap.add_argument("--duration", type=float, default=20.0, help="walk length, seconds")
    ap.add_argument("--speed", type=float, default=1.4, help="walking speed, m/s")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--scene", default="village")
    ap.add_argument("--triangles", type=int, default=20_000)
    ap.add_argument("--cell-size", type=float, default=4.0)
    ap.add_argument("--core", default=Settings.model_fields["core"].default,
                    help="core the server computes with (default: the server settings' default)")
    ap.add_argument("--params", default="{}",
                    help="core parameters, JSON (default: the core's defaults)")
    ap.add_argument("--budget", type=int, default=None, help="client triangle budget")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--replicas", type=int, default=1,
                    help="server processes sharing one fresh redis-server (PVS_CACHE); the "
                         "walkers are spread over them in turn (default 1: no Redis)")
    ap.add_argument("--progressive", action=argparse.BooleanOptionalAction, default=None,
                    help="ask for progressive streams (or not); default: the server's")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--grace", type=float, default=10.0,
                    help="seconds after its walk a client still waits for stalled frames' cells")
    ap.add_argument("--cache", default="cold,warm",
                    help="cold (a fresh server per run), warm (one server with every cell "
                         "computed before the clients come), or both")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results",
                    help="folder for NAME.md, NAME.png and NAME.json")
    ap.add_argument("--name", default="load",
                    help="file stem of the outputs (e.g. load_from_segment for another core)")
    ap.add_argument("--no-files", action="store_true", help="print only")
    ap.add_argument("--quick", action="store_true", help="5 clients, 6 s walks, cold (smoke)")
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
        rerender(args.rerender)
        return 0
    if args.clients is None:
        args.clients = "50" if args.hostile else "5,10,20,50"
    if args.first_cell_timeout is None:
        args.first_cell_timeout = 30.0 if args.hostile else 300.0
    args.hostile_params = (json.loads(args.hostile_params) if args.hostile_params else
                           HOSTILE_PARAMS.get(args.core, {"resolution": 2048}))
    if args.hostile_concurrency < 1 or args.hostile_timeout <= 0:
        ap.error("--hostile-concurrency takes a positive count, --hostile-timeout seconds > 0")
    counts = [int(x) for x in str(args.clients).split(",") if x.strip()]
    caches = [x.strip() for x in args.cache.split(",") if x.strip()]
    if not counts or min(counts) < 1 or set(caches) - {"cold", "warm"} or not caches:
        ap.error("--clients takes positive counts, --cache cold and/or warm")
    if args.quick:
        counts, args.duration, caches = [min(counts[0], 5)], min(args.duration, 6.0), ["cold"]
    args.params = json.loads(args.params)

    command = "python -m benchmarks.bench_load " + " ".join(
        argv if argv is not None else sys.argv[1:])
    where = machine()
    print("command: " + command)
    print("machine: " + where)
    scene = make_scene(args.scene, triangles=args.triangles, seed=0)
    grid = ViewcellGrid.for_scene(scene, scene.meta.get("cell_size") or args.cell_size)
    runs: list[dict] = []

    def report(r: dict) -> None:
        print("\n".join(run_lines(r)))
        print("json: " + json.dumps({k: v for k, v in r.items() if k != "latencies_s"}))
        runs.append(r)

    if args.hostile:
        # Pairs: the same run without, then with the hostile client (module docstring).
        for cache in caches:
            for n in counts:
                if cache == "cold":
                    for hostile in (False, True):
                        with serving(args) as (url, proc):
                            report(measure(url, proc, args, n, "cold", scene.n_triangles, grid,
                                           hostile))
                    continue
                with serving(args) as (url, proc):
                    warm_seconds = asyncio.run(warm_up(url, args, len(grid)))
                    print(f"warm-up: {len(grid)} cells computed in {warm_seconds:.1f} s")
                    for hostile in (False, True):
                        r = measure(url, proc, args, n, "warm", scene.n_triangles, grid, hostile)
                        r["warm_up_seconds"] = warm_seconds
                        report(r)
        caches = []
    if "cold" in caches:
        for n in counts:
            with serving(args) as (url, proc):
                report(measure(url, proc, args, n, "cold", scene.n_triangles, grid))
    warm_seconds = None
    if "warm" in caches:
        with serving(args) as (url, proc):
            warm_seconds = asyncio.run(warm_up(url, args, len(grid)))
            print(f"warm-up: {len(grid)} cells computed in {warm_seconds:.1f} s")
            for n in counts:
                r = measure(url, proc, args, n, "warm", scene.n_triangles, grid)
                r["warm_up_seconds"] = warm_seconds
                report(r)
    print("\n".join(abuse_table(runs) if args.hostile else capacity_table(runs)))
    if not args.no_files:
        write_outputs(args.out, args.name, command, where, runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
