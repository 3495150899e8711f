"""The server decides 2.5D from each loaded scene's geometry (visibility.scene_analysis) when no
meta states it: the scene description says whether and why, 2.5D-only cores are offered and
chosen for such scenes and refused elsewhere. Real uvicorn server on loopback."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from server.resolve import choose_core, core_fits
from tests.conftest import NearCore, _box, make_tiny_scene
from visibility.cores import base as core_base
from visibility.scene import Scene


class FlatCore(NearCore):
    """A 2.5D-only stand-in (what ``dual_ray`` will be)."""

    name = "test_flat"
    requires_2_5d = True


def roofed(scene: Scene) -> Scene:
    """``scene`` under a 0.2 m slab 3 m up covering it all: open space under a surface."""
    v, f = _box((-3.0, 3.0, -3.0), (19.0, 3.2, 11.0))
    n = len(scene.vertices)
    faces = np.concatenate([scene.faces, f + n])
    return Scene(vertices=np.concatenate([scene.vertices, v]), faces=faces,
                 object_ids=np.concatenate([scene.object_ids, np.full(len(f), 999, np.int32)]),
                 colors=np.concatenate([scene.colors, np.full((len(f), 3), 90, np.uint8)]),
                 name="tiny_roofed", walk=scene.walk)


@pytest.fixture(scope="module")
def server_app(settings, registered_test_cores) -> Iterator:
    """The app with "tiny" (boxes on a ground: 2.5D by geometry), "tiny_roofed" (not) and the
    2.5D-only ``test_flat`` core registered for this module."""
    from server.app import create_app

    core_base.register(FlatCore)
    app = create_app(settings)
    app.state.server.catalog.register("tiny", make_tiny_scene())
    app.state.server.catalog.register("tiny_roofed", roofed(make_tiny_scene()))
    yield app
    core_base.unregister(FlatCore.name)


def test_scene_description_says_whether_and_why(live_server):
    tiny = httpx.get(f"{live_server}/scenes/tiny", timeout=60).json()["is_2_5d"]
    assert tiny["value"] is True and tiny["source"] == "geometry" and "height field" in tiny["why"]
    roof = httpx.get(f"{live_server}/scenes/tiny_roofed", timeout=60).json()["is_2_5d"]
    assert roof["value"] is False and "overhang" in roof["why"]
    city = httpx.get(f"{live_server}/scenes/city", timeout=120).json()["is_2_5d"]
    assert city["value"] is True and city["source"] == "meta" and "generator" in city["why"]


def test_a_2_5d_only_core_serves_geometry_2_5d_scenes_only(live_server):
    box = [[1.0, 0.0, 1.0], [3.0, 2.0, 3.0]]
    ok = httpx.post(f"{live_server}/scenes/tiny/pvs", timeout=60,
                    json={"box": box, "core": "test_flat"})
    assert ok.status_code == 200, ok.text
    refused = httpx.post(f"{live_server}/scenes/tiny_roofed/pvs", timeout=60,
                         json={"box": box, "core": "test_flat"})
    assert refused.status_code == 422, refused.text
    assert "2.5D" in refused.text and "overhang" in refused.text


def test_auto_choice_offers_the_2_5d_core_from_geometry(server_app):
    catalog = server_app.state.server.catalog
    tiny, roof = catalog.get("tiny").scene, catalog.get("tiny_roofed").scene
    assert "is_2_5d" not in tiny.meta  # nothing states it: the geometry decides
    name, why = choose_core(tiny)
    assert name == "test_flat" and "geometry" in why
    assert choose_core(roof)[0] != "test_flat"
    fits, why = core_fits(FlatCore(), roof)
    assert not fits and "overhang" in why
