"""The cycle counter the cores' kernels time their steps with."""

from __future__ import annotations

from numba import njit

from visibility.cycles import cycles


@njit(cache=True)
def _timed(n):  # pragma: no cover - numba
    t0 = cycles()
    s = 0.0
    for i in range(n):
        s += i ** 0.5
    return cycles() - t0, s


def test_the_counter_runs_forward_and_grows_with_the_work():
    # The least of a few short runs: a busy machine may preempt one of them.
    short = min(_timed(10)[0] for _ in range(5))
    long, _ = _timed(10_000_000)
    assert short >= 0 and long > 0
    # Ten million square roots take far more cycles than ten.
    assert long > 100 * short
