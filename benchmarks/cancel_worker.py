"""The worker process of ``benchmarks.bench_cancel``'s kill-and-replace measurements.

A process that imports numpy, numba and the cores, receives a pickled scene, warms its core up
(numba loads or compiles its kernels) and then computes jobs sent over a pipe until told to stop
or killed. Every phase is stamped with ``time.monotonic()`` (CLOCK_MONOTONIC: one clock for all
processes of the machine), so the parent can say what a replacement costs phase by phase.

Only the standard library is imported at module level, on purpose: a spawned or forked child
imports this module before ``serve`` starts, and the imports it pays for are what ``serve``
times. Not meant to be run by hand; usage is ``bench_cancel``'s ``start_worker``::

    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    ctx.Process(target=serve, args=(child, "sampling", box, {"samples": 1})).start()

Messages (parent -> worker): scene bytes (``send_bytes``) once after "imported";
``("job", box, params)``; ``("ship", None, None)`` followed by scene bytes (a scene shipped per
job: the worker unpickles it and answers how long that took); ``("stop", None, None)``.
Answers (worker -> parent): ``("imported", marks)``, ``("ready", marks)``, ``("started", t)``,
``("done", ids_bytes, seconds)``, ``("shipped", seconds, nbytes)``, ``("error", text)``.
"""

from __future__ import annotations

import time
from typing import Any


def serve(conn: Any, core_name: str, box: list[list[float]], warm_params: dict[str, Any]) -> None:
    """Run the worker: import, receive the scene, warm up, then answer jobs.

    Parameters
    ----------
    conn : the worker's end of a ``multiprocessing.Pipe``.
    core_name : the core (``visibility.cores.base.get_core``) the worker computes with.
    box : the viewcell [min, max] (metres) of the warm-up computation.
    warm_params : the core parameters of the warm-up computation (small: it only has to make
        numba load the kernels and the core build its per-scene caches).
    """
    marks: list[tuple[str, float]] = [("boot", time.monotonic())]
    try:
        import numpy as np

        marks.append(("numpy", time.monotonic()))
        import numba  # noqa: F401  (timed on its own: the JIT runtime is most of the import)

        marks.append(("numba", time.monotonic()))
        import pickle

        from visibility.cores.base import get_core
        from visibility.viewcells import Viewcell

        core = get_core(core_name)  # imports every core package (discover), as the server does
        marks.append(("cores", time.monotonic()))
        conn.send(("imported", marks))
        scene = pickle.loads(conn.recv_bytes())
        marks.append(("scene", time.monotonic()))
        cell = Viewcell(np.asarray(box, dtype=np.float64))
        core.compute(scene, cell, core.make_params(**warm_params))
        marks.append(("warm", time.monotonic()))
        conn.send(("ready", marks))
        while True:
            kind, a, b = conn.recv()
            if kind == "stop":
                return
            if kind == "ship":
                data = conn.recv_bytes()
                t0 = time.monotonic()
                pickle.loads(data)
                conn.send(("shipped", time.monotonic() - t0, len(data)))
                continue
            conn.send(("started", time.monotonic()))
            t0 = time.monotonic()
            pvs = core.compute(scene, Viewcell(np.asarray(a, dtype=np.float64)),
                               core.make_params(**b))
            conn.send(("done", pvs.triangle_ids.tobytes(), time.monotonic() - t0))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        return
    except Exception as exc:  # the parent must hear why, not wait forever
        try:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        except OSError:
            pass
