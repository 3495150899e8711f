"""A worker that dies mid-computation, through the real server on loopback: the pool replaces
it, the job runs once more, and the HTTP caller and the walker both get their answer."""

from __future__ import annotations

import asyncio
import threading

import httpx
import numpy as np
import pytest
from websockets.asyncio.client import connect

from protocol.frames import decode_geometry
from protocol.messages import Hello, Pose, dump_message, parse_server_message
from server.pool import WorkerDied
from tests.conftest import NearCore, make_tiny_scene, near_ids, serving
from visibility.cores import base as core_base

TINY = make_tiny_scene()
RADIUS = 4.5


class DiesOncePerCell(NearCore):
    """Kills the worker running it on the first computation of each cell box."""

    name = "test_dies_once"
    _lock = threading.Lock()
    died: set = set()

    def _compute(self, scene, cell, params):
        key = tuple(np.asarray(cell.box).ravel().tolist())
        with self._lock:
            first = key not in self.died
            self.died.add(key)
        if first:
            raise WorkerDied("killed mid-computation")
        return super()._compute(scene, cell, params)


@pytest.fixture(scope="module")
def server(settings, registered_test_cores):
    core_base.register(DiesOncePerCell)
    try:
        with serving(settings, {"tiny": make_tiny_scene()}, workers=1) as served:
            yield served
    finally:
        core_base.unregister(DiesOncePerCell.name)


def _pool(app) -> dict:
    return app.state.server.compute.stats()["pool"]


def test_http_answer_arrives_after_a_worker_death(server):
    url, app = server
    with httpx.Client(base_url=url, timeout=60) as http:
        box = np.asarray(http.get("/scenes/tiny/cells").json()["cells"][2]["box"])
        r = http.get("/scenes/tiny/cells/2/pvs", params={"core": DiesOncePerCell.name,
                                                          "radius": RADIUS})
        assert r.status_code == 200, r.text
        assert r.json()["triangle_ids"] == near_ids(TINY, box, RADIUS).tolist()
        assert not r.json()["cached"]
        metrics = http.get("/metrics").text
    pool = _pool(app)
    assert pool["replaced"] >= 1 and pool["retried"] >= 1
    assert "pvs_worker_replacements_total" in metrics
    # The one worker was replaced: the pool still computes (another cell, another death).
    with httpx.Client(base_url=url, timeout=60) as http:
        r = http.get("/scenes/tiny/cells/6/pvs", params={"core": DiesOncePerCell.name,
                                                          "radius": RADIUS})
    assert r.status_code == 200, r.text
    assert _pool(app)["replaced"] == pool["replaced"] + 1


def test_walker_gets_its_cell_after_a_worker_death(server):
    url, app = server
    with httpx.Client(base_url=url, timeout=60) as http:
        cells = http.get("/scenes/tiny/cells").json()["cells"]
    box = np.asarray(cells[5]["box"])
    before = _pool(app)["replaced"]

    async def main():
        async with connect(url.replace("http://", "ws://") + "/ws") as ws:
            await ws.send(dump_message(Hello(scene="tiny", core=DiesOncePerCell.name,
                                             params={"radius": RADIUS}, prefetch=False)))
            msgs = []
            await ws.send(dump_message(Pose(seq=0, t=0.0, position=tuple(box.mean(axis=0)),
                                            forward=(0.0, 0.0, -1.0))))
            while True:
                raw = await asyncio.wait_for(ws.recv(), 60)
                msg = raw if isinstance(raw, bytes) else parse_server_message(raw)
                msgs.append(msg)
                if getattr(msg, "type", None) == "cell_end":
                    return msgs

    msgs = asyncio.run(asyncio.wait_for(main(), 120))
    assert not [m for m in msgs if getattr(m, "type", None) == "error"]
    end = msgs[-1]
    assert end.cell == 5 and not end.partial
    ids = np.concatenate([decode_geometry(m).ids for m in msgs if isinstance(m, bytes)])
    np.testing.assert_array_equal(np.sort(ids), near_ids(TINY, box, RADIUS))
    assert _pool(app)["replaced"] == before + 1
