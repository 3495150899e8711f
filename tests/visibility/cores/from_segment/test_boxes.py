"""Binning of primitives into tiles: each tile lists the primitives whose hull (or box) reaches
it, front to back."""

from __future__ import annotations

import numpy as np

from visibility.cores.from_segment.boxes import TILE, _sort_and_bin, _tile_cols, _tile_ranges
from visibility.cores.from_segment.hull import HMAX, Hulls

RES = 64
NEAR = 0.05
PAD = 0.5
NTX = RES // TILE


def _hulls(polys):
    """``Hulls`` with primitive k's hull ``polys[k]`` (None = scan its box)."""
    n = len(polys)
    pts = np.zeros((n, HMAX, 2), np.float32)
    count = np.zeros(n, np.int8)
    for k, poly in enumerate(polys):
        if poly is not None:
            pts[k, :len(poly)] = poly
            count[k] = len(poly)
    return Hulls(np.arange(n, dtype=np.int32), pts, count)


def _lists(face, box, z, hulls):
    rstart, cols = _tile_ranges(box, hulls, PAD)
    zkey, start, items = _sort_and_bin(face, box, z, rstart, cols, RES, NEAR)
    return zkey, {t: items[start[t]:start[t + 1]].tolist() for t in range(len(start) - 1)
                  if start[t + 1] > start[t]}


def test_a_hull_lists_only_the_tiles_it_reaches():
    # Box over 3 x 3 tiles; prim 0's hull is a vertical sliver in tile column 1, prim 1 has no
    # hull, prim 2's box is one tile column wide (its hull is not consulted).
    box = np.array([[0, 47, 0, 47], [0, 47, 0, 47], [20, 40, 17, 30]], np.int32)
    sliver = [(20.0, 3.0), (22.0, 3.0), (22.0, 40.0), (20.0, 40.0)]
    far_away = [(60.0, 60.0), (61.0, 60.0), (61.0, 61.0)]
    hulls = _hulls([sliver, None, far_away])
    face = np.array([0, 0, 2], np.int32)
    z = np.array([3.0, 1.0, 2.0])
    zkey, lists = _lists(face, box, z, hulls)
    tile = {(f, ty, tx): f * NTX * NTX + ty * NTX + tx
            for f in range(6) for ty in range(NTX) for tx in range(NTX)}
    expect = {}
    for ty in range(3):
        for tx in range(3):
            expect[tile[0, ty, tx]] = [1, 0] if tx == 1 else [1]
    expect[tile[2, 1, 1]] = [2]
    expect[tile[2, 2, 1]] = [2]
    assert lists == expect
    assert np.all(zkey <= z)


def test_tile_lists_match_the_tile_columns_and_stay_front_to_back():
    rng = np.random.default_rng(3)
    n = 300
    face = rng.integers(0, 6, n).astype(np.int32)
    r0, c0 = rng.integers(0, RES - 1, n), rng.integers(0, RES - 1, n)
    r1 = np.minimum(RES - 1, r0 + rng.integers(0, 40, n))
    c1 = np.minimum(RES - 1, c0 + rng.integers(0, 40, n))
    box = np.stack([r0, r1, c0, c1], axis=1).astype(np.int32)
    polys = []
    for k in range(n):
        if k % 4 == 0:
            polys.append(None)
            continue
        # A thin parallelogram from the box's top-left to its bottom-right corner.
        w = rng.uniform(0.1, 3.0)
        polys.append([(c0[k], r0[k]), (c0[k] + w, r0[k]), (c1[k] + w, r1[k]), (c1[k], r1[k])])
    hulls = _hulls(polys)
    z = rng.uniform(0.1, 100.0, n)
    zkey, lists = _lists(face, box, z, hulls)
    want = {}
    for p in range(n):
        for ty in range(box[p, 0] // TILE, box[p, 1] // TILE + 1):
            tx0, tx1 = _tile_cols(hulls, p, box, ty, PAD)
            for tx in range(tx0, tx1 + 1):
                want.setdefault(face[p] * NTX * NTX + ty * NTX + tx, set()).add(p)
    assert {t: set(v) for t, v in lists.items()} == want
    assert sum(map(len, lists.values())) == sum(map(len, want.values()))
    for items in lists.values():
        assert np.all(np.diff(zkey[items]) >= 0)
    assert np.all(zkey <= z)
