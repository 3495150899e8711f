"""``cos`` solved as sub-cells (``subcells``, ``core.cos_subcells``): the union of the
sub-cells' answers, unchanged by what each passes on as known, and still conservative."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cores.base import get_core
from visibility.cores.cos.core import cos_pvs, cos_subcells, sub_boxes
from visibility.generators import make_scene
from visibility.ground_truth import cell_around
from visibility.viewcells import Viewcell


def test_sub_boxes_tile_the_cell_in_snake_order():
    box = np.array([[0.0, 1.4, 10.0], [4.0, 1.8, 14.0]])
    subs = sub_boxes(box, 3)
    assert subs.shape == (9, 2, 3)
    # The height stays whole, the ground is split into equal parts covering the box.
    np.testing.assert_array_equal(subs[:, :, 1], np.broadcast_to(box[:, 1], (9, 2)))
    np.testing.assert_allclose((subs[:, 1] - subs[:, 0])[:, [0, 2]], 4.0 / 3.0)
    assert np.prod(subs[:, 1] - subs[:, 0], axis=1).sum() == pytest.approx(np.prod(box[1] - box[0]))
    np.testing.assert_allclose(subs[:, 0].min(axis=0), box[0])
    np.testing.assert_allclose(subs[:, 1].max(axis=0), box[1])
    # Consecutive boxes share a side.
    for a, b in zip(subs[:-1], subs[1:], strict=True):
        touch = np.isclose(a[1], b[0]) | np.isclose(a[0], b[1])
        same = np.isclose(a, b).all(axis=0)
        assert touch[[0, 2]].sum() == 1 and same.sum() == 2


def test_the_answer_is_the_union_of_the_sub_cells():
    scene = make_scene("village", triangles=5000)
    box = cell_around(scene, 4.0, 0)
    ids, stats = cos_subcells(scene, box, 2, 32)
    union = np.unique(np.concatenate([cos_pvs(scene, b, 32)[0] for b in sub_boxes(box, 2)]))
    np.testing.assert_array_equal(ids, union)
    assert stats["subcells"] == 2 and stats["views"] == 4 * 30
    assert stats["union_sizes"][-1] == len(ids)
    assert stats["union_sizes"] == sorted(stats["union_sizes"])


def test_the_core_parameter_runs_the_sub_cells():
    scene = make_scene("city", triangles=5000)
    box = cell_around(scene, 4.0, 1)
    core = get_core("cos")
    pvs = core.compute(scene, Viewcell(box), core.make_params(resolution=32, subcells=2))
    ids, _ = cos_subcells(scene, box, 2, 32)
    np.testing.assert_array_equal(pvs.triangle_ids, ids)
    assert core.estimate_cost(scene, Viewcell(box), core.make_params(subcells=2)).seconds == \
        pytest.approx(4 * core.estimate_cost(scene, Viewcell(box), core.make_params()).seconds)
    with pytest.raises(ValueError):
        core.make_params(subcells=0)
