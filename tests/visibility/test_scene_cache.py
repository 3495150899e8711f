"""Tests of ``visibility.scene_cache``'s file helpers (``save_npz``, ``load_npz``)."""

from __future__ import annotations

import gc
import sys
import threading
import time
import zipfile

import numpy as np
import pytest

from visibility.scene_cache import load_npz, save_npz


class _Finalized:
    """Garbage whose finalizer runs Python code: a collection in the middle of numpy's header
    parsing then lets another thread run, as a busy server's garbage does."""

    def __del__(self) -> None:
        total = 0
        for i in range(50):
            total += i


@pytest.fixture
def eager_thread_switches():
    """Threads switching every microsecond and the garbage collector running every 50
    allocations, restored afterwards."""
    interval, thresholds = sys.getswitchinterval(), gc.get_threshold()
    sys.setswitchinterval(1e-6)
    gc.set_threshold(50, 1, 1)
    yield
    sys.setswitchinterval(interval)
    gc.set_threshold(*thresholds)


def test_save_then_load_gives_the_arrays_back(tmp_path):
    arrays = {"format": np.array("x-1"), "ids": np.arange(7, dtype=np.int32),
              "boxes": np.zeros((2, 2, 3))}
    save_npz(tmp_path / "sub" / "a.npz", **arrays)
    got = load_npz(tmp_path / "sub" / "a.npz")
    assert sorted(got) == sorted(arrays)
    for name, a in arrays.items():
        np.testing.assert_array_equal(got[name], a)
        assert got[name].dtype == a.dtype


def test_load_npz_refuses_pickles_and_raises_for_a_damaged_file(tmp_path):
    np.savez(tmp_path / "p.npz", obj=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError):
        load_npz(tmp_path / "p.npz")
    good = tmp_path / "g.npz"
    save_npz(good, ids=np.arange(1000))
    (tmp_path / "cut.npz").write_bytes(good.read_bytes()[:300])
    with pytest.raises(zipfile.BadZipFile):
        load_npz(tmp_path / "cut.npz")


def test_many_threads_read_at_once_without_a_spurious_error(tmp_path, eager_thread_switches):
    # Without the lock, numpy.load from four threads under these conditions raised
    # SystemError ("AST constructor recursion depth mismatch") within seconds on CPython 3.11.
    path = tmp_path / "a.npz"
    save_npz(path, format=np.array("x-1"), ids=np.arange(10, dtype=np.int32),
             boxes=np.zeros((3, 3)))
    errors: list[BaseException] = []
    reads = [0] * 4
    stop = time.perf_counter() + 4.0

    def read(slot: int) -> None:
        while time.perf_counter() < stop and not errors:
            a, b = _Finalized(), _Finalized()
            a.other, b.other = b, a  # a cycle: only the collector frees it
            try:
                got = load_npz(path)
            except BaseException as exc:  # noqa: BLE001 - any error here is the failure
                errors.append(exc)
                return
            assert int(got["ids"][-1]) == 9
            reads[slot] += 1

    threads = [threading.Thread(target=read, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, repr(errors[0])
    assert min(reads) > 0
