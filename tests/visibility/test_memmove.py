"""move_items: numba block moves with memmove's overlap semantics."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError

from tests.grouping import module_on_one_worker
from visibility.borrow import borrow
from visibility.memmove import move_items

pytestmark = module_on_one_worker("memmove")  # kernels of its own (tests/grouping.py)


@njit(cache=False)
def _move(a, dst, src, n):
    move_items(a, dst, src, n)


@njit(cache=False)
def _move_borrowed(a, dst, src, n):
    move_items(borrow(a), dst, src, n)


@pytest.mark.parametrize("dtype", [np.float64, np.int32])
@pytest.mark.parametrize("dst,src,n", [(3, 0, 10), (0, 3, 10), (5, 5, 4), (2, 9, 0), (0, 12, 8)])
def test_moves_like_a_copy_through_a_temporary(dtype, dst, src, n):
    """Overlapping forwards and backwards, in place, nothing: as numpy's copy of the source."""
    rng = np.random.default_rng(dst * 31 + src)
    for fn in (_move, _move_borrowed):
        a = (rng.random(20) * 1000).astype(dtype)
        want = a.copy()
        want[dst:dst + n] = a[src:src + n].copy()
        fn(a, dst, src, n)
        assert np.array_equal(a, want)


def test_flat_indices_of_a_3d_array_move_whole_rows():
    """The layout ``from_segment``'s envelopes use: (pixels, rows, 4), rows shifted by one."""
    a = np.arange(2 * 6 * 4, dtype=np.float64).reshape(2, 6, 4)
    want = a.copy()
    want[1, 3:6] = a[1, 2:5]
    cap = a.shape[1]
    _move(a, (1 * cap + 3) * 4, (1 * cap + 2) * 4, 3 * 4)
    assert np.array_equal(a, want)


def test_a_strided_array_is_refused():
    a = np.zeros((4, 4))[:, ::2]
    with pytest.raises(TypingError):
        _move(a, 0, 1, 1)
