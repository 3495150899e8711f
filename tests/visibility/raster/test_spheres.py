"""Sphere id buffers against a brute-force ray cast; spheres in the sampled ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from tests.visibility.segment_reference import sphere_depths
from visibility.ground_truth import sample_pvs
from visibility.raster.camera import random_rotation
from visibility.raster.spheres import draw_spheres_cubemap
from visibility.scene import Scene
from visibility.viewcells import Viewcell


@pytest.mark.parametrize("offset", [0.0, 1e5])
def test_spheres_match_brute_force_ray_cast(offset):
    rng = np.random.default_rng(3)
    eye = np.array([0.3, 1.6, -0.2]) + offset
    centers = eye + rng.uniform(-6, 6, size=(60, 3))
    radii = rng.uniform(0.1, 1.5, size=60)
    # One sphere around the eye (near-clipped: its far hit shows everywhere) and one that
    # reaches the near plane.
    centers[0] = eye + [20.0, 0.0, 0.0]
    centers[1] = eye + [0.0, 0.0, -0.3]
    radii[1] = 0.28
    rot = random_rotation(rng)
    res = 48
    depth = np.full((6, res, res), np.inf)
    ids = np.full((6, res, res), -1, dtype=np.int64)
    draw_spheres_cubemap(centers, radii, eye, depth, ids, rot, base_id=0)
    ref_depth, ref_ids = sphere_depths(centers, radii, eye, res, rot)
    assert (ids >= 0).sum() > 0.3 * ids.size
    agree = ids == ref_ids
    # Ties between spheres at equal depth are the only tolerated difference.
    close = np.isclose(depth, ref_depth, rtol=1e-9, atol=1e-9) | (~np.isfinite(ref_depth)
                                                                   & ~np.isfinite(depth))
    assert agree.mean() > 0.9999
    assert close.all()


def test_spheres_keep_their_buffers_when_nothing_is_in_front():
    depth = np.full((6, 8, 8), 1.0)
    ids = np.full((6, 8, 8), 7, dtype=np.int32)
    draw_spheres_cubemap(np.array([[0.0, 0.0, -5.0]]), np.array([1.0]), np.zeros(3), depth, ids)
    assert (ids == 7).all() and (depth == 1.0).all()
    # Bad spheres are skipped, not drawn and not an error.
    draw_spheres_cubemap(np.array([[np.nan, 0, -2.0], [0, 0, -2.0]]), np.array([1.0, -1.0]),
                         np.zeros(3), depth, ids)
    assert (ids == 7).all()
    with pytest.raises(ValueError):
        draw_spheres_cubemap(np.zeros((2, 3)), np.ones(3), np.zeros(3), depth, ids)


def test_ground_truth_sees_spheres_and_their_occlusion():
    """A wall with a sphere in front: the sphere is seen, the triangle hidden behind the sphere
    (and only behind it) is not; spheres come back as sphere ids."""
    wall = np.array([[-5, -5, -6], [5, -5, -6], [5, 5, -6], [-5, 5, -6]], dtype=np.float64)
    small = np.array([[-0.1, -0.1, -4.0], [0.1, -0.1, -4.0], [0.0, 0.1, -4.0]])
    verts = np.concatenate([wall, small])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    scene = Scene(verts, faces, sphere_centers=np.array([[[0.0, 0.0, -3.0]]]),
                  sphere_radii=np.array([0.8]))
    cell = Viewcell(np.array([[-0.01, -0.01, -0.01], [0.01, 0.01, 0.01]]))
    gt = sample_pvs(scene, cell, n_points=8, resolution=64, seed=1)
    assert gt.sphere_ids.tolist() == [0]
    assert 2 not in gt.triangle_ids  # behind the sphere from every sample
    assert set(gt.triangle_ids.tolist()) == {0, 1}
    # Without the sphere the small triangle is seen.
    bare = Scene(verts, faces)
    assert 2 in sample_pvs(bare, cell, n_points=8, resolution=64, seed=1).triangle_ids


def test_ground_truth_follows_moving_spheres():
    """A sphere that moves out of the way over the keyframes uncovers the triangle behind it."""
    verts = np.array([[-0.1, -0.1, -4.0], [0.1, -0.1, -4.0], [0.0, 0.1, -4.0]])
    centers = np.array([[[0.0, 0.0, -3.0]], [[30.0, 0.0, -3.0]]])
    scene = Scene(verts, np.array([[0, 1, 2]]), sphere_centers=centers,
                  sphere_radii=np.array([0.8]))
    assert scene.is_dynamic and scene.time_range() == (0.0, 1.0)
    np.testing.assert_allclose(scene.sphere_centers_at(0.5), [[15.0, 0.0, -3.0]])
    cell = Viewcell(np.zeros((2, 3)))
    gt = sample_pvs(scene, cell, n_points=16, resolution=32, seed=2)
    assert gt.triangle_ids.tolist() == [0]
    assert gt.sphere_ids.tolist() == [0]
