"""PVS computation off the event loop: submit, release, run.

``ComputeService.submit`` answers from memory when it can, joins an identical computation that is
already running, or starts a job on the pool (``server.pool``). The job looks in Redis and on disk
(``server.cache``: one key, ``PVSKey``, for cells, boxes and segments) before it computes on the
executor (``server.executor``: here, or on a Dask cluster), and stores what it computed in every
tier. The in-flight entry of a request lives until its future is done, so a request that arrives
while a job is being retried after its worker died joins the retry instead of starting a second
run. Which core and parameters a request runs is decided before it gets here
(``server.resolve``).

Walkers' work is ranked across sessions (``docs/scheduling.md``): each session states its needs
(``want``: current cell 0, cells ahead their expected arrival seconds) in ``demand``
(``server.demand``); a walker's job runs at its key's rank there, re-ranked sooner or later as
walkers move, and a job no walker wants any more and no caller waits for is cancelled.

With progressive streams, a walker's first answer for the cell it stands in comes before any
refinement: while one is queued or running, the session cores' computations computing here wait
at their next checkpoint (``FIRST_ANSWER_HOLD_S`` at most per checkpoint, so a steady stream of
first answers slows them without stopping them). They share the CPUs, and the Python between
a computation's kernels shares the GIL: beside refinements, first answers slowed down and
queued (``docs/scheduling.md``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import Future
from typing import Any

import numpy as np

from server.admission import Admission
from server.cache import PVSKey, TieredCache
from server.catalog import LoadedScene, SceneCatalog, UnknownSceneError
from server.demand import Demand, Rank
from server.executor import Executor, LocalExecutor, make_executor
from server.inflight import InFlight
from server.pool import PriorityWorkerPool, WorkerPool
from server.region import (
    PVSResult,
    Region,
    UnknownCellError,
    UnsupportedSceneError,
    region_of,
)
from server.settings import Settings
from visibility.cancel import CancelToken, ComputationCancelled
from visibility.cores.base import Core, CoreParams, Cost

log = logging.getLogger(__name__)

#: Queued jobs listed in ``stats`` (the pool's queue, first to run first).
QUEUE_LISTED = 50
#: The longest a session core's computation waits at one checkpoint for walkers' first
#: answers (``ComputeService.hold_for_first_answers``).
FIRST_ANSWER_HOLD_S = 0.5
#: How often a held computation looks whether it was cancelled meanwhile (a cancel sets the
#: token, which the hold's condition does not hear).
HOLD_CANCEL_POLL_S = 0.01


class ComputeService:
    """PVS requests for catalogue scenes: the tiered cache (``cache``), shared in-flight work, a
    worker pool whose jobs compute on an executor.

    Hooks: ``still_wanted(key)`` is asked before a computation nobody waits for any more is
    cancelled (True keeps it: a walker's prefetch list still names the cell);
    ``on_computed(seconds)`` is called after every computation (the metrics' histogram).
    """

    def __init__(
        self, catalog: SceneCatalog, settings: Settings, pool: WorkerPool | None = None,
        executor: Executor | None = None, cache: TieredCache | None = None,
    ) -> None:
        self.catalog = catalog
        self.settings = settings
        #: Where the session cores' computations run (``settings.executor``).
        self.executor = executor or make_executor(settings.executor, settings.workers,
                                                  settings.scenes_dir)
        # A pool thread waits on each remote job: as many threads as the cluster has workers,
        # keeping the light lane's reserve of settings.workers - heavy_lane_workers().
        jobs = max(settings.workers, self.executor.slots())
        heavy = jobs - (settings.workers - settings.heavy_lane_workers())
        self.pool = pool or PriorityWorkerPool(jobs, heavy, nice=settings.worker_nice)
        #: First answers (``settings.progressive``) run here, on workers of their own: they
        #: take tens of milliseconds, and must not queue behind the session cores' work. They
        #: compute in this process whatever the executor: a cluster's round trip costs as much.
        #: Warm-ups for cells ahead (priority > 0) take one of its two workers at most, so a
        #: walker's own cell never waits behind one; a warm-up promoted to a walker's cell
        #: (priority 0) leaves that lane.
        self.first_pool = (PriorityWorkerPool(2, 1, heavy_above=0.0) if settings.progressive
                           else None)
        self._here = LocalExecutor(1)
        self.admission = Admission(settings)
        #: Memory, Redis, disk (``settings.cache_bytes``, ``cache``, ``cache_dir``).
        self.cache = cache or TieredCache.from_settings(settings)
        self.on_computed: Callable[[float], None] | None = None
        # Re-entrant: a pool that runs work inline would re-enter from _run.
        self._lock = threading.RLock()
        #: What every walker wants and how soon (``want``): walkers' jobs run at its ranks.
        self.demand = Demand()
        #: The computations queued or running: their callers, ranks and cancellation.
        self.inflight = InFlight(self.demand, self._lock)
        self.cancelled = 0
        self.computed = 0
        self.failed = 0
        #: Checkpoints at which a computation waited for first answers, and seconds waited.
        self.holds = 0
        self.held_seconds = 0.0

    @property
    def still_wanted(self) -> Callable[[Hashable], bool] | None:
        """Hook asked before a computation nobody waits for is cancelled (``InFlight``)."""
        return self.inflight.still_wanted

    @still_wanted.setter
    def still_wanted(self, hook: Callable[[Hashable], bool] | None) -> None:
        self.inflight.still_wanted = hook

    def key(self, scene: str, core: Core, params: CoreParams, cell: int | None = None,
            box: np.ndarray | None = None, segment: np.ndarray | None = None) -> PVSKey:
        """The cache key ``submit`` uses for the same arguments (loads the scene)."""
        loaded = self.catalog.get(scene)
        return region_of(loaded, cell, box, segment).key(loaded.fingerprint, core, params)

    def submit(
        self,
        scene: str,
        core: Core,
        params: CoreParams,
        cell: int | None = None,
        box: np.ndarray | None = None,
        *,
        segment: np.ndarray | None = None,
        priority: float = 0.0,
        wanted: Callable[[], bool] | None = None,
        deadline: float | None = None,
        client: Hashable | None = None,
        lane: str = "main",
        since: float = 0.0,
        walker: bool = False,
    ) -> Future:
        """A future of the ``PVSResult`` for a grid cell (``cell``), an ad-hoc ``box`` (2, 3) or
        a ``segment`` (2, 3) [p, q] (metres; ``Core.compute_segment``, exact for cores that
        solve segments natively).

        ``priority``: lower runs first (0: a walker needs it now; prefetch uses larger values);
        ``since`` breaks ties, lower first. ``walker``: a session's job, which runs at its key's
        rank in ``demand`` (``want``; ``priority``/``since`` only while no walker states a
        need for it). ``wanted``: for prefetch, asked when a worker is about to start the job;
        False cancels it (the future is then cancelled). Joining an in-flight job with a lower
        priority promotes it. ``deadline``: seconds this computation may take from now, capped by
        ``settings.compute_deadline``; past it the future raises ``ComputationCancelled``.

        Admission (``server.admission``) applies to new computations only (a cached answer or
        an identical computation under way is always given): ``OverLimit`` when the core's
        estimate exceeds ``max_compute_bytes`` or the deadline; ``TooManyInFlight`` when
        ``client`` (an HTTP client's address; None: not counted) is at its cap; ``Busy`` when
        the queue is full, except for a walker's current cell (priority 0 without ``client``).
        Every caller that gets a future without ``wanted`` should ``release`` it when it stops
        waiting before it is done: the last one to go cancels the computation. ``lane``:
        "first" runs a new computation on the first answers' worker.
        The scene is loaded first if it is not yet (callers on the event loop load it before).
        Raises at once UnknownSceneError, SceneLoadFailed, UnknownCellError, ValueError (not
        exactly one region; a bad box or segment); the future raises UnsupportedSceneError or
        the core's errors.
        """
        loaded = self.catalog.get(scene)
        region = region_of(loaded, cell, box, segment)
        key = region.key(loaded.fingerprint, core, params)
        with self._lock:
            pvs = self.cache.get(key, upto="memory")
            fut = None if pvs is not None else self.inflight.get(key)
            mine = (float(priority), float(since))
            if pvs is None and fut is None:
                rank = (self.demand.rank(key) or mine) if walker else mine
                return self._start(key, loaded, region, core, params, rank, wanted,
                                   deadline, client, lane, walker)
            if fut is not None:
                self.inflight.join(key, fut, mine, wanted is None, walker)
                if client is None:
                    # A walker's cell, current or prefetched: asked alone it would have run in
                    # the light lane if its estimate is light, so it takes a job heavy only for
                    # being an HTTP request out of the heavy lane.
                    self.pool.lighten(fut, self.settings.heavy_seconds)
                return fut
        done: Future = Future()
        done.set_result(PVSResult(scene, region.cell, region.box.copy(), core.name, params, pvs,
                                  True))
        return done

    def _start(self, key: PVSKey, loaded: LoadedScene, region: Region, core: Core,
               params: CoreParams, rank: Rank, wanted: Callable[[], bool] | None,
               deadline: float | None, client: Hashable | None, lane: str,
               walker: bool) -> Future:
        """Admit and queue a new computation at ``rank`` (``submit``; lock held)."""
        priority, since = rank
        limit = self.settings.compute_deadline
        budget = limit if deadline is None else min(limit, deadline)
        pool = self.first_pool if lane == "first" and self.first_pool else self.pool
        cost = self._admit(loaded, core, params, region, budget, priority, client, pool)
        token = CancelToken.after(budget)
        model = float(cost.detail.get("model_seconds", cost.seconds))
        executor = self._here if pool is self.first_pool else self.executor
        if self.first_pool is not None and pool is not self.first_pool:
            token.hold = self.hold_for_first_answers
        job: dict[str, Any] = {"priority": priority}
        args = (self._run, key, loaded, region, core, params, token, model, executor, job)
        if isinstance(pool, PriorityWorkerPool):
            where = f"cell {region.cell}" if region.cell is not None else "region"
            # The first pool's lane follows the rank (``heavy_above``). An HTTP request runs
            # in the heavy lane whatever its estimate: an estimate learnt from a client's cheap
            # requests can price its dear ones under heavy_seconds, and two of those would take
            # every worker from the walkers' current cells.
            # A walker's cell that joins one estimated light makes it light again (``submit``).
            heavy = client is not None or cost.seconds > self.settings.heavy_seconds
            fut = pool.submit(*args, priority=priority, wanted=wanted, seconds=cost.seconds,
                              heavy=heavy, since=since,
                              label=f"{loaded.name} {where} {core.name}")
            # The executor reads the priority when the job starts: a promoted job (a walker
            # reached a prefetched cell) goes to a cluster at its new rank.
            job["pool_job"] = getattr(fut, "job", None)
        else:
            fut = pool.submit(*args)
        if client is not None:
            fut.add_done_callback(lambda f, c=client: self.admission.release(c))
        self.inflight.add(key, fut, token, pool, rank, wanted is None, walker)
        return fut

    async def compute(
        self,
        scene: str,
        core: Core,
        params: CoreParams,
        cell: int | None = None,
        box: np.ndarray | None = None,
        segment: np.ndarray | None = None,
        *,
        deadline: float | None = None,
        client: Hashable | None = None,
    ) -> PVSResult:
        """``submit`` awaited from the event loop. When the caller is cancelled (its client
        left) the computation is cancelled too, unless another request shares it or a walker
        still wants the cell (``release``)."""
        fut = self.submit(scene, core, params, cell, box, segment=segment, deadline=deadline,
                          client=client)
        inner = asyncio.wrap_future(fut)
        # When the caller is gone, retrieve the outcome anyway so asyncio does not log it.
        inner.add_done_callback(lambda f: f.cancelled() or f.exception())
        try:
            return await asyncio.shield(inner)
        except asyncio.CancelledError:
            self.release(fut)
            raise

    def release(self, fut: Future, reason: str = "no client wants the result") -> bool:
        """The caller of ``submit`` stops waiting for ``fut``. When it was the last caller and
        no walker wants the result any more (``still_wanted``), the computation is cancelled:
        unstarted, it never runs; running, it stops at its core's next checkpoint. True when
        it was cancelled."""
        return self.inflight.release(fut, reason)

    def want(self, walker: Hashable, needs: Mapping[PVSKey, Rank]) -> int:
        """Replace ``walker``'s needs: {cache key: (priority, since)} (``server.demand``: its
        current cell (0, the instant it entered), the cells ahead (expected arrival seconds,
        0)). The queued jobs of the keys whose rank changed move sooner or later; one that no
        walker wants any more and no caller waits for is cancelled, queued or running.
        Returns how many were cancelled."""
        return self.inflight.want(walker, needs)

    def unwant(self, walker: Hashable) -> int:
        """``walker`` left: ``want`` with no needs."""
        return self.inflight.unwant(walker)

    def _admit(self, loaded: LoadedScene, core: Core, params: CoreParams, region: Region,
               deadline: float, priority: float, client: Hashable | None,
               pool: WorkerPool) -> Cost:
        """The cost estimate of a new computation on ``pool``, after the admission checks
        (``server.admission``; raises its ``Refused`` errors). Called with the lock held."""
        adm = self.admission
        cost = adm.estimate(core, loaded.scene, region.viewcell, params, loaded.name)
        adm.check_limits(cost, deadline, core.name)
        prio = pool if isinstance(pool, PriorityWorkerPool) else None
        ahead = prio.queued_seconds() if prio is not None else 0.0
        if prio is not None and (priority > 0 or client is not None):
            adm.check_queue(prio.queued(), ahead)
        adm.acquire(client, ahead)
        return cost

    def cancel_all(self, reason: str = "server shutting down") -> int:
        """Cancel every queued and running computation (each stops at its core's next
        checkpoint); the number cancelled."""
        return self.inflight.cancel_all(reason)

    def _run(self, key: PVSKey, loaded: LoadedScene, region: Region, core: Core,
             params: CoreParams, token: CancelToken | None = None, model_seconds: float = 0.0,
             executor: Executor | None = None, job: dict[str, Any] | None = None) -> PVSResult:
        name = loaded.name
        try:
            fit = core.fit(loaded.scene, float(loaded.grid.cell_size))
            if not fit.ok:
                raise UnsupportedSceneError(f"core {core.name!r} does not fit {name!r}: "
                                            f"{fit.why}")
            n = loaded.scene.n_triangles
            # Memory missed (``submit``): the shared tier, then this machine's disk.
            pvs = self.cache.get(key, n, first="shared")
            if pvs is not None:
                return PVSResult(name, region.cell, region.box.copy(), core.name, params, pvs,
                                 True)
            t0 = time.perf_counter()
            pool_job = (job or {}).get("pool_job")
            priority = pool_job.priority if pool_job is not None else (job or {}).get(
                "priority", 0.0)
            pvs = (executor or self.executor).compute(
                loaded, core, params, cell=region.viewcell if region.segment is None else None,
                segment=region.segment, token=token, priority=priority)
            seconds = time.perf_counter() - t0
            # The core's own time: a remote round trip must not teach the cost model that
            # this machine is slower.
            self.admission.observe(name, core.name, model_seconds, pvs.seconds or seconds)
            log.debug("PVS %s cell=%s core=%s: %d triangles in %.3f s", name, region.cell,
                      core.name, len(pvs), seconds)
            # Grid cells only on disk: ad-hoc regions are unbounded in number (Redis bounds
            # them with its maxmemory and TTL; the disk tier has no bound of its own).
            self.cache.put(key, pvs, n, disk=region.cell is not None)
            with self._lock:
                self.computed += 1
            if self.on_computed is not None:
                self.on_computed(seconds)
            return PVSResult(name, region.cell, region.box.copy(), core.name, params, pvs, False)
        except (UnknownSceneError, UnknownCellError, UnsupportedSceneError):
            raise
        except ComputationCancelled as exc:
            with self._lock:
                self.cancelled += 1
            log.warning("PVS %s cell=%s core=%s stopped: %s", name, region.cell, core.name, exc)
            raise
        except Exception:
            with self._lock:
                self.failed += 1
            raise

    def hold_for_first_answers(self, token: CancelToken) -> None:
        """Wait while a walker's first answer (priority 0 on the first answers' pool, a
        promoted warm-up included) is queued or running, up to ``FIRST_ANSWER_HOLD_S`` and no
        longer than ``token`` stays uncancelled: the ``hold`` of the session cores'
        computations (module docstring), called at their checkpoints in the computing
        thread."""
        pool = self.first_pool
        if pool is None or pool.pending(0.0) == 0:
            return
        t0 = time.perf_counter()
        end = t0 + FIRST_ANSWER_HOLD_S
        while not token.cancelled:
            left = end - time.perf_counter()
            if left <= 0 or pool.wait_clear(0.0, min(left, HOLD_CANCEL_POLL_S)):
                break
        with self._lock:
            self.holds += 1
            self.held_seconds += time.perf_counter() - t0

    def stats(self) -> dict[str, Any]:
        """Cache statistics per tier plus computations done, failed, shared and in flight, and
        the checkpoints at which computations waited for first answers (``holds``,
        ``held_seconds``)."""
        inflight = len(self.inflight)
        out = {**self.cache.stats(), "computed": self.computed, "failed": self.failed,
               "cancelled": self.cancelled, "abandoned": self.inflight.abandoned,
               "holds": self.holds, "held_seconds": round(self.held_seconds, 3),
               "shared": self.inflight.shared, "inflight": inflight,
               "workers": getattr(self.pool, "workers", None),
               "admission": self.admission.stats(), "executor": self.executor.state(),
               "demand": self.demand.stats()}
        cancels = self.inflight.stats()
        if isinstance(self.pool, PriorityWorkerPool):
            cancels["skipped"] = {"queued": self.pool.skipped}
            out["pool"] = {"retried": self.pool.retried, "replaced": self.pool.replaced,
                           "skipped": self.pool.skipped, "queued": self.pool.queued(),
                           "queued_seconds": round(self.pool.queued_seconds(), 3),
                           "heavy_running": self.pool.heavy_running(),
                           "heavy_workers": self.pool.heavy_workers,
                           "reranks": {"sooner": self.pool.reranks["sooner"],
                                       "later": self.pool.reranks["later"]},
                           "queue": self.pool.snapshot(QUEUE_LISTED)}
        out["cancellations"] = cancels
        return out

    def shutdown(self) -> None:
        """Stop the pool, dropping queued work; running computations stop at their cores'
        next checkpoint."""
        self.cancel_all()
        self.pool.shutdown(wait=False, cancel_futures=True)
        if self.first_pool is not None:
            self.first_pool.shutdown(wait=False, cancel_futures=True)
        self.executor.close()
        self.cache.close()
