"""Checks every PVS read back from a cache tier passes before it is served (disk and Redis)."""

from __future__ import annotations

import numpy as np


class BadEntry(ValueError):
    """A cache entry that fails a check (the reason is safe to log: no paths)."""


def check_ids(name: str, arr: np.ndarray, upper: int | None) -> np.ndarray:
    """``arr`` as int32 when it is a 1-D array of sorted unique ids in [0, upper) (``upper``
    None: no upper bound but int32's); BadEntry naming ``name`` otherwise."""
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise BadEntry(f"{name} are not a 1-D integer array ({arr.dtype}, {arr.shape})")
    if len(arr):
        a = arr.astype(np.int64)
        if a[0] < 0:
            raise BadEntry(f"{name} hold a negative id")
        if upper is not None and a[-1] >= upper:
            raise BadEntry(f"{name} hold id {int(a[-1])}, outside [0, {upper})")
        if a[-1] > np.iinfo(np.int32).max:
            raise BadEntry(f"{name} hold ids beyond int32")
        if len(a) > 1 and not np.all(a[1:] > a[:-1]):
            raise BadEntry(f"{name} are not sorted and unique")
    return arr.astype(np.int32)
