"""The computations queued or running, by cache key: who waits on each, how walkers rank it,
and when it is cancelled.

A computation lives here from the moment it is queued until its future is done. Two kinds of
callers keep it alive: callers that wait on its future (HTTP requests, a walker's current cell;
``release`` when they stop waiting) and walkers that want its key (``want``, ranked in
``server.demand``). It runs at the best rank among them, and is cancelled (queued: never run;
running: stopped at its core's next checkpoint) when the last of them goes.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import Future

from server.cache import PVSKey
from server.demand import Demand, Rank
from server.pool import PriorityWorkerPool, WorkerPool
from visibility.cancel import CancelToken

log = logging.getLogger(__name__)


class InFlight:
    """Queued and running computations (module docstring). ``lock`` is the compute service's
    (re-entrant: a pool that runs work inline re-enters).

    Hook: ``still_wanted(key)`` is asked before a computation nobody waits for any more is
    cancelled (True keeps it: a walker's prefetch list still names the cell).
    """

    def __init__(self, demand: Demand, lock: threading.RLock) -> None:
        self.demand = demand
        self.lock = lock
        self.still_wanted: Callable[[Hashable], bool] | None = None
        self._jobs: dict[PVSKey, Future] = {}
        #: The cancellation token of every queued or running computation, by future.
        self._tokens: dict[Future, CancelToken] = {}
        #: Callers waiting on each computation (``release``).
        self._waiters: dict[Future, int] = {}
        #: The best rank among a job's callers that are not walkers (HTTP), while they wait.
        self._base: dict[Future, Rank] = {}
        #: The pool each computation is on.
        self._lanes: dict[Future, WorkerPool] = {}
        #: Cancellations by (reason, "queued" or "running"): "unwanted" (no walker wants the
        #: result any more, nobody waits), "released" (its last caller stopped waiting).
        self.cancellations: Counter = Counter()
        self.abandoned = 0
        self.shared = 0

    def __len__(self) -> int:
        with self.lock:
            return len(self._jobs)

    def get(self, key: PVSKey) -> Future | None:
        """The computation of ``key`` that a new caller may join, or None. Lock held."""
        fut = self._jobs.get(key)
        if fut is not None and fut.cancelled():
            del self._jobs[key]
            return None
        return fut

    def add(self, key: PVSKey, fut: Future, token: CancelToken, pool: WorkerPool, rank: Rank,
            waits: bool, walker: bool) -> None:
        """A new computation of ``key`` on ``pool`` at ``rank``; ``waits``: its caller waits on
        the future; ``walker``: the caller is a walker (ranked by ``demand``). Lock held."""
        if fut.done():
            return
        self._tokens[fut] = token
        if waits:
            self._waiters[fut] = 1
            if not walker:
                self._base[fut] = rank
        self._lanes[fut] = pool
        # Forgotten only when the future is done: a job retried after its worker died keeps
        # this future, so identical requests keep joining it.
        self._jobs[key] = fut
        fut.add_done_callback(lambda f, k=key: self._forget(k, f))

    def join(self, key: PVSKey, fut: Future, rank: Rank, waits: bool, walker: bool) -> None:
        """Another caller joins ``fut`` (``add``'s arguments); a better rank promotes the job.
        Lock held."""
        self.shared += 1
        if waits:
            self._waiters[fut] = self._waiters.get(fut, 0) + 1
            if not walker:
                self._base[fut] = min(self._base.get(fut, rank), rank)
        pool = self._lanes.get(fut)
        best = self._rank(key, fut)
        if isinstance(pool, PriorityWorkerPool) and best is not None:
            pool.rerank(fut, *best, needed=waits)

    def release(self, fut: Future, reason: str = "no client wants the result") -> bool:
        """A caller stops waiting for ``fut``. When it was the last and no walker wants the
        result (``demand``, ``still_wanted``), the computation is cancelled. True when it was."""
        with self.lock:
            n = self._waiters.get(fut)
            if n is None:
                return False
            if n > 1:
                self._waiters[fut] = n - 1
                return False
            del self._waiters[fut]
            self._base.pop(fut, None)
            if fut.done():
                return False
            key = next((k for k, f in self._jobs.items() if f is fut), None)
        if key is not None and self._walker_wants(key):
            # It goes on at the rank the walkers give it (no longer its last caller's).
            with self.lock:
                rank = self._rank(key, fut)
                pool = self._lanes.get(fut)
                if isinstance(pool, PriorityWorkerPool) and rank is not None:
                    pool.rerank(fut, *rank)
            return False
        with self.lock:
            self.abandoned += 1
            if key is not None and self._jobs.get(key) is fut:
                del self._jobs[key]  # a new request starts afresh, never joins it
        self._cancel(key, fut, "released", reason)
        return True

    def want(self, walker: Hashable, needs: Mapping[PVSKey, Rank]) -> int:
        """Replace ``walker``'s needs: {cache key: (priority, since)}. The queued jobs whose
        rank changed move sooner or later; one no walker wants any more and no caller waits
        for is cancelled, queued or running. Returns how many were cancelled."""
        return self._apply(self.demand.update(walker, needs))

    def unwant(self, walker: Hashable) -> int:
        """``walker`` left: ``want`` with no needs."""
        return self._apply(self.demand.remove(walker))

    def cancel_all(self, reason: str) -> int:
        """Cancel every queued and running computation; the number cancelled."""
        with self.lock:
            tokens = list(self._tokens.values())
        for t in tokens:
            t.cancel(reason)
        return len(tokens)

    def stats(self) -> dict[str, dict[str, int]]:
        """Cancellations by reason ("unwanted", "released") and state ("queued", "running")."""
        with self.lock:
            out: dict[str, dict[str, int]] = {"unwanted": {}, "released": {}}
            for (reason, state), n in self.cancellations.items():
                out.setdefault(reason, {})[state] = n
        return out

    def _walker_wants(self, key: PVSKey) -> bool:
        return self.demand.wanted(key) or (self.still_wanted is not None
                                           and self.still_wanted(key))

    def _rank(self, key: PVSKey, fut: Future) -> Rank | None:
        """The best of ``fut``'s waiting non-walker callers' rank and the walkers' rank of
        ``key``; None when neither wants it. Lock held."""
        ranks = [r for r in (self._base.get(fut), self.demand.rank(key)) if r is not None]
        return min(ranks) if ranks else None

    def _cancel(self, key: PVSKey | None, fut: Future, reason: str, why: str) -> None:
        with self.lock:
            token = self._tokens.get(fut)
        state = "queued" if fut.cancel() else "running"
        if state == "running" and token is not None:
            token.cancel(why)
        with self.lock:
            self.cancellations[(reason, state)] += 1
        log.info("PVS %s: cancelled (%s), %s", key, state, why)

    def _apply(self, changed: Mapping[Hashable, Rank | None]) -> int:
        doomed = []
        with self.lock:
            for key in changed:
                fut = self._jobs.get(key)
                if fut is None or fut.done():
                    continue
                rank = self._rank(key, fut)
                if rank is None:
                    if self._waiters.get(fut):
                        continue  # a caller still waits: its ``release`` decides
                    del self._jobs[key]  # a new request starts afresh, never joins it
                    doomed.append((key, fut))
                    continue
                pool = self._lanes.get(fut)
                if isinstance(pool, PriorityWorkerPool):
                    pool.rerank(fut, *rank)
        for key, fut in doomed:
            self._cancel(key, fut, "unwanted", "no walker wants it any more")
        return len(doomed)

    def _forget(self, key: PVSKey, fut: Future) -> None:
        with self.lock:
            if self._jobs.get(key) is fut:
                del self._jobs[key]
            self._tokens.pop(fut, None)
            self._waiters.pop(fut, None)
            self._base.pop(fut, None)
            self._lanes.pop(fut, None)
