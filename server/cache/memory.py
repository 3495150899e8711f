"""The memory tier: a thread-safe LRU bounded in bytes (``ByteLRU``; ``PVSCache`` holds PVS in it).

Eviction never drops what a walker needs now: a key is kept while it is pinned (``pin``, counted)
or while the cache's ``keep(key)`` predicate says so (asked only when an eviction considers the
key), so the bound may be exceeded while such entries hold it; eviction catches up later.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

import numpy as np

from visibility.cores.base import PVS

log = logging.getLogger(__name__)


def pvs_nbytes(pvs: PVS) -> int:
    """Approximate memory held by a PVS (its arrays plus a fixed overhead), bytes."""
    n = 512 + pvs.triangle_ids.nbytes
    for arr in (pvs.object_ids, pvs.sphere_ids):
        if arr is not None:
            n += arr.nbytes
    for v in pvs.stats.values():
        n += v.nbytes if isinstance(v, np.ndarray) else 64
    return int(n)


def nbytes_of(value: Any) -> int:
    """Approximate memory held by ``value``, bytes: buffers (bytes, arrays) by their length,
    dataclasses and containers by the sum of their parts, anything else a fixed 64."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return 64 + len(value)
    if isinstance(value, np.ndarray):
        return 128 + int(value.nbytes)
    if isinstance(value, PVS):
        return pvs_nbytes(value)
    if isinstance(value, (list, tuple)):
        return 64 + sum(nbytes_of(v) for v in value)
    if isinstance(value, dict):
        return 64 + sum(nbytes_of(v) for v in value.values())
    fields = getattr(value, "__dataclass_fields__", None)
    if fields:
        return 64 + sum(nbytes_of(getattr(value, f)) for f in fields)
    return 64


class ByteLRU:
    """A thread-safe LRU map bounded by the total ``sizeof`` of its values (bytes).

    A value larger than the whole bound is not stored (unless its key is pinned). Pinned keys
    (``pin``; a count per key) and keys for which ``keep(key)`` is true are never evicted.
    """

    def __init__(self, max_bytes: int, sizeof: Callable[[Any], int] = nbytes_of,
                 keep: Callable[[Hashable], bool] | None = None) -> None:
        self.max_bytes = int(max_bytes)
        self.sizeof = sizeof
        self.keep = keep
        self._data: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._lock = threading.Lock()
        self._pins: dict[Hashable, int] = {}
        self.nbytes = 0
        self.hits = 0
        self.misses = 0
        self.evictions = 0

    def get(self, key: Hashable, count: bool = True) -> Any | None:
        """The cached value (now the most recently used) or None. ``count`` False: a look that
        counts no hit or miss (``TieredCache.peek``)."""
        with self._lock:
            item = self._data.get(key)
            if item is None:
                self.misses += count
                return None
            self._data.move_to_end(key)
            self.hits += count
            return item[0]

    def put(self, key: Hashable, value: Any) -> None:
        """Store ``value``, evicting least recently used entries that nobody needs to stay
        within ``max_bytes``."""
        size = int(self.sizeof(value))
        with self._lock:
            old = self._data.pop(key, None)
            if old is not None:
                self.nbytes -= old[1]
            if size > self.max_bytes and key not in self._pins:
                return
            self._data[key] = (value, size)
            self.nbytes += size
            self._evict()

    def _kept(self, key: Hashable) -> bool:
        if key in self._pins:
            return True
        if self.keep is None:
            return False
        try:
            return bool(self.keep(key))
        except Exception:  # a failing predicate must not break a put: keep the entry
            log.exception("cache keep() failed for %r", key)
            return True

    def _evict(self) -> None:
        if self.nbytes <= self.max_bytes:
            return
        for k in list(self._data):
            if self.nbytes <= self.max_bytes:
                break
            if self._kept(k):
                continue
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
        """Keys pinned now."""
        with self._lock:
            return len(self._pins)

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._data

    def clear(self) -> None:
        """Drop every entry (pins stay)."""
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


class PVSCache(ByteLRU):
    """A ``ByteLRU`` of PVS sized by ``pvs_nbytes`` (keys: ``server.cache.key.PVSKey``)."""

    def __init__(self, max_bytes: int, keep: Callable[[Hashable], bool] | None = None) -> None:
        super().__init__(max_bytes, pvs_nbytes, keep)
