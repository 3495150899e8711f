"""Work in the order walkers need it (``docs/scheduling.md``), on the REAL server over loopback
with real WebSocket clients (``client.session.SyncSession``).

The server runs ONE worker; an HTTP request for a slow computation occupies it (the *blocker*)
while walkers' jobs queue behind it, so the queue and its priorities are observable in
``/health``. The stand-in core ``test_order`` is ``test_slow`` that also records, in order, the
cells it starts and finishes, and sleeps in small steps between checkpoints so a cancelled
computation stops. The scene is the tiny scene's geometry on a 40 x 8 m walk area (a 10 x 2 grid
of 4 m cells), so walkers can stand far apart.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from client.session import SyncSession
from server.prefetch import arrival_seconds
from tests.conftest import SlowCore, make_tiny_scene, serving, wait_for
from visibility.cancel import ComputationCancelled, checkpoint
from visibility.cores import base as core_base
from visibility.scene import WalkArea
from visibility.viewcells import ViewcellGrid

SCENE = "strip"
#: The walkers' parameters: their cells' computations take this long each.
WALK = {"radius": 5.0, "delay": 0.4}
#: The blocker's (another cache key): long enough for the walkers' jobs to queue behind it.
BLOCK = {"radius": 5.5, "delay": 5.0}
SPEED = 1.4


class OrderCore(SlowCore):
    """``test_slow`` that records (cell centre, radius) of what it starts, finishes and stops
    (cancelled) and honours cancellation between 10 ms naps."""

    name = "test_order"
    started: list[tuple[np.ndarray, float]] = []
    finished: list[tuple[np.ndarray, float]] = []
    stopped: list[tuple[np.ndarray, float]] = []

    def _compute(self, scene, cell, params):
        me = (np.asarray(cell.box, dtype=np.float64).mean(axis=0), float(params.radius))
        OrderCore.started.append(me)
        end = time.monotonic() + params.delay
        try:
            while time.monotonic() < end:
                checkpoint()
                time.sleep(0.01)
            checkpoint()
        except ComputationCancelled:
            OrderCore.stopped.append(me)
            raise
        OrderCore.finished.append(me)
        return super()._compute(scene, cell, dataclasses.replace(params, delay=0.0))


def strip_scene():
    return dataclasses.replace(make_tiny_scene(), name=SCENE,
                               walk=WalkArea(rects=np.array([[0.0, 0.0, 40.0, 8.0, 0.0]])))


@pytest.fixture(scope="module")
def order_core() -> Iterator[None]:
    core_base.register(OrderCore)
    yield
    core_base.unregister(OrderCore.name)


@pytest.fixture(scope="module")
def served(settings, order_core) -> Iterator[tuple[str, object, ViewcellGrid]]:
    with serving(settings, scenes={SCENE: strip_scene()}, workers=1) as (url, app):
        grid = app.state.server.catalog.get(SCENE).grid
        assert grid.cell_size == 4.0 and len(grid) == 20
        yield url, app, grid


@pytest.fixture(scope="module")
def progressive_served(settings, order_core) -> Iterator[tuple[str, object, ViewcellGrid]]:
    """``served`` with progressive streams: a walker's cell first gets a cheap answer, then
    its refinement (the session core's computation)."""
    with serving(settings, scenes={SCENE: strip_scene()}, workers=1,
                 progressive=True) as (url, app):
        grid = app.state.server.catalog.get(SCENE).grid
        # The first answers' core compiles on first use: not while a test's blocker runs.
        first = app.state.server.resolver.first()
        httpx.get(f"{url}/scenes/{SCENE}/cells/0/pvs", timeout=300,
                  params={"core": first.core.name, **first.params.as_dict()}).raise_for_status()
        yield url, app, grid


def _cells(grid, log, radius=WALK["radius"]) -> list[int]:
    return [grid.cell_of(np.array([c[0], 1.0, c[2]])) for c, r in list(log) if r == radius]


def _at(grid, x, z) -> int:
    return grid.cell_of(np.array([x, 1.7, z]))


def _health(url) -> dict:
    return httpx.get(url + "/health", timeout=30).json()


def _queue(url) -> list[dict]:
    return _health(url)["compute"]["pool"]["queue"]


def _label(cell: int) -> str:
    return f"{SCENE} cell {cell} {OrderCore.name}"


def _warm(url, cells, params=WALK) -> None:
    """Compute the walkers' current cells ahead of time (cached: their streams need no job)."""
    with httpx.Client(base_url=url, timeout=60) as http:
        for c in cells:
            r = http.get(f"/scenes/{SCENE}/cells/{c}/pvs", params={"core": OrderCore.name,
                                                                   **params})
            assert r.status_code == 200, r.text


class Blocker:
    """An HTTP request whose computation holds the only worker for ``BLOCK['delay']`` s."""

    def __init__(self, url, grid, cell: int) -> None:
        self.n = len(OrderCore.started)
        self.thread = threading.Thread(target=httpx.get, daemon=True, args=(
            f"{url}/scenes/{SCENE}/cells/{cell}/pvs",), kwargs={
            "params": {"core": OrderCore.name, **BLOCK}, "timeout": 60})
        self.thread.start()
        # Running: whatever comes next queues.
        wait_for(lambda: any(r == BLOCK["radius"] for _, r in OrderCore.started[self.n:]))

    def join(self) -> None:
        self.thread.join(60)
        assert not self.thread.is_alive()


def _walker(url, grid, x, z, vx, vz, seq=0, params=WALK) -> SyncSession:
    s = SyncSession.connect(url, SCENE, OrderCore.name, params, prefetch=True)
    _pose(s, x, z, vx, vz, seq)
    wait_for(lambda: s.is_complete(_at(grid, x, z)))
    return s


def _pose(s, x, z, vx, vz, seq) -> None:
    s.send_pose(seq, 0.1 * seq, (x, 1.7, z), (vx, 0.0, vz), (SPEED * vx, 0.0, SPEED * vz))


def _eta(grid, cell, x, z, vx, vz) -> float:
    return round(float(arrival_seconds(grid.boxes[[cell]], np.array([x, 1.7, z]),
                                       np.array([vx, vz], dtype=float), SPEED)[0]), 3)


def _close(*sessions: SyncSession) -> None:
    for s in sessions:
        if s._thread.is_alive():
            s.close()


def _reset() -> None:
    OrderCore.started.clear()
    OrderCore.finished.clear()
    OrderCore.stopped.clear()


def _clear_cache(app) -> None:
    """Forget every computed PVS (memory tier: the test settings have no other) so each test
    computes its cells anew."""
    app.state.server.compute.cache.memory.clear()


# --------------------------------------------------------------------------- tests
def test_the_walker_arriving_sooner_is_computed_first(served):
    """Two walkers' prefetches compete for the one worker: the one who reaches its next cell
    sooner goes first, though its job was queued last."""
    url, app, grid = served
    _clear_cache(app)
    _reset()
    # Both walk from their cells' far sides: 3.5 m to go (B), 1.5 m to go (A).
    b_at, a_at = (39.5, 2.0), (2.5, 2.0)
    _warm(url, [_at(grid, *b_at), _at(grid, *a_at)])
    b_next, a_next = _at(grid, 34.0, 2.0), _at(grid, 5.0, 2.0)
    blocker = Blocker(url, grid, _at(grid, 20.0, 6.0))
    b = _walker(url, grid, *b_at, -1.0, 0.0)
    wait_for(lambda: _label(b_next) in [j["what"] for j in _queue(url)])
    a = _walker(url, grid, *a_at, 1.0, 0.0)
    wait_for(lambda: _label(a_next) in [j["what"] for j in _queue(url)])
    try:
        queue = _queue(url)
        assert [j["what"] for j in queue[:2]] == [_label(a_next), _label(b_next)]
        # Each job ranks by its walker's expected arrival (seconds), not by submission.
        assert queue[0]["priority"] == _eta(grid, a_next, *a_at, 1.0, 0.0)
        assert queue[1]["priority"] == _eta(grid, b_next, *b_at, -1.0, 0.0)
        blocker.join()
        wait_for(lambda: {a_next, b_next} <= set(_cells(grid, OrderCore.finished)))
        done = _cells(grid, OrderCore.finished)
        assert done.index(a_next) < done.index(b_next)
        wait_for(lambda: a.is_complete(a_next) and b.is_complete(b_next))
        assert not a.errors and not b.errors
    finally:
        _close(a, b)


def test_a_walker_turning_demotes_the_cells_it_no_longer_heads_for(served):
    url, app, grid = served
    _clear_cache(app)
    _reset()
    at = (6.0, 2.0)  # mid-row cell, 2 m from its +x and its +z neighbour
    _warm(url, [_at(grid, *at)])
    east, north = _at(grid, 10.0, 2.0), _at(grid, 6.0, 6.0)
    stats0 = _health(url)["compute"]["pool"]["reranks"]
    blocker = Blocker(url, grid, _at(grid, 30.0, 6.0))
    w = _walker(url, grid, *at, 1.0, 0.0)  # heading east
    try:
        wait_for(lambda: _label(east) in [j["what"] for j in _queue(url)])
        assert _queue(url)[0]["priority"] == _eta(grid, east, *at, 1.0, 0.0)
        _pose(w, *at, 0.0, 1.0, seq=1)  # turns north
        wait_for(lambda: {_label(east), _label(north)} <= {j["what"] for j in _queue(url)})
        queue = {j["what"]: j["priority"] for j in _queue(url)}
        # East is still ahead-ish (sideways now) but later: a quarter turn away.
        assert queue[_label(east)] == _eta(grid, east, *at, 0.0, 1.0)
        assert queue[_label(north)] == _eta(grid, north, *at, 0.0, 1.0)
        assert queue[_label(north)] < queue[_label(east)]
        assert _eta(grid, east, *at, 0.0, 1.0) > _eta(grid, east, *at, 1.0, 0.0)
        stats = _health(url)["compute"]["pool"]["reranks"]
        assert stats["later"] > stats0["later"]
        blocker.join()
        wait_for(lambda: {east, north} <= set(_cells(grid, OrderCore.finished)))
        done = _cells(grid, OrderCore.finished)
        assert done.index(north) < done.index(east)
        text = httpx.get(url + "/metrics", timeout=30).text
        later = next(line for line in text.splitlines()
                     if line.startswith('pvs_reranks_total{direction="later"}'))
        assert float(later.split()[-1]) >= stats["later"]
    finally:
        _close(w)


def test_a_walker_leaving_cancels_what_only_it_wanted(served):
    """Three walkers: A and C head for the same cell, B for one of its own. A leaves: the
    shared cell is still computed (C wants it). B leaves: its cell is cancelled unrun."""
    url, app, grid = served
    _clear_cache(app)
    _reset()
    a_at, c_at, b_at = (6.0, 2.0), (14.0, 2.0), (30.0, 2.0)
    _warm(url, [_at(grid, *p) for p in (a_at, c_at, b_at)])
    shared, own = _at(grid, 10.0, 2.0), _at(grid, 34.0, 2.0)
    before = _health(url)["compute"]["cancellations"]["unwanted"].get("queued", 0)
    blocker = Blocker(url, grid, _at(grid, 22.0, 6.0))
    a = _walker(url, grid, *a_at, 1.0, 0.0)
    c = _walker(url, grid, *c_at, -1.0, 0.0)
    b = _walker(url, grid, *b_at, 1.0, 0.0)
    try:
        wait_for(lambda: {_label(shared), _label(own)} <= {j["what"] for j in _queue(url)})
        a.close()
        b.close()
        wait_for(lambda: _label(own) not in {j["what"] for j in _queue(url)})
        after = _health(url)["compute"]["cancellations"]["unwanted"].get("queued", 0)
        assert after == before + 1
        assert _label(shared) in {j["what"] for j in _queue(url)}
        blocker.join()
        wait_for(lambda: c.is_complete(shared))
        assert shared in _cells(grid, OrderCore.started)
        assert own not in _cells(grid, OrderCore.started)
        text = httpx.get(url + "/metrics", timeout=30).text
        line = next(ln for ln in text.splitlines() if ln.startswith(
            'pvs_cancellations_total{reason="unwanted",state="queued"}'))
        assert float(line.split()[-1]) == after
    finally:
        _close(a, b, c)


def test_a_running_computation_nobody_wants_stops(served):
    url, app, grid = served
    _clear_cache(app)
    _reset()
    at = (26.0, 6.0)
    slow = {**WALK, "delay": 5.0}  # time enough to leave while it runs
    _warm(url, [_at(grid, *at)], slow)
    ahead = _at(grid, 30.0, 6.0)
    before = _health(url)["compute"]["cancellations"]["unwanted"].get("running", 0)
    w = _walker(url, grid, *at, 1.0, 0.0, params=slow)
    wait_for(lambda: ahead in _cells(grid, OrderCore.started))
    t0 = time.monotonic()
    w.close()
    wait_for(lambda: _health(url)["compute"]["cancellations"]["unwanted"].get("running", 0)
             == before + 1)
    wait_for(lambda: ahead in _cells(grid, OrderCore.stopped))
    # Stopped at a checkpoint, before its time was up.
    assert time.monotonic() - t0 < slow["delay"]
    assert ahead not in _cells(grid, OrderCore.finished)


def test_a_current_cell_jumps_the_queue(served):
    """A walker's prefetch is queued; another walker enters a cell nobody computed: its cell
    (priority 0) runs first. Two walkers' current cells run newest entered first: that walker
    stays longest in its cell, so its answer serves the most frames."""
    url, app, grid = served
    _clear_cache(app)
    _reset()
    a_at = (2.5, 2.0)
    _warm(url, [_at(grid, *a_at)])
    a_next = _at(grid, 5.0, 2.0)
    first_in, second_in = (30.0, 6.0), (18.0, 6.0)
    blocker = Blocker(url, grid, _at(grid, 38.0, 2.0))
    a = _walker(url, grid, *a_at, 1.0, 0.0)
    wait_for(lambda: _label(a_next) in [j["what"] for j in _queue(url)])
    b = SyncSession.connect(url, SCENE, OrderCore.name, WALK, prefetch=False)
    c = SyncSession.connect(url, SCENE, OrderCore.name, WALK, prefetch=False)
    try:
        _pose(b, *first_in, 0.0, 0.0, 0)
        wait_for(lambda: len(_queue(url)) >= 2)
        _pose(c, *second_in, 0.0, 0.0, 0)
        wait_for(lambda: len(_queue(url)) >= 3)
        queue = _queue(url)
        b_cell, c_cell = _at(grid, *first_in), _at(grid, *second_in)
        assert [j["what"] for j in queue] == [_label(c_cell), _label(b_cell), _label(a_next)]
        assert queue[0]["priority"] == queue[1]["priority"] == 0.0 < queue[2]["priority"]
        assert queue[0]["since"] < queue[1]["since"]
        blocker.join()
        wait_for(lambda: b.is_complete(b_cell) and c.is_complete(c_cell)
                 and a.is_complete(a_next))
        done = _cells(grid, OrderCore.finished)
        assert done.index(c_cell) < done.index(b_cell) < done.index(a_next)
        assert not b.errors and not c.errors
    finally:
        _close(a, b, c)


def test_the_walkers_cell_is_refined_before_the_cells_ahead(progressive_served):
    """The walker's cell gets its first answer at once; its refinement (priority 0) and the
    prefetch of the cell ahead queue behind the blocker; the refinement runs first."""
    url, app, grid = progressive_served
    _clear_cache(app)
    _reset()
    at = (10.5, 2.0)
    cell, ahead = _at(grid, *at), _at(grid, 13.0, 2.0)
    blocker = Blocker(url, grid, _at(grid, 30.0, 6.0))
    w = SyncSession.connect(url, SCENE, OrderCore.name, WALK, prefetch=True)
    try:
        _pose(w, *at, 1.0, 0.0, 0)
        wait_for(lambda: w.is_complete(cell))
        assert w.cells[cell].answer in ("first", "known")
        wait_for(lambda: {_label(cell), _label(ahead)} <= {j["what"] for j in _queue(url)})
        queue = _queue(url)
        assert [j["what"] for j in queue[:2]] == [_label(cell), _label(ahead)]
        assert queue[0]["priority"] == 0.0
        assert queue[1]["priority"] == _eta(grid, ahead, *at, 1.0, 0.0)
        blocker.join()
        wait_for(lambda: w.cells[cell].answer == "refined")
        wait_for(lambda: ahead in _cells(grid, OrderCore.finished))
        done = _cells(grid, OrderCore.finished)
        assert done.index(cell) < done.index(ahead)
        assert not w.errors
    finally:
        _close(w)
