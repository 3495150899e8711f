"""The pipeline's per-triangle filters (``filters``) against their definitions written in numpy,
on random triangles and on the cases each exists for."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.filters import grazing_mask, plane_holds_box, planes_near


def _grazing_numpy(t, normals, plane, centres, delta, px):
    close = np.zeros(len(t), dtype=bool)
    mid = t.mean(axis=1)
    for c in centres:
        off = np.abs(normals @ c - plane)
        dist = np.maximum(np.linalg.norm(mid - c, axis=1), 1e-12)
        d = np.maximum(np.linalg.norm(t - c, axis=2), 1e-12)
        across = off * (1.0 / d.min(axis=1) - 1.0 / d.max(axis=1))
        close |= (off <= delta) & ((off / dist * px < 1.0) | (across * px < 1.0))
    return close


def _soup(gen, n, spread):
    verts = gen.uniform(-spread, spread, (3 * n, 3))
    # int32 faces, as the pipeline passes them: the kernels compile once.
    return verts, np.arange(3 * n, dtype=np.int32).reshape(n, 3)


def test_grazing_mask_matches_its_definition():
    gen = np.random.default_rng(7)
    verts, faces = _soup(gen, 3000, 3.0)
    # Thin triangles (a door jamb: long in depth, narrow across) next to the centres.
    verts[1::3] = verts[0::3] + gen.normal(0.0, 0.01, (3000, 3))
    t = verts[faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    plane = np.einsum("ij,ij->i", n, t[:, 0])
    centres = gen.uniform(-0.5, 0.5, (3, 3))
    out = np.zeros(3000, dtype=np.bool_)
    grazing_mask(verts, faces, np.arange(3000), n, plane, centres, 0.4, 128.0, out)
    want = _grazing_numpy(t, n, plane, centres, 0.4, 128.0)
    assert want.sum() > 50 and (~want).sum() > 50
    assert np.array_equal(out, want)


def test_plane_holds_box_drops_only_planes_through_the_whole_cell():
    box = np.array([[1.0e5, 2.0, 5.0e6], [1.0e5 + 0.3, 2.3, 5.0e6 + 0.3]])  # georeferenced
    verts = np.array([
        [1.0e5 - 1, 2.0, 5.0e6 - 1], [1.0e5 + 2, 2.0, 5.0e6 - 1], [1.0e5, 2.0, 5.0e6 + 2],  # floor
        [1.0e5 - 1, 0.0, 5.0e6 + 0.15], [1.0e5 + 2, 0.0, 5.0e6 + 0.15],
        [1.0e5, 3.0, 5.0e6 + 0.15],  # a wall through the middle: the cell's face holds no eye
        [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0],  # no area
    ])
    # A plane holding the whole (flat) cell: the cell squeezed to its floor.
    flat = box.copy()
    flat[1, 1] = flat[0, 1]
    faces = np.arange(9, dtype=np.int32).reshape(3, 3)
    ids = np.arange(3, dtype=np.int64)
    out = np.zeros(3, dtype=np.bool_)
    plane_holds_box(verts, faces, ids, box, out)
    assert not out.any()
    plane_holds_box(verts, faces, ids, flat, out)
    assert out.tolist() == [True, False, False]


def test_planes_near_matches_its_definition_for_boxes_and_spheres():
    gen = np.random.default_rng(7)
    normals = gen.normal(size=(2000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    plane = gen.uniform(-2.0, 2.0, 2000)
    q, half = gen.uniform(-1.0, 1.0, 3), np.array([0.3, 0.1, 0.5])
    out = np.empty(2000, dtype=bool)
    planes_near(normals, plane, q, half, 0.0, out)
    box = np.abs(normals @ q - plane) <= np.abs(normals) @ half
    assert np.array_equal(out, box) and 0 < box.sum() < 2000
    planes_near(normals, plane, q, np.zeros(3), 0.4, out)
    sphere = np.abs(normals @ q - plane) <= 0.4
    assert np.array_equal(out, sphere) and 0 < sphere.sum() < 2000
