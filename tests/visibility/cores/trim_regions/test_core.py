"""The core around the kernels: stats per phase (no NaN), moving geometry tested as hulls,
granularity, determinism and cancellation."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

import visibility.cores.trim_regions.pipeline as pipeline
from visibility.cancel import CancelToken, ComputationCancelled
from visibility.cores.base import get_core
from visibility.generators import make_scene
from visibility.ground_truth import cell_around, sample_pvs
from visibility.scene import moving_faces
from visibility.topology import unseen_back_faces
from visibility.viewcells import Viewcell

CORE = get_core("trim_regions")


def test_stats_report_every_phase_and_the_k_buffers():
    scene = make_scene("village", triangles=5000)
    pvs = CORE.compute(scene, Viewcell(cell_around(scene, 0.3, 0)), CORE.make_params())
    st = pvs.stats
    for k in pipeline.PHASES:
        assert st[k] >= 0.0
    assert st["views"] == 6 * st["spheres"] and st["layers"] >= st["views"]
    assert 0 < st["kbuffer_used_bytes"] <= st["kbuffer_allocated_bytes"]
    assert st["mean_sequence_length"] > 0 and st["active_pixels"] > 0
    assert st["sealed_pixels"] + st["trimmed_pixels"] <= st["views"] * 256 * 256
    for k, v in st.items():
        if isinstance(v, float):
            assert math.isfinite(v), k


def test_back_faces_no_eye_of_the_cell_can_see_leave_the_answer():
    # The village's houses are closed boxes: the interval rules let some of their far sides
    # through, and the closed-surface rule (topology.unseen_back_faces) takes them out.
    scene = make_scene("village", triangles=20_000)
    box = cell_around(scene, 0.3, 0)
    pvs = CORE.compute(scene, Viewcell(box), CORE.make_params())
    assert pvs.stats["unseen_back_faces"] > 0
    assert not unseen_back_faces(scene, box)[pvs.triangle_ids].any()


def test_moving_triangles_and_spheres_are_always_tested():
    for name, seed in (("swaying_grass", 1), ("spheres", 2)):
        scene = make_scene(name, triangles=3000 if name == "swaying_grass" else 300)
        box = cell_around(scene, 0.3, 0)
        pvs = CORE.compute(scene, Viewcell(box), CORE.make_params(resolution=128))
        gt = sample_pvs(scene, Viewcell(box), n_points=32, resolution=128, seed=seed)
        moving = np.flatnonzero(moving_faces(scene))
        seen_moving = np.intersect1d(gt.triangle_ids, moving)
        assert not np.setdiff1d(seen_moving, pvs.triangle_ids).size, name
        if scene.n_spheres:
            assert not np.setdiff1d(gt.sphere_ids, pvs.sphere_ids).size


def test_object_granularity_and_determinism():
    scene = make_scene("city", triangles=5000)
    cell = Viewcell(cell_around(scene, 0.3, 1))
    tri = CORE.compute(scene, cell, CORE.make_params())
    again = CORE.compute(scene, cell, CORE.make_params())
    np.testing.assert_array_equal(tri.triangle_ids, again.triangle_ids)
    obj = CORE.compute(scene, cell, CORE.make_params(granularity="object"))
    assert set(tri.triangle_ids.tolist()) <= set(obj.triangle_ids.tolist())
    np.testing.assert_array_equal(np.unique(scene.object_ids[tri.triangle_ids]), obj.object_ids)


def test_a_cancelled_computation_stops_between_layers():
    scene = make_scene("rooms", triangles=5000)
    cell = Viewcell(cell_around(scene, 0.3, 0))
    token = CancelToken()
    token.cancel("test")
    with pytest.raises(ComputationCancelled):
        CORE.compute(scene, cell, CORE.make_params(), token=token)


def _box(scene, side):
    c = cell_around(scene, 0.3, 0).mean(axis=0)
    return np.stack([c - 0.5 * side, c + 0.5 * side])


def test_views_solved_two_at_a_time_give_the_answer_of_one_at_a_time(monkeypatch):
    # A 0.6 m box in spheres of 0.3 m: 8 spheres, 48 views, with two spheres' views in
    # flight at once.
    scene = make_scene("village", triangles=5000)
    box = _box(scene, 0.6)
    runs = {}
    for w in (1, 2):
        monkeypatch.setattr(pipeline, "_view_workers", lambda w=w: w)
        runs[w] = CORE.compute(scene, Viewcell(box), CORE.make_params(resolution=64,
                                                                      max_delta=0.3))
    one, two = runs[1], runs[2]
    assert one.stats["spheres"] == 8
    np.testing.assert_array_equal(one.triangle_ids, two.triangle_ids)
    for k in ("views", "layers", "silhouette_trims", "active_pixels", "trimmed_pixels",
              "sealed_pixels", "near_eye", "mean_sequence_length", "kbuffer_used_bytes"):
        assert one.stats[k] == two.stats[k], k
    assert (one.stats["view_workers"], two.stats["view_workers"]) == (1, 2)
    assert two.stats["kbuffer_allocated_bytes"] == 2 * one.stats["kbuffer_allocated_bytes"]


def test_gathers_made_aside_by_another_worker_give_the_same_answer(monkeypatch):
    # Every sphere's leading view has its gather from v* queued aside (ASIDE_SHARE 0), and
    # a worker with no view left makes it while that view rasterizes.
    scene = make_scene("village", triangles=5000)
    box = _box(scene, 0.6)
    monkeypatch.setattr(pipeline, "_view_workers", lambda: 1)
    one = CORE.compute(scene, Viewcell(box), CORE.make_params(resolution=64))
    monkeypatch.setattr(pipeline, "_view_workers", lambda: 2)
    monkeypatch.setattr(pipeline, "ASIDE_SHARE", 0.0)
    # A view waits (a second at most) for the other worker to take up its gather
    # before it goes on, so the aside path runs however fast the view is.
    started: dict[int, threading.Event] = {}
    task, set_up = pipeline._render_task, pipeline._Gather.set_up

    def aside_task(render, crew):
        started.setdefault(id(render), threading.Event()).set()
        return task(render, crew)

    def waiting_set_up(self, *a):
        started.setdefault(id(self), threading.Event()).wait(1.0)
        return set_up(self, *a)

    monkeypatch.setattr(pipeline, "_render_task", aside_task)
    monkeypatch.setattr(pipeline._Gather, "set_up", waiting_set_up)
    aside = CORE.compute(scene, Viewcell(box), CORE.make_params(resolution=64))
    np.testing.assert_array_equal(one.triangle_ids, aside.triangle_ids)
    assert one.stats["gathers_aside"] == 0
    assert 0 < aside.stats["gathers_aside"] <= aside.stats["spheres"]


def test_a_cancel_while_views_run_in_threads_stops_them_all(monkeypatch):
    monkeypatch.setattr(pipeline, "_view_workers", lambda: 2)
    scene = make_scene("village", triangles=5000)
    cell = Viewcell(_box(scene, 1.0))
    before = _threads()
    token = CancelToken()
    timer = threading.Timer(0.2, token.cancel, args=("test",))
    timer.start()
    t0 = time.perf_counter()
    with pytest.raises(ComputationCancelled):
        CORE.compute(scene, cell, CORE.make_params(), token=token)
    stopped = time.perf_counter() - t0
    timer.join()
    # The whole cell takes seconds; a cancel ends it within about one view's time, and no
    # view thread outlives the computation.
    full = CORE.compute(scene, cell, CORE.make_params()).seconds
    assert stopped < full
    assert not _threads() - before


def _threads() -> set[threading.Thread]:
    """The live threads but the timers: ``warm.WARM`` keeps one that releases the kept
    buffers after ``KEEP_SECONDS`` idle (a computation replaces it), whose lifetime depends
    on when the last computation of the process ended, not on this one."""
    return {t for t in threading.enumerate() if not isinstance(t, threading.Timer)}


def test_auto_considers_it_for_small_cells_only():
    scene = make_scene("city", triangles=2000)
    assert CORE.fit(scene, 0.3).score > 1.0
    assert CORE.fit(scene, 4.0).score < 1.0


def test_the_eyes_gather_adds_what_eyes_inside_the_cell_see():
    # gather_eyes, a sampling add-on: the views of eyes stratified in the cell (the pipeline's
    # seed, SUPERSAMPLE times the resolution) join the answer; the default, 0, leaves the
    # paper's gather from v* alone: the method.
    from visibility.cores.trim_regions.quality import FRAME_NEAR

    assert CORE.make_params().gather_eyes == 0
    scene = make_scene("rooms", triangles=5000)
    box = cell_around(scene, 0.3, 2)
    with_eyes = CORE.compute(scene, Viewcell(box),
                             CORE.make_params(resolution=64, gather_eyes=pipeline.GATHER_EYES))
    without = CORE.compute(scene, Viewcell(box), CORE.make_params(resolution=64))
    assert with_eyes.stats["eye_gathered"] >= len(with_eyes) - len(without) >= 0
    assert without.stats["eye_gathered"] == 0
    assert set(without.triangle_ids.tolist()) <= set(with_eyes.triangle_ids.tolist())
    eyes = sample_pvs(scene, Viewcell(box), n_points=pipeline.GATHER_EYES,
                      resolution=pipeline.SUPERSAMPLE * 64, seed=pipeline.GATHER_SEED,
                      near=FRAME_NEAR)
    seen = eyes.triangle_ids[~unseen_back_faces(scene, box)[eyes.triangle_ids]]
    assert not np.setdiff1d(seen, with_eyes.triangle_ids).size


@pytest.mark.parametrize("name", ["two_rooms_and_a_door", "open_ring", "stiff_cases"])
def test_the_sampling_add_on_keeps_the_declared_bounds_on_the_designed_scenes(name):
    # fn_bound and fp_bound are what the designed scenes measure in both modes, so the
    # conformance suite (at the defaults: the method alone) and this test (with the eyes'
    # gather) fail on a regression of either.
    from visibility.cores import designed_scenes as ds
    from visibility.cores.checks import check_params, designed_reference
    from visibility.ground_truth import fn_fp_rates

    scene, cell, _ = getattr(ds, name)()
    pvs = CORE.compute(scene, cell, check_params(CORE, gather_eyes=pipeline.GATHER_EYES))
    fn, fp = fn_fp_rates(pvs.triangle_ids, designed_reference(name))
    assert fn <= CORE.fn_bound and fp <= CORE.fp_bound, (fn, fp)


def test_each_layer_resolves_the_pixels_it_marked_and_counts_entries_without_a_frame_pass(
        monkeypatch):
    # The rasterizers keep each band's list of active pixels and its entries held; before
    # every resolve those must be exactly the active pixels and the k-buffers' total, and the
    # lists are empty after it.
    seen = {"layers": 0}
    resolve = pipeline._resolve

    def checked(kb, res, final, *args):
        bands = (res + 7) // 8
        queued = np.concatenate([kb.queue[b * 8 * res:b * 8 * res + kb.queued[b]]
                                 for b in range(bands)])
        assert np.array_equal(np.sort(queued), np.flatnonzero(kb.active))
        assert kb.held_entries[:bands].sum() == kb.count.sum()
        resolve(kb, res, final, *args)
        assert not kb.queued.any() and not kb.active.any()
        assert kb.held_entries[:bands].sum() == kb.count.sum()
        seen["layers"] += 1

    monkeypatch.setattr(pipeline, "_resolve", checked)
    scene = make_scene("village", triangles=5000)
    pvs = CORE.compute(scene, Viewcell(cell_around(scene, 0.3, 2)),
                       CORE.make_params(resolution=64))
    assert len(pvs) and seen["layers"] > 6


def test_an_unknown_small_raster_is_refused_by_name():
    from visibility.cores.trim_regions.cache import build_scene_data

    with pytest.raises(ValueError, match="small"):
        CORE.make_params(small="everywhere")
    scene = make_scene("rooms", triangles=2_000)
    with pytest.raises(ValueError, match="small"):
        pipeline.trim_pvs(scene, build_scene_data(scene), cell_around(scene, 0.3, 0), 32, 0.3,
                 small="everywhere")


def test_a_pixel_keeps_the_hidden_spans_of_each_wall_a_row_of_rooms_puts_on_it(monkeypatch):
    # A cube of the generated rooms looks through door after door: a pixel validates one
    # wall's interval per door frame it passes, more than 4 on this cube. Each hidden span
    # kept hides small triangles behind that wall (``hulls.small_in_front``); with room for
    # only 4 the rest were dropped and reported, so the answer grows by triangles no eye of
    # the cube sees (cos, conservative, leaves them out of the box holding the sphere).
    import visibility.cores.trim_regions.kbuffer as kbuffer
    from visibility.cores.trim_regions.frustum import cover_box
    from visibility.cores.trim_regions.warm import WARM
    from visibility.ray_frames import first_open_cell
    from visibility.viewcells import ViewcellGrid

    scene = make_scene("rooms", triangles=20_000)
    grid = ViewcellGrid.for_scene(scene)
    c = grid.cell(first_open_cell(scene, grid, len(grid) // 2)).center
    box = np.stack([c - 0.15, c + 0.15])
    kept = kbuffer.SPANS
    answers = {}
    for spans in (4, kept):
        monkeypatch.setattr(kbuffer, "SPANS", spans)
        WARM.release()  # fresh k-buffers, sized by SPANS
        answers[spans] = CORE.compute(scene, Viewcell(box), CORE.make_params()).triangle_ids
    WARM.release()
    wide, narrow = answers[kept], answers[4]
    assert kept > 4 and len(wide) < len(narrow)
    assert np.isin(wide, narrow).all()
    centres, delta = cover_box(box, CORE.make_params().max_delta)
    around = np.stack([centres.min(axis=0) - delta, centres.max(axis=0) + delta])
    cos = get_core("cos")
    seen = cos.compute(scene, Viewcell(around), cos.make_params()).triangle_ids
    # What the narrow buffers added beyond the wide ones, no eye of the cube sees.
    assert not np.isin(np.setdiff1d(narrow, wide), seen).any()
