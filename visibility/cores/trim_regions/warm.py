"""Per-view buffers kept warm between computations for a few seconds.

A view worker holds a k-buffer (``kbuffer.KBuffer``) and the set-up scratch of its views
(``visibility.scratch.Scratch``: a polygon, a box and a facing flag per static triangle, over
a hundred megabytes on a million-triangle scene). Fresh ones cost their first-touch page
faults at every computation: the kernel zeroes each page the views write, which on the 1M
kitchen took as much CPU as the surface rasterization. A server computing a walker's cells
runs computations back to back, so the buffers of one that ends are kept for the next, and
released once no computation has taken them for ``KEEP_SECONDS``: memory held while the
core is in use, given back when it is idle.
"""

from __future__ import annotations

import threading
from typing import Any

from visibility.cores.trim_regions.kbuffer import KBuffer
from visibility.scratch import Scratch

#: Seconds the buffers of a finished computation wait for the next one before they go.
KEEP_SECONDS = 5.0
#: Most buffer pairs kept (two computations of two workers side by side).
MAX_KEPT = 4


class _Pool:
    """Items kept for the next taker, all released once ``keep_seconds`` pass with nothing
    given back (the module docstring). Thread-safe."""

    def __init__(self, keep_seconds: float = KEEP_SECONDS, max_kept: int = MAX_KEPT) -> None:
        self.keep_seconds = float(keep_seconds)
        self.max_kept = int(max_kept)
        self._lock = threading.Lock()
        self._kept: list[Any] = []
        self._timer: threading.Timer | None = None

    def _keep(self, items: list[Any]) -> None:
        """Keep ``items`` first (up to ``max_kept`` in all) and restart the release timer."""
        if self.keep_seconds <= 0.0:
            return
        with self._lock:
            self._kept = (list(items) + self._kept)[:self.max_kept]
            if self._timer is not None:
                self._timer.cancel()
            self._timer = threading.Timer(self.keep_seconds, self.release)
            self._timer.daemon = True
            self._timer.start()

    def release(self) -> None:
        """Drop everything kept: its memory goes back."""
        with self._lock:
            self._kept = []
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None

    @property
    def kept(self) -> int:
        """Items held now."""
        with self._lock:
            return len(self._kept)


class WarmBuffers(_Pool):
    """(k-buffer, scratch) pairs handed to computations and kept after them (see the module
    docstring). Thread-safe: computations running side by side each take their own pairs."""

    def take(self, pixels: int, count: int) -> tuple[list[tuple[KBuffer, Scratch]], int]:
        """``count`` pairs for views of ``pixels`` pixels: kept ones first (those of another
        size are dropped), fresh ones for the rest. Returns (pairs, how many were kept)."""
        with self._lock:
            self._kept = [p for p in self._kept if len(p[0].count) == pixels]
            reused = self._kept[:count]
            del self._kept[:count]
        fresh = [(KBuffer.empty(pixels), Scratch()) for _ in range(count - len(reused))]
        return reused + fresh, len(reused)

    def give(self, pairs: list[tuple[KBuffer, Scratch]]) -> None:
        """Keep ``pairs`` (up to ``max_kept`` in all) for the next computation, and release
        them all once ``keep_seconds`` pass with no other call of ``give``."""
        self._keep(pairs)


class WarmScratch(_Pool):
    """Scratch buffers (``visibility.scratch.Scratch``) handed out one at a time and kept
    for the next taker as ``WarmBuffers`` keeps its pairs:
    the views' gathers from v* render over a million samples each into theirs, and fresh
    pages would cost their faults at every view. Thread-safe."""

    def take(self) -> Scratch:
        """A kept scratch, or a fresh one."""
        with self._lock:
            if self._kept:
                return self._kept.pop(0)
        return Scratch()

    def give(self, scratch: Scratch) -> None:
        """Keep ``scratch`` (up to ``max_kept``) for the next taker; all are released once
        ``keep_seconds`` pass with no other call of ``give``."""
        self._keep([scratch])


#: The buffers every trim_regions computation of this process shares.
WARM = WarmBuffers()
#: The scratch of the views' gathers from v* (``pipeline._Gather``).
GATHER_SCRATCH = WarmScratch()
