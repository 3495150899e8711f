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


def test_static_vertices_stay_bit_for_bit_between_keyframes():
    # The hierarchy of the static faces recognises its vertices exactly (Hierarchy.matches):
    # a vertex that does not move keeps its value at every time, and keyframes are exact.
    rng = np.random.default_rng(0)
    v0 = rng.uniform(-1e3, 1e3, (50, 3))
    moved = v0.copy()
    moved[:10] += rng.normal(size=(10, 3))
    s = Scene(v0, [[0, 1, 2]], states=np.stack([v0, moved, v0]), state_times=[0.0, 0.7, 3.1])
    for t in rng.uniform(-1.0, 4.0, 40):
        assert np.array_equal(s.vertices_at(t)[10:], v0[10:])
    assert np.array_equal(s.vertices_at(0.7), moved)
    assert np.array_equal(s.vertices_at(3.1), v0)


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


# ----------------------------------------------------------------------------- memory
def _messy_scene(states: bool = False, spheres: bool = False) -> Scene:
    """600 random faces over 200 vertices (4 NaN), with out-of-range, repeated-index and
    zero-area rows; optionally 3 keyframes (one vertex NaN in the last) and 5 spheres."""
    rng = np.random.default_rng(7)
    v = rng.uniform(-50, 50, (200, 3)) + [1e6, 0.0, 5e6]
    v[[3, 50, 120, 199]] = np.nan
    f = rng.integers(0, 200, (600, 3))
    f[::37, 2] = 250  # out of range
    f[5::41, 1] = f[5::41, 0]  # repeated index
    v[10] = (v[11] + v[12]) / 2
    f[7] = [10, 11, 12]  # collinear: zero area
    kw = {}
    if states:
        st = np.stack([v, v + [0.0, 0.0, 3.0], v * [1.0, 2.0, 1.0]])
        st[2, 7] = np.nan
        kw.update(states=st, state_times=[0.0, 1.0, 2.5])
    if spheres:
        kw.update(sphere_centers=rng.uniform(-5, 5, (1, 5, 3)), sphere_radii=np.ones(5))
    return Scene(v, f, object_ids=np.arange(600) % 9, **kw)


def _passes(scene: Scene) -> tuple:
    from visibility.scene import scene_fingerprint

    return (scene.valid_faces.copy(), scene.degenerate_report, scene.bounds(),
            scene_fingerprint(scene), scene.centroids(), scene.used_vertices())


@pytest.mark.parametrize("states, spheres", [(False, False), (True, False), (False, True)])
def test_block_passes_equal_one_pass_over_the_whole_arrays(monkeypatch, states, spheres):
    import visibility.scene as scene_module

    monkeypatch.setattr(scene_module, "FACE_BLOCK", 1 << 30)
    whole = _passes(_messy_scene(states, spheres))
    monkeypatch.setattr(scene_module, "FACE_BLOCK", 7)
    blocks = _passes(_messy_scene(states, spheres))
    assert whole[1].total_reasons > 0 and not whole[0].all()
    for a, b in zip(whole, blocks, strict=True):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b


def test_fingerprint_is_the_hash_of_the_whole_arrays():
    # The fingerprint keys on-disk and Redis caches: hashing by blocks must not change it.
    import hashlib

    from visibility.scene import scene_fingerprint

    for s in (_messy_scene(), _messy_scene(states=True), _messy_scene(spheres=True)):
        h = hashlib.blake2b(digest_size=8)
        for arr, dtype in ((s.vertices, np.float64), (s.faces, np.int64),
                           (s.object_ids, np.int32), (s.states, np.float64),
                           (s.sphere_centers, np.float64), (s.sphere_radii, np.float64)):
            if arr is None:
                h.update(b"-")
                continue
            a = np.ascontiguousarray(arr, dtype=dtype)
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())
        assert scene_fingerprint(s) == h.hexdigest()


def test_int32_faces_are_kept_not_copied_and_others_convert():
    v = np.zeros((4, 3))
    f = np.array([[0, 1, 2], [1, 2, 3]], dtype=np.int32)
    assert np.shares_memory(Scene(v, f).faces, f)
    for other in (f.astype(np.int64), f.astype(np.uint16), f.tolist(), f.astype(float),
                  f.reshape(-1)):
        s = Scene(v, other)
        assert s.faces.dtype == np.int32 and s.faces.flags.c_contiguous
        np.testing.assert_array_equal(s.faces, f)
    # A strided int32 view is made contiguous (the rasterizer needs C order).
    wide = np.zeros((2, 6), dtype=np.int32)
    wide[:, ::2] = f
    s = Scene(v, wide[:, ::2])
    assert s.faces.flags.c_contiguous
    np.testing.assert_array_equal(s.faces, f)


def test_centroids_are_the_corner_means_and_nan_out_of_range():
    s = _messy_scene(states=True)
    ok = np.all((s.faces >= 0) & (s.faces < s.n_vertices), axis=1)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(s.centroids()[ok], s.triangles(np.flatnonzero(ok))
                                      .mean(axis=1))
        np.testing.assert_array_equal(s.centroids(t=1.7)[ok],
                                      s.triangles(np.flatnonzero(ok), t=1.7).mean(axis=1))
    assert np.isnan(s.centroids()[~ok]).all() and (~ok).any()


def test_used_vertices_are_the_corners_of_valid_faces():
    s = _messy_scene()
    expect = np.zeros(s.n_vertices, dtype=bool)
    expect[np.unique(s.faces[s.valid_faces])] = True
    np.testing.assert_array_equal(s.used_vertices(), expect)
