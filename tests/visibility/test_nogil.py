"""Every numba kernel of the project releases the GIL: cores run on a server's worker threads
beside the event loop and the first answers' worker, and a kernel holding the GIL stalls every
walker for as long as it runs (``cell_walk`` once took minutes on a big cell so)."""

from __future__ import annotations

import importlib
import pkgutil

from numba.core.registry import CPUDispatcher

import client
import visibility


def _kernels():
    for pkg in (visibility, client):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            mod = importlib.import_module(info.name)
            for name, attr in vars(mod).items():
                if isinstance(attr, CPUDispatcher) and attr.py_func.__module__ == info.name:
                    yield f"{info.name}.{name}", attr


def test_every_kernel_called_from_python_releases_the_gil():
    kernels = dict(_kernels())
    assert len(kernels) > 100  # the walk found the cores' kernels
    # Inlined helpers are compiled into their callers; only what Python calls matters.
    held = sorted(k for k, d in kernels.items()
                  if d.targetoptions.get("inline", "never") != "always"
                  and not d.targetoptions.get("nogil", False))
    assert held == []
