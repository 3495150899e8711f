"""Admission control: which PVS computations the server takes on, before any of them starts.

Three checks, cheapest first, each with its own refusal:

- **limits** (``OverLimit``, 422 ``over_limit``): the core's own estimate of the computation
  (``Core.estimate_cost``: seconds and peak scratch memory from the scene's size, the cell and
  the parameters) against ``settings.max_compute_bytes`` and the computation's deadline
  (times ``refuse_over_deadline``: the estimates are good to a factor of 2 to 3). A
  request that could only run out of memory, or be cancelled at its deadline, is refused at
  once with the limit it hit, instead of holding a worker for nothing.
- **the client's share** (``TooManyInFlight``, 429 ``too_many_requests``): at most
  ``settings.max_inflight_per_client`` computations started by one client (an HTTP client is
  its address; a WebSocket walker has one current cell at a time by construction) run or wait
  at once. Joining an identical computation already under way costs nothing and is not counted.
- **the queue** (``Busy``, 503 ``busy`` with ``Retry-After``): at most ``settings.max_queued``
  computations wait for a worker; past that new ones are refused. A walker's current cell is
  never refused for a full queue (it is what a walker stalls on; there is one per walker), so
  a flood of HTTP requests cannot starve walkers of their cells.

What is admitted runs in one of two lanes (``server.pool.PriorityWorkerPool``): computations
estimated above ``settings.heavy_seconds`` may occupy at most ``heavy_workers`` workers (default:
all but one), so cheap ones always find a free worker; within a priority the queue takes the
shortest estimate first, and a deadline bounds how long a long one can wait.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from collections.abc import Hashable
from typing import Any

from server.settings import Settings
from visibility.cores.base import Core, CoreParams, Cost
from visibility.scene import Scene
from visibility.viewcells import Viewcell


class Refused(Exception):
    """A computation the server will not take on now; ``retry_after`` seconds (None: retrying
    the same request will not help)."""

    retry_after: float | None = None

    def __init__(self, message: str, **detail: Any) -> None:
        super().__init__(message)
        self.detail = detail


class OverLimit(Refused, ValueError):
    """The estimate exceeds one of the server's limits (``detail``: ``limit``, its ``value``,
    the ``estimate``)."""


class TooManyInFlight(Refused):
    """This client already has ``max_inflight_per_client`` computations in flight."""

    def __init__(self, message: str, retry_after: float, **detail: Any) -> None:
        super().__init__(message, **detail)
        self.retry_after = retry_after


class Busy(Refused):
    """The queue of computations waiting for a worker is full."""

    def __init__(self, message: str, retry_after: float, **detail: Any) -> None:
        super().__init__(message, **detail)
        self.retry_after = retry_after


#: Bounds of a ``Retry-After`` the server suggests, seconds.
RETRY_AFTER_MIN = 1
RETRY_AFTER_MAX = 60


def retry_after(queued_seconds: float, workers: int) -> int:
    """Whole seconds to suggest in ``Retry-After``: the estimated work ahead spread over the
    workers, clamped to [RETRY_AFTER_MIN, RETRY_AFTER_MAX]."""
    s = queued_seconds / max(1, workers)
    if not math.isfinite(s):
        return RETRY_AFTER_MAX
    return int(min(RETRY_AFTER_MAX, max(RETRY_AFTER_MIN, math.ceil(s))))


#: ``Admission.observe``: weight of the newest measurement, and the range of scale factors.
OBSERVE_WEIGHT = 0.3
OBSERVE_RANGE = (0.01, 1000.0)


def _mib(n: float) -> str:
    return f"{n / (1 << 20):.0f} MiB"


class Admission:
    """The checks above, with counts of every refusal (``stats``, ``/health``) and the
    per-client computations in flight."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._inflight: Counter = Counter()
        self.refused: Counter = Counter()
        #: log(measured / estimated seconds) per (scene, core), averaged (``observe``).
        self._log_ratio: dict[tuple[str, str], float] = {}

    def estimate(self, core: Core, scene: Scene, cell: Viewcell, params: CoreParams,
                 scene_name: str | None = None) -> Cost:
        """The core's estimate, its seconds scaled by what this scene has measured so far
        (``observe``). A core whose estimate fails is priced at zero (admitted, its deadline
        still bounds it) rather than refused for a bug of its own."""
        try:
            cost = core.estimate_cost(scene, cell, params)
        except Exception as exc:  # an estimate is advice, never a reason to fail a request
            return Cost(0.0, 0, {"estimate_failed": f"{type(exc).__name__}: {exc}"})
        r = self._log_ratio.get((scene_name or "", core.name))
        if r is None:
            return cost
        scale = math.exp(r)
        return Cost(cost.seconds * scale, cost.peak_bytes,
                    {**cost.detail, "model_seconds": cost.seconds, "scene_factor": scale})

    def observe(self, scene_name: str, core: str, model_seconds: float, seconds: float) -> None:
        """Learn from a finished computation: the cores' models price a scene by its size
        alone, but how much of it a cell sees (a cluttered kitchen against a street of
        facades) changes the true cost fifty-fold. The ratio of measured to modelled seconds,
        averaged in log space per scene and core (weight ``OBSERVE_WEIGHT`` for the newest,
        clamped to ``OBSERVE_RANGE``), scales later estimates."""
        if not (model_seconds > 0 and seconds > 0):
            return
        lo, hi = OBSERVE_RANGE
        r = math.log(min(hi, max(lo, seconds / model_seconds)))
        key = (scene_name, core)
        with self._lock:
            old = self._log_ratio.get(key)
            self._log_ratio[key] = r if old is None else (
                (1 - OBSERVE_WEIGHT) * old + OBSERVE_WEIGHT * r)

    def check_limits(self, cost: Cost, deadline: float, core: str) -> None:
        """Raise ``OverLimit`` when ``cost`` needs more memory than ``max_compute_bytes`` or
        more than ``refuse_over_deadline`` times ``deadline`` seconds."""
        limit = self.settings.max_compute_bytes
        if cost.peak_bytes > limit:
            self._count("over_limit")
            raise OverLimit(
                f"core {core!r} would need about {_mib(cost.peak_bytes)} of memory for this "
                f"request, over the server's max_compute_bytes of {_mib(limit)}: lower the "
                "resolution or the samples", limit="max_compute_bytes", value=limit,
                estimate=cost.as_dict())
        if cost.seconds > deadline * self.settings.refuse_over_deadline:
            self._count("over_limit")
            raise OverLimit(
                f"core {core!r} would take about {cost.seconds:.0f} s for this request, over "
                f"its deadline of {deadline:g} s: lower the resolution or the samples",
                limit="compute_deadline", value=deadline, estimate=cost.as_dict())

    def check_queue(self, queued: int, queued_seconds: float) -> None:
        """Raise ``Busy`` when ``queued`` computations already wait (``max_queued``)."""
        if queued >= self.settings.max_queued:
            self._count("busy")
            after = retry_after(queued_seconds, self.settings.workers)
            raise Busy(f"{queued} computations are waiting for a worker, the most the server "
                       f"queues (max_queued); retry in {after} s", after,
                       limit="max_queued", value=self.settings.max_queued)

    def acquire(self, client: Hashable | None, queued_seconds: float = 0.0) -> None:
        """Count one more computation in flight for ``client`` (None: not counted); raise
        ``TooManyInFlight`` at ``max_inflight_per_client``."""
        if client is None:
            return
        cap = self.settings.max_inflight_per_client
        with self._lock:
            if self._inflight[client] >= cap:
                n = self._inflight[client]
            else:
                self._inflight[client] += 1
                return
        self._count("too_many_requests")
        after = retry_after(queued_seconds, self.settings.workers)
        raise TooManyInFlight(f"this client has {n} computations in flight, the most one "
                              f"client may (max_inflight_per_client); retry in {after} s",
                              after, limit="max_inflight_per_client", value=cap)

    def release(self, client: Hashable | None) -> None:
        """One computation of ``client`` is done."""
        if client is None:
            return
        with self._lock:
            self._inflight[client] -= 1
            if self._inflight[client] <= 0:
                del self._inflight[client]

    def _count(self, what: str) -> None:
        with self._lock:
            self.refused[what] += 1

    def stats(self) -> dict[str, Any]:
        """Refusals by kind and the clients with computations in flight."""
        with self._lock:
            return {"refused": {k: int(self.refused[k]) for k in
                                ("over_limit", "too_many_requests", "busy")},
                    "clients_in_flight": len(self._inflight)}
