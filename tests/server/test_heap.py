"""``server.heap.release_freed_memory``: freed heap pages go back to the operating system."""

from __future__ import annotations

import numpy as np

from server.heap import release_freed_memory


def _rss() -> int:
    with open("/proc/self/status") as fh:
        return next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmRSS"))


def test_freed_heap_pages_are_returned():
    # A freed 24 MB array raises glibc's mmap threshold, so later 1 MB arrays come from the
    # heap; freeing every other one leaves holes between live arrays, which the heap cannot
    # give back by shrinking.
    big = np.ones(24 << 20, np.uint8)
    del big
    n, size = 48, 1 << 20
    arrays = [np.ones(size, np.uint8) for _ in range(2 * n)]
    before = _rss()
    del arrays[1::2]
    held = _rss()
    assert release_freed_memory() is True
    after = _rss()
    assert before - held < size  # glibc keeps the freed pages resident...
    assert held - after >= 0.95 * n * size  # ...until they are released
    assert len(arrays) == n and all(a[-1] == 1 for a in arrays)  # the live ones are intact
