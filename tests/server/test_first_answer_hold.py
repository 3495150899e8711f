"""Refinements wait for walkers' first answers (``server.compute``): while a first answer for a
walker's cell (priority 0, the first answers' lane) is queued or running, the session cores'
computations that compute here wait at their checkpoints, ``FIRST_ANSWER_HOLD_S`` at most
each. Real pools and threads, a real ``ComputeService``; stand-in cores that record when they
pass their checkpoints."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from server.catalog import SceneCatalog
from server.compute import FIRST_ANSWER_HOLD_S, ComputeService
from server.settings import Settings
from visibility.cancel import checkpoint
from visibility.cores import base as core_base
from visibility.cores.base import Core, CoreParams

#: Seconds between the ticking core's checkpoints.
TICK = 0.005


@dataclass
class TickParams(CoreParams):
    ticks: int = 200


class TickCore(Core):
    """A refinement: ``ticks`` checkpoints ``TICK`` apart; records when each one returned."""

    name = "test_tick"
    Params = TickParams
    passed: list[float] = []

    def _compute(self, scene, cell, params):
        for _ in range(params.ticks):
            time.sleep(TICK)
            checkpoint()
            TickCore.passed.append(time.monotonic())
        return np.zeros(0, dtype=np.int32), {}


@dataclass
class NapParams(CoreParams):
    seconds: float = 0.8


class NapCore(Core):
    """A first answer that takes ``seconds``; records when it ran."""

    name = "test_nap"
    Params = NapParams
    ran: tuple[float, float] = (0.0, 0.0)

    def _compute(self, scene, cell, params):
        t0 = time.monotonic()
        time.sleep(params.seconds)
        NapCore.ran = (t0, time.monotonic())
        return np.zeros(0, dtype=np.int32), {}


@pytest.fixture(scope="module")
def cores() -> Iterator[None]:
    for cls in (TickCore, NapCore):
        core_base.register(cls)
    yield
    for cls in (TickCore, NapCore):
        core_base.unregister(cls.name)


def _service(progressive: bool = True) -> ComputeService:
    settings = Settings(generated={"village": 2000}, workers=2, progressive=progressive)
    return ComputeService(SceneCatalog(settings), settings)


def _run(svc: ComputeService, nap: float, priority: float) -> list[float]:
    """A refinement, then (0.2 s in) a first answer of ``nap`` seconds at ``priority``; the
    refinement's checkpoints passed while the first answer ran."""
    tick, first = core_base.get_core("test_tick"), core_base.get_core("test_nap")
    TickCore.passed = []
    main = svc.submit("village", tick, tick.make_params(ticks=int((nap + 0.5) / TICK)), 0)
    time.sleep(0.2)
    fa = svc.submit("village", first, first.make_params(seconds=nap), 1, priority=priority,
                    lane="first")
    fa.result(timeout=30)
    main.result(timeout=60)
    t0, t1 = NapCore.ran
    return [t for t in TickCore.passed if t0 < t < t1]


def test_a_refinement_waits_while_a_walkers_first_answer_runs(cores):
    svc = _service()
    try:
        inside = _run(svc, 0.8, priority=0.0)
        # Left alone it passes a checkpoint every TICK (160 in 0.8 s); held, one that was
        # under way when the first answer came, then one per hold that ran out.
        assert len(inside) <= 1 + int(np.ceil(0.8 / FIRST_ANSWER_HOLD_S))
        stats = svc.stats()
        assert stats["holds"] >= 1 and stats["held_seconds"] > 0
    finally:
        svc.shutdown()


def test_a_hold_is_bounded_so_refinements_still_advance(cores):
    svc = _service()
    try:
        inside = _run(svc, 1.6, priority=0.0)
        # 1.6 s of first answer against holds of 0.5 s: the refinement passes checkpoints in
        # between, never one closer than a hold after the previous.
        assert len(inside) >= 2
        assert np.diff(inside).min() >= FIRST_ANSWER_HOLD_S - TICK
    finally:
        svc.shutdown()


def test_first_answers_for_cells_ahead_hold_nothing(cores):
    svc = _service()
    try:
        inside = _run(svc, 0.8, priority=1.0)
        assert len(inside) > 10
        assert svc.stats()["holds"] == 0
    finally:
        svc.shutdown()


def test_without_progressive_streams_nothing_holds(cores):
    svc = _service(progressive=False)
    try:
        inside = _run(svc, 0.8, priority=0.0)
        assert len(inside) > 10
        assert svc.stats()["holds"] == 0
    finally:
        svc.shutdown()
