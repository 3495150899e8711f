"""The frame measure of a PVS (``quality.frame_errors``)."""

from __future__ import annotations

import numpy as np

from visibility.cores.designed_scenes import Builder
from visibility.cores.trim_regions.quality import FRAME_NEAR, frame_errors


def _wall_beside_the_cell():
    """A one-sided wall 0.09 m from a 11.5 cm cell's centre (its nearest eyes 3 cm from it),
    as in a Quake level, and a wall 2 m behind it."""
    b = Builder()
    wall = b.quad((0.09, -1.2, -1.2), (0.09, 1.3, -1.2), (0.09, 1.3, 0.25), (0.09, -1.2, 0.25), 0)
    behind = b.box((1.95, -1.2, -1.2), (2.0, 1.3, 0.25), 1)
    return b.scene("beside"), np.asarray(wall), np.asarray(behind)


def test_the_frames_do_not_cut_a_wall_beside_the_eye():
    scene, wall, behind = _wall_beside_the_cell()
    h = 0.1 / np.sqrt(3.0)
    box = np.array([[-h, -h, -h], [h, h, h]])
    e = frame_errors(scene, wall, box, n_points=48, seed=1)
    assert e["fn_pixels_max"] == 0 and len(e["missed"]) == 0
    # At the projection's 5 cm near plane some frame's corner rays cut the wall and show the
    # one behind it, which no occlusion method reports.
    cut = frame_errors(scene, wall, box, n_points=48, seed=1, near=0.05)
    assert cut["fn_pixels_max"] > 0 and set(cut["missed"]) <= set(behind.tolist())
    assert FRAME_NEAR < 0.01
