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
import logging
import threading
import time
import typing
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol

import numpy as np
from pydantic import ConfigDict, TypeAdapter, ValidationError

from server.catalog import SceneCatalog, UnknownSceneError
from server.settings import Settings
from visibility.cores.base import PVS, Core, CoreParams, get_core
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

    An entry larger than the whole bound is not stored.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._data: OrderedDict[Hashable, tuple[PVS, int]] = OrderedDict()
        self._lock = threading.Lock()
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
        """Store ``pvs``, evicting least recently used entries to stay within ``max_bytes``."""
        size = pvs_nbytes(pvs)
        with self._lock:
            old = self._data.pop(key, None)
            if old is not None:
                self.nbytes -= old[1]
            if size > self.max_bytes:
                return
            self._data[key] = (pvs, size)
            self.nbytes += size
            while self.nbytes > self.max_bytes:
                _, (_, s) = self._data.popitem(last=False)
                self.nbytes -= s
                self.evictions += 1

    def clear(self) -> None:
        with self._lock:
            self._data.clear()
            self.nbytes = 0

    def __len__(self) -> int:
        return len(self._data)

    def stats(self) -> dict[str, int]:
        """Entries, bytes, bound, hits, misses, evictions."""
        with self._lock:
            return {"entries": len(self._data), "bytes": self.nbytes, "max_bytes": self.max_bytes,
                    "hits": self.hits, "misses": self.misses, "evictions": self.evictions}


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
        self.pool = pool or ThreadWorkerPool(settings.workers)
        self.cache = PVSCache(settings.cache_bytes)
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
        core = resolve_core(name)
        raw = dict(self.settings.core_params) if name == self.settings.core else {}
        raw.update(params or {})
        return core, coerce_params(core, raw)

    def submit(
        self,
        scene: str,
        core: Core,
        params: CoreParams,
        cell: int | None = None,
        box: np.ndarray | None = None,
    ) -> Future:
        """A future of the ``PVSResult`` for a grid cell (``cell``) or an ad-hoc ``box`` (2, 3).

        Raises UnknownSceneError at once for names outside the catalogue; the future raises
        UnknownCellError, UnsupportedSceneError, SceneLoadFailed or the core's errors.
        """
        self.catalog.require(scene)
        if (cell is None) == (box is None):
            raise ValueError("give exactly one of cell and box")
        if box is not None:
            box = Viewcell(box).box
            where: Hashable = ("box", *box.ravel().tolist())
        else:
            where = int(cell)
        key = (scene, where, core.name, params.cache_key())
        with self._lock:
            pvs = self.cache.get(key)
            fut = None if pvs is not None else self._inflight.get(key)
            if pvs is None and fut is None:
                fut = self.pool.submit(self._run, key, scene, core, params, cell, box)
                if not fut.done():
                    self._inflight[key] = fut
                return fut
            if fut is not None:
                self.shared += 1
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
    ) -> PVSResult:
        """``submit`` awaited from the event loop. Cancelling the caller does not cancel the
        computation (another request may share it; its result lands in the cache)."""
        fut = self.submit(scene, core, params, cell, box)
        inner = asyncio.wrap_future(fut)
        # When the caller is gone, retrieve the outcome anyway so asyncio does not log it.
        inner.add_done_callback(lambda f: f.cancelled() or f.exception())
        return await asyncio.shield(inner)

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
            ok, why = core.supports(loaded.scene)
            if not ok:
                raise UnsupportedSceneError(f"core {core.name!r} does not fit {scene!r}: {why}")
            t0 = time.perf_counter()
            pvs = core.compute(loaded.scene, viewcell, params)
            log.debug("PVS %s cell=%s core=%s: %d triangles in %.3f s", scene, cell, core.name,
                      len(pvs), time.perf_counter() - t0)
            self.cache.put(key, pvs)
            with self._lock:
                self.computed += 1
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
        return {"cache": self.cache.stats(), "computed": self.computed, "failed": self.failed,
                "shared": self.shared, "inflight": inflight,
                "workers": getattr(self.pool, "workers", None)}

    def shutdown(self) -> None:
        """Stop the pool, dropping queued work (running computations finish)."""
        self.pool.shutdown(wait=False, cancel_futures=True)
