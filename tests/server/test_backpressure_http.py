"""Backpressure (a client that stops reading is closed with ``slow_client``), /metrics, binary
and segment PVS answers, against the real server on loopback."""

from __future__ import annotations

import asyncio
import socket

import httpx
import numpy as np
import pytest
from websockets.asyncio.client import connect

from protocol.frames import decode_geometry, frame_bytes
from protocol.messages import Hello, Pose, dump_message, parse_server_message
from tests.conftest import TINY_WALK, make_tiny_scene, near_ids, serving
from visibility.scene import Scene, WalkArea

TINY = make_tiny_scene()


def _big_scene(n: int = 200_000) -> Scene:
    """``n`` small random triangles over the tiny walk area (a stream of megabytes)."""
    rng = np.random.default_rng(0)
    base = rng.uniform([0, 0, 0], [16, 3, 8], (n, 1, 3))
    v = (base + rng.normal(scale=0.05, size=(n, 3, 3))).reshape(-1, 3)
    f = np.arange(3 * n).reshape(n, 3)
    return Scene(vertices=v, faces=f, object_ids=np.arange(n, dtype=np.int32),
                 colors=rng.integers(0, 256, (n, 3), dtype=np.uint8), name="big",
                 walk=WalkArea(rects=np.array(TINY_WALK)))


@pytest.fixture(scope="module")
def slow_server(settings, registered_test_cores):
    """A server that closes clients whose sends wait over 1 s. The big scene streams ~9 MB,
    more than loopback socket buffers (up to ~4 MB) hold."""
    with serving(settings, {"big": _big_scene()}, send_timeout=1.0, send_queue_frames=4,
                 max_frame_bytes=64 * 1024) as served:
        yield served


def test_client_that_stops_reading_is_closed_with_slow_client(slow_server):
    url, app = slow_server
    state = app.state.server

    async def main():
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect(("127.0.0.1", int(url.rsplit(":", 1)[1])))
        ws = await connect(url.replace("http", "ws") + "/ws", sock=sock, max_queue=1,
                           compression=None, max_size=None)
        await ws.send(dump_message(Hello(scene="big", core="test_near",
                                         params={"radius": 100.0})))
        assert parse_server_message(await ws.recv()).type == "welcome"
        await ws.send(dump_message(Pose(seq=0, t=0, position=(2.0, 1.7, 2.0),
                                        forward=(0, 0, -1))))
        # Stop reading: the server's sends back up until its send timeout closes us.
        for _ in range(200):
            await asyncio.sleep(0.1)
            if state.counters["slow_clients"]:
                break
        closed_for_slowness = state.counters["slow_clients"]
        codes = []
        try:
            async for _ in ws:
                pass
        except Exception:
            pass
        codes.append(ws.close_code)
        return closed_for_slowness, codes

    slow, codes = asyncio.run(asyncio.wait_for(main(), 120))
    assert slow == 1
    assert codes[0] in (4008, 1006)  # 4008 when the close frame got through the backlog
    # The session is gone and memory with it; the server serves others.
    for _ in range(50):
        if not state.sessions:
            break
        import time

        time.sleep(0.1)
    assert not state.sessions
    assert httpx.get(url + "/health", timeout=30).status_code == 200


# --------------------------------------------------------------------------- /metrics
def test_metrics_prometheus_text(live_server):
    with httpx.Client(base_url=live_server, timeout=60) as http:
        http.get("/scenes/tiny/cells/4/pvs", params={"core": "test_near", "radius": 2.25})
        r = http.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    values = {}
    for line in r.text.splitlines():
        if line and not line.startswith("#"):
            name, _, v = line.rpartition(" ")
            values[name] = float(v)
    for name in ("pvs_computations_total", "pvs_cache_hits_total", "pvs_bytes_sent_total",
                 "pvs_sessions", "pvs_stalls_total", "pvs_computation_seconds_count",
                 "pvs_sessions_opened_total"):
        assert name in values, name
    assert values["pvs_computations_total"] >= 1
    assert values["pvs_computation_seconds_count"] >= 1


# --------------------------------------------------------------------------- HTTP additions
def test_binary_ids_and_geometry_answers(live_server):
    box = np.array(httpx.get(live_server + "/scenes/tiny/cells", timeout=60).json()
                   ["cells"][3]["box"])
    expected = near_ids(TINY, box, 4.5)
    q = {"core": "test_near", "radius": 4.5}
    with httpx.Client(base_url=live_server, timeout=60) as http:
        r = http.get("/scenes/tiny/cells/3/pvs", params=q,
                     headers={"Accept": "application/octet-stream"})
        assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
        np.testing.assert_array_equal(np.frombuffer(r.content, "<i4"), expected)
        assert int(r.headers["x-pvs-count"]) == len(expected)
        g = http.get("/scenes/tiny/cells/3/pvs", params=q,
                     headers={"Accept": "application/vnd.pvs.geometry"})
        assert g.status_code == 200
    data, ids, p = g.content, [], 0
    while p < len(data):
        n = int.from_bytes(data[p + 24:p + 28], "little")
        chunk = decode_geometry(data[p:p + frame_bytes(n)])
        np.testing.assert_allclose(chunk.triangles, TINY.triangles(chunk.ids), atol=1e-5)
        ids.append(chunk.ids)
        p += frame_bytes(n)
    np.testing.assert_array_equal(np.concatenate(ids), expected)


def test_segment_pvs_and_validation(live_server):
    with httpx.Client(base_url=live_server, timeout=60) as http:
        seg = [[1.0, 1.7, 1.0], [3.0, 1.7, 1.0]]
        r = http.post("/scenes/tiny/pvs", json={"segment": seg, "core": "test_near",
                                                "params": {"radius": 2.5}})
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["box"] == seg and body["cell"] is None
        assert body["triangle_ids"] == near_ids(TINY, np.array(seg), 2.5).tolist()
        # Backwards segments are fine (a segment has no min/max order).
        r2 = http.post("/scenes/tiny/pvs", json={"segment": seg[::-1], "core": "test_near",
                                                 "params": {"radius": 2.5}})
        assert r2.json()["triangle_ids"] == body["triangle_ids"]
        for bad in ({}, {"box": [[0, 0, 0], [1, 1, 1]], "segment": seg},
                    {"segment": [[0, 0, 0]]}):
            r = http.post("/scenes/tiny/pvs", json=bad)
            assert r.status_code == 422 and r.json()["error"]["code"] == "validation"
        r = http.get("/scenes/tiny/cells/99999999999/pvs", params={"core": "test_near"})
        assert r.status_code == 404 and r.json()["error"]["code"] == "unknown_cell"
        r = http.get("/scenes/tiny/cells/1/pvs", params={"core": "test_near",
                                                          "granularity": "pixel"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "bad_params"
        r = http.get("/scenes/tiny/cells/1/pvs", params={"core": "test_near",
                                                          "granularity": "object"})
        assert r.status_code == 200 and r.json()["granularity"] == "object"
        r = http.get("/scenes/tiny/cells/1/pvs", params={"core": "test_near",
                                                          "resolution": "1000000"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "bad_params"


def test_diagonal_segment_is_answered_exactly_or_refused(live_server):
    """A diagonal segment goes to the core's own segment solver (the answer equals the core's
    ``compute_segment``), and a box-only core refuses it with ``unsupported_region``."""
    from visibility.cores.base import get_core

    seg = [[1.0, 1.7, 1.0], [3.0, 1.9, 2.5]]
    core = get_core("from_segment")
    want = core.compute_segment(TINY, *np.array(seg), core.make_params(resolution=32))
    with httpx.Client(base_url=live_server, timeout=120) as http:
        r = http.post("/scenes/tiny/pvs", json={"segment": seg, "core": "from_segment",
                                                "params": {"resolution": 32}})
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["segment"] == seg and body["cell"] is None
        assert body["box"] == [[1.0, 1.7, 1.0], [3.0, 1.9, 2.5]]
        assert body["triangle_ids"] == want.triangle_ids.tolist()
        r = http.post("/scenes/tiny/pvs", json={"segment": seg, "core": "test_near",
                                                "params": {"radius": 2.5}})
        assert r.status_code == 422 and r.json()["error"]["code"] == "unsupported_region"
        # The server is still fine.
        assert http.get("/health").status_code == 200
