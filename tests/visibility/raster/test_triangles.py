"""The numba rasterizer against hand-built cases with known answers and a brute-force ray caster."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from visibility.raster import triangles as raster
from visibility.raster.camera import (
    DEFAULT_NEAR,
    cube_face_rotations,
    look_rotation,
    pixel_rays,
    random_rotation,
)
from visibility.raster.render import render_cubemap, render_cubemap_ids, render_ids

I3 = np.eye(3)
O3 = np.zeros(3)


def ray_cast(vertices, faces, eye, rotation, width, height, tan_x=1.0, tan_y=1.0,
             near=DEFAULT_NEAR):
    """Brute-force reference: Moller-Trumbore from the eye through every pixel centre, nearest
    hit at depth >= near (depth = ray parameter, since the rays have z = -1)."""
    cam = (np.asarray(vertices, dtype=np.float64) - eye) @ np.asarray(rotation).T
    d = pixel_rays(width, height, tan_x, tan_y).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    best_id = np.full(len(d), -1)
    for k, (a, b, c) in enumerate(cam[np.asarray(faces)]):
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = p @ e1
        s = -a
        q = np.cross(s, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            u = (p @ s) * inv
            v = (d @ q) * inv
            t = np.full(len(d), q @ e2) * inv
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= near) & (t < best)
        best[hit] = t[hit]
        best_id[hit] = k
    return best.reshape(height, width), best_id.reshape(height, width)


def random_scene(rng, m=150, spread=5.0, size=1.0):
    centres = rng.uniform(-spread, spread, (m, 1, 3))
    v = (centres + rng.normal(0.0, size, (m, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


# ----------------------------------------------------------------------------- known answers
def test_one_triangle_covers_exactly_the_centres_inside_it():
    # At z = -4 with tan = 1 the screen spans x, y in [-4, 4]; 16x16 px: centres every 0.5 m.
    v = np.array([[-2.1, -1.9, -4.0], [2.3, -1.9, -4.0], [-2.1, 2.7, -4.0]])
    depth, ids = render_ids(v, np.array([[0, 1, 2]]), O3, I3, 16, 16)
    rays = pixel_rays(16, 16) * 4.0  # points of the z = -4 plane
    x, y = rays[..., 0], rays[..., 1]
    # Inside the right triangle: x > -2.1, y > -1.9, and below the hypotenuse.
    inside = (x > -2.1) & (y > -1.9) & ((x + 2.1) / 4.4 + (y + 1.9) / 4.6 < 1)
    assert inside.sum() > 20
    np.testing.assert_array_equal(ids >= 0, inside)
    assert np.all(ids[inside] == 0)
    np.testing.assert_allclose(depth[inside], 4.0, rtol=1e-6)
    assert np.all(np.isinf(depth[~inside]))
    assert depth.dtype == np.float32 and ids.dtype == np.int32


def test_pixel_orientation_follows_camera_conventions():
    # A small triangle up and to the right in camera space lands top-right in the image.
    v = np.array([[0.5, 0.5, -1.0], [0.9, 0.5, -1.0], [0.5, 0.9, -1.0]])
    _, ids = render_ids(v, np.array([[0, 1, 2]]), O3, I3, 8, 8)
    rows, cols = np.nonzero(ids == 0)
    assert len(rows) and rows.max() < 4 and cols.min() >= 4


def test_nearer_triangle_wins_and_depth_is_exact():
    far = [[-3, -3, -6.0], [3, -3, -6.0], [0, 3, -6.0]]
    near = [[-1, -1, -3.0], [1, -1, -3.0], [0, 1, -3.0]]
    for order in ([far, near], [near, far]):
        v = np.array(order[0] + order[1], dtype=np.float64)
        faces = np.array([[0, 1, 2], [3, 4, 5]])
        depth, ids = render_ids(v, faces, O3, I3, 32, 32)
        near_id = 1 if order[1] is near else 0
        both = ids == near_id
        assert both.sum() > 10
        np.testing.assert_allclose(depth[both], 3.0, rtol=1e-6)
        np.testing.assert_allclose(depth[ids == 1 - near_id], 6.0, rtol=1e-6)


def test_slanted_triangle_depth_is_perspective_correct():
    v = np.array([[-5, -1, -2.0], [5, -1, -20.0], [0, 6, -8.0]])
    f = np.array([[0, 1, 2]])
    depth, ids = render_ids(v, f, O3, I3, 40, 30, tan_x=1.3, tan_y=0.9)
    ref_depth, ref_ids = ray_cast(v, f, O3, I3, 40, 30, 1.3, 0.9)
    both = (ids == 0) & (ref_ids == 0)
    assert both.sum() > 100
    np.testing.assert_allclose(depth[both], ref_depth[both], rtol=1e-6)


def test_triangle_crossing_the_near_plane_matches_a_ray_cast():
    # One corner behind the eye, one beside it, one far ahead: the triangle crosses z = -near.
    v = np.array([[-0.5, -0.3, 2.0], [3.0, -0.4, -0.02], [0.2, 0.8, -9.0]])
    f = np.array([[0, 1, 2]])
    for near in (DEFAULT_NEAR, 0.5):
        depth, ids = render_ids(v, f, O3, I3, 64, 64, near=near)
        ref_depth, ref_ids = ray_cast(v, f, O3, I3, 64, 64, near=near)
        assert (ref_ids == 0).sum() > 200
        assert np.mean(ids == ref_ids) >= 0.998
        both = (ids == 0) & (ref_ids == 0)
        np.testing.assert_allclose(depth[both], ref_depth[both], rtol=1e-6)
        assert depth[ids == 0].min() >= near * (1 - 1e-6)


def test_triangle_wholly_behind_the_near_plane_is_dropped():
    v = np.array([[-1, -1, -0.01], [1, -1, -0.02], [0, 1, 3.0]])
    depth, ids = render_ids(v, np.array([[0, 1, 2]]), O3, I3, 16, 16)
    assert np.all(ids == -1) and np.all(np.isinf(depth))


def test_no_back_face_culling():
    v = np.array([[-1, -1, -3.0], [1, -1, -3.0], [0, 1, -3.0]])
    _, a = render_ids(v, np.array([[0, 1, 2]]), O3, I3, 16, 16)
    _, b = render_ids(v, np.array([[0, 2, 1]]), O3, I3, 16, 16)
    assert (a == 0).sum() > 5
    np.testing.assert_array_equal(a, b)


# ----------------------------------------------------------------------------- fill rule
def coverage_counts(v, faces, width, height, **kw):
    """(H, W) how many of the faces cover each pixel, each face rendered alone."""
    total = np.zeros((height, width), dtype=np.int64)
    for f in faces:
        _, ids = render_ids(v, np.asarray([f]), O3, I3, width, height, **kw)
        total += ids >= 0
    return total


def test_shared_diagonal_through_pixel_centres_covers_each_centre_once():
    # A square bigger than the view, split along x = y: 8 pixel centres lie exactly on the edge.
    v = np.array([[-2, -2, -1.0], [2, -2, -1.0], [2, 2, -1.0], [-2, 2, -1.0]])
    for faces in ([[0, 1, 2], [0, 2, 3]], [[2, 1, 0], [0, 3, 2]], [[1, 2, 0], [3, 2, 0]]):
        counts = coverage_counts(v, faces, 8, 8)
        np.testing.assert_array_equal(counts, 1)
        _, ids = render_ids(v, np.array(faces), O3, I3, 8, 8)
        assert np.all(ids >= 0)


def test_fan_around_a_pixel_centre_covers_each_centre_once():
    # Triangles around a vertex exactly on a pixel centre of a 16x16 view (centres sit at odd
    # multiples of 1/16 at z = -1); the axis and diagonal spokes run through rows of centres.
    c = np.array([1 / 16, 1 / 16, -1.0])
    spokes = [(3, 0), (3, 1.3), (3, 3), (0.7, 3), (0, 3), (-3, 3), (-3, 0.4), (-3, 0),
              (-3, -3), (-1.1, -3), (0, -3), (3, -3)]
    ring = np.array([[c[0] + x, c[1] + y, -1.0] for x, y in spokes])
    v = np.vstack([c, ring])
    n = len(spokes)
    faces = [[0, 1 + k, 1 + (k + 1) % n] for k in range(n)]
    counts = coverage_counts(v, faces, 16, 16)
    np.testing.assert_array_equal(counts, 1)


def grid_mesh(pts, n):
    v = np.column_stack([pts, np.full(len(pts), -1.0)])
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j
            faces += [[a, b, c], [a, c, d]] if (i + j) % 2 else [[a, b, d], [b, c, d]]
    return v, faces


def test_perturbed_grid_mesh_covers_each_centre_once():
    rng = np.random.default_rng(3)
    n = 7
    g = np.linspace(-1.5, 1.5, n)
    xx, yy = np.meshgrid(g, g)
    pts = np.stack([xx.ravel(), yy.ravel()], axis=1)
    inner = (np.abs(pts) < 1.4).all(axis=1)
    pts[inner] += rng.uniform(-0.15, 0.15, (inner.sum(), 2))
    v, faces = grid_mesh(pts, n)
    np.testing.assert_array_equal(coverage_counts(v, faces, 24, 24), 1)


def test_grid_mesh_with_corners_on_pixel_centres_covers_each_centre_once():
    # Corners exactly on pixel centres (odd multiples of 1/32 at z = -1 for 32 px) and every
    # edge through a row of centres: the arithmetic is exact, so the top-left rule alone decides
    # every vertex and edge pixel. (A corner only within rounding, ~1e-16, of a centre is not
    # decided exactly: that pixel may go to none or two of its triangles.)
    n = 7
    g = (np.array([-40, -19, -9, 1, 7, 15, 40]) * 2 + 1) / 32
    xx, yy = np.meshgrid(g, g[::-1] * 1.0)
    v, faces = grid_mesh(np.stack([xx.ravel(), yy.ravel()], axis=1), n)
    np.testing.assert_array_equal(coverage_counts(v, faces, 32, 32), 1)


# ----------------------------------------------------------------------------- precision
@pytest.mark.parametrize("offset", [1e5, 1e7])
def test_large_coordinate_offset_gives_the_same_image(offset):
    rng = np.random.default_rng(5)
    # Coordinates on a 1/64 m lattice stay exact after the offset: the images must be identical.
    v, f = random_scene(rng, m=120, spread=4.0, size=0.8)
    v = np.round(v * 64) / 64
    eye = np.array([0.25, 0.5, 0.125])
    rot = random_rotation(rng)
    shift = np.array([offset, -offset / 3, offset])
    shift = np.round(shift * 64) / 64
    d0, i0 = render_ids(v, f, eye, rot, 48, 48)
    d1, i1 = render_ids(v + shift, f, eye + shift, rot, 48, 48)
    assert (i0 >= 0).mean() > 0.3
    np.testing.assert_array_equal(i0, i1)
    np.testing.assert_array_equal(d0, d1)
    # Arbitrary coordinates: rounding at the offset moves vertices by < 1e-8 m only.
    v2, f2 = random_scene(rng, m=120, spread=4.0, size=0.8)
    d0, i0 = render_ids(v2, f2, eye, rot, 48, 48)
    d1, i1 = render_ids(v2 + shift, f2, eye + shift, rot, 48, 48)
    assert np.mean(i0 == i1) >= 0.999


# ----------------------------------------------------------------------------- against a ray cast
def test_random_scenes_agree_with_brute_force_ray_casting():
    rng = np.random.default_rng(11)
    agree = total = 0
    for _ in range(6):
        v, f = random_scene(rng)
        eye = rng.uniform(-1, 1, 3)
        rot = random_rotation(rng)
        depth, ids = render_ids(v, f, eye, rot, 40, 32, tan_x=1.2, tan_y=0.8)
        ref_depth, ref_ids = ray_cast(v, f, eye, rot, 40, 32, 1.2, 0.8)
        agree += np.count_nonzero(ids == ref_ids)
        total += ids.size
        same = (ids == ref_ids) & (ids >= 0)
        np.testing.assert_allclose(depth[same], ref_depth[same], rtol=1e-5)
        np.testing.assert_array_equal(np.isinf(depth), ids < 0)
    assert agree / total >= 0.995


# ----------------------------------------------------------------------------- cubemaps
def test_cube_faces_together_see_every_direction():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    eye = np.array([0.3, -0.2, 0.1])
    rng = np.random.default_rng(2)
    for base in (None, random_rotation(rng)):
        depth, ids = render_cubemap(sphere.vertices + eye, sphere.faces, eye, 24, base)
        assert depth.shape == ids.shape == (6, 24, 24)
        assert np.all(ids >= 0)
        # Distance from the eye = depth x length of the pixel's ray: within the sphere's shell.
        dist = depth * np.linalg.norm(pixel_rays(24, 24), axis=-1)
        assert np.all((dist > 9.0) & (dist < 10.5))


def test_cubemap_faces_equal_single_views_and_point_the_right_way():
    rng = np.random.default_rng(4)
    v, f = random_scene(rng, m=100)
    eye = np.array([0.1, 0.2, -0.3])
    base = random_rotation(rng)
    depth, ids = render_cubemap(v, f, eye, 20, base)
    for k, rot in enumerate(cube_face_rotations(base)):
        d1, i1 = render_ids(v, f, eye, rot, 20, 20)
        np.testing.assert_array_equal(ids[k], i1)
        np.testing.assert_array_equal(depth[k], d1)
    np.testing.assert_array_equal(render_cubemap_ids(v, f, eye, 20, base), ids)
    # A triangle straight along +X (identity cube) shows up in face 0 only.
    tri = np.array([[5.0, -2.0, -2.0], [5.0, 2.0, -2.0], [5.0, 0.0, 2.0]])
    _, ids = render_cubemap(tri, np.array([[0, 1, 2]]), O3, 16)
    assert (ids[0] == 0).sum() > 10 and np.all(ids[1:] == -1)


# ----------------------------------------------------------------------------- ties and options
def test_exact_depth_ties_go_to_the_smaller_id():
    v = np.array([[-2, -2, -3.0], [2, -2, -3.0], [0, 2, -3.0]])
    v = np.vstack([v, v])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    _, ids = render_ids(v, faces, O3, I3, 16, 16)
    assert set(np.unique(ids)) == {-1, 0}
    _, ids = render_ids(v, faces, O3, I3, 16, 16, face_ids=np.array([9, 4], dtype=np.int32))
    assert set(np.unique(ids)) == {-1, 4}


def test_face_mask_and_face_ids():
    rng = np.random.default_rng(8)
    v, f = random_scene(rng, m=60)
    rot = look_rotation([0.2, 0.1, -1.0])
    mask = np.zeros(len(f), dtype=bool)
    mask[::2] = True
    _, ids = render_ids(v, f, O3, rot, 32, 32, face_mask=mask)
    drawn = ids[ids >= 0]
    assert len(drawn) and np.all(drawn % 2 == 0)
    _, ref = render_ids(v[f[mask]].reshape(-1, 3), np.arange(3 * mask.sum()).reshape(-1, 3),
                        O3, rot, 32, 32)
    np.testing.assert_array_equal(np.where(ref >= 0, np.flatnonzero(mask)[ref], -1), ids)
    labels = np.arange(len(f), dtype=np.int32) + 1000
    _, lab = render_ids(v, f, O3, rot, 32, 32, face_ids=labels)
    _, plain = render_ids(v, f, O3, rot, 32, 32)
    np.testing.assert_array_equal(lab, np.where(plain >= 0, plain + 1000, -1))


def test_result_does_not_depend_on_threads_or_batches(monkeypatch):
    rng = np.random.default_rng(9)
    v, f = random_scene(rng, m=400, size=2.0)
    # Duplicated faces make exact depth ties: the winner must still be deterministic.
    f = np.vstack([f, f[::-1]])
    rot = random_rotation(rng)
    d0, i0 = render_ids(v, f, O3, rot, 64, 64)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        d1, i1 = render_ids(v, f, O3, rot, 64, 64)
    finally:
        numba.set_num_threads(threads)
    monkeypatch.setattr(raster, "BATCH", 37)
    d2, i2 = render_ids(v, f, O3, rot, 64, 64)
    # Small jobs run on one thread; force the parallel path (pool of workers) as well.
    monkeypatch.setattr(raster, "PARALLEL_MIN_TRIANGLES", 0)
    monkeypatch.setattr(raster, "PARALLEL_MIN_PIXELS", 0)
    d3, i3 = render_ids(v, f, O3, rot, 64, 64)
    for d, i in ((d1, i1), (d2, i2), (d3, i3)):
        np.testing.assert_array_equal(i0, i)
        np.testing.assert_array_equal(d0, d)
    assert i0.max() < 400, "ties between duplicates must go to the smaller id"


def test_degenerate_faces_are_skipped_without_nan():
    v = np.array(
        [[-1, -1, -3.0], [1, -1, -3.0], [0, 1, -3.0],  # a good face
         [np.nan, 0, -2.0], [np.inf, 1, -2.0], [0, -np.inf, -2.0],
         [-1, -1, -2.0], [1, 1, -2.0], [2, 2, -2.0]]  # collinear: zero area
    )
    faces = np.array([[0, 1, 2], [3, 1, 2], [4, 5, 0], [6, 7, 8], [6, 6, 7], [0, 1, 99],
                      [-5, 1, 2]])
    stats: dict = {}
    depth, ids = render_ids(v, faces, O3, I3, 32, 32, stats=stats)
    assert set(np.unique(ids)) == {-1, 0}
    assert not np.isnan(depth).any()
    assert stats["triangles"] == 7 and stats["pixels"] == 32 * 32
    depth, ids = render_cubemap(v, faces, np.array([0.0, 0.0, 0.5]), 16)
    assert set(np.unique(ids)) <= {-1, 0} and not np.isnan(depth).any()
    # Faces in a larger integer type, indices beyond int32, empty input.
    big = np.array([[0, 1, 2], [0, 1, 2**40]], dtype=np.int64)
    _, ids = render_ids(v, big, O3, I3, 8, 8)
    assert set(np.unique(ids)) <= {-1, 0}
    depth, ids = render_ids(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), O3, I3, 4, 4)
    assert np.all(ids == -1) and np.all(np.isinf(depth))


def test_bad_arguments_raise_value_errors():
    v = np.zeros((3, 3))
    f = np.array([[0, 1, 2]])
    bad = [
        dict(vertices=np.zeros((3, 2))),
        dict(faces=np.array([[0.0, 1.0, 2.0]])),
        dict(eye=np.array([np.nan, 0, 0])),
        dict(rotation=np.ones((3, 3))),
        dict(width=0),
        dict(height=2.5),
        dict(near=0.0),
        dict(tan_x=-1.0),
        dict(face_mask=np.ones(2, dtype=bool)),
        dict(face_mask=np.ones(1, dtype=np.int32)),
        dict(face_ids=np.zeros(3, dtype=np.int32)),
        dict(face_ids=np.array([-1])),
        dict(face_ids=np.array([2**40])),
    ]
    base = dict(vertices=v, faces=f, eye=O3, rotation=I3, width=4, height=4)
    for kw in bad:
        with pytest.raises(ValueError):
            render_ids(**{**base, **kw})
    with pytest.raises(ValueError):
        render_cubemap(v, f, O3, 0)
    with pytest.raises(ValueError):
        render_cubemap(v, f, O3, 8, base_rotation=np.zeros((3, 3)))


def test_random_rotations_are_the_loops_draws_vectorized():
    """Same rotations as one ``random_rotation`` per draw (a seed keeps its views), orthonormal
    with determinant 1."""
    from visibility.raster.camera import random_rotation, random_rotations

    a, b = np.random.default_rng(5), np.random.default_rng(5)
    loop = np.stack([random_rotation(a) for _ in range(50)])
    many = random_rotations(b, 50)
    np.testing.assert_allclose(many, loop, atol=1e-12)
    assert a.normal() == b.normal()  # the generators are at the same place
    np.testing.assert_allclose(many @ many.transpose(0, 2, 1), np.broadcast_to(np.eye(3),
                               (50, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(many), 1.0)
