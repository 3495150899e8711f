"""What the scene hierarchy buys: a cell's cost against the scene's size, culled and not.

Run ``python -m benchmarks.bench_culling`` (city at 1M and 4M triangles and the real scenes),
``--sizes 1000000,4000000,16000000`` for the 16M city, ``--quick`` for a smoke run. For each
scene it builds the hierarchy (``visibility.raster.hierarchy``: time, bytes a triangle), then on
three 4 m cells spread over the middle of the scene (the scene's own cell size for real scenes):

- per cubemap (256 px, eyes drawn in the cell, random orientations): the full render's and the
  culled render's time, triangles drawn, nodes tested and hidden, triangles seen, and whether
  the two id buffers are identical (they must be);
- the ``sampling`` core at its defaults on the cell, culled and (up to ``--full-max``
  triangles) not, with the PVS size beside each time.

Prints the tables (command and machine on top), writes ``OUT/culling.md`` and ``.json`` and a
PNG of time per cell against scene size. Wall times on a shared machine vary: CPU seconds are
printed beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_SCENES = Path(__file__).resolve().parents[2] / "shared" / "scenes"


def _machine() -> str:
    import numba

    cpu = platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (f"{cpu}, {os.cpu_count()} CPUs, numba {numba.__version__} "
            f"({numba.get_num_threads()} threads), load average {os.getloadavg()[0]:.2f} at start")


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def _scenes(args: argparse.Namespace):
    """(label, scene, cell size) for each requested scene, loaded lazily."""
    from visibility.generators import make_scene
    from visibility.loaders import load_scene

    for n in [int(x) for x in args.sizes.split(",") if x]:
        yield f"city {n // 1_000_000}M" if n >= 1_000_000 else f"city {n // 1000}k", \
            (lambda n=n: make_scene("city", n)), 4.0
    for name in [x for x in args.real.split(",") if x]:
        path = next(SHARED_SCENES.glob(f"{name}.*[bf]"), None)
        if path is None:
            raise SystemExit(f"no scene file {name} in {SHARED_SCENES}")
        yield name, (lambda p=path: load_scene(p)), None


def _cells(grid, k: int) -> list[int]:
    """k cells near the middle of the grid (by centre), spread apart."""
    centres = grid.boxes.mean(axis=1)
    mid = np.median(centres, axis=0)
    order = np.argsort(np.linalg.norm((centres - mid)[:, [0, 2]], axis=1))
    picked: list[int] = []
    for c in order:
        if all(np.linalg.norm(centres[c] - centres[p]) > 12.0 for p in picked):
            picked.append(int(c))
        if len(picked) == k:
            break
    return picked


def run_scene(label: str, make, cell_size: float | None, args: argparse.Namespace) -> dict:
    from visibility.cores.base import get_core
    from visibility.raster import hierarchy as hmod
    from visibility.raster import render_cubemap_ids
    from visibility.raster.camera import random_rotation
    from visibility.scene import Scene
    from visibility.viewcells import ViewcellGrid

    hmod.MIN_TRIANGLES = 1 << 62  # no background build: this benchmark builds it itself
    scene, gen_s, _ = _timed(make)
    grid = ViewcellGrid.for_scene(scene, cell_size)
    h, build_s, build_cpu = _timed(lambda: hmod.scene_hierarchy(scene))
    out: dict[str, Any] = {"scene": label, "triangles": scene.n_triangles,
                           "cell_size": float(grid.cell_size), "load_seconds": gen_s,
                           "hierarchy_seconds": build_s, "hierarchy_cpu": build_cpu,
                           "hierarchy_bytes_per_triangle": h.nbytes / max(scene.n_triangles, 1),
                           "cells": []}
    print(f"{label}: {scene.n_triangles} triangles, {len(grid)} cells of {grid.cell_size:g} m; "
          f"hierarchy {build_s:.2f} s, {out['hierarchy_bytes_per_triangle']:.1f} B/triangle",
          flush=True)
    mask = scene.valid_faces
    core = get_core("sampling")
    params = core.make_params()
    rng = np.random.default_rng(args.seed)
    for cell in _cells(grid, args.cells):
        lo, hi = grid.boxes[cell]
        views = []
        for _ in range(args.views):
            eye, rot = lo + (hi - lo) * rng.random(3), random_rotation(rng)
            full, fw, fc = _timed(lambda e=eye, r=rot: render_cubemap_ids(
                scene.vertices, scene.faces, e, args.resolution, r, face_mask=mask))
            st: dict = {}
            culled, cw, cc = _timed(lambda e=eye, r=rot, st=st: render_cubemap_ids(
                scene.vertices, scene.faces, e, args.resolution, r, face_mask=mask,
                hierarchy=h, stats=st))
            views.append({"full_s": fw, "full_cpu": fc, "culled_s": cw, "culled_cpu": cc,
                          "identical": bool(np.array_equal(full, culled)),
                          "seen": int(len(np.unique(full)) - 1), **st})
        row: dict[str, Any] = {"cell": cell, "views": views}
        pvs, row["sampling_s"], row["sampling_cpu"] = _timed(
            lambda c=cell: core.compute(scene, grid.cell(c), params))
        row["pvs"] = len(pvs)
        if scene.n_triangles <= args.full_max:
            # The same arrays in another scene object: it has no hierarchy, so the sampling
            # core draws everything (MIN_TRIANGLES above keeps one from being built).
            bare = Scene(scene.vertices, scene.faces, scene.object_ids, scene.colors)
            full_pvs, row["sampling_full_s"], row["sampling_full_cpu"] = _timed(
                lambda c=cell, b=bare: core.compute(b, grid.cell(c), params))
            row["same_pvs"] = bool(np.array_equal(full_pvs.triangle_ids, pvs.triangle_ids))
        out["cells"].append(row)
        v = views
        print(f"  cell {cell}: view full {np.median([x['full_s'] for x in v]):.3f} s, culled "
              f"{np.median([x['culled_s'] for x in v]):.3f} s, drawn "
              f"{int(np.median([x['triangles'] for x in v]))}, seen "
              f"{int(np.median([x['seen'] for x in v]))}, identical "
              f"{all(x['identical'] for x in v)}; sampling {row['sampling_s']:.2f} s "
              f"(PVS {row['pvs']})"
              + (f", unculled {row['sampling_full_s']:.2f} s" if "sampling_full_s" in row
                 else ""), flush=True)
    return out


def tables(results: list[dict]) -> list[str]:
    lines = ["| scene | triangles | hierarchy s | B/triangle | view full s | view culled s | "
             "drawn | seen | nodes tested | identical | sampling cell s (culled) | "
             "sampling cell s (unculled) | PVS |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        v = [x for c in r["cells"] for x in c["views"]]
        med = {k: float(np.median([x[k] for x in v])) for k in
               ("full_s", "culled_s", "triangles", "seen", "nodes_tested")}
        samp = [c["sampling_s"] for c in r["cells"]]
        full = [c["sampling_full_s"] for c in r["cells"] if "sampling_full_s" in c]
        pvs = [c["pvs"] for c in r["cells"]]
        lines.append(
            f"| {r['scene']} | {r['triangles']:,} | {r['hierarchy_seconds']:.1f} | "
            f"{r['hierarchy_bytes_per_triangle']:.1f} | {med['full_s']:.3f} | "
            f"{med['culled_s']:.3f} | {int(med['triangles']):,} | {int(med['seen']):,} | "
            f"{int(med['nodes_tested']):,} | {all(x['identical'] for x in v)} | "
            f"{min(samp):.2f}-{max(samp):.2f} | "
            + (f"{min(full):.2f}-{max(full):.2f}" if full else "not run") + " | "
            f"{min(pvs):,}-{max(pvs):,} |")
    return lines


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    city = [r for r in results if r["scene"].startswith("city")]
    if not city:
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    n = [r["triangles"] for r in city]
    for key, label in (("sampling_s", "culled"), ("sampling_full_s", "unculled")):
        pts = [(r["triangles"], np.median([c[key] for c in r["cells"] if key in c]))
               for r in city if any(key in c for c in r["cells"])]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("city triangles")
    ax.set_ylabel("sampling, s per 4 m cell (median)")
    ax.set_xticks(n)
    ax.set_xticklabels([r["scene"].split()[1] for r in city])
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1000000,4000000", help="city sizes, comma separated")
    ap.add_argument("--real", default="lyon_vilo3d,kitchen,denhaag,lavaducts",
                    help="real scenes (file stems in ../shared/scenes)")
    ap.add_argument("--cells", type=int, default=3)
    ap.add_argument("--views", type=int, default=4, help="cubemaps timed per cell")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--full-max", type=int, default=4_000_000,
                    help="largest scene whose sampling cell is also timed unculled")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--no-files", action="store_true")
    ap.add_argument("--quick", action="store_true", help="city 200k, one cell, two views")
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.real, args.cells, args.views = "200000", "", 1, 2
    command = "python -m benchmarks.bench_culling " + " ".join(argv if argv is not None
                                                                else sys.argv[1:])
    head = [f"command: `{command.strip()}`", "", f"machine: {_machine()}", ""]
    print("\n".join(head), flush=True)
    results = [run_scene(label, make, cs, args) for label, make, cs in _scenes(args)]
    lines = ["# Culling: a cell's cost against the scene's size", "", *head,
             f"Cubemaps of {args.resolution} px from eyes in {args.cells} cells near each "
             "scene's middle (medians over their views); sampling at its defaults per cell "
             "(range over the cells). 'drawn' counts the triangles the culled render "
             "rasterized, 'seen' those the image holds.", "", *tables(results), "",
             "![sampling per cell against city size](culling.png)", ""]
    print("\n".join(tables(results)))
    if not args.no_files:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "culling.md").write_text("\n".join(lines))
        (args.out / "culling.json").write_text(json.dumps(
            {"command": command, "results": results}, indent=1))
        plot(results, args.out / "culling.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
