"""T-junctions cut (``visibility.tjunctions``): where, into what, and what is left alone."""

from __future__ import annotations

import numpy as np

from visibility.cores.cos.fusion import open_edge_share
from visibility.scene import Scene
from visibility.tjunctions import edge_points, scene_t_split, split_t_junctions
from visibility.topology import weld_vertices


def _seamed_wall(dy: float = 0.0) -> Scene:
    """A wall in z = -3 of a left quad (x <= 0, one edge from y = -5 to 15 along x = 0) and two
    right quads meeting at (0, 5 + dy) on that line: a T-junction when ``dy`` is 0."""
    v = np.array([
        [-20, -5, -3], [0, -5, -3], [0, 15, -3], [-20, 15, -3],  # left quad
        [0, 5 + dy, -3], [20, -5, -3], [20, 5, -3], [20, 15, -3],  # right quads' own corners
    ], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3],  # left: edge 1 -> 2 along x = 0
                  [1, 5, 6], [1, 6, 4],  # lower right: edge 4 -> 1 along x = 0
                  [4, 6, 7], [4, 7, 2]])  # upper right: edge 2 -> 4 along x = 0
    return Scene(v, f)


def _areas(tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def test_a_t_junction_is_cut_into_pieces_that_tile_the_triangle_and_share_the_seam():
    scene = _seamed_wall()
    split = split_t_junctions(scene)
    assert split.cut == 1
    # The left triangle holding the long edge becomes a fan of 4 (its 3 corners and the point).
    assert np.bincount(split.source, minlength=6).tolist() == [4, 1, 1, 1, 1, 1]
    got = np.bincount(split.source, weights=_areas(split.scene.triangles()), minlength=6)
    assert np.allclose(got, _areas(scene.triangles()), rtol=0, atol=1e-12)
    # The seam is a run of shared edges now: only the wall's outline stays open.
    assert open_edge_share(split.scene) < open_edge_share(scene)
    f = split.scene.faces
    ids = weld_vertices(split.scene.vertices)
    und = np.sort(ids[np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])], axis=1)
    edges, counts = np.unique(und, axis=0, return_counts=True)
    shared = {tuple(e) for e in edges[counts == 2].tolist()}
    seam = {tuple(sorted((int(ids[1]), int(ids[4])))), tuple(sorted((int(ids[4]), int(ids[2]))))}
    assert seam <= shared
    # Cached per scene object.
    assert scene_t_split(scene)[0] is scene_t_split(scene)[0]


def test_a_corner_a_millimetre_off_the_edge_is_a_slit_and_left_alone():
    scene = _seamed_wall(dy=0.0)
    scene.vertices[4, 0] = 1e-3
    split = split_t_junctions(scene)
    assert split.cut == 0 and split.source is None and split.scene is scene


def test_a_corner_within_rounding_of_the_edge_is_on_it():
    # Coordinates with no exact binary form: the point lies on the edge up to rounding.
    v = np.array([[0.1, 0.3, 0.7], [1.1, 2.3, -0.7]])
    p = v[0] + (v[1] - v[0]) * (1.0 / 3.0)
    pts = np.vstack([v, p, p + np.array([0.0, 1e-6, 0.0])])
    e, point, t = edge_points(pts, np.array([[0, 1]]), weld_vertices(pts))
    assert point.tolist() == [2]
    assert np.allclose(t, [1.0 / 3.0])


def test_only_an_open_edge_with_another_open_edge_along_it_is_a_seam():
    # A ridge (edge 0-1, held by two triangles) touched in its middle by the corner of a
    # third triangle standing on it: no silhouette runs along the ridge, nothing to close.
    v = np.array([[0, 0, 0], [2, 0, 0], [1, 1, 0], [1, -1, 0], [1, 0, 0], [1.5, 0, 0],
                  [1.2, -0.5, 0], [1.2, -0.5, 1]], dtype=float)
    split = split_t_junctions(Scene(v, np.array([[0, 1, 2], [1, 0, 3], [4, 6, 5]])))
    assert split.cut == 0
    # Held by one triangle only, the same edge is a seam (the third triangle's edge 5-4 runs
    # back along it) and is cut.
    assert split_t_junctions(Scene(v, np.array([[0, 1, 2], [4, 6, 5]]))).cut == 1
    # A corner touching it from another direction (a pole's foot on a kerb) is no seam.
    assert split_t_junctions(Scene(v, np.array([[0, 1, 2], [4, 6, 7]]))).cut == 0


def test_keyframed_scenes_and_spheres():
    scene = _seamed_wall()
    moving = Scene(scene.vertices, scene.faces,
                   states=np.stack([scene.vertices, scene.vertices + 1.0]))
    assert split_t_junctions(moving).cut == 0
    balls = Scene(scene.vertices, scene.faces, sphere_centers=np.array([[[1.0, 2.0, -9.0]]]),
                  sphere_radii=np.array([0.5]))
    split = split_t_junctions(balls)
    assert split.cut == 1
    assert np.array_equal(split.scene.sphere_centers, balls.sphere_centers)
    assert np.array_equal(split.scene.sphere_radii, balls.sphere_radii)


def test_a_handful_of_seams_in_a_large_scene_is_left_alone():
    # One seamed triangle among 2,006: under MIN_CUT_SHARE, the scene stays whole (a cut
    # scene builds its hierarchy and closed parts again).
    wall = _seamed_wall()
    rng = np.random.default_rng(0)
    far = 100.0 * rng.random((2000, 1, 3)) + 0.1 * rng.random((2000, 3, 3)) + [200.0, 0, 0]
    v = np.concatenate([wall.vertices, far.reshape(-1, 3)])
    f = np.concatenate([wall.faces, 8 + np.arange(6000).reshape(-1, 3)])
    assert split_t_junctions(Scene(v, f)).cut == 0
    assert split_t_junctions(Scene(v[:8 + 600], f[:6 + 200])).cut == 1
