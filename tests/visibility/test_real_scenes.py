"""Every real scene gets a PVS from the sampling core for one of its cells."""

import numpy as np
import pytest
import trimesh

from tests.visibility.real_scenes import REAL, SHARED_SCENES, discover, real_grid, real_scene
from visibility.cores.base import get_core

#: Real scenes: out of the fast lane (``-m "not slow"``), always in CI.
pytestmark = pytest.mark.slow


def test_real_scenes_are_listed_from_the_folder():
    # The four documented in ../shared/scenes/README.md; any other file there joins them.
    assert {"denhaag", "kitchen", "lavaducts", "lyon_vilo3d"} <= set(REAL)
    assert REAL == sorted(REAL)
    for name in REAL:
        assert (SHARED_SCENES / f"{name}.json").is_file(), f"{name}: no sidecar beside it"


def test_a_new_scene_file_is_discovered(tmp_path):
    box = trimesh.creation.box()
    box.export(tmp_path / "crate.obj")
    box.export(tmp_path / "ball.PLY")
    (tmp_path / "crate.json").write_text('{"scale": 1.0}')
    (tmp_path / "notes.txt").write_text("not a scene")
    found = discover(tmp_path)
    assert list(found) == ["ball", "crate"]
    assert found["crate"].suffix == ".obj"
    assert discover(tmp_path / "missing") == {}


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
