"""The discontinuity metric δ (near-far paper, Eqs. 4-6)."""

from __future__ import annotations

import numpy as np
import pytest

from client.discontinuity import discontinuity, points_from_depth, project_points

EYE = np.array([0.0, 1.7, 0.0])
FWD = np.array([0.0, 0.0, -1.0])


def _wall_points(n: int = 48) -> np.ndarray:
    depth = np.full((n, n), 10.0, dtype=np.float32)
    return points_from_depth(depth, EYE, FWD, 1.0, 1.0)


def test_ground_truth_has_zero_delta():
    pts = _wall_points()
    d = discontinuity(pts, EYE, FWD, 1.0, 1.0, eps=4.0)
    assert d.pixels == 48 * 48 and d.mean_abs < 1e-12
    pos = project_points(pts, EYE, FWD, 48, 48, 1.0, 1.0)
    assert np.allclose(pos[5, 7], [7, 5])


def test_seam_gives_delta_along_it_only():
    pts = _wall_points()
    # The right half shows surface points shifted by 3 pixels' worth to the right: a seam.
    shifted = pts.copy()
    shifted[:, 24:, 0] -= 3 * (2 * 10.0 / 48)
    d = discontinuity(shifted, EYE, FWD, 1.0, 1.0, eps=4.0)
    assert d.mean_abs > 0.05
    assert np.nanmax(np.abs(d.delta[:, :16])) < 1e-12  # far from the seam: exact
    assert np.nanmax(np.abs(d.delta[:, 20:28])) > 0.3


def test_uniform_scale_gives_its_ratio():
    pts = _wall_points()
    # Points spread 1.25x apart in the ground truth: I is compressed, δ = 1/1.25 - 1 inside.
    centre = pts[24, 24]
    scaled = centre + (pts - centre) * 1.25
    d = discontinuity(scaled, EYE, FWD, 1.0, 1.0, eps=3.0)
    assert np.allclose(d.delta[16:32, 16:32], 1 / 1.25 - 1, atol=1e-6)


def test_empty_and_bad_input():
    pts = np.full((8, 8, 3), np.nan)
    d = discontinuity(pts, EYE, FWD, 1.0, 1.0)
    assert d.pixels == 0 and d.mean_abs == 0.0 and np.all(np.isnan(d.delta))
    with pytest.raises(ValueError):
        discontinuity(pts[..., :2], EYE, FWD, 1.0, 1.0)
    with pytest.raises(ValueError):
        discontinuity(pts, EYE, FWD, 1.0, 1.0, eps=0)
    with pytest.raises(ValueError):
        points_from_depth(np.full((4, 4), np.nan), EYE, FWD, 1.0, 1.0)
