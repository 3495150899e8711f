"""PVS computation off the event loop: a worker pool, a byte-bounded LRU cache, shared in-flight
requests.

``ComputeService.submit`` answers from the cache when it can, joins an identical computation that
is already running, or starts one on the pool. The pool sits behind ``WorkerPool`` (anything with
``submit``/``shutdown`` like ``concurrent.futures`` executors) so a process pool can replace the
thread pool later; threads suffice now because the numba kernels release the GIL.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import heapq
import io
import logging
import os
import threading
import time
import typing
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from pydantic import ConfigDict, TypeAdapter, ValidationError

from server.catalog import SceneCatalog, UnknownSceneError
from server.settings import Settings
from visibility.cores.base import PVS, Core, CoreParams, available_cores, get_core
from visibility.scene import Scene
from visibility.viewcells import Viewcell

log = logging.getLogger(__name__)


class UnknownCoreError(LookupError):
    """No core registered under this name."""


class UnknownCellError(LookupError):
    """A cell id outside the scene's grid."""


class UnsupportedSceneError(ValueError):
    """The core does not fit the scene (``Core.supports`` said no)."""


# --------------------------------------------------------------------------- pool
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


class WorkerDied(BaseException):
    """Raised inside a job to simulate (or signal) the death of the worker thread running it."""


@dataclass(eq=False)
class _Job:
    fn: Callable[..., Any]
    args: tuple
    future: Future
    priority: float
    wanted: Callable[[], bool] | None = None
    attempts: int = 0
    started: bool = False


class PriorityWorkerPool:
    """``workers`` threads taking jobs lowest ``priority`` first (FIFO among equals).

    A job whose ``wanted()`` says False when a worker picks it is cancelled unrun (prefetch work
    no walker is heading for any more); ``promote`` moves a queued job forward. A job that raises
    an unexpected ``Exception`` is retried once; a worker killed by a ``BaseException``
    (``WorkerDied``, ``SystemExit``...) is replaced by a fresh thread and its job retried once.
    ``retry_exempt`` names exception types that are answers, not faults (never retried).
    """

    def __init__(self, workers: int, retry_exempt: tuple[type[BaseException], ...] = ()) -> None:
        self.workers = int(workers)
        self.retry_exempt = retry_exempt
        self._cv = threading.Condition()
        self._heap: list[tuple[float, int, _Job]] = []
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
               wanted: Callable[[], bool] | None = None) -> Future:
        """Queue ``fn(*args)``; its future (``job`` attribute: the handle for ``promote``)."""
        fut: Future = Future()
        job = _Job(fn, args, fut, float(priority), wanted)
        fut.job = job  # type: ignore[attr-defined]
        self._push(job)
        return fut

    def _push(self, job: _Job) -> None:
        with self._cv:
            if self._stop:
                job.future.cancel()
                return
            heapq.heappush(self._heap, (job.priority, self._count, job))
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
            heapq.heappush(self._heap, (priority, self._count, job))
            self._count += 1
            self._cv.notify()

    def queued(self) -> int:
        with self._cv:
            return sum(1 for _, _, j in self._heap if not j.started)

    def _next(self) -> _Job | None:
        with self._cv:
            while True:
                while not self._heap and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return None
                _, _, job = heapq.heappop(self._heap)
                if job.started or job.future.done():
                    continue
                if job.wanted is not None and not job.wanted():
                    self.skipped += 1
                    job.future.cancel()
                    continue
                job.started = True
                return job

    def _worker(self) -> None:
        while True:
            job = self._next()
            if job is None:
                return
            if not job.future.set_running_or_notify_cancel():
                continue
            try:
                result = job.fn(*job.args)
            except self.retry_exempt as exc:
                job.future.set_exception(exc)
            except Exception as exc:
                if not self._retry(job, exc):
                    job.future.set_exception(exc)
            except BaseException as exc:
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
                job.future.set_result(result)

    def _retry(self, job: _Job, exc: BaseException) -> bool:
        if job.attempts >= 1 or self._stop:
            return False
        log.warning("job %s failed (%r); retrying once", getattr(job.fn, "__name__", job.fn),
                    exc)
        with self._cv:
            self.retried += 1
        # A fresh future keeps the caller's: chain the retry's outcome into it.
        fut = job.future
        retry = _Job(job.fn, job.args, Future(), job.priority, None, job.attempts + 1)
        retry.future = _ChainedFuture(fut)
        self._push(retry)
        return True

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._cv:
            self._stop = True
            if cancel_futures:
                for _, _, job in self._heap:
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
        return False

    def set_running_or_notify_cancel(self) -> bool:
        return not self._target.done()

    def set_result(self, result: Any) -> None:
        if not self._target.done():
            self._target.set_result(result)

    def set_exception(self, exc: BaseException) -> None:
        if not self._target.done():
            self._target.set_exception(exc)


# --------------------------------------------------------------------------- cache
def pvs_nbytes(pvs: PVS) -> int:
    """Approximate memory held by a PVS (its arrays plus a fixed overhead), bytes."""
    n = 512 + pvs.triangle_ids.nbytes
    for arr in (pvs.object_ids, pvs.sphere_ids):
        if arr is not None:
            n += arr.nbytes
    for v in pvs.stats.values():
        n += v.nbytes if isinstance(v, np.ndarray) else 64
    return int(n)


class PVSCache:
    """A thread-safe LRU map from keys to PVS, bounded by the PVS' total ``pvs_nbytes``.

    An entry larger than the whole bound is not stored. Pinned keys (``pin``; a count per key,
    e.g. one per walker standing in the cell) are never evicted, so the bound may be exceeded
    while pins hold entries; eviction catches up on ``unpin``.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._data: OrderedDict[Hashable, tuple[PVS, int]] = OrderedDict()
        self._lock = threading.Lock()
        self._pins: dict[Hashable, int] = {}
        self.nbytes = 0
        self.hits = 0
        self.misses = 0
        self.evictions = 0

    def get(self, key: Hashable) -> PVS | None:
        """The cached PVS (now the most recently used) or None."""
        with self._lock:
            item = self._data.get(key)
            if item is None:
                self.misses += 1
                return None
            self._data.move_to_end(key)
            self.hits += 1
            return item[0]

    def put(self, key: Hashable, pvs: PVS) -> None:
        """Store ``pvs``, evicting least recently used unpinned entries to stay within
        ``max_bytes``."""
        size = pvs_nbytes(pvs)
        with self._lock:
            old = self._data.pop(key, None)
            if old is not None:
                self.nbytes -= old[1]
            if size > self.max_bytes and key not in self._pins:
                return
            self._data[key] = (pvs, size)
            self.nbytes += size
            self._evict()

    def _evict(self) -> None:
        if self.nbytes <= self.max_bytes:
            return
        for k in [k for k in self._data if k not in self._pins]:
            if self.nbytes <= self.max_bytes:
                break
            _, s = self._data.pop(k)
            self.nbytes -= s
            self.evictions += 1

    def pin(self, key: Hashable) -> None:
        """Keep ``key`` (now or once stored) from eviction until as many ``unpin`` calls."""
        with self._lock:
            self._pins[key] = self._pins.get(key, 0) + 1

    def unpin(self, key: Hashable) -> None:
        """Undo one ``pin``; unknown keys are ignored."""
        with self._lock:
            n = self._pins.get(key, 0) - 1
            if n > 0:
                self._pins[key] = n
            else:
                self._pins.pop(key, None)
                self._evict()

    def pinned(self) -> int:
        with self._lock:
            return len(self._pins)

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._data

    def clear(self) -> None:
        with self._lock:
            self._data.clear()
            self.nbytes = 0

    def __len__(self) -> int:
        return len(self._data)

    def stats(self) -> dict[str, int]:
        """Entries, bytes, bound, hits, misses, evictions, pinned keys."""
        with self._lock:
            return {"entries": len(self._data), "bytes": self.nbytes, "max_bytes": self.max_bytes,
                    "hits": self.hits, "misses": self.misses, "evictions": self.evictions,
                    "pinned": len(self._pins)}


class DiskPVSCache:
    """PVS as ``.npz`` files under ``folder`` (one per key), surviving restarts.

    File name: ``<scene>/<sha256 of repr(key)>.npz`` holding the ids, granularity, seconds and the
    key's ``repr`` (checked on load, so a hash collision or a foreign file is a miss). Files that
    cannot be read (truncated, corrupt, wrong content) are ignored (and removed). Writes go to a
    temporary file renamed into place, so a crash never leaves a half file under a real name.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.hits = 0
        self.misses = 0
        self.corrupt = 0
        self.writes = 0

    def path(self, key: tuple) -> Path:
        digest = hashlib.sha256(repr(key).encode()).hexdigest()[:40]
        scene = hashlib.sha256(str(key[0]).encode()).hexdigest()[:16]
        return self.folder / scene / f"{digest}.npz"

    def get(self, key: tuple) -> PVS | None:
        """The stored PVS of ``key`` or None (missing or unreadable file)."""
        p = self.path(key)
        if not p.is_file():
            self.misses += 1
            return None
        try:
            with np.load(p, allow_pickle=False) as z:
                if str(z["key"]) != repr(key):
                    raise ValueError("key mismatch")
                ids = z["triangle_ids"].astype(np.int32)
                obj = z["object_ids"].astype(np.int32) if int(z["has_objects"]) else None
                sph = z["sphere_ids"].astype(np.int32) if int(z["has_spheres"]) else None
                pvs = PVS(ids, granularity=str(z["granularity"]), object_ids=obj,
                          sphere_ids=sph, stats={"seconds": float(z["seconds"]), "disk": True})
        except Exception as exc:  # any unreadable file is a miss, never an error
            log.warning("ignoring unreadable PVS cache file %s: %s", p, exc)
            self.corrupt += 1
            self.misses += 1
            try:
                p.unlink()
            except OSError:
                pass
            return None
        self.hits += 1
        return pvs

    def put(self, key: tuple, pvs: PVS) -> None:
        """Store ``pvs`` under ``key`` (errors are logged, never raised)."""
        p = self.path(key)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            buf = io.BytesIO()
            empty = np.zeros(0, np.int32)
            np.savez(buf, key=np.array(repr(key)), triangle_ids=pvs.triangle_ids,
                     granularity=np.array(pvs.granularity), seconds=np.array(pvs.seconds),
                     has_objects=np.array(pvs.object_ids is not None),
                     object_ids=pvs.object_ids if pvs.object_ids is not None else empty,
                     has_spheres=np.array(pvs.sphere_ids is not None),
                     sphere_ids=pvs.sphere_ids if pvs.sphere_ids is not None else empty)
            tmp = p.with_name(f".{p.name}.{os.getpid()}.{threading.get_ident()}.tmp")
            tmp.write_bytes(buf.getvalue())
            os.replace(tmp, p)
            self.writes += 1
        except OSError as exc:
            log.warning("could not write PVS cache file %s: %s", p, exc)

    def stats(self) -> dict[str, Any]:
        return {"folder": str(self.folder), "hits": self.hits, "misses": self.misses,
                "corrupt": self.corrupt, "writes": self.writes}


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
    """PVS requests for catalogue scenes: cache, shared in-flight work, a worker pool."""

    def __init__(
        self, catalog: SceneCatalog, settings: Settings, pool: WorkerPool | None = None
    ) -> None:
        self.catalog = catalog
        self.settings = settings
        self.pool = pool or PriorityWorkerPool(
            settings.workers, retry_exempt=(UnknownSceneError, UnknownCellError,
                                            UnsupportedSceneError))
        self.cache = PVSCache(settings.cache_bytes)
        self.disk = DiskPVSCache(settings.cache_dir) if settings.cache_dir is not None else None
        #: Called with the seconds of every finished computation (metrics hook).
        self.on_computed: Callable[[float], None] | None = None
        # Re-entrant: a pool that runs work inline would re-enter from _run.
        self._lock = threading.RLock()
        self._inflight: dict[Hashable, Future] = {}
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
        self, scene: Scene, core_name: str | None = None, params: Mapping[str, Any] | None = None
    ) -> tuple[Core, CoreParams, str]:
        """``resolve`` for a loaded scene, also accepting ``"auto"``: (core, params, why).

        ``why`` says why the core was chosen ("requested" when named). The auto choice's
        parameters start from ``settings.core_params`` only when it lands on ``settings.core``.
        """
        name = core_name or self.settings.core
        if name != AUTO_CORE:
            core, p = self.resolve(name, params)
            return core, p, "requested" if core_name else "server default"
        chosen, why = choose_core(scene)
        core, p = self.resolve(chosen, params)
        return core, p, why

    @staticmethod
    def key(scene: str, core: Core, params: CoreParams, cell: int) -> tuple:
        """The cache key of a grid cell's PVS (for ``cache.pin``)."""
        return (scene, int(cell), core.name, params.cache_key())

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
    ) -> Future:
        """A future of the ``PVSResult`` for a grid cell (``cell``), an ad-hoc ``box`` (2, 3) or
        a ``segment`` (2, 3) [p, q] (metres; ``Core.compute_segment``, exact for cores that
        solve segments natively).

        ``priority``: lower runs first (0: a walker needs it now; prefetch uses larger values).
        ``wanted``: for prefetch, asked when a worker is about to start the job; False cancels
        it (the future is then cancelled). Joining an in-flight job with a lower priority
        promotes it. Raises UnknownSceneError at once for names outside the catalogue; the
        future raises UnknownCellError, UnsupportedSceneError, SceneLoadFailed or the core's
        errors.
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
                if isinstance(self.pool, PriorityWorkerPool):
                    fut = self.pool.submit(self._run, key, scene, core, params, cell, box,
                                           segment, priority=priority, wanted=wanted)
                else:
                    fut = self.pool.submit(self._run, key, scene, core, params, cell, box,
                                           segment)
                if not fut.done():
                    self._inflight[key] = fut
                    fut.add_done_callback(lambda f, k=key: f.cancelled() and self._forget(k, f))
                return fut
            if fut is not None:
                self.shared += 1
                if wanted is None and isinstance(self.pool, PriorityWorkerPool):
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
    ) -> PVSResult:
        """``submit`` awaited from the event loop. Cancelling the caller does not cancel the
        computation (another request may share it; its result lands in the cache)."""
        fut = self.submit(scene, core, params, cell, box, segment=segment)
        inner = asyncio.wrap_future(fut)
        # When the caller is gone, retrieve the outcome anyway so asyncio does not log it.
        inner.add_done_callback(lambda f: f.cancelled() or f.exception())
        return await asyncio.shield(inner)

    def _forget(self, key: Hashable, fut: Future) -> None:
        with self._lock:
            if self._inflight.get(key) is fut:
                del self._inflight[key]

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
            ok, why = core_fits(core, loaded.scene)
            if not ok:
                raise UnsupportedSceneError(f"core {core.name!r} does not fit {scene!r}: {why}")
            pvs = self.disk.get(key) if self.disk is not None and cell is not None else None
            if pvs is not None:
                self.cache.put(key, pvs)
                return PVSResult(scene, cell, viewcell.box.copy(), core.name, params, pvs, True)
            t0 = time.perf_counter()
            if segment is not None:
                pvs = core.compute_segment(loaded.scene, segment[0], segment[1], params)
            else:
                pvs = core.compute(loaded.scene, viewcell, params)
            seconds = time.perf_counter() - t0
            log.debug("PVS %s cell=%s core=%s: %d triangles in %.3f s", scene, cell, core.name,
                      len(pvs), seconds)
            self.cache.put(key, pvs)
            if self.disk is not None and cell is not None:
                self.disk.put(key, pvs)
            with self._lock:
                self.computed += 1
            if self.on_computed is not None:
                self.on_computed(seconds)
            return PVSResult(scene, cell, viewcell.box.copy(), core.name, params, pvs, False)
        except (UnknownSceneError, UnknownCellError, UnsupportedSceneError):
            raise
        except Exception:
            with self._lock:
                self.failed += 1
            raise
        finally:
            with self._lock:
                self._inflight.pop(key, None)

    def stats(self) -> dict[str, Any]:
        """Cache statistics plus computations done, failed, shared and in flight."""
        with self._lock:
            inflight = len(self._inflight)
        out = {"cache": self.cache.stats(), "computed": self.computed, "failed": self.failed,
               "shared": self.shared, "inflight": inflight,
               "workers": getattr(self.pool, "workers", None)}
        if isinstance(self.pool, PriorityWorkerPool):
            out["pool"] = {"retried": self.pool.retried, "replaced": self.pool.replaced,
                           "skipped": self.pool.skipped, "queued": self.pool.queued()}
        if self.disk is not None:
            out["disk"] = self.disk.stats()
        return out

    def shutdown(self) -> None:
        """Stop the pool, dropping queued work (running computations finish)."""
        self.pool.shutdown(wait=False, cancel_futures=True)


# --------------------------------------------------------------------------- auto core
#: The core name that asks the server to pick a core per scene.
AUTO_CORE = "auto"


def core_fits(core: Core, scene: Scene) -> tuple[bool, str]:
    """Whether ``core`` may be used on ``scene`` and why not: ``core.supports`` plus the rule
    that 2.5D-only cores (``requires_2_5d``) fit only scenes with ``meta["is_2_5d"]``."""
    if core.requires_2_5d and not scene.meta.get("is_2_5d"):
        return False, "this core needs a 2.5D scene (scene.meta['is_2_5d'])"
    try:
        return core.supports(scene)
    except Exception as exc:  # a core's own check must not take a request down
        return False, f"supports() failed: {type(exc).__name__}: {exc}"


def offered_cores(scene: Scene) -> list[str]:
    """Registered cores that fit ``scene`` (``supports``; 2.5D-only cores only for scenes with
    ``meta["is_2_5d"]``)."""
    out = []
    for name in available_cores():
        try:
            core = get_core(name)
        except KeyError:
            continue
        if core_fits(core, scene)[0]:
            out.append(name)
    return out


def choose_core(scene: Scene) -> tuple[str, str]:
    """The ``auto`` core for ``scene`` and why: a 2.5D core for 2.5D scenes, ``from_segment``
    (exact, continuous) for static scenes, else ``sampling``; else the first core that fits.
    Raises UnknownCoreError when no registered core fits."""
    offered = offered_cores(scene)
    if scene.meta.get("is_2_5d"):
        for name in offered:
            if get_core(name).requires_2_5d:
                return name, "2.5D scene: a core made for heightfield-like occluders"
    static = scene.states is None
    if static and "from_segment" in offered:
        return "from_segment", "static triangle scene: exact continuous from-segment visibility"
    if "sampling" in offered:
        why = "dynamic scene" if not static else "from_segment not available for this scene"
        return "sampling", f"{why}: sampling is the general fallback"
    if offered:
        return offered[0], "the only kind of registered core that fits this scene"
    raise UnknownCoreError(f"no registered core fits scene {scene.name!r}")
