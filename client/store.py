"""The client's geometry store: the triangles received so far, by id.

Chunks are appended as they arrive (cheap) and merged into one id-sorted set of arrays only when
someone reads (``arrays``, ``len``, ``ids``...), so receiving N chunks costs O(total) rather than
O(N * total). A triangle received twice keeps its latest data. ``version`` bumps on every change so
a renderer re-uploads only when the content changed. Thread-safe: the network session writes
from its event loop while a renderer reads from another thread.
"""

from __future__ import annotations

import threading

import numpy as np

from protocol.frames import GeometryChunk


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


class GeometryStore:
    """Triangles by id: absolute float64 corner positions (metres) and uint8 RGB colours.

    Parameters
    ----------
    budget : most triangles the client means to hold (None: no limit). The store does not evict
        by itself (it cannot know what is still visible); ``over_budget`` tells when the holder
        should ``retain`` the current PVS.
    """

    def __init__(self, budget: int | None = None) -> None:
        if budget is not None and int(budget) <= 0:
            raise ValueError(f"budget must be positive, got {budget}")
        self.budget = None if budget is None else int(budget)
        self._lock = threading.RLock()
        self._ids = np.zeros(0, dtype=np.int32)
        self._tris = np.zeros((0, 3, 3), dtype=np.float64)
        self._colors = np.zeros((0, 3), dtype=np.uint8)
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.version = 0
        self._out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # ----------------------------------------------------------------------------- writing
    def add(self, ids: np.ndarray, triangles: np.ndarray, colors: np.ndarray) -> None:
        """Add (or replace) triangles: ``ids`` (n,) ints >= 0, ``triangles`` (n, 3, 3) metres,
        ``colors`` (n, 3) uint8. ValueError on inconsistent shapes or non-finite positions."""
        ids = np.asarray(ids)
        n = len(ids)
        if ids.ndim != 1 or (n and not np.issubdtype(ids.dtype, np.integer)):
            raise ValueError(f"ids must be a 1-D integer array, got {ids.dtype} {ids.shape}")
        if n and (ids.min() < 0 or ids.max() > np.iinfo(np.int32).max):
            raise ValueError("ids must be in [0, 2**31)")
        tris = np.asarray(triangles, dtype=np.float64)
        cols = np.asarray(colors)
        if tris.shape != (n, 3, 3) or cols.shape != (n, 3):
            raise ValueError(
                f"need triangles ({n}, 3, 3) and colors ({n}, 3), got {tris.shape}, {cols.shape}"
            )
        if not np.all(np.isfinite(tris)):
            raise ValueError("triangle positions must be finite")
        if n == 0:
            return
        with self._lock:
            self._pending.append((ids.astype(np.int32), tris.copy(), cols.astype(np.uint8)))
            self._changed()

    def add_chunk(self, chunk: GeometryChunk) -> None:
        """Add a decoded geometry frame (positions made absolute in float64)."""
        self.add(chunk.ids, chunk.triangles, chunk.colors)

    def drop(self, ids: np.ndarray) -> int:
        """Remove these ids (absent ones are ignored); returns how many were removed."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        with self._lock:
            self._merge()
            keep = ~np.isin(self._ids, ids)
            removed = int(len(keep) - np.count_nonzero(keep))
            if removed:
                self._set(self._ids[keep], self._tris[keep], self._colors[keep])
            return removed

    def retain(self, ids: np.ndarray) -> int:
        """Keep only these ids (e.g. the current PVS); returns how many were removed."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        with self._lock:
            self._merge()
            keep = np.isin(self._ids, ids)
            removed = int(len(keep) - np.count_nonzero(keep))
            if removed:
                self._set(self._ids[keep], self._tris[keep], self._colors[keep])
            return removed

    def clear(self) -> None:
        """Remove everything."""
        with self._lock:
            self._pending.clear()
            self._set(self._ids[:0], self._tris[:0], self._colors[:0])

    # ----------------------------------------------------------------------------- reading
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (k,) int32 sorted, triangles (k, 3, 3) float64 metres, colors (k, 3) uint8).

        The same read-only arrays are returned until the store changes (compare ``version``).
        """
        with self._lock:
            self._merge()
            if self._out is None:
                self._out = (_readonly(self._ids.copy()), _readonly(self._tris.copy()),
                             _readonly(self._colors.copy()))
            return self._out

    def snapshot(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """(version, ids, triangles, colors) read atomically: the version that matches the arrays
        even while the network thread keeps adding (reading ``version`` and ``arrays()`` one
        after the other can pair new version with old arrays)."""
        with self._lock:
            return (self.version, *self.arrays())

    @property
    def ids(self) -> np.ndarray:
        """(k,) int32 sorted ids held."""
        return self.arrays()[0]

    def __len__(self) -> int:
        with self._lock:
            self._merge()
            return int(len(self._ids))

    def contains(self, ids: np.ndarray) -> np.ndarray:
        """(n,) bool: which of ``ids`` the store holds."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        with self._lock:
            self._merge()
            held = self._ids
            pos = np.clip(np.searchsorted(held, ids), 0, max(len(held) - 1, 0))
            return (held[pos] == ids) if len(held) else np.zeros(len(ids), dtype=bool)

    def __contains__(self, tid: object) -> bool:
        return bool(self.contains(np.array([tid]))[0])

    @property
    def over_budget(self) -> bool:
        """True when a budget is set and the store holds more triangles than it."""
        return self.budget is not None and len(self) > self.budget

    @property
    def nbytes(self) -> int:
        """Memory held by the merged arrays and pending chunks, bytes."""
        with self._lock:
            n = self._ids.nbytes + self._tris.nbytes + self._colors.nbytes
            return n + sum(a.nbytes + b.nbytes + c.nbytes for a, b, c in self._pending)

    # ----------------------------------------------------------------------------- internals
    def _changed(self) -> None:
        self.version += 1
        self._out = None

    def _set(self, ids: np.ndarray, tris: np.ndarray, colors: np.ndarray) -> None:
        self._ids, self._tris, self._colors = ids, tris, colors
        self._changed()

    def _merge(self) -> None:
        if not self._pending:
            return
        ids = np.concatenate([self._ids] + [p[0] for p in self._pending])
        tris = np.concatenate([self._tris] + [p[1] for p in self._pending])
        cols = np.concatenate([self._colors] + [p[2] for p in self._pending])
        self._pending.clear()
        # Latest data wins for repeated ids: a stable sort keeps arrival order within equal ids,
        # so the last of each run is the latest copy. (np.unique is hash-based and many times
        # slower in numpy 2.x.)
        order = np.argsort(ids, kind="stable")
        s = ids[order]
        last = np.ones(len(s), dtype=bool)
        last[:-1] = s[1:] != s[:-1]
        src = order[last]
        self._ids, self._tris, self._colors = s[last].astype(np.int32), tris[src], cols[src]
        # Merging does not change the content, so version stays; cached outputs are stale.
        self._out = None
