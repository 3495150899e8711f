"""Cancellation of a running computation: kernels cannot be interrupted, so the code that calls
them (cores, the sampled ground truth) polls ``checkpoint()`` between chunks of bounded work; a
``CancelToken`` (a deadline and a cancel flag) set for the computation's context decides."""

from __future__ import annotations

import contextlib
import contextvars
import threading
import time
from collections.abc import Iterator


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

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    def check(self) -> None:
        """Raise ``ComputationCancelled`` when cancelled or past the deadline."""
        if self._cancelled.is_set():
            raise ComputationCancelled(self.reason)
        if self.deadline is not None and time.monotonic() > self.deadline:
            self.cancel(f"deadline of {self.budget:g} s passed")
            raise ComputationCancelled(self.reason)


_TOKEN: contextvars.ContextVar[CancelToken | None] = contextvars.ContextVar("pvs_cancel_token",
                                                                            default=None)


def checkpoint() -> None:
    """Raise ``ComputationCancelled`` if the computation running in this context was cancelled
    or passed its deadline; a no-op outside ``Core.compute`` with a token. Cores call it
    between chunks of work."""
    token = _TOKEN.get()
    if token is not None:
        token.check()


@contextlib.contextmanager
def running_under(token: CancelToken | None) -> Iterator[None]:
    """Make ``token`` the one ``checkpoint()`` polls in this context for the ``with`` block
    (None: nothing to poll), and check it once on entry."""
    reset = _TOKEN.set(token)
    try:
        checkpoint()
        yield
    finally:
        _TOKEN.reset(reset)
