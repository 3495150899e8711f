"""The priority worker pool (retry, dead workers, prefetch skipping), cache pins and the on-disk
PVS cache."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from server.catalog import SceneCatalog
from server.compute import (
    ComputeService,
    DiskPVSCache,
    PriorityWorkerPool,
    PVSCache,
    WorkerDied,
    choose_core,
    core_fits,
)
from server.settings import Settings
from tests.conftest import NearCore, make_tiny_scene
from visibility.cores.base import PVS


def _pvs(n: int, start: int = 0) -> PVS:
    return PVS(np.arange(start, start + n, dtype=np.int32))


# --------------------------------------------------------------------------- pool
def test_pool_runs_by_priority_and_skips_unwanted():
    pool = PriorityWorkerPool(1)
    gate = threading.Event()
    order = []
    try:
        first = pool.submit(gate.wait, 10)  # occupies the only worker
        time.sleep(0.05)
        low = pool.submit(order.append, "low", priority=5)
        high = pool.submit(order.append, "high", priority=0)
        gone = pool.submit(order.append, "unwanted", priority=1, wanted=lambda: False)
        kept = pool.submit(order.append, "promoted", priority=9, wanted=lambda: False)
        pool.promote(kept, 0.5)  # a walker needs it now: runs, wanted or not
        gate.set()
        for f in (first, low, high, kept):
            f.result(10)
        assert gone.cancelled()
        assert order == ["high", "promoted", "low"]
        assert pool.skipped == 1
    finally:
        pool.shutdown()


def test_pool_retries_a_failed_job_once():
    pool = PriorityWorkerPool(2)
    calls = []

    def flaky():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("transient")
        return "ok"

    def broken():
        raise RuntimeError("always")

    try:
        assert pool.submit(flaky).result(10) == "ok" and len(calls) == 2
        with pytest.raises(RuntimeError, match="always"):
            pool.submit(broken).result(10)
        assert pool.retried == 2
    finally:
        pool.shutdown()


def test_dead_worker_is_replaced_and_job_retried():
    pool = PriorityWorkerPool(1)
    calls = []

    def dies_once():
        calls.append(1)
        if len(calls) == 1:
            raise WorkerDied("killed")
        return threading.current_thread().name

    try:
        name = pool.submit(dies_once).result(10)
        assert len(calls) == 2 and pool.replaced == 1
        assert name != "pvs-worker-0"  # a fresh thread ran the retry
        # The pool still has its full strength.
        assert pool.submit(lambda: 42).result(10) == 42
        with pytest.raises(RuntimeError, match="worker died"):
            pool.submit(_always_dies).result(10)
        assert pool.replaced == 3
        assert pool.submit(lambda: 7).result(10) == 7
    finally:
        pool.shutdown()


def _always_dies():
    raise WorkerDied("again")


def test_exempt_errors_are_not_retried():
    pool = PriorityWorkerPool(1, retry_exempt=(LookupError,))
    calls = []

    def missing():
        calls.append(1)
        raise KeyError("no such cell")

    try:
        with pytest.raises(KeyError):
            pool.submit(missing).result(10)
        assert len(calls) == 1 and pool.retried == 0
    finally:
        pool.shutdown()


# --------------------------------------------------------------------------- cache
def test_pinned_entries_survive_eviction():
    one = _pvs(100)
    size = 512 + 400
    cache = PVSCache(2 * size)
    cache.pin("a")
    cache.put("a", one)
    cache.put("b", _pvs(100, 1))
    cache.put("c", _pvs(100, 2))  # evicts b, never the pinned a
    assert "a" in cache and "b" not in cache and "c" in cache
    cache.put("d", _pvs(100, 3))
    assert "a" in cache and "c" not in cache
    cache.pin("a")
    cache.unpin("a")
    assert "a" in cache  # still pinned once
    cache.unpin("a")
    cache.put("e", _pvs(100, 4))
    assert "a" not in cache and cache.stats()["pinned"] == 0
    # A pinned entry bigger than the bound is kept (the walker needs it).
    small = PVSCache(100)
    small.pin("x")
    small.put("x", one)
    assert "x" in small


def test_disk_cache_survives_restart_and_ignores_corrupt_files(tmp_path, registered_test_cores):
    settings = Settings(generated={}, cache_dir=tmp_path / "pvs", workers=1)

    def service():
        cat = SceneCatalog(settings)
        cat.register("tiny", make_tiny_scene())
        return ComputeService(cat, settings)

    a = service()
    core, params = a.resolve("test_near", {"radius": 4.0})
    before = NearCore.calls
    first = a.submit("tiny", core, params, cell=2).result(30)
    assert not first.cached and NearCore.calls == before + 1
    a.shutdown()
    files = list((tmp_path / "pvs").rglob("*.npz"))
    assert len(files) == 1

    b = service()  # a restarted server: empty memory, same folder
    again = b.submit("tiny", core, params, cell=2).result(30)
    assert again.cached and NearCore.calls == before + 1
    np.testing.assert_array_equal(again.pvs.triangle_ids, first.pvs.triangle_ids)
    assert b.stats()["disk"]["hits"] == 1
    b.shutdown()

    files[0].write_bytes(b"PK\x03\x04 this is not a zip")
    c = service()
    third = c.submit("tiny", core, params, cell=2).result(30)
    assert not third.cached and NearCore.calls == before + 2  # recomputed, no error
    np.testing.assert_array_equal(third.pvs.triangle_ids, first.pvs.triangle_ids)
    assert c.stats()["disk"]["corrupt"] == 1
    c.shutdown()
    disk = DiskPVSCache(tmp_path / "pvs")
    assert disk.get(("tiny", 2, "test_near", params.cache_key())) is not None  # rewritten


def test_core_fits_and_auto_choice():
    scene = make_tiny_scene()

    class Flat(NearCore):
        name = "flat_only"
        requires_2_5d = True

    ok, why = core_fits(Flat(), scene)
    assert not ok and "2.5D" in why
    scene.meta["is_2_5d"] = True
    assert core_fits(Flat(), scene)[0]
    del scene.meta["is_2_5d"]
    name, why = choose_core(scene)
    assert name in ("from_segment", "sampling") and why
