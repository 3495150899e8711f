"""The k-buffers' band order (``kbuffer.band_stride``)."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.kbuffer import KBuffer, band_stride


def test_band_stride_visits_every_band_once():
    for n in range(1, 300):
        s = band_stride(n)
        assert sorted((j * s) % n for j in range(n)) == list(range(n)), n


def test_each_thread_gets_a_share_of_every_part_of_the_frame():
    # Numba gives each of t threads one contiguous run of steps: each run must reach across
    # the frame, not one part of it, so work crowded in a few rows is shared.
    for n in (8, 16, 32, 64, 128, 512):
        s = band_stride(n)
        for t in (2, 3, 4):
            for run in np.array_split(np.arange(n), t):
                bands = (run * s) % n
                quarters = np.unique(bands * 4 // n)
                assert len(quarters) == 4 if len(run) >= 8 else len(quarters) >= 2, (n, t)


def test_band_count_of_a_buffer():
    kb = KBuffer.empty(256 * 256)
    assert len(kb.queued) == len(kb.held_entries) == 256 // 8 + 1


def test_entries_lie_in_blocks_and_read_back_in_slot_order():
    from visibility.cores.trim_regions.kbuffer import LANES, TRIM, K

    kb = KBuffer.empty(5)
    assert kb.depth.shape == (K // LANES, 5, LANES)
    for q in range(LANES + 3):
        kb.put(2, q, TRIM, 1.0 + q, -1, 10.0 + q, 1.5 + q)
    kb.count[2] = LANES + 3
    kind, depth, ident, umbra, far = kb.entries(2)
    assert np.array_equal(depth, 1.0 + np.arange(LANES + 3))
    assert np.array_equal(far, depth + 0.5) and np.array_equal(umbra, depth + 9.0)
    assert (kind == TRIM).all() and (ident == -1).all()
    # Entry LANES sits in the second block: the first block of its neighbours is untouched,
    # and a pixel holding fewer entries never reaches a later block.
    assert kb.depth[1, 2, 0] == 1.0 + LANES and not kb.depth[:, [1, 3]].any()
    assert not kb.depth[2:].any()
