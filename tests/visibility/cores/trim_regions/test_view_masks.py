"""The per-view masks against the whole-array numpy expressions they replace."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.silhouettes import AMBIGUOUS
from visibility.cores.trim_regions.view_masks import drawn_edges, drawn_instances, drawn_rows


def test_masks_match_their_numpy_definitions():
    rng = np.random.default_rng(3)
    m, leaves, items, n_edges = 500, 40, 900, 800
    static = np.sort(rng.choice(m, 400, replace=False)).astype(np.int64)
    item_leaf = rng.integers(0, leaves, items).astype(np.int64)
    # Items of moving triangles have no static row (-1).
    item_rows = np.where(rng.random(items) < 0.1, -1, rng.integers(0, len(static), items))
    drawn = rng.random(leaves) < 0.5
    need = np.ones(len(static), dtype=np.bool_)  # cleared by the kernel
    drawn_rows(drawn, item_leaf, item_rows.astype(np.int64), need)
    rows = item_rows[drawn[item_leaf]]
    want = np.zeros(len(static), dtype=np.bool_)
    want[rows[rows >= 0]] = True
    np.testing.assert_array_equal(need, want)
    assert 0 < need.sum() < len(static)

    facing = rng.integers(-1, 2, len(static)).astype(np.int8)
    ambiguous = rng.choice(static, 20, replace=False).astype(np.int64)
    edge_face = rng.integers(-1, m, (n_edges, 2)).astype(np.int64)
    facing_of = np.full(m, 7, dtype=np.int8)
    edge_on = np.zeros(n_edges, dtype=np.bool_)
    drawn_edges(static, need, facing, ambiguous, AMBIGUOUS, edge_face, facing_of, edge_on)
    want_facing = np.zeros(m, dtype=np.int8)
    want_facing[static] = facing
    want_facing[ambiguous] = AMBIGUOUS
    np.testing.assert_array_equal(facing_of, want_facing)
    drawn_id = np.zeros(m, dtype=np.bool_)
    drawn_id[static[need]] = True
    f = edge_face
    want_on = ((f[:, 0] >= 0) & drawn_id[np.maximum(f[:, 0], 0)]) | (
        (f[:, 1] >= 0) & drawn_id[np.maximum(f[:, 1], 0)])
    np.testing.assert_array_equal(edge_on, want_on)
    assert 0 < edge_on.sum() < n_edges


def test_drawn_instances_match_their_numpy_definition():
    rng = np.random.default_rng(5)
    leaves, rows, items = 40, 300, 900
    drawn = rng.random(leaves) < 0.5
    item_leaf = rng.integers(0, leaves, items)
    item_rows = rng.integers(0, rows, items)
    tri_items = item_rows * 2  # the triangle ids of the rows
    npoly = rng.integers(0, 4, rows) * (rng.random(rows) < 0.7)
    near = (rng.random(2 * rows) < 0.1).astype(np.uint8)
    layer = rng.integers(0, 9, leaves)
    out_item = np.empty(items, dtype=np.int64)
    out_layer = np.empty(items, dtype=np.int64)
    k = drawn_instances(drawn, item_leaf, item_rows, tri_items, npoly, near, layer, out_item,
                        out_layer)
    want = np.flatnonzero(drawn[item_leaf] & (npoly[item_rows] > 0) & (near[tri_items] == 0))
    assert 0 < k < items
    assert np.array_equal(out_item[:k], want)
    assert np.array_equal(out_layer[:k], layer[item_leaf[want]])
