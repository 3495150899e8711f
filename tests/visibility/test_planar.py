"""The shared planar kernels (``visibility.planar``)."""

from __future__ import annotations

import numpy as np

from visibility.planar import convex_hull


def test_convex_hull_of_points_segments_and_duplicates():
    p = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5], [0.5, 0.0]])
    h = np.empty((12, 2))
    n = convex_hull(p.copy(), 6, h)
    assert n == 4
    assert {tuple(v) for v in h[:n]} == {(0, 0), (1, 0), (1, 1), (0, 1)}
    x, y = h[:n, 0], h[:n, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0.0  # counter-clockwise
    # Collinear points: the segment's two ends; repeated points: one or two copies of it.
    assert convex_hull(np.array([[0.0, 0.0], [2.0, 2.0], [1.0, 1.0]]), 3, h) == 2
    assert {tuple(v) for v in h[:2]} == {(0, 0), (2, 2)}
    n = convex_hull(np.array([[3.0, 1.0]] * 4), 4, h)
    assert 1 <= n <= 2 and np.all(h[:n] == (3.0, 1.0))
