"""A computation that runs once, on whichever thread claims it first.

A view's gather from v* (P4: the renders and the footprint tests against them) does not depend
on its layers, so a worker with no view left can make it while the view that needs it still
rasterizes (the one looking into a dense room holds most of a cell's work). Whoever asks first
computes; a later caller waits only for a computation already running on another thread, never
for one still queued, so views and gather tasks sharing a pool of workers cannot deadlock.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class Once(Generic[T]):
    """``fn()`` computed once (see the module docstring)."""

    def __init__(self, fn: Callable[[], T]) -> None:
        self._fn = fn
        self._lock = threading.Lock()
        self._claimed = False
        self._done = threading.Event()
        self._value: T | None = None
        self._error: BaseException | None = None

    def run(self) -> bool:
        """Compute here unless some thread has claimed it; True when this call computed it.
        An exception is kept for ``get`` and raised here too."""
        with self._lock:
            if self._claimed:
                return False
            self._claimed = True
        try:
            self._value = self._fn()
        except BaseException as exc:
            self._error = exc
            raise
        finally:
            self._fn = None  # type: ignore[assignment]  # its arguments are not kept alive
            self._done.set()
        return True

    def close(self) -> None:
        """Never compute from now on: claim it unclaimed (``get`` then raises), or wait for
        the thread computing it. What ``fn`` reads may then be released."""
        with self._lock:
            if not self._claimed:
                self._claimed = True
                self._error = RuntimeError("closed before it was computed")
                self._fn = None  # type: ignore[assignment]
                self._done.set()
                return
        self._done.wait()

    def get(self) -> T:
        """The value, computed here if no thread has started it, else waited for."""
        self.run()
        self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]


__all__ = ["Once"]
