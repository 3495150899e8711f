"""The ``sampling`` core: registration, parameters, and its PVS against a denser ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from tests.visibility.test_ground_truth import CELL, walled_scene
from visibility.cores.base import available_cores, get_core
from visibility.cores.sampling import MAX_SAMPLES, SamplingCore, SamplingParams
from visibility.generators import make_scene
from visibility.ground_truth import fn_fp_rates, sample_pvs
from visibility.viewcells import ViewcellGrid


def test_registered_under_its_name():
    assert "sampling" in available_cores()
    core = get_core("sampling")
    assert isinstance(core, SamplingCore) and core.Params is SamplingParams
    assert core.description and 0.0 < core.fn_bound < 1.0


def test_parameters_are_validated():
    core = SamplingCore()
    p = core.make_params()
    assert (p.samples, p.batch, p.resolution) == (32, 8, 256)
    assert core.make_params(samples=1, batch=1).samples == 1
    assert core.make_params(samples=MAX_SAMPLES).samples == MAX_SAMPLES
    for bad in ({"samples": 0}, {"samples": MAX_SAMPLES + 1}, {"samples": 2.5}, {"batch": 0},
                {"resolution": 4}, {"nope": 1}):
        with pytest.raises(ValueError):
            core.make_params(**bad)
    assert "samples=32" in p.cache_key()


def test_compute_matches_sample_pvs_and_reports_stats():
    scene, known = walled_scene()
    core = SamplingCore()
    params = core.make_params(samples=12, batch=4, resolution=48, seed=2)
    pvs = core.compute(scene, CELL, params)
    gt = sample_pvs(scene, CELL, n_points=12, resolution=48, seed=2, batch=4)
    np.testing.assert_array_equal(pvs.triangle_ids, gt.triangle_ids)
    assert pvs.stats["samples"] == 12 and pvs.stats["resolution"] == 48
    assert pvs.stats["pixels_rendered"] == 12 * 6 * 48 * 48
    assert [c[0] for c in pvs.stats["convergence"]] == [4, 8, 12]
    assert pvs.seconds > 0
    assert not set(pvs.triangle_ids.tolist()) & set(known["hidden_box"] + known["degenerate"])


def test_object_granularity():
    scene, known = walled_scene()
    core = SamplingCore()
    pvs = core.compute(scene, CELL, core.make_params(samples=4, resolution=32,
                                                     granularity="object"))
    assert pvs.granularity == "object" and pvs.object_ids is not None


def test_false_negatives_within_bound_against_denser_ground_truth():
    scene, _ = walled_scene()
    core = SamplingCore()
    pvs = core.compute(scene, CELL, core.make_params(samples=16, resolution=64))
    gt = sample_pvs(scene, CELL, n_points=64, resolution=128, seed=7)
    fn, fp = fn_fp_rates(pvs.triangle_ids, gt.triangle_ids)
    assert fn <= core.fn_bound
    # It reports only what it saw: anything beyond the reference is a sliver the reference missed.
    assert fp <= 0.1


def test_segment_points_lie_on_the_segment_and_spread_over_it():
    from visibility.ground_truth import segment_points

    p, q = np.array([1.0, 2.0, 3.0]), np.array([5.0, 2.0, -1.0])
    pts = segment_points(p, q, 16, np.random.default_rng(0))
    t = (pts - p) @ (q - p) / ((q - p) @ (q - p))
    np.testing.assert_allclose(p + t[:, None] * (q - p), pts, atol=1e-12)
    # One point in each sixteenth of the segment.
    np.testing.assert_array_equal(np.sort(np.floor(t * 16)), np.arange(16))
    assert segment_points(p, q, 0, np.random.default_rng(0)).shape == (0, 3)


def test_sampling_segment_pvs_is_within_from_segment_pvs():
    """Sampling along a diagonal segment only finds what the exact from-segment core finds there.
    Its random cube orientations see far grazing ground between the pixel centres of an
    axis-aligned cube, so the exact side gets jittered runs too (measured: 101 extras with one
    run, none with four)."""
    from visibility.generators import make_scene
    from visibility.viewcells import ViewcellGrid

    scene = make_scene("village", triangles=4000, seed=3)
    grid = ViewcellGrid.for_scene(scene)
    box = grid.cell(len(grid) // 2).box
    p, q = box[0].copy(), box[1].copy()
    sampling = get_core("sampling")
    a = sampling.compute_segment(scene, p, q, sampling.make_params(samples=16, resolution=64))
    exact = get_core("from_segment")
    b = exact.compute_segment(scene, p, q, exact.make_params(resolution=128, runs=4))
    assert a.stats["samples"] == 16 and len(a) > 0
    extra = np.setdiff1d(a.triangle_ids, b.triangle_ids)
    assert len(extra) <= 0.01 * len(a), len(extra)


def test_spheres_seen_by_the_sampler_come_back_as_sphere_ids():
    scene = make_scene("spheres", spheres=150, states=3, seed=1)
    cell = ViewcellGrid.for_scene(scene).cell(0)
    core = get_core("sampling")
    params = core.make_params(samples=8, resolution=48, seed=3)
    pvs = core.compute(scene, cell, params)
    gt = sample_pvs(scene, cell, n_points=8, resolution=48, seed=3, batch=8)
    assert len(gt.sphere_ids) > 0
    assert pvs.sphere_ids is not None
    np.testing.assert_array_equal(pvs.sphere_ids, gt.sphere_ids)
