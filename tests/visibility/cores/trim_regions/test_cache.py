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
