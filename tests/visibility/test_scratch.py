"""``Scratch``: named buffers reused while they fit, grown when they do not, kept up to a cap."""

from __future__ import annotations

import numpy as np

from visibility.scratch import Scratch


def test_a_buffer_is_reused_while_it_fits_and_grown_when_it_does_not():
    s = Scratch()
    a = s.array("poly", (10, 4, 3))
    assert a.shape == (10, 4, 3) and a.dtype == np.float64
    b = s.array("poly", (6, 4, 3))  # smaller: the same memory
    assert np.shares_memory(a, b)
    c = s.array("poly", (20, 4, 3))  # larger: a new buffer, kept from now on
    assert not np.shares_memory(a, c) and np.shares_memory(c, s.array("poly", 5))
    d = s.array("poly", 5, np.int64)  # another dtype: a new buffer
    assert d.dtype == np.int64 and not np.shares_memory(c, d)
    assert not np.shares_memory(s.array("other", 5), d)  # names do not share


def test_a_buffer_over_the_cap_is_not_kept_and_release_drops_the_rest():
    s = Scratch(keep=100)
    big = s.array("big", 100)  # 800 bytes: handed out, not kept
    assert not np.shares_memory(big, s.array("big", 100))
    small = s.array("small", 10)
    assert np.shares_memory(small, s.array("small", 10))
    s.release()
    assert not np.shares_memory(small, s.array("small", 10))
