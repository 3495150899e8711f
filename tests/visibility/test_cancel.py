"""``visibility.cancel``: tokens, checkpoints and the stop flag kernels poll."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from numba import njit

from tests.conftest import wait_for
from tests.grouping import module_on_one_worker
from visibility.cancel import (
    CancelToken,
    ComputationCancelled,
    checkpoint,
    flag_set,
    running_under,
    stop_flag,
)

pytestmark = module_on_one_worker("cancel_kernels")  # kernels of its own (tests/grouping.py)


@njit(nogil=True, cache=True)
def _spin(flag, limit, count):  # pragma: no cover - numba
    """Count up to ``limit`` unless the flag is set first, the count so far in ``count[0]``;
    returns the count."""
    n = 0
    while n < limit:
        if flag_set(flag):
            break
        n += 1
        count[0] = n
    return n


def test_a_kernel_sees_the_flag_set_by_another_thread():
    flag = np.zeros(1, dtype=np.uint8)
    count = np.zeros(1, dtype=np.int64)
    _spin(flag, 10, count)
    count[0] = 0
    out = []
    th = threading.Thread(target=lambda: out.append(_spin(flag, 1 << 62, count)))
    th.start()
    try:
        # Set before the kernel loops, the flag would stop it at 0 and prove nothing.
        wait_for(lambda: count[0] > 0, 30, "the kernel counting")
    finally:
        flag[0] = 1  # a failed wait must not leave the thread spinning
    th.join(timeout=30)
    # A plain read of flag[0] is hoisted out of the loop and the kernel would spin for ever.
    assert not th.is_alive(), "the kernel never saw the flag"
    assert 0 < out[0] < 1 << 62


def test_the_flag_follows_cancel_and_the_deadline():
    assert not stop_flag()[0]  # outside a computation: never set
    token = CancelToken()
    with running_under(token):
        assert stop_flag() is token.flag
        token.cancel("enough")
        assert token.flag[0] == 1
        with pytest.raises(ComputationCancelled, match="enough"):
            checkpoint()
    late = CancelToken.after(0.05)
    with running_under(late):
        wait_for(lambda: late.flag[0] == 1, 30, "the deadline's timer setting the flag")
        # No checkpoint ran: the deadline's timer set the flag for the kernels.
        assert late.flag[0] == 1 and late.cancelled
        assert "deadline" in late.reason


def test_the_timer_is_gone_after_the_computation():
    token = CancelToken.after(0.2)
    with running_under(token):
        pass
    time.sleep(0.4)
    assert not token.cancelled and token.flag[0] == 0


def test_a_hold_runs_at_each_checkpoint_before_the_checks():
    token = CancelToken()
    seen = []

    def hold(held: CancelToken):
        seen.append((threading.get_ident(), held is token, token.cancelled))
        token.cancel("cancelled while held")

    token.hold = hold
    with pytest.raises(ComputationCancelled, match="cancelled while held"):
        with running_under(token):  # its first checkpoint runs the hold, then raises
            pass
    # In the computing thread, before the cancel check: what the hold did is seen at once.
    assert seen == [(threading.get_ident(), True, False)]
    checkpoint()  # outside the computation: no token, no hold
    assert len(seen) == 1
