"""The shaft, the dual ray space and the rasterized test against the exact one (planar)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.grouping import module_on_one_worker
from visibility.cores.dual_ray.dual_space import (
    ceiling,
    cut_piece,
    floor,
    occluders,
    raster_visible,
    region,
    shaft_frame,
)
from visibility.cores.dual_ray.planar import exact_visible, uncovered

pytestmark = module_on_one_worker("dual_space")  # kernels of its own (tests/grouping.py)

A = (np.array([-5.0, 1.5, -5.0]), np.array([5.0, 1.9, 5.0]))
B = (np.array([-3.0, 0.0, 40.0]), np.array([3.0, 5.0, 44.0]))


def _segments(frame, pieces):
    """Occluding segments (n, 6) and piece ids of ``pieces``: rows [px, pz, qx, qz, bottom,
    top] (a flat strip)."""
    out, ids = [], []
    for k, (px, pz, qx, qz, b, t) in enumerate(pieces):
        cut = np.zeros(6)
        # Upright (no lean), passed as the core passes it: the kernel's one specialization.
        if cut_piece(frame, px, pz, qx, qz, t, t, b, b, cut, 0.0, 0.0):
            out.append(cut)
            ids.append(k)
    return np.array(out).reshape(-1, 6), np.array(ids, dtype=np.int64)


def _vid(pieces):
    ends = np.concatenate([np.asarray(pieces)[:, :2], np.asarray(pieces)[:, 2:4]])
    _, inv = np.unique(ends, axis=0, return_inverse=True)
    return np.ascontiguousarray(inv.reshape(2, -1).T).astype(np.int64)


def _visible(pieces, resolution=128, a=A, b=B):
    frame = shaft_frame(a[0], a[1], b[0], b[1])
    segs, ids = _segments(frame, pieces)
    vf, start = occluders(frame, segs, ids, _vid(pieces))
    regs = np.zeros((len(segs), 6))
    for i, s in enumerate(segs):
        region(frame, s[0], s[1], s[2], s[3], regs[i])
    return raster_visible(vf, start, resolution, 16)[0], exact_visible(regs)


def test_the_shaft_runs_from_a_to_b_along_the_larger_gap():
    f = shaft_frame(A[0], A[1], B[0], B[1])
    assert f[13] == 1.0 and f[0] == 2 and f[1] == 1.0  # along +z
    assert f[2] == 5.0 and f[3] == 40.0
    # Every segment from A to B crosses z = 5 within s1 and z = 40 within s2.
    assert f[6] <= -5.0 and f[7] >= 5.0 and f[8] <= -3.0 and f[9] >= 3.0
    # Ceiling above both tops, floor under both bottoms, over the slab.
    for u in np.linspace(5.0, 40.0, 8):
        assert ceiling(f, u) >= 1.9 - 1e-12 and floor(f, u) <= 1.5 + 1e-12


def test_overlapping_footprints_have_no_shaft():
    f = shaft_frame(A[0], A[1], np.array([4.0, 0.0, 4.0]), np.array([9.0, 3.0, 9.0]))
    assert f[13] == 0.0


def test_a_wall_across_the_shaft_hides_b_and_a_low_wall_does_not():
    wall = [(-60.0, 20.0, 60.0, 20.0, 0.0, 15.0)]
    assert _visible(wall) == (False, False)
    low = [(-60.0, 20.0, 60.0, 20.0, 0.0, 2.0)]  # under the ceiling from A to B's top
    assert _visible(low) == (True, True)


def test_a_floating_wall_does_not_hide_what_passes_under_it():
    # The strip starts 1 m up: segments from A's bottom (1.5) to B's (0) pass under it.
    floating = [(-60.0, 20.0, 60.0, 20.0, 1.0, 15.0)]
    assert _visible(floating) == (True, True)


def test_a_gap_between_two_walls_lets_b_be_seen():
    pieces = [(-60.0, 20.0, -1.0, 20.0, 0.0, 15.0), (1.0, 20.0, 60.0, 20.0, 0.0, 15.0)]
    assert _visible(pieces) == (True, True)


def test_walls_meeting_at_a_corner_hide_together():
    # Two walls meeting at (0, 20): each alone leaves rays through the corner's far side;
    # joined they block every ray, and the raster sees the join at any resolution.
    pieces = [(-60.0, 20.0, 0.0, 20.0, 0.0, 15.0), (0.0, 20.0, 60.0, 20.0, 0.0, 15.0)]
    for r in (16, 64, 256):
        assert _visible(pieces, r) == (False, False)
    assert _visible(pieces[:1])[1] and _visible(pieces[1:])[1]


def test_fusion_of_separate_walls_is_found_by_the_exact_test_and_refined_raster():
    # Two staggered walls, each covering half of the shaft; the second row covers the first
    # row's gap seen from every point of A.
    pieces = [(-60.0, 20.0, 0.5, 20.0, 0.0, 15.0), (-0.5, 25.0, 60.0, 25.0, 0.0, 15.0)]
    assert _visible(pieces)[1] is False
    assert _visible(pieces, 256)[0] is False
    # Either wall alone leaves B in view.
    assert _visible(pieces[:1]) == (True, True) and _visible(pieces[1:]) == (True, True)


@pytest.mark.parametrize("seed", range(12))
def test_the_raster_never_hides_what_the_exact_test_sees(seed):
    rng = np.random.default_rng(seed)
    pieces = []
    for _ in range(int(rng.integers(1, 14))):
        p = rng.uniform([-40.0, 8.0], [40.0, 36.0])
        d = rng.normal(size=2)
        d *= rng.uniform(2.0, 25.0) / np.linalg.norm(d)
        q = p + d
        pieces.append((p[0], p[1], q[0], q[1], 0.0, 15.0))
    raster = {r: _visible(pieces, r)[0] for r in (16, 32, 128)}
    exact = _visible(pieces)[1]
    if exact:
        assert all(raster.values()), (raster, exact)
    # A pixel covered whole covers its sub-pixels: what a coarser raster hides, a finer one
    # hides too.
    assert not raster[128] or raster[32]
    assert not raster[32] or raster[16]


def test_uncovered_area_of_two_half_squares():
    # Regions f0 <= 0 <= f1 with f1 = 1: the halves x <= 0.5 and x >= 0.5 of the square.
    left = np.array([-0.5, 1.0, 0.0, 1.0, 0.0, 0.0])   # f0 = x - 0.5 <= 0, f1 = 1 >= 0
    right = np.array([0.5, -1.0, 0.0, 1.0, 0.0, 0.0])  # f0 = 0.5 - x <= 0
    assert uncovered(np.array([left]))
    assert not uncovered(np.array([left, right]))
