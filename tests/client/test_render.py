"""Tests of client.render: analytic coverage and depth, conventions, precision, caching."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from client.render import BACKGROUND, OffscreenRenderer, shade_colors
from visibility.raster.camera import look_rotation, pixel_rays
from visibility.scene import Scene

W = H = 64


@pytest.fixture(scope="module")
def renderer():
    r = OffscreenRenderer(W, H, yfov_deg=90.0)
    yield r
    r.close()


def _ray_hits(tris: np.ndarray, eye, forward, w=W, h=H, tan=1.0):
    """(H, W) depth of the nearest triangle hit per pixel-centre ray (inf when none), and the
    (H, W) smallest barycentric coordinate of that hit (how far inside the triangle it is)."""
    rot = look_rotation(forward)
    rays_cam = pixel_rays(w, h, tan, tan)  # z = -1, so ray parameter = view depth
    rays = rays_cam @ rot  # camera -> world (rows of rot are the camera axes)
    depth = np.full((h, w), np.inf)
    margin = np.full((h, w), -np.inf)
    closest_miss = np.full((h, w), -np.inf)
    for a, b, c in np.asarray(tris, dtype=np.float64):
        e1, e2 = b - a, c - a
        p = np.cross(rays, e2)
        det = p @ e1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = np.asarray(eye, dtype=np.float64) - a
            u = (p @ s) * inv
            q = np.cross(s, e1)
            v = (rays * q).sum(-1) * inv
            d = (q @ e2) * inv
        bary = np.minimum(np.minimum(u, v), 1 - u - v)
        bary = np.where(np.isfinite(bary), bary, -np.inf)
        hit = (bary >= 0) & (d > 0) & (d < depth)
        depth[hit] = d[hit]
        margin[hit] = bary[hit]
        closest_miss = np.maximum(closest_miss, np.where(d > 0, bary, -np.inf))
    return depth, np.where(np.isfinite(depth), margin, closest_miss)


def test_known_triangle_coverage_depth_and_colour(renderer):
    tri = np.array([[[-1.0, -1.0, -2.0], [1.5, -0.5, -2.0], [0.0, 1.2, -3.0]]])
    col = np.array([[250, 40, 10]], dtype=np.uint8)
    f = renderer.render(tri, col, [0, 0, 0], [0, 0, -1])
    assert f.color.shape == (H, W, 3) and f.color.dtype == np.uint8
    assert f.depth.shape == (H, W) and f.depth.dtype == np.float32
    ref, margin = _ray_hits(tri, [0, 0, 0], [0, 0, -1])
    covered = np.isfinite(f.depth)
    sure = np.abs(margin) > 1e-3  # pixel centres clearly inside or outside
    assert np.array_equal(covered[sure], np.isfinite(ref)[sure])
    assert 300 < covered.sum() < H * W
    # Depth of pixel (32, 32): its centre ray (1/64, -1/64, -1) against the triangle's plane.
    np.testing.assert_allclose(f.depth[32, 32], ref[32, 32], rtol=1e-4)
    both = covered & np.isfinite(ref)
    np.testing.assert_allclose(f.depth[both], ref[both], rtol=2e-4)
    # Flat colour = face colour with the baked lambert term; background elsewhere.
    expect = shade_colors(tri, col)[0]
    assert np.abs(f.color[covered].astype(int) - expect).max() <= 1
    assert np.all(f.color[~covered] == BACKGROUND)


def test_two_sided_and_orientation(renderer):
    # Triangle at +X, seen looking along +X; its winding faces away from the camera.
    tri = np.array([[[5.0, -1.0, 0.0], [5.0, 1.0, 0.0], [5.0, 0.0, 1.0]]])
    f = renderer.render(tri, np.array([[0, 200, 0]], np.uint8), [0, 0, 0], [1, 0, 0])
    covered = np.isfinite(f.depth)
    assert covered.any()
    np.testing.assert_allclose(f.depth[covered], 5.0, rtol=1e-4)
    # Looking along +X with +Y up, right is +Z: the triangle (z >= 0) is in the right half.
    cols = np.nonzero(covered.any(axis=0))[0]
    assert cols.min() >= W // 2 - 1
    # An object above the eye is in the top rows.
    up = np.array([[[5.0, 2.0, -0.5], [5.0, 3.0, -0.5], [5.0, 2.5, 0.5]]])
    g = renderer.render(up, np.array([[0, 0, 200]], np.uint8), [0, 0, 0], [1, 0, 0])
    rows = np.nonzero(np.isfinite(g.depth).any(axis=1))[0]
    assert rows.max() < H // 2


def _room(offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed 10 m box made of 12 triangles plus a pillar, shifted by ``offset``."""
    import trimesh

    box = trimesh.creation.box(extents=[10.0, 4.0, 10.0])
    pillar = trimesh.creation.box(extents=[0.5, 3.0, 0.5])
    pillar.apply_translation([1.5, 0.0, -2.0])
    tris = np.concatenate([box.triangles, pillar.triangles]) + offset
    rng = np.random.default_rng(1)
    cols = rng.integers(30, 255, size=(len(tris), 3), dtype=np.uint8)
    return tris, cols


def test_large_offset_renders_like_origin(renderer):
    eye = np.array([0.3, 0.2, 3.1])
    fwd = np.array([0.2, -0.1, -1.0])
    tris0, cols = _room(np.zeros(3))
    off = np.array([1e5, 2e3, -1e5])
    tris1, _ = _room(off)
    f0 = renderer.render(tris0, cols, eye, fwd)
    f1 = renderer.render(tris1, cols, eye + off, fwd)
    assert np.isfinite(f0.depth).all()  # inside a closed box: every pixel covered
    same_colour = np.all(f0.color == f1.color, axis=-1).mean()
    assert same_colour > 0.999
    # A few depth-buffer quanta (float32 arithmetic); naive float32 at 1e5 m would be off by cm.
    np.testing.assert_allclose(f1.depth, f0.depth, rtol=1e-4, atol=1e-4)


def test_store_version_caching_counts_uploads():
    r = OffscreenRenderer(32, 32)
    try:
        tris, cols = _room(np.zeros(3))
        eye, fwd = np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0])
        a = r.render(tris, cols, eye, fwd, key="store", version=1)
        assert r.uploads == 1
        for k in range(3):
            r.render(tris, cols, eye + [0.1 * k, 0, 0], fwd, key="store", version=1)
        assert r.uploads == 1
        # The ground-truth scene in between does not evict the store.
        scene = Scene(vertices=tris.reshape(-1, 3), faces=np.arange(len(tris) * 3).reshape(-1, 3))
        r.render_scene(scene, eye, fwd)
        r.render_scene(scene, eye, fwd)
        assert r.uploads == 2
        b = r.render(tris, cols, eye, fwd, key="store", version=1)
        assert r.uploads == 2
        assert np.array_equal(a.color, b.color)
        # A new version is uploaded and shows the new content.
        c = r.render(tris[:-12], cols[:-12], eye, fwd, key="store", version=2)
        assert r.uploads == 3
        assert not np.array_equal(a.depth, c.depth)
        # A changed triangle count also triggers an upload, even with the same version.
        r.render(tris, cols, eye, fwd, key="store", version=2)
        assert r.uploads == 4
        # Ad hoc renders (no key) always upload.
        r.render(tris, cols, eye, fwd)
        r.render(tris, cols, eye, fwd)
        assert r.uploads == 6
        # Moving the eye beyond the recentre distance re-uploads once.
        far = eye + [r.recenter_distance + 5.0, 0, 0]
        r.render(tris, cols, far, fwd, key="store", version=2)
        r.render(tris, cols, far, fwd, key="store", version=2)
        assert r.uploads == 7
    finally:
        r.close()


def test_render_scene_dynamic_and_valid_faces(renderer):
    # Triangle 0 static far away, triangle 1 moves across the view, triangle 2 is degenerate.
    static = [[-4, -4, -10], [4, -4, -10], [0, 4, -10]]  # big, far
    moving = [[-3, -1, -5], [-1, -1, -5], [-2, 1, -5]]  # starts at the left
    degenerate = [[0, 0, -1], [0, 0, -1], [0, 0, -1]]  # right in front
    v0 = np.array(static + moving + degenerate, dtype=np.float64)
    v1 = v0.copy()
    v1[3:6, 0] += 4.0  # moves to the right at t = 1
    scene = Scene(
        vertices=v0,
        faces=np.arange(9).reshape(3, 3),
        colors=np.array([[200, 200, 200], [200, 0, 0], [0, 0, 200]], np.uint8),
        states=np.stack([v0, v1]),
        state_times=np.array([0.0, 1.0]),
    )
    r = OffscreenRenderer(32, 32)
    try:
        f0 = r.render_scene(scene, [0, 0, 0], [0, 0, -1], t=0.0)
        f1 = r.render_scene(scene, [0, 0, 0], [0, 0, -1], t=1.0)
        assert r.uploads == 3  # static once, moving part per t
        near0 = np.isclose(f0.depth, 5.0, rtol=1e-3)
        near1 = np.isclose(f1.depth, 5.0, rtol=1e-3)
        assert near0.any() and near1.any()
        assert np.nonzero(near0)[1].mean() < 16 < np.nonzero(near1)[1].mean()
        # The degenerate face at depth 1 is never drawn.
        assert np.nanmin(f0.depth) > 4.0
        r.render_scene(scene, [0, 0, 0], [0, 0, -1], t=1.0)
        assert r.uploads == 3
    finally:
        r.close()


def test_render_store_at_scene_time_matches_the_scene(renderer):
    """What a store holds (rest geometry + keyframes + spheres) drawn at time t is the scene at t;
    the static layer is uploaded once, the moving one per t."""
    from client.store import GeometryStore

    static = [[-4, -4, -10], [4, -4, -10], [0, 4, -10]]
    moving = [[-3, -1, -5], [-1, -1, -5], [-2, 1, -5]]
    v0 = np.array(static + moving, dtype=np.float64)
    v1 = v0.copy()
    v1[3:6, 0] += 4.0
    centers = np.array([[[2.0, 2.0, -6.0]], [[-2.0, 2.0, -6.0]]])
    scene = Scene(vertices=v0, faces=np.arange(6).reshape(2, 3),
                  colors=np.array([[200, 200, 200], [200, 0, 0]], np.uint8),
                  states=np.stack([v0, v1]), state_times=np.array([0.0, 1.0]),
                  sphere_centers=centers, sphere_radii=np.array([0.5]),
                  sphere_colors=np.array([[0, 0, 250]], np.uint8))
    store = GeometryStore()
    store.add(np.arange(2), scene.triangles(), scene.colors)
    store.add_keyframes(np.array([1]), scene.state_times, scene.states[:, scene.faces[1:]])
    store.add_spheres(np.array([0]), scene.sphere_times, centers, scene.sphere_radii,
                      scene.sphere_colors)
    r = OffscreenRenderer(32, 32)
    try:
        frames = {}
        for t in (0.0, 0.3, 1.0):
            got = r.render_store(store, [0, 0, 0], [0, 0, -1], t=t)
            want = r.render_scene(scene, [0, 0, 0], [0, 0, -1], t=t)
            np.testing.assert_array_equal(got.color, want.color)
            np.testing.assert_allclose(got.depth, want.depth, rtol=1e-5)
            frames[t] = got
        assert not np.array_equal(frames[0.0].color, frames[1.0].color)  # it does move
        before = r.uploads
        r.render_store(store, [0, 0, 0], [0, 0, -1], t=0.6)
        assert r.uploads == before + 2  # moving layer and spheres, not the static layer
        rest = r.render_store(store, [0, 0, 0], [0, 0, -1])
        np.testing.assert_array_equal(rest.color, frames[0.0].color)
    finally:
        r.close()


def test_render_scene_spheres(renderer):
    scene = Scene(
        vertices=np.array([[-50, -50, -40], [50, -50, -40], [0, 50, -40]], float),
        faces=np.array([[0, 1, 2]]),
        sphere_centers=np.array([[[0.0, 0.0, -10.0]]]),
        sphere_radii=np.array([2.0]),
    )
    f = renderer.render_scene(scene, [0, 0, 0], [0, 0, -1])
    centre = f.depth[H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1]
    np.testing.assert_allclose(centre, 8.0, atol=0.1)  # icosphere ~ sphere
    assert np.isclose(f.depth, 40.0, rtol=1e-3).any()  # the backdrop around it


def test_empty_and_bad_input(renderer):
    f = renderer.render(np.zeros((0, 3, 3)), np.zeros((0, 3), np.uint8), [0, 0, 0], [0, 0, -1])
    assert np.isinf(f.depth).all()
    assert np.all(f.color == BACKGROUND)
    tri = np.zeros((1, 3, 3))
    with pytest.raises(ValueError):
        renderer.render(tri, np.zeros((2, 3), np.uint8), [0, 0, 0], [0, 0, -1])
    with pytest.raises(ValueError):
        renderer.render(np.zeros((1, 4, 3)), np.zeros((1, 3), np.uint8), [0, 0, 0], [0, 0, -1])
    with pytest.raises(ValueError):
        renderer.render(tri, np.zeros((1, 3), np.uint8), [np.nan, 0, 0], [0, 0, -1])
    with pytest.raises(ValueError):
        renderer.render(tri, np.zeros((1, 3), np.uint8), [0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        OffscreenRenderer(0, 10)


def test_threads_and_close():
    r = OffscreenRenderer(32, 32)
    tris, cols = _room(np.zeros(3))
    views = [([0.0, 0.0, 2.0], [np.sin(a), 0.0, -np.cos(a)]) for a in np.linspace(0, 3, 8)]
    serial = [r.render(tris, cols, e, f, key="room", version=0) for e, f in views]
    with ThreadPoolExecutor(4) as ex:
        par = list(ex.map(lambda v: r.render(tris, cols, *v, key="room", version=0), views))
    for a, b in zip(serial, par, strict=True):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.color, b.color)
    assert r.uploads == 1
    r.close()
    with pytest.raises(RuntimeError):
        r.render(tris, cols, [0, 0, 0], [0, 0, -1])
