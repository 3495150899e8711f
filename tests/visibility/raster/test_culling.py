"""Culled renders equal full renders bit for bit (ids and depth): on generated scenes, on the
real scenes beside the repository, at georeferenced offsets, with masks and moving faces,
and with the eye inside geometry; and culling does skip work where walls close the view."""

from __future__ import annotations

import numpy as np
import pytest

from tests.visibility.real_scenes import REAL, real_grid, real_scene
from visibility.generators import make_scene
from visibility.generators._mesh import box_mesh
from visibility.raster.camera import look_rotation, random_rotation
from visibility.raster.culling import Coherence
from visibility.raster.hierarchy import build_hierarchy, scene_hierarchy
from visibility.raster.render import render_cubemap, render_cubemap_ids, render_ids
from visibility.scene import Scene, moving_faces
from visibility.viewcells import ViewcellGrid


def _eyes(grid, n, rng):
    """Eyes drawn uniformly in ``n`` cells of ``grid`` spread over it, and random rotations."""
    cells = np.linspace(0, len(grid) - 1, n).astype(int)
    out = []
    for c in cells:
        lo, hi = grid.boxes[c]
        out.append((lo + (hi - lo) * rng.random(3), random_rotation(rng)))
    return out


def _same(scene, h, eye, rot, res, mask=None, t=None):
    verts = scene.vertices if t is None else scene.vertices_at(t)
    d0, i0 = render_cubemap(verts, scene.faces, eye, res, rot, face_mask=mask)
    st: dict = {}
    d1, i1 = render_cubemap(verts, scene.faces, eye, res, rot, face_mask=mask, hierarchy=h,
                            stats=st)
    assert np.array_equal(i0, i1), f"{int((i0 != i1).sum())} pixels differ"
    assert np.array_equal(d0, d1)
    return st


def test_city_views_identical_and_culled():
    scene = make_scene("city", 200_000, seed=0)
    grid = ViewcellGrid.for_scene(scene, 4.0)
    h = scene_hierarchy(scene)
    rng = np.random.default_rng(0)
    drawn = []
    for eye, rot in _eyes(grid, 6, rng):
        st = _same(scene, h, eye, rot, 128, mask=scene.valid_faces)
        drawn.append(st["triangles"])
        assert st["nodes_hidden"] > 0
    # A street view sees a small part of a city: culling must skip most of it.
    assert np.median(drawn) < 0.5 * scene.n_triangles


@pytest.mark.parametrize("name", REAL)
def test_real_scene_views_identical(name):
    scene = real_scene(name)
    grid = real_grid(name)
    h = scene_hierarchy(scene)
    rng = np.random.default_rng(7)
    for eye, rot in _eyes(grid, 3, rng):
        _same(scene, h, eye, rot, 128, mask=scene.valid_faces)
        # One perspective view too, off the cube's axes.
        fwd = rng.normal(size=3)
        r = look_rotation(fwd)
        a = render_ids(scene.vertices, scene.faces, eye, r, 96, 64, 1.3, 0.8,
                       face_mask=scene.valid_faces)
        b = render_ids(scene.vertices, scene.faces, eye, r, 96, 64, 1.3, 0.8,
                       face_mask=scene.valid_faces, hierarchy=h)
        assert np.array_equal(a[1], b[1]) and np.array_equal(a[0], b[0])


def test_georeferenced_offset_and_subset_mask():
    base = make_scene("village", 30_000, seed=2)
    far = Scene(base.vertices + np.array([4.2e6, 35.0, 5.6e6]), base.faces, base.object_ids,
                base.colors)
    h = build_hierarchy(far.vertices, far.faces)
    rng = np.random.default_rng(3)
    mask = far.valid_faces & (rng.random(far.n_triangles) < 0.7)
    for eye, rot in _eyes(ViewcellGrid.for_scene(far, 4.0), 4, rng):
        _same(far, h, eye, rot, 96, mask=mask)
        ids = render_cubemap_ids(far.vertices, far.faces, eye, 96, rot, face_mask=mask,
                                 hierarchy=h)
        assert not np.isin(ids[ids >= 0], np.flatnonzero(~mask)).any()


def test_moving_faces_drawn_at_every_time():
    scene = make_scene("swaying_grass", 2000, seed=1)
    assert moving_faces(scene).any()
    h = scene_hierarchy(scene)
    lo, hi = scene.bounds()
    rng = np.random.default_rng(4)
    for t in np.linspace(*scene.time_range(), 4):
        eye = np.array([(lo[0] + hi[0]) / 2, lo[1] + 1.0, (lo[2] + hi[2]) / 2])
        _same(scene, h, eye + rng.normal(size=3) * [3, 0.2, 3], random_rotation(rng), 64,
              mask=scene.valid_faces, t=t)


def test_eye_inside_a_box_and_behind_the_near_plane(monkeypatch):
    # A closed box around the eye, and a large scene outside it: nothing outside is drawn,
    # and the box's own faces, some nearer than the near plane, are all where they should be.
    # Culled to the end: where the near plane cuts the floor the city shows through, more
    # than culling pays for, and the render would give culling up.
    from visibility.raster import culling

    monkeypatch.setattr(culling, "PAYS_UP_TO", 1.0)
    city = make_scene("city", 20_000, seed=6)
    v, f, _, _ = box_mesh(np.array([-0.5, 1.0, -0.5]), np.array([0.5, 2.0, 0.5]))
    verts = np.concatenate([city.vertices, v])
    faces = np.concatenate([city.faces, f + len(city.vertices)])
    h = build_hierarchy(verts, faces)
    scene = Scene(verts, faces)
    for eye in (np.array([0.0, 1.5, 0.0]), np.array([0.0, 1.01, 0.0]),
                np.array([0.49, 1.97, -0.48])):
        st = _same(scene, h, eye, np.eye(3), 64)
        assert st["triangles"] < scene.n_triangles


def test_wrong_hierarchy_is_refused():
    a = make_scene("village", 2000, seed=0)
    b = make_scene("village", 3000, seed=0)
    h = build_hierarchy(a.vertices, a.faces)
    with pytest.raises(ValueError, match="built for"):
        render_cubemap_ids(b.vertices, b.faces, np.zeros(3), 16, hierarchy=h)


def test_vertices_in_another_frame_are_refused():
    # A render in a frame centred elsewhere (as trim_regions draws) cannot use the scene's
    # hierarchy: its boxes are in the scene's frame.
    scene = make_scene("village", 3000, seed=0)
    h = build_hierarchy(scene.vertices, scene.faces)
    moved = scene.vertices - np.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="other vertex positions"):
        render_cubemap_ids(moved, scene.faces, np.zeros(3), 16, hierarchy=h)
    assert h.matches(scene.vertices) and not h.matches(moved)


def test_coherent_views_identical_and_cheaper():
    """A run of views from nearby eyes sharing a ``Coherence``: each draws the last one's
    leaves first; the images stay those of the full render, and less is drawn."""
    scene = make_scene("city", 200_000, seed=8)
    grid = ViewcellGrid.for_scene(scene, 4.0)
    h = scene_hierarchy(scene)
    rng = np.random.default_rng(9)
    lo, hi = grid.boxes[len(grid) // 2]
    coh = Coherence()
    alone, seeded = [], []
    for k in range(6):
        eye, rot = lo + (hi - lo) * rng.random(3), random_rotation(rng)
        full = render_cubemap_ids(scene.vertices, scene.faces, eye, 128, rot,
                                  face_mask=scene.valid_faces)
        st0: dict = {}
        render_cubemap_ids(scene.vertices, scene.faces, eye, 128, rot,
                           face_mask=scene.valid_faces, hierarchy=h, stats=st0)
        st1: dict = {}
        got = render_cubemap_ids(scene.vertices, scene.faces, eye, 128, rot,
                                 face_mask=scene.valid_faces, hierarchy=h, stats=st1,
                                 coherence=coh)
        assert np.array_equal(full, got), k
        seen = np.unique(full[full >= 0])
        assert np.array_equal(np.sort(coh.leaves), np.unique(h.leaf_of[seen]))
        if k:
            assert st1["seeded"] > 0
            alone.append(st0["nodes_tested"])
            seeded.append(st1["nodes_tested"])
    assert sum(seeded) < sum(alone)
    with pytest.raises(ValueError, match="face_ids None"):
        render_cubemap_ids(scene.vertices, scene.faces, lo, 16, hierarchy=h, coherence=coh,
                           face_ids=np.arange(scene.n_triangles))


def _confetti(n, rng):
    """``n`` small triangles scattered over a shell 5-20 m around the origin, facing it: from
    the origin nearly all of them are seen, so culling hides almost nothing."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centres = d * rng.uniform(5.0, 20.0, size=(n, 1))
    a = np.cross(d, rng.normal(size=(n, 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(d, a)
    s = 0.02
    v = np.concatenate([centres + s * a, centres - s * a + s * b, centres - s * a - s * b])
    f = np.stack([np.arange(n), np.arange(n, 2 * n), np.arange(2 * n, 3 * n)], axis=1)
    return Scene(v, f)


def test_a_render_gives_culling_up_where_it_does_not_pay(monkeypatch):
    """A view that sees most of the scene stops culling once it has drawn more than
    ``PAYS_UP_TO`` of the tree and draws every face: the same images; with a limit it never
    reaches, it culls to the end, the same images again."""
    from visibility.raster import culling

    scene = _confetti(60_000, np.random.default_rng(3))
    h = build_hierarchy(scene.vertices, scene.faces)
    eye = np.zeros(3)
    st = _same(scene, h, eye, np.eye(3), 128)
    assert st["gave_up"] == 1
    monkeypatch.setattr(culling, "PAYS_UP_TO", 1.0)
    st = _same(scene, h, eye, np.eye(3), 128)
    assert st.get("gave_up", 0) == 0
    assert st["triangles"] > 0.5 * scene.n_triangles  # what made it give up before
    # A run sharing a Coherence learns it from the render that gave up.
    monkeypatch.setattr(culling, "PAYS_UP_TO", 0.08)
    coh = Coherence()
    render_cubemap_ids(scene.vertices, scene.faces, eye, 64, hierarchy=h, coherence=coh)
    assert h.stats["pays"] is False and coh.hierarchy_for(h) is None


def test_a_run_stops_culling_where_it_does_not_pay(monkeypatch):
    from visibility.raster import culling

    scene = make_scene("city", 60_000, seed=2)
    h = build_hierarchy(scene.vertices, scene.faces)
    coh = Coherence()
    assert coh.hierarchy_for(h) is h and coh.hierarchy_for(None) is None
    coh.drew(h, int(culling.PAYS_UP_TO * len(h.order)))  # at the limit: still pays
    assert coh.hierarchy_for(h) is h and h.stats["pays"]
    coh.drew(h, int(culling.PAYS_UP_TO * len(h.order)) + 1)
    assert coh.hierarchy_for(h) is None and not h.stats["pays"]
    # Later runs on that scene start without culling, but every RETRY_EVERY-th tries it.
    tried = [Coherence().hierarchy_for(h) is h for _ in range(2 * culling.RETRY_EVERY)]
    assert tried.count(True) == 2
    # A view that culls well makes the scene's runs cull again.
    c = Coherence()
    while c.hierarchy_for(h) is None:
        c = Coherence()
    c.drew(h, 0)
    assert Coherence().hierarchy_for(h) is h
    # Through the sampled ground truth: a cell of an open scene where culling draws most of
    # it gives up, and the answer is the same.
    monkeypatch.setattr(culling, "PAYS_UP_TO", 0.0)
    grid = ViewcellGrid.for_scene(scene, 4.0)
    from visibility.ground_truth import sample_pvs
    from visibility.raster.hierarchy import scene_hierarchy as sh

    hs = sh(scene)
    a = sample_pvs(scene, grid.cell(len(grid) // 2), n_points=4, resolution=64, seed=1)
    assert hs.stats["pays"] is False
    bare = Scene(scene.vertices, scene.faces)
    b = sample_pvs(bare, grid.cell(len(grid) // 2), n_points=4, resolution=64, seed=1)
    assert np.array_equal(a.triangle_ids, b.triangle_ids)


@pytest.mark.parametrize("culled", [False, True])
def test_render_into_given_buffers_is_the_same_render(culled):
    """``render_ids(out=...)`` writes the render into the caller's buffers, whatever they held
    before, and returns (views of) them; a None depth skips the depth pass (ids unchanged)."""
    scene = make_scene("village", 60_000, seed=4)
    h = scene_hierarchy(scene) if culled else None
    grid = ViewcellGrid.for_scene(scene, 4.0)
    rng = np.random.default_rng(11)
    depth = np.full((64, 96), 7.0, dtype=np.float32)
    ids = np.full((64, 96), 123, dtype=np.int32)
    for eye, rot in _eyes(grid, 3, rng):
        d0, i0 = render_ids(scene.vertices, scene.faces, eye, rot, 96, 64, 1.3, 0.8,
                            face_mask=scene.valid_faces, hierarchy=h)
        d1, i1 = render_ids(scene.vertices, scene.faces, eye, rot, 96, 64, 1.3, 0.8,
                            face_mask=scene.valid_faces, hierarchy=h, out=(depth, ids))
        assert np.shares_memory(d1, depth) and np.shares_memory(i1, ids)
        assert np.array_equal(i0, ids) and np.array_equal(d0, depth)
        d2, i2 = render_ids(scene.vertices, scene.faces, eye, rot, 96, 64, 1.3, 0.8,
                            face_mask=scene.valid_faces, hierarchy=h, out=(None, ids))
        assert d2 is None and np.shares_memory(i2, ids) and np.array_equal(i0, ids)


def test_render_into_wrong_buffers_is_refused():
    scene = make_scene("village", 2_000, seed=4)
    eye = scene.vertices.mean(axis=0)
    args = (scene.vertices, scene.faces, eye, np.eye(3), 32, 16)
    good_d = np.zeros((16, 32), np.float32)
    good_i = np.zeros((16, 32), np.int32)
    for out in [(good_d, np.zeros((32, 16), np.int32)),  # transposed
                (np.zeros((16, 32)), good_i),  # float64 depth
                (good_d, np.zeros((16, 32), np.int64)),
                (good_d, np.zeros((16, 64), np.int32)[:, ::2]),  # not contiguous
                (good_d,), good_i]:
        with pytest.raises(ValueError, match="out"):
            render_ids(*args, out=out)
