"""Near-far streams (server side of the integration with ``visibility.nearfar``): a scene with
nothing beyond r2 gets no cubemap; a city cell gets one, and its geometry is the near part."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

import visibility.nearfar as nearfar
from client.session import Session
from tests.conftest import make_tiny_scene, serving


@pytest.fixture(scope="module")
def nf_server(settings, registered_test_cores):
    with serving(settings, {"tiny": make_tiny_scene()}, near_far=True, near_far_r1=40.0,
                 near_far_r2=80.0, near_far_resolution=32) as served:
        yield served


def _stream(url, scene, cell_pos):
    async def main():
        s = await Session.connect(url, scene, "test_near", {"radius": 30.0}, prefetch=False)
        await s.send_pose(0, 0.0, cell_pos, (0, 0, -1))
        cell = None
        for _ in range(600):
            if s.complete:
                cell = next(iter(s.complete))
                break
            await asyncio.sleep(0.1)
        await s.close()
        return s, cell

    return asyncio.run(asyncio.wait_for(main(), 120))


def test_tiny_scene_gets_no_cubemap(nf_server):
    url, _ = nf_server
    s, cell = _stream(url, "tiny", (2.0, 1.7, 2.0))
    assert cell is not None
    assert s.welcome.features["cubemap"]["on"] is False
    assert s.cells[cell].begin.near_far["cubemap"] is False
    assert not s.cubemaps and not s.local_errors


def test_city_cell_gets_a_cubemap_and_near_geometry(nf_server):
    url, app = nf_server
    loaded = app.state.server.catalog.get("city")
    grid, scene = loaded.grid, loaded.scene
    cfg = nearfar.NearFarConfig(r1=40.0, r2=80.0, resolution=32)
    cid = next(c for c in range(len(grid))
               if nearfar.needs_cubemap(scene, grid.boxes[c].mean(axis=0), cfg))
    centre = grid.boxes[cid].mean(axis=0)
    s, cell = _stream(url, "city", centre)
    assert cell == cid and not s.local_errors
    assert s.welcome.features["cubemap"]["on"] is True
    nfinfo = s.cells[cid].begin.near_far
    assert nfinfo["cubemap"] is True and nfinfo["r2"] == 80.0
    np.testing.assert_allclose(nfinfo["center"], centre)
    cube = s.cubemaps[cid]
    assert cube.colors.shape == (6, 32, 32, 3)
    split = nearfar.split_ids(scene, centre, cfg)
    allowed = np.union1d(split.near_ids, split.far_dynamic_ids)
    assert np.all(np.isin(s.store.ids, allowed))  # nothing far and static as geometry
    finite = np.isfinite(cube.ranges)
    assert finite.any()


def test_cell_whose_near_region_fits_the_budget_is_sent_whole(nf_server):
    """With a budget that holds a city cell's near region (but not the scene), the server sends
    that region without computing a PVS: the client holds every near triangle, not a subset."""
    url, app = nf_server
    state = app.state.server
    loaded = state.catalog.get("city")
    grid, scene = loaded.grid, loaded.scene
    cfg = nearfar.NearFarConfig(r1=40.0, r2=80.0, resolution=32)
    cid = next(c for c in range(len(grid))
               if nearfar.needs_cubemap(scene, grid.boxes[c].mean(axis=0), cfg))
    centre = grid.boxes[cid].mean(axis=0)
    split = nearfar.split_ids(scene, centre, cfg)
    near = np.union1d(split.near_ids, split.far_dynamic_ids)
    assert len(near) < int(scene.valid_faces.sum())
    computed, whole = state.compute.computed, state.counters["cells_sent_whole"]
    s = _walk_in(url, "city", cid, centre, budget=len(near))
    assert cid in s.complete and not s.local_errors
    np.testing.assert_array_equal(np.sort(s.store.ids), near)  # all of it, though radius 1 m
    assert state.compute.computed == computed  # no PVS was computed for it
    assert state.counters["cells_sent_whole"] == whole + 1
    # One triangle less of budget and the cell is culled as usual.
    s = _walk_in(url, "city", cid, centre, budget=len(near) - 1)
    assert cid in s.complete and len(s.store.ids) < len(near)


def _walk_in(url, scene, cid, position, budget):
    """A session with a 1 m ``test_near`` PVS and ``budget`` that stands at ``position`` until
    cell ``cid`` is complete."""
    async def main():
        s = await Session.connect(url, scene, "test_near", {"radius": 1.0}, budget=budget,
                                  prefetch=False)
        await s.send_pose(0, 0.0, position, (0, 0, -1))
        for _ in range(600):
            if cid in s.complete:
                break
            await asyncio.sleep(0.1)
        await s.close()
        return s

    return asyncio.run(asyncio.wait_for(main(), 120))


def test_cells_of_a_block_share_one_cubemap(settings, registered_test_cores):
    """With ``near_far_block`` 3, two cells of one block compose with the cubemap baked at
    their block's anchor cell: it is sent once, named by both cells' ``cell_begin``."""
    with serving(settings, near_far=True, near_far_r1=40.0, near_far_r2=80.0,
                 near_far_resolution=32, near_far_block=3) as (url, app):
        state = app.state.server
        loaded = state.catalog.get("city")
        grid = loaded.grid
        cfg = nearfar.NearFarConfig(r1=40.0, r2=80.0, resolution=32)
        anchors = state.near_far.anchors(loaded, 3)
        need = state.near_far.cubemap_cells(loaded, cfg)
        anchor = next(a for a in np.unique(anchors)
                      if need[a] and np.count_nonzero(anchors == a) >= 3)
        others = [int(c) for c in np.flatnonzero(anchors == anchor) if c != anchor][:2]
        sent = state.counters["cubemaps_sent"]

        async def main():
            s = await Session.connect(url, "city", "test_near", {"radius": 5.0},
                                      prefetch=False)
            for k, cid in enumerate(others):
                await s.send_pose(k, float(k), grid.boxes[cid].mean(axis=0), (0, 0, -1))
                await s.wait_cell(cid, 60)
            await s.close()
            return s

        s = asyncio.run(asyncio.wait_for(main(), 120))
        assert not s.local_errors and not s.errors
        features = s.welcome.features["cubemap"]
        assert features["block"] == 3 and features["cubemaps"] < features["cells"]
        centre = grid.boxes[anchor].mean(axis=0)
        for cid in others:
            info = s.cells[cid].begin.near_far
            assert info["cubemap"] is True and info["cubemap_cell"] == anchor
            np.testing.assert_allclose(info["center"], centre)
        assert list(s.cubemaps) == [anchor]
        assert s.cubemap_for(others[0]) is s.cubemap_for(others[1]) is s.cubemaps[anchor]
        np.testing.assert_allclose(s.cubemaps[anchor].center, centre)
        assert state.counters["cubemaps_sent"] == sent + 1
