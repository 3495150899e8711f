"""Per-view buffers kept between computations (``warm``): reused while fresh, dropped when
their size no longer fits or once idle, and the answer the same either way."""

from __future__ import annotations

import time

import numpy as np

from visibility.cores.base import get_core
from visibility.cores.trim_regions.warm import WARM, WarmBuffers, WarmScratch
from visibility.generators import make_scene
from visibility.ground_truth import cell_around
from visibility.viewcells import Viewcell

CORE = get_core("trim_regions")


def test_pairs_given_back_are_taken_again_until_released():
    warm = WarmBuffers(keep_seconds=60.0, max_kept=2)
    first, reused = warm.take(64, 2)
    assert reused == 0 and len(first) == 2
    warm.give(first)
    again, reused = warm.take(64, 3)
    assert reused == 2 and again[0] is first[0] and again[1] is first[1]
    warm.give(again)
    assert warm.kept == 2  # at most max_kept
    other, reused = warm.take(256, 1)  # another view size: the kept ones go
    assert reused == 0 and warm.kept == 0 and len(other[0][0].count) == 256
    warm.give(other)
    warm.release()
    assert warm.kept == 0


def test_kept_pairs_are_released_once_idle():
    warm = WarmBuffers(keep_seconds=0.05)
    pairs, _ = warm.take(64, 1)
    warm.give(pairs)
    deadline = time.monotonic() + 30.0
    while warm.kept and time.monotonic() < deadline:
        time.sleep(0.02)
    assert warm.kept == 0


def test_a_computation_on_kept_buffers_gives_the_same_answer():
    scene = make_scene("village", triangles=20_000)
    params = CORE.make_params(resolution=128)
    WARM.release()
    answers = []
    for box in (cell_around(scene, 0.3, 0), cell_around(scene, 0.3, 1)):
        fresh = CORE.compute(scene, Viewcell(box), params)
        warm = CORE.compute(scene, Viewcell(box), params)
        assert fresh.stats["buffers_reused"] == 0 or answers
        assert warm.stats["buffers_reused"] == warm.stats["view_workers"]
        assert np.array_equal(np.sort(fresh.triangle_ids), np.sort(warm.triangle_ids))
        answers.append(warm.triangle_ids)
    WARM.release()
    assert CORE.compute(scene, Viewcell(box), params).stats["buffers_reused"] == 0


def test_gather_scratch_given_back_is_taken_again_until_released():
    pool = WarmScratch(keep_seconds=60.0, max_kept=1)
    a = pool.take()
    b = pool.take()
    assert a is not b
    pool.give(a)
    pool.give(b)  # over max_kept: the latest is kept
    assert pool.kept == 1 and pool.take() is b and pool.kept == 0
    pool.give(a)
    pool.release()
    assert pool.kept == 0 and pool.take() is not a


def test_kept_gather_scratch_is_released_once_idle():
    pool = WarmScratch(keep_seconds=0.05)
    pool.give(pool.take())
    deadline = time.monotonic() + 30.0
    while pool.kept and time.monotonic() < deadline:
        time.sleep(0.02)
    assert pool.kept == 0
