"""Where a core's CPU goes, numba kernels named: ``perf`` over a loop of computations.

``perf record`` sees compiled numba code as anonymous addresses. This tool writes the map
``perf`` reads for such code (``/tmp/perf-<pid>.map``: start, size and name of each compiled
kernel of the project's modules), then times ``--runs`` computations of one cell while
``perf record -g`` samples the process, and prints the symbols that took the most samples:
the kernels, and beside them what lies outside them (page faults in ``clear_page_erms``,
numpy's fills and fancy indexing, a BLAS pool spinning in ``blas_thread_server``, idle
cores). The trim_regions speed-ups of 2026-12 were found this way
(``docs/cores/trim_regions.md``).

A kernel's range runs to the next known entry point, so the bodies of its parallel loops and
its helpers that were not inlined usually count towards it, and now and then towards the
kernel loaded before them: read the names as close, not exact.

Usage::

    python -m benchmarks.perf_kernels --core trim_regions --scene kitchen --side 0.3
    python -m benchmarks.perf_kernels --core cos --scene city --triangles 100000 --side 4

Needs Linux ``perf`` (Debian: ``linux-perf``) and the right to sample its own process.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from pvs_cli import parse_params

#: Module prefixes whose compiled kernels are named in the map.
PREFIXES = ("visibility.",)


def kernel_symbols(prefixes: tuple[str, ...] = PREFIXES) -> list[tuple[int, str]]:
    """(address, name) of the compiled entry points (native and Python wrapper) of every numba
    dispatcher defined at module level in the loaded modules under ``prefixes``; names read
    ``module.function``. Only what has been compiled (or loaded from the cache) is there."""
    from numba.core.registry import CPUDispatcher

    out = set()
    for name, mod in list(sys.modules.items()):
        if mod is None or not name.startswith(prefixes):
            continue
        for attr in list(vars(mod).values()):
            if not isinstance(attr, CPUDispatcher) or attr.py_func.__module__ != name:
                continue
            label = f"{name.rsplit('.', 1)[-1]}.{attr.py_func.__qualname__}"
            for cres in list(attr.overloads.values()):
                for sym in (cres.fndesc.llvm_func_name, cres.fndesc.llvm_cpython_wrapper_name):
                    try:
                        addr = cres.library.get_pointer_to_function(sym)
                    except Exception:  # noqa: BLE001 - a symbol the library does not export
                        continue
                    if addr:
                        out.add((int(addr), label))
    return sorted(out)


def write_perf_map(path: Path | None = None, prefixes: tuple[str, ...] = PREFIXES,
                   max_size: int = 1 << 20) -> Path:
    """Write ``perf``'s map of this process's kernels (``kernel_symbols``): one line
    ``start size name`` (hex) per entry point, each running to the next (at most
    ``max_size`` bytes). Returns the path (``/tmp/perf-<pid>.map`` by default)."""
    path = Path(path) if path is not None else Path(f"/tmp/perf-{os.getpid()}.map")
    syms = kernel_symbols(prefixes)
    lines = []
    for k, (addr, name) in enumerate(syms):
        size = syms[k + 1][0] - addr if k + 1 < len(syms) else max_size
        lines.append(f"{addr:x} {min(max(size, 1), max_size):x} {name}")
    path.write_text("\n".join(lines) + ("\n" if lines else ""))
    return path


def _cell(args: argparse.Namespace) -> tuple[Any, Any]:
    from benchmarks.bench_trim_regions import load
    from visibility.ray_frames import first_open_cell
    from visibility.viewcells import Viewcell, ViewcellGrid

    scene = load(args.scene, args.triangles)
    grid = ViewcellGrid.for_scene(scene)
    c = grid.cell(first_open_cell(scene, grid, len(grid) // 2)).center
    height = args.side if args.height is None else args.height
    half = 0.5 * np.array([args.side, height, args.side])
    return scene, Viewcell(np.stack([c - half, c + half]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--core", default="trim_regions")
    ap.add_argument("--scene", default="village", help="a generated scene or one of "
                    "../shared/scenes (benchmarks.bench_trim_regions.load)")
    ap.add_argument("--triangles", type=int, default=None, help="generated scenes: size")
    ap.add_argument("--side", type=float, default=0.3, help="the cell's side, metres")
    ap.add_argument("--height", type=float, default=None,
                    help="the cell's height, metres (default: the side, a cube; the server's "
                         "cells are the eye range high, 0.4 m)")
    ap.add_argument("--runs", type=int, default=8, help="computations sampled")
    ap.add_argument("--top", type=int, default=30, help="symbols printed")
    ap.add_argument("--param", action="append", default=[], help="core parameter k=v")
    args = ap.parse_args(argv)
    perf = shutil.which("perf")
    if perf is None:
        print("perf is not installed (Debian: apt install linux-perf)", file=sys.stderr)
        return 2
    from visibility.cores.base import get_core

    scene, cell = _cell(args)
    core = get_core(args.core)
    params = core.make_params(**parse_params(args.param))
    # Two untimed runs: kernels compiled or loaded, per-scene builds done.
    for _ in range(2):
        core.compute(scene, cell, params)
    time.sleep(1.0)
    core.compute(scene, cell, params)
    mapped = write_perf_map()
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "perf.data"
        rec = subprocess.Popen([perf, "record", "-g", "-p", str(os.getpid()), "-o", str(data)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(0.5)
        t0 = time.perf_counter()
        for _ in range(args.runs):
            pvs = core.compute(scene, cell, params)
        seconds = (time.perf_counter() - t0) / args.runs
        rec.send_signal(2)
        _, err = rec.communicate(timeout=120)
        if not data.is_file():
            print(f"perf record failed: {err.decode(errors='replace').strip()}",
                  file=sys.stderr)
            return 1
        rep = subprocess.run([perf, "report", "-i", str(data), "--no-children", "--sort",
                              "sym", "-g", "none", "--stdio"], capture_output=True, text=True,
                             check=False)
    print(f"{args.core} on {args.scene}, a {args.side:g} m cell: {seconds:.3f} s a computation "
          f"over {args.runs} (perf attached), PVS {len(pvs):,}; kernels named from {mapped}")
    # The last computation's work counters, beside where the time went.
    counters = {k: v for k, v in pvs.stats.items()
                if isinstance(v, (int, np.integer)) and not isinstance(v, bool)}
    print("counters: " + ", ".join(f"{k} {v:,}" for k, v in sorted(counters.items())))
    rows = [ln for ln in rep.stdout.splitlines() if ln.strip() and not ln.startswith("#")]
    print("\n".join(rows[:args.top]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
