"""Per-scene builds start in the background when a scene loads (a real server): the
hierarchy, the kd-tree and fences of a dual_ray server, the closed parts of a cos server, the
clusters of a from_segment server;
they are kept on disk by content hash, so a restart reads them; small scenes build nothing."""

from __future__ import annotations

import httpx
import numpy as np

from server.scene_builds import builds_for
from tests.conftest import serving, wait_for
from visibility.cores.base import choose_core, get_core
from visibility.generators import make_scene
from visibility.raster import hierarchy
from visibility.scene_cache import peek
from visibility.topology import CLOSED_KIND


def _load(url: str, name: str) -> dict:
    r = httpx.get(f"{url}/scenes/{name}", timeout=60)
    assert r.status_code == 200, r.text
    return r.json()


def test_hierarchy_built_after_load_and_read_back_after_a_restart(settings, tmp_path):
    city = make_scene("city", 60_000, seed=0)
    with serving(settings, scenes={"big": city}, cache_dir=tmp_path) as (url, app):
        _load(url, "big")
        scene = app.state.server.catalog.get("big").scene
        wait_for(lambda: peek(scene, hierarchy.KIND) is not None, timeout=120)
        built = peek(scene, hierarchy.KIND)
        assert not built.stats.get("loaded")
        wait_for(lambda: hierarchy.KIND in _load(url, "big").get("builds", {}), timeout=30)
        assert list((tmp_path / "scenes").rglob("*.npz"))
    # A restart: the same geometry in a new process state finds the build on disk.
    again = make_scene("city", 60_000, seed=0)
    with serving(settings, scenes={"big": again}, cache_dir=tmp_path) as (url, app):
        _load(url, "big")
        scene = app.state.server.catalog.get("big").scene
        wait_for(lambda: peek(scene, hierarchy.KIND) is not None, timeout=120)
        read = peek(scene, hierarchy.KIND)
        assert read.stats.get("loaded")
        assert np.array_equal(read.order, built.order)


def test_dual_ray_server_builds_its_kdtree_before_any_request(settings):
    city = make_scene("city", 20_000, seed=1)
    with serving(settings, scenes={"town": city}, core="dual_ray") as (url, app):
        info = _load(url, "town")
        assert info["is_2_5d"]["value"]
        scene = app.state.server.catalog.get("town").scene
        # No PVS was asked for: the kd-tree and fences come from the load's builds.
        wait_for(lambda: peek(scene, "kdtree") is not None and peek(scene, "fences")
                 is not None, timeout=120)
        assert app.state.server.compute.computed == 0


def test_cos_server_builds_the_closed_parts_before_any_request(settings, tmp_path):
    # cos leaves the back faces of closed surfaces out: their parts are a per-scene build.
    city = make_scene("city", 20_000, seed=2)
    with serving(settings, scenes={"town": city}, core="cos", cache_dir=tmp_path) as (url, app):
        _load(url, "town")
        scene = app.state.server.catalog.get("town").scene
        wait_for(lambda: peek(scene, CLOSED_KIND) is not None, timeout=120)
        assert app.state.server.compute.computed == 0
        wait_for(lambda: CLOSED_KIND in _load(url, "town").get("builds", {}), timeout=30)
        assert list((tmp_path / "scenes").rglob("*closed_parts*.npz"))


def test_from_segment_server_builds_its_clusters_before_any_request(settings):
    city = make_scene("city", 20_000, seed=3)
    with serving(settings, scenes={"town": city}, core="from_segment") as (url, app):
        _load(url, "town")
        scene = app.state.server.catalog.get("town").scene
        wait_for(lambda: peek(scene, "from_segment/clusters") is not None, timeout=120)
        assert app.state.server.compute.computed == 0
        wait_for(lambda: "from_segment/clusters" in _load(url, "town").get("builds", {}),
                 timeout=30)


def test_what_is_built(settings):
    from server.catalog import SceneCatalog

    catalog = SceneCatalog(settings)
    small = make_scene("village", 3_000, seed=0)
    catalog.register("small", small)
    assert builds_for(catalog.get("small"), settings) == []
    big = make_scene("city", 60_000, seed=0)
    catalog.register("big", big)
    kinds = [b.kind for b in builds_for(catalog.get("big"), settings)]
    assert kinds == [hierarchy.KIND]
    dual = settings.model_copy(update={"core": "dual_ray"})
    assert [b.kind for b in builds_for(catalog.get("big"), dual)] == \
        [hierarchy.KIND, "kdtree", "fences"]
    cos = settings.model_copy(update={"core": "cos"})
    assert [b.kind for b in builds_for(catalog.get("big"), cos)] == [hierarchy.KIND, CLOSED_KIND]
    segment = settings.model_copy(update={"core": "from_segment"})
    assert [b.kind for b in builds_for(catalog.get("big"), segment)] == \
        [hierarchy.KIND, "from_segment/clusters"]
    # auto: the builds of the core its declared fits pick.
    auto = settings.model_copy(update={"core": "auto"})
    loaded = catalog.get("big")
    chosen = get_core(choose_core(big, float(loaded.grid.cell_size))[0])
    assert [b.kind for b in builds_for(loaded, auto)] == \
        [hierarchy.KIND] + [b.kind for b in chosen.scene_builds(big)]
