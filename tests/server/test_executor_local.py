"""The local executor gives each concurrent computation its share of the CPUs for its parallel
kernels, in the computing thread only (numba's thread count is per thread)."""

from __future__ import annotations

import os
import threading

import numba

from server.catalog import SceneCatalog
from server.executor import LocalExecutor, kernel_threads
from visibility.cores.base import get_core
from visibility.generators import make_scene


def test_kernel_threads_share_the_cpus():
    cpus = os.cpu_count() or 1
    assert kernel_threads(1) == cpus
    assert kernel_threads(cpus) == 1
    assert kernel_threads(4 * cpus) == 1 and kernel_threads(0) == cpus


def test_a_computation_runs_its_kernels_on_its_share(settings):
    catalog = SceneCatalog(settings)
    catalog.register("v", make_scene("village", 2000, seed=0))
    loaded = catalog.get("v")
    core = get_core("sampling")
    ex = LocalExecutor(workers=2 * (os.cpu_count() or 1))
    seen = {}

    def work():
        ex.compute(loaded, core, core.make_params(samples=2, resolution=16),
                   cell=loaded.grid.cell(0))
        seen["worker"] = numba.get_num_threads()

    before = numba.get_num_threads()
    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen["worker"] == 1
    assert numba.get_num_threads() == before  # other threads keep theirs
