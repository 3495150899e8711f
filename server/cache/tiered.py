"""One PVS cache in three tiers behind one ``get``/``put`` and one key (``PVSKey``).

Memory (``PVSCache``, this process, bounded in bytes, pins) first; then the shared tier
(``SharedCache``: Redis, which replicas share, behind its circuit breaker with short timeouts,
bounded by ``redis_max_value_bytes``, the TTL and Redis's ``maxmemory``); then the disk
(``DiskPVSCache``: ``cache_dir``, entries checked, not trusted). A hit in a slower tier is copied
into the faster ones (a disk hit into Redis too: the other replicas' gain); ``put`` writes every
tier. Grid cells, ad-hoc boxes and segments alike: a box computed on one replica is answered by
every other from Redis. The disk holds only what ``put`` is told to keep there (``disk=True``:
the service keeps grid cells), since ad-hoc regions are unbounded in number and the disk tier
has no byte bound of its own.

``get`` and ``put`` block on Redis and the disk: call them from worker threads. ``peek`` looks
without computing and without the disk (memory, then Redis, each call bounded by
``redis_timeout``); ``peek_async`` is the event loop's: memory inline, Redis in a thread.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Hashable
from typing import Any

from server.cache.disk import DiskPVSCache
from server.cache.key import PVSKey
from server.cache.memory import PVSCache
from server.cache.shared import SharedCache
from visibility.cores.base import PVS

#: The tiers in the order ``get`` asks them (``first``/``upto`` name one).
TIERS = ("memory", "shared", "disk")


def _tier(name: str) -> int:
    try:
        return TIERS.index(name)
    except ValueError:
        raise ValueError(f"a tier is one of {TIERS}, got {name!r}") from None


class TieredCache:
    """Memory, then Redis, then disk (module docstring). Thread-safe.

    Attributes
    ----------
    memory : the memory tier (pins, ``keep``, byte bound ``settings.cache_bytes``).
    shared : the Redis tier, or None (``settings.cache`` is ``"disk"``); replicas also share
        near-far cubemaps through it (``server.nearfar_store``).
    disk : the disk tier, or None (no ``settings.cache_dir``).
    """

    def __init__(self, memory: PVSCache, shared: SharedCache | None = None,
                 disk: DiskPVSCache | None = None) -> None:
        self.memory = memory
        self.shared = shared
        self.disk = disk
        self._lock = threading.Lock()
        self.peeks = 0
        self.peek_hits = 0

    @classmethod
    def from_settings(cls, settings: Any, keep: Callable[[Hashable], bool] | None = None
                      ) -> TieredCache:
        """The tiers ``settings`` name: ``cache_bytes``, ``cache`` (a Redis URL or ``"disk"``),
        ``cache_dir``; ``keep``: the memory tier's keep predicate."""
        disk = DiskPVSCache(settings.cache_dir) if settings.cache_dir is not None else None
        return cls(PVSCache(settings.cache_bytes, keep), SharedCache.from_settings(settings),
                   disk)

    @property
    def shared_up(self) -> bool:
        """Whether there is a shared tier and it answers now."""
        return self.shared is not None and self.shared.up

    # ----------------------------------------------------------------------------- lookups
    def get(self, key: PVSKey, n_triangles: int | None = None, *, first: str = "memory",
            upto: str = "disk", count: bool = True) -> PVS | None:
        """The PVS of ``key`` from the first tier that holds a valid one, or None; the tiers
        from ``first`` to ``upto`` (``TIERS``) are asked, in order (``first="shared"``: memory
        was just asked). A slower tier's hit is copied into the faster ones. ``n_triangles``:
        the scene's triangle count, bounding the ids read back. ``count`` False: hits and
        misses are not counted (``peek``)."""
        lo, hi = _tier(first), _tier(upto)
        pvs = self.memory.get(key, count) if lo == 0 else None
        if pvs is not None or hi == 0:
            return pvs
        if lo <= 1 and self.shared is not None:
            pvs = self.shared.get_pvs(key.shared(), n_triangles, count=count)
        if pvs is None and hi == 2 and self.disk is not None:
            pvs = self.disk.get(key, n_triangles=n_triangles)
            if pvs is not None and self.shared is not None:
                self.shared.put_pvs(key.shared(), pvs, n_triangles)
        if pvs is not None:
            self.memory.put(key, pvs)
        return pvs

    def peek(self, key: PVSKey, n_triangles: int | None = None) -> PVS | None:
        """The PVS of ``key`` when memory or Redis holds it, else None: never a computation,
        never the disk, hits and misses left uncounted (counted as ``peeks``). Blocks for at
        most ``redis_timeout`` (nothing while Redis is down): from a thread, or
        ``peek_async``."""
        pvs = self.get(key, n_triangles, upto="shared", count=False)
        self._peeked(pvs)
        return pvs

    async def peek_async(self, key: PVSKey, n_triangles: int | None = None) -> PVS | None:
        """``peek`` from the event loop: memory inline, Redis (only while it is up) in a
        thread."""
        pvs = self.memory.get(key, count=False)
        if pvs is None and self.shared_up:
            pvs = await asyncio.to_thread(self.get, key, n_triangles, upto="shared",
                                          count=False)
        self._peeked(pvs)
        return pvs

    def _peeked(self, pvs: PVS | None) -> None:
        with self._lock:
            self.peeks += 1
            self.peek_hits += pvs is not None

    def missing(self, key: PVSKey, n_triangles: int | None = None) -> list[str]:
        """The lasting tiers (``"disk"``, ``"shared"``) configured here that hold no valid
        entry of ``key`` (a bad disk entry is rejected and deleted); counts no hits."""
        out = []
        if self.disk is not None and not self.disk.check(key, n_triangles):
            out.append("disk")
        if self.shared is not None and self.shared.get_pvs(key.shared(), n_triangles,
                                                           count=False) is None:
            out.append("shared")
        return out

    # ----------------------------------------------------------------------------- writes
    def put(self, key: PVSKey, pvs: PVS, n_triangles: int | None = None, *,
            disk: bool = True) -> None:
        """Store ``pvs`` in memory, Redis and (``disk``, when configured) on disk. Never raises
        for a tier that fails (each counts its errors)."""
        self.memory.put(key, pvs)
        if self.shared is not None:
            self.shared.put_pvs(key.shared(), pvs, n_triangles)
        if disk and self.disk is not None:
            self.disk.put(key, pvs, n_triangles=n_triangles)

    def pin(self, key: PVSKey) -> None:
        """Keep ``key``'s PVS in memory (now or once stored) until as many ``unpin`` calls."""
        self.memory.pin(key)

    def unpin(self, key: PVSKey) -> None:
        """Undo one ``pin``."""
        self.memory.unpin(key)

    # ----------------------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """Which tiers serve and whether the shared one is up (``/health``'s ``cache``):
        ``{"backend": "redis", "up": ..., ..., "disk": bool}`` or ``{"backend": "disk", "up":
        true, "disk": bool}``."""
        if self.shared is not None:
            return {**self.shared.link.state(), "disk": self.disk is not None}
        return {"backend": "disk", "up": True, "disk": self.disk is not None}

    def stats(self) -> dict[str, Any]:
        """Per tier: ``cache`` (memory, with ``peeks`` and ``peek_hits``), ``disk`` and
        ``redis`` when configured (``/health``'s ``compute``, ``/metrics``)."""
        with self._lock:
            peeks = {"peeks": self.peeks, "peek_hits": self.peek_hits}
        out: dict[str, Any] = {"cache": {**self.memory.stats(), **peeks}}
        if self.disk is not None:
            out["disk"] = self.disk.stats()
        if self.shared is not None:
            out["redis"] = self.shared.stats()
        return out

    def close(self) -> None:
        """Close the shared tier's connections."""
        if self.shared is not None:
            self.shared.close()
