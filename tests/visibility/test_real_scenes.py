"""Every real scene gets a PVS from the sampling core for one of its cells."""

import numpy as np
import pytest

from tests.visibility.real_scenes import REAL, real_grid, real_scene
from visibility.cores.base import get_core


@pytest.mark.parametrize("name", REAL)
def test_sampling_core_returns_a_pvs_for_a_real_cell(name):
    scene, grid = real_scene(name), real_grid(name)
    cell = grid.cell(len(grid) // 2)
    core = get_core("sampling")
    pvs = core.compute(scene, cell, core.make_params(resolution=64, samples=4))
    ids = pvs.triangle_ids
    assert 0 < len(ids) < scene.n_triangles
    assert np.all(np.diff(ids) > 0) and ids[-1] < scene.n_triangles
    assert scene.valid_faces[ids].all()
    # What is seen lies around the cell: the nearest visible triangle is close to it.
    centres = scene.triangles(ids).mean(axis=1)
    assert np.min(np.linalg.norm(centres - cell.center, axis=1)) < 20.0
