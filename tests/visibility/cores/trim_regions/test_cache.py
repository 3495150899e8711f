"""The per-scene structures of the trim region core."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.cache import build_scene_data
from visibility.scene import Scene


def test_scene_data_holds_a_piece_for_every_static_triangle():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [4, 0, 0], [3, 1, 0]], float)
    scene = Scene(v, np.array([[0, 1, 2], [3, 4, 5]]))
    data = build_scene_data(scene)
    assert data.piece.shape == (2,) and data.piece[0] != data.piece[1]
    assert (data.piece[data.static] >= 0).all()


def _box_scene(lo, hi, inward: bool) -> Scene:
    """A closed box [lo, hi], wound outward or inward (inside out, or a room's walls)."""
    import trimesh

    box = trimesh.creation.box(bounds=[lo, hi])
    faces = np.asarray(box.faces)
    if inward:
        faces = faces[:, [0, 2, 1]]
    return Scene(np.asarray(box.vertices, dtype=np.float64), faces)


def test_an_inside_out_part_faces_out_for_a_cell_outside_it():
    from visibility.cores.trim_regions.cache import faced_out_for

    cell = np.array([[0.0, 2.0, 0.0], [0.3, 2.3, 0.3]])
    inside_out = _box_scene([-1.0, 0.0, -1.0], [1.0, 0.5, 1.0], inward=True)
    data = build_scene_data(inside_out)
    before = data.faces.copy()
    faced = faced_out_for(inside_out, data, cell)
    # Turned: the same triangles, wound the other way, with their normals and planes.
    np.testing.assert_array_equal(faced.faces, data.faces[:, [0, 2, 1]])
    np.testing.assert_array_equal(faced.normal_of, -data.normal_of)
    np.testing.assert_array_equal(faced.normals, -data.normals)
    np.testing.assert_array_equal(faced.plane, -data.plane)
    # As if the box had been wound outward from the start.
    outward = build_scene_data(_box_scene([-1.0, 0.0, -1.0], [1.0, 0.5, 1.0], inward=False))
    np.testing.assert_allclose(faced.normal_of, outward.normal_of)
    # The scene's own data (cached, shared by every cell) is left as it was.
    np.testing.assert_array_equal(data.faces, before)


def test_a_part_around_the_cell_or_wound_outward_keeps_its_winding():
    from visibility.cores.trim_regions.cache import faced_out_for

    cell = np.array([[0.0, 1.0, 0.0], [0.3, 1.3, 0.3]])
    # A room modelled as an inward-facing box around the cell: its eyes see its inner side.
    room = _box_scene([-2.0, 0.0, -2.0], [2.0, 3.0, 2.0], inward=True)
    data = build_scene_data(room)
    assert faced_out_for(room, data, cell) is data
    solid = _box_scene([1.0, 0.0, 1.0], [1.5, 0.5, 1.5], inward=False)
    data = build_scene_data(solid)
    assert faced_out_for(solid, data, cell) is data
