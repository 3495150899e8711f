"""Silhouettes of a cube as seen from v*, and the trim width (paper Secs. 3.3, 4.1, Fig. 7)."""

from __future__ import annotations

import numpy as np

from visibility.cores.designed_scenes import Builder
from visibility.cores.trim_regions.cache import build_scene_data
from visibility.cores.trim_regions.frustum import sphere_views
from visibility.cores.trim_regions.layers import leaf_frame
from visibility.cores.trim_regions.raster import setup_triangles, to_camera
from visibility.cores.trim_regions.silhouettes import (
    AMBIGUOUS,
    BLOCK,
    MAX_LOOKUP_CELLS,
    _cell_layers,
    _trim_layer,
    silhouette_trims,
)


def _trims(eye, delta=0.0, face=5, margin_px=0.0, res=64, scene=None, ambiguous=()):
    if scene is None:
        b = Builder()
        b.box((-1, -1, -6), (1, 1, -4), 0)
        scene = b.scene("cube")
    data = build_scene_data(scene)
    view = sphere_views(np.asarray(eye, float), delta, res)[face]
    cam = to_camera(scene.vertices, view.vstar, view.rot)
    s = len(data.static)
    facing = np.zeros(s, dtype=np.int8)
    setup_triangles(cam, scene.faces.astype(np.int64), data.static, np.ones(s, dtype=bool),
                    view.near, view.tan, res,
                    facing, np.empty((s, 4, 3)), np.zeros(s, dtype=np.int64),
                    np.zeros((s, 4), dtype=np.int64))
    facing_of = np.zeros(scene.n_triangles, dtype=np.int8)
    facing_of[data.static] = facing
    facing_of[list(ambiguous)] = AMBIGUOUS
    frame = leaf_frame(data.octree, np.zeros(3))
    e = data.edges
    lay = np.zeros(len(data.octree), dtype=np.int64)
    return silhouette_trims(cam, e.vert, e.face, e.opp, e.many, facing_of,
                            np.ones(len(e.vert), dtype=bool), view.near, view.tan,
                            res, view.delta, view.back, margin_px, view.vstar, view.rot,
                            frame.grid_origin, data.octree.cell, data.octree.leaf_of_cell,
                            lay, data.piece)[0], view


def test_a_cube_seen_face_on_has_four_silhouette_edges():
    trims, _ = _trims((0.0, 0.0, 0.0))
    assert len(trims) == 4


def test_a_cube_beside_the_face_trims_nothing_there():
    # Seen from the +x face the cube lies 76 degrees and more off its axis, in front of v*:
    # its silhouettes' strips reach no pixel of that face, so they make no trim rows.
    assert len(_trims((0.0, 0.0, 0.0), face=0)[0]) == 0


def test_a_cube_seen_from_off_a_corner_has_a_hexagon_of_silhouettes():
    trims, _ = _trims((3.0, 2.5, 0.0))
    assert len(trims) == 6


def _expected_widths(trims, view):
    """Trim widths at both ends by the formula: (Δ sqrt(1 + σ²) + σ R) / (z - R - Δ), σ the
    end's image coordinate along the normal into the occluder, at least 0."""
    out = np.empty((len(trims), 2))
    for i, row in enumerate(trims):
        n, side = row[:3], row[3]
        into = side * n[:2] / np.hypot(n[0], n[1])
        for k in range(2):
            uv = row[4 + 2 * k:6 + 2 * k]
            sigma = float(uv @ into)
            z = 1.0 / row[8 + k]
            w = view.delta * np.sqrt(1 + sigma**2) + sigma * view.back
            out[i, k] = max(0.0, w) / (z - view.back - view.delta)
    return out


def test_trims_lie_inside_the_cube_image_and_widen_with_delta():
    narrow, _ = _trims((0.0, 0.0, 0.0), delta=0.05)
    wide, view = _trims((0.0, 0.0, 0.0), delta=0.2)
    assert np.all(wide[:, 10:12] > narrow[:, 10:12])
    np.testing.assert_allclose(wide[:, 10:12], _expected_widths(wide, view), rtol=1e-9)
    # The inner side is towards the image centre (where the cube is), so moving forward only
    # hides more there: narrower than the lateral motion alone (σ = 0.25 at the front face's
    # edge midpoints, 4 m from v0).
    z = 4.0 + view.back
    lateral = 0.2 * np.sqrt(1 + 0.25**2) / (z - view.back - 0.2)
    assert np.all(wide[:, 10:12] < lateral)
    for row in wide:
        n, side = row[:3], row[3]
        assert side * (n[0] * 0.0 + n[1] * 0.0 - n[2]) > 0


def test_forward_motion_widens_the_trim_of_an_occluder_away_from_the_centre():
    # From 3 m to the side the cube's image lies left of the centre: its right silhouette has
    # the cube away from the centre (the eye's forward motion lets the image grow past it),
    # its left one towards the centre.
    trims, view = _trims((3.0, 0.0, 0.0), delta=0.2)
    expected = _expected_widths(trims, view)
    np.testing.assert_allclose(trims[:, 10:12], expected, rtol=1e-9)
    signs = []
    for row in trims:
        n, side = row[:3], row[3]
        into = side * n[:2] / np.hypot(n[0], n[1])
        for k in range(2):
            sigma = float(row[4 + 2 * k:6 + 2 * k] @ into)
            z = 1.0 / row[8 + k]
            lateral = view.delta * np.sqrt(1 + sigma**2) / (z - view.back - view.delta)
            if abs(sigma) > 1e-9:  # an end at the image's centre line: equal
                assert (row[10 + k] > lateral) == (sigma > 0), (sigma, row[10 + k], lateral)
                signs.append(sigma > 0)
    assert any(signs) and not all(signs)


def test_margin_is_added_in_pixels():
    a, view = _trims((0.0, 0.0, 0.0), margin_px=0.0)
    b, _ = _trims((0.0, 0.0, 0.0), margin_px=1.5)
    np.testing.assert_allclose(b[:, 10:12] - a[:, 10:12], 1.5 * 2 * view.tan / view.res)


def test_an_edge_of_a_triangle_whose_plane_passes_through_the_sphere_is_a_silhouette():
    # A concave fold (two walls meeting in a corner, both facing v*): no silhouette, unless
    # one wall's plane passes through the sphere, whose eyes behind it see past the corner.
    b = Builder()
    b.tris.append(np.array([(-2.0, -1.0, -4.0), (0.5, -1.0, -4.0), (0.5, 1.0, -4.0)]))
    b.tris.append(np.array([(0.5, -1.0, -4.0), (0.5, -1.0, -1.0), (0.5, 1.0, -4.0)]))
    b.obj += [0, 1]
    b.col += [(100, 100, 100)] * 2
    scene = b.scene("fold")
    plain, _ = _trims((0.0, 0.0, 0.0), delta=0.3, scene=scene)
    with_side, _ = _trims((0.0, 0.0, 0.0), delta=0.3, scene=scene, ambiguous=[1])
    def at_corner(rows):
        # The corner edge, x = 0.5 at depth 4 + R from v*: a vertical line near u = 0.11.
        return [r for r in rows if abs(r[4] - r[6]) < 1e-9 and 0.05 < r[4] < 0.13]

    assert len(with_side) > len(plain) and len(at_corner(with_side)) == 2
    assert not at_corner(plain)
    # Two triangles of one plane through the sphere: no silhouette between them.
    b = Builder()
    b.quad((-1.0, -1.0, -4.0), (1.0, -1.0, -4.0), (1.0, 1.0, -4.0), (-1.0, 1.0, -4.0), 0)
    quad = b.scene("quad")
    both, _ = _trims((0.0, 0.0, 0.0), delta=0.3, scene=quad, ambiguous=[0, 1])
    alone, _ = _trims((0.0, 0.0, 0.0), delta=0.3, scene=quad)
    assert len(both) > len(alone) == 4  # its borders now trim on both sides
    assert not [r for r in both if abs(r[4] - r[6]) > 1e-9 and abs(r[5] - r[7]) > 1e-9]


def test_a_trims_layer_is_the_least_layer_of_the_cells_its_box_meets():
    """``_trim_layer`` reads blocks of cells where it can; its answer is the brute-force least
    layer over the grid cells the grown box meets (0 where none holds a leaf, or where the box
    is too large to look up)."""
    rng = np.random.default_rng(5)
    g = 19  # not a multiple of the blocks' side
    leaf_of_cell = np.where(rng.random((g, g, g)) < 0.4, -1,
                            rng.integers(0, 50, (g, g, g))).astype(np.int32)
    leaf_layer = rng.integers(0, 40, 50).astype(np.int64)
    cell_layer = np.empty((g, g, g), dtype=np.int32)
    nb = -(-g // BLOCK)
    block_layer = np.empty((nb, nb, nb), dtype=np.int32)
    # int32 cells and layer, as the pipeline passes them: the kernels compile once.
    first = np.int32(_cell_layers(leaf_of_cell, leaf_layer, cell_layer, block_layer))
    layers = np.where(leaf_of_cell >= 0, leaf_layer[np.maximum(leaf_of_cell, 0)], 1 << 40)
    assert first == layers.min()
    origin, cell = np.array([-1.0, 2.0, 0.5]), 0.25
    part = np.empty((64, 4), dtype=np.int32)
    for _ in range(400):
        pa = origin + rng.uniform(-0.5, g * cell + 0.5, 3)
        pb = pa + rng.normal(0.0, 0.6, 3)
        grow = rng.uniform(0.0, 0.4)
        lo = np.clip(np.floor((np.minimum(pa, pb) - grow - origin) / cell), 0, g - 1).astype(int)
        hi = np.clip(np.floor((np.maximum(pa, pb) + grow - origin) / cell), 0, g - 1).astype(int)
        box = layers[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1]
        want = 0 if box.size > MAX_LOOKUP_CELLS or box.min() == 1 << 40 else box.min()
        assert _trim_layer(pa, pb, grow, origin, cell, cell_layer, block_layer, first,
                           part) == want
