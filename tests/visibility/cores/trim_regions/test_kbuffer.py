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
