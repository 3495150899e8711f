"""Frames of one set of triangles share one origin (``protocol.frames.common_origin``)."""

from __future__ import annotations

import numpy as np

from protocol.frames import chunk_geometry, common_origin, decode_geometry


def test_chunked_frames_of_one_set_share_its_origin():
    # The HTTP geometry answer splits a PVS into frames: they carry one origin, the set's.
    rng = np.random.default_rng(3)
    tris = rng.uniform(-2000, 2000, (300, 3, 3))
    cols = np.zeros((300, 3), np.uint8)
    frames = [decode_geometry(f) for f in chunk_geometry(np.arange(300), tris, cols,
                                                         max_frame_bytes=2048)]
    assert len(frames) > 1
    for f in frames:
        np.testing.assert_array_equal(f.origin, common_origin(tris.reshape(-1, 3)))
