"""Progressive PVS on a real server and client: a walker's cell comes first as a cheap answer,
then only what the session core adds (``cell_begin.answer``); prefetched cells skip the first
pass; the setting and the hello turn it off."""

from __future__ import annotations

import time

import numpy as np
import pytest

from client.session import SyncSession
from server.ws import streams
from tests.conftest import make_tiny_scene, near_ids, serving, wait_for
from visibility.viewcells import ViewcellGrid

pytestmark = pytest.mark.usefixtures("registered_test_cores")

#: The session core's answer takes this long: the first answer (sampling, tens of ms) comes
#: well before it.
DELAY = 1.5


@pytest.fixture(scope="module")
def progressive_server(settings):
    scene = make_tiny_scene()
    with serving(settings, scenes={"tiny": scene}, progressive=True) as (url, app):
        yield url, app, scene


def _pose(session: SyncSession, scene, cell: int, seq: int) -> None:
    grid = ViewcellGrid.for_scene(scene, session.welcome.grid.cell_size)
    c = grid.boxes[cell].mean(axis=0)
    session.send_pose(seq, float(seq), c, (1.0, 0.0, 0.0))


def _ids(stream) -> set[int]:
    return set(np.concatenate(stream.ids).tolist()) if stream.ids else set()


def test_first_answer_then_what_the_core_adds(progressive_server):
    url, app, scene = progressive_server
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": DELAY}, prefetch=False) as s:
        feature = s.welcome.features["progressive"]
        assert feature["on"] and feature["first"]["core"] == "sampling"
        t0 = time.perf_counter()
        _pose(s, scene, 0, 0)
        s.wait_cell(0, timeout=DELAY * 0.8)  # the first answer, before the core's
        assert time.perf_counter() - t0 < DELAY
        first = s.cells[0]
        assert first.answer == "first" and first.begin.answer == "first"
        first_ids = _ids(first)
        # The first answer is the first core's PVS of the cell, as computed directly.
        first = app.state.server.resolver.first()
        core, params = first.core, first.params
        grid = app.state.server.catalog.get("tiny").grid
        direct = core.compute(scene, grid.cell(0), params).triangle_ids
        assert first_ids == set(direct.tolist())
        wait_for(lambda: s.cells[0].answer == "refined")
        refined = s.cells[0]
        assert refined.begin.answer == "refined" and refined.end.answer == "refined"
        want = set(near_ids(scene, grid.boxes[0], 5.0).tolist())
        # Only the difference travelled, and the cell now holds the core's whole PVS.
        assert refined.begin.new == len(want - first_ids)
        assert refined.begin.triangles == len(want)
        assert want <= set(s.store.ids.tolist())
        assert not s.errors and not s.local_errors


def test_a_cell_already_computed_comes_whole(progressive_server):
    url, _, scene = progressive_server
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": DELAY}, prefetch=False) as s:
        _pose(s, scene, 1, 0)
        wait_for(lambda: 1 in s.cells and s.cells[1].answer == "refined")
    # A second walker finds the core's answer in the cache: no first pass.
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": DELAY}, prefetch=False) as s:
        _pose(s, scene, 1, 0)
        s.wait_cell(1, timeout=10)
        assert s.cells[1].answer == "full"


def test_prefetched_cells_skip_the_first_pass(progressive_server):
    url, _, scene = progressive_server
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": 0.3, "radius": 4.0},
                             prefetch=True) as s:
        _pose(s, scene, 4, 0)
        wait_for(lambda: len([c for c in s.cells.values() if c.answer]) >= 3)
        ahead = [c for c in s.cells.values() if c.begin.prefetch and c.answer]
        assert ahead and all(c.answer == "full" for c in ahead)


def test_the_client_or_the_server_turns_it_off(progressive_server, settings):
    url, _, scene = progressive_server
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": 0.5}, prefetch=False,
                             progressive=False) as s:
        feature = s.welcome.features["progressive"]
        assert not feature["on"] and "client" in feature["why"]
        _pose(s, scene, 2, 0)
        s.wait_cell(2, timeout=10)
        assert s.cells[2].answer == "full"
    with serving(settings, scenes={"tiny": make_tiny_scene()}) as (url2, _):
        with SyncSession.connect(url2, "tiny", "test_slow", {"delay": 0.5},
                                 prefetch=False) as s:
            assert not s.welcome.features["progressive"]["on"]


def test_the_first_core_itself_is_not_refined(progressive_server):
    url, app, _ = progressive_server
    first = app.state.server.resolver.first()
    core, params = first.core, first.params
    with SyncSession.connect(url, "tiny", core.name, params.as_dict(), prefetch=False) as s:
        feature = s.welcome.features["progressive"]
        assert not feature["on"] and "nothing to refine" in feature["why"]


def test_leaving_before_the_refinement_gives_it_up(progressive_server):
    url, app, scene = progressive_server
    counters = app.state.server.counters
    dropped = counters["refinements_dropped"]
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": 3.0, "radius": 3.0},
                             prefetch=False) as s:
        _pose(s, scene, 5, 0)
        s.wait_cell(5, timeout=2.5)
        assert s.cells[5].answer == "first"
        _pose(s, scene, 7, 1)  # far from cell 5: it is neither current nor ahead
        s.wait_cell(7, timeout=2.5)
        wait_for(lambda: counters["refinements_dropped"] > dropped)
        # Back in cell 5: it streams again, and this time its refinement arrives.
        _pose(s, scene, 5, 2)
        wait_for(lambda: s.cells[5].answer == "refined", timeout=30)
        grid = app.state.server.catalog.get("tiny").grid
        assert set(near_ids(scene, grid.boxes[5], 3.0).tolist()) <= set(s.store.ids.tolist())


def test_progressive_settings_from_the_environment():
    from server.settings import Settings

    s = Settings.from_env({"PVS_PROGRESSIVE": "0", "PVS_FIRST_CORE": "sampling",
                           "PVS_FIRST_PARAMS": '{"samples": 2}'})
    assert s.progressive is False and s.first_params == {"samples": 2}
    with pytest.raises(ValueError, match="PVS_FIRST_PARAMS"):
        Settings.from_env({"PVS_FIRST_PARAMS": "[1]"})


def test_first_answers_do_not_wait_for_busy_workers(settings):
    """Both workers busy with the session core's work: the first answer still comes at once,
    from its own worker."""
    scene = make_tiny_scene()
    with serving(settings, scenes={"tiny": scene}, progressive=True, workers=1) as (url, app):
        with SyncSession.connect(url, "tiny", "test_slow", {"delay": 2.0},
                                 prefetch=False) as a, \
                SyncSession.connect(url, "tiny", "test_slow", {"delay": 2.0},
                                    prefetch=False) as b:
            _pose(a, scene, 0, 0)
            time.sleep(0.1)  # a's computation holds the only worker
            t0 = time.perf_counter()
            _pose(b, scene, 3, 0)
            b.wait_cell(3, timeout=1.5)
            assert time.perf_counter() - t0 < 1.5
            assert b.cells[3].answer == "first"


def test_cells_ahead_have_their_first_answer_ready(settings):
    """While a walker stands in a cell, the cells ahead of it get their first answers computed
    (after those walkers wait for), so stepping into one costs no first pass."""
    scene = make_tiny_scene()
    with serving(settings, scenes={"tiny": scene}, progressive=True) as (url, app), \
            SyncSession.connect(url, "tiny", "test_slow", {"delay": 5.0, "radius": 2.5},
                                prefetch=True) as s:
        compute = app.state.server.compute
        first = app.state.server.resolver.first()
        core, params = first.core, first.params
        assert all(compute.cache.get(compute.key("tiny", core, params, n), upto="memory") is None
                   for n in range(8))
        _pose(s, scene, 5, 0)
        s.wait_cell(5, timeout=4)

        def warmed() -> list[int]:
            return [n for n in range(8) if n != 5 and compute.cache.get(
                compute.key("tiny", core, params, n), upto="memory") is not None]

        wait_for(lambda: warmed(), timeout=10)
        ahead = warmed()[0]
        _pose(s, scene, ahead, 1)
        s.wait_cell(ahead, timeout=1.0)
        assert s.cells[ahead].answer == "first"


def test_coming_back_before_the_refinement_is_announced_as_the_first_answer(settings):
    """A walker steps out of a cell and back while its core still computes: the cell is
    announced again as holding its first answer, and its refinement follows."""
    scene = make_tiny_scene()
    with serving(settings, scenes={"tiny": scene}, progressive=True) as (url, _), \
            SyncSession.connect(url, "tiny", "test_slow", {"delay": 3.0, "radius": 3.0},
                                prefetch=True) as s:
        grid = ViewcellGrid.for_scene(scene, s.welcome.grid.cell_size)
        a, b = grid.boxes[0].mean(axis=0), grid.boxes[1].mean(axis=0)
        s.send_pose(0, 0.0, a, (1.0, 0.0, 0.0))
        s.wait_cell(0, timeout=2.5)
        assert s.cells[0].answer == "first"
        # Into the next cell, heading back: the first cell stays ahead, its refinement kept.
        s.send_pose(1, 1.0, b, (-1.0, 0.0, 0.0), a - b)
        s.wait_cell(1, timeout=2.5)
        s.send_pose(2, 2.0, a, (-1.0, 0.0, 0.0), a - b)
        # The announcement's begin and its end (which carries the answer) arrive apart: a busy
        # machine can run the check between them.
        wait_for(lambda: s.cells[0].begin.seq == 2 and s.cells[0].answer is not None, timeout=5)
        assert s.cells[0].begin.answer == "first" and s.cells[0].answer == "first"
        wait_for(lambda: s.cells[0].answer == "refined", timeout=15)


@pytest.fixture()
def fresh_server(settings):
    """A progressive server of its own (an empty cache), known answers on."""
    scene = make_tiny_scene()
    with serving(settings, scenes={"tiny": scene}, progressive=True) as (url, app):
        yield url, app, scene


def _counter(app, name: str) -> int:
    return int(app.state.server.counters[name])


def _compute_over_http(url: str, cells) -> None:
    """The session core's PVS of ``cells`` (as ``test_slow`` computes it for sessions: the
    same cache key), computed through the HTTP route, in parallel."""
    from concurrent.futures import ThreadPoolExecutor

    import httpx

    def one(c):
        r = httpx.get(f"{url}/scenes/tiny/cells/{c}/pvs",
                      params={"core": "test_slow", "delay": DELAY}, timeout=60)
        assert r.status_code == 200, r.text

    with ThreadPoolExecutor(4) as pool:
        list(pool.map(one, cells))


def test_known_answer_is_the_union_of_the_neighbours_pvs(fresh_server):
    """A walker entering a cell whose PVS is not computed, next to enough cells whose PVS is,
    gets their union at once ("known": no first answer computed), then what the core adds."""
    url, app, scene = fresh_server
    grid = app.state.server.catalog.get("tiny").grid
    b = max(range(len(grid)), key=lambda c: len(grid.neighbours(c)))
    nbrs = grid.neighbours(b)
    known = nbrs[:streams.KNOWN_MIN]
    _compute_over_http(url, known)
    firsts = _counter(app, "first_answers")
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": DELAY}, prefetch=False) as s:
        t0 = time.perf_counter()
        _pose(s, scene, b, 0)
        s.wait_cell(b, timeout=DELAY * 0.8)
        assert time.perf_counter() - t0 < DELAY
        got = s.cells[b]
        held = set(s.store.ids.tolist())
        assert got.answer == "known" and got.begin.answer == "known"
        # The union of what is known around b, and nothing computed for it.
        union = set().union(*(near_ids(scene, grid.boxes[c], 5.0).tolist() for c in known))
        assert _ids(got) == union and held == union
        assert _counter(app, "known_answers") >= 1
        assert _counter(app, "first_answers") == firsts
        wait_for(lambda: s.cells[b].answer == "refined")
        want = set(near_ids(scene, grid.boxes[b], 5.0).tolist())
        assert s.cells[b].begin.triangles == len(want)
        # Only what b's PVS adds to what the client held travelled.
        assert s.cells[b].begin.new == len(want - held)
        assert want <= set(s.store.ids.tolist())
        assert not s.errors and not s.local_errors


def test_too_little_known_joins_a_computed_first_answer(fresh_server):
    """With fewer known neighbours than ``KNOWN_MIN``, a first answer is computed, and what is
    known joins it."""
    url, app, scene = fresh_server
    grid = app.state.server.catalog.get("tiny").grid
    b = max(range(len(grid)), key=lambda c: len(grid.neighbours(c)))
    a = grid.neighbours(b)[-1]
    assert len(grid.neighbours(b)) > 1
    _compute_over_http(url, [a])
    with SyncSession.connect(url, "tiny", "test_slow", {"delay": DELAY}, prefetch=False) as s:
        _pose(s, scene, b, 0)
        s.wait_cell(b, timeout=DELAY * 0.8)
        got = s.cells[b]
        assert got.answer == "first"
        first = app.state.server.resolver.first()
        direct = first.core.compute(scene, grid.cell(b), first.params).triangle_ids
        assert _ids(got) == set(direct.tolist()) | set(near_ids(scene, grid.boxes[a],
                                                                 5.0).tolist())


def test_no_known_answer_when_nothing_is_known_or_it_is_off(settings):
    scene = make_tiny_scene()
    with serving(settings, scenes={"tiny": scene}, progressive=True,
                 known_answers=False) as (url, app):
        grid = app.state.server.catalog.get("tiny").grid
        a = 0
        b = grid.neighbours(a)[0]
        with SyncSession.connect(url, "tiny", "test_slow", {"delay": DELAY},
                                 prefetch=False) as s:
            _pose(s, scene, a, 0)  # nothing known yet: a computed first answer
            s.wait_cell(a, timeout=DELAY * 0.8)
            assert s.cells[a].answer == "first"
            wait_for(lambda: s.cells[a].answer == "refined")
            _pose(s, scene, b, 1)  # known answers off: computed again
            s.wait_cell(b, timeout=DELAY * 0.8)
            assert s.cells[b].answer == "first"
        assert _counter(app, "known_answers") == 0
