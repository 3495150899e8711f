"""Cancellation of a running computation: kernels cannot be interrupted, so the code that calls
them (cores, the sampled ground truth) polls ``checkpoint()`` between chunks of bounded work; a
``CancelToken`` (a deadline and a cancel flag) set for the computation's context decides.

A kernel whose single call may run for seconds (a cos view in dense clutter) polls
``stop_flag()`` itself: a one-byte array the token sets on ``cancel()`` and, through a timer
started by ``running_under``, at its deadline; the kernel reads it with ``flag_set`` (an atomic
load: a plain read of an array the loop never writes is hoisted out of the loop by the
compiler and never seen to change). The kernel returns early and the caller's next
``checkpoint()`` raises, so a partial result is never used.

A token may also carry a ``hold``: called by ``checkpoint()`` before its checks, it lets a
scheduler pause a computation between chunks while more urgent work runs on the same CPUs (the
server holds a session core's refinement while a walker waits for its first answer)."""

from __future__ import annotations

import contextlib
import contextvars
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
from numba import types
from numba.extending import intrinsic


class ComputationCancelled(RuntimeError):
    """A computation stopped at a checkpoint: it was cancelled or its deadline passed."""


class CancelToken:
    """Cancellation and deadline of one computation, polled by ``checkpoint()``.

    Kernels cannot be interrupted, so cores call ``checkpoint()`` between chunks of bounded
    work (a batch of samples, a segment, a group of pixel tiles); a cancelled or late
    computation stops at the next one. ``deadline`` is a ``time.monotonic()`` instant.
    """

    def __init__(self, deadline: float | None = None, budget: float | None = None) -> None:
        self.deadline = deadline
        self.budget = budget
        self._cancelled = threading.Event()
        self.reason = ""
        #: 1 once cancelled (or late, see ``running_under``): what kernels poll.
        self.flag = np.zeros(1, dtype=np.uint8)
        #: Called with the token by ``checkpoint()`` in the computing thread before its checks
        #: (None: nothing); it may block, for a bounded time, and should end early once the
        #: token is cancelled.
        self.hold: Callable[[CancelToken], None] | None = None

    @classmethod
    def after(cls, seconds: float | None) -> CancelToken:
        """A token whose deadline is ``seconds`` from now (None: no deadline)."""
        if seconds is None:
            return cls()
        return cls(time.monotonic() + float(seconds), float(seconds))

    def cancel(self, reason: str = "cancelled") -> None:
        """Stop the computation at its next checkpoint."""
        if not self._cancelled.is_set():
            self.reason = reason
            self._cancelled.set()
            self.flag[0] = 1

    def expire(self) -> None:
        """Cancel for the deadline (its timer calls this when the deadline passes)."""
        self.cancel(f"deadline of {self.budget:g} s passed")

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    def check(self) -> None:
        """Raise ``ComputationCancelled`` when cancelled or past the deadline."""
        if self._cancelled.is_set():
            raise ComputationCancelled(self.reason)
        if self.deadline is not None and time.monotonic() > self.deadline:
            self.expire()
            raise ComputationCancelled(self.reason)


_TOKEN: contextvars.ContextVar[CancelToken | None] = contextvars.ContextVar("pvs_cancel_token",
                                                                            default=None)


def checkpoint() -> None:
    """Raise ``ComputationCancelled`` if the computation running in this context was cancelled
    or passed its deadline; a no-op outside ``Core.compute`` with a token. Cores call it
    between chunks of work. A token's ``hold`` runs first (a scheduler's pause)."""
    token = _TOKEN.get()
    if token is not None:
        if token.hold is not None:
            token.hold(token)
        token.check()


@contextlib.contextmanager
def running_under(token: CancelToken | None) -> Iterator[None]:
    """Make ``token`` the one ``checkpoint()`` polls in this context for the ``with`` block
    (None: nothing to poll), and check it once on entry."""
    reset = _TOKEN.set(token)
    timer = None
    if token is not None and token.deadline is not None and not token.cancelled:
        # Kernels poll the flag, not the clock: a timer sets it when the deadline passes.
        timer = threading.Timer(max(0.0, token.deadline - time.monotonic()), token.expire)
        timer.daemon = True
        timer.start()
    try:
        checkpoint()
        yield
    finally:
        if timer is not None:
            timer.cancel()
        _TOKEN.reset(reset)


#: The flag of computations without a token: never set.
_NEVER = np.zeros(1, dtype=np.uint8)


def stop_flag() -> np.ndarray:
    """(1,) uint8 array that becomes 1 when the computation running in this context is
    cancelled or passes its deadline (never, outside ``Core.compute`` with a token). Kernels
    read ``flag[0]`` between bounded steps and return early; the caller then calls
    ``checkpoint()``, which raises."""
    token = _TOKEN.get()
    return _NEVER if token is None else token.flag


@intrinsic
def flag_set(typingctx, flag):  # pragma: no cover - compiled
    """In a numba kernel: whether ``flag[0]`` (a (1,) uint8 array, ``stop_flag()``) is
    non-zero, read afresh on every call (a monotonic atomic load), so a loop sees another
    thread set it."""
    if not isinstance(flag, types.Array) or flag.dtype != types.uint8:
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        byte = builder.load_atomic(ary.data, "monotonic", 1)
        return builder.icmp_unsigned("!=", byte, byte.type(0))

    return types.boolean(flag), codegen
