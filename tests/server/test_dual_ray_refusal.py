"""The dual-ray core (2.5D scenes only) through the real server: a scene that is not 2.5D is
refused with the reason (HTTP 422, the WebSocket hello's fatal error), and ``auto`` picks it
for a city at big cells only. Real uvicorn server on loopback."""

from __future__ import annotations

import asyncio

import httpx
import pytest
from websockets.asyncio.client import connect

from protocol.messages import Hello, dump_message, parse_server_message
from server.resolve import choose_core
from visibility.cores.base import choose_core as registry_choose_core
from visibility.generators import make_scene


def _says_why_not_2_5d(message: str) -> None:
    assert "2.5D" in message, message
    # Why: the measured share under overhangs and where the first one is.
    assert "overhang" in message and "%" in message and "first found" in message, message


def test_http_refuses_a_scene_that_is_not_2_5d(live_server):
    r = httpx.get(f"{live_server}/scenes/village/cells/0/pvs", params={"core": "dual_ray"},
                  timeout=120)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["code"] == "unsupported_scene"
    _says_why_not_2_5d(err["message"])


def test_http_serves_a_city(live_server):
    r = httpx.post(f"{live_server}/scenes/city/pvs", timeout=120,
                   json={"box": [[-20.0, 1.5, -20.0], [20.0, 1.9, 20.0]], "core": "dual_ray"})
    assert r.status_code == 200, r.text
    assert r.json()["core"] == "dual_ray"


def test_websocket_hello_is_refused_the_same_way(live_server):
    url = live_server.replace("http://", "ws://") + "/ws"

    async def main():
        async with connect(url, open_timeout=60) as ws:
            await ws.send(dump_message(Hello(scene="village", core="dual_ray", params={},
                                             prefetch=False)))
            msgs = []
            try:
                async for raw in ws:
                    if isinstance(raw, str):
                        msgs.append(parse_server_message(raw))
            except Exception:
                pass
            return msgs

    msgs = asyncio.run(asyncio.wait_for(main(), 120))
    errors = [m for m in msgs if getattr(m, "type", None) == "error"]
    assert len(errors) == 1 and errors[0].fatal, msgs
    assert errors[0].code == "unsupported_scene"
    assert not [m for m in msgs if getattr(m, "type", None) == "welcome"]
    _says_why_not_2_5d(errors[0].message)


@pytest.mark.parametrize("cell_size", [25.0, 100.0, 300.0])
def test_auto_picks_dual_ray_for_a_city_at_big_cells(cell_size):
    city = make_scene("city", triangles=10_000)
    name, why = choose_core(city, cell_size)
    assert name == "dual_ray" and "big cells" in why
    assert registry_choose_core(city, cell_size)[0] == "dual_ray"


@pytest.mark.parametrize("name", ["village", "rooms"])
@pytest.mark.parametrize("cell_size", [0.3, 4.0, 100.0, None])
def test_auto_never_picks_it_where_it_does_not_fit(name, cell_size):
    assert choose_core(make_scene(name, triangles=10_000), cell_size)[0] != "dual_ray"


@pytest.mark.parametrize("cell_size", [0.3, 4.0, None])
def test_auto_leaves_small_city_cells_to_the_other_cores(cell_size):
    assert choose_core(make_scene("city", triangles=10_000), cell_size)[0] != "dual_ray"


def test_a_city_served_at_big_cells_is_answered_by_dual_ray_under_auto(settings):
    # PVS_CELL_SIZE (here the settings' cell_size) sets the grid; auto weighs the scene at it.
    from tests.conftest import serving

    with serving(settings, cell_size=50.0) as (url, _):
        r = httpx.post(f"{url}/scenes/city/pvs", timeout=120,
                       json={"box": [[-25.0, 1.0, -25.0], [25.0, 3.0, 25.0]], "core": "auto"})
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["core"] == "dual_ray" and "big cells" in body["chosen_because"]
        assert len(body["triangle_ids"]) > 0
