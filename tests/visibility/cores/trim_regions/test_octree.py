"""The octree (paper Sec. 5.1) and its layers (Sec. 5.2): every triangle is in the leaves its box
meets, neighbours are symmetric and balanced, and layers grow away from v*."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.frustum import layers
from visibility.cores.trim_regions.layers import leaf_frame
from visibility.cores.trim_regions.octree import build_octree
from visibility.generators import make_scene


def _octree(max_prims=64):
    scene = make_scene("village", triangles=5000)
    tris = scene.vertices[scene.faces.astype(np.int64)]
    ids = np.flatnonzero(scene.valid_faces)
    return scene, tris[ids], ids, build_octree(tris[ids].min(axis=1), tris[ids].max(axis=1),
                                               ids, max_prims)


def test_every_triangle_is_listed_in_every_leaf_its_box_meets():
    _, tris, ids, tree = _octree()
    assert len(tree) > 8
    boxes = tree.leaf_boxes() + tree.origin
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    for k in range(0, len(tree), max(1, len(tree) // 40)):
        listed = set(tree.tri_items[tree.tri_start[k]:tree.tri_start[k + 1]].tolist())
        meets = np.all((lo <= boxes[k, 1]) & (hi >= boxes[k, 0]), axis=1)
        assert listed == set(ids[meets].tolist())


def test_leaves_tile_the_root_and_neighbours_are_symmetric_and_balanced():
    _, _, _, tree = _octree()
    g = 1 << tree.depth
    assert (tree.leaf_of_cell >= 0).all()
    vol = np.prod(tree.leaf_cells[:, 1] - tree.leaf_cells[:, 0], axis=1).sum()
    assert vol == g ** 3
    pairs = set()
    for k in range(len(tree)):
        for q in range(tree.nbr_start[k], tree.nbr_start[k + 1]):
            b = int(tree.nbr_items[q])
            pairs.add((k, b))
            assert abs(tree.leaf_level[k] - tree.leaf_level[b]) <= 2
    assert all((b, a) in pairs for a, b in pairs)


def test_layers_put_every_neighbour_nearer_to_v_star_first():
    scene, _, _, tree = _octree()
    frame = leaf_frame(tree, np.zeros(3))
    vstar = 0.5 * (frame.lo[0] + frame.hi[-1]) + 0.123
    lay = layers(frame.lo, frame.hi, tree.nbr_start, tree.nbr_items, tree.nbr_face, vstar)
    assert lay.min() == 0 and lay.max() > 0
    for k in range(len(tree)):
        for q in range(tree.nbr_start[k], tree.nbr_start[k + 1]):
            b = tree.nbr_items[q]
            axis, upper = divmod(int(tree.nbr_face[q]), 2)
            # b lies beyond k's face; when v* is beyond that face too, b is in front of k.
            beyond = vstar[axis] > frame.hi[k, axis] if upper else vstar[axis] < frame.lo[k, axis]
            if beyond:
                assert lay[b] < lay[k]
