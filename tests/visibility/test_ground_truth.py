"""Sampled ground truth: stratified points (extreme boxes too), the PVS of known scenes, motion,
FN/FP rates, and the bounded buffers and cost estimate of sampling."""

from __future__ import annotations

import contextlib
import signal
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import visibility.ground_truth as gt_module
from visibility.ground_truth import (
    MAX_POINTS,
    MIN_EXTENT,
    GroundTruth,
    _grid_counts,
    estimate_sampling_cost,
    fn_fp_rates,
    sample_points,
    sample_pvs,
    segment_points,
)
from visibility.scene import Scene
from visibility.viewcells import Viewcell


class Tris:
    """Collects quads and boxes as separate triangles, remembering their ids."""

    def __init__(self) -> None:
        self.tris: list[list] = []

    def quad(self, a, b, c, d) -> list[int]:
        first = len(self.tris)
        self.tris += [[a, b, c], [a, c, d]]
        return [first, first + 1]

    def box(self, lo, hi) -> list[int]:
        (x0, y0, z0), (x1, y1, z1) = lo, hi
        ids = []
        ids += self.quad((x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0))
        ids += self.quad((x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1))
        ids += self.quad((x0, y0, z0), (x0, y0, z1), (x0, y1, z1), (x0, y1, z0))
        ids += self.quad((x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1))
        ids += self.quad((x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1))
        ids += self.quad((x0, y1, z0), (x0, y1, z1), (x1, y1, z1), (x1, y1, z0))
        return ids

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        v = np.array(self.tris, dtype=np.float64).reshape(-1, 3)
        return v, np.arange(len(v), dtype=np.int32).reshape(-1, 3)


CELL = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]))


def walled_scene():
    """A wall at z = 5 (x in [-20, 20], y in [0, 6]); a box in front of it, one behind it,
    and a floor quad; plus degenerate faces in plain view."""
    t = Tris()
    known = {
        "floor": t.quad((-20, 0, -20), (-20, 0, 4), (20, 0, 4), (20, 0, -20)),
        "wall": t.quad((-20, 0, 5), (20, 0, 5), (20, 6, 5), (-20, 6, 5)),
        "front_box": t.box((-0.5, 0.0, 2.5), (0.5, 1.0, 3.5)),
        "hidden_box": t.box((-0.5, 0.0, 7.0), (0.5, 1.0, 8.0)),
    }
    v, f = t.arrays()
    n, m = len(v), len(f)
    extra = np.array([[0, 1, 3.0], [1, 1, 3.0], [2, 1, 3.0], [np.nan, 1, 3.0], [0, 2, 3.0]])
    v = np.vstack([v, extra])
    f = np.vstack([f, [[n, n + 1, n + 2], [n, n + 3, n + 4], [n, n, n + 4]]])
    known["degenerate"] = [m, m + 1, m + 2]
    return Scene(v, f, name="walled"), known


# ----------------------------------------------------------------------------- sample_points
def test_sample_points_are_stratified_inside_the_box():
    box = np.array([[1.0, 1.5, -2.0], [5.0, 1.9, 2.0]])
    rng = np.random.default_rng(0)
    pts = sample_points(box, 64, rng)
    assert pts.shape == (64, 3) and pts.dtype == np.float64
    assert np.all(pts >= box[0]) and np.all(pts <= box[1])
    # 64 points on a 4 x 4 m square, 0.4 m tall: an 8 x 1 x 8 grid, one point per cell.
    cells = np.floor((pts - box[0]) / (box[1] - box[0]) * [8, 1, 8]).astype(int)
    assert len({tuple(c) for c in cells}) == 64
    # Any prefix is spread out too: the first 16 fall in at least 12 of the 16 quadrants-of-2m.
    q = np.floor((pts[:16] - box[0]) / 1.0)[:, [0, 2]]
    assert len({tuple(c) for c in q}) >= 10


def test_sample_points_deterministic_and_flat_boxes():
    box = np.array([[0.0, 1.7, 0.0], [3.0, 1.7, 2.0]])  # zero height
    a = sample_points(box, 10, np.random.default_rng(5))
    b = sample_points(box, 10, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert np.all(a[:, 1] == 1.7)
    point = np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(sample_points(point, 3, np.random.default_rng(0)),
                                  np.tile([1.0, 2.0, 3.0], (3, 1)))
    assert sample_points(box, 0, np.random.default_rng(0)).shape == (0, 3)
    with pytest.raises(ValueError):
        sample_points(np.array([[1.0, 0, 0], [0.0, 1, 1]]), 4, np.random.default_rng(0))
    with pytest.raises(ValueError):
        sample_points(box, -1, np.random.default_rng(0))


# ----------------------------------------------------------------------------- sample_pvs
def test_sample_pvs_finds_the_visible_and_never_the_hidden():
    scene, known = walled_scene()
    gt = sample_pvs(scene, CELL, n_points=24, resolution=64, seed=1, batch=8)
    assert isinstance(gt, GroundTruth)
    found = set(gt.triangle_ids.tolist())
    for name in ("floor", "wall"):
        assert set(known[name]) <= found, name
    # The side of the front box facing the cell (z = 2.5 quad) and its top are seen.
    assert set(known["front_box"][:2]) <= found
    assert set(known["front_box"][10:]) <= found
    assert not found & set(known["hidden_box"])
    assert not found & set(known["degenerate"])
    # Its far side (z = 3.5, facing away, behind the box itself) is hidden.
    assert not found & set(known["front_box"][2:4])
    assert gt.triangle_ids.dtype == np.int32
    assert np.all(np.diff(gt.triangle_ids) > 0)


def test_convergence_record_and_determinism():
    scene, _ = walled_scene()
    gt = sample_pvs(scene, CELL, n_points=20, resolution=48, seed=3, batch=8)
    assert [c[0] for c in gt.convergence] == [8, 16, 20]
    totals = [c[1] for c in gt.convergence]
    assert totals == sorted(totals)
    assert sum(c[2] for c in gt.convergence) == totals[-1] == len(gt.triangle_ids)
    assert gt.samples == 20 and gt.pixels == 20 * 6 * 48 * 48 and gt.seconds > 0
    again = sample_pvs(scene, CELL, n_points=20, resolution=48, seed=3, batch=8)
    np.testing.assert_array_equal(gt.triangle_ids, again.triangle_ids)
    assert gt.convergence == again.convergence


def test_dynamic_scene_unites_all_states():
    # A panel that slides from behind the wall (hidden) to in front of it (visible).
    scene, known = walled_scene()
    t = Tris()
    t.quad((-1, 0.5, 7.0), (1, 0.5, 7.0), (1, 2.5, 7.0), (-1, 2.5, 7.0))
    pv, pf = t.arrays()
    v = np.vstack([scene.vertices, pv])
    f = np.vstack([scene.faces, pf + len(scene.vertices)])
    moved = v.copy()
    moved[len(scene.vertices):, 2] = 4.0
    panel = [scene.n_triangles, scene.n_triangles + 1]
    static = Scene(v, f, states=np.stack([v, v]), state_times=[0.0, 1.0])
    gt = sample_pvs(static, CELL, n_points=8, resolution=48, seed=0)
    assert not set(panel) & set(gt.triangle_ids.tolist())
    dynamic = Scene(v, f, states=np.stack([v, moved]), state_times=[0.0, 2.0])
    gt = sample_pvs(dynamic, CELL, n_points=16, resolution=48, seed=0)
    assert set(panel) <= set(gt.triangle_ids.tolist())


def test_empty_scene_and_bad_arguments():
    empty = Scene(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32))
    gt = sample_pvs(empty, CELL, n_points=4, resolution=16, batch=3)
    assert len(gt.triangle_ids) == 0
    assert [c[0] for c in gt.convergence] == [3, 4]
    scene, _ = walled_scene()
    for kw in ({"n_points": 0}, {"batch": 0}, {"resolution": 0}):
        with pytest.raises(ValueError):
            sample_pvs(scene, CELL, **kw)


def test_progress_bar_runs(capsys):
    scene, _ = walled_scene()
    gt = sample_pvs(scene, CELL, n_points=2, resolution=16, progress=True)
    assert gt.samples == 2
    assert "ground truth" in capsys.readouterr().err


# ----------------------------------------------------------------------------- rates
def test_fn_fp_rates():
    assert fn_fp_rates([1, 2, 3, 4], [1, 2, 3, 4]) == (0.0, 0.0)
    fn, fp = fn_fp_rates([1, 2, 9], [1, 2, 3, 4])
    assert fn == pytest.approx(0.5) and fp == pytest.approx(1 / 3)
    assert fn_fp_rates([], []) == (0.0, 0.0)
    assert fn_fp_rates([], [1, 2]) == (1.0, 0.0)
    assert fn_fp_rates([5], []) == (0.0, 1.0)
    fn, fp = fn_fp_rates(np.array([3, 3, 1], dtype=np.int32), np.array([1, 3]))
    assert (fn, fp) == (0.0, 0.0)


# ----------------------------------------------------------------------------- extreme boxes
@contextlib.contextmanager
def _deadline(seconds: float):
    """TimeoutError when the block runs longer than ``seconds`` (a loop that never ends fails
    the test instead of hanging it)."""

    def _fire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, _fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def test_subnormal_box_of_the_report_is_a_point():
    """Issue 19: the box [[0,0,0],[1e-300]*3] spun ``_grid_counts`` forever."""
    for top in (1e-300, 5e-324, 1e-7):
        box = np.array([[0.0, 0.0, 0.0], [top, top, top]])
        with _deadline(5):
            pts = sample_points(box, 64, np.random.default_rng(0))
        assert pts.shape == (64, 3) and np.all(pts >= box[0]) and np.all(pts <= box[1])
    assert np.array_equal(_grid_counts(np.full(3, 1e-300), 1000), [1, 1, 1])


def test_thin_axes_are_flat_and_huge_boxes_stay_finite():
    # A segment 10 m long and 1e-9 m thick: every point is on the segment, spread along it.
    seg = np.array([[0.0, 0.0, 0.0], [10.0, 1e-9, 1e-9]])
    pts = sample_points(seg, 10, np.random.default_rng(1))
    assert np.array_equal(np.sort(np.floor(pts[:, 0])), np.arange(10))
    assert np.array_equal(_grid_counts(seg[1] - seg[0], 10), [10, 1, 1])
    # Corners near the float64 limit: the extent overflows, the points must not.
    wide = np.array([[-1.7e308] * 3, [1.7e308] * 3])
    pts = sample_points(wide, 27, np.random.default_rng(2))
    assert np.all(np.isfinite(pts)) and np.all(pts >= wide[0]) and np.all(pts <= wide[1])
    assert len(np.unique(np.sign(pts), axis=0)) == 8  # spread over all octants
    for bad in (np.inf, np.nan, -np.inf):
        with pytest.raises(ValueError):
            sample_points(np.array([[0.0, 0, 0], [1.0, 1, bad]]), 4, np.random.default_rng(0))
        with pytest.raises(ValueError):
            _grid_counts(np.array([1.0, bad, 1.0]), 4)
    with pytest.raises(ValueError):
        sample_points(seg, MAX_POINTS + 1, np.random.default_rng(0))


_coord = st.floats(min_value=-1.7e308, max_value=1.7e308, allow_nan=False,
                   allow_infinity=False, allow_subnormal=True)
_extent = st.one_of(st.just(0.0), st.sampled_from([5e-324, 1e-300, 1e-9, 1e-6, 1.0, 1e6, 1e300]),
                    st.floats(min_value=0.0, max_value=1e308, allow_subnormal=True))


@settings(max_examples=300, deadline=None)
@given(lo=st.tuples(_coord, _coord, _coord), ext=st.tuples(_extent, _extent, _extent),
       n=st.integers(min_value=0, max_value=3000), seed=st.integers(0, 2**32 - 1))
def test_sampling_grid_terminates_and_stays_inside_any_box(lo, ext, n, seed):
    lo = np.array(lo)
    with np.errstate(over="ignore"):
        hi = np.minimum(lo + np.array(ext), 1.7e308)
    box = np.stack([lo, np.maximum(lo, hi)])
    with _deadline(10):
        pts = sample_points(box, n, np.random.default_rng(seed))
    assert pts.shape == (n, 3) and np.all(np.isfinite(pts))
    assert np.all(pts >= box[0]) and np.all(pts <= box[1])
    with np.errstate(over="ignore"):
        size = box[1] - box[0]
    size = np.where(np.isfinite(size), size, box[1] * 0.5 - box[0] * 0.5)
    counts = _grid_counts(size, n)
    assert counts.dtype == np.int64 and np.all(counts >= 1) and np.all(counts <= MAX_POINTS)
    thick = size >= MIN_EXTENT
    assert np.all(counts[~thick] == 1)
    if thick.any() and n > 1:
        assert counts.prod() >= n  # room for n distinct strata


def test_segment_points_cap():
    with pytest.raises(ValueError):
        segment_points(np.zeros(3), np.ones(3), MAX_POINTS + 1, np.random.default_rng(0))


# ----------------------------------------------------------------------------- bounded memory
def _rooms(triangles: int):
    from visibility.generators import make_scene
    from visibility.viewcells import ViewcellGrid

    scene = make_scene("rooms", triangles=triangles, seed=0)
    grid = ViewcellGrid.for_scene(scene)
    return scene, grid.cell(len(grid) // 2)


def test_face_by_face_pass_gives_the_same_views(monkeypatch):
    scene, cell = _rooms(20000)
    whole = sample_pvs(scene, cell, n_points=12, resolution=96, seed=5, batch=4)
    monkeypatch.setattr(gt_module, "CUBEMAP_PIXELS_AT_ONCE", 0)
    faces = sample_pvs(scene, cell, n_points=12, resolution=96, seed=5, batch=4)
    np.testing.assert_array_equal(whole.triangle_ids, faces.triangle_ids)
    assert whole.convergence == faces.convergence and len(whole.triangle_ids) > 100


def test_large_resolution_buffers_stay_within_the_estimate():
    """At R = 2048 a view renders one face at a time: the traced peak stays under the estimate
    and well under the six-face buffers (6 R^2 x 12 bytes) one pass used to hold."""
    scene, cell = _rooms(2000)
    r = 2048
    assert not gt_module._whole_cubemap(r, False)
    sample_pvs(scene, cell, n_points=1, resolution=64, seed=0)  # compile outside the trace
    # Buffers kept by earlier renders (other tests) would hide this one's allocations.
    from visibility.raster.triangles import release_scratch

    release_scratch()
    tracemalloc.start()
    try:
        sample_pvs(scene, cell, n_points=2, resolution=r, seed=0)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    _, estimate = estimate_sampling_cost(scene.n_triangles, r, 2)
    assert r * r * 12 <= peak <= estimate
    assert peak < 6 * r * r * 12 / 2


def test_estimate_sampling_cost_scales_with_its_inputs():
    s1, b1 = estimate_sampling_cost(10_000, 256, 100)
    s2, b2 = estimate_sampling_cost(10_000, 256, 200)
    assert s2 == pytest.approx(2 * s1) and b2 > b1
    _, small = estimate_sampling_cost(10_000, 1024, 1)
    _, big = estimate_sampling_cost(10_000, 4096, 1)
    # R = 4096 renders one face at a time: 16 Mi pixels of buffers, not 96 Mi.
    assert 4096 ** 2 * 16 <= big < 6 * 4096 ** 2 * 12
    assert small >= 6 * 1024 ** 2 * 16
    seconds, peak = estimate_sampling_cost(1_000_000, 4096, 100_000)
    assert seconds > 3600 and peak < 1 << 30
    assert estimate_sampling_cost(1000, 256, 10, dynamic=True)[1] > \
        estimate_sampling_cost(1000, 256, 10)[1]
    with pytest.raises(ValueError):
        estimate_sampling_cost(-1, 256, 1)


def test_estimate_is_within_a_factor_of_the_measured_time():
    scene, cell = _rooms(20000)
    sample_pvs(scene, cell, n_points=1, resolution=64, seed=0)
    gt = sample_pvs(scene, cell, n_points=16, resolution=256, seed=0)
    seconds, _ = estimate_sampling_cost(scene.n_triangles, 256, 16)
    assert gt.seconds / 10 < seconds < gt.seconds * 10


def test_sampled_pvs_same_with_the_scene_hierarchy(monkeypatch):
    """The sampled PVS through culling (once the scene's hierarchy is built) equals the one
    drawing every face, id for id."""
    from visibility.generators import make_scene
    from visibility.raster import hierarchy
    from visibility.raster.hierarchy import peek, scene_hierarchy
    from visibility.scene import Scene
    from visibility.viewcells import ViewcellGrid

    scene = make_scene("city", 80_000, seed=3)
    grid = ViewcellGrid.for_scene(scene, 4.0)
    # The same arrays in a scene object that never gets a hierarchy: every face drawn.
    bare = Scene(scene.vertices, scene.faces, scene.object_ids, scene.colors)
    monkeypatch.setattr(hierarchy, "MIN_TRIANGLES", 1 << 62)
    scene_hierarchy(scene)
    for cell in (len(grid) // 2, len(grid) // 3):
        a = sample_pvs(scene, grid.cell(cell), n_points=8, resolution=96, seed=cell)
        b = sample_pvs(bare, grid.cell(cell), n_points=8, resolution=96, seed=cell)
        assert len(a.triangle_ids) > 0
        assert np.array_equal(a.triangle_ids, b.triangle_ids)
    assert peek(bare, hierarchy.KIND) is None


def test_mark_seen_marks_every_id_shown_and_skips_empty_samples():
    ids = np.array([[3, -1, 3], [0, 7, -1]], dtype=np.int32)
    seen = np.zeros(9, dtype=bool)
    gt_module.mark_seen(ids.reshape(-1), seen)
    assert np.flatnonzero(seen).tolist() == [0, 3, 7]
