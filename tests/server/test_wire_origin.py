"""Geometry frames of one scene share one origin (``server.catalog.wire_origin``), so a
vertex that two frames hold decodes to the same position in both: no cracks along shared edges
at chunk boundaries."""

from __future__ import annotations

import numpy as np

from protocol.frames import common_origin, decode_geometry, encode_geometry
from server.catalog import wire_origin
from visibility.scene import Scene


def test_a_shared_vertex_decodes_the_same_in_every_frame():
    # Two triangles sharing an edge, 1.5 km from the scene's centre, sent in different frames
    # whose own bounding boxes are far apart (as two chunks of a big city cell's PVS are).
    v = np.array([[1500.123456789, 20.1, -900.987654321], [1530.5, 20.1, -900.9],
                  [1500.123456789, 45.7, -900.987654321], [-1400.0, 0.0, 800.0],
                  [-1390.0, 0.0, 800.0], [-1400.0, 9.0, 810.0], [1530.5, 45.7, -900.9]])
    f = np.array([[0, 1, 2], [3, 4, 5], [1, 6, 2]])
    scene = Scene(v, f, name="far")
    origin = wire_origin(scene)
    assert wire_origin(scene) is origin  # computed once per scene
    np.testing.assert_array_equal(origin, np.round((v.min(0) + v.max(0)) / 2))
    cols = np.full((1, 3), 200, np.uint8)
    a = decode_geometry(encode_geometry(np.array([0]), v[f[[0]]], cols, origin=origin))
    # The second frame also holds a far-away triangle: its own bounding-box centre would differ.
    b = decode_geometry(encode_geometry(np.array([2, 1]), v[f[[2, 1]]],
                                        np.full((2, 3), 200, np.uint8), origin=origin))
    pa = np.asarray(a.positions, dtype=np.float64) + a.origin
    pb = np.asarray(b.positions, dtype=np.float64) + b.origin
    # Vertices 1 and 2 are corners (1, 2) of triangle 0 and (0, 2) of triangle 2.
    np.testing.assert_array_equal(pa[0, 1], pb[0, 0])
    np.testing.assert_array_equal(pa[0, 2], pb[0, 2])
    # A scene's NaN vertices (kept for its invalid faces) do not spoil the origin.
    bad = Scene(np.vstack([v, [np.nan, 0, 0]]), f, name="nan")
    np.testing.assert_array_equal(wire_origin(bad), origin)
    # Without the shared origin the two frames round the shared vertex differently.
    c = decode_geometry(encode_geometry(np.array([2, 1]), v[f[[2, 1]]],
                                        np.full((2, 3), 200, np.uint8)))
    pc = np.asarray(c.positions, dtype=np.float64) + c.origin
    assert not np.array_equal(pa[0, 1], pc[0, 0]) or not np.array_equal(pa[0, 2], pc[0, 2])



def test_the_origin_by_blocks_is_common_origin():
    from server.catalog import _blockwise_origin

    rng = np.random.default_rng(3)
    v = rng.uniform(-800, 1200, (1000, 3)) + [4.5e5, 90.0, 5.2e6]
    v[rng.integers(0, 1000, 40), rng.integers(0, 3, 40)] = np.nan
    v[17] = [np.inf, 0.0, 0.0]
    for block in (1, 7, 1000, 1 << 18):
        np.testing.assert_array_equal(_blockwise_origin(v, block), common_origin(v))
    np.testing.assert_array_equal(_blockwise_origin(np.full((5, 3), np.nan), 2), np.zeros(3))
    np.testing.assert_array_equal(_blockwise_origin(np.zeros((0, 3))), np.zeros(3))
