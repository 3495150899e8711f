"""The priority worker pool (retry, dead workers, prefetch skipping), cache pins and the on-disk
PVS cache."""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import Future
from contextlib import contextmanager

import numpy as np
import pytest

from server.cache import DiskPVSCache, PVSCache, PVSKey
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.pool import PriorityWorkerPool, WorkerDied
from server.region import cell_key
from server.resolve import Resolver, choose_core, core_fits
from server.settings import Settings
from tests.conftest import NearCore, make_tiny_scene, near_ids, wait_for
from visibility.cores.base import PVS


def _pvs(n: int, start: int = 0) -> PVS:
    return PVS(np.arange(start, start + n, dtype=np.int32))


def _named(svc: ComputeService, core: str, params: dict):
    choice = Resolver(svc.settings).named(core, params)
    return choice.core, choice.params


#: A key of a made-up scene for the disk tier on its own.
KEY = PVSKey.of("f" * 16, "box", np.zeros((2, 3)), "core", "p=1")


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


def test_ordinary_exceptions_are_answers_never_retried():
    """A job's Exception (a core's ValueError, an unknown cell) is deterministic: it reaches the
    caller after one run, without a second attempt."""
    pool = PriorityWorkerPool(2)
    calls = []

    def bad_params():
        calls.append(1)
        raise ValueError("resolution out of range")

    def missing():
        calls.append(1)
        raise KeyError("no such cell")

    try:
        with pytest.raises(ValueError, match="resolution"):
            pool.submit(bad_params).result(10)
        with pytest.raises(KeyError):
            pool.submit(missing).result(10)
        assert len(calls) == 2 and pool.retried == 0 and pool.replaced == 0
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


def _blocked_pool():
    """A one-worker pool whose worker is busy until the returned event is set."""
    pool = PriorityWorkerPool(1)
    gate = threading.Event()
    started = threading.Event()

    def block():
        started.set()
        gate.wait(30)

    blocker = pool.submit(block)
    assert started.wait(10)
    return pool, gate, blocker


def test_rerank_moves_queued_jobs_both_ways():
    pool, gate, blocker = _blocked_pool()
    order = []
    try:
        futs = {n: pool.submit(order.append, n, priority=p) for n, p in
                (("a", 1.0), ("b", 2.0), ("c", 3.0))}
        assert [j["priority"] for j in pool.snapshot()] == [1.0, 2.0, 3.0]
        assert pool.rerank(futs["a"], 5.0)  # later: the walker turned away
        assert pool.rerank(futs["c"], 0.5)  # sooner: the walker is about to arrive
        assert not pool.rerank(futs["b"], 2.0)  # no change, not counted
        assert pool.reranks == {"sooner": 1, "later": 1}
        assert [j["priority"] for j in pool.snapshot()] == [0.5, 2.0, 5.0]
        assert pool.queued() == 3  # each job once, whatever its stale entries
        gate.set()
        for f in [blocker, *futs.values()]:
            f.result(10)
        assert order == ["c", "b", "a"]
        # A started (here: finished) job is never re-ranked.
        assert not pool.rerank(futs["a"], 0.0)
        assert pool.reranks == {"sooner": 1, "later": 1}
    finally:
        gate.set()
        pool.shutdown()


def test_lighten_moves_only_a_queued_heavy_job_estimated_light():
    pool, gate, blocker = _blocked_pool()
    try:
        cheap = pool.submit(lambda: None, seconds=0.5, heavy=True)
        dear = pool.submit(lambda: None, seconds=9.0, heavy=True)
        assert not pool.lighten(dear, 2.0)  # heavy for its estimate: it stays heavy
        assert pool.lighten(cheap, 2.0)  # heavy only for who asked: it moves
        assert not pool.lighten(cheap, 2.0)  # already light
        lanes = {j["seconds"]: j["heavy"] for j in pool.snapshot()}
        assert lanes == {0.5: False, 9.0: True}
        gate.set()
        for f in (blocker, cheap, dear):
            f.result(10)
        assert not pool.lighten(dear, 100.0)  # done: never moved
    finally:
        gate.set()
        pool.shutdown()


def test_since_breaks_ties_before_the_estimate():
    """Among priority 0 (walkers' current cells), the cell entered earliest goes first, even
    when a later one is cheaper; equal ``since``: shortest estimate first."""
    pool, gate, blocker = _blocked_pool()
    order = []
    try:
        late = pool.submit(order.append, "entered at 2", since=2.0, seconds=0.1)
        early = pool.submit(order.append, "entered at 1", since=1.0, seconds=9.0)
        short = pool.submit(order.append, "entered at 1, short", since=1.0, seconds=1.0)
        ahead = pool.submit(order.append, "ahead", priority=0.001, since=0.0)
        gate.set()
        for f in (blocker, late, early, short, ahead):
            f.result(10)
        assert order == ["entered at 1, short", "entered at 1", "entered at 2", "ahead"]
    finally:
        gate.set()
        pool.shutdown()


def test_many_reranks_keep_order_and_a_bounded_heap():
    from server.pool import MIN_STALE_TO_COMPACT

    rng = np.random.default_rng(1)
    pool, gate, blocker = _blocked_pool()
    order = []
    try:
        futs = [pool.submit(order.append, i, priority=float(i)) for i in range(20)]
        final = {}
        for _ in range(2000):
            i = int(rng.integers(20))
            final[i] = float(rng.uniform(0, 100))
            pool.rerank(futs[i], final[i])
            # Live entries plus at most the stale ones tolerated before a rebuild.
            assert len(pool._heap) <= 20 + MIN_STALE_TO_COMPACT + 1
        prio = [final.get(i, float(i)) for i in range(20)]
        listed = [j["priority"] for j in pool.snapshot()]
        assert listed == sorted(round(p, 3) for p in prio)
        gate.set()
        for f in [blocker, *futs]:
            f.result(10)
        assert order == sorted(range(20), key=lambda i: prio[i])
        assert pool.reranks["sooner"] + pool.reranks["later"] > 1000
    finally:
        gate.set()
        pool.shutdown()


def test_rerank_leaves_other_pools_and_dropped_jobs_alone():
    pool, gate, blocker = _blocked_pool()
    other = PriorityWorkerPool(1)
    try:
        mine = pool.submit(lambda: 1, priority=1.0)
        theirs = other.submit(lambda: 2, priority=1.0)
        assert not pool.rerank(theirs, 0.0) and not pool.rerank(Future(), 0.0)
        gone = pool.submit(lambda: 3, priority=0.5, wanted=lambda: False)
        gate.set()
        assert mine.result(10) == 1 and theirs.result(10) == 2
        wait_for(gone.cancelled, 10)
        assert not pool.rerank(gone, 0.0)  # skipped: never queued again
        assert pool.skipped == 1 and pool.queued() == 0
    finally:
        gate.set()
        pool.shutdown()
        other.shutdown()


def test_a_rerank_wins_over_needed_and_promote_only_moves_sooner():
    pool, gate, blocker = _blocked_pool()
    order = []
    try:
        x = pool.submit(order.append, "x", priority=3.0, wanted=lambda: False)
        y = pool.submit(order.append, "y", priority=2.0)
        pool.promote(x, 5.0)  # not sooner: stays at 3, but now runs wanted or not
        assert pool.snapshot()[1]["priority"] == 3.0
        pool.promote(x, 1.0)
        gate.set()
        for f in (blocker, x, y):
            f.result(10)
        assert order == ["x", "y"] and pool.skipped == 0
    finally:
        gate.set()
        pool.shutdown()


def test_service_ranks_walkers_needs_and_http_callers_together(registered_test_cores):
    """A walker's job runs at the walker's rank; an HTTP caller joining lifts it to 0 while it
    waits; when the caller leaves it drops back to the walker's rank; when no walker wants it
    and nobody waits it is cancelled unrun, while one a caller waits for goes on."""
    settings = Settings(generated={}, workers=1)
    cat = SceneCatalog(settings)
    cat.register("tiny", make_tiny_scene())
    svc = ComputeService(cat, settings)
    core = NearCore()
    walk = core.make_params(radius=3.0)
    try:
        blocker = svc.submit("tiny", core, core.make_params(radius=4.0, delay=2.0), cell=0)
        wait_for(lambda: svc.stats()["pool"]["queued"] == 0)  # running: the rest queues
        k1, k2 = (svc.key("tiny", core, walk, cell=c) for c in (1, 2))
        svc.want("w", {k1: (2.0, 0.0), k2: (3.0, 0.0)})
        f1 = svc.submit("tiny", core, walk, cell=1, priority=9.0, walker=True,
                        wanted=lambda: True)
        f2 = svc.submit("tiny", core, walk, cell=2, priority=9.0, walker=True,
                        wanted=lambda: True)

        def queue():
            return [(j["what"].split()[2], j["priority"]) for j in svc.stats()["pool"]["queue"]]

        assert queue() == [("1", 2.0), ("2", 3.0)]  # the walker's ranks, not the argument
        http = svc.submit("tiny", core, walk, cell=2)  # an HTTP caller joins cell 2
        assert http is f2 and queue() == [("2", 0.0), ("1", 2.0)]
        assert not svc.release(http)  # it leaves; the walker still wants the cell
        assert queue() == [("1", 2.0), ("2", 3.0)]
        assert svc.stats()["pool"]["reranks"] == {"sooner": 1, "later": 1}
        again = svc.submit("tiny", core, walk, cell=2)  # a caller waits for cell 2 again
        assert svc.unwant("w") == 1  # the walker leaves: cell 1 goes, cell 2 stays
        assert f1.cancelled() and not f2.done()
        assert svc.stats()["cancellations"]["unwanted"] == {"queued": 1}
        blocker.result(30)
        np.testing.assert_array_equal(again.result(30).pvs.triangle_ids,
                                      near_ids(make_tiny_scene(),
                                               cat.get("tiny").grid.boxes[2], 3.0))
    finally:
        svc.shutdown()


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
    core, params = _named(a, "test_near", {"radius": 4.0})
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
    key = cell_key(c.catalog.get("tiny"), 2, core, params)
    assert disk.get(key) is not None  # rewritten


def test_core_fits_and_auto_choice():
    scene = make_tiny_scene()

    class Flat(NearCore):
        name = "flat_only"
        requires_2_5d = True

    scene.meta["is_2_5d"] = False  # the meta overrides the geometry (boxes on a ground: 2.5D)
    ok, why = core_fits(Flat(), scene)
    assert not ok and "2.5D" in why
    scene.meta["is_2_5d"] = True
    assert core_fits(Flat(), scene)[0]
    del scene.meta["is_2_5d"]
    assert core_fits(Flat(), scene)[0]  # decided from the geometry now
    name, why = choose_core(scene)
    assert name in ("from_segment", "sampling") and why


# --------------------------------------------------------------------------- disk cache keys
def test_disk_cache_never_shares_entries_across_grids_or_geometry(tmp_path, registered_test_cores):
    """The on-disk key names the scene's geometry and the cell's box: a restart with another
    cell size or another scene under the same name computes afresh; the same set-up reuses."""
    folder = tmp_path / "pvs"

    def answer(scene, cell_size: float):
        settings = Settings(generated={}, cache_dir=folder, workers=1, cell_size=cell_size)
        cat = SceneCatalog(settings)
        cat.register("tiny", scene)
        svc = ComputeService(cat, settings)
        core, params = _named(svc, "test_near", {"radius": 2.0})
        try:
            r = svc.submit("tiny", core, params, cell=1).result(30)
        finally:
            svc.shutdown()
        box = cat.get("tiny").grid.boxes[1]
        np.testing.assert_array_equal(r.pvs.triangle_ids, near_ids(scene, box, 2.0))
        return r

    tiny = make_tiny_scene()
    assert not answer(tiny, 4.0).cached
    assert not answer(tiny, 3.0).cached  # cell 1 is another box now
    moved = make_tiny_scene()
    moved.vertices[:, 0] += 1.5  # same name, other geometry
    assert not answer(moved, 4.0).cached
    assert answer(tiny, 4.0).cached and answer(tiny, 3.0).cached and answer(moved, 4.0).cached
    assert len(list(folder.rglob("*.npz"))) == 3


# --------------------------------------------------------------------------- worker death
class DyingCore(NearCore):
    """Kills its worker on the first call; the retry waits for ``release``."""

    name = "test_dying"
    runs = 0
    retry_started = threading.Event()
    release = threading.Event()

    def _compute(self, scene, cell, params):
        type(self).runs += 1
        if type(self).runs == 1:
            raise WorkerDied("killed mid-computation")
        type(self).retry_started.set()
        type(self).release.wait(30)
        return super()._compute(scene, cell, params)


def test_worker_death_is_retried_once_and_joined_not_duplicated(registered_test_cores):
    settings = Settings(generated={}, workers=1)
    cat = SceneCatalog(settings)
    cat.register("tiny", make_tiny_scene())
    svc = ComputeService(cat, settings)
    core = DyingCore()
    params = core.make_params(radius=3.0)
    try:
        first = svc.submit("tiny", core, params, cell=5)
        assert DyingCore.retry_started.wait(30)  # the worker died; its replacement retries
        # An identical request during the retry joins it instead of computing again.
        second = svc.submit("tiny", core, params, cell=5)
        assert second is first and svc.stats()["inflight"] == 1
        DyingCore.release.set()
        result = first.result(30)
        box = cat.get("tiny").grid.boxes[5]
        np.testing.assert_array_equal(result.pvs.triangle_ids,
                                      near_ids(make_tiny_scene(), box, 3.0))
        assert DyingCore.runs == 2
        stats = svc.stats()
        assert stats["pool"]["replaced"] == 1 and stats["pool"]["retried"] == 1
        assert stats["inflight"] == 0 and stats["computed"] == 1
        # The replacement worker serves later requests.
        assert svc.submit("tiny", core, params, cell=5).result(30).cached
    finally:
        DyingCore.release.set()
        svc.shutdown()


# --------------------------------------------------------------------------- disk entries checked
def _disk_service(folder):
    settings = Settings(generated={}, cache_dir=folder, workers=1)
    cat = SceneCatalog(settings)
    cat.register("tiny", make_tiny_scene())
    return ComputeService(cat, settings)


def _rewrite(path, **changes) -> None:
    """Rewrite the entry at ``path`` with ``changes``; ``resign=True`` recomputes the checksum
    (a forged entry), otherwise it is left stale (a corrupted one)."""
    from server.cache.disk import _checksum

    resign = changes.pop("resign", False)
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d.update({k: np.asarray(v) for k, v in changes.items()})
    if resign:
        d["checksum"] = np.array(_checksum(str(d["key"]), int(d["n_triangles"]),
                                           str(d["granularity"]), d["triangle_ids"],
                                           d["object_ids"] if d["has_objects"] else None,
                                           d["sphere_ids"] if d["has_spheres"] else None))
    with open(path, "wb") as fh:
        np.savez(fh, **d)


def _tamper_other_fingerprint(path):
    with np.load(path, allow_pickle=False) as z:
        key = str(z["key"])
    fp = key.split("'")[1]
    _rewrite(path, key=key.replace(fp, "0" * len(fp)), fingerprint="0" * len(fp), resign=True)


TAMPERINGS = {
    "bad checksum": lambda p: _rewrite(p, triangle_ids=np.array([0, 1], np.int32)),
    "out-of-range ids, stale checksum": lambda p: _rewrite(
        p, triangle_ids=np.array([0, 10**6], np.int32)),
    "out-of-range ids, forged checksum": lambda p: _rewrite(
        p, triangle_ids=np.array([0, 10**6], np.int32), n_triangles=12, resign=True),
    "unsorted ids, forged checksum": lambda p: _rewrite(
        p, triangle_ids=np.array([3, 1], np.int32), resign=True),
    "wrong key": lambda p: _rewrite(p, key="('another', 'key')", resign=True),
    "other fingerprint": _tamper_other_fingerprint,
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]),
    "not a zip": lambda p: p.write_bytes(b"PK\x03\x04 garbage"),
}


@pytest.mark.parametrize("how", list(TAMPERINGS))
def test_bad_disk_entries_are_rejected_deleted_and_recomputed(tmp_path, registered_test_cores,
                                                                how, caplog):
    folder = tmp_path / "pvs"
    a = _disk_service(folder)
    core, params = _named(a, "test_near", {"radius": 4.0})
    first = a.submit("tiny", core, params, cell=2).result(30)
    a.shutdown()
    [entry] = list(folder.rglob("*.npz"))
    TAMPERINGS[how](entry)

    b = _disk_service(folder)
    before = NearCore.calls
    again = b.submit("tiny", core, params, cell=2).result(30)
    b.shutdown()
    assert not again.cached and NearCore.calls == before + 1  # recomputed, never served
    np.testing.assert_array_equal(again.pvs.triangle_ids, first.pvs.triangle_ids)
    disk = b.stats()["disk"]
    assert disk["rejected"] == 1 and disk["hits"] == 0 and disk["writes"] == 1
    assert "rejected an on-disk PVS cache entry" in caplog.text
    assert str(tmp_path) not in caplog.text and str(tmp_path) not in repr(disk)
    # The bad file was replaced by a good entry that the next start reads.
    loaded = b.catalog.get("tiny")
    key = cell_key(loaded, 2, core, params)
    assert DiskPVSCache(folder).check(key, loaded.scene.n_triangles)
    c = _disk_service(folder)
    assert c.submit("tiny", core, params, cell=2).result(30).cached
    c.shutdown()


def test_reader_bounds_ids_by_the_scene_it_knows(tmp_path):
    disk = DiskPVSCache(tmp_path)
    key = KEY
    assert disk.put(key, _pvs(5, start=3))  # writer did not know the triangle count
    assert disk.get(key) is not None
    assert disk.get(key, n_triangles=8) is not None
    assert disk.get(key, n_triangles=7) is None  # id 7 is out of a 7-triangle scene
    assert disk.stats()["rejected"] == 1 and not disk.path(key).exists()
    # A stored count must match the reader's.
    assert disk.put(key, _pvs(5), n_triangles=100)
    assert disk.get(key, n_triangles=101) is None and disk.stats()["rejected"] == 2
    # A PVS that would be rejected is never written.
    assert not disk.put(key, _pvs(5, start=98), n_triangles=100)
    assert disk.stats()["write_errors"] == 1 and not disk.path(key).exists()


def test_old_format_entries_are_misses_not_errors(tmp_path):
    disk = DiskPVSCache(tmp_path)
    key = KEY
    p = disk.path(key)
    p.parent.mkdir(parents=True)
    with open(p, "wb") as fh:  # what the previous server wrote
        np.savez(fh, key=np.array(repr(key)), triangle_ids=np.arange(3, dtype=np.int32),
                 granularity=np.array("triangle"), seconds=np.array(0.1),
                 has_objects=np.array(False), object_ids=np.zeros(0, np.int32),
                 has_spheres=np.array(False), sphere_ids=np.zeros(0, np.int32))
    assert disk.get(key) is None
    s = disk.stats()
    assert (s["misses"], s["outdated"], s["rejected"], s["hits"]) == (1, 1, 0, 0)
    assert disk.put(key, _pvs(3)) and disk.get(key, 3) is not None


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="thread priorities are Linux's")
def test_pool_threads_run_nicer_than_the_process():
    """``worker_nice``: a job sees its thread's nice value raised by the pool's ``nice``; a pool
    without it (the first answers' worker) runs at the caller's priority, as does the caller."""
    here = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    def own_nice():
        return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    nicer, plain = PriorityWorkerPool(1, nice=5), PriorityWorkerPool(1)
    try:
        assert nicer.submit(own_nice).result(timeout=10) == min(19, here + 5)
        assert plain.submit(own_nice).result(timeout=10) == here
    finally:
        nicer.shutdown()
        plain.shutdown()
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == here
    assert Settings().worker_nice == 5
    assert Settings.from_env({"PVS_WORKER_NICE": "0"}).worker_nice == 0
    settings = Settings(generated={}, workers=1, worker_nice=3)
    svc = ComputeService(SceneCatalog(settings), settings)
    try:
        assert svc.pool.nice == 3 and svc.first_pool.nice == 0
    finally:
        svc.shutdown()


@contextmanager
def _first_pool(settings):
    """The first answers' pool of a progressive ``ComputeService``, a job ``job(name)`` that
    records its start in ``started`` and holds its worker until ``release`` is set."""
    on = settings.model_copy(update={"progressive": True})
    svc = ComputeService(SceneCatalog(on), on)
    release = threading.Event()
    started: list[str] = []

    def job(name):
        started.append(name)
        release.wait(10)
        return name

    try:
        yield svc.first_pool, job, started, release
    finally:
        release.set()
        svc.shutdown()


def test_first_answers_of_walkers_cells_never_wait_behind_warm_ups(settings):
    """The first answers' pool has two workers, and warm-ups for cells ahead (priority > 0)
    may take one of them at most: a walker's own cell (priority 0) starts at once."""
    with _first_pool(settings) as (pool, job, started, release):
        assert pool.workers == 2 and pool.heavy_workers == 1
        warm = [pool.submit(job, f"ahead{i}", priority=1.0 + i, heavy=True) for i in range(3)]
        wait_for(lambda: started == ["ahead0"])
        own = pool.submit(job, "own", priority=0.0, heavy=False)
        wait_for(lambda: "own" in started)
        assert started == ["ahead0", "own"]  # the other warm-ups wait
        release.set()
        assert own.result(10) == "own" and [f.result(10) for f in warm]


def test_a_warm_up_promoted_to_a_walkers_cell_leaves_the_warm_up_lane(settings):
    """A warm-up for a cell ahead that a walker reached (promoted to priority 0) is then a
    walker's first answer: it starts on the free worker instead of waiting for the warm-up
    lane, and it counts as pending at priority 0 (what refinements are held for)."""
    with _first_pool(settings) as (pool, job, started, release):
        warm = [pool.submit(job, f"ahead{i}", priority=1.0 + i) for i in range(3)]
        wait_for(lambda: started == ["ahead0"])
        assert pool.pending(0.0) == 0
        pool.promote(warm[2], 0.0)
        wait_for(lambda: "ahead2" in started)
        assert started == ["ahead0", "ahead2"] and pool.pending(0.0) == 1
        assert not pool.wait_clear(0.0, 0.05)
        release.set()
        assert pool.wait_clear(0.0, 10) and pool.pending(0.0) == 0
        assert [f.result(10) for f in warm] == ["ahead0", "ahead1", "ahead2"]
