"""Scene files that fail to load, on the real server: every answer (HTTP error bodies, WebSocket
error messages) names the scene and what is wrong, never a path of the server's file system;
files over the server's ``max_scene_triangles`` are refused naming the limit; ``/health`` says
whether a disk cache is configured, not where."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import websockets
from websockets.asyncio.client import connect

from protocol.messages import Error, parse_server_message
from tests.conftest import serving, write_scene_files

#: The limit of the server under test: box.obj (12 triangles) is over it, quad.obj (2) is not.
MAX_TRIANGLES = 10
TIMEOUT = 60.0
QUAD = "v 0 0 0\nv 4 0 0\nv 4 0 4\nv 0 0 4\nf 1 3 2\nf 1 4 3\n"


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A scenes folder of failures: a malformed sidecar, a garbage file, a file deleted after
    it was listed, one over the triangle limit (box.obj), and quad.obj, within it."""
    scenes = tmp_path_factory.mktemp("scene_errors") / "scenes"
    write_scene_files(scenes)
    (scenes / "badside.obj").write_text(QUAD)
    (scenes / "badside.json").write_text('{"walk": {"rects": [[0, 0')
    (scenes / "garbage.glb").write_bytes(bytes(range(256)) * 16)
    (scenes / "gone.obj").write_text(QUAD)
    (scenes / "quad.obj").write_text(QUAD)
    (scenes / "quad.json").write_text('{"walk": {"rects": [[0, 0, 4, 4, 0]]}}')
    return scenes


@pytest.fixture(scope="module")
def server(settings, folder: Path) -> Iterator[tuple[str, Path]]:
    """(base URL, disk cache folder) of a live server on ``folder`` with a small triangle
    limit and a disk cache."""
    cache = folder.parent / "disk_cache"
    with serving(settings, scenes_dir=folder, cache_dir=cache,
                 max_scene_triangles=MAX_TRIANGLES) as (url, _):
        with httpx.Client(base_url=url, timeout=120) as http:
            assert http.get("/scenes").status_code == 200  # lists gone.obj while it exists
        (folder / "gone.obj").unlink()
        yield url, cache


def _paths(folder: Path) -> list[str]:
    """Every spelling of the server's folders an answer must not show."""
    roots = {folder, folder.resolve(), folder.parent, folder.parent.resolve()}
    return sorted(str(p) for p in roots)


def _assert_no_path(text: str, folder: Path) -> None:
    for p in _paths(folder):
        assert p not in text, f"answer shows the path {p}: {text}"


async def _hello(url: str, scene: str) -> tuple[list, int | None]:
    """Every message answering a hello for ``scene`` until the server closes, and the close
    code."""
    out = []
    async with connect(url.replace("http://", "ws://") + "/ws", open_timeout=TIMEOUT) as ws:
        await ws.send(json.dumps({"type": "hello", "scene": scene}))
        try:
            async for raw in ws:
                out.append(raw if isinstance(raw, bytes) else parse_server_message(raw))
        except websockets.ConnectionClosed:
            pass
        return out, ws.close_code


def _ws_error(url: str, scene: str) -> tuple[Error, int | None]:
    msgs, close = asyncio.run(asyncio.wait_for(_hello(url, scene), 120))
    errors = [m for m in msgs if isinstance(m, Error)]
    assert len(errors) == 1, msgs
    return errors[0], close


FAILURES = [
    ("badside", "badside.json is not valid JSON"),
    ("garbage", "cannot read garbage.glb"),
    ("gone", "no scene file 'gone.obj'"),
]


@pytest.mark.parametrize("scene, why", FAILURES)
def test_http_load_failures_name_the_scene_not_a_path(server, folder, scene, why):
    url, _ = server
    with httpx.Client(base_url=url, timeout=120) as http:
        for r in (http.get(f"/scenes/{scene}"),
                  http.get(f"/scenes/{scene}/cells/0/pvs"),
                  http.post(f"/scenes/{scene}/pvs", json={"box": [[0, 0, 0], [1, 1, 1]]})):
            assert r.status_code == 500, r.text
            _assert_no_path(r.text, folder)
            error = r.json()["error"]
            assert error["code"] == "scene_load_failed"
            assert f"scene {scene!r}" in error["message"] and why in error["message"]


@pytest.mark.parametrize("scene, why", FAILURES)
def test_ws_load_failures_name_the_scene_not_a_path(server, folder, scene, why):
    error, close = _ws_error(server[0], scene)
    assert error.code == "scene_load_failed" and error.fatal and close == 1011
    _assert_no_path(error.message, folder)
    assert f"scene {scene!r}" in error.message and why in error.message


def test_scene_over_the_triangle_limit_is_refused_naming_the_limit(server, folder):
    url, _ = server
    with httpx.Client(base_url=url, timeout=120) as http:
        r = http.get("/scenes/box")
        assert r.status_code == 500, r.text
        error = r.json()["error"]
        assert error["code"] == "scene_load_failed"
        ws_error, close = _ws_error(url, "box")
        assert ws_error.code == "scene_load_failed" and close == 1011
        for message in (error["message"], ws_error.message):
            _assert_no_path(message, folder)
            assert "scene 'box'" in message and "12 triangles" in message
            assert f"limit of {MAX_TRIANGLES}" in message and "max_scene_triangles" in message
        # Within the limit a file loads.
        quad = http.get("/scenes/quad")
        assert quad.status_code == 200, quad.text
        assert quad.json()["triangles"] == 2


def test_health_says_a_disk_cache_is_configured_not_where(server, folder):
    url, cache = server
    r = httpx.get(url + "/health", timeout=60)
    assert r.status_code == 200
    assert "disk" in r.json()["compute"]
    for p in [*_paths(folder), str(cache), str(cache.resolve())]:
        assert p not in r.text
