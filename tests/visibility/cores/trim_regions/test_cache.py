"""The per-scene structures of the trim region core: connected pieces."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.cache import build_scene_data, connected_pieces
from visibility.scene import Scene
from visibility.topology import weld_vertices


def test_triangles_meeting_at_a_corner_position_are_one_piece():
    # Triangles 0 and 1 share a corner by position only (rows 2 and 3, unwelded); 2 stands
    # apart; 3 is not among the ids asked for.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0],
                  [5, 5, 5], [6, 5, 5], [5, 6, 5], [9, 9, 9], [9, 8, 9], [8, 9, 9]], float)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]])
    label = connected_pieces(f, np.array([0, 1, 2]), weld_vertices(v), 4)
    assert label[0] == label[1] != label[2] and label[3] == -1
    assert connected_pieces(f, np.zeros(0, dtype=np.int64), weld_vertices(v), 4).tolist() \
        == [-1] * 4


def test_scene_data_holds_a_piece_for_every_static_triangle():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [4, 0, 0], [3, 1, 0]], float)
    scene = Scene(v, np.array([[0, 1, 2], [3, 4, 5]]))
    data = build_scene_data(scene)
    assert data.piece.shape == (2,) and data.piece[0] != data.piece[1]
    assert (data.piece[data.static] >= 0).all()
