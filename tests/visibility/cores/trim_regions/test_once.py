"""``Once``: a view's renders from v* are made by one thread, whichever asks first, and a
caller waits only for a computation that is running, with real threads."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from visibility.cores.trim_regions.once import Once


def test_many_threads_asking_at_once_compute_it_once_and_all_get_its_value():
    calls = []
    gate = threading.Event()

    def work():
        calls.append(threading.get_ident())
        gate.wait(5)
        return 42

    once = Once(work)
    with ThreadPoolExecutor(8) as pool:
        futures = [pool.submit(once.get) for _ in range(8)]
        gate.set()
        values = [f.result(10) for f in futures]
    assert values == [42] * 8
    assert len(calls) == 1


def test_run_says_whether_this_call_computed_it():
    once = Once(lambda: "v")
    assert once.run() is True
    assert once.run() is False
    assert once.get() == "v"


def test_a_caller_waits_for_the_thread_that_is_computing_it():
    started = threading.Event()
    release = threading.Event()
    order = []

    def work():
        started.set()
        release.wait(5)
        order.append("computed")
        return 1

    once = Once(work)
    worker = threading.Thread(target=once.run)
    worker.start()
    assert started.wait(5)
    # Claimed by the worker: this call does not compute it, and get waits for the worker.
    assert once.run() is False
    threading.Timer(0.05, release.set).start()
    assert once.get() == 1
    order.append("got")
    worker.join(5)
    assert order == ["computed", "got"]


def test_an_error_reaches_every_caller():
    def fail():
        raise ValueError("render failed")

    once = Once(fail)
    with pytest.raises(ValueError, match="render failed"):
        once.run()
    with pytest.raises(ValueError, match="render failed"):
        once.get()


def test_closed_before_it_began_it_never_runs():
    calls = []
    once = Once(lambda: calls.append(1))
    once.close()
    assert once.run() is False
    with pytest.raises(RuntimeError, match="closed"):
        once.get()
    assert calls == []


def test_close_waits_for_the_thread_computing_it():
    # What the computation reads may be released once close returns.
    started = threading.Event()
    release = threading.Event()
    state = {"reading": False}

    def work():
        state["reading"] = True
        started.set()
        release.wait(5)
        state["reading"] = False

    once = Once(work)
    worker = threading.Thread(target=once.run)
    worker.start()
    assert started.wait(5)
    threading.Timer(0.05, release.set).start()
    once.close()
    assert state["reading"] is False
    worker.join(5)
