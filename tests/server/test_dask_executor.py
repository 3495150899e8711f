"""The Dask executor (``server.dask_executor``) on a REAL ``distributed.LocalCluster`` of worker
processes: the same PVS as the local pool for every registered core, a live server streaming a
walkthrough through the cluster, a worker process killed mid-job (the job is retried, the client
sees no error), a scheduler that goes away (the server computes locally and keeps serving) and
``pvs precompute --executor dask://...`` (same cells as the local pool, resumable).

One module-wide cluster of 2 single-thread workers serves most tests; kernels compile once in
this process first (``NUMBA_CACHE_DIR``), so the workers load them from the cache.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from client.session import Session
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.dask_executor import DaskExecutor
from server.executor import LocalExecutor
from server.executor_address import scheduler_address
from server.region import cell_key
from server.resolve import Resolver
from server.settings import Settings
from tests.conftest import make_tiny_scene, near_ids, serving, wait_for
from visibility.cores import checks
from visibility.cores.base import available_cores, get_core

#: One worker runs this module, so its costly module fixtures run once, not once per worker.
pytestmark = pytest.mark.xdist_group("dask_executor")

FAST = {"samples": 4, "resolution": 32}
TINY = make_tiny_scene()


def dask_url(cluster) -> str:
    return cluster.scheduler_address.replace("tcp://", "dask://")


@pytest.fixture(scope="module")
def cluster():
    from distributed import LocalCluster

    c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                     silence_logs=logging.ERROR)
    try:
        yield c
    finally:
        c.close()


@pytest.fixture(scope="module")
def client(cluster):
    """A client of the test's own, to look into the cluster."""
    from distributed import Client

    with Client(cluster, set_as_default=False) as c:
        yield c


# --------------------------------------------------------------------------- settings
def test_the_executor_setting_names_local_or_a_scheduler():
    assert Settings().executor == "local"
    assert Settings(executor="dask://10.0.0.5:8786").executor == "dask://10.0.0.5:8786"
    assert scheduler_address("dask://sched.example:8786") == "tcp://sched.example:8786"
    assert Settings.from_env({"PVS_EXECUTOR": "dask://h:1"}).executor == "dask://h:1"
    for bad in ("dask://host", "spark://h:1", "dask://h:0", "dask://h:99999", "",
                "dask://h:1?scenes=copy"):
        with pytest.raises(ValueError):
            Settings(executor=bad)


def test_the_local_default_never_imports_distributed():
    code = ("import sys\nfrom server.app import create_app\nfrom server.settings import Settings\n"
            "app = create_app(Settings(generated={}))\n"
            "assert app.state.server.compute.stats()['executor']['kind'] == 'local'\n"
            "assert 'distributed' not in sys.modules, 'distributed imported'\n")
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": root}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr


def test_an_unreachable_scheduler_leaves_the_local_pool_computing(settings, caplog):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with caplog.at_level(logging.WARNING, logger="server.dask_executor"):
        ex = DaskExecutor(f"tcp://127.0.0.1:{port}", 1, connect_timeout=0.5,
                          reconnect_every=3600)
    s = settings.model_copy(update={"generated": {}})
    service = ComputeService(SceneCatalog(s), s, executor=ex)
    service.catalog.register("tiny", TINY)
    try:
        core = get_core("sampling")
        r = service.submit("tiny", core, core.make_params(**FAST), cell=1).result(timeout=60)
        want = core.compute(TINY, service.catalog.get("tiny").grid.cell(1),
                            core.make_params(**FAST))
    finally:
        service.shutdown()
    np.testing.assert_array_equal(r.pvs.triangle_ids, want.triangle_ids)
    assert ex.state()["state"] == "local_fallback" and ex.state()["local_jobs"] == 1
    assert [r.message for r in caplog.records if "unreachable" in r.getMessage()]


def test_the_executor_goes_back_to_the_cluster_when_its_scheduler_comes(settings, caplog):
    from distributed import LocalCluster

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ex = DaskExecutor(f"tcp://127.0.0.1:{port}", 1, connect_timeout=0.5, reconnect_every=0.5)
    catalog = SceneCatalog(settings.model_copy(update={"generated": {}}))
    catalog.register("tiny", TINY)
    loaded = catalog.get("tiny")
    core = get_core("sampling")
    params = core.make_params(**FAST)
    want = core.compute(TINY, loaded.grid.cell(0), params).triangle_ids
    late = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                        scheduler_port=port, dashboard_address=":0",
                        silence_logs=logging.ERROR)
    try:
        with caplog.at_level(logging.INFO, logger="server.dask_executor"):
            # Each job asks for the cluster; one of them starts the reconnection.
            wait_for(lambda: ex.compute(loaded, core, params, cell=loaded.grid.cell(0)) is not None
                     and ex.state()["state"] == "dask", 60)
            got = ex.compute(loaded, core, params, cell=loaded.grid.cell(0))
        state = ex.state()
    finally:
        ex.close()
        late.close()
    np.testing.assert_array_equal(got.triangle_ids, want)
    assert state["remote_jobs"] >= 1 and state["local_jobs"] >= 1
    assert any("computing on the Dask cluster" in r.getMessage() for r in caplog.records)


# --------------------------------------------------------------------------- same answers
@pytest.fixture(scope="module")
def services(cluster):
    """(service on the cluster, local service), each with the designed scenes registered."""
    from visibility.cores import designed_scenes as ds

    base = Settings(generated={}, progressive=False, calibrate=False, workers=2)
    out = []
    for executor in (dask_url(cluster), "local"):
        s = base.model_copy(update={"executor": executor})
        svc = ComputeService(SceneCatalog(s), s)
        for name in ("two_rooms_and_a_door", "city_blocks"):
            svc.catalog.register(name, getattr(ds, name)()[0])
        out.append(svc)
    yield tuple(out)
    for svc in out:
        svc.shutdown()


@pytest.mark.parametrize("core_name", available_cores())
def test_same_pvs_on_the_cluster_as_on_the_local_pool(services, core_name):
    remote, local = services
    core = get_core(core_name)
    scene, cell, _, _ = checks.main_case(core)
    name = "city_blocks" if core.requires_2_5d else "two_rooms_and_a_door"
    params = checks.check_params(core, 64)
    before = remote.executor.state()["remote_jobs"]
    # Local first: its compilation fills the numba cache the workers then read.
    want = local.submit(name, core, params, box=cell.box).result(timeout=300)
    got = remote.submit(name, core, params, box=cell.box).result(timeout=300)
    assert len(want.pvs) > 0
    np.testing.assert_array_equal(got.pvs.triangle_ids, want.pvs.triangle_ids)
    assert got.pvs.granularity == want.pvs.granularity
    state = remote.executor.state()
    assert state["state"] == "dask" and state["remote_jobs"] == before + 1
    assert state["local_jobs"] == 0


def test_workers_load_scenes_themselves_by_content_hash(cluster, settings, scenes_dir, tmp_path,
                                                        caplog):
    """``?scenes=load``: the workers load scene files (the same path) and regenerate generated
    scenes, checked by content hash, and nothing is scattered; a scene registered in memory,
    and a file whose content changed after the server loaded it, are scattered instead."""
    import shutil

    folder = tmp_path / "scenes"
    folder.mkdir()
    for f in ("box.obj", "box.json"):
        shutil.copy(scenes_dir / f, folder / f)
    shutil.copy(scenes_dir / "box.obj", folder / "changed.obj")
    s = settings.model_copy(update={"scenes_dir": folder, "generated": {"rooms": 3000},
                                    "executor": dask_url(cluster) + "?scenes=load"})
    assert Settings(executor="dask://h:1?scenes=load").executor.endswith("?scenes=load")
    service = ComputeService(SceneCatalog(s), s)
    service.catalog.register("tiny", TINY)
    core = get_core("sampling")
    params = core.make_params(**FAST)

    def both(name: str, cell: int) -> tuple[np.ndarray, np.ndarray]:
        loaded = service.catalog.get(name)
        want = core.compute(loaded.scene, loaded.grid.cell(cell), params).triangle_ids
        got = service.submit(name, core, params, cell=cell).result(timeout=120)
        return got.pvs.triangle_ids, want

    try:
        for name in ("box", "rooms"):
            np.testing.assert_array_equal(*both(name, 0))
        state = service.executor.state()
        assert state["scenes"] == "load" and state["scattered"] == 0
        assert state["remote_jobs"] == 2 and state["local_jobs"] == 0
        np.testing.assert_array_equal(*both("tiny", 1))  # in memory: scattered
        assert service.executor.state()["scattered"] == 1
        service.catalog.get("changed")  # the server holds the box...
        v = "\n".join(f"v {x} {y} {z}" for x, y, z in
                      [(0, 0, 0), (9, 0, 0), (9, 4, 0), (0, 4, 9)])
        (folder / "changed.obj").write_text(v + "\nf 1 2 3\nf 1 3 4\n")  # ...the file, other
        with caplog.at_level(logging.WARNING, logger="server.dask_executor"):
            got, want = both("changed", 0)
        np.testing.assert_array_equal(got, want)
        assert len(want) > 0
        state = service.executor.state()
    finally:
        service.shutdown()
    assert state["scattered"] == 2 and state["local_jobs"] == 0
    assert [r for r in caplog.records if "could not load scene changed" in r.getMessage()]


# --------------------------------------------------------------------------- live server
def test_a_walkthrough_streams_through_the_cluster(cluster, settings):
    core = get_core("sampling")
    params = core.make_params(**FAST, seed=3)
    with serving(settings, {"tiny": TINY}, executor=dask_url(cluster)) as (url, app):
        grid = app.state.server.catalog.get("tiny").grid
        walk = [0, 1, 2, 3, 7]
        want = {c: core.compute(TINY, grid.cell(c), params).triangle_ids for c in walk}

        async def main():
            s = await Session.connect(url, "tiny", "sampling", {**FAST, "seed": 3},
                                      prefetch=False)
            held = []
            for seq, c in enumerate(walk):
                await s.send_pose(seq, 0.5 * seq, grid.boxes[c].mean(axis=0), (1.0, 0.0, 0.0))
                await s.wait_cell(c, 120)
                held.append(s.store.ids.copy())
            await s.close()
            return s, held

        s, held = asyncio.run(asyncio.wait_for(main(), 240))
        health = httpx.get(url + "/health", timeout=30).json()
    assert not s.errors
    seen: set[int] = set()
    for c, ids in zip(walk, held, strict=True):
        seen |= set(want[c].tolist())
        # The store holds exactly the union of the PVS of the cells walked so far.
        assert set(ids.tolist()) == seen, c
    ex = health["compute"]["executor"]
    assert ex["kind"] == "dask" and ex["state"] == "dask"
    assert ex["remote_jobs"] >= len(walk) and ex["local_jobs"] == 0
    assert ex["overhead_ms"] is not None and ex["overhead_ms"] >= 0


def test_a_worker_killed_mid_job_is_retried_and_the_client_sees_no_error(
        cluster, client, settings, registered_test_cores):
    with serving(settings, {"tiny": TINY}, executor=dask_url(cluster)) as (url, app):
        box = app.state.server.catalog.get("tiny").grid.boxes[3]
        out: dict = {}

        def ask():
            out["r"] = httpx.get(f"{url}/scenes/tiny/cells/3/pvs",
                                 params={"core": "test_slow", "radius": 4.5, "delay": 3.0},
                                 timeout=180)

        t = threading.Thread(target=ask)
        t.start()
        busy: list = []

        def running():
            busy[:] = [w for w, keys in client.processing().items()
                       if any(str(k).startswith("pvs-test_slow") for k in keys)]
            return bool(busy)

        wait_for(running, 60)
        time.sleep(0.5)  # inside its 3 s sleep
        pid = client.run(os.getpid, workers=busy[:1])[busy[0]]
        os.kill(pid, signal.SIGKILL)
        t.join(180)
        state = app.state.server.compute.executor.state()
    r = out["r"]
    assert r.status_code == 200, r.text
    np.testing.assert_array_equal(r.json()["triangle_ids"], near_ids(TINY, box, 4.5))
    # It ran on the cluster again, not on the server's fallback.
    assert state["state"] == "dask" and state["local_jobs"] == 0 and state["losses"] == 0
    # The nanny restarts it for the next tests; on a machine busy with the suite and other
    # jobs a worker process took over 120 s to start.
    client.wait_for_workers(2, timeout=300)
    assert pid not in client.run(os.getpid).values()


def test_a_walkthrough_survives_a_worker_killed_mid_job(cluster, client, settings,
                                                       registered_test_cores):
    """A walker's cell is being computed on a worker that is SIGKILLed: the scheduler reruns
    the job elsewhere, the walker gets the cell and then the next one, with no error."""
    radius = 4.5
    with serving(settings, {"tiny": TINY}, executor=dask_url(cluster)) as (url, app):
        grid = app.state.server.catalog.get("tiny").grid
        walk = [3, 2]

        def busy() -> list:
            return [w for w, keys in client.processing().items()
                    if any(str(k).startswith("pvs-test_slow") for k in keys)]

        async def main():
            s = await Session.connect(url, "tiny", "test_slow",
                                      {"radius": radius, "delay": 3.0}, prefetch=False)
            await s.send_pose(0, 0.0, grid.boxes[walk[0]].mean(axis=0), (1.0, 0.0, 0.0))
            await asyncio.to_thread(wait_for, lambda: bool(busy()), 60)
            await asyncio.sleep(0.5)  # inside the job's 3 s sleep
            victim = busy()[:1]
            pid = client.run(os.getpid, workers=victim)[victim[0]]
            os.kill(pid, signal.SIGKILL)
            await s.wait_cell(walk[0], 180)
            await s.send_pose(1, 1.0, grid.boxes[walk[1]].mean(axis=0), (1.0, 0.0, 0.0))
            await s.wait_cell(walk[1], 180)
            held = s.store.ids.copy()
            await s.close()
            return s, held, pid

        s, held, pid = asyncio.run(asyncio.wait_for(main(), 300))
        state = app.state.server.compute.executor.state()
    assert not s.errors
    want = set(near_ids(TINY, grid.boxes[walk[0]], radius).tolist()) \
        | set(near_ids(TINY, grid.boxes[walk[1]], radius).tolist())
    assert set(held.tolist()) == want
    assert state["state"] == "dask" and state["local_jobs"] == 0
    # The nanny restarts it for the next tests; on a machine busy with the suite and other
    # jobs a worker process took over 120 s to start.
    client.wait_for_workers(2, timeout=300)
    assert pid not in client.run(os.getpid).values()


def test_a_lost_scheduler_degrades_to_the_local_pool(settings, registered_test_cores, caplog):
    from distributed import LocalCluster

    # A cluster of its own (one worker thread in this process), closed under a running job.
    doomed = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                          dashboard_address=":0", silence_logs=logging.ERROR)
    try:
        with caplog.at_level(logging.WARNING, logger="server.dask_executor"), \
                serving(settings, {"tiny": TINY}, executor=dask_url(doomed)) as (url, app):
            grid = app.state.server.catalog.get("tiny").grid
            out: dict = {}

            def ask():
                out["r"] = httpx.get(f"{url}/scenes/tiny/cells/2/pvs",
                                     params={"core": "test_slow", "radius": 4.5, "delay": 2.0},
                                     timeout=120)

            t = threading.Thread(target=ask)
            t.start()
            wait_for(lambda: any(str(k).startswith("pvs-test_slow")
                                 for k in doomed.scheduler.tasks), 60)
            doomed.close()
            t.join(120)
            r = out["r"]
            assert r.status_code == 200, r.text
            np.testing.assert_array_equal(r.json()["triangle_ids"],
                                          near_ids(TINY, grid.boxes[2], 4.5))
            # The server goes on serving, locally.
            again = httpx.get(f"{url}/scenes/tiny/cells/5/pvs",
                              params={"core": "test_near", "radius": 4.5}, timeout=120)
            health = httpx.get(url + "/health", timeout=30).json()
    finally:
        doomed.close()
    assert again.status_code == 200
    np.testing.assert_array_equal(again.json()["triangle_ids"],
                                  near_ids(TINY, grid.boxes[5], 4.5))
    ex = health["status"], health["compute"]["executor"]
    assert ex[0] == "ok" and ex[1]["state"] == "local_fallback"
    assert ex[1]["local_jobs"] == 2 and ex[1]["losses"] == 1
    lost = [r for r in caplog.records if "lost" in r.getMessage()]
    assert len(lost) == 1 and "local pool" in lost[0].getMessage()


# --------------------------------------------------------------------------- precompute
def test_precompute_on_the_cluster_equals_the_local_pool_and_resumes(cluster, tmp_path,
                                                                     monkeypatch, capsys):
    from pvs_cli import main

    monkeypatch.setenv("PVS_GENERATED", "rooms=3000")
    monkeypatch.setenv("PVS_SCENES_DIR", str(tmp_path / "no-scenes"))
    (tmp_path / "no-scenes").mkdir()
    common = ["precompute", "--scene", "rooms", "--core", "sampling", "--param", "samples=4",
              "--param", "resolution=32", "--quiet"]
    on_cluster = str(tmp_path / "dask-cache")
    assert main([*common, "--cache-dir", on_cluster, "--cells", "0-3",
                 "--executor", dask_url(cluster)]) == 0
    assert "4 computed" in capsys.readouterr().out
    assert main([*common, "--cache-dir", on_cluster, "--executor", dask_url(cluster)]) == 0
    summary = capsys.readouterr().out
    assert "4 already cached" in summary and "0 failed" in summary
    n = int(summary.split(": ")[1].split(" cells")[0])
    assert f"{n - 4} computed" in summary
    here = str(tmp_path / "local-cache")
    assert main([*common, "--cache-dir", here]) == 0
    capsys.readouterr()

    def read_all(folder: str) -> list[np.ndarray]:
        s = Settings(generated={"rooms": 3000}, cache_dir=Path(folder), calibrate=False,
                     progressive=False)
        svc = ComputeService(SceneCatalog(s), s, executor=LocalExecutor(1))
        try:
            core = get_core("sampling")
            p = core.make_params(**FAST)
            out = [svc.submit("rooms", core, p, cell=c).result(timeout=60) for c in range(n)]
            assert svc.computed == 0, "every cell must come from the disk cache"
            return [r.pvs.triangle_ids for r in out]
        finally:
            svc.shutdown()

    for a, b in zip(read_all(on_cluster), read_all(here), strict=True):
        np.testing.assert_array_equal(a, b)


def test_precompute_on_the_cluster_into_redis_resumes(cluster, redis_server, tmp_path,
                                                      monkeypatch, capsys):
    """The scale-out pieces together: cells computed on the cluster land in the shared Redis
    cache (no disk cache), and a second run finds them there."""
    from pvs_cli import main

    monkeypatch.setenv("PVS_GENERATED", "rooms=3000")
    monkeypatch.setenv("PVS_SCENES_DIR", str(tmp_path / "no-scenes"))
    (tmp_path / "no-scenes").mkdir()
    common = ["precompute", "--scene", "rooms", "--core", "sampling", "--param", "samples=4",
              "--param", "resolution=32", "--quiet", "--cache", redis_server.url,
              "--executor", dask_url(cluster), "--cells", "0-3"]
    assert main(common) == 0
    assert "4 computed" in capsys.readouterr().out
    keys = {k.decode() for k in redis_server.client().keys("pvs:*:sampling:*")}
    s = Settings(generated={"rooms": 3000})
    loaded = SceneCatalog(s).get("rooms")
    choice = Resolver(s).named("sampling", {"samples": 4, "resolution": 32})
    assert keys == {cell_key(loaded, c, choice.core, choice.params).shared() for c in range(4)}
    assert main(common) == 0
    summary = capsys.readouterr().out
    assert "4 already cached" in summary and "0 computed" in summary, summary
