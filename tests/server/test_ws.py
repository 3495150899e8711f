"""The /ws streaming endpoint of the real server, driven by a real websockets client."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np
import pytest
import websockets
from websockets.asyncio.client import connect

from client.session import Session, SessionError
from protocol.frames import decode_geometry, triangles_per_frame
from protocol.messages import Hello, Pose, dump_message, parse_server_message
from tests.conftest import make_tiny_scene, near_ids

TINY = make_tiny_scene()
NEAR = {"radius": 4.5}
TIMEOUT = 60.0


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


@pytest.fixture(autouse=True)
def still_healthy(live_server):
    """After every test the server still answers /health."""
    yield
    r = httpx.get(live_server + "/health", timeout=60)
    assert r.status_code == 200 and r.json()["status"] == "ok"


@pytest.fixture(scope="module")
def cells(live_server) -> list[dict]:
    return httpx.get(live_server + "/scenes/tiny/cells", timeout=60).json()["cells"]


def centre(cells, cid: int) -> list[float]:
    return np.asarray(cells[cid]["box"]).mean(axis=0).tolist()


def hello(**kw) -> str:
    args = {"scene": "tiny", "core": "test_near", "params": NEAR, "prefetch": False}
    args.update(kw)
    return dump_message(Hello(**args))


def pose(seq: int, position, t: float = 0.0) -> str:
    return dump_message(Pose(seq=seq, t=t, position=tuple(position), forward=(0.0, 0.0, -1.0)))


async def collect_until_close(ws) -> list:
    """Every message until the server closes: parsed text messages and raw bytes."""
    out = []
    try:
        async for raw in ws:
            out.append(raw if isinstance(raw, bytes) else parse_server_message(raw))
    except websockets.ConnectionClosed:
        pass
    return out


async def fatal_after(ws_endpoint: str, *frames) -> tuple[list, int]:
    """Send ``frames``; the messages received until close and the close code."""
    async with connect(ws_endpoint, open_timeout=TIMEOUT) as ws:
        for f in frames:
            await ws.send(f)
        msgs = await asyncio.wait_for(collect_until_close(ws), TIMEOUT)
        return msgs, ws.close_code


async def recv_until(ws, kind: str, timeout: float = TIMEOUT):
    """Messages up to and including the first of type ``kind`` (bytes are kept raw)."""
    out = []
    while True:
        raw = await asyncio.wait_for(ws.recv(), timeout)
        msg = raw if isinstance(raw, bytes) else parse_server_message(raw)
        out.append(msg)
        if getattr(msg, "type", None) == kind:
            return out


# --------------------------------------------------------------------------- happy path
def test_stream_matches_http_pvs_and_sends_each_triangle_once(live_server, cells, settings):
    walk = [0, 1, 3, 2, 0, 4, 5]  # includes a return to cell 0

    async def main():
        s = await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
        assert s.welcome.scene.triangles == TINY.n_triangles
        assert s.welcome.grid.cells == 8 and s.welcome.core == "test_near"
        assert s.welcome.params["radius"] == 4.5
        assert s.welcome.limits.max_frame_bytes == settings.max_frame_bytes
        streams = []
        for seq, cid in enumerate(walk):
            await s.send_pose(seq, seq * 0.1, centre(cells, cid), (0, 0, -1))
            # Wait for this pose's stream (cell 0 is already complete when revisited).
            await asyncio.wait_for(_wait_seq(s, cid, seq), TIMEOUT)
            streams.append(s.cells[cid])
        await s.close()
        return s, streams

    s, streams = run(main())
    assert not s.errors and not s.local_errors
    union = np.zeros(0, dtype=np.int32)
    all_sent = []
    with httpx.Client(base_url=live_server, timeout=60) as http:
        for cid, cs in zip(walk, streams, strict=True):
            body = http.get(f"/scenes/tiny/cells/{cid}/pvs",
                            params={"core": "test_near", **NEAR}).json()
            pvs = np.array(body["triangle_ids"], dtype=np.int32)
            np.testing.assert_array_equal(pvs, near_ids(TINY, cells[cid]["box"], 4.5))
            assert cs.begin.triangles == len(pvs) and cs.end.cell == cid
            got = np.concatenate(cs.ids) if cs.ids else np.zeros(0, np.int32)
            # A cell stream carries exactly its PVS minus what the session already has.
            np.testing.assert_array_equal(np.sort(got), np.setdiff1d(pvs, union))
            union = np.union1d(union, pvs)
            all_sent.append(got)
    assert streams[4].begin.new == 0  # the revisit of cell 0 sends nothing
    all_sent = np.concatenate(all_sent)
    assert len(all_sent) == len(np.unique(all_sent))  # each triangle id once per session
    # The store holds exactly the union, with the scene's geometry and colours.
    ids, tris, cols = s.store.arrays()
    np.testing.assert_array_equal(ids, union)
    np.testing.assert_allclose(tris, TINY.triangles(ids), atol=1e-5)
    np.testing.assert_array_equal(cols, TINY.colors[ids])
    # Small frames: the biggest cell spans several chunks, none over the limit.
    per = triangles_per_frame(settings.max_frame_bytes)
    assert max(c.begin.chunks for c in streams) > 1
    for c in streams:
        assert c.begin.chunks == -(-c.begin.new // per) == c.chunks
        assert c.end.seconds >= 0 and c.end.seq == c.begin.seq


async def _wait_seq(s: Session, cell: int, seq: int) -> None:
    while True:
        cs = s.cells.get(cell)
        if cs is not None and cs.end is not None and cs.end.seq == seq:
            return
        await asyncio.sleep(0.01)


def test_far_scene_streams_with_precision(live_server, cells):
    far = make_tiny_scene(offset=1e5)

    async def main():
        s = await Session.connect(live_server, "tiny_far", "test_near", NEAR, prefetch=False)
        c = (np.asarray(centre(cells, 2)) + [1e5, 0, 1e5]).tolist()
        await s.send_pose(0, 0.0, c, (1, 0, 0))
        await s.wait_cell(2, TIMEOUT)
        await s.close()
        return s

    s = run(main())
    ids, tris, _ = s.store.arrays()
    assert len(ids) > 0
    # float32 offsets from a per-chunk origin: sub-millimetre at 100 km from the origin.
    assert np.abs(tris - far.triangles(ids)).max() < 1e-4


def test_same_cell_poses_send_one_stream(live_server, cells, ws_endpoint):
    async def main():
        async with connect(ws_endpoint) as ws:
            await ws.send(hello())
            await recv_until(ws, "welcome")
            c = np.asarray(centre(cells, 6))
            for i in range(5):  # head bob inside one cell
                await ws.send(pose(i, c + [0.1 * i, 0.05 * i, -0.1 * i]))
            msgs = await recv_until(ws, "cell_end")
            await ws.send(pose(9, centre(cells, 7)))
            msgs += await recv_until(ws, "cell_end")
            return msgs

    msgs = run(main())
    begins = [m for m in msgs if getattr(m, "type", None) == "cell_begin"]
    assert [(b.cell, b.seq) for b in begins] == [(6, 0), (7, 9)]
    frames = [decode_geometry(m) for m in msgs if isinstance(m, bytes)]
    assert {f.cell for f in frames} <= {6, 7}
    assert all(f.seq in (0, 9) for f in frames)


def test_compute_failure_is_not_fatal(live_server, cells, ws_endpoint):
    async def main():
        async with connect(ws_endpoint) as ws:
            await ws.send(hello(core="test_fail", params={}))
            await recv_until(ws, "welcome")
            await ws.send(pose(0, centre(cells, 0)))
            err = (await recv_until(ws, "error"))[-1]
            await ws.send(pose(1, centre(cells, 1)))
            err2 = (await recv_until(ws, "error"))[-1]
            return err, err2

    err, err2 = run(main())
    assert err.code == "compute_failed" and not err.fatal and err.seq == 0
    assert "deliberate failure" in err.message
    assert err2.seq == 1  # the session went on


# --------------------------------------------------------------------------- non-fatal errors
def test_non_fatal_errors_keep_the_session(live_server, cells, ws_endpoint):
    nan_pose = ('{"type": "pose", "seq": 1, "t": 0, "position": [NaN, 1.7, 1], '
                '"forward": [0, 0, -1]}')

    async def main():
        async with connect(ws_endpoint) as ws:
            await ws.send(hello())
            await recv_until(ws, "welcome")
            errors = []
            await ws.send(nan_pose)
            errors.append((await recv_until(ws, "error"))[-1])
            await ws.send('{"type": "teleport", "to": [1, 2, 3]}')
            errors.append((await recv_until(ws, "error"))[-1])
            await ws.send('{"type": "pose", "seq": 2}')
            errors.append((await recv_until(ws, "error"))[-1])
            await ws.send(pose(3, [500.0, 1.7, 500.0]))  # outside every cell
            errors.append((await recv_until(ws, "error"))[-1])
            await ws.send(pose(4, [501.0, 1.7, 500.0]))  # still outside: no repeat
            await ws.send(pose(5, centre(cells, 3)))
            msgs = await recv_until(ws, "cell_end")
            return errors, msgs

    errors, msgs = run(main())
    assert [e.code for e in errors] == ["invalid_pose", "unknown_type", "invalid_pose",
                                        "outside_grid"]
    assert not any(e.fatal for e in errors)
    assert errors[0].seq == 1 and errors[3].seq == 3
    assert not [m for m in msgs if getattr(m, "type", None) == "error"]
    assert msgs[-1].cell == 3 and msgs[-1].seq == 5


@pytest.mark.parametrize("bad_seq", [2**32, 2**64, -1])
def test_pose_seq_past_uint32_is_refused_and_the_session_goes_on(live_server, cells,
                                                                 ws_endpoint, bad_seq):
    """Frames carry ``seq`` as uint32: a pose whose seq the wire cannot carry is answered with a
    non-fatal ``invalid_pose`` (it used to reach the frame encoder and close the session with
    1011 ``internal``), and the next valid pose streams its cell."""
    bad = json.dumps({"type": "pose", "seq": bad_seq, "t": 0,
                      "position": centre(cells, 2), "forward": [0, 0, -1]})

    async def main():
        async with connect(ws_endpoint) as ws:
            await ws.send(hello())
            await recv_until(ws, "welcome")
            await ws.send(bad)
            err = (await recv_until(ws, "error"))[-1]
            await ws.send(pose(2**32 - 1, centre(cells, 2)))
            return err, await recv_until(ws, "cell_end")

    err, msgs = run(main())
    assert err.code == "invalid_pose" and not err.fatal and err.seq is None
    assert "seq" in err.message
    assert not [m for m in msgs if getattr(m, "type", None) == "error"]
    end = msgs[-1]
    assert (end.cell, end.seq, end.partial) == (2, 2**32 - 1, False)
    frames = [decode_geometry(m) for m in msgs if isinstance(m, bytes)]
    assert frames and all(f.seq == 2**32 - 1 for f in frames)


BAD_AFTER_WELCOME = [
    ('{"type": "pose", "seq": 0, "t": 0, "pos', "bad_json"),
    ("[1, 2, 3]", "bad_json"),
    ('{"type": "teleport", "to": [1, 2, 3]}', "unknown_type"),
    (b"\x00\x01binary", "binary_unsupported"),
    (json.dumps({"type": "pose", "pad": "y" * 5000}), "too_big"),
]


def test_bad_messages_after_welcome_keep_the_session(live_server, cells, ws_endpoint):
    """Malformed JSON, an unknown type, a binary frame and an oversized text message after
    ``welcome`` are each answered with a non-fatal error, and the same session then streams the
    next cell it walks into."""

    async def main():
        out = []
        async with connect(ws_endpoint) as ws:
            await ws.send(hello())
            await recv_until(ws, "welcome")
            for seq, (bad, _) in enumerate(BAD_AFTER_WELCOME):
                await ws.send(bad)
                err = (await recv_until(ws, "error"))[-1]
                await ws.send(pose(seq, centre(cells, seq)))
                msgs = await recv_until(ws, "cell_end")
                out.append((err, msgs))
        return out

    out = run(main())
    for (_, code), (err, msgs) in zip(BAD_AFTER_WELCOME, out, strict=True):
        assert err.code == code and not err.fatal, err
        end = msgs[-1]
        assert (end.cell, end.seq, end.partial) == (msgs[-1].seq, msgs[-1].seq, False)
        assert not [m for m in msgs if getattr(m, "type", None) == "error"]
        frames = [decode_geometry(m) for m in msgs if isinstance(m, bytes)]
        got = np.sort(np.concatenate([f.ids for f in frames])) if frames else []
        begin = next(m for m in msgs if getattr(m, "type", None) == "cell_begin")
        assert len(got) == begin.new


def test_abuse_past_the_limit_closes_the_session(ws_endpoint):
    from protocol.codes import BAD_MESSAGE_LIMIT

    async def main():
        async with connect(ws_endpoint) as ws:
            await ws.send(hello())
            await recv_until(ws, "welcome")
            for _ in range(BAD_MESSAGE_LIMIT + 1):
                await ws.send("{garbage")
            msgs = await asyncio.wait_for(collect_until_close(ws), TIMEOUT)
            return msgs, ws.close_code

    msgs, close_code = run(main())
    errors = [m for m in msgs if getattr(m, "type", None) == "error"]
    assert [e.code for e in errors[:-1]] == ["bad_json"] * BAD_MESSAGE_LIMIT
    assert not any(e.fatal for e in errors[:-1])
    assert errors[-1].code == "too_many_errors" and errors[-1].fatal
    assert close_code == 1008


# --------------------------------------------------------------------------- fatal errors
@pytest.mark.parametrize(
    "frames, code, close",
    [
        (['{"type": "pose", "seq": 0, "t": 0, "position": [0, 0, 0], "forward": [0, 0, 1]}'],
         "expected_hello", 1008),
        (["{nope"], "bad_json", 1008),
        (['{"type": "hello"}'], "invalid_hello", 1008),
        (['{"type": "hello", "scene": "tiny", "colour": 1}'], "invalid_hello", 1008),
        ([hello(version=99)], "version_mismatch", 4001),
        ([hello(scene="nope")], "unknown_scene", 4004),
        ([hello(scene="../secret_outside")], "unknown_scene", 4004),
        ([hello(scene="outside")], "unknown_scene", 4004),
        ([hello(core="nope")], "unknown_core", 4005),
        ([hello(params={"radius": -1})], "bad_params", 4022),
        ([hello(params={"bogus": 1})], "bad_params", 4022),
        ([hello(core="test_picky")], "unsupported_scene", 4023),
        ([hello(scene="broken")], "scene_load_failed", 1011),
        ([b"\x00\x01binary"], "binary_unsupported", 1003),
        (["x" * 5000], "too_big", 1009),
        ([hello(), hello()], "duplicate_hello", 1008),
    ],
)
def test_fatal_errors_close_with_named_codes(ws_endpoint, frames, code, close):
    """Before ``welcome`` every bad message ends the session (nothing is agreed yet); after it
    only a second hello does (see ``test_bad_messages_after_welcome_keep_the_session``)."""
    msgs, close_code = run(fatal_after(ws_endpoint, *frames))
    errors = [m for m in msgs if getattr(m, "type", None) == "error"]
    assert len(errors) == 1, msgs
    assert errors[0].code == code and errors[0].fatal
    assert close_code == close


def test_hello_timeout(ws_endpoint, server_app):
    state = server_app.state.server
    saved = state.settings
    # Sessions read the settings when they start: a short timeout for this one only.
    state.settings = saved.model_copy(update={"hello_timeout": 0.5})

    async def main():
        async with connect(ws_endpoint) as ws:
            t0 = asyncio.get_running_loop().time()
            msgs = await asyncio.wait_for(collect_until_close(ws), 30)
            return msgs, ws.close_code, asyncio.get_running_loop().time() - t0

    try:
        msgs, close_code, waited = run(main())
    finally:
        state.settings = saved
    assert waited >= 0.45
    assert msgs[-1].code == "expected_hello" and close_code == 1008


def test_bye_closes_normally(ws_endpoint):
    msgs, close_code = run(fatal_after(ws_endpoint, hello(), '{"type": "bye"}'))
    assert [m.type for m in msgs] == ["welcome"]
    assert close_code == 1000


def test_huge_message_is_refused_without_harm(ws_endpoint):
    async def main():
        async with connect(ws_endpoint, max_size=None) as ws:
            await ws.send(hello())
            await recv_until(ws, "welcome")
            try:
                await ws.send("z" * (4 << 20))  # beyond even the WebSocket library's cap
            except websockets.ConnectionClosed:
                pass
            await collect_until_close(ws)
            return ws.close_code

    assert run(main()) == 1009


def test_other_sessions_are_unaffected(live_server, cells, ws_endpoint):
    async def main():
        good = await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
        await good.send_pose(0, 0.0, centre(cells, 4), (0, 0, 1))
        await good.wait_cell(4, TIMEOUT)
        # Misbehaving clients come and go...
        for frames in (["{nope"], [b"\x00"], [hello(), hello()], ["y" * 9000]):
            _, code = await fatal_after(ws_endpoint, *frames)
            assert code in (1003, 1008, 1009)
        async with connect(ws_endpoint) as rude:
            await rude.send(hello())
        # ... while the good session keeps streaming.
        await good.send_pose(1, 0.1, centre(cells, 5), (0, 0, 1))
        await good.wait_cell(5, TIMEOUT)
        assert not good.closed and not good.errors
        await good.close()

    run(main())


def test_session_count_returns_to_zero(live_server, cells):
    async def main():
        sessions = [await Session.connect(live_server, "tiny", "test_near", NEAR, prefetch=False)
                    for _ in range(3)]
        h = httpx.get(live_server + "/health", timeout=60).json()
        for s in sessions:
            await s.close()
        return h

    during = run(main())
    assert during["sessions"] >= 3
    for _ in range(200):
        if httpx.get(live_server + "/health", timeout=60).json()["sessions"] == 0:
            break
        time.sleep(0.05)
    assert httpx.get(live_server + "/health", timeout=60).json()["sessions"] == 0


def test_connect_refusal_raises_session_error(live_server):
    async def main():
        with pytest.raises(SessionError) as exc:
            await Session.connect(live_server, "nope", "test_near")
        return exc.value

    err = run(main())
    assert err.code == "unknown_scene" and err.close_code == 4004


# --------------------------------------------------------------------------- real core
def test_generated_scene_stream_equals_http_pvs(live_server, server_app):

    gens = sorted(server_app.state.server.settings.generated)
    name = "rooms" if "rooms" in gens else gens[0]
    params = {"resolution": 32, "samples": 4}
    with httpx.Client(base_url=live_server, timeout=120) as http:
        cells = http.get(f"/scenes/{name}/cells").json()["cells"]
        pick = [0, min(1, len(cells) - 1)]
        expected = {c: http.get(f"/scenes/{name}/cells/{c}/pvs",
                                params={"core": "sampling", **params}).json()["triangle_ids"]
                    for c in pick}

    async def main():
        s = await Session.connect(live_server, name, "sampling", params, prefetch=False)
        for seq, c in enumerate(pick):
            await s.send_pose(seq, float(seq), centre(cells, c), (1, 0, 0))
            await s.wait_cell(c, 120)
        await s.close()
        return s

    s = run(main())
    assert not s.errors and not s.local_errors
    union = sorted(set().union(*map(set, expected.values())))
    assert s.store.ids.tolist() == union
    got0 = np.concatenate(s.cells[pick[0]].ids).tolist()
    assert sorted(got0) == expected[pick[0]]
