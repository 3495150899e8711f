"""The client's GeometryStore and network Session (against the real server on loopback)."""

from __future__ import annotations

import asyncio
import threading
import time

import httpx
import numpy as np
import pytest

from client.session import Session, SessionError, SyncSession, ws_url
from client.store import MERGE_ROWS, GeometryStore
from protocol.frames import decode_geometry, encode_geometry
from protocol.messages import CellBegin, CellEnd, dump_message
from tests.conftest import make_tiny_scene, near_ids

TINY = make_tiny_scene()
NEAR = {"radius": 4.5}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


def _tris(ids, seed=0):
    rng = np.random.default_rng(seed)
    n = len(ids)
    return rng.normal(size=(n, 3, 3)), rng.integers(0, 256, (n, 3), dtype=np.uint8)


# --------------------------------------------------------------------------- store
def test_store_add_arrays_and_version():
    s = GeometryStore()
    assert len(s) == 0 and s.version == 0
    ids0, tris0, cols0 = s.arrays()
    assert ids0.shape == (0,) and tris0.shape == (0, 3, 3) and cols0.shape == (0, 3)
    t, c = _tris([5, 1, 3])
    s.add(np.array([5, 1, 3]), t, c)
    assert s.version == 1
    ids, tris, cols = s.arrays()
    assert ids.tolist() == [1, 3, 5] and ids.dtype == np.int32
    assert tris.dtype == np.float64 and cols.dtype == np.uint8
    np.testing.assert_array_equal(tris, t[[1, 2, 0]])
    np.testing.assert_array_equal(cols, c[[1, 2, 0]])
    # Cached until changed: the very same (read-only) arrays, same version.
    again = s.arrays()
    assert all(a is b for a, b in zip(again, (ids, tris, cols), strict=True))
    assert s.version == 1 and len(s) == 3
    with pytest.raises(ValueError):
        ids[0] = 7
    t2, c2 = _tris([2], 1)
    s.add(np.array([2]), t2, c2)
    assert s.version == 2 and s.arrays()[0] is not ids and s.ids.tolist() == [1, 2, 3, 5]
    version, *arrays = s.snapshot()
    assert version == 2 and all(a is b for a, b in zip(arrays, s.arrays(), strict=True))


def test_store_latest_copy_wins_and_empty_add_is_no_change():
    s = GeometryStore()
    t, c = _tris([1, 2], 0)
    s.add(np.array([1, 2]), t, c)
    t2, c2 = _tris([2], 9)
    s.add(np.array([2]), t2, c2)
    s.add(np.array([2]), t2 + 1.0, c2)
    ids, tris, cols = s.arrays()
    assert ids.tolist() == [1, 2]
    np.testing.assert_array_equal(tris[1], t2[0] + 1.0)
    v = s.version
    s.add(np.zeros(0, np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3), np.uint8))
    assert s.version == v


def test_store_drop_retain_contains_clear():
    s = GeometryStore()
    ids = np.arange(0, 20, 2)
    t, c = _tris(ids)
    s.add(ids, t, c)
    assert s.contains([0, 1, 2, 18, 19, 100]).tolist() == [True, False, True, True, False, False]
    assert 4 in s and 5 not in s
    v = s.version
    assert s.drop([2, 4, 5]) == 2 and s.version == v + 1
    assert s.drop([5]) == 0 and s.version == v + 1  # nothing removed: no change
    assert s.ids.tolist() == [0, 6, 8, 10, 12, 14, 16, 18]
    np.testing.assert_array_equal(s.arrays()[1], t[[0, 3, 4, 5, 6, 7, 8, 9]])
    assert s.retain([6, 8, 99]) == 6
    assert s.ids.tolist() == [6, 8]
    s.clear()
    assert len(s) == 0 and s.contains([6]).tolist() == [False]


def test_store_budget():
    with pytest.raises(ValueError):
        GeometryStore(budget=0)
    s = GeometryStore(budget=3)
    t, c = _tris(range(4))
    s.add(np.arange(3), t[:3], c[:3])
    assert not s.over_budget
    s.add(np.array([3]), t[3:], c[3:])
    assert s.over_budget  # the store reports; the holder decides what to drop
    s.retain([0, 1])
    assert not s.over_budget


@pytest.mark.parametrize(
    "ids, tris, cols",
    [
        ([1.5], np.zeros((1, 3, 3)), np.zeros((1, 3), np.uint8)),
        ([-1], np.zeros((1, 3, 3)), np.zeros((1, 3), np.uint8)),
        ([1, 2], np.zeros((1, 3, 3)), np.zeros((2, 3), np.uint8)),
        ([1], np.zeros((1, 3, 3)), np.zeros((1, 4), np.uint8)),
        ([1], np.full((1, 3, 3), np.nan), np.zeros((1, 3), np.uint8)),
    ],
)
def test_store_rejects_bad_input(ids, tris, cols):
    with pytest.raises(ValueError):
        GeometryStore().add(np.asarray(ids), tris, cols)


def test_store_add_chunk_makes_positions_absolute():
    ids = np.array([7, 3])
    t = np.random.default_rng(1).uniform(-1, 1, (2, 3, 3)) + 1e5
    c = np.array([[1, 2, 3], [4, 5, 6]], np.uint8)
    s = GeometryStore()
    s.add_chunk(decode_geometry(encode_geometry(ids, t, c)))
    out_ids, out_t, out_c = s.arrays()
    assert out_ids.tolist() == [3, 7]
    np.testing.assert_allclose(out_t, t[[1, 0]], atol=1e-6)
    np.testing.assert_array_equal(out_c, c[[1, 0]])


def test_store_many_chunks_merge_fast():
    s = GeometryStore()
    rng = np.random.default_rng(2)
    n, k = 200_000, 100
    ids = rng.permutation(n)
    t0 = time.perf_counter()
    for part in np.array_split(ids, k):
        s.add(part, np.zeros((len(part), 3, 3)), np.zeros((len(part), 3), np.uint8))
    out = s.arrays()[0]
    elapsed = time.perf_counter() - t0
    assert out.tolist() == list(range(n))
    assert elapsed < 5.0, elapsed  # one merge, not 100 (about 0.1 s unloaded)


def test_store_is_thread_safe():
    s = GeometryStore()
    errors = []

    def writer(base):
        for i in range(50):
            ids = np.arange(base + i * 10, base + i * 10 + 10)
            s.add(ids, np.zeros((10, 3, 3)), np.zeros((10, 3), np.uint8))

    def reader():
        try:
            for _ in range(200):
                ids, tris, cols = s.arrays()
                assert len(ids) == len(tris) == len(cols)
                assert np.all(np.diff(ids) > 0)
        except AssertionError as exc:
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(b,)) for b in (0, 100_000)]
    threads += [threading.Thread(target=reader) for _ in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors and len(s) == 1000


# --------------------------------------------------------------------------- keyframes
def _moving_scene():
    """Three triangles; the 2nd and 3rd move over keyframes at 0, 0.5, 2 s (the 1st does not)."""
    rng = np.random.default_rng(3)
    v0 = rng.normal(size=(9, 3))
    states = np.stack([v0, v0 + [0.0, 0.0, 0.0], v0.copy()])
    states[1, 3:] += rng.normal(size=(6, 3))
    states[2, 3:] += rng.normal(size=(6, 3))
    from visibility.scene import Scene

    return Scene(vertices=v0, faces=np.arange(9).reshape(3, 3), states=states,
                 state_times=np.array([0.0, 0.5, 2.0]))


def test_store_interpolates_keyframes_as_the_scene_does():
    sc = _moving_scene()
    s = GeometryStore()
    s.add(np.arange(3), sc.triangles(), sc.colors)
    s.add_keyframes(np.array([1, 2]), sc.state_times, sc.states[:, sc.faces[1:]])
    assert s.keyframes()[0].tolist() == [1, 2]
    for t in (-1.0, 0.0, 0.2, 0.5, 1.3, 2.0, 7.0):  # clamped outside [0, 2]
        ids, tris, _ = s.triangles_at(t)
        assert ids.tolist() == [0, 1, 2]
        np.testing.assert_allclose(tris, sc.vertices_at(t)[sc.faces], atol=1e-12)
    # None is at rest; the static layer is the same object until the store changes.
    (si, st, _), (mi, mt, _) = s.layers_at(None)
    assert si.tolist() == [0] and mi.tolist() == [1, 2]
    np.testing.assert_allclose(mt, sc.triangles()[1:])
    assert s.layers_at(1.0)[0][1] is st


def test_store_keyframes_arrive_before_geometry_and_drop_with_it():
    sc = _moving_scene()
    s = GeometryStore()
    s.add_keyframes(np.array([1, 2]), sc.state_times, sc.states[:, sc.faces[1:]])
    assert len(s.triangles_at(1.0)[0]) == 0  # nothing drawn without its triangle
    s.add(np.arange(3), sc.triangles(), sc.colors)
    np.testing.assert_allclose(s.triangles_at(1.0)[1], sc.vertices_at(1.0)[sc.faces])
    s.drop([2])
    assert s.keyframes()[0].tolist() == [1]
    s.add([2], sc.triangles()[2:], sc.colors[2:])  # sent again without keyframes: at rest
    np.testing.assert_allclose(s.triangles_at(1.0)[1][2], sc.triangles()[2])
    s.retain([0])
    assert s.keyframes()[0].size == 0
    s.clear()
    assert len(s) == 0 and s.n_spheres == 0


def test_store_spheres_and_bad_keyframes():
    s = GeometryStore()
    times = np.array([0.0, 1.0])
    centers = np.array([[[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]], [[0.0, 2.0, 0.0], [5.0, 0.0, 4.0]]])
    s.add_spheres(np.array([3, 7]), times, centers, np.array([1.0, 0.5]),
                  np.array([[255, 0, 0], [0, 255, 0]], np.uint8))
    ids, c, r, cols = s.spheres_at(0.25)
    assert ids.tolist() == [3, 7] and s.n_spheres == 2
    np.testing.assert_allclose(c, [[0.0, 0.5, 0.0], [5.0, 0.0, 1.0]])
    np.testing.assert_allclose(r, [1.0, 0.5])
    s.drop([3, 7])  # drops name triangles: spheres stay
    assert s.n_spheres == 2
    with pytest.raises(ValueError):
        s.add_spheres(np.array([1]), times, centers[:, :1], np.array([-1.0]),
                      np.zeros((1, 3), np.uint8))
    with pytest.raises(ValueError):  # wrong shape
        s.add_keyframes(np.array([0]), times, np.zeros((3, 1, 3, 3)))
    with pytest.raises(ValueError):  # non-finite
        s.add_keyframes(np.array([0]), times, np.full((2, 1, 3, 3), np.nan))
    with pytest.raises(ValueError):  # times not increasing
        s.add_keyframes(np.array([0]), np.array([1.0, 0.0]), np.zeros((2, 1, 3, 3)))
    s.add_keyframes(np.array([0]), times, np.zeros((2, 1, 3, 3)))
    with pytest.raises(ValueError):  # one scene has one set of keyframe times
        s.add_keyframes(np.array([1]), np.array([0.0, 3.0]), np.zeros((2, 1, 3, 3)))


def test_store_refuses_ids_outside_the_scene():
    s = GeometryStore(scene_triangles=10, scene_spheres=2)
    t, c = _tris([0, 9])
    s.add(np.array([0, 9]), t, c)
    for bad in ([10], [3, 2**31 - 1], [-1]):
        t, c = _tris(bad)
        with pytest.raises(ValueError, match=r"\[0, 10, the scene's triangle count\)"):
            s.add(np.array(bad), t, c)
    with pytest.raises(ValueError, match="triangle count"):
        s.add_keyframes(np.array([10]), np.array([0.0]), np.zeros((1, 1, 3, 3)))
    with pytest.raises(ValueError, match="sphere count"):
        s.add_spheres(np.array([2]), np.array([0.0]), np.zeros((1, 1, 3)), np.array([1.0]),
                      np.zeros((1, 3), np.uint8))
    assert s.ids.tolist() == [0, 9] and s.version == 1  # nothing refused was added


def test_store_memory_stays_bounded_by_the_scene_whatever_is_repeated():
    """A server sending the same triangles again and again: chunks waiting to merge never
    outgrow max(MERGE_ROWS, rows held), so the store stays near one copy per id."""
    n = 1000
    s = GeometryStore(scene_triangles=n)
    ids = np.arange(n)
    t, c = _tris(ids)
    row = t[0].nbytes + c[0].nbytes + 4
    for _ in range(3 * MERGE_ROWS // n):
        s.add(ids, t, c)
        assert s.nbytes <= (n + MERGE_ROWS + n) * row
    assert len(s) == n


# --------------------------------------------------------------------------- session
def test_ws_url():
    assert ws_url("http://127.0.0.1:8000") == "ws://127.0.0.1:8000/ws"
    assert ws_url("https://h/") == "wss://h/ws"
    assert ws_url("ws://h:1/ws") == "ws://h:1/ws"
    assert ws_url("http://h/prefix") == "ws://h/prefix/ws"
    with pytest.raises(ValueError):
        ws_url("ftp://h")


@pytest.fixture(scope="module")
def cell_boxes(live_server):
    cells = httpx.get(live_server + "/scenes/tiny/cells", timeout=60).json()["cells"]
    return [np.array(c["box"]) for c in cells]


def test_session_streams_into_its_store(live_server, cell_boxes):
    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", NEAR, budget=150,
                                  prefetch=False)
        assert s.welcome.budget == 150 and s.store.budget == 150
        assert not s.is_complete(2)
        await s.send_pose(0, 0.0, cell_boxes[2].mean(axis=0), [0, 0, -1],
                          velocity=np.array([1.0, 0, 0]))
        cs = await s.wait_cell(2, timeout=60)
        assert s.is_complete(2) and cs.complete and cs.begin.cell == 2
        version = s.store.version
        # Waiting for a cell nobody walks to times out.
        with pytest.raises(TimeoutError):
            await s.wait_cell(3, timeout=0.2)
        await s.close()
        assert s.closed and s.close_code == 1000
        with pytest.raises(SessionError):
            await s.send_pose(1, 0.1, cell_boxes[3].mean(axis=0), [0, 0, -1])
        with pytest.raises(SessionError):
            await s.wait_cell(3, timeout=1)  # ended sessions wake waiters at once
        return s, version

    s, version = run(main())
    assert version > 0 and not s.errors and not s.local_errors
    expected = near_ids(TINY, cell_boxes[2], 4.5)
    np.testing.assert_array_equal(s.store.ids, expected)
    np.testing.assert_allclose(s.store.arrays()[1], TINY.triangles(expected), atol=1e-5)


def test_session_routes_keyframe_and_sphere_frames(live_server):
    """Keyframe and sphere frames go into the store by kind; a corrupt one, or spheres in a
    scene the welcome says has none, is a local error and the session goes on."""
    from protocol.keyframes import encode_keyframes, encode_spheres

    sc = _moving_scene()

    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
        try:
            kf = encode_keyframes(np.array([1, 2]), sc.state_times, sc.states[:, sc.faces[1:]])
            sp = encode_spheres(np.array([4]), np.array([0.0]), np.zeros((1, 1, 3)),
                                np.array([0.5]), np.zeros((1, 3), np.uint8))
            s._on_frame(kf)
            assert s.keyframes_received == 2
            assert s.store.keyframes()[0].tolist() == [1, 2]
            assert s.welcome.scene.spheres == 0
            s._on_frame(sp)
            assert s.spheres_received == 0 and s.store.n_spheres == 0
            assert "sphere ids up to 4, outside [0, 0)" in s.local_errors[0]
            s._on_frame(kf[: len(kf) // 2])
            assert s.keyframe_frames == 2 and len(s.local_errors) == 2
            assert "keyframes" in s.local_errors[1]
            await s.send_pose(0, 0.0, (2.0, 1.7, 2.0), (0, 0, -1))
            await s.wait_cell(0, timeout=60)  # still streaming
        finally:
            await s.close()

    run(main())


def test_session_keeps_server_errors(live_server, cell_boxes):
    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
        await s.send_pose(0, 0.0, [900.0, 1.7, 900.0], [0, 0, -1])
        await s.send_raw('{"type": "pose", "seq": 1, "t": 0, "position": [1, NaN, 1], '
                         '"forward": [0, 0, 1]}')
        await s.send_pose(2, 0.0, cell_boxes[1].mean(axis=0), [0, 0, -1])
        await s.wait_cell(1, 60)
        await s.close()
        return s

    s = run(main())
    assert [(e.code, e.seq, e.fatal) for e in s.errors] == [("outside_grid", 0, False),
                                                            ("invalid_pose", 1, False)]


def test_session_end_by_fatal_error_wakes_waiters(live_server):
    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
        waiter = asyncio.create_task(s.wait_cell(0, 60))
        await asyncio.sleep(0.05)
        # A second hello is fatal in any phase (binary frames are fatal only before welcome).
        await s.send_raw('{"type": "hello", "version": 2, "scene": "tiny", "core": "test_near"}')
        with pytest.raises(SessionError) as exc:
            await waiter
        await s.wait_closed(5)
        await s.close()
        return s, exc.value

    s, err = run(main())
    assert err.code == "duplicate_hello" and s.close_code == 1008
    assert s.errors[-1].fatal


def test_send_pose_validates_locally(live_server):
    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
        with pytest.raises(ValueError, match="invalid pose"):
            await s.send_pose(0, 0.0, [np.nan, 0, 0], [0, 0, 1])
        with pytest.raises(ValueError):
            await s.send_pose(0, 0.0, [0, 0], [0, 0, 1])
        with pytest.raises(ValueError):
            await s.send_pose(-1, 0.0, [0, 0, 0], [0, 0, 1])
        await s.close()
        return s

    assert not run(main()).errors  # nothing bad reached the server


@pytest.mark.parametrize(
    "kwargs, code, close",
    [
        ({"scene": "nope"}, "unknown_scene", 4004),
        ({"core": "nope"}, "unknown_core", 4005),
        ({"params": {"radius": "far"}}, "bad_params", 4022),
    ],
)
def test_connect_refused(live_server, kwargs, code, close):
    args = {"scene": "tiny", "core": "test_near", "params": NEAR, **kwargs}

    async def main():
        with pytest.raises(SessionError) as exc:
            await Session.connect(live_server, **args)
        return exc.value

    err = run(main())
    assert err.code == code and err.close_code == close


def test_sync_session(live_server, cell_boxes):
    with SyncSession.connect(live_server, "tiny", "test_near", NEAR, prefetch=False) as s:
        assert s.welcome.scene.name == "tiny"
        s.send_pose(0, 0.0, cell_boxes[5].mean(axis=0), [0, 0, -1])
        cs = s.wait_cell(5, timeout=60)
        assert cs.end.cell == 5 and s.is_complete(5)
        assert s.store.ids.tolist() == near_ids(TINY, cell_boxes[5], 4.5).tolist()
        with pytest.raises(TimeoutError):
            s.wait_cell(6, timeout=0.2)
    assert s.closed
    with pytest.raises(SessionError):
        SyncSession.connect(live_server, "nope", "test_near")


# --------------------------------------------------------------------------- hostile server
def _hostile_stream() -> list:
    """What a hostile (or broken) server sends after its welcome for a scene of 10 triangles
    in 2 cells: a stream of cell 0 announcing 3 new triangles, with frames whose ids are past
    the scene, a repeat past the announced count, and a cell_begin and cubemap for cells the
    grid does not have."""
    def frame(ids, cell=0):
        t, c = _tris(ids)
        return encode_geometry(np.array(ids), t, c, cell=cell)

    from protocol.cubemap import encode_cubemap

    cube = encode_cubemap(5, np.zeros(3), np.zeros((6, 8, 8, 3), np.uint8),
                          np.ones((6, 8, 8), np.float32), 1.0, 2.0)
    return [
        dump_message(CellBegin(cell=0, seq=0, triangles=3, new=3, chunks=2)),
        frame([0, 1]),
        frame([5, 2**31 - 1]),
        frame([10]),
        frame([2]),
        frame([3]),  # past the 3 announced
        dump_message(CellEnd(cell=0, seq=0, seconds=0.0)),
        dump_message(CellBegin(cell=7, seq=1, triangles=1, new=1, chunks=1)),
        frame([4], cell=7),
        dump_message(CellBegin(cell=1, seq=2, triangles=11, new=11, chunks=1)),
        cube,
    ]


def test_session_refuses_what_the_welcome_rules_out():
    """A real WebSocket server that lies: ids outside [0, scene triangles), more triangles than
    announced, cells the grid does not have. The client keeps only what the welcome allows and
    says why in ``local_errors``."""
    from websockets.asyncio.server import serve

    from tests.protocol.test_messages import _welcome

    welcome = _welcome()  # 10 triangles, 8 cells
    welcome = welcome.model_copy(update={"grid": welcome.grid.model_copy(update={"cells": 2})})

    async def hostile(ws):
        await ws.recv()
        await ws.send(dump_message(welcome))
        for msg in _hostile_stream():
            await ws.send(msg)
        await ws.close()

    async def main():
        async with serve(hostile, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            s = await Session.connect(f"http://127.0.0.1:{port}", "x")
            await s.wait_closed(timeout=30)  # the server closes after its whole stream
            await s.close()
            return s

    s = run(main())
    # Triangle 4 came outside any stream (its cell_begin was refused): ids in the scene are
    # kept, as ever, and the stray chunk reported.
    assert s.store.ids.tolist() == [0, 1, 2, 4] and s.held == 4
    assert s.store.scene_triangles == 10
    assert set(s.cells) == {0} and s.complete == {0} and not s.cubemaps
    assert s.cells[0].triangles == 3
    errors = "\n".join(s.local_errors)
    assert "ids up to 2147483647, outside [0, 10)" in errors
    assert "ids up to 10, outside [0, 10)" in errors
    assert "past the 3 triangles its cell_begin announced" in errors
    assert "cell_begin for cell 7" in errors and "cell_begin for cell 1" in errors
    assert "chunk of cell 7 outside its cell stream" in errors
    assert "cubemap of cell 5" in errors
