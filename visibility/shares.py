"""A kernel's shares of work run on threads at once, in place of a numba ``prange`` loop.

A ``prange`` loop whose body calls one large kernel makes numba compile that kernel's code a
second time, into the parallel loop's own library, where LLVM optimizes and emits all of it
again, and numba's parallel passes add their own (``docs/cores.md``, writing a core). A
kernel compiled ``nogil=True`` releases the GIL while it runs, so calling it once per share
from Python threads runs the shares at once as the loop did, without those costs.
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable
from typing import Any

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

_lock = threading.Lock()
#: The process's share threads' queue of (kernel, args, share, shares, done), and the process
#: that made them (a forked child inherits the queue but none of its threads).
_jobs: queue.SimpleQueue | None = None
_jobs_pid = -1


def _serve(jobs: queue.SimpleQueue) -> None:
    """A share thread: run each share it takes, telling its caller it returned (or raised)."""
    while True:
        kernel, args, share, shares, done = jobs.get()
        try:
            kernel(*args, share, shares)
        except BaseException as error:  # the caller raises it
            done.put(error)
        else:
            done.put(None)


def _queue() -> queue.SimpleQueue:
    """The share threads' queue, with the threads started at first use in a process."""
    global _jobs, _jobs_pid
    with _lock:
        if _jobs is None or _jobs_pid != os.getpid():
            _jobs = queue.SimpleQueue()
            _jobs_pid = os.getpid()
            # Enough for a few computations at once, each running its shares beyond the first
            # here; more callers than that wait for a thread, they never deadlock (a share
            # waits on nothing).
            for k in range(max(4, 2 * (os.cpu_count() or 1))):
                threading.Thread(target=_serve, args=(_jobs,), name=f"share-{k}",
                                 daemon=True).start()
        return _jobs


def run_shares(kernel: Callable[..., Any], shares: int, *args: Any) -> None:
    """Call ``kernel(*args, share, shares)`` for every share in [0, shares): share 0 on the
    calling thread, the others on the process's share threads, at once when ``kernel``
    releases the GIL (numba ``nogil=True``) and a share thread is free (a share beyond them
    waits for one: slower, never stuck, since no share waits on another). Returns once every
    share has; an exception of any share is raised after all have returned (they write the
    same arrays). Never call it from a share: its shares would wait for threads its caller
    holds."""
    done: queue.SimpleQueue = queue.SimpleQueue()
    if shares > 1:
        jobs = _queue()
        for share in range(1, shares):
            jobs.put((kernel, args, share, shares, done))
    errors: list[BaseException] = []
    try:
        kernel(*args, 0, shares)
    except BaseException as error:
        errors.append(error)
    for _ in range(1, shares):
        error = done.get()
        if error is not None:
            errors.append(error)
    if errors:
        raise errors[0]


@intrinsic
def take_next(typingctx, counter):
    """Atomically add 1 to ``counter[0]`` (int64 array) and return its previous value, in a
    numba kernel: the shares hand themselves work items one at a time, so one share's costly
    items do not hold the others up (work ``run_shares`` splits unevenly)."""
    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary,
                                       [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", ptr, context.get_constant(types.int64, 1), "monotonic")
    return types.int64(counter), codegen
