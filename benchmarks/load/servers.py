"""The servers under load: fresh ``pvs serve`` processes on free loopback ports (and with
``replicas`` > 1 a fresh ``redis-server`` they share), their counters and their warm-up.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from benchmarks.common import free_port, prometheus_value
from benchmarks.load.scenes import BenchScene, check_served

ROOT = Path(__file__).resolve().parents[2]

#: PVS answered from the shared Redis cache (``--replicas``; NaN without Redis).
REDIS_HITS = 'pvs_cache_tier_hits_total{kind="pvs",tier="redis"}'
#: Server counters a run reports (``/metrics``), as differences over the run.
COUNTERS = ("pvs_bytes_sent_total", "pvs_computations_total", "pvs_stalls_total",
            "pvs_computation_seconds_sum", "pvs_cache_hits_total",
            "pvs_computations_shared_total", "pvs_prefetch_skipped_total",
            "pvs_prefetch_yields_total", "pvs_slow_clients_total", "pvs_triangles_sent_total",
            REDIS_HITS)


@dataclass
class Served:
    """Running servers: their base URLs and processes (one each, or one per replica)."""

    urls: list[str]
    procs: list[subprocess.Popen]

    @property
    def pids(self) -> list[int]:
        """The servers' process ids."""
        return [p.pid for p in self.procs]

    def counters(self) -> dict[str, float]:
        """The servers' ``COUNTERS`` now, summed over replicas."""
        texts = [httpx.get(u + "/metrics", timeout=30).text for u in self.urls]
        return {k: sum(prometheus_value(t, k) for t in texts) for k in COUNTERS}


@contextlib.contextmanager
def redis_server(maxmemory: str = "1gb") -> Iterator[str]:
    """A fresh ``redis-server`` on a free loopback port that persists nothing, LRU-bounded by
    ``maxmemory``, for the ``with`` block: its URL. RuntimeError when it does not answer."""
    import redis

    if shutil.which("redis-server") is None:
        raise RuntimeError("--replicas needs redis-server on PATH (scripts/setup.sh)")
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="pvs-bench-redis-") as folder:
        proc = subprocess.Popen(
            ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "",
             "--appendonly", "no", "--dir", folder, "--maxmemory", maxmemory,
             "--maxmemory-policy", "allkeys-lru"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            client = redis.Redis(host="127.0.0.1", port=port, socket_timeout=0.5,
                                 socket_connect_timeout=0.5)
            deadline = time.monotonic() + 15
            while True:
                try:
                    if client.ping():
                        break
                except redis.RedisError:
                    pass
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"redis-server on port {port} did not start")
                time.sleep(0.05)
            client.close()
            yield f"redis://127.0.0.1:{port}/0"
        finally:
            _stop(proc)


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


def server_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment the servers run in: this one, with ``extra`` and the project's numba
    cache (``.numba_cache``) unless ``NUMBA_CACHE_DIR`` names another."""
    env = {**os.environ, **(extra or {})}
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    return env


def compile_kernels() -> float:
    """Compile every core's kernels into the servers' numba cache (``pvs warmup``, in its own
    processes) before any server starts; seconds (a few when nothing changed since).

    A server compiles a kernel missing from the cache at its first use, on the thread that
    serves the walkers' cells, holding the GIL: a cold run would then measure compilation
    (seconds of stalls, no core answer in a 20 s walk), not the serving of cells."""
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pvs_cli", "warmup"], cwd=ROOT,
                          env=server_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    if proc.returncode:
        raise RuntimeError("pvs warmup failed: "
                           + proc.stderr.decode(errors="replace")[-3000:])
    return time.perf_counter() - t


@contextlib.contextmanager
def _serve_one(bs: BenchScene, core: str, workers: int,
               extra_env: dict[str, str] | None = None) -> Iterator[tuple[str, subprocess.Popen]]:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = server_env({**bs.env, "PVS_CORE": core, "PVS_WORKERS": str(workers),
                      "PVS_LOG_LEVEL": "warning", "PVS_WS_PING_INTERVAL": "none",
                      **(extra_env or {})})
    cmd = [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--scenes", str(bs.scenes_dir or ROOT / "nonexistent-scenes-dir")]
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=log)
        try:
            from pvs_cli import wait_until_healthy

            if not wait_until_healthy(url, proc):
                log.seek(0)
                raise RuntimeError("the server did not start: "
                                   + log.read().decode(errors="replace")[-3000:])
            check_served(url, bs)
            yield url, proc
        finally:
            _stop(proc)


@contextlib.contextmanager
def serving(bs: BenchScene, core: str, workers: int, replicas: int = 1) -> Iterator[Served]:
    """Fresh servers of scene ``bs`` with ``core`` and ``workers``, each on a free loopback
    port with empty caches and the scene loaded (``check_served``) before it is yielded. With
    ``replicas`` > 1: a fresh ``redis-server`` and that many servers sharing it
    (``PVS_CACHE``)."""
    if replicas <= 1:
        with _serve_one(bs, core, workers) as (url, proc):
            yield Served([url], [proc])
        return
    with redis_server() as redis_url, contextlib.ExitStack() as stack:
        served = [stack.enter_context(_serve_one(bs, core, workers, {"PVS_CACHE": redis_url}))
                  for _ in range(replicas)]
        yield Served([u for u, _ in served], [p for _, p in served])


async def warm_up(url: str, scene: str, core: str, params: dict, cells: list[int],
                  concurrency: int) -> float:
    """Compute ``cells``' PVS through the HTTP route (the walkers' cache keys: same scene, core
    and parameters), ``concurrency`` at a time; seconds taken. Not ``pvs precompute``: that
    fills an on-disk cache for a server yet to start, while this fills the memory cache of the
    server under test, so the warm rows measure streaming alone. With replicas, one computes;
    the others then find every cell in Redis."""
    t0 = time.perf_counter()
    gate = asyncio.Semaphore(max(1, concurrency))
    query = {"core": core, **{k: json.dumps(v) if not isinstance(v, str) else v
                              for k, v in params.items()}}
    async with httpx.AsyncClient(base_url=url, timeout=600) as http:
        async def one(cell: int) -> None:
            async with gate:
                r = await http.get(f"/scenes/{scene}/cells/{cell}/pvs", params=query)
                r.raise_for_status()

        await asyncio.gather(*(one(c) for c in cells))
    return time.perf_counter() - t0
