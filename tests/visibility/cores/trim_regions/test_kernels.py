"""Known answers of the whole pipeline on hand-built scenes: a box hiding a triangle, a gap, the
umbra of a silhouette, Δ = 0 as from-point visibility at pixel centres."""

from __future__ import annotations

import numpy as np

import visibility.cores.trim_regions.pipeline as pipeline
from visibility.cores.designed_scenes import Builder
from visibility.cores.trim_regions.cache import build_scene_data
from visibility.cores.trim_regions.frustum import cover_box, sphere_counts, sphere_views
from visibility.cores.trim_regions.pipeline import trim_pvs
from visibility.generators import make_scene
from visibility.raster.render import render_ids
from visibility.viewcells import ViewcellGrid


def _solve(scene, delta, centre=(0.0, 1.7, 0.0), res=128, **kw):
    c = np.asarray(centre, dtype=np.float64)
    h = delta / np.sqrt(3.0)
    ids, stats = trim_pvs(scene, build_scene_data(scene), np.stack([c - h, c + h]), res,
                          delta, **kw)
    return set(ids.tolist()), stats


def _wall_and_triangle(tri_x: float, half: float = 0.1):
    """A closed 2 m wide wall 4 m ahead and a small triangle (``half`` m half-width) 2 m
    behind it at x = tri_x."""
    b = Builder()
    wall = b.box((-1.0, 0.7, -4.2), (1.0, 2.7, -4.0), 0)
    tri = len(b.tris)
    b.tris.append(np.array([(tri_x - half, 1.6, -6.0), (tri_x + half, 1.6, -6.0),
                            (tri_x, 1.8, -6.0)]))
    b.obj.append(1)
    b.col.append((200, 0, 0))
    return b.scene("wall"), wall, tri


def test_a_box_hides_a_triangle_behind_its_middle():
    scene, wall, tri = _wall_and_triangle(0.0)
    found, _ = _solve(scene, 0.05)
    assert tri not in found
    assert set(wall) & found


def test_a_triangle_in_a_gap_between_two_boxes_is_seen():
    b = Builder()
    b.box((-2.0, 0.7, -4.2), (-0.1, 2.7, -4.0), 0)
    b.box((0.1, 0.7, -4.2), (2.0, 2.7, -4.0), 1)
    tri = len(b.tris)
    b.tris.append(np.array([(-0.2, 1.5, -6.0), (0.2, 1.5, -6.0), (0.0, 1.9, -6.0)]))
    b.obj.append(2)
    b.col.append((200, 0, 0))
    found, _ = _solve(b.scene("gap"), 0.01)
    assert tri in found


def test_the_penumbra_past_a_silhouette_widens_with_delta():
    # Rays from the centre past the wall's edge (x = 1, z = -4) reach x = 1.5 at z = -6: the
    # triangle (x 1.42..1.48, 2.4 px at 512 px) hides there, shows from an eye 0.2 m aside
    # (past the edge to x = 1.4) and not from one 1 cm aside (x = 1.495).
    scene, _, tri = _wall_and_triangle(1.45, 0.03)
    near, _ = _solve(scene, 0.01, res=512)
    wide, stats = _solve(scene, 0.2, res=512)
    assert tri not in near
    assert tri in wide
    assert stats["validated_intervals"] > 0 and stats["trimmed_pixels"] > 0


def test_delta_zero_is_from_point_visibility_at_pixel_centres():
    scene = make_scene("city", triangles=3000)
    grid = ViewcellGrid.for_scene(scene)
    c = grid.cell(len(grid) // 2).center
    res = 64
    found, stats = _solve(scene, 1e-6, c, res, margin_px=0.0, footprints=False)
    centres, delta = cover_box(np.stack([c - 1e-6 / np.sqrt(3), c + 1e-6 / np.sqrt(3)]), 1e-6)
    ref: set[int] = set()
    for v in sphere_views(centres[0], delta, res):
        _, ids = render_ids(scene.vertices, scene.faces, v.vstar, v.rot, res, res, v.tan, v.tan,
                            near=v.near, face_mask=scene.valid_faces)
        ref |= set(ids[ids >= 0].tolist())
    # Equal up to triangles whose edges pass exactly through pixel centres (the reference
    # renderer's fill rule is top-left, the core's is inclusive).
    assert ref <= found and len(found - ref) <= max(2, 0.01 * len(ref))
    # The occludee footprints only add (sub-pixel triangles).
    more, _ = _solve(scene, 1e-6, c, res, margin_px=0.0)
    assert found <= more


def test_a_larger_cell_is_covered_by_more_spheres():
    centres, delta = cover_box(np.array([[0.0, 1.5, 0.0], [1.0, 1.9, 1.0]]), 0.3)
    assert len(centres) > 1 and delta <= 0.3
    lo, hi = centres.min(axis=0) - delta, centres.max(axis=0) + delta
    assert np.all(lo <= [0.0, 1.5, 0.0]) and np.all(hi >= [1.0, 1.9, 1.0])
    # Every corner of the box lies in some sphere.
    corners = np.array([[x, y, z] for x in (0, 1) for y in (1.5, 1.9) for z in (0, 1)])
    d = np.linalg.norm(corners[:, None] - centres[None], axis=2).min(axis=1)
    assert np.all(d <= delta + 1e-12)


def test_sphere_counts_are_the_fewest_that_fit():
    """Against a brute force over every split of up to 40 sub-boxes: no fewer fit, and the
    server's flat 1 m cell (0.4 m of eye range) takes 12 spheres where cubes took 18."""
    for size in ([1.0, 0.4, 1.0], [1.0, 1.0, 1.0], [0.5, 0.4, 0.5], [0.9, 0.4, 1.3],
                 [0.3, 0.3, 0.3], [0.0, 0.4, 1.0], [1.0, 2.0, 0.2]):
        size = np.array(size)
        n = sphere_counts(size, 0.3)
        assert 0.5 * np.linalg.norm(size / n) <= 0.3 * (1 + 1e-9)
        fits = [(a * b * c) for a in range(1, 41) for b in range(1, 41) for c in range(1, 41)
                if 0.5 * np.linalg.norm(size / [a, b, c]) <= 0.3 and a * b * c <= 40]
        assert int(np.prod(n)) == min(fits)
    assert int(np.prod(sphere_counts(np.array([1.0, 0.4, 1.0]), 0.3))) == 12
    centres, delta = cover_box(np.array([[0.0, 1.5, 0.0], [1.0, 1.9, 1.0]]), 0.3)
    assert len(centres) == 12 and delta <= 0.3


def _jamb_scene():
    """A 0.2 m thick wall 4.1-4.3 m ahead along +x from z = 0.037 m up, and a far wall
    behind its opening: the wall's end face (the jamb, normal -z) lies 3.7 cm beside the
    cell's centre, so the centre sees it at under a tenth of a pixel, an eye 3.4 cm along -z sees
    it in a line of pixels."""
    b = Builder()
    b.box((4.092, -1.7, 0.037), (4.292, 1.3, 1.395), 0)
    b.box((8.0, -3.0, -3.0), (8.2, 3.0, 3.0), 1)
    scene = b.scene("jamb")
    v = scene.vertices[scene.faces.astype(np.int64)]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    jamb = np.flatnonzero((n[:, 2] < 0) & np.all(np.abs(v[:, :, 2] - 0.037) < 1e-9, axis=1)
                          & np.all(v[:, :, 0] < 5.0, axis=1))
    assert len(jamb) == 2
    return scene, jamb


def test_a_face_thin_across_its_line_is_tested_as_grazing():
    # The jamb's line lies 0.037 / 4.2 rad (1.1 px at 256 px) off the centre, so "seen
    # edge-on" alone misses it; its extent across that line is 0.05 px.
    scene, jamb = _jamb_scene()
    graze, _ = pipeline._grazing(scene, build_scene_data(scene), np.zeros((1, 3)), 0.0866, 256)
    assert set(jamb.tolist()) <= set(graze.tolist())
    found, stats = _solve(scene, 0.0866, centre=(0.0, 0.0, 0.0), res=256)
    assert set(jamb.tolist()) & found and stats["grazing"] >= 2
    # An eye of the cell 3.4 cm along -z does see it (a line of pixels).
    eye = np.array([0.0, 0.0, -0.034])
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # looking along +x
    _, ids = render_ids(scene.vertices, scene.faces, eye, rot, 1024, 1024, 0.2, 0.2)
    assert np.isin(ids, jamb).any()


def test_a_sliver_along_the_grid_is_sampled_on_the_rolled_grid():
    # A vertical sliver 0.1 px wide in front of a wall, centred between two columns of the
    # 4 x 4 samples per pixel v* draws: no sample of that grid meets it, the rolled grid does.
    res = 64
    view = sphere_views(np.zeros(3), 0.05, res)[5]  # the face looking along -z
    ss = pipeline.SUPERSAMPLE * res
    depth = 3.0
    x_img = (40 / ss) * 2.0 * view.tan - view.tan  # a boundary between sample columns
    half = 0.05 * 2.0 * view.tan / res
    cam_pts = np.array([[x_img - half, -0.5, -depth], [x_img + half, -0.5, -depth],
                        [x_img, 0.5, -depth]]) * np.array([depth, depth, 1.0])
    world = view.vstar + cam_pts @ view.rot
    b = Builder()
    b.box((-4.0, -4.0, -8.2), (4.0, 4.0, -8.0), 0)
    sliver = len(b.tris)
    b.tris.append(world)
    b.obj.append(1)
    b.col.append((200, 0, 0))
    scene = b.scene("sliver")
    _, ids = render_ids(scene.vertices, scene.faces, view.vstar, view.rot, ss, ss, view.tan,
                        view.tan, near=view.near)
    assert not (ids == sliver).any()
    _, seen, _, _ = pipeline._sample_from_vstar(scene, np.ones(scene.n_triangles, bool),
                                          scene.vertices, view)
    assert sliver in seen


def test_vstar_draws_the_same_through_the_scenes_hierarchy():
    # v*'s renders in the computation's frame, or in the scene's own frame through its
    # hierarchy (frustum and occlusion culled): the same nearest surfaces and triangles.
    from visibility.raster.hierarchy import scene_hierarchy

    scene = make_scene("village", triangles=20_000)
    grid = ViewcellGrid.for_scene(scene)
    centre = grid.cell(len(grid) // 2).center
    verts = scene.vertices - centre
    mask = np.ones(scene.n_triangles, bool)
    hier = scene_hierarchy(scene)
    drawn: dict = {}
    for view in sphere_views(np.zeros(3), 0.2, 64):
        first, seen, _, _ = pipeline._sample_from_vstar(scene, mask, verts, view)
        first_h, seen_h, _, _ = pipeline._sample_from_vstar(scene, mask, verts, view, centre, hier)
        assert np.allclose(first_h, first, rtol=1e-5) and np.array_equal(seen_h, seen)
        drawn[view.face] = len(seen)
    assert sum(drawn.values()) > 0
