"""The depth pyramid: each level the minimum of the one below (level 0 the inverse-depth
buffer itself), and rectangle queries that never exceed the exact minimum over the
rectangle."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.raster.pyramid import PyramidLayout, build_pyramid, rect_min, update_pyramid


@pytest.mark.parametrize("shape", [(1, 1), (5, 3), (64, 64), (37, 100)])
def test_levels_hold_the_minimum_below(shape):
    rng = np.random.default_rng(0)
    invd = rng.random((2, *shape))
    invd[rng.random(invd.shape) < 0.2] = 0.0
    lay = PyramidLayout.of(*shape)
    hz = lay.empty(2)
    build_pyramid(invd, lay.heights, lay.widths, lay.offsets, hz)
    assert lay.heights[-1] == 1 and lay.widths[-1] == 1
    assert lay.size == int((lay.heights[1:] * lay.widths[1:]).sum())
    for k in range(2):
        lvl = invd[k]
        for i in range(len(lay.heights)):
            h, w, o = lay.heights[i], lay.widths[i], lay.offsets[i]
            if i:
                assert np.array_equal(hz[k, o:o + h * w].reshape(h, w), lvl)
            pad = np.full((2 * ((h + 1) // 2), 2 * ((w + 1) // 2)), np.inf)
            pad[:h, :w] = lvl
            lvl = pad.reshape(pad.shape[0] // 2, 2, pad.shape[1] // 2, 2).min(axis=(1, 3))
        if lay.size:
            assert hz[k, -1] == invd[k].min()


def test_rect_min_is_a_lower_bound_and_exact_for_small_rects():
    rng = np.random.default_rng(1)
    invd = rng.random((1, 70, 90))
    lay = PyramidLayout.of(70, 90)
    hz = lay.empty(1)
    build_pyramid(invd, lay.heights, lay.widths, lay.offsets, hz)
    for _ in range(500):
        x0, x1 = np.sort(rng.integers(0, 90, 2))
        y0, y1 = np.sort(rng.integers(0, 70, 2))
        exact = invd[0, y0:y1 + 1, x0:x1 + 1].min()
        got = rect_min(invd, hz, 0, lay.heights, lay.widths, lay.offsets, x0, x1, y0, y1)
        assert got <= exact
        if x1 - x0 <= 7 and y1 - y0 <= 7:
            assert got == exact


def test_update_over_a_dirty_rect_equals_a_rebuild():
    rng = np.random.default_rng(2)
    invd = rng.random((3, 45, 61))
    lay = PyramidLayout.of(45, 61)
    hz = lay.empty(3)
    build_pyramid(invd, lay.heights, lay.widths, lay.offsets, hz)
    for _ in range(50):
        dirty = np.zeros((3, 4), dtype=np.int64)
        dirty[:] = (1, 0, 1, 0)
        k = int(rng.integers(0, 3))
        x0, x1 = np.sort(rng.integers(0, 61, 2))
        y0, y1 = np.sort(rng.integers(0, 45, 2))
        invd[k, y0:y1 + 1, x0:x1 + 1] = rng.random((y1 - y0 + 1, x1 - x0 + 1))
        dirty[k] = (x0, x1, y0, y1)
        update_pyramid(invd, lay.heights, lay.widths, lay.offsets, hz, dirty)
        full = lay.empty(3)
        build_pyramid(invd, lay.heights, lay.widths, lay.offsets, full)
        assert np.array_equal(hz, full)
