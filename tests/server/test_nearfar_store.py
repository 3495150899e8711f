"""Near-far data shared by the server's sessions: which cells need a cubemap (all cells at once,
equal to ``visibility.nearfar.needs_cubemap`` per cell), the byte-bounded split/cubemap cache that
never evicts a connected walker's current cell, and the welcome's report on a 100k ``city``."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from client.session import Session
from server.cache import ByteLRU, nbytes_of
from server.catalog import SceneCatalog
from server.nearfar_store import NearFarStore
from server.settings import Settings
from tests.conftest import make_tiny_scene, serving
from visibility import nearfar
from visibility.generators import make_scene
from visibility.nearfar.cells import cells_needing_cubemap, farthest_static_distance
from visibility.scene import Scene, WalkArea
from visibility.viewcells import ViewcellGrid


def _tri_at(x: float, z: float) -> np.ndarray:
    return np.array([[x, 0.0, z - 0.5], [x, 0.0, z + 0.5], [x, 2.0, z]])


def _strip_scene() -> Scene:
    """Triangles along +X at x = 0..60 m (so cells near x = 0 see geometry beyond r2 = 40 m and
    cells near x = 30 do not), plus a far triangle at x = 200 m that moves (never baked)."""
    tris = [_tri_at(x, 2.0) for x in np.arange(0.0, 61.0, 3.0)] + [_tri_at(200.0, 2.0)]
    v = np.concatenate(tris)
    faces = np.arange(len(v)).reshape(-1, 3)
    states = np.stack([v, v.copy()])
    states[1, -3:, 1] += 1.0  # only the last triangle moves
    walk = WalkArea(rects=np.array([[0.0, 0.0, 60.0, 4.0, 0.0]]))
    return Scene(vertices=v, faces=faces, states=states, state_times=[0.0, 1.0], walk=walk,
                 name="strip")


@pytest.mark.parametrize("r2", [20.0, 40.0, 45.0, 80.0])
def test_all_cells_at_once_equal_needs_cubemap_per_cell(r2):
    scene = _strip_scene()
    grid = ViewcellGrid.for_scene(scene, 4.0)
    centers = grid.boxes.mean(axis=1)
    cfg = nearfar.NearFarConfig(r1=r2 / 2, r2=r2, resolution=16)
    want = np.array([nearfar.needs_cubemap(scene, c, cfg) for c in centers])
    got = cells_needing_cubemap(scene, centers, r2)
    np.testing.assert_array_equal(got, want)
    if r2 == 40.0:
        assert want.any() and not want.all()  # the case that can tell them apart
    if r2 == 80.0:  # the moving triangle at 200 m never counts: nothing static is that far
        assert not got.any()


def test_all_cells_at_once_on_a_generated_city():
    scene = make_scene("city", triangles=5000, seed=3)
    grid = ViewcellGrid.for_scene(scene, 4.0)
    centers = grid.boxes.mean(axis=1)
    rho = farthest_static_distance(scene, centers)
    # An r2 between the nearest and farthest "farthest corner" splits the cells both ways.
    r2 = float(np.median(rho))
    cfg = nearfar.NearFarConfig(r1=r2 / 2, r2=r2, resolution=16)
    got = cells_needing_cubemap(scene, centers, r2)
    assert got.any() and not got.all()
    pick = np.unique(np.concatenate([np.linspace(0, len(grid) - 1, 40).astype(int),
                                     np.flatnonzero(got)[:5], np.flatnonzero(~got)[:5]]))
    want = [nearfar.needs_cubemap(scene, centers[i], cfg) for i in pick]
    np.testing.assert_array_equal(got[pick], want)


def test_scene_without_static_faces_needs_no_cubemap():
    v = np.zeros((0, 3))
    empty = Scene(vertices=v, faces=np.zeros((0, 3), dtype=np.int32))
    assert not cells_needing_cubemap(empty, np.zeros((3, 3)), 1.0).any()


# --------------------------------------------------------------------------- bounded cache
def test_byte_lru_keep_predicate_protects_entries():
    kept = {"walker"}
    cache = ByteLRU(3 * (64 + 1000), keep=lambda k: k in kept)
    cache.put("walker", b"x" * 1000)
    for i in range(6):
        cache.put(i, b"y" * 1000)
        assert cache.nbytes <= cache.max_bytes
    assert "walker" in cache  # the oldest entry, but a walker needs it
    assert 0 not in cache and 5 in cache
    kept.clear()
    cache.put("late", b"z" * 1000)
    assert "walker" not in cache and cache.nbytes <= cache.max_bytes


def test_near_far_store_is_bounded_and_keeps_walkers_cells():
    scene = _strip_scene()
    settings = Settings(generated={})
    cat = SceneCatalog(settings)
    cat.register("strip", scene)
    loaded = cat.get("strip")
    cfg = nearfar.NearFarConfig(r1=10.0, r2=20.0, resolution=16)
    mask = cells_needing_cubemap(scene, loaded.grid.boxes.mean(axis=1), cfg.r2)
    cells = np.flatnonzero(mask)
    assert len(cells) >= 6
    one = nbytes_of(nearfar.split_ids(scene, loaded.grid.boxes[cells[0]].mean(axis=0), cfg))
    walkers = {int(cells[0])}
    store = NearFarStore(3 * one, in_use=lambda name, cell: name == "strip" and cell in walkers)
    for c in cells:
        split = store.split(loaded, int(c), cfg)
        assert split is not False and len(split.far_static_ids)
        assert store.cache.nbytes <= store.cache.max_bytes
    assert store.cached_split(loaded, int(cells[0]), cfg) is not None  # the walker's cell
    assert store.cache.stats()["evictions"] >= len(cells) - 3
    # A cell without far geometry is answered from the per-scene mask, never cached.
    if not mask.all():
        assert store.split(loaded, int(np.flatnonzero(~mask)[0]), cfg) is False
    # Cubemap frames share the bound.
    frame = store.cubemap(loaded, int(cells[1]), cfg, lambda: b"c" * one)
    assert frame == b"c" * one and store.cache.nbytes <= store.cache.max_bytes
    assert store.cached_split(loaded, int(cells[0]), cfg) is not None


# --------------------------------------------------------------------------- the welcome
@pytest.fixture(scope="module")
def city_server(settings, registered_test_cores):
    with serving(settings, {"tiny": make_tiny_scene()}, near_far=True,
                 generated={"city": 100_000}) as served:
        yield served


def test_welcome_reports_cubemap_cells_of_a_100k_city(city_server):
    """With near-far on, a hello on the default-size city is answered (the per-cell check used
    to take minutes), and the count it reports agrees with ``needs_cubemap`` per cell."""
    url, app = city_server

    async def main():
        s = await Session.connect(url, "city", "test_near", {"radius": 2.0}, prefetch=False)
        again = await Session.connect(url, "city", "test_near", {"radius": 2.0},
                                      prefetch=False)
        await s.close()
        await again.close()
        return s.welcome, again.welcome

    welcome, again = asyncio.run(asyncio.wait_for(main(), 120))
    loaded = app.state.server.catalog.get("city")
    cfg = app.state.server.settings.near_far_config()
    centers = loaded.grid.boxes.mean(axis=1)
    report = welcome.features["cubemap"]
    assert report["r2"] == cfg.r2 and again.features["cubemap"] == report
    pick = np.linspace(0, len(centers) - 1, 12).astype(int)
    want = np.array([nearfar.needs_cubemap(loaded.scene, centers[i], cfg) for i in pick])
    mask = app.state.server.near_far.cubemap_cells(loaded, cfg)
    np.testing.assert_array_equal(mask[pick], want)
    assert report["cells"] == int(mask.sum()) and report["on"] is bool(mask.any())
    assert app.state.server.near_far.stats()["masks"] == 1  # once per scene and r2
