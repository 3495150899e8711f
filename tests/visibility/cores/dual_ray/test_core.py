"""The dual-ray core: designed cases, fences, per-scene caches, stats, cancellation, bad input,
moving triangles and the refusal of scenes that are not 2.5D."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cancel import CancelToken, ComputationCancelled
from visibility.cores import designed_scenes as ds
from visibility.cores.base import get_core
from visibility.cores.dual_ray.core import NotTwoPointFiveD, dual_ray_pvs
from visibility.cores.dual_ray.fences import build_fences
from visibility.cores.dual_ray.kdtree import scene_kdtree
from visibility.generators import make_scene
from visibility.scene import Scene
from visibility.viewcells import Viewcell

CORE = get_core("dual_ray")


@pytest.mark.parametrize("resolution", [16, 64, 128, 256])
def test_designed_cases_at_every_resolution(resolution):
    scene, cell, known = ds.city_blocks()
    found = set(CORE.compute(scene, cell, CORE.make_params(resolution=resolution))
                .triangle_ids.tolist())
    assert set(known["gap_visible"]) <= found and set(known["tall_visible"]) <= found
    assert not set(known["hidden"]) & found


def test_less_triangle_refinement_gives_supersets():
    scene, cell, known = ds.city_blocks()
    found = {p: set(CORE.compute(scene, cell, CORE.make_params(triangle_refine=p))
                    .triangle_ids.tolist()) for p in ("all", "marginal", "none")}
    assert found["all"] <= found["marginal"] <= found["none"]
    assert found["all"] != found["none"]
    for f in found.values():
        assert set(known["visible"]) <= f


def test_auto_refinement_tests_every_triangle_only_while_that_is_cheap(monkeypatch):
    import visibility.cores.dual_ray.core as dual_ray_core

    scene, cell, _ = ds.city_blocks()
    box = np.asarray(cell.box, dtype=np.float64)
    ids = {p: dual_ray_pvs(scene, box, 64, p) for p in ("all", "marginal", "auto")}
    assert ids["auto"][1]["triangle_refine"] == "all"
    assert np.array_equal(np.sort(ids["auto"][0]), np.sort(ids["all"][0]))
    held = ids["auto"][1]["leaf_triangles"]
    monkeypatch.setattr(dual_ray_core, "REFINE_ALL_MAX", held - 1)
    ids_small, stats = dual_ray_pvs(scene, box, 64, "auto")
    assert stats["triangle_refine"] == "marginal"
    assert np.array_equal(np.sort(ids_small), np.sort(ids["marginal"][0]))


def test_a_facade_grid_becomes_one_strip_per_side():
    scene = make_scene("city", triangles=20_000)
    fences = build_fences(scene)
    walls = fences.walls
    assert 0 < len(fences) < walls / 4, (len(fences), walls)
    # Strips stay inside the walls: tops no higher, bottoms no lower than the scene's.
    assert fences.top.max() <= scene.vertices[:, 1].max() + 1e-9
    assert fences.bot.min() >= scene.vertices[:, 1].min() - 1e-9
    assert np.all(fences.top >= fences.bot - 1e-9)


def test_only_upright_static_faces_occlude():
    b = ds.Builder()
    b.quad((0, 0, 5), (1, 0, 5), (1, 1, 5), (0, 1, 5), 0)  # upright: a wall
    b.quad((0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0), 1)  # flat: a roof
    assert len(build_fences(b.scene("two"))) == 1


def test_the_tree_and_fences_are_built_once_per_scene():
    scene, cell, _ = ds.city_blocks()
    first = CORE.compute(scene, cell).stats
    again = CORE.compute(scene, cell).stats
    assert again["kdtree_seconds"] == 0.0 and again["fence_seconds"] == 0.0
    assert first["kd_nodes"] == again["kd_nodes"] and scene_kdtree(scene)[1] == 0.0


def test_stats_report_the_phases():
    scene, cell, _ = ds.city_blocks()
    stats = CORE.compute(scene, cell).stats
    for k in ("traversal_seconds", "refine_seconds", "kdtree_seconds", "fence_seconds"):
        assert isinstance(stats[k], float) and stats[k] >= 0.0
    assert stats["nodes_visited"] >= stats["nodes_culled"] >= 0
    assert stats["triangle_tests"] >= stats["triangles_culled"] > 0
    assert all(np.isfinite(v) for v in stats.values() if isinstance(v, float))


def test_a_cancelled_computation_stops():
    scene, cell, _ = ds.city_blocks()
    token = CancelToken()
    token.cancel("test")
    with pytest.raises(ComputationCancelled):
        CORE.compute(scene, cell, token=token)


def test_a_scene_that_is_not_2_5d_raises_with_the_reason():
    village = make_scene("village", triangles=5_000)
    with pytest.raises(NotTwoPointFiveD, match="2.5D.*overhang"):
        CORE.compute(village, Viewcell(np.array([[0.0, 1.5, 0.0], [20.0, 1.9, 20.0]])))


@pytest.mark.parametrize("box", [
    [[5000.0, 1.5, 5000.0], [5100.0, 1.9, 5100.0]],    # far outside the scene
    [[-1e4, -1e4, -1e4], [1e4, 1e4, 1e4]],              # around everything
    [[0.0, 1.7, 0.0], [0.0, 1.7, 0.0]],                  # a point
    [[-5.0, 30.0, -5.0], [5.0, 30.0, 5.0]],              # flat, above the roofs
])
def test_odd_cells_give_a_valid_pvs(box):
    scene, _, known = ds.city_blocks()
    pvs = CORE.compute(scene, Viewcell(np.array(box)))
    ids = pvs.triangle_ids
    assert np.all(np.diff(ids) > 0) and np.all(scene.valid_faces[ids])
    if box[0][0] == -1e4:
        assert len(ids) == int(scene.valid_faces.sum())


def test_degenerate_and_nan_faces_are_never_reported():
    scene, cell, _ = ds.city_blocks()
    n = scene.n_vertices
    v = np.concatenate([scene.vertices, [[0, 0, 12], [1, 0, 12], [np.nan, 0, 12]]])
    f = np.concatenate([scene.faces, [[n, n + 1, n + 2], [n, n, n + 1]]])
    bad = Scene(v, f, name="bad")
    bad.meta["is_2_5d"] = True
    ids = CORE.compute(bad, cell).triangle_ids
    assert not {scene.n_triangles, scene.n_triangles + 1} & set(ids.tolist())


def test_moving_triangles_never_occlude_and_are_found_over_their_sweep():
    scene, cell, known = ds.city_blocks()
    # The wall hiding "wall_hidden" (object 1) slides 200 m aside and back: it may be
    # anywhere along its way, so it must not hide the box behind it.
    wall = scene.object_ids == 1
    moved = scene.vertices.copy()
    wall_v = np.unique(scene.faces[wall])
    moved[wall_v, 0] += 200.0
    dyn = Scene(scene.vertices, scene.faces, scene.object_ids, scene.colors, name="dyn",
                states=np.stack([scene.vertices, moved, scene.vertices]),
                state_times=np.array([0.0, 1.0, 2.0]))
    dyn.meta["is_2_5d"] = True
    found = set(CORE.compute(dyn, cell).triangle_ids.tolist())
    assert set(known["wall_hidden"]) & found
    assert set(np.flatnonzero(wall).tolist()) & found


def test_the_answer_is_the_same_far_from_the_origin():
    a_scene, a_cell, _ = ds.city_blocks()
    b_scene, b_cell, _ = ds.city_blocks(offset=(1e6, 0.0, -1e6))
    a, _ = dual_ray_pvs(a_scene, a_cell.box, 128)
    b, _ = dual_ray_pvs(b_scene, b_cell.box, 128)
    np.testing.assert_array_equal(np.sort(a), np.sort(b))
