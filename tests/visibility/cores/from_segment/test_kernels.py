"""Kernel-level tests of continuous from-segment visibility: numerics, envelopes, exactness."""

from __future__ import annotations

import numpy as np
import pytest

from tests.grouping import module_on_one_worker
from tests.visibility.segment_reference import jittered_visible, sampled_visible, unwitnessed
from visibility.cores.from_segment.dynamic import cubic_roots01, quadratic_roots
from visibility.cores.from_segment.envelope import envelope_insert, pixel_bound
from visibility.cores.from_segment.geometry import scene_geometries
from visibility.cores.from_segment.raster import sample_offset
from visibility.cores.from_segment.segment import segment_visible
from visibility.raster import render_cubemap
from visibility.raster.camera import random_rotation
from visibility.scene import Scene

pytestmark = module_on_one_worker("from_segment_kernels")  # kernels of its own (tests/grouping.py)


# ----------------------------------------------------------------------------- root solvers
def test_quadratic_roots_without_cancellation():
    # x^2 + 1e8 x + 1 = 0: the small root is -1e-8 to full precision (naive formula: 0 or junk).
    n, r0, r1 = quadratic_roots(1.0, 1e8, 1.0)
    assert n == 2
    assert r1 == pytest.approx(-1e-8, rel=1e-12)
    assert r0 == pytest.approx(-1e8, rel=1e-12)


def test_quadratic_roots_degenerate_leading_coefficient():
    assert quadratic_roots(0.0, 2.0, -1.0)[:2] == (1, 0.5)
    # Vanishing a: the finite root is the linear one; the other escapes far from [0, 1].
    n, r0, r1 = quadratic_roots(1e-300, 2.0, -1.0)
    assert n == 2 and 0.5 in (r0, r1)
    assert quadratic_roots(0.0, 0.0, 1.0)[0] == 0
    assert quadratic_roots(1.0, 0.0, 1.0)[0] == 0
    assert quadratic_roots(np.nan, 1.0, 1.0)[0] == 0
    assert quadratic_roots(np.inf, 1.0, 1.0)[0] == 0
    # Huge coefficients do not overflow b^2.
    n, r0, r1 = quadratic_roots(1e200, -3e200, 2e200)
    assert n == 2 and (r0, r1) == (pytest.approx(1.0), pytest.approx(2.0))


def test_cubic_roots_in_unit_interval():
    out = np.zeros(3)
    # (t - 0.2)(t - 0.5)(t - 0.9)
    c = np.polynomial.polynomial.polyfromroots([0.2, 0.5, 0.9])
    n = cubic_roots01(c[0], c[1], c[2], c[3], out)
    assert n == 3
    np.testing.assert_allclose(out[:3], [0.2, 0.5, 0.9], atol=1e-14)
    c = np.polynomial.polynomial.polyfromroots([-1.0, 0.3, 2.0])
    assert cubic_roots01(c[0], c[1], c[2], c[3], out) == 1
    assert out[0] == pytest.approx(0.3, abs=1e-14)
    assert cubic_roots01(1.0, 0.0, 0.0, 0.0, out) == 0


# ----------------------------------------------------------------------------- envelopes
def _env(cap=8):
    return (np.zeros((1, cap, 4)), np.zeros((1, cap), dtype=np.int32),
            np.zeros((2 * cap + 8, 4)), np.zeros(2 * cap + 8, dtype=np.int32))


def _pieces(env, eid, n):
    return [(round(env[0, k, 0], 9), round(env[0, k, 1], 9), int(eid[0, k])) for k in range(n)]


def _ins(env, eid, n, a, b, za, zb, pid, T, tid):
    """envelope_insert on pixel 0 of a pixel without a bound: (count, changed)."""
    n, changed, _ = envelope_insert(env, eid, 0, n, a, b, za, zb, pid, T, tid, np.inf)
    return n, changed


def test_envelope_keeps_the_nearer_surface_and_splits_at_the_hinge():
    env, eid, T, tid = _env()
    n, changed = _ins(env, eid, 0, 0.0, 1.0, 5.0, 5.0, 1, T, tid)
    assert (n, changed) == (1, True)
    # A surface crossing the first at t = 0.5 (depth 4 -> 6): nearer on [0, 0.5].
    n, changed = _ins(env, eid, n, 0.0, 1.0, 4.0, 6.0, 2, T, tid)
    assert changed and _pieces(env, eid, n) == [(0.0, 0.5, 2), (0.5, 1.0, 1)]
    # Entirely behind: nothing changes.
    n2, changed = _ins(env, eid, n, 0.2, 0.9, 7.0, 8.0, 3, T, tid)
    assert not changed and n2 == n
    # An exact tie keeps the existing piece.
    n2, changed = _ins(env, eid, n, 0.6, 0.8, 5.0, 5.0, 4, T, tid)
    assert not changed
    # A short nearer piece in the middle splits the far one in three.
    n, changed = _ins(env, eid, n, 0.6, 0.7, 1.0, 1.0, 5, T, tid)
    assert _pieces(env, eid, n) == [(0.0, 0.5, 2), (0.5, 0.6, 1), (0.6, 0.7, 5), (0.7, 1.0, 1)]
    assert pixel_bound(env, 0, n) == pytest.approx(5.0)


def test_envelope_fills_gaps_and_reports_overflow():
    env, eid, T, tid = _env(cap=3)
    n, _ = _ins(env, eid, 0, 0.0, 0.2, 1.0, 1.0, 1, T, tid)
    n, _ = _ins(env, eid, n, 0.5, 0.7, 1.0, 1.0, 2, T, tid)
    assert pixel_bound(env, 0, n) == np.inf  # gaps: not covered
    n, _ = _ins(env, eid, n, 0.0, 1.0, 9.0, 9.0, 3, T, tid)
    assert n == -1  # five pieces do not fit three
    env, eid, T, tid = _env(cap=8)
    n, _ = _ins(env, eid, 0, 0.0, 0.2, 1.0, 1.0, 1, T, tid)
    n, _ = _ins(env, eid, n, 0.5, 0.7, 1.0, 1.0, 2, T, tid)
    n, _ = _ins(env, eid, n, 0.0, 1.0, 9.0, 9.0, 3, T, tid)
    assert _pieces(env, eid, n) == [(0.0, 0.2, 1), (0.2, 0.5, 3), (0.5, 0.7, 2), (0.7, 1.0, 3)]
    assert pixel_bound(env, 0, n) == pytest.approx(9.0)
    # Zero-length chords change nothing.
    assert _ins(env, eid, n, 0.3, 0.3, 0.1, 0.1, 7, T, tid) == (n, False)


@pytest.mark.parametrize("seed", range(4))
def test_envelope_is_the_lower_envelope_and_its_bound_is_kept_lazily(seed):
    """Random chords: the envelope is the pointwise nearest chord at every t, and the bound the
    raster keeps (read again only when ``envelope_insert`` says it may have changed) is always
    what a full ``pixel_bound`` reads."""
    rng = np.random.default_rng(seed)
    env, eid, T, tid = _env(cap=1024)
    n, bound, chords = 0, np.inf, []
    for pid in range(300):
        a, b = np.sort(rng.random(2))
        if pid % 7 == 0:
            a, b = 0.0, 1.0  # whole-segment chords close the pixel early
        za, zb = rng.uniform(1.0, 10.0, 2)
        n2, changed, rebound = envelope_insert(env, eid, 0, n, a, b, za, zb, pid, T, tid, bound)
        assert n2 >= 0
        if changed and rebound:
            bound = pixel_bound(env, 0, n2)
        n = n2
        chords.append((a, b, za, zb))
        assert bound == pixel_bound(env, 0, n)
    rows = env[0, :n]
    assert np.all(rows[1:, 0] >= rows[:-1, 1])  # sorted, disjoint
    ts = rng.random(2000)
    for t in ts:
        near = min((za + (zb - za) * (t - a) / (b - a) for a, b, za, zb in chords
                    if a <= t <= b and b > a), default=np.inf)
        k = np.searchsorted(rows[:, 1], t)
        if k < n and rows[k, 0] <= t:
            z = rows[k, 2] + rows[k, 3] * (t - rows[k, 0])
            assert z == pytest.approx(near, rel=1e-9, abs=1e-9)
        else:
            assert near == np.inf


# ----------------------------------------------------------------------------- exactness
def _soup(n, seed, spread=0.6, lo=2.0, hi=9.0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    c = d * rng.uniform(lo, hi, (n, 1))
    v = (c[:, None, :] + rng.normal(0, spread, (n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n).reshape(-1, 3)


# ----------------------------------------------------------------------------- jittered samples
def test_sample_offsets_are_fixed_bounded_and_decorrelated():
    res = 64
    offs = np.array([[sample_offset(f, i, j, res, 0.5, 3) for j in range(res)]
                     for f in (0, 5) for i in range(res)])  # (2 res, res, 2)
    assert np.all(np.abs(offs) <= 0.5)
    # Uniform over the pixel: mean about 0, mean |offset| about 1/4, neighbours unrelated.
    assert abs(offs.mean()) < 0.02
    assert abs(np.abs(offs).mean() - 0.25) < 0.02
    dx = offs[..., 0]
    assert abs(np.corrcoef(dx[:, :-1].ravel(), dx[:, 1:].ravel())[0, 1]) < 0.05
    assert abs(np.corrcoef(dx[:-1].ravel(), dx[1:].ravel())[0, 1]) < 0.05
    assert sample_offset(2, 7, 9, res, 0.5, 3) == sample_offset(2, 7, 9, res, 0.5, 3)
    assert sample_offset(2, 7, 9, res, 0.5, 3) != sample_offset(2, 7, 9, res, 0.5, 4)
    assert sample_offset(2, 7, 9, res, 0.0, 3) == (0.0, 0.0)
    dx2, dy2 = sample_offset(2, 7, 9, res, 0.25, 3)
    assert np.allclose((2 * dx2, 2 * dy2), sample_offset(2, 7, 9, res, 0.5, 3))


def test_jittered_samples_are_exact_both_ways():
    """With jitter, exactness holds at the jittered samples: a brute-force ray cast through
    every sample at 120 points of the segment finds nothing the kernel missed, and every
    reported triangle is confirmed at its witness sample. Pixel boxes are widened by the
    jitter, so a triangle whose box holds no pixel centre but reaches a sample is still found."""
    v, f = _soup(250, seed=21, spread=0.3)
    scene = Scene(v, f)
    a, b = np.array([-0.6, 0.2, 0.1]), np.array([0.8, -0.3, 0.5])
    rot = random_rotation(np.random.default_rng(2))
    res, seed = 20, 11
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, rot, resolution=res, witness=wit, jitter=0.5, seed=seed)
    ref = jittered_visible(v, f, a, b, res, 120, 0.5, seed, base_rotation=rot)
    assert ref.sum() > 50
    assert not np.any(ref & ~vis), np.flatnonzero(ref & ~vis)
    assert unwitnessed(wit, vis, v, v, f, a, b, res, rot, jitter=0.5, seed=seed) == []
    # The jittered samples see something the pixel centres never do, and the other way round.
    centres = segment_visible(geom, a, b, rot, resolution=res)
    assert np.any(vis & ~centres) and np.any(centres & ~vis)


def test_jitter_finds_a_band_sliding_between_two_rows_of_pixel_centres():
    """A strip 0.2 px high lies between the centre rows 15 and 16 of the axis-aligned -Z face
    (tangents +-1/32 at 32 px) and slides along itself as the eye walks x: pixel centres never
    meet it anywhere on the segment, jittered samples do."""
    d, h = 8.0, 0.2 * (2.0 / 32) * 8.0  # 0.2 px at 8 m
    y0 = 1.7 + 0.4 * h
    tri = np.array([[(-4, y0, -d), (4, y0, -d), (4, y0 + h, -d)],
                    [(-4, y0, -d), (4, y0 + h, -d), (-4, y0 + h, -d)]], dtype=np.float64)
    scene = Scene(tri.reshape(-1, 3), np.arange(6).reshape(2, 3))
    geom = scene_geometries(scene)[0]
    a, b = np.array([-1.0, 1.7, 0.0]), np.array([1.0, 1.7, 0.0])
    assert not segment_visible(geom, a, b, resolution=32).any()
    found = np.zeros(2, dtype=bool)
    for seed in range(4):
        wit = np.zeros((geom.n_ids, 5))
        vis = segment_visible(geom, a, b, resolution=32, jitter=0.5, seed=seed, witness=wit)
        assert vis.any(), seed  # the strip is seen; each half of it in most patterns
        v, f = scene.vertices, scene.faces
        assert unwitnessed(wit, vis, v, v, f, a, b, 32, jitter=0.5, seed=seed) == []
        found |= vis
    assert found.all()


def test_jittered_spheres_are_confirmed_at_their_samples():
    rng = np.random.default_rng(31)
    c = rng.normal(size=(40, 3))
    c = c / np.linalg.norm(c, axis=1)[:, None] * rng.uniform(2.0, 9.0, (40, 1))
    r = rng.uniform(0.02, 0.3, 40)
    v, f = _soup(100, seed=32)
    scene = Scene(v, f, sphere_centers=c, sphere_radii=r)
    a, b = np.array([-0.5, 0.1, 0.0]), np.array([0.7, 0.0, 0.4])
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, resolution=24, witness=wit, jitter=0.5, seed=5)
    assert vis[100:].sum() > 5
    bad = unwitnessed(wit, vis, v, v, f, a, b, 24, centers0=c, centers1=c, radii=r,
                      jitter=0.5, seed=5)
    assert len(bad) <= 0.01 * np.count_nonzero(vis), bad


def test_a_segment_cut_into_pieces_sees_what_the_whole_sees(monkeypatch):
    """Pieces (``segment._piece``): forced to cut every piece (up to 2^6 of them), the segment's
    visible set is the same as solved whole, every witness time is a time of the whole segment
    confirmed by a brute-force ray cast, and ``stats["splits"]`` counts the cuts."""
    from visibility.cores.from_segment import segment

    v, f = _soup(500, seed=41, lo=0.5, hi=4.0)
    scene = Scene(v, f)
    a, b = np.array([-0.9, 0.1, 0.3]), np.array([1.1, -0.3, 0.2])
    geom = scene_geometries(scene)[0]
    whole = segment_visible(geom, a, b, resolution=24, jitter=0.5, seed=2)
    monkeypatch.setattr(segment, "SPLIT_AREA", 0)
    stats = {}
    assert np.array_equal(whole, segment_visible(geom, a, b, resolution=24, jitter=0.5, seed=2,
                                                 max_cuts=0, stats=stats))
    assert "splits" not in stats
    wit = np.zeros((geom.n_ids, 5))
    cut = segment_visible(geom, a, b, resolution=24, jitter=0.5, seed=2, witness=wit,
                          stats=stats, max_cuts=3)
    assert stats["splits"] == 1 + 2 + 4
    assert np.array_equal(whole, cut)
    assert unwitnessed(wit, cut, v, v, f, a, b, 24, jitter=0.5, seed=2) == []
    times = wit[cut, 1]
    assert times.min() < 0.125 and times.max() > 0.875  # spread over the whole segment


def test_pieces_far_over_the_limit_are_cut_without_measuring_them(monkeypatch):
    """A piece whose parent's boxes added up to more than four times the limit is cut with no
    area pass of its own (a half keeps about a quarter of the area); one nearer the limit is
    measured. The pieces and the answer are the same either way."""
    from visibility.cores.from_segment import segment

    v, f = _soup(300, seed=43, lo=0.5, hi=4.0)
    geom = scene_geometries(Scene(v, f))[0]
    a, b = np.array([-0.9, 0.1, 0.3]), np.array([1.1, -0.3, 0.2])
    collect = segment._collect_prims
    calls = []

    def counted(*args, area_only=False, **kw):
        out = collect(*args, area_only=area_only, **kw)
        if area_only:
            calls.append(out)
        return out

    monkeypatch.setattr(segment, "_collect_prims", counted)
    whole = segment_visible(geom, a, b, resolution=24, max_cuts=0)
    cube = 6 * 24 * 24
    area = collect(geom, a, b - a, np.eye(3), segment.cube_face_rotations(np.eye(3)), 24,
                   segment.DEFAULT_NEAR, 0.0, segment.DEFAULT_BATCH, {}, area_only=True)
    for limit, measured in ((area / cube / 8, 1), (area / cube / 2, 3)):
        monkeypatch.setattr(segment, "SPLIT_AREA", limit)
        calls.clear()
        stats = {}
        cut = segment_visible(geom, a, b, resolution=24, max_cuts=2, stats=stats)
        assert len(calls) == measured and calls[0] == area
        halves = 2 if measured == 1 else sum(c > limit * cube for c in calls[1:])
        assert stats["splits"] == 1 + halves
        assert np.array_equal(whole, cut)


def test_moving_geometry_is_never_cut(monkeypatch):
    from visibility.cores.from_segment import segment

    v0, f = _soup(100, seed=42)
    scene = Scene(v0, f, states=np.stack([v0, v0 + 0.3]))
    monkeypatch.setattr(segment, "SPLIT_AREA", 0)
    stats = {}
    segment_visible(scene_geometries(scene)[0], np.zeros(3), np.ones(3), resolution=16,
                    stats=stats)
    assert "splits" not in stats


def _skip_scene(kind):
    v, f = _soup(400, seed=8, spread=0.3)
    if kind == "static":
        return Scene(v, f)
    rng = np.random.default_rng(9)
    c0 = rng.normal(size=(40, 3))
    c0 = c0 / np.linalg.norm(c0, axis=1)[:, None] * rng.uniform(2.0, 8.0, (40, 1))
    r = rng.uniform(0.1, 0.5, 40)
    if kind == "spheres":
        return Scene(v, f, sphere_centers=c0, sphere_radii=r)
    v1 = v + np.repeat(rng.normal(0, 0.3, (400, 1, 3)), 3, axis=1).reshape(-1, 3)
    return Scene(v, f, states=np.stack([v, v1]),
                 sphere_centers=np.stack([c0, c0 + rng.normal(0, 0.5, (40, 3))]), sphere_radii=r)


@pytest.mark.parametrize("kind", ["static", "spheres", "moving"])
def test_tiles_holding_only_marked_primitives_are_skipped_with_the_same_answer(kind):
    """Segments solved into one mask skip every tile whose primitives an earlier segment
    already marked (``tiles_known``); in tiles listing few unmarked ones, the pixels none of
    those reach (``pixels_known``) and the primitives beyond the farthest point any of them
    reaches along the segment (``items_behind_new``); the union is the one found with every
    pixel resolved (a witness array turns the skips off, since it records each primitive's
    samples). Static and moving triangles and spheres each bound that depth their own way."""
    geom = scene_geometries(_skip_scene(kind))[0]
    segs = [(np.array([-0.5, 0.0, 0.0]), np.array([0.5, 0.0, 0.0])),
            (np.array([0.5, 0.0, 0.0]), np.array([0.5, 0.0, 0.6])),
            (np.array([0.5, 0.0, 0.6]), np.array([-0.5, 0.1, 0.6]))]
    skipped, full = np.zeros(geom.n_ids, bool), np.zeros(geom.n_ids, bool)
    stats = {}
    for a, b in segs:
        segment_visible(geom, a, b, resolution=32, jitter=0.5, visible=skipped, stats=stats)
        segment_visible(geom, a, b, resolution=32, jitter=0.5, visible=full,
                        witness=np.zeros((geom.n_ids, 5)))
    # Whole tiles skipped, and pixels of tiles listing few primitives not yet marked.
    assert stats["tiles_known"] > 0 and stats["pixels_known"] > 0
    assert stats["items_behind_new"] > 0
    assert 50 < full.sum() < geom.n_ids
    np.testing.assert_array_equal(skipped, full)


def test_segment_equals_union_of_id_buffers_along_it():
    """Exactness at pixel centres, both ways: nothing the id buffers see along the segment is
    missed, and every triangle reported has a witness (a time and pixel centre where a
    brute-force ray cast confirms it is the nearest surface)."""
    v, f = _soup(700, seed=5)
    scene = Scene(v, f)
    a, b = np.array([-0.8, 0.3, 0.2]), np.array([1.0, -0.2, 0.6])
    res = 32
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, resolution=res, witness=wit)
    ref, _ = sampled_visible(v, v, f, a, b, res, 100)
    assert not np.any(ref & ~vis), np.flatnonzero(ref & ~vis)
    assert unwitnessed(wit, vis, v, v, f, a, b, res) == []
    # Sampling only catches up slowly: a fair share is seen only between 100 sample points.
    assert np.count_nonzero(vis & ~ref) > 0


def _fence(layers=3, slats=40, width=0.02, pitch=0.05):
    """Layers of thin vertical slats in front of a wall (-z of the origin): a pixel ray of an
    eye walking along x crosses slat after slat, so its envelope holds many pieces."""
    quads = []
    for k in range(layers):
        z = -1.0 - 0.3 * k
        for i in range(slats):
            x0 = -1.0 + i * pitch + 0.013 * k
            quads.append([(x0, -1, z), (x0 + width, -1, z), (x0 + width, 1, z), (x0, 1, z)])
    quads.append([(-5, -5, -3), (5, -5, -3), (5, 5, -3), (-5, 5, -3)])
    q = np.array(quads, dtype=float)
    v = q.reshape(-1, 3)
    base = 4 * np.arange(len(q))[:, None]
    f = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return v, f


def test_envelopes_that_outgrow_their_storage_are_grown_and_stay_exact():
    """A fence seen from an eye walking past it: envelopes outgrow the starting storage, the
    draw under way when one does resumes where it stopped in the grown storage, and the answer
    is still exact at the pixel centres both ways (nothing the id buffers see is missed, every
    reported triangle is confirmed by a ray cast at its witness)."""
    v, f = _fence()
    scene = Scene(v, f)
    a, b = np.array([-1.0, 0.1, 0.0]), np.array([1.0, -0.1, 0.0])
    res = 32
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    stats = {}
    vis = segment_visible(geom, a, b, resolution=res, witness=wit, stats=stats, max_cuts=0,
                          envelope_cap=2)
    assert stats["envelope_grows"] >= 3 and stats["max_cap"] >= 128
    # Room enough from the start: the same envelopes, piece for piece (with a witness, so
    # that no tile is skipped for what other threads' tiles marked first).
    roomy = {}
    assert np.array_equal(vis, segment_visible(geom, a, b, resolution=res, stats=roomy,
                                               witness=np.zeros((geom.n_ids, 5)), max_cuts=0,
                                               envelope_cap=1024))
    assert roomy["envelope_grows"] == 0
    assert stats["final_pieces"] == roomy["final_pieces"]
    ref, _ = sampled_visible(v, v, f, a, b, res, 200)
    assert ref.sum() > 100
    assert not np.any(ref & ~vis), np.flatnonzero(ref & ~vis)
    assert unwitnessed(wit, vis, v, v, f, a, b, res) == []


def test_rotated_cube_is_exact_too():
    v, f = _soup(300, seed=6)
    scene = Scene(v, f)
    rot = random_rotation(np.random.default_rng(2))
    a, b = np.array([0.0, 0.0, 0.0]), np.array([1.2, 0.4, -0.3])
    vis = segment_visible(scene_geometries(scene)[0], a, b, rot, resolution=24)
    ref, _ = sampled_visible(v, v, f, a, b, 24, 200, base_rotation=rot)
    assert not np.any(ref & ~vis)


def test_zero_length_segment_is_from_point_visibility():
    v, f = _soup(500, seed=7)
    eye = np.array([0.1, -0.2, 0.3])
    vis = segment_visible(scene_geometries(Scene(v, f))[0], eye, eye, resolution=40)
    _, ids = render_cubemap(v, f, eye, 40)
    u = np.unique(ids)
    ref = np.zeros(len(f), dtype=bool)
    ref[u[u >= 0]] = True
    np.testing.assert_array_equal(vis, ref)


def test_triangle_crossing_the_moving_near_plane():
    """The eye passes through a triangle (and has others behind it for part of the segment):
    handled per pixel like a near-clipping rasterizer, nothing visible is dropped."""
    tris = np.array([
        [[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]],   # the eye flies through it
        [[-0.3, -0.3, -1.5], [0.3, -0.3, -1.5], [0.0, 0.3, -1.5]],  # ahead, then behind
        [[-0.5, -0.5, 3.0], [0.5, -0.5, 3.0], [0.0, 0.5, 3.0]],    # behind, then ahead
        [[-4.0, -4.0, -6.0], [4.0, -4.0, -6.0], [0.0, 4.0, -6.0]],  # far wall
    ])
    v = tris.reshape(-1, 3)
    f = np.arange(12).reshape(-1, 3)
    a, b = np.array([0.05, 0.02, 1.0]), np.array([-0.04, 0.03, -2.0])
    vis = segment_visible(scene_geometries(Scene(v, f))[0], a, b, resolution=32)
    ref, _ = sampled_visible(v, v, f, a, b, 32, 300)
    assert not np.any(ref & ~vis)
    assert vis.all()


def test_pixel_centres_exactly_on_a_shared_edge_leave_no_crack():
    """A quad split along its diagonal whose projection passes exactly through pixel centres (at
    t = 0 and again as the eye moves), in front of a wall: shared edges are evaluated from their
    corners in one canonical order, so at every t a centre on the diagonal belongs to one of the
    two halves and the wall behind never shows through."""
    quad = np.array([[-10.0, -10.0, -2.0], [10.0, -10.0, -2.0], [10.0, 10.0, -2.0],
                     [-10.0, 10.0, -2.0]])
    wall = np.array([[-3.0, -3.0, -5.0], [3.0, -3.0, -5.0], [0.0, 3.0, -5.0]])
    v = np.concatenate([quad, wall])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    res = 32
    step = 2.0 / res
    # Moving by whole pixels (at depth 2) keeps the diagonal on pixel centres at many t.
    for a, b in [(np.zeros(3), np.array([8 * step * 2, 0.0, 0.0])),
                 (np.array([0.0, 0.0, 0.0]), np.array([0.0, -4 * step * 2, 0.0]))]:
        vis = segment_visible(scene_geometries(Scene(v, f))[0], a, b, resolution=res)
        assert vis[:2].all()
        assert not vis[2]
    # The reference rasterizer agrees at the end points (its fill rule has no crack either).
    _, ids = render_cubemap(v, f, np.zeros(3), res)
    assert 2 not in np.unique(ids)


def test_static_spheres_and_triangles_occlude_each_other():
    rng = np.random.default_rng(11)
    v, f = _soup(400, seed=12)
    c = rng.normal(size=(60, 3))
    c = c / np.linalg.norm(c, axis=1)[:, None] * rng.uniform(1.5, 8.0, (60, 1))
    r = rng.uniform(0.1, 0.7, 60)
    scene = Scene(v, f, sphere_centers=c, sphere_radii=r)
    a, b = np.array([-0.5, 0.1, 0.0]), np.array([0.7, 0.0, 0.4])
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, resolution=24, witness=wit)
    rt, rs = sampled_visible(v, v, f, a, b, 24, 60, centers0=c, centers1=c, radii=r)
    assert not np.any(rt & ~vis[:400])
    assert not np.any(rs & ~vis[400:])
    # Sphere depth is interpolated between knots: the witnesses hold up to that approximation.
    bad = unwitnessed(wit, vis, v, v, f, a, b, 24, centers0=c, centers1=c, radii=r)
    assert len(bad) <= 0.01 * np.count_nonzero(vis), bad
    assert not vis[400:].all()  # some spheres are hidden: occlusion works both ways


def test_moving_triangles_and_spheres():
    rng = np.random.default_rng(13)
    v0, f = _soup(300, seed=14, lo=2.5)
    v1 = v0 + np.repeat(rng.normal(0, 0.5, (300, 1, 3)), 3, axis=1).reshape(-1, 3)
    c0 = rng.normal(size=(30, 3))
    c0 = c0 / np.linalg.norm(c0, axis=1)[:, None] * rng.uniform(2.0, 8.0, (30, 1))
    c1 = c0 + rng.normal(0, 0.8, (30, 3))
    r = rng.uniform(0.1, 0.6, 30)
    scene = Scene(v0, f, states=np.stack([v0, v1]), sphere_centers=np.stack([c0, c1]),
                  sphere_radii=r)
    (geom,) = scene_geometries(scene)
    assert geom.moving.all()
    a, b = np.array([-0.4, 0.2, 0.1]), np.array([0.8, -0.1, 0.3])
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, resolution=24, witness=wit)
    rt, rs = sampled_visible(v0, v1, f, a, b, 24, 60, centers0=c0, centers1=c1, radii=r)
    assert not np.any(rt & ~vis[:300])
    assert not np.any(rs & ~vis[300:])
    bad = unwitnessed(wit, vis, v0, v1, f, a, b, 24, centers0=c0, centers1=c1, radii=r)
    assert len(bad) <= 0.01 * np.count_nonzero(vis), bad


def test_sphere_around_the_eye_is_seen_from_inside():
    c = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -10.0]])
    r = np.array([2.0, 1.0])
    scene = Scene(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), sphere_centers=c,
                  sphere_radii=r)
    vis = segment_visible(scene_geometries(scene)[0], np.array([0.0, 0.0, 0.5]),
                          np.array([0.0, 0.5, 0.0]), resolution=16)
    np.testing.assert_array_equal(vis, [True, False])  # the enclosing sphere hides the other


def test_bad_segment_inputs_raise():
    (geom,) = scene_geometries(Scene(*_soup(10, seed=1)))
    with pytest.raises(ValueError):
        segment_visible(geom, np.array([np.nan, 0, 0]), np.zeros(3))
    with pytest.raises(ValueError):
        segment_visible(geom, np.zeros(3), np.zeros(3), resolution=0)
    with pytest.raises(ValueError):
        segment_visible(geom, np.zeros(3), np.zeros(3), near=-1.0)
    with pytest.raises(ValueError, match="jitter"):
        segment_visible(geom, np.zeros(3), np.zeros(3), jitter=0.7)
    with pytest.raises(ValueError, match="seed"):
        segment_visible(geom, np.zeros(3), np.zeros(3), jitter=0.5, seed=-1)
    with pytest.raises(ValueError, match="max_cuts"):
        segment_visible(geom, np.zeros(3), np.zeros(3), max_cuts=-1)
    for cap in (0, 1 << 20):
        with pytest.raises(ValueError, match="envelope_cap"):
            segment_visible(geom, np.zeros(3), np.zeros(3), envelope_cap=cap)
