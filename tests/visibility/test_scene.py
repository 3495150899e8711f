import numpy as np
import pytest

from visibility.scene import Scene, WalkArea


def tri_scene(**kw):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [np.nan, 0, 0]], float)
    f = np.array([[0, 1, 2], [0, 1, 3], [1, 1, 2], [0, 4, 2], [0, 1, 7]])
    return Scene(v, f, **kw)


def test_degenerate_faces_are_reported_and_kept_out():
    s = tri_scene()
    np.testing.assert_array_equal(s.valid_faces, [True, False, False, False, False])
    rep = s.degenerate_report.as_dict()
    assert rep == {"zero_area": 1, "non_finite": 1, "repeated_index": 1, "out_of_range": 1}
    # Ids stay stable: the degenerate rows are still there.
    assert s.n_triangles == 5
    assert np.all(np.isfinite(s.bounds()))


def test_defaults_and_dtypes():
    s = tri_scene()
    assert s.vertices.dtype == np.float64 and s.faces.dtype == np.int32
    assert s.object_ids.shape == (5,) and s.colors.shape == (5, 3) and s.colors.dtype == np.uint8
    assert not s.is_dynamic


def test_dynamic_states_interpolate_linearly():
    v0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    states = np.stack([v0, v0 + [0, 0, 2], v0 + [0, 0, 4]])
    s = Scene(v0, [[0, 1, 2]], states=states, state_times=[0.0, 1.0, 3.0])
    assert s.is_dynamic
    np.testing.assert_allclose(s.vertices_at(0.5)[:, 2], 1.0)
    np.testing.assert_allclose(s.vertices_at(2.0)[:, 2], 3.0)
    np.testing.assert_allclose(s.vertices_at(99.0)[:, 2], 4.0)  # clamped
    with pytest.raises(ValueError):
        Scene(v0, [[0, 1, 2]], states=states, state_times=[0.0, 2.0, 1.0])
    with pytest.raises(ValueError):
        Scene(v0, [[0, 1, 2]], states=states[:, :2])


def test_moving_face_with_area_in_one_state_is_valid():
    v0 = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)  # collinear at rest
    v1 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    s = Scene(v0, [[0, 1, 2]], states=np.stack([v0, v1]))
    assert s.valid_faces.all()


def test_spheres_and_bounds():
    s = Scene(
        np.zeros((0, 3)),
        np.zeros((0, 3), int),
        sphere_centers=[[[0, 0, 0], [10, 0, 0]]],
        sphere_radii=[1.0, 2.0],
    )
    assert s.n_spheres == 2
    np.testing.assert_allclose(s.bounds(), [[-1, -2, -2], [12, 2, 2]])


def test_subset_renumbers():
    s = tri_scene(colors=np.arange(15).reshape(5, 3))
    sub = s.subset([0])
    assert sub.n_triangles == 1 and sub.n_vertices == 3
    np.testing.assert_array_equal(sub.colors[0], [0, 1, 2])


def test_walk_area_validation():
    w = WalkArea([[0, 0, 1, 1, 0]])
    assert w.rects.shape == (1, 6) and np.isinf(w.rects[0, 5])
    with pytest.raises(ValueError):
        WalkArea([[0, 0, 1, 1]])
    with pytest.raises(ValueError):
        WalkArea([[0, 0, np.nan, 1, 0]])
