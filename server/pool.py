"""Worker pools for PVS computations: a plain thread pool and a priority pool that replaces dead
workers.

``ComputeService`` needs only ``submit``/``shutdown`` (``WorkerPool``), so a process pool can
replace the thread pool later; threads suffice now because the numba kernels release the GIL.

Fault rule of ``PriorityWorkerPool``: an ordinary ``Exception`` raised by a job is its answer
(a core's ValueError, an unknown cell) and goes to its future at once, never retried, since a
deterministic failure would only fail again. A worker that *dies* (the job raised a
``BaseException`` such as ``WorkerDied`` or ``SystemExit``) is replaced by a fresh thread and its
job runs once more; the caller's future is the same object throughout, so whoever waits on it
(or joined it) gets the retry's answer.
"""

from __future__ import annotations

import heapq
import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

log = logging.getLogger(__name__)


class WorkerPool(Protocol):
    """What ``ComputeService`` needs from an executor."""

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future: ...

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None: ...


class ThreadWorkerPool:
    """A ``ThreadPoolExecutor`` of ``workers`` threads named ``pvs-worker-*``."""

    def __init__(self, workers: int) -> None:
        self.workers = int(workers)
        self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix="pvs-worker")

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future:
        return self._executor.submit(fn, *args)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._executor.shutdown(wait=wait, cancel_futures=cancel_futures)


def lower_priority(nice: int) -> bool:
    """Make the calling thread ``nice`` steps nicer (Linux: the nice value is per thread, and the
    threads it starts later, such as a numba kernel's OpenMP team, inherit it). Returns whether
    it took effect; elsewhere it does nothing. Raising one's nice value needs no privilege."""
    if nice <= 0 or not hasattr(os, "setpriority") or not hasattr(threading, "get_native_id"):
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + int(nice))
    except OSError as exc:  # a sandbox that forbids it: run at the usual priority
        log.warning("could not lower the priority of %s: %s", threading.current_thread().name,
                    exc)
        return False
    return True


class WorkerDied(BaseException):
    """Raised inside a job to simulate (or signal) the death of the worker thread running it."""


@dataclass(eq=False)
class _Job:
    fn: Callable[..., Any]
    args: tuple
    future: Any  # Future, or _ChainedFuture for a retry
    priority: float
    wanted: Callable[[], bool] | None = None
    attempts: int = 0
    started: bool = False
    #: Estimated seconds (shortest first within a priority) and the lane.
    seconds: float = 0.0
    heavy: bool = False


class PriorityWorkerPool:
    """``workers`` threads taking jobs lowest ``priority`` first, then shortest estimated
    ``seconds`` first (FIFO among equals).

    Two lanes: ``heavy`` jobs may occupy at most ``heavy_workers`` threads at once (default:
    all), so with fewer heavy workers than workers a light job always finds one free.

    A job whose ``wanted()`` says False when a worker picks it is cancelled unrun (prefetch work
    no walker is heading for any more); ``promote`` moves a queued job forward. A job's
    ``Exception`` is its answer (never retried); a worker killed by a ``BaseException``
    (``WorkerDied``, ``SystemExit``...) is replaced by a fresh thread and its job retried once
    (see the module docstring). ``retried``, ``replaced`` and ``skipped`` count those events.
    """

    def __init__(self, workers: int, heavy_workers: int | None = None, nice: int = 0) -> None:
        self.workers = int(workers)
        #: How much nicer (lower CPU priority) its threads run (``lower_priority``).
        self.nice = max(0, int(nice))
        self.heavy_workers = self.workers if heavy_workers is None else max(1, int(heavy_workers))
        self._heavy_running = 0
        self._cv = threading.Condition()
        self._heap: list[tuple[float, float, int, _Job]] = []
        self._count = 0
        self._stop = False
        self.retried = 0
        self.replaced = 0
        self.skipped = 0
        self._threads: list[threading.Thread] = []
        for _ in range(self.workers):
            self._spawn()

    def _spawn(self) -> None:
        t = threading.Thread(target=self._worker, name=f"pvs-worker-{len(self._threads)}",
                             daemon=True)
        self._threads.append(t)
        t.start()

    def submit(self, fn: Callable[..., Any], /, *args: Any, priority: float = 0.0,
               wanted: Callable[[], bool] | None = None, seconds: float = 0.0,
               heavy: bool = False) -> Future:
        """Queue ``fn(*args)``; its future (``job`` attribute: the handle for ``promote``).
        ``seconds``: its estimated run time (shortest first within a priority); ``heavy``: it
        runs in the heavy lane."""
        fut: Future = Future()
        job = _Job(fn, args, fut, float(priority), wanted, seconds=float(seconds),
                   heavy=bool(heavy))
        fut.job = job  # type: ignore[attr-defined]
        self._push(job)
        return fut

    def _push(self, job: _Job) -> None:
        with self._cv:
            if self._stop:
                job.future.cancel()
                return
            heapq.heappush(self._heap, (job.priority, job.seconds, self._count, job))
            self._count += 1
            self._cv.notify()

    def promote(self, future: Future, priority: float = 0.0) -> None:
        """Run the (still queued) job of ``future`` at ``priority`` and run it even if unwanted."""
        job = getattr(future, "job", None)
        if job is None:
            return
        with self._cv:
            job.wanted = None
            if job.started or priority >= job.priority:
                return
            job.priority = priority
            # The old heap entry stays; whichever entry comes first runs the job, the other is
            # skipped because the job has started.
            heapq.heappush(self._heap, (priority, job.seconds, self._count, job))
            self._count += 1
            self._cv.notify()

    def _waiting(self) -> list[_Job]:
        # Unique jobs still waiting (a promoted job has two heap entries).
        return list({id(j): j for *_, j in self._heap
                     if not j.started and not j.future.done()}.values())

    def queued(self) -> int:
        """Jobs waiting for a worker."""
        with self._cv:
            return len(self._waiting())

    def queued_seconds(self) -> float:
        """The estimated seconds of the jobs waiting for a worker, summed."""
        with self._cv:
            return float(sum(j.seconds for j in self._waiting()))

    def heavy_running(self) -> int:
        """Heavy-lane jobs running now."""
        with self._cv:
            return self._heavy_running

    def _next(self) -> _Job | None:
        with self._cv:
            while True:
                while not self._heap and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return None
                job = self._pop_runnable()
                if job is None:
                    # Only heavy jobs wait and their lane is full: a heavy job's end wakes us.
                    self._cv.wait()
                    continue
                job.started = True
                if job.heavy:
                    self._heavy_running += 1
                return job

    def _pop_runnable(self) -> _Job | None:
        """The first queued job a worker may start (its lane has room); unwanted jobs met on
        the way are cancelled. Called with the lock held."""
        blocked = []
        found = None
        while self._heap:
            entry = heapq.heappop(self._heap)
            job = entry[-1]
            if job.started or job.future.done():
                continue
            if job.heavy and self._heavy_running >= self.heavy_workers:
                blocked.append(entry)
                continue
            if job.wanted is not None and not job.wanted():
                self.skipped += 1
                job.future.cancel()
                continue
            found = job
            break
        for entry in blocked:
            heapq.heappush(self._heap, entry)
        return found

    def _finished(self, job: _Job) -> None:
        if job.heavy:
            with self._cv:
                self._heavy_running -= 1
                self._cv.notify_all()

    def _worker(self) -> None:
        if self.nice:
            lower_priority(self.nice)
        while True:
            job = self._next()
            if job is None:
                return
            if not job.future.set_running_or_notify_cancel():
                self._finished(job)
                continue
            try:
                result = job.fn(*job.args)
            except Exception as exc:  # the job's answer: a deterministic failure stays one
                self._finished(job)
                job.future.set_exception(exc)
            except BaseException as exc:
                self._finished(job)
                # The worker is dead: a fresh one takes its place, the job gets one more go.
                log.error("worker %s died (%r); replacing it", threading.current_thread().name,
                          exc)
                with self._cv:
                    self.replaced += 1
                    if not self._stop:
                        self._spawn()
                if not self._retry(job, exc):
                    job.future.set_exception(RuntimeError(f"worker died: {exc!r}"))
                return
            else:
                self._finished(job)
                job.future.set_result(result)

    def _retry(self, job: _Job, exc: BaseException) -> bool:
        with self._cv:
            if job.attempts >= 1 or self._stop:
                return False
            self.retried += 1
        log.warning("retrying %s once after its worker died (%r)",
                    getattr(job.fn, "__name__", job.fn), exc)
        # The caller's future stays the one it holds: the retry's outcome is chained into it.
        retry = _Job(job.fn, job.args, _ChainedFuture(job.future), job.priority, None,
                     job.attempts + 1, seconds=job.seconds, heavy=job.heavy)
        self._push(retry)
        return True

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop the workers (running jobs finish); ``cancel_futures`` cancels queued jobs."""
        with self._cv:
            self._stop = True
            if cancel_futures:
                for *_, job in self._heap:
                    if not job.started:
                        job.future.cancel()
                self._heap.clear()
            self._cv.notify_all()
        if wait:
            for t in list(self._threads):
                t.join(timeout=30)


class _ChainedFuture:
    """Stands for a running future in a retry: forwards the outcome to it."""

    def __init__(self, target: Future) -> None:
        self._target = target

    def done(self) -> bool:
        return self._target.done()

    def cancel(self) -> bool:
        # A queued retry dropped at shutdown: its caller must not wait for ever.
        if not self._target.done():
            self._target.set_exception(RuntimeError("worker pool shut down before the retry"))
        return False

    def set_running_or_notify_cancel(self) -> bool:
        return not self._target.done()

    def set_result(self, result: Any) -> None:
        if not self._target.done():
            self._target.set_result(result)

    def set_exception(self, exc: BaseException) -> None:
        if not self._target.done():
            self._target.set_exception(exc)
