"""The per-view masks against the whole-array numpy expressions they replace."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.silhouettes import AMBIGUOUS
from visibility.cores.trim_regions.view_masks import drawn_edges, drawn_rows


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
