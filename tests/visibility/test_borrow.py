"""``visibility.borrow``: arrays without an owner inside numba kernels."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest
from numba import njit
from numba.core.errors import TypingError

from tests.grouping import module_on_one_worker
from visibility.borrow import NO_REFCOUNT, borrow, keep_alive

pytestmark = module_on_one_worker("borrow")  # kernels of its own (tests/grouping.py)


@njit(cache=True, nogil=True)
def _sum_rows(m):
    out = np.zeros(m.shape[0])
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            out[i] += m[i, j]
    return out


@njit(cache=True, nogil=True)
def _through_borrowed(a):
    """Writes through a borrowed view of ``a`` and of a local owner, reads slices of both."""
    b = borrow(a)
    b[0, 0] = 7.0
    own = np.arange(6.0).reshape((2, 3))
    c = borrow(own)
    c[1, 2] = 10.0
    s = _sum_rows(b)[0] + _sum_rows(c[1:])[0] + c.reshape(6)[5]
    keep_alive(own)
    return s


def test_a_borrowed_array_is_the_same_memory():
    a = np.ones((3, 4))
    # b[0] sums to 7 + 3, c's second row to 3 + 4 + 10, and c's last item is 10.
    assert _through_borrowed(a) == 10.0 + 17.0 + 10.0
    assert a[0, 0] == 7.0 and a.sum() == 18.0



class _Scratch(NamedTuple):
    a: np.ndarray
    b: np.ndarray


@njit(cache=True, nogil=True)
def _scratch(n):
    return _Scratch(np.zeros(n), np.zeros((2, n), dtype=np.int64))


@njit(cache=True, nogil=True)
def _through_borrowed_tuple(n):
    """A named tuple of owners borrowed at once, written through its unpacked views."""
    own = _scratch(n)
    a, b = borrow(own)
    t0, (t1,) = borrow((own.a, (own.b,)))  # nested tuples too
    for i in range(n):
        a[i] = i
        b[1, i] = 2 * i
    t0[0] = 5.0
    s = _sum_rows(b)[1] + own.a.sum() + t1[1, n - 1]
    keep_alive(own)
    return s, own.a.copy()


def test_a_borrowed_tuple_is_the_same_memory():
    s, a = _through_borrowed_tuple(4)
    # b's second row sums to 2 (0 + 1 + 2 + 3) = 12; a to 5 + 1 + 2 + 3 = 11; b[1, 3] = 6.
    assert s == 12 + 11 + 6
    assert a.tolist() == [5.0, 1.0, 2.0, 3.0]


def _incref_sites(fn) -> int:
    import re

    return sum(len(re.findall(r"call void @NRT_incref", fn.inspect_llvm(sig)))
               for sig in fn.overloads)


@njit(cache=False)
def _term(a, b, i):
    return a[i] * b[i % b.shape[0]]


def _walk(pair, k):
    """A helper called per item with arrays unpacked from a tuple, and an early exit: the
    shape of the kernels' per-primitive helpers, where numba keeps its reference counts."""
    a, b = pair
    s = 0.0
    for i in range(k, a.shape[0]):
        if a[i] < 0:
            break
        s += _term(a, b, i)
    return s


_walk_counted = njit(cache=False)(_walk)
_walk_free = njit(cache=False, **NO_REFCOUNT)(_walk)


def test_no_refcount_leaves_no_reference_counts_and_refuses_allocation():
    a, b = np.arange(6.0), np.ones(2)
    assert _walk_counted((a, b), 1) == _walk_free((a, b), 1) == 15.0
    assert _incref_sites(_walk_counted) > 0  # what the option removes
    assert _incref_sites(_walk_free) == 0

    @njit(cache=False, **NO_REFCOUNT)
    def alloc(n):
        return np.zeros(n).sum()

    with pytest.raises(TypingError):
        alloc(3)
