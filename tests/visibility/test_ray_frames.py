"""Frames of independent rays (``visibility.ray_frames``): directions, first hits, the
float64 confirmation of missed pixels, eyes inside geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from visibility.cores.designed_scenes import Builder
from visibility.raster.camera import random_rotations
from visibility.ray_frames import (
    cube_directions,
    missed_pixels,
    missed_triangles,
    ray_frames,
    seen_ids,
)
from visibility.ray_reference import ExactCaster, frame_triangles


def _wall_and_back():
    """A quad wall (two triangles) 1 m in front of the origin along +x, 2 x 2 m, and a wider
    wall 3 m out that it hides in part."""
    b = Builder()
    wall = b.quad((1.0, -1.0, -1.0), (1.0, 1.0, -1.0), (1.0, 1.0, 1.0), (1.0, -1.0, 1.0), 0)
    back = b.quad((3.0, -5.0, -5.0), (3.0, 5.0, -5.0), (3.0, 5.0, 5.0), (3.0, -5.0, 5.0), 1)
    return b.scene("wall"), np.asarray(wall), np.asarray(back)


def test_cube_directions_fill_each_face_once():
    rng = np.random.default_rng(0)
    cube = random_rotations(rng, 1)[0]
    r = 16
    d = cube_directions(cube, r, rng)
    assert d.shape == (6 * r * r, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # Face k's rays lie in its frustum: its signed axis is the nearest.
    local = d @ cube.T
    face = np.argmax(np.abs(local), axis=1) * 2 + (np.take_along_axis(
        local, np.argmax(np.abs(local), axis=1)[:, None], axis=1)[:, 0] < 0)
    np.testing.assert_array_equal(face, np.repeat(np.arange(6), r * r))
    # One ray per pixel: the tangent coordinates of face 0 fall one in each pixel.
    f0 = local[: r * r]
    u = f0[:, 1] / f0[:, 0]
    v = f0[:, 2] / f0[:, 0]
    cells = np.floor((u + 1.0) * r / 2).astype(int) + r * np.floor((v + 1.0) * r / 2).astype(int)
    assert sorted(cells.tolist()) == list(range(r * r))


def test_a_wall_shows_in_about_its_solid_angle_and_hides_the_back():
    scene, wall, back = _wall_and_back()
    box = np.array([[-0.01] * 3, [0.01] * 3])
    fr = ray_frames(scene, box, n_eyes=4, resolution=64, seed=2)
    assert len(fr.ids) == 4 and fr.dropped == 0
    assert set(seen_ids(fr).tolist()) == set(wall.tolist()) | set(back.tolist())
    # The wall covers the +x face of a cube at the origin: a sixth of the sphere of directions.
    wall_share = np.isin(fr.ids, wall).mean(axis=1)
    np.testing.assert_allclose(wall_share, 1.0 / 6.0, atol=0.01)
    # A PVS without the wall misses exactly its pixels; with both, nothing.
    np.testing.assert_array_equal(missed_pixels(scene, fr, back),
                                  np.isin(fr.ids, wall).sum(axis=1))
    assert missed_pixels(scene, fr, np.concatenate([wall, back])).max() == 0


def test_directions_are_the_rays_each_frame_cast():
    """``RayFrames.directions`` draws a frame's rays again from its generator state: cast
    exactly from the frame's eye they meet what the frame recorded, and with a dropped eye
    before them (inside the solid) the kept frames keep their own states."""
    b = Builder()
    b.quad((1.0, -1.0, -1.0), (1.0, 1.0, -1.0), (1.0, 1.0, 1.0), (1.0, -1.0, 1.0), 0)
    b.box((-0.5, -0.5, -0.5), (-0.2, 0.5, 0.5), 1)
    scene = b.scene("wall and solid")
    box = np.array([[-0.4, -0.1, -0.1], [0.1, 0.1, 0.1]])
    fr = ray_frames(scene, box, n_eyes=6, resolution=16, seed=4, near=0.0)
    assert fr.dropped > 0 and len(fr.ids) > 0
    tri, tri_ids = frame_triangles(scene, fr.centre)
    caster = ExactCaster(tri)
    for k in range(len(fr.ids)):
        d = fr.directions(k, np.arange(fr.pixels)).astype(np.float64)
        orig = np.broadcast_to(fr.eyes[k] - fr.centre, d.shape)
        got, _ = caster.first_hits(np.ascontiguousarray(orig), d, np.zeros(len(d)))
        ids = np.where(got >= 0, tri_ids[np.maximum(got, 0)], -1)
        # float32 (Embree) and float64 may part at a shared edge: a ray in a thousand at most.
        print("MISMATCH", (ids != fr.ids[k]).sum())
        assert (ids != fr.ids[k]).sum() <= fr.pixels // 1000


def test_a_miss_float64_contradicts_does_not_count():
    scene, wall, back = _wall_and_back()
    box = np.array([[-0.01] * 3, [0.01] * 3])
    fr = ray_frames(scene, box, n_eyes=2, resolution=32, seed=3)
    pvs = np.concatenate([wall, back[:1]])
    # Pretend float32 leaked through the wall at some of its pixels onto a triangle the PVS
    # lacks (the back wall's second one).
    ids = fr.ids.copy()
    leak = np.flatnonzero(np.isin(ids[0], wall))[:7]
    ids[0, leak] = back[1]
    forged = dataclasses.replace(fr, ids=ids)
    honest = missed_pixels(scene, fr, pvs)
    assert missed_pixels(scene, forged, pvs, confirm=False)[0] == honest[0] + 7
    # Cast again exactly, those rays meet the wall, which the PVS holds.
    assert missed_pixels(scene, forged, pvs)[0] == honest[0]
    # The triangles missed: the back wall's second one where some pixel really shows it, and
    # never on the forged pixels' word alone.
    truly = np.isin(fr.ids, back[1]).any()
    assert missed_triangles(scene, forged, pvs).tolist() == ([int(back[1])] if truly else [])
    assert missed_triangles(scene, fr, wall).tolist() == sorted(back.tolist())
    assert len(missed_triangles(scene, fr, np.concatenate([wall, back]))) == 0


def test_eyes_inside_a_closed_solid_are_dropped():
    b = Builder()
    b.box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0)
    scene = b.scene("solid")
    inside = np.array([[-0.1] * 3, [0.1] * 3])
    fr = ray_frames(scene, inside, n_eyes=3, resolution=16, seed=0)
    assert fr.dropped == 3 and len(fr.ids) == 0
    outside = np.array([[1.5] * 3, [1.6] * 3])
    fr = ray_frames(scene, outside, n_eyes=3, resolution=16, seed=0)
    assert fr.dropped == 0 and len(fr.ids) == 3 and len(seen_ids(fr)) > 0


def test_bad_parameters_are_refused():
    scene, _, _ = _wall_and_back()
    box = np.array([[-0.01] * 3, [0.01] * 3])
    with pytest.raises(ValueError, match="resolution"):
        ray_frames(scene, box, resolution=0)
    with pytest.raises(ValueError, match="near"):
        ray_frames(scene, box, near=-1.0)


def test_open_space_is_outside_closed_solids():
    from visibility.ray_frames import in_open_space

    b = Builder()
    b.box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0)
    scene = b.scene("solid")
    got = in_open_space(scene, np.array([[0.0, 0.0, 0.0], [0.5, -0.3, 0.2], [3.0, 0.0, 0.0]]))
    np.testing.assert_array_equal(got, [False, False, True])


def test_a_batch_split_over_threads_casts_the_same_hits(monkeypatch):
    """``EmbreeCaster.first_hits`` splits large batches over threads; every ray keeps its own
    answer and distance, whatever the split."""
    import visibility.ray_reference as rr
    from visibility.generators import make_scene

    scene = make_scene("rooms", triangles=2000)
    tri, _ = frame_triangles(scene, scene.vertices.mean(axis=0))
    caster = rr.EmbreeCaster(tri)
    rng = np.random.default_rng(4)
    n = 40_000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    orig = rng.uniform(-1.0, 1.0, size=(n, 3))
    tmin = rng.uniform(0.0, 0.5, size=n)
    monkeypatch.setattr(rr, "CAST_CHUNK_MIN", n + 1)
    one_ids, one_t = caster.first_hits(orig, d, tmin)
    monkeypatch.setattr(rr, "CAST_CHUNK_MIN", 1000)
    monkeypatch.setattr(rr, "get_num_threads", lambda: 7)
    split_ids, split_t = caster.first_hits(orig, d, tmin)
    assert (one_ids >= 0).mean() > 0.5
    np.testing.assert_array_equal(split_ids, one_ids)
    np.testing.assert_array_equal(split_t, one_t)
