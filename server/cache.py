"""Caches of the server: a thread-safe LRU bounded in bytes (``ByteLRU``; ``PVSCache`` holds PVS
in it) and the on-disk PVS cache that survives restarts (``DiskPVSCache``).

Eviction never drops what a walker needs now: a key is kept while it is pinned (``pin``, counted)
or while the cache's ``keep(key)`` predicate says so (asked only when an eviction considers the
key), so the bound may be exceeded while such entries hold it; eviction catches up later.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from pathlib import Path
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

    def get(self, key: Hashable) -> Any | None:
        """The cached value (now the most recently used) or None."""
        with self._lock:
            item = self._data.get(key)
            if item is None:
                self.misses += 1
                return None
            self._data.move_to_end(key)
            self.hits += 1
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
    """A ``ByteLRU`` of PVS sized by ``pvs_nbytes`` (keys: ``ComputeService.key``)."""

    def __init__(self, max_bytes: int, keep: Callable[[Hashable], bool] | None = None) -> None:
        super().__init__(max_bytes, pvs_nbytes, keep)


class DiskPVSCache:
    """PVS as ``.npz`` files under ``folder`` (one per key), surviving restarts.

    A key is a tuple whose first item names the scene's geometry (``ComputeService.disk_key``:
    the scene fingerprint, so a changed scene file or generator size never meets old files).
    File name: ``<sha256 of key[0]>/<sha256 of repr(key)>.npz`` holding the ids, granularity,
    seconds and the key's ``repr`` (checked on load, so a hash collision or a foreign file is a
    miss). Files that cannot be read (truncated, corrupt, wrong content) are ignored (and
    removed). Writes go to a temporary file renamed into place, so a crash never leaves a half
    file under a real name.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.hits = 0
        self.misses = 0
        self.corrupt = 0
        self.writes = 0

    def path(self, key: tuple) -> Path:
        """Where the PVS of ``key`` lives."""
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
        """Folder, hits, misses, corrupt files, writes."""
        return {"folder": str(self.folder), "hits": self.hits, "misses": self.misses,
                "corrupt": self.corrupt, "writes": self.writes}
