"""Every computation runs under a deadline (``compute_deadline``, a request may ask for less) and
stops at its core's next checkpoint when it passes or when the service shuts down; the workers
are then free for the next request."""

from __future__ import annotations

import time

import pytest

from server.catalog import SceneCatalog
from server.compute import ComputeService
from server.settings import Settings
from tests.conftest import wait_for
from visibility.cancel import ComputationCancelled
from visibility.cores.base import get_core

#: from_segment at 1024 px on a 20k village cell takes tens of seconds on 2 cores.
SLOW = {"resolution": 1024, "eye_levels": 3}


@pytest.fixture(scope="module")
def service():
    # Admission would refuse what cannot finish in time: these tests need it to start.
    settings = Settings(generated={"village": 20_000}, compute_deadline=60.0, workers=2,
                        refuse_over_deadline=1e6)
    svc = ComputeService(SceneCatalog(settings), settings)
    yield svc
    svc.shutdown()


def _cell(svc: ComputeService) -> int:
    return len(svc.catalog.get("village").grid) // 2


@pytest.fixture(scope="module")
def warm(service):
    """A cheap answer first: loading the core's kernels takes seconds on a busy machine and
    stops at no checkpoint, and the bounds below time the stop, not the load."""
    core = get_core("from_segment")
    cheap = service.submit("village", core, core.make_params(resolution=32, eye_levels=1),
                           _cell(service))
    assert len(cheap.result(timeout=120).pvs) > 0


def test_a_request_deadline_stops_a_real_core_and_frees_the_worker(service, warm):
    core = get_core("from_segment")
    cell = _cell(service)
    t0 = time.monotonic()
    fut = service.submit("village", core, core.make_params(**SLOW), cell, deadline=0.5)
    with pytest.raises(ComputationCancelled, match="deadline of 0.5 s"):
        fut.result(timeout=30)
    assert time.monotonic() - t0 < 5.0
    assert service.stats()["cancelled"] >= 1
    # The worker is free: a cheap request is answered at once.
    cheap = service.submit("village", core, core.make_params(resolution=32, eye_levels=1), cell)
    assert len(cheap.result(timeout=60).pvs) > 0


def test_the_setting_caps_what_a_request_asks_for():
    settings = Settings(generated={"village": 20_000}, compute_deadline=0.5, workers=1,
                        refuse_over_deadline=1e6)
    svc = ComputeService(SceneCatalog(settings), settings)
    try:
        core = get_core("from_segment")
        fut = svc.submit("village", core, core.make_params(**SLOW), _cell(svc), deadline=3600)
        with pytest.raises(ComputationCancelled, match="deadline of 0.5 s"):
            fut.result(timeout=30)
    finally:
        svc.shutdown()


def test_shutdown_cancels_running_computations(warm):
    settings = Settings(generated={"village": 20_000}, workers=1)
    svc = ComputeService(SceneCatalog(settings), settings)
    core = get_core("from_segment")
    fut = svc.submit("village", core, core.make_params(**SLOW), _cell(svc))
    wait_for(fut.running, 60, "the computation running")
    time.sleep(0.3)  # into the core's loop: either way shutdown must stop it
    t0 = time.monotonic()
    svc.shutdown()
    with pytest.raises(ComputationCancelled, match="shutting down"):
        fut.result(timeout=30)
    assert time.monotonic() - t0 < 5.0
