"""Load benchmark: N concurrent protocol clients replaying walkthroughs against a real server.

Starts ``python -m pvs_cli serve`` on a free loopback port (configured through ``PVS_*``
environment variables), then runs N asyncio clients (``client.session.Session``: receiving and
accounting, not rendering), each replaying its own generated walkthrough
(``client.walkthrough.generate_walkthrough``) at real-time pacing. Prints one table with the
command line on top:

- stalls: frames whose cell was not complete one frame interval after the pose was sent (the
  first cell of each client, waited for before its clock starts, is not counted);
- frame delivery latency p50/p95: per frame, the time from sending its pose until the client
  holds the pose's cell complete (0 when it already did);
- bytes received by the clients and bytes sent according to the server's /metrics;
- server memory: the RSS of the server process (``/proc/PID/status``), peak over the run;
- duplicates (triangles received twice without a drop between: must be 0) and client errors.

Usage::

    python -m benchmarks.bench_load              # 50 clients, 20 s walks
    python -m benchmarks.bench_load --quick      # 5 clients, 6 s walks (smoke)
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from client.session import Session, SessionError  # noqa: E402
from client.walkthrough import generate_walkthrough  # noqa: E402
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
        self.errors: list[str] = []


async def one_client(url: str, args: argparse.Namespace, grid: ViewcellGrid, seed: int,
                     stats: ClientStats) -> None:
    walk = generate_walkthrough(grid, duration=args.duration, speed=args.speed, fps=args.fps,
                                seed=seed)
    pos, t = walk.positions, walk.t
    vel = np.gradient(pos, t, axis=0) if len(t) > 1 else np.zeros_like(pos)
    pending: list[asyncio.Task] = []
    try:
        s = await Session.connect(url, args.scene, args.core, args.params, budget=args.budget,
                                  timeout=120)
    except (SessionError, OSError, TimeoutError) as exc:
        stats.errors.append(f"connect: {exc}")
        return
    try:
        first = grid.cell_of(pos[0])
        await s.send_pose(0, 0.0, pos[0], walk.forwards[0], vel[0])
        await s.wait_cell(first, 300)
        t0 = time.perf_counter()
        frame = 1.0 / args.fps

        async def late(cell: int, sent: float) -> None:
            try:
                await s.wait_cell(cell, 120)
                stats.latencies.append(time.perf_counter() - sent)
            except (TimeoutError, SessionError):
                stats.latencies.append(float("inf"))

        for i in range(1, len(walk)):
            await asyncio.sleep(max(0.0, t0 + t[i] - t[0] - time.perf_counter()))
            sent = time.perf_counter()
            await s.send_pose(i, float(t[i]), pos[i], walk.forwards[i], vel[i])
            stats.frames += 1
            cell = grid.cell_of(pos[i])
            if s.is_complete(cell):
                stats.latencies.append(0.0)
                continue
            try:
                await s.wait_cell(cell, frame)
                stats.latencies.append(time.perf_counter() - sent)
            except TimeoutError:
                stats.stalls += 1
                pending.append(asyncio.create_task(late(cell, sent)))
        if pending:
            await asyncio.gather(*pending)
    except SessionError as exc:
        stats.errors.append(str(exc))
    finally:
        stats.bytes = s.bytes_received
        stats.duplicates = s.duplicates
        stats.dropped = s.dropped
        stats.errors += [f"{e.code}: {e.message}" for e in s.errors]
        stats.errors += s.local_errors
        await s.close()


async def run_clients(url: str, args: argparse.Namespace, grid: ViewcellGrid, pid: int
                      ) -> tuple[list[ClientStats], int, float]:
    stats = [ClientStats() for _ in range(args.clients)]
    peak = [rss_bytes(pid)]

    async def sample_rss() -> None:
        while True:
            peak[0] = max(peak[0], rss_bytes(pid))
            await asyncio.sleep(0.25)

    sampler = asyncio.create_task(sample_rss())
    t0 = time.perf_counter()
    # Stagger the starts over a second, as real clients arrive.
    async def delayed(i: int) -> None:
        await asyncio.sleep(i / max(1, args.clients))
        await one_client(url, args, grid, args.seed + i, stats[i])

    await asyncio.gather(*(delayed(i) for i in range(args.clients)))
    wall = time.perf_counter() - t0
    sampler.cancel()
    return stats, peak[0], wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--duration", type=float, default=20.0, help="walk length, seconds")
    ap.add_argument("--speed", type=float, default=1.4, help="walking speed, m/s")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--scene", default="village")
    ap.add_argument("--triangles", type=int, default=20_000)
    ap.add_argument("--cell-size", type=float, default=4.0)
    ap.add_argument("--core", default="sampling")
    ap.add_argument("--params", default='{"resolution": 32, "samples": 4}',
                    help="core parameters, JSON")
    ap.add_argument("--budget", type=int, default=None, help="client triangle budget")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="5 clients, 6 s walks (smoke)")
    args = ap.parse_args(argv)
    if args.quick:
        args.clients, args.duration = min(args.clients, 5), min(args.duration, 6.0)
    args.params = json.loads(args.params)

    print("command: " + " ".join([sys.executable, "-m", "benchmarks.bench_load",
                                  *(argv if argv is not None else sys.argv[1:])]))
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, PVS_GENERATED=f"{args.scene}={args.triangles}",
               PVS_CORE=args.core, PVS_WORKERS=str(args.workers), PVS_LOG_LEVEL="warning",
               PVS_CELL_SIZE=str(args.cell_size), PVS_WS_PING_INTERVAL="none")
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    cmd = [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--scenes", str(ROOT / "nonexistent-scenes-dir")]
    print("server:  " + " ".join(cmd))
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 120
        while True:
            try:
                if httpx.get(url + "/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.time() > deadline:
                print(proc.stderr.read().decode()[-3000:] if proc.stderr else "")
                raise SystemExit("server did not start")
            time.sleep(0.2)
        scene = make_scene(args.scene, triangles=args.triangles, seed=0)
        grid = ViewcellGrid.for_scene(scene, scene.meta.get("cell_size") or args.cell_size)
        stats, peak_rss, wall = asyncio.run(run_clients(url, args, grid, proc.pid))
        text = httpx.get(url + "/metrics", timeout=30).text
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()

    lat = np.array([x for s in stats for x in s.latencies])
    finite = lat[np.isfinite(lat)]
    frames = sum(s.frames for s in stats)
    stalls = sum(s.stalls for s in stats)
    rows = [
        ("clients", f"{args.clients}"),
        ("scene / triangles / cells", f"{args.scene} / {scene.n_triangles} / {len(grid)}"),
        ("core / params", f"{args.core} / {json.dumps(args.params)}"),
        ("walk", f"{args.duration:g} s at {args.speed:g} m/s, {args.fps:g} fps"),
        ("frames", f"{frames}"),
        ("stalls", f"{stalls} ({100.0 * stalls / max(1, frames):.2f} %)"),
        ("clients with stalls", f"{sum(1 for s in stats if s.stalls)}"),
        ("frame latency p50", f"{1e3 * np.percentile(finite, 50):.1f} ms" if len(finite)
         else "n/a"),
        ("frame latency p95", f"{1e3 * np.percentile(finite, 95):.1f} ms" if len(finite)
         else "n/a"),
        ("frames never delivered", f"{int(np.sum(~np.isfinite(lat)))}"),
        ("bytes received (clients)", f"{sum(s.bytes for s in stats) / 1e6:.2f} MB"),
        ("bytes sent (server metrics)", f"{metric(text, 'pvs_bytes_sent_total') / 1e6:.2f} MB"),
        ("PVS computations", f"{metric(text, 'pvs_computations_total'):.0f}"),
        ("server stalls (metrics)", f"{metric(text, 'pvs_stalls_total'):.0f}"),
        ("server RSS peak", f"{peak_rss / 2**20:.1f} MiB"),
        ("duplicate triangles", f"{sum(s.duplicates for s in stats)}"),
        ("triangles dropped", f"{sum(s.dropped for s in stats)}"),
        ("client errors", f"{sum(len(s.errors) for s in stats)}"),
        ("wall time", f"{wall:.1f} s"),
    ]
    w = max(len(k) for k, _ in rows)
    print("-" * (w + 24))
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
    print("-" * (w + 24))
    errs = [e for s in stats for e in s.errors][:5]
    for e in errs:
        print("error:", e)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
