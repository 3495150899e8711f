"""PVS computation off the event loop: cache, shared in-flight requests, a worker pool.

``ComputeService.submit`` answers from the cache when it can, joins an identical computation that
is already running, or starts one on the pool (``server.pool``; caches in ``server.cache``). The
in-flight entry of a request lives until its future is done, so a request that arrives while a
job is being retried after its worker died joins the retry instead of starting a second run.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import threading
import time
import typing
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from pydantic import ConfigDict, TypeAdapter, ValidationError

from server.admission import Admission, Refused
from server.cache import ByteLRU, DiskPVSCache, PVSCache, pvs_nbytes
from server.catalog import LoadedScene, SceneCatalog, UnknownSceneError
from server.executor import Executor, LocalExecutor, make_executor
from server.pool import PriorityWorkerPool, ThreadWorkerPool, WorkerDied, WorkerPool
from server.redis_cache import SharedCache
from server.redis_codec import pvs_key
from server.settings import Settings
from visibility.calibration import Calibration
from visibility.cancel import CancelToken, ComputationCancelled
from visibility.cores.base import (
    AUTO_CORE,
    PVS,
    Core,
    CoreParams,
    Cost,
    get_core,
)
from visibility.cores.base import all_fits as registry_fits
from visibility.cores.base import choose_core as registry_choose_core
from visibility.scene import Scene
from visibility.viewcells import Viewcell

#: Re-exported: the pool and cache classes lived here before ``server.pool``/``server.cache``.
__all__ = ["AUTO_CORE", "ByteLRU", "ComputeService", "DiskPVSCache", "PVSCache", "PVSResult",
           "PriorityWorkerPool", "Refused", "ThreadWorkerPool", "UnknownCellError",
           "UnknownCoreError", "UnsupportedSceneError", "WorkerDied", "WorkerPool", "choose_core",
           "coerce_params", "core_fits", "offered_cores", "pvs_nbytes", "resolve_core"]

log = logging.getLogger(__name__)


class UnknownCoreError(LookupError):
    """No core registered under this name."""


class UnknownCellError(LookupError):
    """A cell id outside the scene's grid."""


class UnsupportedSceneError(ValueError):
    """The core does not fit the scene (``Core.supports`` said no)."""


# --------------------------------------------------------------------------- parameters
@lru_cache(maxsize=256)
def _adapter(hint: Any) -> TypeAdapter:
    return TypeAdapter(hint, config=ConfigDict(allow_inf_nan=False))


def resolve_core(name: str) -> Core:
    """The core registered as ``name``; UnknownCoreError otherwise."""
    try:
        return get_core(name)
    except KeyError as exc:
        raise UnknownCoreError(exc.args[0] if exc.args else f"unknown core {name!r}") from None


def coerce_params(core: Core, raw: Mapping[str, Any]) -> CoreParams:
    """``core``'s parameters from loosely typed values (query strings, JSON), validated.

    Each value is converted to its dataclass field's type ("32" -> 32, "true" -> True; NaN and
    fractional ints rejected), then ``core.make_params`` checks names and ranges. Raises
    ValueError with a readable message.
    """
    fields = {f.name for f in dataclasses.fields(core.Params)}
    unknown = sorted(set(raw) - fields)
    if unknown:
        raise ValueError(f"unknown parameters for core {core.name!r}: {unknown}; known: "
                         f"{sorted(fields)}")
    hints = typing.get_type_hints(core.Params)
    values = {}
    for k, v in raw.items():
        try:
            values[k] = _adapter(hints[k]).validate_python(v)
        except ValidationError as exc:
            msg = exc.errors(include_url=False)[0]["msg"]
            raise ValueError(f"parameter {k}={v!r}: {msg}") from None
    try:
        return core.make_params(**values)
    except TypeError as exc:
        raise ValueError(str(exc)) from None


@dataclass(frozen=True)
class PVSResult:
    """A computed (or cached) PVS with what it was computed for.

    ``box`` is the (2, 3) viewcell box, metres; ``seconds`` the computation time (of the
    original computation for cached results); ``cached`` whether it came from the cache.
    """

    scene: str
    cell: int | None
    box: np.ndarray
    core: str
    params: CoreParams
    pvs: PVS
    cached: bool

    @property
    def seconds(self) -> float:
        return self.pvs.seconds


# --------------------------------------------------------------------------- service
class ComputeService:
    """PVS requests for catalogue scenes: cache, shared in-flight work, a worker pool whose
    jobs compute on an executor (``server.executor``: here, or on a Dask cluster)."""

    def __init__(
        self, catalog: SceneCatalog, settings: Settings, pool: WorkerPool | None = None,
        executor: Executor | None = None,
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
        #: First answers (``settings.progressive``) run here, on a worker of their own: they
        #: take tens of milliseconds, and must not queue behind the session cores' work. They
        #: compute in this process whatever the executor: a cluster's round trip costs as much.
        self.first_pool = PriorityWorkerPool(1) if settings.progressive else None
        self._here = LocalExecutor(1)
        self._first: tuple[Core, CoreParams] | None = None
        #: Calibrations of ``auto`` by (scene name, cell size); None while one is measured.
        self.calibrations: dict[tuple[str, float], Calibration | None] = {}
        self.admission = Admission(settings)
        #: Asked, with a cache key, before a computation nobody waits for any more is
        #: cancelled: True keeps it (a walker's prefetch list still names the cell).
        self.still_wanted: Callable[[Hashable], bool] | None = None
        self.cache = PVSCache(settings.cache_bytes)
        self.disk = DiskPVSCache(settings.cache_dir) if settings.cache_dir is not None else None
        #: The cache replicas share (``settings.cache``: Redis), between memory and disk.
        self.redis = SharedCache.from_settings(settings)
        #: Called with the seconds of every finished computation (metrics hook).
        self.on_computed: Callable[[float], None] | None = None
        # Re-entrant: a pool that runs work inline would re-enter from _run.
        self._lock = threading.RLock()
        self._inflight: dict[Hashable, Future] = {}
        #: The cancellation token of every queued or running computation, by future.
        self._tokens: dict[Future, CancelToken] = {}
        #: Callers waiting on each queued or running computation (``release``).
        self._waiters: dict[Future, int] = {}
        self.abandoned = 0
        self.cancelled = 0
        self.computed = 0
        self.failed = 0
        self.shared = 0

    def resolve(
        self, core_name: str | None = None, params: Mapping[str, Any] | None = None
    ) -> tuple[Core, CoreParams]:
        """The core (default ``settings.core``) and its validated parameters. Requests for the
        default core start from ``settings.core_params``. Raises UnknownCoreError, ValueError."""
        name = core_name or self.settings.core
        if name == AUTO_CORE:
            raise UnknownCoreError("the auto core is chosen per scene: use resolve_for(scene)")
        core = resolve_core(name)
        raw = dict(self.settings.core_params) if name == self.settings.core else {}
        raw.update(params or {})
        return core, coerce_params(core, raw)

    def resolve_for(
        self, scene: Scene, core_name: str | None = None, params: Mapping[str, Any] | None = None,
        cell_size: float | None = None,
    ) -> tuple[Core, CoreParams, str]:
        """``resolve`` for a loaded scene, also accepting ``"auto"``: (core, params, why).

        ``why`` says why the core was chosen ("requested" when named). ``auto`` weighs the
        scene at ``cell_size`` metres (default: the catalogue grid's cell size for the scene,
        else ``settings.cell_size``). The auto choice's parameters start from
        ``settings.core_params`` only when it lands on ``settings.core``.
        """
        name = core_name or self.settings.core
        if name != AUTO_CORE:
            core, p = self.resolve(name, params)
            return core, p, "requested" if core_name else "server default"
        if cell_size is None:
            cell_size = self.cell_size_of(scene)
        picked = self._calibrated_choice(scene, cell_size)
        if picked is not None:
            trial, why = picked
            core, p = self.resolve(trial.core, {**trial.params, **(params or {})})
            return core, p, why
        chosen, why = choose_core(scene, cell_size)
        core, p = self.resolve(chosen, params)
        if self.settings.calibrate:
            why += "; calibration under way: the cores' declared fits decide until it is done"
        return core, p, why

    # ----------------------------------------------------------------------------- calibration
    def calibration(self, scene: Scene, cell_size: float, wait: bool = False,
                    progress: Callable[[str], None] | None = None) -> Calibration | None:
        """The calibration of ``scene`` at ``cell_size`` metres (``visibility.calibration``),
        from memory or ``settings.cache_dir``; else one is started in the background (None
        until it is done) or, with ``wait``, measured now. None when ``settings.calibrate`` is
        off (and not ``wait``)."""
        key = (scene.name, float(cell_size))
        with self._lock:
            if key in self.calibrations:
                cal = self.calibrations[key]
                if cal is not None or not wait:
                    return cal
            elif not self.settings.calibrate and not wait:
                return None
            else:
                self.calibrations[key] = None
        if wait:
            return self._calibrate(scene, float(cell_size), progress)
        threading.Thread(target=self._calibrate, args=(scene, float(cell_size), None),
                         name=f"pvs-calibrate-{scene.name}", daemon=True).start()
        return None

    def _calibrate(self, scene: Scene, cell_size: float,
                   progress: Callable[[str], None] | None) -> Calibration | None:
        from visibility.calibration import calibrate, load_calibration, save_calibration
        from visibility.scene import scene_fingerprint

        key = (scene.name, cell_size)
        folder = self.settings.cache_dir
        try:
            cal = None
            if folder is not None:
                cal = load_calibration(folder, scene_fingerprint(scene), cell_size)
            if cal is None:
                log.info("calibrating auto on %s at %g m cells (at most %g s)", scene.name,
                         cell_size, self.settings.calibration_seconds)
                cal = calibrate(scene, cell_size, budget_seconds=self.settings.auto_budget,
                                time_limit=self.settings.calibration_seconds,
                                progress=progress)
                if folder is not None:
                    save_calibration(folder, cal)
                log.info("calibrated auto on %s in %.1f s", scene.name, cal.seconds)
        except Exception:
            log.exception("calibration of %s failed: auto keeps the declared fits", scene.name)
            with self._lock:
                self.calibrations.pop(key, None)
            return None
        with self._lock:
            self.calibrations[key] = cal
        return cal

    def _calibrated_choice(self, scene: Scene, cell_size: float) -> tuple[Any, str] | None:
        """``visibility.calibration.choose`` on the scene's calibration (starting one when
        there is none yet), among the cores that fit; None while there is none."""
        from visibility.calibration import choose

        cal = self.calibration(scene, cell_size)
        if cal is None:
            return None

        def allowed(name: str) -> bool:
            try:
                return core_fits(resolve_core(name), scene, cell_size)[0]
            except UnknownCoreError:  # measured, then unregistered
                return False

        return choose(cal, self.settings.auto_budget, allowed=allowed)

    @staticmethod
    def key(scene: str, core: Core, params: CoreParams, cell: int) -> tuple:
        """The in-memory cache key of a grid cell's PVS (for ``cache.pin``): (scene name, cell,
        core name, parameters). Names suffice in memory: a process serves one grid per scene."""
        return (scene, int(cell), core.name, params.cache_key())

    @staticmethod
    def disk_key(loaded: LoadedScene, core: Core, params: CoreParams, box: np.ndarray) -> tuple:
        """The on-disk cache key of a region's PVS: (scene fingerprint, the region's box corners
        in metres, core name, parameters). Keys survive restarts, so they name the geometry and
        the box itself, never a scene name or cell id whose meaning a restart may change
        (another cell size, an edited scene file, another generated size)."""
        corners = tuple(float(x) for x in np.asarray(box, dtype=np.float64).ravel())
        return (loaded.fingerprint, corners, core.name, params.cache_key())

    @staticmethod
    def redis_key(loaded: LoadedScene, core: Core, params: CoreParams, cell: int) -> str:
        """The shared-cache key of a grid cell's PVS (``server.redis_codec.pvs_key``: scene
        content hash, core, parameters, cell and its box, format version)."""
        return pvs_key(loaded.fingerprint, core.name, params.cache_key(), cell,
                       loaded.grid.boxes[int(cell)])

    def cache_state(self) -> dict[str, Any]:
        """Which cache tiers serve and whether the shared one is up (``/health``'s
        ``cache``): ``{"backend": "redis", "up": ..., ...}`` or ``{"backend": "disk", "up":
        true, "disk": bool}``."""
        if self.redis is not None:
            return {**self.redis.link.state(), "disk": self.disk is not None}
        return {"backend": "disk", "up": True, "disk": self.disk is not None}

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
    ) -> Future:
        """A future of the ``PVSResult`` for a grid cell (``cell``), an ad-hoc ``box`` (2, 3) or
        a ``segment`` (2, 3) [p, q] (metres; ``Core.compute_segment``, exact for cores that
        solve segments natively).

        ``priority``: lower runs first (0: a walker needs it now; prefetch uses larger values).
        ``wanted``: for prefetch, asked when a worker is about to start the job; False cancels
        it (the future is then cancelled). Joining an in-flight job with a lower priority
        promotes it. ``deadline``: seconds this computation may take from now, capped by
        ``settings.compute_deadline``; past it the future raises ``ComputationCancelled``.

        Admission (``server.admission``) applies to new computations only (a cached answer or
        an identical computation under way is always given): ``OverLimit`` when the core's
        estimate exceeds ``max_compute_bytes`` or the deadline; ``TooManyInFlight`` when
        ``client`` (an HTTP client's address; None: not counted) is at its cap; ``Busy`` when
        the queue is full, except for a walker's current cell (priority 0 without ``client``).
        Every caller that gets a future without ``wanted`` should ``release`` it when it stops
        waiting before it is done: the last one to go cancels the computation. ``lane``:
        "first" runs a new computation on the first answers' worker (``first_answer``).
        Raises UnknownSceneError at once for names outside the catalogue; the future raises
        UnknownCellError, UnsupportedSceneError, SceneLoadFailed or the core's errors.
        """
        self.catalog.require(scene)
        if sum(x is not None for x in (cell, box, segment)) != 1:
            raise ValueError("give exactly one of cell, box and segment")
        if segment is not None:
            segment = np.asarray(segment, dtype=np.float64).reshape(2, 3)
            if not np.all(np.isfinite(segment)):
                raise ValueError("segment end points must be finite")
            box = np.stack([segment.min(axis=0), segment.max(axis=0)])
            where: Hashable = ("segment", *segment.ravel().tolist())
        elif box is not None:
            box = Viewcell(box).box
            where = ("box", *box.ravel().tolist())
        else:
            where = int(cell)
        key = (scene, where, core.name, params.cache_key())
        with self._lock:
            pvs = self.cache.get(key)
            fut = None if pvs is not None else self._inflight.get(key)
            if fut is not None and fut.cancelled():
                self._inflight.pop(key, None)
                fut = None
            if pvs is None and fut is None:
                limit = self.settings.compute_deadline
                budget = limit if deadline is None else min(limit, deadline)
                pool = self.first_pool if lane == "first" and self.first_pool else self.pool
                cost = self._admit(scene, core, params, cell, box, budget, priority, client,
                                   pool)
                token = CancelToken.after(budget)
                model = float(cost.detail.get("model_seconds", cost.seconds))
                executor = self._here if pool is self.first_pool else self.executor
                job: dict[str, Any] = {"priority": priority}
                args = (self._run, key, scene, core, params, cell, box, segment, token, model,
                        executor, job)
                if isinstance(pool, PriorityWorkerPool):
                    fut = pool.submit(
                        *args, priority=priority, wanted=wanted, seconds=cost.seconds,
                        heavy=cost.seconds > self.settings.heavy_seconds)
                    # The executor reads the priority when the job starts: a promoted job
                    # (a walker reached a prefetched cell) goes to a cluster at its new rank.
                    job["pool_job"] = getattr(fut, "job", None)
                else:
                    fut = pool.submit(*args)
                if client is not None:
                    fut.add_done_callback(lambda f, c=client: self.admission.release(c))
                if not fut.done():
                    self._tokens[fut] = token
                    if wanted is None:
                        self._waiters[fut] = 1
                    # Forgotten only when the caller's future is done: a job retried after its
                    # worker died keeps this future, so identical requests keep joining it.
                    self._inflight[key] = fut
                    fut.add_done_callback(lambda f, k=key: self._forget(k, f))
                return fut
            if fut is not None:
                self.shared += 1
                if wanted is None:
                    self._waiters[fut] = self._waiters.get(fut, 0) + 1
                    if isinstance(self.pool, PriorityWorkerPool):
                        self.pool.promote(fut, priority)
                return fut
        done: Future = Future()
        ready_box = box if box is not None else self._cell_box(scene, int(cell))
        done.set_result(PVSResult(scene, cell, ready_box, core.name, params, pvs, True))
        return done

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
        with self._lock:
            n = self._waiters.get(fut)
            if n is None:
                return False
            if n > 1:
                self._waiters[fut] = n - 1
                return False
            del self._waiters[fut]
            if fut.done():
                return False
            key = next((k for k, f in self._inflight.items() if f is fut), None)
            token = self._tokens.get(fut)
        if key is not None and self.still_wanted is not None and self.still_wanted(key):
            return False
        with self._lock:
            self.abandoned += 1
        log.info("PVS %s: cancelled, %s", key, reason)
        if not fut.cancel() and token is not None:
            token.cancel(reason)
        return True

    def first_core(self) -> tuple[Core, CoreParams]:
        """The core and parameters of first answers (``settings.first_core``,
        ``first_params``); raises UnknownCoreError, ValueError for bad settings."""
        if self._first is None:
            core = resolve_core(self.settings.first_core)
            self._first = core, coerce_params(core, self.settings.first_params)
        return self._first

    def first_answer(self, scene: str, cell: int, priority: float = 0.0) -> Future:
        """A future of the cheap first answer for a walker's cell (``first_core``), run on the
        first answers' worker (lowest ``priority`` first: 0 for the cell a walker stands in);
        cached like any PVS."""
        core, params = self.first_core()
        return self.submit(scene, core, params, cell=cell, priority=priority, lane="first")

    def _admit(self, scene: str, core: Core, params: CoreParams, cell: int | None,
               box: np.ndarray | None, deadline: float, priority: float,
               client: Hashable | None, pool: WorkerPool | None = None) -> Cost:
        """The cost estimate of a new computation, after the admission checks
        (``server.admission``; raises its ``Refused`` errors). Called with the lock held.
        ``pool``: the one it will run on (default the main pool)."""
        adm = self.admission
        cost = Cost(0.0, 0)
        if self.catalog.is_loaded(scene):
            loaded = self.catalog.get(scene)
            try:
                viewcell = loaded.grid.cell(cell) if cell is not None else Viewcell(box)
            except IndexError:
                raise UnknownCellError(f"scene {scene!r} has no cell {cell} (cells "
                                       f"0..{len(loaded.grid) - 1})") from None
            cost = adm.estimate(core, loaded.scene, viewcell, params, scene)
        adm.check_limits(cost, deadline, core.name)
        pool = pool or self.pool
        pool = pool if isinstance(pool, PriorityWorkerPool) else None
        ahead = pool.queued_seconds() if pool is not None else 0.0
        if pool is not None and (priority > 0 or client is not None):
            adm.check_queue(pool.queued(), ahead)
        adm.acquire(client, ahead)
        return cost

    def _forget(self, key: Hashable, fut: Future) -> None:
        with self._lock:
            if self._inflight.get(key) is fut:
                del self._inflight[key]
            self._tokens.pop(fut, None)
            self._waiters.pop(fut, None)

    def cancel_all(self, reason: str = "server shutting down") -> int:
        """Cancel every queued and running computation (each stops at its core's next
        checkpoint); the number cancelled."""
        with self._lock:
            tokens = list(self._tokens.values())
        for t in tokens:
            t.cancel(reason)
        return len(tokens)

    def cell_size_of(self, scene: Scene) -> float:
        """The viewcell size (metres) the catalogue gives ``scene`` (``SceneCatalog``'s rule,
        ``Settings.cell_size_for``)."""
        return self.settings.cell_size_for(scene.meta.get("cell_size"))

    def _cell_box(self, scene: str, cell: int) -> np.ndarray:
        return self.catalog.get(scene).grid.boxes[cell].copy()

    def _run(
        self,
        key: Hashable,
        scene: str,
        core: Core,
        params: CoreParams,
        cell: int | None,
        box: np.ndarray | None,
        segment: np.ndarray | None = None,
        token: CancelToken | None = None,
        model_seconds: float = 0.0,
        executor: Executor | None = None,
        job: dict[str, Any] | None = None,
    ) -> PVSResult:
        try:
            loaded = self.catalog.get(scene)
            if cell is not None:
                try:
                    viewcell = loaded.grid.cell(cell)
                except IndexError:
                    raise UnknownCellError(
                        f"scene {scene!r} has no cell {cell} (cells 0..{len(loaded.grid) - 1})"
                    ) from None
            else:
                viewcell = Viewcell(box)
            ok, why = core_fits(core, loaded.scene, float(loaded.grid.cell_size))
            if not ok:
                raise UnsupportedSceneError(f"core {core.name!r} does not fit {scene!r}: {why}")
            dkey = rkey = None
            if self.disk is not None and cell is not None:
                dkey = self.disk_key(loaded, core, params, viewcell.box)
            if self.redis is not None and cell is not None:
                rkey = self.redis_key(loaded, core, params, cell)
            n = loaded.scene.n_triangles
            # Memory missed (``submit``): the shared tier first, then this machine's disk.
            pvs = self.redis.get_pvs(rkey, n) if rkey is not None else None
            if pvs is None and dkey is not None:
                pvs = self.disk.get(dkey, n_triangles=n)
                if pvs is not None and rkey is not None:
                    self.redis.put_pvs(rkey, pvs, n)  # the other replicas' gain
            if pvs is not None:
                self.cache.put(key, pvs)
                return PVSResult(scene, cell, viewcell.box.copy(), core.name, params, pvs, True)
            t0 = time.perf_counter()
            pool_job = (job or {}).get("pool_job")
            priority = pool_job.priority if pool_job is not None else (job or {}).get(
                "priority", 0.0)
            pvs = (executor or self.executor).compute(
                loaded, core, params, cell=None if segment is not None else viewcell,
                segment=segment, token=token, priority=priority)
            seconds = time.perf_counter() - t0
            # The core's own time: a remote round trip must not teach the cost model that
            # this machine is slower.
            self.admission.observe(scene, core.name, model_seconds, pvs.seconds or seconds)
            log.debug("PVS %s cell=%s core=%s: %d triangles in %.3f s", scene, cell, core.name,
                      len(pvs), seconds)
            self.cache.put(key, pvs)
            if dkey is not None:
                self.disk.put(dkey, pvs, n_triangles=n)
            if rkey is not None:
                self.redis.put_pvs(rkey, pvs, n)
            with self._lock:
                self.computed += 1
            if self.on_computed is not None:
                self.on_computed(seconds)
            return PVSResult(scene, cell, viewcell.box.copy(), core.name, params, pvs, False)
        except (UnknownSceneError, UnknownCellError, UnsupportedSceneError):
            raise
        except ComputationCancelled as exc:
            with self._lock:
                self.cancelled += 1
            log.warning("PVS %s cell=%s core=%s stopped: %s", scene, cell, core.name, exc)
            raise
        except Exception:
            with self._lock:
                self.failed += 1
            raise

    def stats(self) -> dict[str, Any]:
        """Cache statistics plus computations done, failed, shared and in flight."""
        with self._lock:
            inflight = len(self._inflight)
        out = {"cache": self.cache.stats(), "computed": self.computed, "failed": self.failed,
               "cancelled": self.cancelled, "abandoned": self.abandoned,
               "shared": self.shared, "inflight": inflight,
               "workers": getattr(self.pool, "workers", None),
               "admission": self.admission.stats(), "executor": self.executor.state()}
        if isinstance(self.pool, PriorityWorkerPool):
            out["pool"] = {"retried": self.pool.retried, "replaced": self.pool.replaced,
                           "skipped": self.pool.skipped, "queued": self.pool.queued(),
                           "queued_seconds": round(self.pool.queued_seconds(), 3),
                           "heavy_running": self.pool.heavy_running(),
                           "heavy_workers": self.pool.heavy_workers}
        if self.disk is not None:
            out["disk"] = self.disk.stats()
        if self.redis is not None:
            out["redis"] = self.redis.stats()
        return out

    def shutdown(self) -> None:
        """Stop the pool, dropping queued work; running computations stop at their cores'
        next checkpoint."""
        self.cancel_all()
        self.pool.shutdown(wait=False, cancel_futures=True)
        if self.first_pool is not None:
            self.first_pool.shutdown(wait=False, cancel_futures=True)
        self.executor.close()
        if self.redis is not None:
            self.redis.close()


# --------------------------------------------------------------------------- auto core
# What fits and what ``auto`` picks is the cores' own declaration (``Core.fit``,
# ``visibility.cores.base.choose_core``); these wrappers give the server's error types.


def core_fits(core: Core, scene: Scene, cell_size: float | None = None) -> tuple[bool, str]:
    """Whether ``core`` may be used on ``scene`` and why not (``Core.fit``)."""
    fit = core.fit(scene, cell_size)
    return fit.ok, fit.why


def offered_cores(scene: Scene, cell_size: float | None = None) -> list[str]:
    """Registered cores that fit ``scene`` (``Core.fit``), sorted."""
    return sorted(n for n, f in registry_fits(scene, cell_size).items() if f.ok)


def choose_core(scene: Scene, cell_size: float | None = None) -> tuple[str, str]:
    """The ``auto`` core for ``scene`` at ``cell_size`` metres and why: the best-scoring core
    that fits (``visibility.cores.base.choose_core``). UnknownCoreError when none fits."""
    try:
        return registry_choose_core(scene, cell_size)
    except LookupError as exc:
        raise UnknownCoreError(str(exc)) from None
