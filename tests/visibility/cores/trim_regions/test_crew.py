"""``Crew``: a view takes one numba thread while views are queued or run beside it, and the
idle workers' threads once it runs alone."""

from __future__ import annotations

import threading

import numba

from visibility.cores.trim_regions.crew import Crew


def test_a_view_gets_the_idle_workers_threads_once_the_queue_is_empty():
    crew = Crew(2)
    crew.queue(3)
    crew.start()
    crew.start()
    assert crew.threads() == 1  # a view still queued
    crew.finish()
    crew.start()
    assert crew.threads() == 1  # two run: one thread each
    crew.finish()
    assert crew.threads() == 2  # alone, the queue empty: both workers' threads
    crew.finish()
    assert crew.threads() == 1


def test_lend_sets_the_calling_threads_numba_threads_and_finish_gives_them_back():
    crew = Crew(numba.config.NUMBA_NUM_THREADS)
    crew.queue(1)
    seen: list[int] = []

    def view() -> None:
        crew.start()
        seen.append(numba.get_num_threads())
        seen.append(crew.lend())
        seen.append(numba.get_num_threads())
        crew.finish()
        seen.append(numba.get_num_threads())

    t = threading.Thread(target=view)
    t.start()
    t.join()
    n = numba.config.NUMBA_NUM_THREADS
    assert seen == [1, n, n, 1]
