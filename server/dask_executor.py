"""PVS computations on a Dask cluster (``distributed``): ``executor = "dask://host:8786"``.

What goes where
---------------
- The scene goes to the workers once per content hash: ``scatter`` with ``broadcast=True``
  under the key ``pvs-scene-<fingerprint>``, so every job refers to it instead of carrying it,
  and two servers on one cluster scattering the same geometry share one key. A worker started
  later fetches it from a peer. With ``?scenes=load`` the jobs carry a
  ``visibility.jobs.SceneSource`` instead (the scene file's path, the same on every machine,
  or the generator and size) and each worker process loads the scene once, checking its
  content hash; a worker that cannot (no such file, other content) fails the job with
  ``SceneUnavailable`` and that scene is scattered from then on (one warning line).
- A job is ``visibility.jobs.compute_within(scene, core, params, cell, segment, seconds)``; it
  returns the ``PVS`` (sorted int32 ids and the core's stats). The core travels as the
  object itself (its class by reference), so a core registered at run time in the server
  works as long as the workers can import its module.
- Priorities: ``ComputeService``'s priority pool decides what to start first (a walker's cell
  at 0, prefetch ranked after it) and this executor passes the same order to the scheduler
  (Dask runs higher ``priority`` first, so it gets the negated value): on a cluster shared by
  several servers one's walker cell goes ahead of another's prefetch.

Faults
------
- A worker that dies mid-job: the scheduler itself gives the job to another worker (a job
  survives ``distributed.scheduler.allowed-failures`` such deaths, default 3; the next fails
  it with ``KilledWorker``, the job's failure: it may be what kills them). ``retries=`` is
  deliberately not used: it re-runs jobs that *raised*, and a core's exception is its
  answer, as in the local pool (``server.pool``).
- A lost scheduler (unreachable at start, closed, network gone): one warning line, then every
  job, including those under way, runs on the local pool (at most ``workers`` at once); a new
  connection is tried every ``RECONNECT_S`` seconds, and an info line says when it is back.

Deadlines and cancellation (what differs from the local pool)
-------------------------------------------------------------
Locally a token reaches the running kernel. A Dask task cannot be interrupted, so: the server
enforces the deadline on its side (the waiting pool thread stops waiting, cancels the Dask
future and raises ``ComputationCancelled``); the job carries the seconds left, so the worker
stops at the core's next checkpoint at about the same time. A cancellation that is not a
deadline (every caller gone) cancels the Dask future: a queued job never runs; a running one
is not stopped, it runs on until done or its deadline, and its answer is dropped.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from visibility.cancel import CancelToken
from visibility.cores.base import PVS, Core, CoreParams
from visibility.jobs import SceneSource, SceneUnavailable, compute_region, compute_within
from visibility.viewcells import Viewcell

if TYPE_CHECKING:
    from distributed import Client, Future

    from server.catalog import LoadedScene

log = logging.getLogger(__name__)

#: Seconds to reach the scheduler (at start, and each reconnection attempt); also how long a
#: client that lost its scheduler keeps trying by itself before it closes.
CONNECT_TIMEOUT_S = 5.0
#: Seconds between reconnection attempts while computing locally.
RECONNECT_S = 15.0
#: Seconds between checks of a waiting job's token and of the connection.
POLL_S = 0.1
#: Seconds to fetch a finished job's answer from its worker.
GATHER_TIMEOUT_S = 60.0
#: Seconds a scatter waits for a cluster without workers to get one.
NO_WORKERS_S = 10.0


class _Lost(Exception):
    """The cluster, not the job, failed: the job runs locally instead."""


class DaskExecutor:
    """Computations on the Dask scheduler at ``address`` (``tcp://host:port``), the local pool
    standing in while it is unreachable (``local_workers`` computations at once).

    ``state()`` says which is in use (/health: ``compute.executor``), with counts of remote
    jobs, local stand-ins and losses, and the mean overhead per remote job (its round trip
    less the core's own seconds: scheduling, transfer, deserialisation).
    """

    kind = "dask"

    def __init__(self, address: str, local_workers: int, *, name: str | None = None,
                 connect_timeout: float = CONNECT_TIMEOUT_S,
                 reconnect_every: float = RECONNECT_S, load_scenes: bool = False,
                 scenes_dir: Path | None = None) -> None:
        self.address = address
        self.load_scenes = bool(load_scenes)
        self.scenes_dir = scenes_dir
        #: Fingerprints of scenes some worker could not load: scattered instead.
        self._scatter_only: set[str] = set()
        self.scattered = 0
        self.name = name or address
        self.connect_timeout = float(connect_timeout)
        self.reconnect_every = float(reconnect_every)
        self._local = threading.BoundedSemaphore(max(1, int(local_workers)))
        self._local_workers = max(1, int(local_workers))
        self._lock = threading.Lock()
        self._client: Client | None = None
        self._scenes: dict[str, Future] = {}
        self._scene_lock = threading.Lock()
        self._connected = False
        self._reconnecting = False
        self._last_try = 0.0
        self._lost_at = 0.0
        self._closed = False
        self._threads = 0
        self.remote_jobs = 0
        self.local_jobs = 0
        self.losses = 0
        self._overhead = 0.0
        self._try_connect(initial=True)

    # ----------------------------------------------------------------------------- connection
    def _try_connect(self, initial: bool = False) -> bool:
        """One attempt to reach the scheduler; True when connected. The first one, failing,
        says so in a warning; later ones only at debug level."""
        from distributed import Client

        self._last_try = time.monotonic()
        client = None
        try:
            client = Client(self.address, timeout=self.connect_timeout, set_as_default=False)
            threads = int(sum(client.nthreads().values()))
        except Exception as exc:  # OSError, TimeoutError, version mismatches...
            if client is not None:
                _close_quietly(client)
            if initial:
                with self._lock:
                    self.losses += 1
                log.warning("Dask scheduler %s unreachable (%s): computing on the local pool "
                            "until it is", self.name, _short(exc))
            else:
                log.debug("Dask scheduler %s still unreachable: %s", self.name, _short(exc))
            return False
        with self._lock:
            if self._closed:
                _close_quietly(client)
                return False
            old, self._client = self._client, client
            self._threads = threads
            self._connected = True
        with self._scene_lock:
            self._scenes.clear()
        if old is not None:
            _close_quietly(old)
        log.info("computing on the Dask cluster at %s (%d worker threads)", self.name, threads)
        return True

    def _reconnect_in_background(self) -> None:
        try:
            self._try_connect()
        finally:
            with self._lock:
                self._reconnecting = False

    def _usable(self) -> Client | None:
        """The client when the scheduler is there; else None (and a reconnection attempt is
        started when one is due)."""
        with self._lock:
            client = self._client
            if client is not None and client.status == "running":
                if not self._connected and \
                        time.monotonic() - self._lost_at < self.reconnect_every:
                    return None  # the cluster failed a job lately: not before the next try
                if not self._connected:
                    # distributed reconnected by itself (scattered data did not survive),
                    # or the cluster failed a job a while ago: try it again.
                    self._connected = True
                    reconnected = True
                else:
                    return client
            else:
                reconnected = False
                if self._connected:
                    self._mark_lost_locked(f"client {getattr(client, 'status', 'gone')}")
                due = time.monotonic() - self._last_try >= self.reconnect_every
                # A client still "connecting" is retrying by itself; a closed one will not.
                if (not self._closed and not self._reconnecting and due
                        and (client is None or client.status != "connecting")):
                    self._reconnecting = True
                    threading.Thread(target=self._reconnect_in_background, daemon=True,
                                     name="pvs-dask-reconnect").start()
                return None
        with self._scene_lock:
            self._scenes.clear()
        if reconnected:
            log.info("Dask scheduler %s is back: computing on the cluster again", self.name)
        return client

    def _mark_lost_locked(self, why: str) -> None:
        if self._connected and not self._closed:  # closing is no loss
            self._connected = False
            self._lost_at = time.monotonic()
            self.losses += 1
            log.warning("Dask cluster %s lost (%s): computing on the local pool until it is "
                        "back", self.name, why)

    def _lost(self, why: str) -> None:
        with self._lock:
            self._mark_lost_locked(why)
        with self._scene_lock:
            self._scenes.clear()

    # ----------------------------------------------------------------------------- jobs
    def _scene_arg(self, client: Client, loaded: LoadedScene) -> Future | SceneSource:
        """What a job gets for its scene: its source when the workers load scenes themselves
        and this one has a file or generator, else the scattered scene."""
        if self.load_scenes and loaded.fingerprint not in self._scatter_only:
            source = scene_source(loaded, self.scenes_dir)
            if source is not None:
                return source
        return self._scene_future(client, loaded)

    def _scene_future(self, client: Client, loaded: LoadedScene) -> Future:
        """The scattered scene (once per fingerprint while the connection lasts)."""
        fp = loaded.fingerprint
        with self._scene_lock:
            fut = self._scenes.get(fp)
            if fut is None or fut.status != "finished":
                key = f"pvs-scene-{fp}"
                fut = client.scatter({key: loaded.scene}, broadcast=True,
                                     timeout=NO_WORKERS_S)[key]
                self._scenes[fp] = fut
                self.scattered += 1
            return fut

    def compute(self, loaded: LoadedScene, core: Core, params: CoreParams, *,
                cell: Viewcell | None = None, segment: np.ndarray | None = None,
                token: CancelToken | None = None, priority: float = 0.0) -> PVS:
        """The PVS on the cluster (see the module docstring), or on the local pool while the
        scheduler is away; the job's own exceptions are raised as they are."""
        for attempt in range(3):
            client = self._usable()
            if client is None:
                break
            try:
                return self._remote(client, loaded, core, params, cell, segment, token, priority)
            except SceneUnavailable as exc:
                with self._lock:
                    first = loaded.fingerprint not in self._scatter_only
                    self._scatter_only.add(loaded.fingerprint)
                if first:
                    log.warning("a Dask worker could not load scene %s (%s): scattering it "
                                "instead", loaded.name, exc)
                continue
            except _Lost as exc:
                if client.status == "running" and attempt == 0:
                    # The scheduler is there but the job failed around it (every holder of
                    # the scene died, no worker to scatter to): scatter again, once.
                    log.warning("Dask job for %s failed on the cluster (%s); trying once more",
                                loaded.name, exc)
                    with self._scene_lock:
                        self._scenes.pop(loaded.fingerprint, None)
                    continue
                self._lost(str(exc))
                break
        return self._compute_here(loaded, core, params, cell, segment, token)

    def _compute_here(self, loaded: LoadedScene, core: Core, params: CoreParams,
                      cell: Viewcell | None, segment: np.ndarray | None,
                      token: CancelToken | None) -> PVS:
        with self._local:
            with self._lock:
                self.local_jobs += 1
            return compute_region(loaded.scene, core, params, cell, segment, token)

    def _remote(self, client: Client, loaded: LoadedScene, core: Core, params: CoreParams,
                cell: Viewcell | None, segment: np.ndarray | None, token: CancelToken | None,
                priority: float) -> PVS:
        if token is not None:
            token.check()
        seconds = None
        if token is not None and token.deadline is not None:
            seconds = max(0.0, token.deadline - time.monotonic())
        t0 = time.monotonic()
        try:
            scene = self._scene_arg(client, loaded)
            fut = client.submit(compute_within, scene, core, params, cell, segment, seconds,
                                key=f"pvs-{core.name}-{uuid.uuid4().hex}", pure=False,
                                priority=-round(1000 * float(priority)))
        except Exception as exc:  # the connection went while scattering or submitting
            raise _Lost(_short(exc)) from None
        done = threading.Event()
        fut.add_done_callback(lambda _f: done.set())
        while not done.wait(POLL_S):
            if token is not None and (token.cancelled or (
                    token.deadline is not None and time.monotonic() > token.deadline)):
                fut.cancel()
                token.check()
            if client.status != "running":
                raise _Lost(f"client {client.status}")
        status = fut.status
        if status == "error":
            fut.result()  # raises the job's own exception (KilledWorker included)
        if status != "finished":
            raise _Lost(_cancel_reason(fut))
        try:
            pvs = fut.result(timeout=GATHER_TIMEOUT_S)
        except Exception as exc:
            raise _Lost(f"fetching the answer failed: {_short(exc)}") from None
        with self._lock:
            self.remote_jobs += 1
            self._overhead += max(0.0, time.monotonic() - t0 - pvs.seconds)
        return pvs

    # ----------------------------------------------------------------------------- the rest
    def slots(self) -> int:
        """The cluster's worker threads at connection (at least the local worker count), so
        the pool keeps every one of them busy."""
        with self._lock:
            return max(self._threads, self._local_workers)

    def state(self) -> dict[str, Any]:
        """kind, scheduler, state ("dask": on the cluster, "local_fallback": the scheduler is
        away), worker threads, remote and local job counts, losses, mean overhead per remote
        job (ms)."""
        with self._lock:
            on = self._connected and self._client is not None \
                and self._client.status == "running"
            n = self.remote_jobs
            return {"kind": "dask", "scheduler": self.name,
                    "state": "dask" if on else "local_fallback",
                    "scenes": "load" if self.load_scenes else "scatter",
                    "scattered": self.scattered,
                    "worker_threads": self._threads, "remote_jobs": n,
                    "local_jobs": self.local_jobs, "losses": self.losses,
                    "overhead_ms": round(1000 * self._overhead / n, 2) if n else None}

    def close(self) -> None:
        """Close the connection (queued jobs on the cluster are released)."""
        with self._lock:
            self._closed = True
            client, self._client = self._client, None
            self._connected = False
        if client is not None:
            _close_quietly(client)


def scene_source(loaded: LoadedScene, scenes_dir: Path | None) -> SceneSource | None:
    """Where a worker finds ``loaded``: its file under ``scenes_dir`` (an absolute path) or
    its generator; None for a scene registered in memory."""
    src = loaded.info.get("source") or {}
    fp = loaded.fingerprint
    if loaded.kind == "file" and scenes_dir is not None and "file" in src:
        return SceneSource(fp, loaded.name, path=str(Path(scenes_dir).resolve() / src["file"]))
    if loaded.kind == "generated" and "generator" in src:
        return SceneSource(fp, loaded.name, generator=src["generator"],
                           triangles=int(src["triangles"]), seed=int(src.get("seed", 0)))
    return None


def _short(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {text}"[:200] if text else type(exc).__name__


def _cancel_reason(fut: Any) -> str:
    try:
        exc = fut.exception(timeout=1)
    except Exception as e:  # the cancellation itself is the exception raised
        exc = e
    reason = getattr(exc, "reason", None)
    return f"job {fut.status}" + (f": {reason}" if reason else "")


def _close_quietly(client: Client) -> None:
    try:
        client.close(timeout=CONNECT_TIMEOUT_S)
    except Exception as exc:  # closing a client whose scheduler is gone may fail: no matter
        log.debug("closing the Dask client: %s", _short(exc))
