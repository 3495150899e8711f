"""``visibility.shares``: every share runs once, at once, and errors wait for the others."""

from __future__ import annotations

import multiprocessing
import threading
import time

import numpy as np
import pytest
from numba import njit

from tests.grouping import module_on_one_worker
from visibility import shares
from visibility.shares import run_shares, take_next

pytestmark = module_on_one_worker("shares")  # kernels of its own (tests/grouping.py)


@njit(nogil=True)
def _fill(out, value, share, k):
    """Write ``value`` into every ``k``-th slot of ``out`` from ``share``."""
    for i in range(share, out.shape[0], k):
        out[i] = value


@njit(nogil=True)
def _take_all(n, nxt, out, share, k):
    """Count each item ``take_next`` hands this share."""
    while True:
        i = take_next(nxt)
        if i >= n:
            break
        out[i] += 1


def test_take_next_hands_out_each_item_once() -> None:
    out = np.zeros(50_000, dtype=np.int64)
    nxt = np.zeros(1, dtype=np.int64)
    run_shares(_take_all, 4, len(out), nxt, out)
    assert np.all(out == 1)
    # Each share stops after one look past the end.
    assert nxt[0] == len(out) + 4


def test_every_share_runs_once_with_its_index_and_count() -> None:
    calls: list[tuple[int, int]] = []
    lock = threading.Lock()

    def kernel(tag: str, share: int, k: int) -> None:
        assert tag == "x"
        with lock:
            calls.append((share, k))

    run_shares(kernel, 5, "x")
    assert sorted(calls) == [(s, 5) for s in range(5)]
    calls.clear()
    run_shares(kernel, 1, "x")
    assert calls == [(0, 1)]


def test_a_nogil_kernel_fills_its_array_from_every_share() -> None:
    out = np.zeros(1001, dtype=np.int64)
    run_shares(_fill, 3, out, 7)
    assert (out == 7).all()


def test_shares_run_at_once() -> None:
    # Each share waits for all the others: run one after another, they would never meet.
    k = 4
    barrier = threading.Barrier(k, timeout=30)
    run_shares(lambda share, n: barrier.wait(), k)


def test_an_error_is_raised_after_every_share_has_returned() -> None:
    done: list[int] = []

    def kernel(share: int, k: int) -> None:
        if share == 0:
            raise ValueError("share 0 failed")
        time.sleep(0.2)
        done.append(share)

    with pytest.raises(ValueError, match="share 0 failed"):
        run_shares(kernel, 3)
    assert sorted(done) == [1, 2]

    def late(share: int, k: int) -> None:
        if share == 2:
            raise RuntimeError("share 2 failed")

    with pytest.raises(RuntimeError, match="share 2 failed"):
        run_shares(late, 3)


def _child(queue: multiprocessing.Queue) -> None:
    out = np.zeros(10, dtype=np.int64)
    run_shares(_fill, 2, out, 3)
    queue.put(int(out.sum()))


def test_a_forked_child_gets_threads_of_its_own() -> None:
    run_shares(_fill, 2, np.zeros(4, dtype=np.int64), 1)  # the parent's pool exists
    assert shares._jobs is not None
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child, args=(queue,))
    child.start()
    try:
        # Without threads of its own the child's shares would wait for ever.
        assert queue.get(timeout=60) == 30
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
    assert child.exitcode == 0
