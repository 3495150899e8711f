import numpy as np
import pytest

from visibility.scene import WalkArea
from visibility.viewcells import Viewcell, ViewcellGrid


def test_grid_tiles_walk_rects_with_levels():
    g = ViewcellGrid(WalkArea([[0, 0, 8, 8, 0.0], [0, 0, 8, 8, 3.5]]), 4.0)
    assert len(g) == 8  # 2 x 2 columns, two levels
    assert g.to_dict()["levels"] == 2
    for cid in range(len(g)):
        c = g.cell(cid)
        assert c.id == cid
        np.testing.assert_allclose(c.size[[0, 2]], [4, 4])
        # cell_of of the cell's centre is the cell itself (id <-> index round trip)
        assert g.cell_of(c.center) == cid


def test_cell_of_outside_and_nan():
    g = ViewcellGrid(WalkArea([[0, 0, 8, 8, 0.0]]), 4.0)
    assert g.cell_of([100, 1.7, 100]) is None
    assert g.cell_of([-0.1, 1.7, 1]) is None
    assert g.cell_of([np.nan, 1.7, 1]) is None


def test_neighbourhood_is_eight_connected_within_a_level():
    g = ViewcellGrid(WalkArea([[0, 0, 12, 12, 0.0], [0, 0, 12, 12, 5.0]]), 4.0)
    centre = g.cell_of([6, 1.7, 6])
    ns = g.neighbours(centre)
    assert len(ns) == 8
    assert all(abs(g.floor[n] - g.floor[centre]) < 1e-9 for n in ns)
    corner = g.cell_of([1, 1.7, 1])
    assert len(g.neighbours(corner)) == 3
    with pytest.raises(IndexError):
        g.neighbours(len(g))


def test_low_ceiling_lowers_the_eye_range():
    g = ViewcellGrid(WalkArea([[0, 0, 4, 4, 0.0, 1.6]], eye_range=(1.5, 1.9)), 4.0)
    box = g.cell(0).box
    assert box[1, 1] <= 1.5 + 1e-9 and box[0, 1] <= box[1, 1]


def test_configurable_cell_size_and_validation():
    w = WalkArea([[0, 0, 10, 10, 0.0]])
    assert len(ViewcellGrid(w, 2.0)) == 25
    assert len(ViewcellGrid(w, 5.0)) == 4
    with pytest.raises(ValueError):
        ViewcellGrid(w, 0.0)
    with pytest.raises(ValueError):
        Viewcell(np.array([[1, 1, 1], [0, 0, 0]]))
    with pytest.raises(ValueError):
        Viewcell(np.array([[np.nan, 1, 1], [2, 2, 2]]))


def test_empty_walk_area():
    g = ViewcellGrid(WalkArea(np.zeros((0, 5))), 4.0)
    assert len(g) == 0 and g.cell_of([0, 0, 0]) is None


def test_walk_area_of_too_many_cells_is_refused_before_allocating():
    from visibility.viewcells import MAX_VIEWCELLS

    per_side = int(np.sqrt(MAX_VIEWCELLS) * 0.55)  # 8 m cells; twice as many 4 m ones
    side = 8.0 * per_side
    assert (2 * per_side) ** 2 > MAX_VIEWCELLS >= per_side ** 2
    walk = WalkArea(np.array([[0.0, 0.0, side, side, 0.0]]))
    with pytest.raises(ValueError, match="MAX_VIEWCELLS"):
        ViewcellGrid(walk, 4.0)
    # The same walk area in cells twice as wide is fine.
    assert len(ViewcellGrid(walk, 8.0)) == per_side ** 2
    # Rectangles wider than float64 spans are refused, not overflowed.
    with pytest.raises(ValueError):
        ViewcellGrid(WalkArea(np.array([[-1.7e308, 0.0, 1.7e308, 4.0, 0.0]])), 4.0)


def test_thin_axes_collapse_to_the_degenerate_region():
    from visibility.viewcells import MIN_EXTENT

    point = Viewcell(np.array([[0.0, 0.0, 0.0], [1e-300, 1e-300, 1e-300]]))
    np.testing.assert_array_equal(point.box, np.zeros((2, 3)))
    # Only the thin axes collapse: a 1e-9 m thick slab is the flat cell it is.
    slab = Viewcell(np.array([[-1.0, 1.7, -1.0], [1.0, 1.7 + 1e-9, 1.0]]))
    np.testing.assert_array_equal(slab.box, [[-1.0, 1.7, -1.0], [1.0, 1.7, 1.0]])
    # At the floor an extent is kept; the 1 mm cell of the cores' tiny-cell check is untouched.
    edge = np.array([[0.0, 0.0, 0.0], [MIN_EXTENT, 2 * MIN_EXTENT, 1e-3]])
    np.testing.assert_array_equal(Viewcell(edge).box, edge)
    tiny = np.array([[2.5, 1.7, 3.0], [2.501, 1.701, 3.001]])
    np.testing.assert_array_equal(Viewcell(tiny).box, tiny)


def test_thin_axes_far_from_the_origin_collapse_by_ulps():
    from visibility.viewcells import MIN_EXTENT, MIN_EXTENT_ULPS, min_extent

    # Near the origin the absolute floor rules; 1e12 m out, a few ulps are more than a micron.
    np.testing.assert_array_equal(min_extent(np.array([[0.0] * 3, [1e3] * 3])), [MIN_EXTENT] * 3)
    far = 1e12
    ulp = np.spacing(far)
    assert MIN_EXTENT_ULPS * ulp > MIN_EXTENT
    noise = Viewcell(np.array([[far, 0.0, 0.0], [far + 8 * ulp, 1.0, 1.0]]))
    assert noise.size[0] == 0.0 and noise.size[1] == 1.0
    kept = Viewcell(np.array([[far, 0.0, 0.0], [far + 1.0, 1.0, 1.0]]))
    assert kept.size[0] == 1.0


def test_streets_narrower_than_a_cell_still_get_cells():
    # Two 10 m streets crossing, under 50 m cells: no column centre lies in either, yet every
    # point of them must lie in a cell (a city served at big cells for dual_ray).
    w = WalkArea([[0, 45, 200, 55, 0.0], [95, 0, 105, 200, 0.0]])
    g = ViewcellGrid(w, 50.0)
    assert len(g) > 0
    rng = np.random.default_rng(0)
    for x0, z0, x1, z1, *_ in w.rects:
        for x, z in zip(rng.uniform(x0, x1, 50), rng.uniform(z0, z1, 50), strict=True):
            assert g.cell_of([x, 1.7, z]) is not None, (x, z)
    # Rectangles at least a cell wide keep the centre rule: nothing changes for them.
    assert len(ViewcellGrid(WalkArea([[0, 0, 10, 10, 0.0]]), 5.0)) == 4


def test_a_cell_over_a_thin_street_walks_on_the_street():
    # A 10 m street under 50 m cells: cell centres lie off the street, walk points on it.
    w = WalkArea([[0, 45, 200, 55, 0.0]])
    g = ViewcellGrid(w, 50.0)
    for c in range(len(g)):
        p = g.walk_point(c)
        assert 45.0 <= p[2] <= 55.0 and g.cell_of(p) == c
    # A cell whose centre is walkable keeps its centre.
    g4 = ViewcellGrid(WalkArea([[0, 0, 10, 10, 0.0]]), 5.0)
    assert np.allclose(g4.walk_point(0), g4.boxes[0].mean(axis=0))


def test_a_stack_of_boxes_collapses_as_each_box_alone():
    from visibility.viewcells import collapse_thin_axes

    rng = np.random.default_rng(4)
    lo = rng.uniform(-1e7, 1e7, (64, 3))
    # Extents from zero through sub-micron to metres, some below the far boxes' ulp floor.
    size = rng.choice([0.0, 1e-9, 1e-7, 5e-6, 1e-3, 1.0], (64, 3))
    boxes = np.stack([lo, lo + size], axis=1)
    stacked = collapse_thin_axes(boxes)
    one_by_one = np.stack([collapse_thin_axes(b) for b in boxes])
    np.testing.assert_array_equal(stacked, one_by_one)
    assert (stacked[:, 1] == stacked[:, 0]).any() and (stacked[:, 1] > stacked[:, 0]).any()


def test_grid_centers_are_the_cells_centres():
    from visibility.generators import make_scene

    grid = ViewcellGrid.for_scene(make_scene("rooms", triangles=5000))
    expected = np.stack([grid.cell(i).center for i in range(len(grid))])
    np.testing.assert_array_equal(grid.centers(), expected)
