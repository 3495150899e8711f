"""Refinements wait for walkers' first answers (``server.compute``): while a first answer for a
walker's cell (priority 0, the first answers' lane) is queued or running, the session cores'
computations that compute here wait at their checkpoints, ``FIRST_ANSWER_HOLD_S`` at most
each. Real pools and threads, a real ``ComputeService``; a stand-in core that records when it
passes its checkpoints and when a first answer runs."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import pytest

import server.compute as compute_module
from server.catalog import SceneCatalog
from server.compute import FIRST_ANSWER_HOLD_S, ComputeService
from server.settings import Settings
from tests.conftest import wait_for
from visibility.cancel import ComputationCancelled, checkpoint
from visibility.cores import base as core_base
from visibility.cores.base import Core, CoreParams

#: Seconds between the ticking core's checkpoints.
TICK = 0.005


@dataclass
class StandInParams(CoreParams):
    #: A refinement: this many checkpoints ``TICK`` apart. A first answer (0): ``seconds``.
    ticks: int = 0
    seconds: float = 0.8


class StandInCore(Core):
    """Records when a refinement passed each checkpoint (``passed``) or stopped there
    (``stopped``), and when a first answer ran (``ran``)."""

    name = "test_stand_in"
    Params = StandInParams
    passed: list[float] = []
    ran: tuple[float, float] = (0.0, 0.0)
    began = 0.0
    stopped = 0.0

    def _compute(self, scene, cell, params):
        t0 = time.monotonic()
        if not params.ticks:
            StandInCore.began = t0
        for _ in range(params.ticks):
            time.sleep(TICK)
            try:
                checkpoint()
            except ComputationCancelled:
                StandInCore.stopped = time.monotonic()
                raise
            StandInCore.passed.append(time.monotonic())
        if not params.ticks:
            time.sleep(params.seconds)
            StandInCore.ran = (t0, time.monotonic())
        return np.zeros(0, dtype=np.int32), {}


@pytest.fixture(scope="module")
def cores() -> Iterator[None]:
    core_base.register(StandInCore)
    yield
    core_base.unregister(StandInCore.name)


@contextmanager
def _service(progressive: bool = True, workers: int = 2) -> Iterator[ComputeService]:
    settings = Settings(generated={"village": 2000}, workers=workers, progressive=progressive)
    svc = ComputeService(SceneCatalog(settings), settings)
    try:
        yield svc
    finally:
        svc.shutdown()


def _run(svc: ComputeService, nap: float, priority: float) -> list[float]:
    """A refinement, then (once it passed a checkpoint) a first answer of ``nap`` seconds at
    ``priority``; the refinement's checkpoints passed while the first answer ran."""
    core = core_base.get_core(StandInCore.name)
    StandInCore.passed = []
    main = svc.submit("village", core, core.make_params(ticks=int((nap + 0.5) / TICK)), 0)
    wait_for(lambda: len(StandInCore.passed) > 0, 30, "the refinement at a checkpoint")
    fa = svc.submit("village", core, core.make_params(seconds=nap), 1, priority=priority,
                    lane="first")
    fa.result(timeout=30)
    main.result(timeout=60)
    t0, t1 = StandInCore.ran
    return [t for t in StandInCore.passed if t0 < t < t1]


def test_a_refinement_waits_while_a_walkers_first_answer_runs(cores):
    with _service() as svc:
        inside = _run(svc, 0.8, priority=0.0)
        # Left alone it passes a checkpoint every TICK (160 in 0.8 s); held, one that was
        # under way when the first answer came, then one per hold that ran out.
        assert len(inside) <= 1 + int(np.ceil(0.8 / FIRST_ANSWER_HOLD_S))
        stats = svc.stats()
        assert stats["holds"] >= 1 and stats["held_seconds"] > 0


def test_a_hold_is_bounded_so_refinements_still_advance(cores):
    with _service() as svc:
        inside = _run(svc, 1.6, priority=0.0)
        # 1.6 s of first answer against holds of 0.5 s: the refinement passes checkpoints in
        # between, never one closer than a hold after the previous.
        assert len(inside) >= 2
        assert np.diff(inside).min() >= FIRST_ANSWER_HOLD_S - TICK


@pytest.mark.parametrize("progressive,priority", [(True, 1.0), (False, 0.0)],
                         ids=["a first answer for a cell ahead", "no progressive streams"])
def test_nothing_holds_but_a_walkers_first_answer(cores, progressive, priority):
    with _service(progressive) as svc:
        assert len(_run(svc, 0.8, priority)) > 10
        assert svc.stats()["holds"] == 0


def test_a_held_refinement_stops_soon_after_it_is_cancelled(cores, monkeypatch):
    # Holds as long as the first answer runs: a hold that missed the cancel would keep the
    # refinement, and its worker, until the first answer is done.
    monkeypatch.setattr(compute_module, "FIRST_ANSWER_HOLD_S", 10.0)
    core = core_base.get_core(StandInCore.name)
    with _service() as svc:
        StandInCore.stopped = StandInCore.began = 0.0
        StandInCore.passed = []
        main = svc.submit("village", core, core.make_params(ticks=2000), 0)
        wait_for(lambda: len(StandInCore.passed) > 0, 30, "the refinement at a checkpoint")
        first = svc.submit("village", core, core.make_params(seconds=2.0), 1, lane="first")
        wait_for(lambda: StandInCore.began > 0, 30, "the first answer running")
        # Held: no checkpoint passed for twenty ticks (one would pass every tick).
        wait_for(lambda: time.monotonic() - StandInCore.passed[-1] > 20 * TICK, 30,
                 "the refinement held")
        t0 = time.monotonic()
        assert svc.release(main)
        first.result(timeout=10)
        assert 0 < StandInCore.stopped - t0 < 0.5


def test_a_warm_up_a_walker_reached_holds_refinements(cores):
    """A first answer queued as a warm-up for a cell ahead (priority 1: no hold) and promoted
    when the walker gets there holds refinements like one asked for at priority 0."""
    core = core_base.get_core(StandInCore.name)
    with _service() as svc:
        StandInCore.passed = []
        main = svc.submit("village", core, core.make_params(ticks=int(3.0 / TICK)), 0)
        wait_for(lambda: len(StandInCore.passed) > 0, 30, "the refinement at a checkpoint")
        params = core.make_params(seconds=0.8)
        StandInCore.began = 0.0
        warm = svc.submit("village", core, params, 1, priority=1.0, lane="first")
        # The refinement passes checkpoints while the warm-up runs, and none holds.
        wait_for(lambda: StandInCore.began > 0
                 and StandInCore.passed[-1] > StandInCore.began + 10 * TICK, 30,
                 "checkpoints passed while the warm-up runs")
        assert svc.stats()["holds"] == 0
        assert svc.submit("village", core, params, 1, priority=0.0, lane="first") is warm
        promoted = time.monotonic()
        warm.result(timeout=30)
        main.result(timeout=60)
        t0, t1 = StandInCore.ran
        inside = [t for t in StandInCore.passed if promoted < t < t1]
        # One under way at the promotion, then one per hold that ran out while it still ran.
        assert len(inside) <= 1 + int(np.ceil((t1 - promoted) / FIRST_ANSWER_HOLD_S))
        assert svc.stats()["holds"] >= 1
