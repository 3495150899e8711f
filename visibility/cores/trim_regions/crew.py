"""The threads a view may use while the views of a computation run side by side.

Views run one per worker thread, each with one numba thread: the per-layer kernels are too
short to keep two threads busy while every worker has a view. But one view can hold most of a
cell's work (the one looking into a dense room), and once the queue is empty the other workers
sit idle until it is done. ``Crew`` counts the views queued and running, and a running view
asks it, between layers, how many numba threads it may use: one while views are queued or as
many run as there are workers, and the idle workers' share once the queue is empty.
"""

from __future__ import annotations

import threading

import numba


class Crew:
    """Views queued and running over ``workers`` threads (see the module docstring)."""

    def __init__(self, workers: int) -> None:
        self.workers = max(1, int(workers))
        self._lock = threading.Lock()
        self._queued = 0
        self._running = 0

    def queue(self, n: int) -> None:
        """``n`` more views were submitted."""
        with self._lock:
            self._queued += n

    def start(self) -> None:
        """A view left the queue and runs (the calling thread starts with one numba
        thread)."""
        with self._lock:
            self._queued -= 1
            self._running += 1
        numba.set_num_threads(1)

    def finish(self) -> None:
        """The view on the calling thread is done (its thread goes back to one numba
        thread)."""
        with self._lock:
            self._running -= 1
        numba.set_num_threads(1)

    def threads(self) -> int:
        """Numba threads the calling view may use now: its share of the workers once no view
        is queued, else one."""
        with self._lock:
            if self._queued > 0 or self._running <= 0:
                return 1
            return max(1, self.workers // self._running)

    def lend(self) -> int:
        """Set the calling thread's numba threads to ``threads()``; returns that count."""
        n = self.threads()
        if n != numba.get_num_threads():
            numba.set_num_threads(n)
        return n


__all__ = ["Crew"]
