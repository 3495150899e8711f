"""Where a PVS computation runs: in the server's own worker threads (``LocalExecutor``, the
default) or on a Dask cluster (``server.dask_executor.DaskExecutor``, ``executor =
"dask://host:8786"``).

``ComputeService`` keeps everything around a computation (cache, shared in-flight requests,
admission, the priority pool that orders the work) and hands only the computation itself to its
executor, so both executors give the same answers under the same keys. ``distributed`` is
imported only when a Dask executor is made: the default path never loads it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from server.executor_address import LOCAL, scheduler_address, workers_load_scenes
from visibility.cancel import CancelToken
from visibility.cores.base import PVS, Core, CoreParams
from visibility.jobs import compute_region
from visibility.viewcells import Viewcell

if TYPE_CHECKING:
    from server.catalog import LoadedScene

class Executor(Protocol):
    """What ``ComputeService`` needs from the place computations run."""

    #: "local" or "dask".
    kind: str

    def compute(self, loaded: LoadedScene, core: Core, params: CoreParams, *,
                cell: Viewcell | None = None, segment: np.ndarray | None = None,
                token: CancelToken | None = None, priority: float = 0.0) -> PVS:
        """The PVS of viewcell ``cell`` or ``segment`` in the loaded scene, blocking the pool
        thread; stops with ``ComputationCancelled`` once ``token`` is cancelled or late.
        ``priority``: lower first (0: a walker needs it now)."""
        ...

    def slots(self) -> int:
        """Computations worth keeping under way at once (the pool's thread count)."""
        ...

    def state(self) -> dict[str, Any]:
        """What /health shows: the kind, where, and whether it is working."""
        ...

    def close(self) -> None:
        """Release connections (idempotent)."""
        ...


def kernel_threads(workers: int) -> int:
    """Threads each of ``workers`` concurrent computations may give its parallel kernels: the
    CPUs shared out, at least one. More would put more threads than CPUs on the machine, and
    a parallel kernel then waits at its barriers for threads the others have descheduled."""
    return max(1, (os.cpu_count() or 1) // max(1, int(workers)))


class LocalExecutor:
    """Computes in the calling thread: the pool's threads are the workers (numba kernels
    release the GIL), each giving its kernels ``kernel_threads(workers)`` threads."""

    kind = LOCAL

    def __init__(self, workers: int = 1) -> None:
        self.workers = int(workers)
        self.threads = kernel_threads(self.workers)

    def compute(self, loaded: LoadedScene, core: Core, params: CoreParams, *,
                cell: Viewcell | None = None, segment: np.ndarray | None = None,
                token: CancelToken | None = None, priority: float = 0.0) -> PVS:
        """``visibility.jobs.compute_region`` here and now (``priority`` is the pool's
        business)."""
        import numba

        # Per thread (numba's setting is thread-local): this worker's share of the CPUs.
        numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
        return compute_region(loaded.scene, core, params, cell, segment, token)

    def slots(self) -> int:
        """The configured worker count."""
        return self.workers

    def state(self) -> dict[str, Any]:
        """``{"kind": "local", "state": "running", "workers": n}``."""
        return {"kind": LOCAL, "state": "running", "workers": self.workers}

    def close(self) -> None:
        """Nothing to release."""


def make_executor(executor: str, workers: int, scenes_dir: Path | None = None) -> Executor:
    """The executor an ``executor`` setting names; ``workers``: local computations at once
    (also the Dask executor's fallback while its scheduler is away); ``scenes_dir``: where the
    server's scene files are (for ``?scenes=load``)."""
    address = scheduler_address(executor)
    if address is None:
        return LocalExecutor(workers)
    from server.dask_executor import DaskExecutor

    return DaskExecutor(address, workers, name=executor.strip(),
                        load_scenes=workers_load_scenes(executor), scenes_dir=scenes_dir)
