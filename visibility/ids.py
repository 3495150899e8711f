"""Fast set operations on id arrays.

``np.unique`` on numpy 2.4 is far slower than sort-and-mask for millions of ids, and PVS
results, object expansion and scene bounds all take the unique ids of arrays of that size.
"""

from __future__ import annotations

import numpy as np


def unique_ids(ids: np.ndarray, dtype: type = np.int64) -> np.ndarray:
    """(k,) sorted unique values of a 1-D integer array, as ``dtype``."""
    a = np.asarray(ids, dtype=np.int64).reshape(-1)
    if len(a) > 1 and bool(np.all(a[1:] > a[:-1])):
        # Already sorted and unique (a core's marks read back in order): a pass, no sort.
        return a.astype(dtype, copy=True)
    a = np.sort(a)
    if len(a) == 0:
        return a.astype(dtype)
    keep = np.empty(len(a), dtype=bool)
    keep[0] = True
    np.not_equal(a[1:], a[:-1], out=keep[1:])
    return a[keep].astype(dtype, copy=False)


def unique_inverse(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sorted unique values, inverse) such that ``unique[inverse] == ids``."""
    a = np.asarray(ids, dtype=np.int64).reshape(-1)
    u = unique_ids(a)
    return u, np.searchsorted(u, a)
