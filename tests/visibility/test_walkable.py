"""Walk-area detection from geometry alone (what loaded scenes get)."""

import numpy as np

from visibility.cores.designed_scenes import Builder
from visibility.viewcells import ViewcellGrid


def test_room_with_two_storeys_has_cells_on_each_floor():
    b = Builder()
    # Inward-facing shell: floor faces up, ceilings face down; a mezzanine floor at 4 m.
    b.quad((0, 0, 0), (0, 0, 16), (16, 0, 16), (16, 0, 0), 0)  # floor (up)
    b.quad((0, 4, 0), (0, 4, 16), (16, 4, 16), (16, 4, 0), 1)  # storey 2 floor (up)
    b.quad((0, 3.9, 0), (16, 3.9, 0), (16, 3.9, 16), (0, 3.9, 16), 1)  # its underside (down)
    b.quad((0, 8, 0), (16, 8, 0), (16, 8, 16), (0, 8, 16), 2)  # roof underside (down)
    grid = ViewcellGrid.for_scene(b.scene("storeys"), 4.0)
    levels = np.unique(np.round(grid.floor, 1))
    np.testing.assert_allclose(levels, [0.0, 4.0])
    assert len(grid) == 32
    assert np.all(grid.boxes[:, 1, 1] < grid.ceiling)


def test_city_without_terrain_walks_the_streets_not_the_roofs():
    b = Builder()
    # Two closed buildings (outward faces) and no ground at all, like the Lyon scene.
    b.box((0, 0, 0), (20, 15, 20), 0)
    b.box((32, 0, 0), (52, 12, 20), 1)
    b.box((0, 0, 32), (52, 18, 52), 2)
    grid = ViewcellGrid.for_scene(b.scene("city"), 4.0)
    assert len(grid) > 0
    assert np.all(np.abs(grid.floor) < 0.5), "cells must stand on the ground, not on roofs"
    # The street between the first two buildings is walkable; their insides are not.
    assert grid.cell_of([26, 1.7, 10]) is not None
    assert grid.cell_of([10, 1.7, 10]) is None
    assert grid.cell_of([42, 1.7, 10]) is None


def test_ground_with_a_building_keeps_cells_off_the_roof_and_out_of_the_inside():
    b = Builder()
    b.quad((-40, 0, -40), (-40, 0, 40), (40, 0, 40), (40, 0, -40), 0)  # ground (up)
    b.box((-10, 0, -10), (10, 12, 10), 1)  # closed building with a bottom face
    grid = ViewcellGrid.for_scene(b.scene("block"), 4.0)
    assert grid.cell_of([-30, 1.7, -30]) is not None
    assert grid.cell_of([0, 1.7, 0]) is None
    assert grid.cell_of([0, 13.7, 0]) is None
    assert np.all(grid.floor < 0.5)


def test_sidecar_walk_overrides_detection(tmp_path):
    import json

    import trimesh

    mesh = trimesh.creation.box(extents=(10, 1, 10))
    path = tmp_path / "slab.ply"
    mesh.export(path)
    (tmp_path / "slab.json").write_text(json.dumps({"walk": {"rects": [[0, 0, 8, 4, 0.5]]}}))
    from visibility.loaders import load_scene

    grid = ViewcellGrid.for_scene(load_scene(path), 4.0)
    assert len(grid) == 2
    np.testing.assert_allclose(grid.floor, 0.5)


def test_clockwise_winding_hint_flips_the_floors():
    b = Builder()
    # A room wound clockwise (as Quake levels are): the floor's computed normal points down.
    b.quad((0, 0, 0), (16, 0, 0), (16, 0, 16), (0, 0, 16), 0)
    b.quad((0, 5, 0), (0, 5, 16), (16, 5, 16), (16, 5, 0), 1)
    scene = b.scene("cw_room")
    assert len(ViewcellGrid.for_scene(scene, 4.0)) == 0
    scene.meta["winding"] = "cw"
    grid = ViewcellGrid.for_scene(scene, 4.0)
    assert len(grid) == 16 and np.allclose(grid.floor, 0.0)
