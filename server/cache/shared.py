"""The shared cache tier: Redis, reached with short timeouts behind a circuit breaker.

Several server replicas pointed at one Redis (``Settings.cache``, ``PVS_CACHE=redis://…``)
share the PVS they compute and the near-far cubemaps they bake. Each process keeps its memory
cache in front (L1); Redis is the shared L2, beside the on-disk cache when ``cache_dir`` is
also set (memory, then Redis, then disk, then a computation; what is computed or read from disk
is written to Redis: ``server.cache.tiered``). Keys and values: ``server.cache.codec``.

Calls are blocking and made from worker threads (the compute pool, the cubemap baker's
``asyncio.to_thread``, ``TieredCache.peek_async``), never from the event loop. Every call has
``redis_timeout`` seconds; a connection error or timeout marks Redis down: calls are then
skipped at once (a miss; the server recomputes and serves from memory) while a background
thread pings Redis every ``redis_retry`` seconds and marks it up again when it answers.
``/health`` (``cache``) and ``/metrics`` (``pvs_redis_up``, per-tier counters) say which.

Bounds: a value over ``redis_max_value_bytes`` is not stored (counted ``too_large``); each
value expires after ``redis_ttl`` seconds (0: never). The total is Redis's own
``maxmemory`` with an LRU policy (``allkeys-lru``, or ``volatile-lru`` with a TTL): one place
that sees every replica's writes. A Redis without ``maxmemory`` is logged as unbounded.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, TypeVar
from urllib.parse import urlsplit

from server.cache.checks import BadEntry
from server.cache.codec import decode_blob, decode_pvs, encode_blob, encode_pvs
from visibility.cores.base import PVS

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Counters kept per kind of value (``pvs``, ``cubemap``).
KIND_COUNTERS = ("hits", "misses", "errors", "rejected", "writes", "too_large", "skipped")


def redact(url: str) -> str:
    """``url`` without credentials (``redis://host:port/db``), safe to show in /health."""
    u = urlsplit(url)
    if u.scheme == "unix":
        return f"unix://{u.path}"
    host = u.hostname or "localhost"
    port = f":{u.port}" if u.port else ""
    return f"{u.scheme}://{host}{port}{u.path}"


class RedisLink:
    """A Redis client with short timeouts and a circuit breaker (module docstring).

    ``call(fn)`` runs ``fn(client)``: ("ok", its result) when Redis answered, ("skipped",
    None) when Redis is down (nothing sent), ("error", None) when the call failed.
    Thread-safe.
    """

    def __init__(self, url: str, timeout: float = 0.25, retry: float = 2.0) -> None:
        import redis
        from redis.backoff import NoBackoff
        from redis.retry import Retry

        self._redis = redis
        self.url = redact(url)
        self.retry = float(retry)
        # No retries inside redis-py: the breaker decides when to try again.
        self.client = redis.Redis.from_url(
            url, socket_timeout=timeout, socket_connect_timeout=timeout,
            retry=Retry(NoBackoff(), 0), retry_on_timeout=False, health_check_interval=0)
        self._up: bool | None = None  # None: not yet known (calls are tried)
        self._lock = threading.Lock()
        self.downs = 0
        self.errors = 0
        self.since = time.monotonic()
        self.maxmemory: int | None = None
        self._closed = threading.Event()
        self._prober = threading.Thread(target=self._probe_loop, name="pvs-redis-probe",
                                        daemon=True)
        self._prober.start()

    @property
    def up(self) -> bool:
        """Whether Redis answered the last call or ping."""
        return self._up is True

    def _mark(self, up: bool, why: str = "") -> None:
        with self._lock:
            was, self._up = self._up, up
            if was is up:
                return
            self.since = time.monotonic()
            if not up:
                self.downs += 1
        if up:
            log.info("Redis cache at %s is up", self.url)
        else:
            log.warning("Redis cache at %s is down (%s): serving from memory and recomputing; "
                        "retrying every %g s", self.url, why, self.retry)

    def _lost(self, exc: BaseException) -> bool:
        """Whether ``exc`` means the connection is gone (else: one command failed)."""
        r = self._redis
        return isinstance(exc, (r.ConnectionError, r.TimeoutError, OSError))

    def call(self, fn: Callable[[Any], T]) -> tuple[str, T | None]:
        """``("ok", fn(client))``; ``("skipped", None)`` while Redis is down; ``("error",
        None)`` when the call fails (a lost connection marks Redis down; other errors are
        logged)."""
        if self._up is False:
            return "skipped", None
        try:
            out = fn(self.client)
        except Exception as exc:  # redis-py raises many types; none may reach a request
            with self._lock:
                self.errors += 1
            if self._lost(exc):
                self._mark(False, type(exc).__name__)
            else:
                log.warning("Redis cache command failed: %s: %s", type(exc).__name__, exc)
            return "error", None
        if self._up is not True:
            self._mark(True)
        return "ok", out

    def ping(self) -> bool:
        """Ping Redis now (marking it up or down); whether it answered."""
        try:
            self.client.ping()
        except Exception as exc:  # noqa: BLE001 - any failure means not up
            self._mark(False, type(exc).__name__)
            return False
        if self._up is not True:
            self._check_bound()
        self._mark(True)
        return True

    def _check_bound(self) -> None:
        # Managed Redis may refuse CONFIG: then the bound is simply unknown.
        try:
            mem = int(self.client.config_get("maxmemory").get("maxmemory", 0))
        except Exception:  # noqa: BLE001
            return
        self.maxmemory = mem
        if mem == 0:
            log.warning("Redis at %s has no maxmemory: the shared cache grows until values "
                        "expire (redis_ttl); set maxmemory and an LRU maxmemory-policy",
                        self.url)

    def _probe_loop(self) -> None:
        while not self._closed.is_set():
            self.ping()
            self._closed.wait(self.retry)

    def state(self) -> dict[str, Any]:
        """Backend, URL (no credentials), up, seconds in this state, times marked down,
        failed calls, Redis's maxmemory when known."""
        return {"backend": "redis", "url": self.url, "up": self.up,
                "state_seconds": round(time.monotonic() - self.since, 3), "downs": self.downs,
                "errors": self.errors, "maxmemory": self.maxmemory}

    def close(self) -> None:
        """Stop the prober and close the connections."""
        self._closed.set()
        try:
            self.client.close()
        except Exception:  # noqa: BLE001 - closing must not fail a shutdown
            pass


class SharedCache:
    """PVS and blobs (cubemap frames) in Redis through a ``RedisLink``: counted per kind,
    checked on read (a value failing ``server.cache.codec``'s checks is deleted and a miss)."""

    def __init__(self, link: RedisLink, ttl: float = 0.0,
                 max_value_bytes: int = 8 << 20) -> None:
        self.link = link
        self.ttl = float(ttl)
        self.max_value_bytes = int(max_value_bytes)
        self.counts: dict[str, Counter] = {k: Counter({c: 0 for c in KIND_COUNTERS})
                                           for k in ("pvs", "cubemap")}
        self._lock = threading.Lock()

    @classmethod
    def from_settings(cls, settings: Any) -> SharedCache | None:
        """The shared cache ``settings.cache`` names, or None for ``"disk"``."""
        if not str(settings.cache).startswith(("redis://", "rediss://", "unix://")):
            return None
        link = RedisLink(settings.cache, settings.redis_timeout, settings.redis_retry)
        return cls(link, settings.redis_ttl, settings.redis_max_value_bytes)

    @property
    def up(self) -> bool:
        return self.link.up

    def _count(self, kind: str, what: str) -> None:
        with self._lock:
            self.counts[kind][what] += 1

    def _get(self, kind: str, key: str) -> bytes | None:
        status, value = self.link.call(lambda r: r.get(key))
        if status != "ok":
            self._count(kind, "skipped" if status == "skipped" else "errors")
            return None
        if value is None:
            self._count(kind, "misses")
        return value

    def _put(self, kind: str, key: str, value: bytes) -> bool:
        if len(value) > self.max_value_bytes:
            self._count(kind, "too_large")
            return False
        ttl_ms = int(self.ttl * 1000) if self.ttl > 0 else None
        status, _ = self.link.call(lambda r: r.set(key, value, px=ttl_ms))
        self._count(kind, {"ok": "writes", "skipped": "skipped"}.get(status, "errors"))
        return status == "ok"

    def _reject(self, kind: str, key: str, why: str) -> None:
        log.warning("rejected a shared-cache %s value (%s): %s; recomputing", kind,
                    key.split(":")[2][:16] if key.count(":") > 2 else "?", why)
        self._count(kind, "rejected")
        self._count(kind, "misses")
        self.link.call(lambda r: r.delete(key))

    def get_pvs(self, key: str, n_triangles: int | None = None, count: bool = True
                ) -> PVS | None:
        """The checked PVS under ``key``, or None (missing, other format, refused, Redis
        down). ``count`` False: a check that counts no hit (``pvs precompute``)."""
        value = self._get("pvs", key)
        if value is None:
            return None
        try:
            pvs = decode_pvs(key, value, n_triangles)
        except BadEntry as exc:
            self._reject("pvs", key, str(exc))
            return None
        if pvs is None:
            self._count("pvs", "misses")
        elif count:
            self._count("pvs", "hits")
        return pvs

    def put_pvs(self, key: str, pvs: PVS, n_triangles: int | None = None) -> bool:
        """Store ``pvs`` under ``key``; True when Redis took it. Never raises."""
        try:
            value = encode_pvs(key, pvs, n_triangles)
        except BadEntry as exc:  # a core's bad answer must not reach other replicas
            log.warning("not sharing a PVS that fails its checks: %s", exc)
            self._count("pvs", "errors")
            return False
        return self._put("pvs", key, value)

    def get_blob(self, key: str, kind: str = "cubemap") -> bytes | None:
        """The checked bytes under ``key``, or None."""
        value = self._get(kind, key)
        if value is None:
            return None
        try:
            data = decode_blob(key, value, self.max_value_bytes * 64)
        except BadEntry as exc:
            self._reject(kind, key, str(exc))
            return None
        self._count(kind, "hits" if data is not None else "misses")
        return data

    def put_blob(self, key: str, data: bytes, kind: str = "cubemap") -> bool:
        """Store ``data`` under ``key``; True when Redis took it. Never raises."""
        return self._put(kind, key, encode_blob(key, data))

    def stats(self) -> dict[str, Any]:
        """The link's state plus the counters per kind, TTL and value bound."""
        with self._lock:
            counts = {k: dict(v) for k, v in self.counts.items()}
        return {**self.link.state(), "ttl_s": self.ttl,
                "max_value_bytes": self.max_value_bytes, **counts}

    def close(self) -> None:
        """Close the link."""
        self.link.close()
