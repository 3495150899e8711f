"""The services of docker/compose.yml started as processes on this machine (Docker cannot run
here): Redis, a Dask scheduler with two workers, two ``pvs serve`` replicas configured as the
compose file configures them, and nginx with docker/nginx.conf (hosts and ports rewritten to
loopback). Walkers connect through the proxy only; the test shows that the system works as one:
sessions spread over both replicas, the computations run on the cluster, and a cell computed
by one replica is answered by the other from Redis."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import yaml

from benchmarks.common import stop_process
from benchmarks.redis_process import RedisProcess, free_port
from client.session import Session
from pvs_cli import wait_until_healthy
from visibility.generators import make_scene
from visibility.viewcells import ViewcellGrid

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
SCENE, TRIANGLES = "rooms", 4000


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               **extra)
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))
    return env


@contextlib.contextmanager
def _process(args: list[str], env: dict[str, str], log: Path) -> Iterator[subprocess.Popen]:
    with open(log, "wb") as out:
        proc = subprocess.Popen(args, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            yield proc
        finally:
            stop_process(proc)


def _wait_port(port: int, proc: subprocess.Popen, log: Path, timeout: float = 60.0) -> None:
    import socket

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"{proc.args[:3]} exited: {log.read_text()[-2000:]}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise RuntimeError(f"nothing listens on {port}: {log.read_text()[-2000:]}")


def _owns_port(proc: subprocess.Popen, port: int, timeout: float = 60.0) -> bool:
    """Whether ``proc`` comes to listen on ``port`` (False once it exits)."""
    import psutil

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            return False
        if any(c.laddr and c.laddr.port == port and c.status == psutil.CONN_LISTEN
               for c in psutil.Process(proc.pid).net_connections(kind="tcp")):
            return True
        time.sleep(0.2)
    return False


def _server_env(redis_url: str, scheduler: str) -> dict[str, str]:
    """The compose file's server environment, with its hosts replaced by loopback ones."""
    compose = yaml.safe_load((ROOT / "docker" / "compose.yml").read_text())
    env = {k: str(v) for k, v in compose["services"]["server1"]["environment"].items()}
    env["PVS_CACHE"] = env["PVS_CACHE"].replace("redis://redis:6379", redis_url.rsplit("/", 1)[0])
    env["PVS_EXECUTOR"] = env["PVS_EXECUTOR"].replace("scheduler:8786", scheduler)
    env.update(PVS_GENERATED=f"{SCENE}={TRIANGLES}", PVS_LOG_LEVEL="warning", PVS_CALIBRATE="0",
               PVS_PROGRESSIVE="0", PVS_CORE="sampling", PVS_WS_PING_INTERVAL="none")
    return env


def _nginx_conf(tmp: Path, listen: int, replicas: list[int]) -> Path:
    """docker/nginx.conf inside a main configuration that runs unprivileged in ``tmp``."""
    conf = (ROOT / "docker" / "nginx.conf").read_text()
    for name, port in zip(("server1", "server2"), replicas, strict=True):
        conf = conf.replace(f"server {name}:8000", f"server 127.0.0.1:{port}")
    conf = re.sub(r"listen \d+;", f"listen 127.0.0.1:{listen};", conf)
    temps = " ".join(f"{k}_temp_path {tmp / k};" for k in
                     ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    main = (f"daemon off;\nmaster_process off;\npid {tmp / 'nginx.pid'};\n"
            f"error_log {tmp / 'error.log'} warn;\nevents {{ worker_connections 256; }}\n"
            f"http {{\naccess_log off;\n{temps}\n{conf}\n}}\n")
    path = tmp / "nginx.conf"
    path.write_text(main)
    return path


async def _walk(url: str, cells: list[tuple[int, tuple]]) -> Session:
    s = await Session.connect(url, SCENE, "sampling", {"samples": 4, "resolution": 32},
                              prefetch=False)
    try:
        for i, (cell, point) in enumerate(cells):
            await s.send_pose(i, 0.1 * i, point, (0.0, 0.0, -1.0))
            await s.wait_cell(cell, timeout=120)
    finally:
        await s.close()
    return s


def test_the_composed_services_work_as_one_system(tmp_path):
    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    assert Path(nginx).exists(), "nginx is missing: scripts/setup.sh installs nginx-light"
    grid = ViewcellGrid.for_scene(make_scene(SCENE, triangles=TRIANGLES))
    walks = [[(c, tuple(grid.walk_point(c))) for c in cells]
             for cells in ([0, 1, 2], [len(grid) - 1, len(grid) - 2, len(grid) - 3])]
    sched_port, replicas, proxy = free_port(), [free_port(), free_port()], free_port()
    scheduler = f"127.0.0.1:{sched_port}"
    redis = RedisProcess().start()
    try:
        with contextlib.ExitStack() as stack:
            sched = stack.enter_context(_process(
                [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                 "--port", str(sched_port), "--no-dashboard"], _env(), tmp_path / "sched.log"))
            _wait_port(sched_port, sched, tmp_path / "sched.log")
            for k in range(2):
                stack.enter_context(_process(
                    [sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://{scheduler}",
                     "--nworkers", "1", "--nthreads", "1", "--no-dashboard", "--name", f"w{k}"],
                    _env(), tmp_path / f"worker{k}.log"))
            urls = []
            for k in range(len(replicas)):
                log = tmp_path / f"server{k}.log"
                for _ in range(3):
                    # The port was free when picked, but a process started since (a worker,
                    # another test's) may bind it first: then the server exits, and the next
                    # try takes another port.
                    proc = stack.enter_context(_process(
                        [sys.executable, "-m", "pvs_cli", "serve", "--host", "127.0.0.1",
                         "--port", str(replicas[k]), "--scenes", str(tmp_path / "no-scenes")],
                        _env(**_server_env(redis.url, scheduler)), log))
                    if _owns_port(proc, replicas[k], timeout=180):
                        break
                    replicas[k] = free_port()
                url = f"http://127.0.0.1:{replicas[k]}"
                assert wait_until_healthy(url, proc, timeout=180), log.read_text()[-3000:]
                urls.append(url)
            for _ in range(3):
                # The port was free when picked, but a process of another test may bind it
                # first: then nginx exits and whatever holds the port would answer.
                nx = stack.enter_context(_process(
                    [nginx, "-p", str(tmp_path), "-e", str(tmp_path / "error.log"), "-c",
                     str(_nginx_conf(tmp_path, proxy, replicas))], _env(),
                    tmp_path / "nginx.log"))
                if _owns_port(nx, proxy):
                    break
                proxy = free_port()
            else:
                raise RuntimeError((tmp_path / "error.log").read_text()[-2000:])
            front = f"http://127.0.0.1:{proxy}"
            assert httpx.get(front + "/health", timeout=30).json()["status"] == "ok"
            for url in urls:  # both replicas joined the cluster (or say they wait for it)
                assert httpx.get(url + f"/scenes/{SCENE}", timeout=120).status_code == 200

            async def both() -> list[Session]:
                ws = front.replace("http://", "ws://") + "/ws"
                return await asyncio.gather(*(_walk(ws, w) for w in walks))

            sessions = asyncio.run(asyncio.wait_for(both(), 300))
            for s, w in zip(sessions, walks, strict=True):
                assert {c for c, _ in w} <= set(s.cells), (s.cells, w)
            health = [httpx.get(u + "/health", timeout=30).json() for u in urls]
            # Two long sessions at once: least_conn gives one to each replica.
            assert [h["sessions_total"] for h in health] == [1, 1], health
            execs = [h["compute"]["executor"] for h in health]
            assert all(e["kind"] == "dask" and e["state"] == "dask" for e in execs), execs
            assert sum(e["remote_jobs"] for e in execs) >= len(walks[0]) + len(walks[1])
            # A cell nobody walked, computed by the first replica, asked of the second:
            # answered from Redis.
            cell = next(c for c in range(len(grid)) if all(c != x for w in walks for x, _ in w))
            q = {"core": "sampling", "samples": 4, "resolution": 32}
            a = httpx.get(f"{urls[0]}/scenes/{SCENE}/cells/{cell}/pvs", params=q, timeout=300)
            b = httpx.get(f"{urls[1]}/scenes/{SCENE}/cells/{cell}/pvs", params=q, timeout=300)
            assert a.status_code == b.status_code == 200, (a.text, b.text)
            assert b.json()["cached"] and b.json()["stats"].get("redis") is True
            assert b.json()["triangle_ids"] == a.json()["triangle_ids"]
    finally:
        redis.stop()
