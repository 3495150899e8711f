"""The k-buffers' band order (``kbuffer.band_stride``)."""

from __future__ import annotations

import numpy as np

from tests.grouping import module_on_one_worker
from visibility.cores.trim_regions.kbuffer import KBuffer, band_stride

pytestmark = module_on_one_worker("trim_kbuffer")  # kernels of its own (tests/grouping.py)


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


def test_a_merged_trims_piece_set_holds_its_pieces_and_few_others():
    from visibility.cores.trim_regions.kbuffer import (
        ANY_PIECE,
        PIECE_SET_BITS,
        joined_pieces,
        piece_bits,
        trim_holds,
    )

    assert joined_pieces(7, 7) == 7 and trim_holds(7, 7) and not trim_holds(7, 8)
    assert all(trim_holds(ANY_PIECE, q) for q in range(1000))
    assert all(piece_bits(q) > 0 for q in range(1000)) and piece_bits(-1) == 0
    gen = np.random.default_rng(0)
    false_holds = 0
    for _ in range(5000):
        # Neighbouring labels, as pieces met in one pixel often are.
        pieces = int(gen.integers(0, 100_000)) + np.arange(5) * int(gen.integers(1, 4))
        s = int(pieces[0])
        for q in pieces[1:4]:
            s = joined_pieces(s, int(q))
        assert s < 0 and all(trim_holds(s, int(q)) for q in pieces[:4])
        false_holds += trim_holds(s, int(pieces[4]))
    # A set of four holds a fifth piece no more often than a two-bit Bloom filter of
    # PIECE_SET_BITS bits would: (1 - exp(-8 / 62))^2 = 1.5 %.
    assert false_holds / 5000 < (1.0 - np.exp(-8.0 / PIECE_SET_BITS)) ** 2
