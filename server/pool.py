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

Order of ``PriorityWorkerPool``: (priority, since, seconds), lowest first, FIFO among equals. A
queued job is re-keyed (``rerank``) either way as the walkers that want it move: the job gets a
fresh heap entry under a new sequence number and the old entry, no longer the job's ``entry``,
is skipped when it surfaces (lazy deletion); the heap is rebuilt once stale entries outnumber
live ones, so it stays within a constant factor of the queue.
"""

from __future__ import annotations

import heapq
import logging
import os
import threading
import time
from collections import Counter
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
    #: Tie-break among equal priorities, lower first (a walker's cell-entry instant).
    since: float = 0.0
    #: What the job computes, for the queue's listing (``snapshot``).
    label: str = ""
    #: The sequence number of the job's live heap entry (others are stale).
    entry: int = -1
    #: The pool that queued it (``rerank`` ignores other pools' jobs).
    owner: Any = None
    queued_at: float = 0.0

    def key(self) -> tuple[float, float, float]:
        return (self.priority, self.since, self.seconds)


#: Stale heap entries tolerated before the heap is rebuilt from its live ones.
MIN_STALE_TO_COMPACT = 64


class PriorityWorkerPool:
    """``workers`` threads taking jobs lowest ``priority`` first, then lowest ``since``, then
    shortest estimated ``seconds`` (FIFO among equals).

    Two lanes: ``heavy`` jobs may occupy at most ``heavy_workers`` threads at once (default:
    all), so with fewer heavy workers than workers a light job always finds one free. With
    ``heavy_above`` set, a job's lane follows its rank instead: heavy while its priority is
    above ``heavy_above``, light from the moment ``rerank`` or ``promote`` brings it there (a
    warm-up a walker now waits for must not queue behind the other warm-ups).

    A job whose ``wanted()`` says False when a worker picks it is cancelled unrun (prefetch work
    no walker is heading for any more); ``rerank`` re-keys a queued job either way, ``promote``
    moves one forward and makes it run wanted or not (a caller now waits for it). A job's
    ``Exception`` is its answer (never retried); a worker killed by a ``BaseException``
    (``WorkerDied``, ``SystemExit``...) is replaced by a fresh thread and its job retried once
    (see the module docstring). ``retried``, ``replaced`` and ``skipped`` count those events,
    ``reranks`` the re-keyings ("sooner", "later").
    """

    def __init__(self, workers: int, heavy_workers: int | None = None, nice: int = 0,
                 heavy_above: float | None = None) -> None:
        self.workers = int(workers)
        #: How much nicer (lower CPU priority) its threads run (``lower_priority``).
        self.nice = max(0, int(nice))
        self.heavy_workers = self.workers if heavy_workers is None else max(1, int(heavy_workers))
        self.heavy_above = None if heavy_above is None else float(heavy_above)
        self._heavy_running = 0
        lock = threading.Lock()
        self._cv = threading.Condition(lock)
        #: Notified when a job ends (``wait_clear``); on the same lock, so a waiter never takes
        #: a wake-up meant for a worker.
        self._ended = threading.Condition(lock)
        self._running: set[_Job] = set()
        self._heap: list[tuple[float, float, float, int, _Job]] = []
        self._count = 0
        self._stale = 0
        self.reranks: Counter = Counter()
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
               heavy: bool = False, since: float = 0.0, label: str = "") -> Future:
        """Queue ``fn(*args)``; its future (``job`` attribute: the handle for ``rerank`` and
        ``promote``). ``seconds``: its estimated run time (shortest first within a priority and
        ``since``); ``heavy``: it runs in the heavy lane; ``since``: the tie-break among equal
        priorities, lower first; ``label``: what it computes (``snapshot``)."""
        fut: Future = Future()
        if self.heavy_above is not None:
            heavy = float(priority) > self.heavy_above
        job = _Job(fn, args, fut, float(priority), wanted, seconds=float(seconds),
                   heavy=bool(heavy), since=float(since), label=str(label), owner=self,
                   queued_at=time.monotonic())
        fut.job = job  # type: ignore[attr-defined]
        self._push(job)
        return fut

    def _push(self, job: _Job) -> None:
        with self._cv:
            stopped = self._stop
            if not stopped:
                self._enqueue(job)
                self._cv.notify()
        if stopped:  # outside the lock, as in ``_next``
            job.future.cancel()

    def _enqueue(self, job: _Job) -> None:
        """Give ``job`` a fresh heap entry (its older ones go stale). Lock held."""
        job.entry = self._count
        heapq.heappush(self._heap, (*job.key(), self._count, job))
        self._count += 1

    @staticmethod
    def _live(entry: tuple) -> bool:
        job = entry[-1]
        return job.entry == entry[-2] and not job.started and not job.future.done()

    def rerank(self, future: Future, priority: float, since: float = 0.0, *,
               needed: bool = False) -> bool:
        """Re-key the still queued job of ``future`` to (``priority``, ``since``), sooner or
        later (a running one keeps its lane but is counted at its new rank by ``pending``);
        ``needed``: a caller now waits for it, so it runs even if unwanted. True when its
        place in the queue changed (counted in ``reranks``)."""
        job = getattr(future, "job", None)
        if job is None or job.owner is not self:
            return False
        with self._cv:
            if needed:
                job.wanted = None
            if job.future.done() or job.entry < 0:
                return False
            new = (float(priority), float(since))
            if job.started:
                # Running: its lane is fixed, but whom it serves now counts (``pending``).
                job.priority, job.since = new
                return False
            old = (job.priority, job.since)
            if new == old:
                return False
            self.reranks["sooner" if new < old else "later"] += 1
            job.priority, job.since = new
            if self.heavy_above is not None:
                job.heavy = job.priority > self.heavy_above
            self._stale += 1
            self._enqueue(job)
            if self._stale > max(MIN_STALE_TO_COMPACT, len(self._heap) // 2):
                self._heap = [e for e in self._heap if self._live(e)]
                heapq.heapify(self._heap)
                self._stale = 0
            self._cv.notify()
            return True

    def promote(self, future: Future, priority: float = 0.0) -> None:
        """Run the (still queued) job of ``future`` at ``priority`` at the latest, and run it
        even if unwanted (a caller now waits for it)."""
        job = getattr(future, "job", None)
        if job is None or job.owner is not self:
            return
        with self._cv:
            job.wanted = None
            if job.started or priority >= job.priority:
                return
        self.rerank(future, priority, job.since)

    def lighten(self, future: Future, heavy_seconds: float) -> bool:
        """Move the still queued job of ``future`` to the light lane when its estimate is at
        most ``heavy_seconds`` (then it was heavy only for whom it was first asked by: an HTTP
        request; a walker's cell joined it). True when it moved."""
        job = getattr(future, "job", None)
        if job is None or job.owner is not self:
            return False
        with self._cv:
            if (job.started or job.future.done() or not job.heavy
                    or job.seconds > heavy_seconds):
                return False
            job.heavy = False
            self._cv.notify()
            return True

    def _waiting(self) -> list[_Job]:
        # Jobs still waiting, each once (a re-ranked job's older entries are stale).
        return [e[-1] for e in self._heap if self._live(e)]

    def snapshot(self, limit: int = 50) -> list[dict[str, Any]]:
        """The first ``limit`` queued jobs in the order they would start (lane limits aside):
        what (``label``), priority, since, estimated seconds, lane, seconds queued."""
        now = time.monotonic()
        with self._cv:
            live = sorted((e for e in self._heap if self._live(e)), key=lambda e: e[:4])
            return [{"what": j.label, "priority": round(j.priority, 3), "since": j.since,
                     "seconds": round(j.seconds, 3), "heavy": j.heavy,
                     "queued_s": round(now - j.queued_at, 3)}
                    for *_, j in live[:max(0, int(limit))]]

    def queued(self) -> int:
        """Jobs waiting for a worker."""
        with self._cv:
            return len(self._waiting())

    def queued_seconds(self) -> float:
        """The estimated seconds of the jobs waiting for a worker, summed."""
        with self._cv:
            return float(sum(j.seconds for j in self._waiting()))

    def pending(self, at_most: float) -> int:
        """Jobs queued or running whose priority is at most ``at_most``."""
        with self._cv:
            return self._pending(at_most)

    def _pending(self, at_most: float) -> int:
        waiting = sum(1 for j in self._waiting() if j.priority <= at_most)
        return waiting + sum(1 for j in self._running if j.priority <= at_most)

    def wait_clear(self, at_most: float, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds until no job of priority at most ``at_most`` is
        queued or running; True when none is. Woken when a job ends; a queued job cancelled
        meanwhile is seen at the timeout."""
        end = time.monotonic() + max(0.0, timeout)
        with self._cv:
            while self._pending(at_most) > 0:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._ended.wait(left)
            return True

    def heavy_running(self) -> int:
        """Heavy-lane jobs running now."""
        with self._cv:
            return self._heavy_running

    def _next(self) -> _Job | None:
        while True:
            unwanted: list[_Job] = []
            with self._cv:
                while not self._heap and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return None
                job = self._pop_runnable(unwanted)
                if job is None and not unwanted:
                    # Only heavy jobs wait and their lane is full: a heavy job's end wakes us.
                    self._cv.wait()
                    continue
                if job is not None:
                    job.started = True
                    self._running.add(job)
                    if job.heavy:
                        self._heavy_running += 1
            # Outside the lock: a future's callbacks may take their owner's lock, which may
            # be held by a thread waiting for ours (``ComputeService``).
            for j in unwanted:
                j.future.cancel()
            if job is not None:
                return job

    def _pop_runnable(self, unwanted: list[_Job]) -> _Job | None:
        """The first queued job a worker may start (its lane has room); unwanted jobs met on
        the way are taken off the queue into ``unwanted`` (the caller cancels them). Called
        with the lock held."""
        blocked = []
        found = None
        while self._heap:
            entry = heapq.heappop(self._heap)
            job = entry[-1]
            if job.entry != entry[-2]:
                self._stale = max(0, self._stale - 1)
                continue
            if job.started or job.future.done():
                continue
            if job.heavy and self._heavy_running >= self.heavy_workers:
                blocked.append(entry)
                continue
            if job.wanted is not None and not job.wanted():
                self.skipped += 1
                job.entry = -1  # off the queue: never re-ranked back onto it
                unwanted.append(job)
                continue
            found = job
            break
        for entry in blocked:
            heapq.heappush(self._heap, entry)
        return found

    def _finished(self, job: _Job) -> None:
        with self._cv:
            self._running.discard(job)
            if job.heavy:
                self._heavy_running -= 1
                self._cv.notify_all()
            self._ended.notify_all()

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
                     job.attempts + 1, seconds=job.seconds, heavy=job.heavy, since=job.since,
                     label=job.label, owner=self, queued_at=time.monotonic())
        if isinstance(job.future, Future):
            # Re-ranking the caller's future now moves the retry.
            job.future.job = retry  # type: ignore[attr-defined]
        self._push(retry)
        return True

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop the workers (running jobs finish); ``cancel_futures`` cancels queued jobs."""
        with self._cv:
            self._stop = True
            dropped = self._waiting() if cancel_futures else []
            if cancel_futures:
                self._heap.clear()
            self._cv.notify_all()
        for job in dropped:  # outside the lock, as in ``_next``
            job.future.cancel()
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
