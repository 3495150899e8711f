"""The welcome states the near plane the answers assume (issue 29, item 4): over a real
WebSocket to the real server, ``welcome.near_plane`` is the clients' near plane the
conservative cores are built for (``visibility.raster.camera.DEFAULT_NEAR``, from which their
``topology.NEAR_CLEARANCE`` derives), and a core with its own ``near`` parameter
(``from_segment``) gets that one stated instead."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from client.session import Session
from tests.conftest import make_tiny_scene
from visibility.cores.base import get_core
from visibility.cores.cos import prims as cos_prims
from visibility.cores.dual_ray import fences as dual_ray_fences
from visibility.raster.camera import DEFAULT_NEAR
from visibility.topology import NEAR_CLEARANCE
from visibility.viewcells import ViewcellGrid


def welcome_of(url: str, core: str, params: dict | None = None):
    async def main():
        s = await Session.connect(url, "tiny", core, params, prefetch=False)
        try:
            return s.welcome
        finally:
            await s.close()

    return asyncio.run(asyncio.wait_for(main(), 120))


@pytest.mark.parametrize("core", ["cos", "sampling"])
def test_the_welcome_states_the_near_plane_the_cores_assume(live_server, core):
    w = welcome_of(live_server, core)
    assert w.core == core
    assert w.near_plane == DEFAULT_NEAR
    # What the conservative cores keep visible through walls nearer than the near plane is
    # built from this very distance (along the ray in a 90 degree view: up to sqrt(3) times).
    assert NEAR_CLEARANCE == pytest.approx(np.sqrt(3.0) * w.near_plane, rel=1e-15)
    assert cos_prims.NEAR_CLEARANCE == dual_ray_fences.NEAR_CLEARANCE == NEAR_CLEARANCE


def test_cos_reports_the_near_plane_the_welcome_states(live_server):
    w = welcome_of(live_server, "cos")
    scene = make_tiny_scene()
    cos = get_core("cos")
    cell = ViewcellGrid.for_scene(scene, w.grid.cell_size).cell(0)
    pvs = cos.compute(scene, cell, cos.make_params(**w.params))
    assert pvs.stats["near_plane"] == w.near_plane


def test_a_core_with_its_own_near_plane_gets_it_stated(live_server):
    w = welcome_of(live_server, "from_segment", {"near": 0.125})
    assert w.params["near"] == 0.125
    assert w.near_plane == 0.125
