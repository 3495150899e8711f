"""Memory of a served scene: what loading a generated scene, building its grid and computing one
``sampling`` cell costs the server process, in bytes per triangle.

Each size runs in a fresh subprocess (so one size's freed pages, allocator state and caches never
count against the next). The child does what the server does with a scene:

``runtime``  imports the server and warms the rasterizer up on a tiny scene (numba kernels loaded
             or compiled): the process's baseline, subtracted from everything per triangle.
``load``     ``SceneCatalog(Settings(generated={generator: n})).get(generator)``: the generator,
             the scene's validity mask and summary, the ``ViewcellGrid``, the 2.5D analysis.
``server``   what the server derives per scene on first use: the fingerprint (disk and Redis
             keys), the wire origin (every geometry frame), the valid count (the handshake), and
             the triangle centroids a streaming session keeps (``server.app.ServerState``).
``hierarchy`` the scene's spatial hierarchy (``visibility.raster.hierarchy.scene_hierarchy``),
             which the server builds in the background as a scene loads and every
             rasterizing path culls with.
``sampling`` one cell of ``get_core("sampling")`` at the server's default parameters
             (``--cells K``: K cells one after the other, a stage each).

Memory is read from ``/proc/self/status`` (VmHWM: the peak resident set, VmRSS, and its anonymous
and file-backed parts, so mapped files count) and ``/proc/self/smaps_rollup``. The peak of each
stage is its own (the kernel's peak counter is reset between stages through
``/proc/self/clear_refs``). The breakdown lists every array the loaded scene keeps (``nbytes``)
and, per stage, the transient: the stage's peak above what it left resident.

Usage: ``python -m benchmarks.bench_memory`` (city at 1M and 4M triangles), ``--big`` adds 16M
(minutes), ``--sizes 200000 ...`` picks others, ``--files a.glb ...`` measures scene files too
(served from their folder, sidecars and walk-area detection included), ``--tag NAME`` writes
``benchmarks/results/NAME.md`` and ``.json`` (default ``memory``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"
DEFAULT_SIZES = (1_000_000, 4_000_000)
BIG_SIZE = 16_000_000
MIB = 1 << 20
#: The issue's targets: bytes per triangle of a loaded scene with its spatial hierarchy, and
#: the peak of the 16M city served.
TARGET_BYTES_PER_TRIANGLE = 150
TARGET_PEAK_16M = 2.5e9


# ----------------------------------------------------------------------------------- /proc
def read_status() -> dict[str, int]:
    """Bytes of VmHWM, VmRSS, RssAnon, RssFile and RssShmem from /proc/self/status."""
    out: dict[str, int] = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("VmHWM", "VmRSS", "RssAnon", "RssFile", "RssShmem"):
                out[key] = int(value.split()[0]) * 1024
    return out


def read_smaps_rollup() -> dict[str, int]:
    """Bytes of Rss, Pss, Anonymous and the private/shared parts from /proc/self/smaps_rollup
    (empty where the kernel has none)."""
    out: dict[str, int] = {}
    try:
        with open("/proc/self/smaps_rollup") as fh:
            for line in fh:
                parts = line.split()
                if len(parts) == 3 and parts[2] == "kB":
                    out[parts[0].rstrip(":")] = int(parts[1]) * 1024
    except OSError:
        pass
    return out


def reset_peak() -> bool:
    """Reset the kernel's peak resident set (VmHWM) to the current one; False when the kernel
    refuses (then every stage's peak is the process's peak so far)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        return False
    return True


# ----------------------------------------------------------------------------------- the child
def _arrays_of(obj: Any, prefix: str, out: dict[str, int], depth: int = 0) -> None:
    """Add ``nbytes`` of every numpy array reachable from ``obj`` (dicts, lists, tuples and
    plain objects, three levels deep) to ``out`` under a dotted name."""
    if depth > 3 or obj is None:
        return
    if isinstance(obj, np.ndarray):
        out[prefix] = out.get(prefix, 0) + int(obj.nbytes)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _arrays_of(v, f"{prefix}.{k}", out, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _arrays_of(v, f"{prefix}[{i}]", out, depth + 1)
    elif hasattr(obj, "__dict__") and not isinstance(obj, type):
        for k, v in vars(obj).items():
            _arrays_of(v, f"{prefix}.{k}", out, depth + 1)


def kept_arrays(loaded: Any, centroids: np.ndarray | None) -> dict[str, int]:
    """Bytes of each array the server keeps for ``loaded`` (a ``server.catalog.LoadedScene``):
    the scene's, the grid's, the per-scene caches' and the session centroids."""
    from server import catalog
    from visibility import scene_analysis, scene_cache

    scene = loaded.scene
    out: dict[str, int] = {}
    for name in ("vertices", "faces", "object_ids", "colors", "_valid", "states", "state_times",
                 "sphere_centers", "sphere_radii", "sphere_colors"):
        arr = getattr(scene, name, None)
        if isinstance(arr, np.ndarray):
            out[f"scene.{name.lstrip('_')}"] = int(arr.nbytes)
    for name, arr in vars(scene).items():
        if isinstance(arr, np.ndarray) and f"scene.{name.lstrip('_')}" not in out:
            out[f"scene.{name.lstrip('_')}"] = int(arr.nbytes)
    if scene.walk is not None:
        out["scene.walk.rects"] = int(scene.walk.rects.nbytes)
    _arrays_of(scene.meta, "scene.meta", out)
    grid = loaded.grid
    for name, arr in vars(grid).items():
        if isinstance(arr, np.ndarray):
            out[f"grid.{name.lstrip('_')}"] = int(arr.nbytes)
    _arrays_of(scene_cache._CACHE.get(scene), "per_scene_cache", out)
    _arrays_of(getattr(scene_analysis, "_CACHE", {}).get(scene), "analysis_2_5d", out)
    origin = catalog._ORIGINS.get(scene)
    if origin is not None:
        out["wire_origin"] = int(origin.nbytes)
    if centroids is not None:
        out["server.centroids"] = int(centroids.nbytes)
    from visibility.raster import triangles as raster

    _arrays_of(getattr(raster._SCRATCH, "pool", None), "raster_scratch", out)
    return {k: v for k, v in out.items() if v}


class Stages:
    """Records the memory after each stage and each stage's own peak."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []
        self.can_reset = reset_peak()
        self._t = time.perf_counter()

    def mark(self, name: str) -> dict[str, Any]:
        st = read_status()
        row = {"stage": name, "seconds": round(time.perf_counter() - self._t, 3),
               "peak": st["VmHWM"], "rss": st["VmRSS"], "anon": st.get("RssAnon", 0),
               "file": st.get("RssFile", 0), "shmem": st.get("RssShmem", 0)}
        self.rows.append(row)
        reset_peak()
        self._t = time.perf_counter()
        return row


def measure(generator: str, triangles: int, file: Path | None = None,
            cells: int = 1) -> dict[str, Any]:
    """Load ``generator`` at ``triangles`` (or the scene ``file``, served from its folder)
    through the catalogue, derive what the server derives, compute ``cells`` sampling cells
    (one stage each); the memory of each stage (see the module docstring)."""
    from types import SimpleNamespace

    from server.app import ServerState
    from server.catalog import SceneCatalog, wire_origin
    from server.settings import Settings
    from visibility.cores.base import get_core
    from visibility.generators import make_scene
    from visibility.raster.hierarchy import scene_hierarchy
    from visibility.viewcells import ViewcellGrid, spread_evenly

    core = get_core("sampling")
    params = core.make_params()
    tiny = make_scene("city", 1000, seed=1)
    tiny_grid = ViewcellGrid.for_scene(tiny)
    core.compute(tiny, tiny_grid.cell(len(tiny_grid) // 2), params)
    del tiny, tiny_grid

    stages = Stages()
    base = stages.mark("runtime")
    if file is None:
        catalog = SceneCatalog(Settings(generated={generator: triangles}, scenes_dir=None))
        loaded = catalog.get(generator)
    else:
        from visibility.loaders import load_scene  # noqa: F401 - imported before measuring

        catalog = SceneCatalog(Settings(generated={}, scenes_dir=file.parent))
        loaded = catalog.get(file.stem)
    scene, grid = loaded.scene, loaded.grid
    stages.mark("load")
    _ = loaded.fingerprint
    wire_origin(scene)
    int(np.count_nonzero(scene.valid_faces))
    # The session centroids, through the server's own method (only its cache dict is needed).
    holder = SimpleNamespace(_centroids={})
    centroids = ServerState.centroids(holder, loaded)
    stages.mark("server")
    scene_hierarchy(scene)
    stages.mark("hierarchy")
    picks = [len(grid) // 2] + [c for c in spread_evenly(np.arange(len(grid)), cells)
                                 if c != len(grid) // 2][:cells - 1]
    for i, cell in enumerate(picks):
        pvs = core.compute(scene, grid.cell(cell), params)
        stages.mark("sampling" if i == 0 else f"sampling {i + 1}")
    arrays = kept_arrays(loaded, centroids)
    n = scene.n_triangles
    return {
        "generator": generator if file is None else file.name,
        "requested": triangles if file is None else n, "triangles": n,
        "vertices": scene.n_vertices, "cells": len(grid), "cell": picks,
        "params": params.as_dict(), "pvs": len(pvs.triangle_ids),
        "peak_reset": stages.can_reset, "baseline_rss": base["rss"],
        "stages": stages.rows, "arrays": arrays, "smaps_rollup": read_smaps_rollup(),
        "process_peak": max(r["peak"] for r in stages.rows),
    }


# ----------------------------------------------------------------------------------- report
def derive(res: dict[str, Any]) -> dict[str, Any]:
    """Per-triangle figures of one child's result: steady and peak bytes per triangle above the
    runtime baseline, and the transient of each stage."""
    n = res["triangles"]
    base = res["baseline_rss"]
    rows = {r["stage"]: r for r in res["stages"]}
    kept = sum(res["arrays"].values())
    load_rss = rows["load"]["rss"]
    out = {
        "kept_arrays_bytes": kept,
        "kept_arrays_per_triangle": kept / n,
        "loaded_rss_per_triangle": (load_rss - base) / n,
        "served_rss_per_triangle": (res["stages"][-1]["rss"] - base) / n,
        "peak_per_triangle": (res["process_peak"] - base) / n,
        # Freed memory the allocator kept: resident, yet no array holds it.
        "allocator_held": res["stages"][-1]["rss"] - base - kept,
        "transient": {},
    }
    prev = base
    for r in res["stages"][1:]:
        out["transient"][r["stage"]] = {"above_before": r["peak"] - prev,
                                        "above_after": r["peak"] - r["rss"]}
        prev = r["rss"]
    return out


def _mb(b: float) -> str:
    return f"{b / MIB:,.0f}"


def report(results: list[dict[str, Any]], argv: list[str], header: str) -> str:
    """The markdown report of every size's result."""
    cmd = "python -m benchmarks.bench_memory " + " ".join(shlex.quote(a) for a in argv)
    lines = [f"`{cmd.strip()}`", "", header, ""]
    lines += ["MiB of process memory (VmHWM peaks, VmRSS resident incl. file-backed pages); "
              "B/tri are bytes per triangle above the runtime baseline (python, numpy, numba "
              "kernels loaded).", ""]
    lines += ["| scene | triangles | vertices | cells | runtime MiB | loaded MiB | served MiB | "
              "peak MiB | kept arrays B/tri | loaded B/tri | served B/tri | peak B/tri |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for res in results:
        d = res["derived"]
        rows = {r["stage"]: r for r in res["stages"]}
        lines.append(
            f"| {res['generator']} {res['requested']:,} | {res['triangles']:,} | "
            f"{res['vertices']:,} | {res['cells']:,} | {_mb(res['baseline_rss'])} | "
            f"{_mb(rows['load']['rss'])} | {_mb(res['stages'][-1]['rss'])} | "
            f"{_mb(res['process_peak'])} | {d['kept_arrays_per_triangle']:.1f} | "
            f"{d['loaded_rss_per_triangle']:.1f} | {d['served_rss_per_triangle']:.1f} | "
            f"{d['peak_per_triangle']:.1f} |")
    for res in results:
        d = res["derived"]
        n = res["triangles"]
        lines += ["", f"### {res['generator']} {res['requested']:,} "
                  f"({n:,} triangles, {res['vertices']:,} vertices)", "",
                  "| stage | seconds | peak MiB | resident MiB | anon MiB | file MiB | "
                  "peak above start B/tri | peak above end B/tri |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in res["stages"]:
            t = d["transient"].get(r["stage"])
            extra = (f"{t['above_before'] / n:.1f} | {t['above_after'] / n:.1f}" if t
                     else "- | -")
            lines.append(f"| {r['stage']} | {r['seconds']:.1f} | {_mb(r['peak'])} | "
                         f"{_mb(r['rss'])} | {_mb(r['anon'])} | {_mb(r['file'])} | {extra} |")
        lines += ["", "| kept array | MiB | B/tri |", "|---|---:|---:|"]
        for name, b in sorted(res["arrays"].items(), key=lambda kv: -kv[1]):
            if b >= 1024:
                lines.append(f"| {name} | {b / MIB:.1f} | {b / n:.2f} |")
        lines.append(f"| **all kept arrays** | {d['kept_arrays_bytes'] / MIB:.1f} | "
                     f"{d['kept_arrays_per_triangle']:.2f} |")
        lines.append(f"| freed, still resident (allocator) | {d['allocator_held'] / MIB:.1f} | "
                     f"{d['allocator_held'] / n:.2f} |")
        if not res["peak_reset"]:
            lines += ["", "(the kernel refused to reset VmHWM: each stage's peak is the "
                      "process's peak so far)"]
    big = [r for r in results if r["triangles"] >= 0.9 * BIG_SIZE]
    lines += ["", f"Targets: kept arrays B/tri <= {TARGET_BYTES_PER_TRIANGLE} "
              f"(the scene with its spatial hierarchy); the {BIG_SIZE / 1e6:.0f}M city served "
              f"with a peak <= {TARGET_PEAK_16M / 1e9:.1f} GB."]
    for r in big:
        ok = r["process_peak"] <= TARGET_PEAK_16M
        lines.append(f"{r['triangles']:,} triangles: process peak {r['process_peak'] / 1e9:.2f} "
                     f"GB ({'met' if ok else 'NOT met'}).")
    return "\n".join(lines) + "\n"


def run_child(generator: str, triangles: int, timeout: float, file: Path | None = None,
              cells: int = 1) -> dict[str, Any]:
    """``measure`` in a fresh interpreter; its result."""
    cmd = [sys.executable, "-m", "benchmarks.bench_memory", "--child", generator,
           str(triangles), "--cells", str(cells)]
    cmd += [] if file is None else ["--child-file", str(file.resolve())]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                          cwd=Path(__file__).resolve().parent.parent)
    if proc.returncode != 0:
        raise RuntimeError(f"{generator} {triangles}: child failed ({proc.returncode}):\n"
                           f"{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def machine() -> str:
    """One line naming the CPU, cores, memory and library versions."""
    import numba

    cpu = platform.processor() or platform.machine()
    mem = "?"
    try:
        text = Path("/proc/cpuinfo").read_text()
        cpu = next(ln.split(":", 1)[1].strip() for ln in text.splitlines()
                   if ln.startswith("model name"))
        kb = next(int(ln.split()[1]) for ln in Path("/proc/meminfo").read_text().splitlines()
                  if ln.startswith("MemTotal"))
        mem = f"{kb / (1 << 20):.0f}"
    except (OSError, StopIteration):
        pass
    return (f"{cpu}, {os.cpu_count()} logical cores, {mem} GiB RAM; {platform.system()} "
            f"{platform.release()}; Python {platform.python_version()}, numpy {np.__version__}, "
            f"numba {numba.__version__}")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (see the module docstring); 0 on success."""
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES),
                    help="triangle counts to measure (each in a fresh process)")
    ap.add_argument("--big", action="store_true", help=f"add {BIG_SIZE:,} triangles")
    ap.add_argument("--generator", default="city", help="generated scene to load")
    ap.add_argument("--tag", default="memory", help="results file stem")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR, help="results folder")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per size")
    ap.add_argument("--files", type=Path, nargs="+", default=[],
                    help="scene files to measure too, each served from its own folder")
    ap.add_argument("--cells", type=int, default=1,
                    help="sampling cells computed one after the other (a stage each)")
    ap.add_argument("--child", nargs=2, metavar=("GENERATOR", "TRIANGLES"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--child-file", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.child[0], int(args.child[1]), args.child_file,
                                 args.cells)))
        return 0
    sizes = list(args.sizes) + ([BIG_SIZE] if args.big and BIG_SIZE not in args.sizes else [])
    jobs = [(n, None) for n in sizes] + [(0, f) for f in args.files]
    results = []
    for n, file in jobs:
        print(f"{file.name if file else f'{args.generator} {n:,}'} ...", flush=True)
        res = run_child(args.generator, n, args.timeout, file, args.cells)
        res["derived"] = derive(res)
        results.append(res)
        d = res["derived"]
        print(f"  {res['triangles']:,} triangles: peak {res['process_peak'] / MIB:,.0f} MiB, "
              f"kept {d['kept_arrays_per_triangle']:.1f} B/tri, loaded "
              f"{d['loaded_rss_per_triangle']:.1f} B/tri, peak {d['peak_per_triangle']:.1f} "
              f"B/tri", flush=True)
    header = f"{time.strftime('%Y-%m-%d %H:%M')}; {machine()}"
    text = report(results, argv, header)
    # Written before printing: a closed stdout (piped into head) must not lose the results.
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.tag}.md").write_text(text)
    (args.out / f"{args.tag}.json").write_text(json.dumps(
        {"command": ["python", "-m", "benchmarks.bench_memory", *argv], "header": header,
         "results": results}, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
