"""The client's own triangle budget, enforced as a last resort.

The server keeps a client under its declared budget with ``drop`` messages sent before new
geometry. Should the store still hold more (a server that does not honour the budget, or one
whose accounting drifted), the client evicts by itself before it renders: triangles outside the
current cell's stream first, farthest from the eye first (the least likely to be seen from
here), and only then, if that is not enough, the farthest of the current cell's own.
"""

from __future__ import annotations

import numpy as np

from client.store import GeometryStore


def choose_evictions(
    ids: np.ndarray,
    centroids: np.ndarray,
    protect: np.ndarray,
    eye: np.ndarray,
    budget: int,
) -> np.ndarray:
    """The ids to evict so at most ``budget`` remain.

    ``ids`` (n,) held triangle ids, ``centroids`` (n, 3) their centroids (metres), ``protect``
    ids of the current cell's PVS as far as the client knows it (evicted last), ``eye`` (3,)
    the viewpoint. Unprotected ones go first, each group farthest from the eye first.
    """
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    need = len(ids) - int(budget)
    if need <= 0:
        return ids[:0]
    dist = np.linalg.norm(np.asarray(centroids, dtype=np.float64) - np.asarray(eye), axis=1)
    protected = np.isin(ids, np.asarray(protect, dtype=np.int64).reshape(-1))
    # Sort by (protected, -distance): unprotected first, farthest first within each group.
    order = np.lexsort((-dist, protected))
    return ids[order[:need]]


def enforce_budget(store: GeometryStore, protect: np.ndarray, eye: np.ndarray) -> int:
    """Evict from ``store`` until it holds at most ``store.budget`` triangles (nothing without a
    budget); how many were evicted. ``protect``: the current cell's ids (evicted last)."""
    if not store.over_budget:
        return 0
    ids, tris, _colors = store.arrays()
    evict = choose_evictions(ids, tris.mean(axis=1), protect, eye, store.budget or 0)
    # drop, not retain: triangles that arrive meanwhile are not the ones chosen here.
    return store.drop(evict)
