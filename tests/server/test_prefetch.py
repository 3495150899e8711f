"""Prefetch, stalls, delta streams and budgets: real-time walkthrough replays with real protocol
clients (``client.session.Session``) against the real server on loopback."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np
import pytest

from client.session import Session
from client.walkthrough import generate_walkthrough
from server.demand import Demand
from server.prefetch import (
    MAX_SPEED,
    SLOW_WALK,
    TURN_SECONDS,
    arrival_seconds,
    choose_drops,
    motion_direction,
    prefetch_order,
    walker_speed,
)
from tests.conftest import make_tiny_scene, near_ids
from visibility.viewcells import ViewcellGrid

TINY = make_tiny_scene()
SCENE = "village"
SPEED, FPS = 1.4, 10.0


def run(coro, timeout=180):
    return asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture(scope="module")
def village(live_server):
    """The served village scene (same generator, size and seed as the server) and its grid."""
    from tests.conftest import SMALL_GENERATED_TRIANGLES
    from visibility.generators import make_scene

    scene = make_scene(SCENE, triangles=SMALL_GENERATED_TRIANGLES, seed=0)
    return scene, ViewcellGrid.for_scene(scene, 4.0)


async def replay(url, grid, walk, params, prefetch, budget=None, core="test_slow"):
    """Replay ``walk`` at real-time pacing; returns (session, stalls, frames, cell sizes).

    A frame stalls when its cell's stream is not complete one frame interval after its pose was
    sent (the client's definition, as in ``client.replay``). The first cell is waited for before
    the clock starts (a start-up stall is not a prefetch failure)."""
    s = await Session.connect(url, SCENE, core, params, budget=budget, prefetch=prefetch)
    pos = walk.positions
    vel = np.gradient(pos, walk.t, axis=0)
    first = grid.cell_of(pos[0])
    await s.send_pose(0, 0.0, pos[0], walk.forwards[0], vel[0])
    await s.wait_cell(first, 60)
    stalls, held = 0, []
    t0 = time.perf_counter()
    for i in range(1, len(walk)):
        await asyncio.sleep(max(0.0, t0 + walk.t[i] - walk.t[0] - time.perf_counter()))
        await s.send_pose(i, float(walk.t[i]), pos[i], walk.forwards[i], vel[i])
        cell = grid.cell_of(pos[i])
        if not s.is_complete(cell):
            try:
                await s.wait_cell(cell, 1.0 / FPS)
            except TimeoutError:
                stalls += 1
        held.append(len(s.store))
    await s.close()
    return s, stalls, len(walk) - 1, held


def _walk(grid, seed, duration):
    return generate_walkthrough(grid, duration=duration, speed=SPEED, fps=FPS, seed=seed)


def test_prefetch_gives_no_stalls_and_no_prefetch_stalls(live_server, village):
    """The issue's 'done when': 0 stalls at walking speed with prefetch on, stalls without.

    The core takes 0.6 s per cell (``test_slow`` with a delay): longer than a frame, so
    computing on entry cannot keep up, while a 4 m cell crossed at 1.4 m/s leaves ~2.9 s to
    prefetch the cells ahead."""
    scene, grid = village
    walk = _walk(grid, seed=3, duration=12.0)
    cells = {grid.cell_of(p) for p in walk.positions}
    assert len(cells) >= 4  # the walk crosses several cells
    on = {"radius": 6.0, "delay": 0.6}
    s, stalls, frames, _ = run(replay(live_server, grid, walk, on, prefetch=True))
    assert s.welcome.prefetch and s.welcome.features["prefetch"]["on"]
    assert stalls == 0, f"{stalls} stalls in {frames} frames with prefetch on"
    assert not s.errors and not s.local_errors and s.duplicates == 0
    # Prefetch streams arrived (cells ahead, flagged) and held the walk's cells.
    assert any(cs.begin.prefetch for cs in s.cells.values())
    assert cells <= set(s.complete)
    # Each triangle once per session: what arrived equals what is held.
    assert s.triangles_received == len(s.store) == s.held

    off = {"radius": 6.5, "delay": 0.6}  # other parameters: nothing cached from the first run
    walk_off = _walk(grid, seed=3, duration=6.0)
    s2, stalls2, frames2, _ = run(replay(live_server, grid, walk_off, off, prefetch=False))
    assert not s2.welcome.prefetch
    assert not any(cs.begin.prefetch for cs in s2.cells.values())
    assert stalls2 > 0, "prefetch off must stall with a 0.6 s core (else the test cannot fail)"

    # The server saw the stalls too and counts them in /metrics.
    text = httpx.get(live_server + "/metrics", timeout=30).text
    value = float(next(line.split()[-1] for line in text.splitlines()
                       if line.startswith("pvs_stalls_total")))
    assert value >= stalls2


def test_real_core_at_walking_speed_gives_no_stalls(live_server, village):
    """A real core (``sampling``) at the default 4 m cell size, a 10 s walk at 1.4 m/s with
    prefetch on: 0 stalls, and the cells walked through came ahead of the walker."""
    scene, grid = village
    assert grid.cell_size == 4.0
    walk = _walk(grid, seed=7, duration=10.0)
    cells = {grid.cell_of(p) for p in walk.positions}
    assert len(cells) >= 3
    params = {"resolution": 64, "samples": 8, "seed": 7}
    s, stalls, frames, _ = run(replay(live_server, grid, walk, params, prefetch=True,
                                      core="sampling"))
    assert s.welcome.core == "sampling" and s.welcome.prefetch
    assert stalls == 0, f"{stalls} stalls in {frames} frames with prefetch on"
    assert not s.errors and not s.local_errors and s.duplicates == 0
    assert cells <= set(s.complete)
    # Cells came ahead of the walker (a prefetch stream's record is replaced by the empty
    # current-cell stream that confirms it on entry, so count at the server).
    text = httpx.get(live_server + "/metrics", timeout=30).text
    prefetched = float(next(line.split()[-1] for line in text.splitlines()
                            if line.startswith("pvs_cells_prefetched_total")))
    assert prefetched >= len(cells) - 1


def test_budget_drops_keep_the_client_within_budget(live_server, village):
    scene, grid = village
    walk = _walk(grid, seed=5, duration=8.0)
    params = {"radius": 6.0}
    pvs_sizes = []
    with httpx.Client(base_url=live_server, timeout=60) as http:
        for c in sorted({grid.cell_of(p) for p in walk.positions}):
            r = http.get(f"/scenes/{SCENE}/cells/{c}/pvs", params={"core": "test_slow", **params})
            pvs_sizes.append(r.json()["count"])
    # Room for a cell and a half: streaming the walk needs drops.
    budget = int(max(pvs_sizes) * 1.5)
    s, stalls, frames, held = run(replay(live_server, grid, walk, params, prefetch=True,
                                         budget=budget))
    assert not s.local_errors
    assert [e for e in s.errors if e.code != "over_budget"] == []
    assert max(held) <= budget and len(s.store) <= budget
    assert s.dropped > 0 and s.drops
    # Never a duplicate: a triangle comes again only after the client dropped it.
    assert s.duplicates == 0
    assert s.held == len(s.store)
    # The current cell survives drops: its PVS is held at the end.
    last = grid.cell_of(walk.positions[-1])
    if s.is_complete(last):
        expected = near_ids(scene, grid.boxes[last], 6.0)
        assert np.all(s.store.contains(expected))


def test_whole_scene_within_budget_needs_no_pvs(live_server):
    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", {"radius": 2.0},
                                  budget=10_000, prefetch=False)
        cells = httpx.get(live_server + "/scenes/tiny/cells", timeout=30).json()["cells"]
        await s.send_pose(0, 0.0, np.mean(cells[0]["box"], axis=0), (0, 0, -1))
        await s.wait_cell(0, 30)
        await s.close()
        return s, cells

    s, cells = run(main())
    assert s.welcome.features["pvs"]["on"] is False
    assert "fits" in s.welcome.features["pvs"]["why"]
    assert s.welcome.features["dynamic_updates"]["on"] is False
    assert "test_near" in s.welcome.features["cores"]
    assert "test_picky" not in s.welcome.features["cores"]
    # Sent whole: every valid triangle, though the core would answer far fewer.
    np.testing.assert_array_equal(s.store.ids, np.flatnonzero(TINY.valid_faces))
    assert len(near_ids(TINY, np.array(cells[0]["box"]), 2.0)) < len(s.store)


def test_auto_core_says_why(live_server):
    async def main():
        s = await Session.connect(live_server, "tiny", "auto", {"resolution": 16},
                                  prefetch=False)
        await s.close()
        return s

    s = run(main())
    choice = s.welcome.features["core_choice"]
    assert choice["core"] == s.welcome.core and choice["why"]
    assert choice["core"] in s.welcome.features["cores"]


# --------------------------------------------------------------------------- pure functions
def test_prefetch_order_follows_motion():
    walk = np.array([[0.0, 0.0, 12.0, 12.0, 0.0]])  # 3 x 3 cells of 4 m
    from visibility.scene import WalkArea

    grid = ViewcellGrid(WalkArea(rects=walk), 4.0)
    centre = grid.cell_of(np.array([6.0, 1.7, 6.0]))
    pos = np.array([6.0, 1.7, 4.2])  # just entered the middle cell, walking +z
    order = prefetch_order(grid, centre, pos, np.array([0.0, 1.0]))
    ahead = grid.cell_of(np.array([6.0, 1.7, 10.0]))
    behind = grid.cell_of(np.array([6.0, 1.7, 2.0]))
    assert order[0] == ahead and behind not in order
    assert len(order) == 5  # ahead, two ahead diagonals, two sides
    # Without motion: every neighbour, nearest first.
    assert sorted(prefetch_order(grid, centre, pos, None)) == grid.neighbours(centre)
    assert prefetch_order(grid, centre, pos, None)[0] == behind
    d = motion_direction(None, np.array([1.0, 0, 1.0]), np.array([1.0, 0, 0.0]))
    np.testing.assert_allclose(d, [0, 1])
    assert motion_direction(np.zeros(3), np.zeros(3), None) is None


def test_choose_drops_prefers_far_and_unneeded():
    n = 10
    held = np.ones(n, dtype=bool)
    held[9] = False
    centroids = np.stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)], axis=1)
    centroids[8] = np.nan  # degenerate: counts as farthest
    protect = np.zeros(n, bool)
    protect[[0, 7]] = True
    spare = np.zeros(n, bool)
    spare[[5, 6]] = True
    out = choose_drops(held, 3, protect, spare, centroids, np.zeros(3))
    assert out.tolist() == [8, 4, 3]
    out = choose_drops(held, 7, protect, spare, centroids, np.zeros(3))
    assert out.tolist() == [8, 4, 3, 2, 1, 6, 5]  # spare-last ones after all others
    assert len(choose_drops(held, 20, protect, spare, centroids, np.zeros(3))) == 7
    assert len(choose_drops(held, 0, protect, spare, centroids, np.zeros(3))) == 0


def _grid3():
    from visibility.scene import WalkArea

    return ViewcellGrid(WalkArea(rects=np.array([[0.0, 0.0, 12.0, 12.0, 0.0]])), 4.0)


def test_arrival_seconds_along_the_walkers_motion():
    grid = _grid3()
    at = np.array([6.0, 1.7, 5.0])  # middle cell, 1 m past its centre towards +z
    cell = grid.cell_of(at)

    def eta_of(p, direction, speed=1.0, turn=TURN_SECONDS):
        return arrival_seconds(grid.boxes[[grid.cell_of(np.array(p))]], at, direction, speed,
                               turn)[0]

    plus_z = np.array([0.0, 1.0])
    assert arrival_seconds(grid.boxes[[cell]], at, plus_z, 1.4)[0] == 0.0
    ahead = eta_of([6, 0, 10], plus_z)
    np.testing.assert_allclose(ahead, 3.0)  # 3 m to the box at 1 m/s, no turn
    np.testing.assert_allclose(eta_of([6, 0, 10], plus_z, speed=2.0), 1.5)
    side = eta_of([10, 0, 6], plus_z)
    np.testing.assert_allclose(side, 2.0 + TURN_SECONDS / 2)  # 2 m, a quarter turn
    behind = eta_of([6, 0, 2], plus_z)
    np.testing.assert_allclose(behind, 1.0 + TURN_SECONDS)  # 1 m, a half turn
    assert ahead < side < behind
    # Heading the other way swaps ahead and behind.
    assert eta_of([6, 0, 2], -plus_z) < eta_of([6, 0, 10], -plus_z)
    # Standing still: the walk alone, whichever way.
    np.testing.assert_allclose(eta_of([6, 0, 2], None), 1.0)
    np.testing.assert_allclose(eta_of([6, 0, 10], None), 3.0)
    # A box the walker all but touches is reached at once, but for the turn (towards its
    # centre: the way to its nearest point is too short to tell).
    edge = np.array([6.0, 1.7, 4.0005])
    back = arrival_seconds(grid.boxes[[grid.cell_of(np.array([6.0, 0, 2.0]))]], edge, plus_z,
                           1.0)
    np.testing.assert_allclose(back, [0.0005 + TURN_SECONDS])
    with pytest.raises(ValueError, match="speed"):
        arrival_seconds(grid.boxes[:1], at, None, 0.0)


def test_walker_speed_from_velocity_or_steps_with_a_floor_and_a_cap():
    p = np.array([0.0, 1.7, 0.0])
    assert walker_speed(np.array([0.0, 0.0, 1.4]), p, None, None) == pytest.approx(1.4)
    # Vertical motion is not walking.
    assert walker_speed(np.array([0.0, 3.0, 0.0]), p, None, None) == SLOW_WALK
    assert walker_speed(None, np.array([0.3, 1.7, 0.4]), p, 0.25) == pytest.approx(2.0)
    assert walker_speed(None, p, p, 0.1) == SLOW_WALK  # standing still
    assert walker_speed(None, p, None, None) == SLOW_WALK  # the first pose
    assert walker_speed(None, np.array([1.0, 0, 0]), p, 0.0) == SLOW_WALK  # clock stood still
    assert walker_speed(np.array([500.0, 0, 0]), p, None, None) == MAX_SPEED
    assert walker_speed(np.array([np.nan, 0, 0]), p, None, None) == SLOW_WALK


def test_demand_ranks_a_key_by_its_most_urgent_walker():
    d = Demand()
    assert d.update("a", {"k1": (2.0, 0.0), "k2": (0.0, 5.0)}) == {"k1": (2.0, 0.0),
                                                                   "k2": (0.0, 5.0)}
    # b wants k1 sooner: k1's rank changes; k2 entered earlier by b: changes too.
    assert d.update("b", {"k1": (1.0, 0.0), "k2": (0.0, 3.0)}) == {"k1": (1.0, 0.0),
                                                                   "k2": (0.0, 3.0)}
    # a heading elsewhere changes nothing another walker's rank decides...
    assert d.update("a", {"k1": (4.0, 0.0), "k2": (0.0, 5.0)}) == {}
    # ...and b turning away hands k1 back to a's later rank (a demotion).
    assert d.update("b", {"k2": (0.0, 3.0)}) == {"k1": (4.0, 0.0)}
    assert d.rank("k1") == (4.0, 0.0) and d.wanted("k1")
    assert d.remove("b") == {"k2": (0.0, 5.0)}
    assert d.remove("a") == {"k1": None, "k2": None}
    assert not d.wanted("k1") and d.rank("k2") is None
    assert d.stats() == {"walkers": 0, "keys": 0}
    assert d.remove("nobody") == {}
