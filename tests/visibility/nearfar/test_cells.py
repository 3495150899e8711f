"""``visibility.nearfar.cells.cubemap_anchors``: which cells share a cubemap centre."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.generators import make_scene
from visibility.nearfar.cells import cubemap_anchors
from visibility.scene import WalkArea
from visibility.viewcells import ViewcellGrid


def _groups(grid: ViewcellGrid, block: int) -> np.ndarray:
    """Reference: (block column i, block column k, level rank) per cell, by plain Python."""
    columns: dict[tuple, list] = {}
    for c in range(len(grid)):
        columns.setdefault(tuple(grid.ij[c]), []).append((grid.floor[c], c))
    rank = {c: r for col in columns.values() for r, (_, c) in enumerate(sorted(col))}
    return np.array([(grid.ij[c][0] // block, grid.ij[c][1] // block, rank[c])
                     for c in range(len(grid))])


def test_block_one_is_a_cubemap_per_cell():
    grid = ViewcellGrid(WalkArea([[0, 0, 20, 12, 0.0]]), 4.0)
    np.testing.assert_array_equal(cubemap_anchors(grid, 1), np.arange(len(grid)))
    with pytest.raises(ValueError):
        cubemap_anchors(grid, 0)


@pytest.mark.parametrize("block", [2, 3, 4])
def test_city_blocks_share_a_central_member(block):
    scene = make_scene("city", triangles=20_000, seed=0)
    grid = ViewcellGrid.for_scene(scene, 4.0)
    a = cubemap_anchors(grid, block)
    groups = _groups(grid, block)
    # Same anchor exactly when same block and level; the anchor is a member of its own group.
    _, gid = np.unique(groups, axis=0, return_inverse=True)
    gid = gid.reshape(-1)
    assert len(np.unique(a)) == gid.max() + 1
    for g in range(gid.max() + 1):
        members = np.flatnonzero(gid == g)
        assert len(np.unique(a[members])) == 1 and a[members[0]] in members
        # The most central member: no member lies nearer the members' mean centre.
        centres = grid.boxes[members].mean(axis=1)
        d = np.sum((centres - centres.mean(axis=0)) ** 2, axis=1)
        assert d[members.tolist().index(a[members[0]])] == d.min()
    np.testing.assert_array_equal(a[a], a)  # an anchor anchors itself
    off = np.hypot(*(grid.boxes[:, :, [0, 2]].mean(axis=1) - grid.boxes[a][:, :, [0, 2]]
                     .mean(axis=1)).T)
    assert off.max() <= block * 4.0 * np.sqrt(2) + 1e-9 and off.max() > 0


def test_levels_of_a_building_keep_their_own_centres():
    # Two storeys over the same 16 x 16 m: one block spans the floor plan, not the storeys.
    grid = ViewcellGrid(WalkArea([[0, 0, 16, 16, 0.0], [0, 0, 16, 16, 3.5]]), 4.0)
    a = cubemap_anchors(grid, 4)
    assert len(grid) == 32 and len(np.unique(a)) == 2
    np.testing.assert_array_equal(grid.floor[a], grid.floor)
