"""Admission control (``server.admission``) and the pool's lanes (``server.pool``): limits,
per-client caps, the bounded queue, what the estimates learn, heavy jobs never taking the last
worker, shortest first."""

from __future__ import annotations

import threading
import time

import pytest

from server.admission import (
    RETRY_AFTER_MAX,
    Admission,
    Busy,
    OverLimit,
    TooManyInFlight,
    retry_after,
)
from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.pool import PriorityWorkerPool
from server.settings import Settings
from tests.conftest import wait_for
from visibility.cores.base import Cost, get_core


def test_limits_name_what_was_hit():
    adm = Admission(Settings(max_compute_bytes=1 << 30, refuse_over_deadline=2.0))
    adm.check_limits(Cost(10.0, 1 << 29), deadline=10.0, core="x")
    with pytest.raises(OverLimit) as exc:
        adm.check_limits(Cost(1.0, 2 << 30), deadline=10.0, core="x")
    assert exc.value.detail["limit"] == "max_compute_bytes"
    assert exc.value.retry_after is None
    with pytest.raises(OverLimit) as exc:
        adm.check_limits(Cost(21.0, 0), deadline=10.0, core="x")
    assert exc.value.detail["limit"] == "compute_deadline"
    assert adm.stats()["refused"]["over_limit"] == 2


def test_per_client_cap_and_release():
    adm = Admission(Settings(max_inflight_per_client=2))
    adm.acquire("a")
    adm.acquire("a")
    adm.acquire("b")
    adm.acquire(None)  # not counted
    with pytest.raises(TooManyInFlight) as exc:
        adm.acquire("a", queued_seconds=30.0)
    assert exc.value.retry_after >= 1
    adm.release("a")
    adm.acquire("a")
    assert adm.stats() == {"refused": {"over_limit": 0, "too_many_requests": 1, "busy": 0},
                           "clients_in_flight": 2}


def test_full_queue_is_busy_with_a_retry_after():
    adm = Admission(Settings(max_queued=3, workers=2))
    adm.check_queue(2, 10.0)
    with pytest.raises(Busy) as exc:
        adm.check_queue(3, 10.0)
    assert exc.value.retry_after == 5


def test_retry_after_is_clamped():
    assert retry_after(0.0, 2) == 1
    assert retry_after(1e9, 2) == RETRY_AFTER_MAX
    assert retry_after(float("nan"), 2) == RETRY_AFTER_MAX


def test_estimates_learn_from_what_a_scene_measures():
    """A scene whose computations take fifty times the model is priced so after a few."""
    settings = Settings(generated={"village": 2000})
    adm = Admission(settings)
    catalog = SceneCatalog(settings)
    loaded = catalog.get("village")
    core = get_core("sampling")
    params = core.make_params()
    cell = loaded.grid.cell(0)
    model = adm.estimate(core, loaded.scene, cell, params, "village")
    for _ in range(10):
        adm.observe("village", "sampling", model.seconds, 50 * model.seconds)
    learned = adm.estimate(core, loaded.scene, cell, params, "village")
    assert learned.seconds == pytest.approx(50 * model.seconds, rel=0.05)
    assert learned.detail["model_seconds"] == pytest.approx(model.seconds)
    # Another scene has learned nothing.
    assert adm.estimate(core, loaded.scene, cell, params, "other").seconds == model.seconds


def test_heavy_jobs_leave_a_worker_to_light_ones():
    pool = PriorityWorkerPool(2, heavy_workers=1)
    release = threading.Event()
    running = []

    def heavy(i):
        running.append(i)
        release.wait(10)
        return i

    try:
        heavies = [pool.submit(heavy, i, heavy=True, seconds=100.0) for i in range(3)]
        # A busy machine may be slow to start the pool's thread on the first heavy job.
        wait_for(lambda: running, 30, "a pool thread running a heavy job")
        assert pool.heavy_running() == 1 and len(running) == 1
        t0 = time.monotonic()
        assert pool.submit(lambda: "light", seconds=0.01).result(timeout=5) == "light"
        assert time.monotonic() - t0 < 1.0
        assert pool.queued() == 2 and pool.queued_seconds() == 200.0
        release.set()
        assert [f.result(timeout=10) for f in heavies] == [0, 1, 2]
        assert pool.heavy_running() == 0
    finally:
        release.set()
        pool.shutdown()


def test_shortest_estimate_first_within_a_priority():
    pool = PriorityWorkerPool(1)
    gate = threading.Event()
    order = []
    try:
        blocker = pool.submit(gate.wait, 10)
        time.sleep(0.1)
        futs = [pool.submit(order.append, s, seconds=s) for s in (5.0, 1.0, 3.0)]
        futs.append(pool.submit(order.append, 9.0, seconds=9.0, priority=-1))
        gate.set()
        for f in [blocker, *futs]:
            f.result(timeout=10)
        assert order == [9.0, 1.0, 3.0, 5.0]
    finally:
        gate.set()
        pool.shutdown()


def test_a_job_nobody_waits_for_is_cancelled():
    """The last caller to ``release`` a computation cancels it; one of two does not."""
    settings = Settings(generated={"village": 2000}, workers=1)
    svc = ComputeService(SceneCatalog(settings), settings)
    gate = threading.Event()
    try:
        svc.catalog.get("village")
        svc.pool.submit(gate.wait, 10)  # holds the only worker
        core = get_core("sampling")
        params = core.make_params()
        a = svc.submit("village", core, params, cell=0)
        b = svc.submit("village", core, params, cell=0)  # joins a
        assert a is b
        assert svc.release(a) is False and not a.cancelled()
        assert svc.release(a) is True and a.cancelled()
        assert svc.stats()["abandoned"] == 1 and svc.stats()["inflight"] == 0
        # A walker that still wants the cell keeps it going.
        svc.still_wanted = lambda key: True
        c = svc.submit("village", core, params, cell=0)
        assert svc.release(c) is False and not c.cancelled()
        gate.set()
        assert len(c.result(timeout=60).pvs) > 0
    finally:
        gate.set()
        svc.shutdown()


def test_http_requests_take_the_heavy_lane_whatever_their_estimate():
    """An estimate a client's cheap requests taught to be low must not let two of its dear
    ones take both workers: HTTP computations run in the heavy lane, a walker's cell with the
    same estimate does not, and one that joins an HTTP computation brings it out, its current
    cell or a prefetch alike (each asked alone would have run light)."""
    settings = Settings(generated={"village": 2000}, workers=2)
    svc = ComputeService(SceneCatalog(settings), settings)
    gate = threading.Event()
    try:
        svc.catalog.get("village")
        running = threading.Semaphore(0)

        def hold():
            running.release()
            gate.wait(60)  # set by the test (finally: at once), not waited out

        for _ in range(2):  # both workers busy: what is submitted next queues in its lane
            svc.pool.submit(hold)
        assert running.acquire(timeout=30) and running.acquire(timeout=30)
        core = get_core("sampling")
        params = core.make_params()
        http = svc.submit("village", core, params, cell=0, client="127.0.0.9")
        http2 = svc.submit("village", core, params, cell=2, client="127.0.0.9")
        walker = svc.submit("village", core, params, cell=1)
        jobs = {j["what"]: j for j in svc.pool.snapshot()}
        http_job, walker_job = jobs["village cell 0 sampling"], jobs["village cell 1 sampling"]
        assert http_job["seconds"] == walker_job["seconds"] < settings.heavy_seconds
        assert http_job["heavy"] and jobs["village cell 2 sampling"]["heavy"]
        assert not walker_job["heavy"]

        def heavy(cell: int) -> bool:
            return {j["what"]: j for j in svc.pool.snapshot()}[f"village cell {cell} sampling"][
                "heavy"]

        # Another HTTP request joining keeps it heavy; a walker's current cell or a walker's
        # prefetch (priority > 0) joining takes it out of the heavy lane.
        assert svc.submit("village", core, params, cell=0, client="127.0.0.8") is http
        assert heavy(0)
        assert svc.submit("village", core, params, cell=0) is http
        assert not heavy(0)
        assert svc.submit("village", core, params, cell=2, priority=1.0) is http2
        assert not heavy(2)
        gate.set()
        assert all(len(f.result(timeout=60).pvs) > 0 for f in (http, http2, walker))
    finally:
        gate.set()
        svc.shutdown()


def test_rate_limit_bucket_refills_and_refusals_cost_more():
    from collections import Counter

    from server.middleware import RateLimit

    rl = RateLimit(app=None, rate=10.0, burst=5, counters=Counter())
    assert all(rl.allow("a", 0.0) for _ in range(5)) and not rl.allow("a", 0.0)
    assert rl.allow("b", 0.0)  # per address
    assert rl.allow("a", 0.1) and not rl.allow("a", 0.1)  # 0.1 s refills one
    rl.charge("a", rl.REFUSED_COST - 1)  # a refused request
    assert not rl.allow("a", 0.3)  # two refilled, four more owed
    assert rl.allow("a", 0.7)
