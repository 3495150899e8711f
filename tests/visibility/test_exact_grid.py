"""The float64 grid caster (``visibility.exact_grid``) answers as the brute force does."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.exact_grid import build_grid, grid_first_hits
from visibility.ray_reference import ExactCaster, exact_first_hits, random_directions


def _brute(tri, orig, dirs, tmin):
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    out_id = np.empty(len(orig), dtype=np.int64)
    out_t = np.empty(len(orig))
    exact_first_hits(tri, lo, hi, orig, dirs, tmin, out_id, out_t)
    return out_id, out_t


def _grid(tri, orig, dirs, tmin):
    grid = build_grid(tri.min(axis=1), tri.max(axis=1))
    out_id = np.empty(len(orig), dtype=np.int64)
    out_t = np.empty(len(orig))
    grid_first_hits(tri, grid, orig, dirs, tmin, out_id, out_t)
    return out_id, out_t


def _clutter(rng, n=3000):
    """Small random triangles in a 10 m box, a few long thin ones across it, a floor of two
    big ones (the grid's list of big triangles) and shared edges (a strip)."""
    c = rng.uniform(-5.0, 5.0, size=(n, 1, 3))
    small = c + rng.normal(scale=0.2, size=(n, 3, 3))
    long_ = rng.uniform(-5.0, 5.0, size=(40, 3, 3))
    floor = np.array([[[-6, -5, -6], [6, -5, -6], [6, -5, 6]], [[-6, -5, -6], [6, -5, 6],
                                                                 [-6, -5, 6]]], dtype=float)
    xs = np.linspace(-4.0, 4.0, 41)
    strip = [[[x0, 0.0, 1.0], [x1, 0.0, 1.0], [x0, 1.0, 1.0]] for x0, x1 in zip(xs, xs[1:],
                                                                                 strict=False)]
    strip += [[[x1, 0.0, 1.0], [x1, 1.0, 1.0], [x0, 1.0, 1.0]] for x0, x1 in zip(xs, xs[1:],
                                                                                  strict=False)]
    return np.ascontiguousarray(np.concatenate([small, long_, floor, np.array(strip)]))


def test_the_grid_gives_the_brute_forces_first_hits():
    rng = np.random.default_rng(0)
    tri = _clutter(rng)
    n = 4000
    orig = np.concatenate([rng.uniform(-5.0, 5.0, size=(n // 2, 3)),      # inside the grid
                           rng.uniform(-40.0, 40.0, size=(n // 2, 3))])   # mostly outside
    dirs = random_directions(n, rng)
    # Rays along the axes and through the strip's shared edges (x = -4 + 0.2 k, z = 1).
    dirs[:200] = np.eye(3)[rng.integers(0, 3, 200)] * rng.choice([-1.0, 1.0], (200, 1))
    k = np.arange(200, 400)
    orig[k] = np.stack([-4.0 + 0.2 * (k % 41), np.full(200, 0.5), np.full(200, -3.0)], axis=1)
    dirs[k] = (0.0, 0.0, 1.0)
    tmin = np.where(rng.random(n) < 0.3, rng.uniform(0.0, 3.0, n), 0.0)
    bid, bt = _brute(tri, orig, dirs, tmin)
    gid, gt = _grid(tri, orig, dirs, tmin)
    assert (bid >= 0).sum() > n // 3  # the rays meet triangles: the comparison says something
    np.testing.assert_array_equal(gid, bid)
    np.testing.assert_array_equal(gt, bt)


@pytest.mark.parametrize("flat_axis", [0, 1, 2])
def test_a_flat_scene_and_rays_in_its_plane(flat_axis):
    rng = np.random.default_rng(flat_axis)
    tri = rng.uniform(-3.0, 3.0, size=(2500, 3, 3))
    tri[:, :, flat_axis] = 0.0
    orig = rng.uniform(-4.0, 4.0, size=(1500, 3))
    dirs = random_directions(1500, rng)
    orig[:300, flat_axis] = 0.0
    dirs[:300, flat_axis] = 0.0
    dirs[:300] /= np.linalg.norm(dirs[:300], axis=1, keepdims=True)
    tmin = np.zeros(1500)
    bid, bt = _brute(tri, orig, dirs, tmin)
    gid, gt = _grid(tri, orig, dirs, tmin)
    np.testing.assert_array_equal(gid, bid)
    np.testing.assert_array_equal(gt, bt)


def test_exact_caster_takes_the_grid_on_large_sets_only():
    rng = np.random.default_rng(3)
    assert ExactCaster(_clutter(rng, 10)).grid is None
    big = ExactCaster(_clutter(rng))
    assert big.grid is not None and len(big.grid.big) >= 2
    orig = rng.uniform(-5.0, 5.0, size=(500, 3))
    dirs = random_directions(500, rng)
    tmin = np.zeros(500)
    got = big.first_hits(orig, dirs, tmin)
    want = _brute(big.tri, orig, dirs, tmin)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
