"""Tile resolution: the work counters the core reports (chunks handed to threads one at a time:
``tests/visibility/test_shares.py``)."""

from __future__ import annotations

import numba
import numpy as np

from tests.grouping import module_on_one_worker
from visibility.cores.from_segment.geometry import scene_geometries
from visibility.cores.from_segment.raster import (
    C_PASSED,
    C_PRIMS_PASSED,
    COUNTERS,
    _box_behind,
    _cam_corners,
    _prim_behind,
    _ray_meets_box,
    _ray_meets_tri_box,
    _tri_hit,
    _world_ray,
)
from visibility.cores.from_segment.segment import segment_visible
from visibility.raster.camera import random_rotation
from visibility.scene import Scene

pytestmark = module_on_one_worker("from_segment_raster")  # kernels of its own (tests/grouping.py)


def _quads(depths):
    """Square quads (two triangles each) of side 2 m facing +z, centred on the axis at z = -d."""
    v, f = [], []
    for d in depths:
        b = len(v)
        v += [(-1.0, -1.0, -d), (1.0, -1.0, -d), (1.0, 1.0, -d), (-1.0, 1.0, -d)]
        f += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
    return Scene(np.array(v), np.array(f))


def _stats(scene, v0, v1):
    """(visible, stats) of one segment with every tile resolved: a witness array turns off
    the skipping of tiles whose primitives are all marked already, which depends on which
    thread marks first."""
    stats = {}
    geom = scene_geometries(scene)[0]
    vis = segment_visible(geom, v0, v1, resolution=32, stats=stats,
                          witness=np.zeros((geom.n_ids, 5)))
    assert stats["tiles_known"] == 0
    return vis, stats


def test_counters_of_a_lone_quad():
    # One quad seen from a fixed point: every cover test that passes inserts into an empty
    # envelope, and each of its pixels ends with one piece per triangle covering its sample.
    vis, st = _stats(_quads([3.0]), np.zeros(3), np.zeros(3))
    assert vis.all()
    assert st["pieces"] == st["inserts"] == st["final_pieces"] > 0
    assert st["insert_scan"] == st["insert_moved"] == 0
    # Each pair covers its sample (a piece: nothing is in front): the cluster's triangles
    # visit only the columns of their swept hulls, here the triangles themselves, not the
    # boxes that overlap along the diagonal.
    assert st["pairs"] == st["pieces"]
    assert st["pairs_behind"] == st["pairs_uncovered"] == 0
    # The quad is one cluster: all its pairs are a cluster's.
    assert st["cluster_pairs"] == st["pairs"]
    assert st["cluster_pairs_uncovered"] == st["pairs_uncovered"]
    # One cluster of two triangles, set up in each tile it reaches, unless the first closed
    # every pixel of the second's box at its own depth: then the second is passed by whole.
    assert st["setups"] + st["prims_passed"] == 2 * st["items_processed"] == 2 * st["tiles"]
    assert not set(COUNTERS) - set(st) - {"thread"}
    assert 0 < st["cycles_setup"] + st["cycles_raster"] + st["cycles_tile"] <= st["cycles"]
    assert st["cycles"] / numba.get_num_threads() <= st["cycles_busiest_thread"] <= st["cycles"]


def test_counters_of_a_hidden_quad_behind_a_near_one():
    # The far quad is hidden all along: the final envelopes are the near quad's. (Both are one
    # cluster, set up in its order, so the far quad may be inserted first and overwritten.)
    near_only = _stats(_quads([3.0]), np.zeros(3), np.array([0.2, 0.0, 0.0]))[1]
    vis, st = _stats(_quads([3.0, 6.0]), np.zeros(3), np.array([0.2, 0.0, 0.0]))
    assert vis.tolist() == [True, True, False, False]
    assert st["final_pieces"] == near_only["final_pieces"]
    assert st["inserts"] >= near_only["inserts"]
    assert st["insert_scan"] >= near_only["insert_scan"]
    assert st["pairs"] > near_only["pairs"]
    assert st["pairs"] == st["pieces"] + st["pairs_uncovered"] + st["pairs_behind"]


def test_footprint_box_test_keeps_rays_that_meet_a_flat_box():
    """The footprint rule skips a cluster whose box its ray cannot meet: a box flat on one
    axis (a cluster of one wall) must still be met where the ray crosses it, at any angle,
    and missed beside it or beyond the ray's depth."""
    lo = np.array([[-1.0, 0.0, -5.0]])
    hi = np.array([[1.0, 2.0, -5.0]])  # flat in z
    rng = np.random.default_rng(0)
    for _ in range(200):
        target = np.array([rng.uniform(-1, 1), rng.uniform(0, 2), -5.0])
        o = rng.uniform(-3, 3, 3) * np.array([1, 1, 0]) + np.array([0, 1, 0])
        d = target - o
        d /= -d[2]  # depth per unit along -z, as the kernels' rays
        assert _ray_meets_box(_world_ray(*o, *d), lo, hi, 0, 0.05, 10.0)
        assert not _ray_meets_box(_world_ray(*o, *d), lo, hi, 0, 0.05, 4.9)  # lies beyond
    beside = _world_ray(0.0, 1.0, 0.0, 0.5, 0.0, -1.0)  # at x 2.5 where the wall is met
    assert not _ray_meets_box(beside, lo, hi, 0, 0.05, 10.0)


def test_footprint_triangle_box_test_keeps_every_ray_that_meets_the_triangle():
    """Inside a cluster the footprint rule's rays skip a triangle whose box (over both of its
    positions) they miss before the exact test: wherever the exact test (``_tri_hit``, what
    the rule's blocking decides by) finds a hit, the box test must pass, for flat,
    axis-aligned and moving triangles, rays aimed at them at any time of the segment; and
    it must spare the exact test for most rays that miss."""
    rng = np.random.default_rng(1)
    near, far = 0.05, 1e3
    met = missed = rejected = 0
    for k in range(300):
        # Every third triangle lies in a plane of constant z (a box flat on one axis), every
        # other one moves.
        v0 = rng.uniform(-3, 3, (3, 3)) + np.array([0.0, 0.0, -8.0])
        if k % 3 == 0:
            v0[:, 2] = v0[0, 2]
        v1 = v0 + (rng.uniform(-1, 1, (3, 3)) if k % 2 else 0.0)
        faces = np.array([[0, 1, 2]])
        R = random_rotation(rng)
        eye0 = rng.uniform(-1, 1, 3)
        dvec = rng.uniform(-2, 2, 3)
        dc = R @ dvec
        P, U, W, tq = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((1, 3, 3))
        _cam_corners(R, v0, v1, faces, 0, eye0, dc, P, U, W)
        for j in range(40):
            t = rng.uniform(0, 1)
            o = eye0 + t * dvec
            if j % 2 == 0:
                # At a random point of the triangle at time t.
                a, b = rng.uniform(0, 1, 2)
                if a + b > 1:
                    a, b = 1 - a, 1 - b
                vt = v0 + t * (v1 - v0)
                target = vt[0] + a * (vt[1] - vt[0]) + b * (vt[2] - vt[0])
            else:
                target = o + rng.normal(size=3) * 5
            c = R @ (target - o)
            if not c[2] < -near:
                continue
            x, y = c[0] / -c[2], c[1] / -c[2]
            d = R.T @ np.array([x, y, -1.0])
            boxed = _ray_meets_tri_box(_world_ray(*o, *d), v0, v1, faces, 0, bool(k % 2),
                                       near, far)
            if _tri_hit(P, U, t, x, y, near, far, tq):
                met += 1
                assert boxed, (k, j)
            else:
                missed += 1
                rejected += not boxed
    assert met > 1000
    assert rejected > 0.5 * missed


def test_a_primitive_behind_every_pixel_of_its_box_is_passed_whole():
    """Before its set-up a primitive is passed by whole when its nearest depth lies at or
    beyond the occlusion bound of every pixel of its box in the tile (``_box_behind``): the
    verdict is numpy's over the same pixels, open pixels (bound inf) and pixels no new
    primitive reaches (bound -inf) included; ``_prim_behind`` clamps the box to the tile,
    counts the box's pixels as passed when it holds, and passes by nothing whose box misses
    the tile."""
    rng = np.random.default_rng(5)
    r0, cl0, tw, th = 32, 48, 16, 12  # a tile of 12 rows of 16 pixels, at row 32, column 48
    agree = behind = 0
    for k in range(400):
        bound = rng.uniform(1.0, 10.0, th * tw)
        bound[rng.random(th * tw) < (0.02 if k % 2 else 0.3)] = np.inf
        bound[rng.random(th * tw) < 0.05] = -np.inf
        ia, ja = r0 + rng.integers(0, th), cl0 + rng.integers(0, tw)
        ib = min(ia + rng.integers(0, 4), r0 + th - 1)
        jb = min(ja + rng.integers(0, 4), cl0 + tw - 1)
        z = rng.uniform(0.5, 12.0)
        want = bool(np.all(z >= bound.reshape(th, tw)[ia - r0:ib - r0 + 1, ja - cl0:jb - cl0 + 1]))
        assert _box_behind(bound, z, ia, ib, ja, jb, r0, cl0, tw) == want
        agree += 1
        behind += want
        work = np.zeros(len(COUNTERS), dtype=np.int64)
        box = np.array([[ia - 2, ib, ja, jb + 3]], dtype=np.int32)  # clamped to the tile
        got = _prim_behind(box, 0, z, r0, r0 + th, cl0, cl0 + tw, tw, bound, work)
        assert got == bool(np.all(z >= bound.reshape(th, tw)[
            max(ia - 2, r0) - r0:ib - r0 + 1, ja - cl0:min(jb + 3, cl0 + tw - 1) - cl0 + 1]))
        assert work[C_PASSED] == ((ib - max(ia - 2, r0) + 1)
                                  * (min(jb + 3, cl0 + tw - 1) - ja + 1) if got else 0)
        assert work[C_PRIMS_PASSED] == int(got)
    assert 50 < behind < agree - 50  # both verdicts drawn often
    outside = np.array([[0, 5, 0, 5]], dtype=np.int32)
    work = np.zeros(len(COUNTERS), dtype=np.int64)
    assert not _prim_behind(outside, 0, 1e9, r0, r0 + th, cl0, cl0 + tw, tw,
                            np.full(th * tw, -np.inf), work)
    assert work[C_PASSED] == work[C_PRIMS_PASSED] == 0
