"""The viewer's files over HTTP (``server.viewer_files``): the page, its modules, three.js from
the npm install, the redirect that keeps a link's query, and the cell listing the page starts
from."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from server.viewer_files import REPO_THREE_DIR, VIEWER_DIR, three_dir, viewer_url


@pytest.fixture(scope="module")
def http(live_server: str):
    with httpx.Client(base_url=live_server, timeout=60) as client:
        yield client


def test_viewer_link_redirects_to_the_page_keeping_its_query(http):
    r = http.get("/viewer?scene=rooms&core=auto")
    assert r.status_code == 307 and r.headers["location"] == "/viewer/?scene=rooms&core=auto"
    page = http.get("/viewer/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '"three": "/viewer/vendor/three.module.js"' in page.text
    assert 'src="/viewer/main.js"' in page.text


def test_every_module_is_served_as_javascript(http):
    names = sorted(p.name for p in VIEWER_DIR.glob("*.js"))
    assert {"main.js", "decode.js", "connection.js", "scene_store.js", "overlay.js",
            "controls.js", "render.js"} <= set(names)
    for name in names:
        r = http.get(f"/viewer/{name}")
        assert r.status_code == 200 and "javascript" in r.headers["content-type"], name
        assert r.text == (VIEWER_DIR / name).read_text()


def test_three_is_served_from_the_npm_install(http):
    assert (REPO_THREE_DIR / "three.module.js").is_file(), "run npm ci (scripts/setup.sh)"
    r = http.get("/viewer/vendor/three.module.js")
    assert r.status_code == 200 and "javascript" in r.headers["content-type"]
    assert r.content == (REPO_THREE_DIR / "three.module.js").read_bytes()
    # The module imports its core from beside it.
    assert http.get("/viewer/vendor/three.core.js").status_code == 200
    missing = http.get("/viewer/no_such_module.js")
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"


def test_three_dir_prefers_the_setting_and_needs_the_module(tmp_path, settings):
    assert three_dir(settings.model_copy(update={"viewer_three_dir": tmp_path})) == REPO_THREE_DIR
    (tmp_path / "three.module.js").write_text("export {};")
    assert three_dir(settings.model_copy(update={"viewer_three_dir": tmp_path})) == tmp_path


def test_viewer_url_names_scene_and_core():
    assert viewer_url("http://h:1/") == "http://h:1/viewer/"
    assert viewer_url("http://h:1", "my rooms", "auto") == \
        "http://h:1/viewer/?scene=my%20rooms&core=auto"


def test_cell_listing_gives_each_cell_its_floor_and_a_walk_point(http):
    body = http.get("/scenes/tiny/cells").json()
    for c in body["cells"]:
        (x0, y0, z0), (x1, y1, z1) = c["box"]
        wx, wy, wz = c["walk"]
        assert x0 <= wx <= x1 and z0 <= wz <= z1 and y0 <= wy <= y1
        assert c["floor"] <= y0


def test_the_viewer_dir_is_package_data():
    text = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
    assert 'server = ["viewer/*.html", "viewer/*.js"]' in text
