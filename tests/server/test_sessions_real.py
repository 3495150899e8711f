"""Session behaviour with a REAL core (``sampling`` at a small resolution) on the small generated
village, over the real uvicorn server on loopback with real protocol clients
(``client.session.Session``): shared computations, prefetch dropped when a walker turns, the
current cell never starved by prefetch, the current cell kept under a tiny cache budget, and the
per-session bound on remembered PVS.

The servers here run ONE worker, so a long computation makes later jobs queue (that is what the
prefetch test needs), and frames of one triangle, so a prefetch stream spans many chunks."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import pytest

import server.ws.inventory as inventory_module
from client.session import Session
from protocol.frames import frame_bytes
from tests.conftest import LiveServer, wait_for_async
from visibility.viewcells import ViewcellGrid

SCENE = "village"
CORE = "sampling"


def params(seed: int, resolution: int = 32, samples: int = 4) -> dict:
    """Small sampling parameters; ``seed`` keeps each test's cache keys its own."""
    return {"resolution": resolution, "samples": samples, "seed": seed}


def run(coro, timeout: float = 240):
    return asyncio.run(asyncio.wait_for(coro, timeout))


def _serve(settings, **update):
    from server.app import create_app

    s = settings.model_copy(update={"workers": 1, "max_frame_bytes": frame_bytes(1),
                                    **update})
    app = create_app(s)
    srv = LiveServer(app, s)
    srv.start()
    return app, srv


@pytest.fixture(scope="module")
def grid():
    from tests.conftest import SMALL_GENERATED_TRIANGLES
    from visibility.generators import make_scene

    scene = make_scene(SCENE, triangles=SMALL_GENERATED_TRIANGLES, seed=0)
    return ViewcellGrid.for_scene(scene, 4.0)


@pytest.fixture(scope="module")
def served(settings):
    """(app, base URL) of a one-worker server with the test settings' cache."""
    app, srv = _serve(settings)
    yield app, srv.url
    srv.stop()


@pytest.fixture(scope="module")
def served_tiny_cache(settings):
    """(app, base URL) of a one-worker server whose PVS cache holds (almost) nothing."""
    app, srv = _serve(settings, cache_bytes=64)
    yield app, srv.url
    srv.stop()


def metrics(url: str) -> dict[str, float]:
    """The server's /metrics samples by name (Prometheus text format)."""
    text = httpx.get(url + "/metrics", timeout=30).text
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def centre(grid: ViewcellGrid, cell: int) -> np.ndarray:
    return grid.boxes[cell].mean(axis=0)


def line_of_cells(grid: ViewcellGrid) -> tuple[int, int, int, int]:
    """Cells (west, a, east, east2) in a row along +x, each a neighbour of the next."""
    step = np.array([grid.cell_size, 0.0, 0.0])
    for a in range(len(grid)):
        c = centre(grid, a)
        cells = [grid.cell_of(c + k * step) for k in (-1, 1, 2)]
        if all(x is not None for x in cells) and cells[0] in grid.neighbours(a) \
                and cells[1] in grid.neighbours(a):
            return cells[0], a, cells[1], cells[2]
    raise AssertionError("the served village has no row of four cells along x")


async def enter(s: Session, seq: int, grid: ViewcellGrid, cell: int,
                velocity=(0.0, 0.0, 0.0)) -> None:
    await s.send_pose(seq, 0.1 * seq, centre(grid, cell), (1.0, 0.0, 0.0), velocity)


# --------------------------------------------------------------------------- tests
def test_two_walkers_in_one_cell_cost_one_computation(served, grid):
    app, url = served
    p = params(seed=11)
    cell = line_of_cells(grid)[1]

    async def main():
        a = await Session.connect(url, SCENE, CORE, p, prefetch=False)
        b = await Session.connect(url, SCENE, CORE, p, prefetch=False)
        before = metrics(url)["pvs_computations_total"]
        await asyncio.gather(enter(a, 1, grid, cell), enter(b, 1, grid, cell))
        await asyncio.gather(a.wait_cell(cell, 120), b.wait_cell(cell, 120))
        after = metrics(url)["pvs_computations_total"]
        await a.close()
        await b.close()
        return a, b, before, after

    a, b, before, after = run(main())
    assert after - before == 1
    np.testing.assert_array_equal(a.store.ids, b.store.ids)
    assert len(a.store) > 0 and not a.errors and not b.errors
    # The HTTP route answers the same PVS from the cache: still one computation.
    r = httpx.get(f"{url}/scenes/{SCENE}/cells/{cell}/pvs", params={"core": CORE, **p},
                  timeout=60).json()
    assert r["cached"] is True and metrics(url)["pvs_computations_total"] == after
    np.testing.assert_array_equal(np.sort(r["triangle_ids"]), a.store.ids)


def test_prefetch_no_longer_ahead_is_dropped_when_the_walker_turns(served, grid):
    """The one worker is busy with another walker's slow cell, so the cell ahead of a walker
    queues; the walker turns round before it runs: the job is skipped, never computed or sent,
    and the cell ahead in the new direction is prefetched instead."""
    app, url = served
    west, a, east, _ = line_of_cells(grid)
    p = params(seed=12)
    far = max(range(len(grid)), key=lambda c: np.linalg.norm(centre(grid, c) - centre(grid, a)))
    compute = app.state.server.compute
    label = f"{SCENE} cell {east} {CORE}"  # the pool's label of east's job (server.compute)
    httpx.get(f"{url}/scenes/{SCENE}/cells/{a}/pvs", params={"core": CORE, **p},
              timeout=120).raise_for_status()  # the walker's own cell comes from the cache

    async def main():
        slow = await Session.connect(url, SCENE, CORE, params(seed=13, resolution=512,
                                                              samples=128), prefetch=False)
        w = await Session.connect(url, SCENE, CORE, p, prefetch=True)
        before = metrics(url)
        await enter(slow, 1, grid, far)
        # One worker: a computation in flight with none queued is the slow cell, running.
        await wait_for_async(lambda: (st := compute.stats())["inflight"] >= 1
                             and st["pool"]["queued"] == 0,
                             what="the slow cell running on the worker")
        await enter(w, 1, grid, a, velocity=(1.4, 0.0, 0.0))
        await w.wait_cell(a, 60)
        # The walker must turn while the cell ahead waits behind the slow one.
        await wait_for_async(lambda: label in {j["what"] for j in compute.stats()["pool"]["queue"]},
                             what=f"the prefetch of cell {east} (ahead) queued")
        await enter(w, 2, grid, a, velocity=(-1.4, 0.0, 0.0))  # turned round
        await w.wait_cell(west, 180)
        await slow.wait_cell(far, 180)
        after = metrics(url)
        await w.close()
        await slow.close()
        return w, before, after

    w, before, after = run(main())
    assert after["pvs_prefetch_skipped_total"] - before["pvs_prefetch_skipped_total"] >= 1
    assert east not in w.cells  # never streamed
    assert w.cells[west].begin.prefetch  # the cell ahead now came as prefetch
    assert not w.errors and not w.local_errors and w.duplicates == 0


def test_current_cell_is_not_starved_by_prefetch(served, grid):
    """While a prefetch stream of many one-triangle frames is under way, the walker enters a
    cell nobody prefetched: the prefetch stream is cut (``cell_end.partial``), the current cell
    arrives whole, and every stream on the wire stays bracketed."""
    app, url = served
    west, a, east, _ = line_of_cells(grid)
    p = params(seed=14, resolution=64, samples=8)

    async def main():
        w = await Session.connect(url, SCENE, CORE, p, prefetch=True)
        before = metrics(url)
        await enter(w, 1, grid, a, velocity=(1.4, 0.0, 0.0))
        await w.wait_cell(a, 120)
        # Wait for a prefetch stream to begin, then turn into the cell behind.
        cs = None
        for _ in range(60_000):
            cs = next((c for c in w.cells.values() if c.begin.prefetch and c.end is None), None)
            if cs is not None or w.closed:
                break
            await asyncio.sleep(0.001)
        assert cs is not None, "no prefetch stream began"
        await enter(w, 2, grid, west, velocity=(-1.4, 0.0, 0.0))
        got = await w.wait_cell(west, 120)
        after = metrics(url)
        await w.close()
        return w, cs, got, before, after

    w, cs, got, before, after = run(main())
    assert cs.cell != west and cs.begin.chunks > 20
    assert cs.end is not None and cs.end.partial and cs.chunks < cs.begin.chunks
    assert cs.cell not in w.complete
    assert after["pvs_prefetch_yields_total"] > before["pvs_prefetch_yields_total"]
    assert not got.begin.prefetch and got.chunks == got.begin.chunks
    assert not w.errors and not w.local_errors and w.duplicates == 0


def test_current_cell_survives_a_tiny_cache(served_tiny_cache, grid):
    app, url = served_tiny_cache
    west, a, east, east2 = line_of_cells(grid)
    p = params(seed=15)

    def http_pvs(cell: int) -> dict:
        r = httpx.get(f"{url}/scenes/{SCENE}/cells/{cell}/pvs", params={"core": CORE, **p},
                      timeout=120)
        r.raise_for_status()
        return r.json()

    async def main():
        w = await Session.connect(url, SCENE, CORE, p, prefetch=False)
        await enter(w, 1, grid, a)
        await w.wait_cell(a, 120)
        # Other cells churn the cache: the 64-byte budget keeps none of them.
        churn = [await asyncio.to_thread(http_pvs, c) for c in (west, east, east2, west)]
        n0 = metrics(url)["pvs_computations_total"]
        again = await asyncio.to_thread(http_pvs, a)
        v = await Session.connect(url, SCENE, CORE, p, prefetch=False)
        await enter(v, 1, grid, a)
        await v.wait_cell(a, 120)
        n1 = metrics(url)["pvs_computations_total"]
        await v.close()
        await w.close()
        return w, v, churn, again, n0, n1

    w, v, churn, again, n0, n1 = run(main())
    assert churn[-1]["cached"] is False  # the cache really holds nothing unpinned
    assert again["cached"] is True and n1 == n0  # the walker's cell stayed, pinned
    np.testing.assert_array_equal(v.store.ids, w.store.ids)
    assert not v.errors and not w.errors


def test_remembered_pvs_per_session_is_bounded(served, grid, monkeypatch):
    monkeypatch.setattr(inventory_module, "MAX_KNOWN_PVS", 3)
    app, url = served
    p = params(seed=16)
    first = line_of_cells(grid)[1]
    cells = [first]
    while len(cells) < 7:  # a walk of neighbouring cells, none twice
        nxt = [n for n in grid.neighbours(cells[-1]) if n not in cells]
        if not nxt:
            break
        cells.append(nxt[0])
    assert len(cells) > 3

    async def main():
        s = await Session.connect(url, SCENE, CORE, p, prefetch=False)
        server_side = app.state.server.sessions[s.welcome.session]
        sizes = []
        for i, c in enumerate(cells, start=1):
            await enter(s, i, grid, c)
            await s.wait_cell(c, 120)
            sizes.append(len(server_side.inventory.pvs_of))
        # Back to the first cell, long forgotten: its stream comes again, whole.
        s.complete.discard(first)
        await enter(s, len(cells) + 1, grid, first)
        back = await s.wait_cell(first, 120)
        sizes.append(len(server_side.inventory.pvs_of))
        await s.close()
        return s, sizes, back

    s, sizes, back = run(main())
    assert max(sizes) == 3 and sizes[-1] <= 3
    assert back.end is not None and not back.end.partial
    assert not s.errors and not s.local_errors and s.duplicates == 0
