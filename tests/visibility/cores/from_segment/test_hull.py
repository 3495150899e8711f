"""Scan conversion of the projected swept hull: conservative against the exact cover tests, and
tighter than the bounding box on slivers."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from tests.grouping import module_on_one_worker
from visibility.cores.from_segment.boxes import (
    _PERM,
    _SGN,
    FLAG_SLOW,
    TILE,
    _expanded_boxes,
    _tile_cols,
)
from visibility.cores.from_segment.dynamic import moving_cover, moving_setup
from visibility.cores.from_segment.geometry import scene_geometries
from visibility.cores.from_segment.groups import CubeFrame, GeometryArrays
from visibility.cores.from_segment.hull import HMAX, Hulls, hull_cols, hull_rows
from visibility.cores.from_segment.raster import _cam_corners, _row_spans
from visibility.cores.from_segment.segment import segment_visible
from visibility.cores.from_segment.static import static_cover, static_setup
from visibility.raster.camera import cube_face_rotations, random_rotation
from visibility.scene import Scene

pytestmark = module_on_one_worker("from_segment_hull")  # kernels of its own (tests/grouping.py)

RES = 24
PAD = 0.5
KNOTS = 4
#: Sample offsets tried per pixel, in pixels: a 5 x 5 grid over the jitter square.
_OFFS = np.array([(a, b) for a in np.linspace(-PAD, PAD, 5) for b in np.linspace(-PAD, PAD, 5)])


@njit(cache=False)
def _brute(kind, coef, res, near, slow, offs, knots, out):  # pragma: no cover - numba
    """out[i, j] = some sample offset of pixel (i, j) is accepted by the exact cover test."""
    step = 2.0 / res
    maxp = 8 * (knots + 2) + 8
    pt0 = np.empty(maxp)
    pt1 = np.empty(maxp)
    pz0 = np.empty(maxp)
    pz1 = np.empty(maxp)
    brk = np.empty(48)
    stk = np.empty((64, 4))
    for i in range(res):
        for j in range(res):
            out[i, j] = False
            for s in range(offs.shape[0]):
                x = (j + 0.5) * step - 1.0 + offs[s, 0] * step
                y = 1.0 - (i + 0.5) * step + offs[s, 1] * step
                if kind == 0:
                    ok = static_cover(coef, x, y, near, slow)[0]
                else:
                    ok = moving_cover(coef, x, y, near, slow, knots, pt0, pt1, pz0, pz1, brk,
                                      stk) > 0
                if ok:
                    out[i, j] = True
                    break


def _triangles(verts0, verts1, faces, moving) -> GeometryArrays:
    """The kernels' geometry group for triangles alone (no clusters, no spheres)."""
    return GeometryArrays(verts0, verts1, faces, moving, np.zeros(1, np.int64),
                          np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                          np.zeros(0), len(faces), np.zeros((0, 3)), np.zeros((0, 3)))


def _check_case(verts0, verts1, v0, v1, rb, near, tally):
    """Every pixel whose sample some exact cover test accepts lies in the triangle's box, its
    scan-converted row span and its binned tiles, on every face."""
    # int32 faces and indices as the core passes them: one specialization of each kernel.
    faces = np.array([[0, 1, 2]], dtype=np.int32)
    moving = np.array([not np.array_equal(verts0, verts1)])
    dvec = v1 - v0
    box = np.zeros((6, 4), np.int32)
    z = np.zeros(6)
    flag = np.zeros(6, np.uint8)
    hulls = Hulls(np.arange(6, dtype=np.int32), np.zeros((6, HMAX, 2), np.float32),
                  np.zeros(6, np.int8))
    _expanded_boxes(_triangles(verts0, verts1, faces, moving), np.zeros(6, np.int64),
                    np.arange(6), CubeFrame(v0, dvec, rb, _PERM, _SGN, RES, near, PAD), box, z,
                    flag, hulls)
    rots = cube_face_rotations(rb)
    P, U, W = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    coef = np.empty(40)
    acc = np.zeros((RES, RES), dtype=np.bool_)
    span = np.empty((TILE, 2), np.int64)
    ext = np.empty((TILE, 2))
    for f in range(6):
        R = np.ascontiguousarray(rots[f])
        dc = R @ dvec
        _cam_corners(R, verts0, verts1, faces, 0, v0, dc, P, U, W)
        if moving[0]:
            moving_setup(P, U, W, coef)
        else:
            static_setup(P, W, dc, coef)
        slow = bool(flag[f] & FLAG_SLOW) if flag[f] else True
        _brute(int(moving[0]), coef, RES, near, slow, _OFFS, KNOTS, acc)
        ii, jj = np.nonzero(acc)
        if flag[f] == 0:
            assert len(ii) == 0
            continue
        tally["slow"] += bool(flag[f] & FLAG_SLOW)
        tally["hulls"] += hulls.count[f] > 0
        tally["pixels"] += len(ii)
        b = box[f]
        assert np.all((ii >= b[0]) & (ii <= b[1]) & (jj >= b[2]) & (jj <= b[3]))
        for i, j in zip(ii, jj, strict=True):
            r0 = (i // TILE) * TILE
            _row_spans(hulls, np.int32(f), int(i), int(i), int(b[2]), int(b[3]), int(r0), PAD,
                       span, ext)
            assert span[i - r0, 0] <= j <= span[i - r0, 1], (f, i, j, span[i - r0])
            tx0, tx1 = _tile_cols(hulls, f, box, i // TILE, PAD)
            assert tx0 <= j // TILE <= tx1
        tally["span_px"] += sum(
            max(0, min(b[3], hull_cols(hulls.pts, f, int(hulls.count[f]), i, i, PAD)[1])
                - max(b[2], hull_cols(hulls.pts, f, int(hulls.count[f]), i, i, PAD)[0]) + 1)
            if hulls.count[f] else b[3] - b[2] + 1 for i in range(b[0], b[1] + 1))
        tally["box_px"] += (b[1] - b[0] + 1) * (b[3] - b[2] + 1)


def test_hull_cols_of_a_diagonal_band():
    # The segment from (0, 0) to (10, 10) (col, row): row 5 meets it at col 5, +-pad on each
    # axis gives columns 4..6 at pad 0.5 (a sample 0.5 below the row reaches col 5.5).
    pts = np.zeros((1, HMAX, 2), np.float32)
    pts[0, :2] = [(0.0, 0.0), (10.0, 10.0)]
    assert hull_cols(pts, 0, 2, 5, 5, 0.5) == (4, 6)
    assert hull_cols(pts, 0, 2, 5, 5, 0.0) == (5, 5)
    a, b = hull_cols(pts, 0, 2, 20, 20, 0.5)
    assert a > b


@pytest.mark.parametrize("seed", range(4))
def test_hull_rows_gives_each_rows_hull_cols(seed):
    # One pass over the edges for a tile's rows, the same columns as a call per row: slivers,
    # points, segments, horizontal edges, far and huge coordinates, every pad in use.
    rng = np.random.default_rng(seed)
    pts = np.zeros((1, HMAX, 2), np.float32)
    ext = np.empty((TILE, 2))
    for trial in range(400):
        m = int(rng.integers(1, HMAX + 1))
        scale = float(rng.choice([0.3, 3.0, 40.0, 1e6]))
        c = rng.normal(0.0, 1.0, (m, 2)) * scale + rng.uniform(-30, 30, 2)
        if trial % 7 == 0:
            c[:, 1] = np.round(c[:, 1])  # rows on integers: edges along the band lines
        if trial % 5 == 0:
            c[1:, 1] = c[0, 1]  # a horizontal sliver
        pts[0, :m] = c
        pad = float(rng.choice([0.0, 0.25, 0.5]))
        r0 = int(rng.integers(-24, 24)) * TILE
        ia = r0 + int(rng.integers(0, TILE))
        ib = min(r0 + TILE - 1, ia + int(rng.integers(0, TILE)))
        hull_rows(pts, np.int64(0), np.int64(m), ia, ib, pad, r0, ext)
        for i in range(ia, ib + 1):
            a, b = hull_cols(pts, 0, m, i, i, pad)
            if a > b:
                assert ext[i - r0, 0] > ext[i - r0, 1], (trial, i)
            else:
                assert (int(ext[i - r0, 0]), int(ext[i - r0, 1])) == (a, b), (trial, i)


def test_spans_hold_every_pixel_the_cover_tests_accept():
    rng = np.random.default_rng(30)
    tally = dict.fromkeys(("slow", "hulls", "pixels", "span_px", "box_px"), 0)
    for case in range(120):
        rb = random_rotation(rng)
        near = float(rng.choice([0.05, 0.3, 1.0]))
        v0 = rng.uniform(-1, 1, 3)
        v1 = v0 + rng.normal(size=3) * rng.choice([0.0, 0.5, 3.0])
        kind = case % 4
        if kind == 0:
            # Anywhere around the eye, often through the near plane.
            verts0 = v0 + rng.normal(size=(3, 3)) * rng.choice([0.5, 2.0, 6.0])
        elif kind == 1:
            # Edge-on: in a plane holding the whole segment (exactly or nearly).
            d = v1 - v0 if np.linalg.norm(v1 - v0) > 0 else rng.normal(size=3)
            e = rng.normal(size=3)
            nrm = np.cross(d, e)
            nrm /= np.linalg.norm(nrm)
            ab = rng.uniform(-3, 3, (3, 2))
            verts0 = (v0 + ab[:, :1] * d + ab[:, 1:] * e
                      + rng.choice([0.0, 1e-9, 1e-3]) * nrm)
        elif kind == 2:
            # A long thin sliver.
            a = v0 + rng.normal(size=3) * 4
            b = v0 + rng.normal(size=3) * 4
            verts0 = np.stack([a, b, b + rng.normal(size=3) * 0.02])
        else:
            verts0 = v0 + rng.normal(size=(3, 3)) * 2.0
        verts1 = verts0
        if case % 3 == 0:
            verts1 = verts0 + rng.normal(size=(3, 3)) * rng.choice([0.3, 2.0])
        _check_case(np.ascontiguousarray(verts0), np.ascontiguousarray(verts1), v0, v1, rb, near,
                    tally)
    # The cases did exercise what they are for.
    assert tally["slow"] >= 20
    assert tally["hulls"] >= 100
    assert tally["pixels"] >= 2000
    assert tally["span_px"] < tally["box_px"]


def test_sliver_visits_fewer_pixels_than_its_box():
    # A long thin diagonal triangle across the -z face, seen from a short segment.
    v = np.array([[-3.0, -3.0, -4.0], [3.0, 3.0, -4.0], [3.0, 3.05, -4.0]])
    f = np.arange(3, dtype=np.int32).reshape(1, 3)
    geom = scene_geometries(Scene(v, f))[0]
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.2, 0.0, 0.0])
    stats: dict = {}
    vis = segment_visible(geom, a, b, resolution=128, jitter=0.5, seed=3, stats=stats)
    assert vis[0]
    assert stats["triangle_prims"] >= 1
    # The box the raster used to scan in full, per face the triangle reaches.
    box = np.zeros((6, 4), np.int32)
    flag = np.zeros(6, np.uint8)
    hulls = Hulls(np.arange(6, dtype=np.int32), np.zeros((6, HMAX, 2), np.float32),
                  np.zeros(6, np.int8))
    _expanded_boxes(_triangles(v, v, f, np.zeros(1, bool)), np.zeros(6, np.int64), np.arange(6),
                    CubeFrame(a, b - a, np.eye(3), _PERM, _SGN, 128, 0.05, 0.5), box,
                    np.zeros(6), flag, hulls)
    box_pairs = sum(int((box[k, 1] - box[k, 0] + 1) * (box[k, 3] - box[k, 2] + 1))
                    for k in range(6) if flag[k])
    assert box_pairs > 5000
    assert stats["pairs"] < 0.1 * box_pairs
