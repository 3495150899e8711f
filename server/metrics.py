"""``GET /metrics``: server metrics in the Prometheus text format (prometheus-client).

Each application gets its own ``CollectorRegistry`` (several apps in one process, as in tests,
never collide). Counters are read from ``ServerState`` at scrape time; computation times are a
histogram observed by the compute service.

| metric                              | type      | meaning                                   |
|-------------------------------------|-----------|-------------------------------------------|
| pvs_computations_total              | counter   | PVS computed (not from a cache)           |
| pvs_computation_failures_total      | counter   | computations that raised                  |
| pvs_computation_seconds             | histogram | seconds per computation                   |
| pvs_cache_hits_total / _misses_total| counter   | in-memory cache lookups                   |
| pvs_cache_bytes / pvs_cache_entries | gauge     | in-memory cache size                      |
| pvs_disk_cache_hits_total           | counter   | on-disk cache hits                        |
| pvs_bytes_sent_total                | counter   | WebSocket bytes sent (frames + messages)  |
| pvs_http_bytes_sent_total           | counter   | HTTP response body bytes sent (all routes) |
| pvs_triangles_sent_total            | counter   | triangles streamed                        |
| pvs_triangles_dropped_total         | counter   | triangles clients were told to drop       |
| pvs_sessions / pvs_sessions_total   | gauge / counter | open sessions / sessions ever       |
| pvs_stalls_total                    | counter   | poses in a cell whose stream was not done |
| pvs_cells_streamed_total            | counter   | complete cell streams (incl. prefetch)    |
| pvs_cells_prefetched_total          | counter   | complete prefetch streams                 |
| pvs_slow_clients_total              | counter   | sessions closed for falling behind        |
| pvs_worker_retries_total / pvs_worker_replacements_total | counter | pool fault handling  |
| pvs_reranks_total{direction}        | counter   | queued jobs moved sooner / later (3)      |
| pvs_cancellations_total{reason, state} | counter | computations cancelled (4)             |
| pvs_queued_computations             | gauge     | computations waiting for a worker         |
| pvs_first_answer_holds_total        | counter   | checkpoints where a computation waited (5) |
| pvs_first_answer_held_seconds_total | counter   | seconds computations waited there (5)     |
| pvs_cache_tier_hits_total etc.      | counter   | hits, misses, errors by tier, kind (1)    |
| pvs_redis_up / pvs_redis_downs_total| gauge / counter | Redis answers (1/0) / went down (2) |
| pvs_redis_skipped_total{kind}       | counter   | Redis calls skipped while it was down (2) |

(1) ``pvs_cache_tier_{hits,misses,errors}_total{tier, kind}``: tier memory, disk or redis; kind
pvs, near_far (the near-far memory LRU) or cubemap (shared cubemaps). (2) With a Redis cache
(``PVS_CACHE=redis://…``) only. (3) As walkers move (``docs/scheduling.md``). (4) reason
unwanted (no walker wants the result any more and no caller waits), released (its last caller
stopped waiting and no walker wants it) or skipped (found unwanted when a worker took it); state
queued (never ran) or running (stopped at its core's next checkpoint). (5) Session cores'
computations wait at their checkpoints while a walker's first answer is queued or running
(``server.compute``, progressive streams).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

if TYPE_CHECKING:
    from server.state import ServerState

router = APIRouter()

#: Histogram buckets for computation seconds.
BUCKETS = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)


class _StateCollector:
    def __init__(self, state: ServerState) -> None:
        self.state = state

    def collect(self) -> Any:
        st = self.state
        c = st.counters
        stats = st.compute.stats()
        cache = stats["cache"]

        def counter(name: str, doc: str, value: float) -> CounterMetricFamily:
            return CounterMetricFamily(name, doc, value=float(value))

        def gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
            return GaugeMetricFamily(name, doc, value=float(value))

        yield counter("pvs_computations", "PVS computations run (cache misses)",
                      stats["computed"])
        yield counter("pvs_computation_failures", "PVS computations that failed",
                      stats["failed"])
        yield counter("pvs_computations_shared", "requests that joined an in-flight computation",
                      stats["shared"])
        yield counter("pvs_cache_hits", "in-memory PVS cache hits", cache["hits"])
        yield counter("pvs_cache_misses", "in-memory PVS cache misses", cache["misses"])
        yield counter("pvs_cache_evictions", "in-memory PVS cache evictions", cache["evictions"])
        yield gauge("pvs_cache_bytes", "bytes held by the in-memory PVS cache", cache["bytes"])
        yield gauge("pvs_cache_entries", "entries of the in-memory PVS cache", cache["entries"])
        yield gauge("pvs_cache_pinned", "cache keys pinned by walkers", cache.get("pinned", 0))
        disk = stats.get("disk")
        yield counter("pvs_disk_cache_hits", "on-disk PVS cache hits",
                      disk["hits"] if disk else 0)
        yield gauge("pvs_computations_inflight", "PVS computations queued or running",
                    stats["inflight"])
        yield counter("pvs_first_answer_holds", "checkpoints at which a computation waited for "
                      "walkers' first answers", stats["holds"])
        yield counter("pvs_first_answer_held_seconds", "seconds computations waited for "
                      "walkers' first answers", stats["held_seconds"])
        pool = stats.get("pool", {})
        yield counter("pvs_worker_retries", "jobs retried after a failure",
                      pool.get("retried", 0))
        yield counter("pvs_worker_replacements", "dead workers replaced",
                      pool.get("replaced", 0))
        # Dropped unrun either way: when a walker's move made it unwanted (only prefetch jobs
        # have no caller waiting), or when a worker found it unwanted.
        yield counter("pvs_prefetch_skipped", "prefetch jobs dropped unrun as no longer wanted",
                      pool.get("skipped", 0)
                      + stats["cancellations"]["unwanted"].get("queued", 0))
        yield gauge("pvs_queued_computations", "computations waiting for a worker",
                    pool.get("queued", 0))
        fam = CounterMetricFamily("pvs_reranks", "queued computations moved as walkers moved",
                                  labels=["direction"])
        for direction in ("sooner", "later"):
            fam.add_metric([direction], float(pool.get("reranks", {}).get(direction, 0)))
        yield fam
        fam = CounterMetricFamily("pvs_cancellations", "computations cancelled, by reason and "
                                  "by whether they had started", labels=["reason", "state"])
        for reason, states in stats["cancellations"].items():
            for state in ("queued", "running"):
                if reason != "skipped" or state == "queued":
                    fam.add_metric([reason, state], float(states.get(state, 0)))
        yield fam
        yield counter("pvs_bytes_sent", "WebSocket payload bytes sent (frames and messages)",
                      c["frame_bytes_sent"] + c["text_bytes_sent"])
        yield counter("pvs_http_bytes_sent", "HTTP response body bytes sent (PVS answers and "
                      "every other route)", c["http_bytes_sent"])
        yield counter("pvs_frames_sent", "binary geometry frames sent", c["frames_sent"])
        yield counter("pvs_triangles_sent", "triangles streamed", c["triangles_sent"])
        yield counter("pvs_triangles_dropped", "triangles clients were told to drop",
                      c["triangles_dropped"])
        yield gauge("pvs_sessions", "open WebSocket sessions", len(st.sessions))
        yield counter("pvs_sessions_opened", "WebSocket sessions opened", c["sessions_total"])
        yield counter("pvs_stalls", "poses in a cell whose stream the server had not finished",
                      c["stalls"])
        yield counter("pvs_cells_streamed", "complete cell streams", c["cells_streamed"])
        yield counter("pvs_cells_sent_whole", "cells whose near region fit the client's budget "
                      "(sent without a PVS computation)", c["cells_sent_whole"])
        yield counter("pvs_cells_prefetched", "complete prefetch cell streams",
                      c["cells_prefetched"])
        yield counter("pvs_prefetch_yields", "prefetch streams cut short for a current cell",
                      c["prefetch_yields"])
        yield counter("pvs_slow_clients", "sessions closed for falling behind",
                      c["slow_clients"])
        yield counter("pvs_errors_sent", "error messages sent", c["errors_sent"])
        yield from _tier_metrics(st, stats)


def _tier_metrics(st: ServerState, stats: dict[str, Any]) -> Any:
    """Hits, misses and errors per cache tier and kind of value; the shared cache's state."""
    rows: list[tuple[str, str, dict]] = [("memory", "pvs", stats["cache"])]
    if "disk" in stats:
        d = stats["disk"]
        rows.append(("disk", "pvs", {**d, "errors": d["write_errors"] + d["rejected"]}))
    if st.near_far is not None:
        rows.append(("memory", "near_far", st.near_far.cache.stats()))
    redis = stats.get("redis")
    if redis is not None:
        for kind in ("pvs", "cubemap"):
            r = redis[kind]
            rows.append(("redis", kind, {**r, "errors": r["errors"] + r["rejected"]}))
    for what in ("hits", "misses", "errors"):
        fam = CounterMetricFamily(f"pvs_cache_tier_{what}", f"cache lookups per tier and kind: "
                                  f"{what}", labels=["tier", "kind"])
        for tier, kind, row in rows:
            fam.add_metric([tier, kind], float(row.get(what, 0)))
        yield fam
    if redis is not None:
        yield GaugeMetricFamily("pvs_redis_up", "the shared Redis cache answers (1) or not (0)",
                                value=1.0 if redis["up"] else 0.0)
        yield CounterMetricFamily("pvs_redis_downs", "times the shared Redis cache went down",
                                  value=float(redis["downs"]))
        fam = CounterMetricFamily("pvs_redis_skipped", "Redis calls skipped while it was down",
                                  labels=["kind"])
        for kind in ("pvs", "cubemap"):
            fam.add_metric([kind], float(redis[kind]["skipped"]))
        yield fam


def install(app_state: ServerState) -> CollectorRegistry:
    """Give ``app_state`` its registry (``app_state.registry``) and hook the computation-time
    histogram into its compute service."""
    registry = CollectorRegistry(auto_describe=True)
    registry.register(_StateCollector(app_state))
    hist = Histogram("pvs_computation_seconds", "seconds per PVS computation",
                     buckets=BUCKETS, registry=registry)
    app_state.compute.on_computed = hist.observe
    app_state.registry = registry
    return registry


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
async def metrics(request: Request) -> Response:
    """Counters and gauges of computations, caches, streams, sessions and stalls in the
    Prometheus text exposition format."""
    registry = request.app.state.server.registry
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
