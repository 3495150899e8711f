"""Which scenes' cells take ``from_segment``'s sub-pixel run, and what it costs there.

``from_segment`` adds ``subpixel_runs`` randomly turned cubes where its first run's footprint
rule tested more than ``SUBPIXEL_CANDIDATES`` triangles per triangle of the answer
(``core.subpixel_ratio``). This prints, for the cells a seeded walk stands in on each scene
(``bench_real_cells.walk_cells``, the scene's own grid), that ratio, the runs taken and the
seconds at the defaults, and where the extra run was taken the same cell with
``subpixel_runs=0`` beside it (the PVS and seconds it saves or costs). The misses each answer
leaves, against dense ray casting, are ``bench_real_cells``' (``--fs-variants
subpixel_runs=0``).

Writes ``benchmarks/results/subpixel_runs.md`` (+ ``.json``). Usage::

    python -m benchmarks.bench_subpixel_runs                  # real scenes and generated ones
    python -m benchmarks.bench_subpixel_runs --scenes lavaducts --generated --out /tmp/s
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.bench_matrix import SHARED_SCENES
from benchmarks.bench_real_cells import parse_generated, prepare, walk_cells
from benchmarks.common import command_line, machine, md_table, write_report

RESULTS = Path(__file__).resolve().parent / "results"
#: Generated scenes measured beside the real ones (name, triangles).
GENERATED = ("city:100000", "village:100000", "rooms:100000", "city:1000000", "grass:100000",
             "spheres:2000")


def measure(scene, label: str, cells: int = 2, seed: int = 1) -> list[dict[str, Any]]:
    """One row per walked cell of ``scene``: the first run's ratio, runs, PVS and seconds at
    the defaults, and with ``subpixel_runs=0`` where more than one run was taken; the seconds
    of finding the cell's walked outline (``view_segments``, cached) apart."""
    from visibility.cores.base import get_core
    from visibility.cores.from_segment import view_segments
    from visibility.viewcells import ViewcellGrid

    core = get_core("from_segment")
    grid = ViewcellGrid.for_scene(scene)
    rows = []
    params = core.make_params()
    for cid in walk_cells(scene, seed, cells):
        cell = grid.cell(cid)
        # The open floor's outline is found once per cell and cached: found before either
        # timed run, so that both compare the runs alone.
        t0 = time.perf_counter()
        view_segments(scene, cell.box, params.eye_levels, params.walk)
        walk_s = time.perf_counter() - t0
        pvs = core.compute(scene, cell, params)
        row = {"scene": label, "triangles": int(scene.n_triangles), "cell": int(cid),
               "cell_size": float(grid.cell_size), "ratio": float(pvs.stats["subpixel_ratio"]),
               "runs": int(pvs.stats["runs"]), "pvs": len(pvs), "seconds": pvs.seconds,
               "walk_seconds": walk_s}
        if row["runs"] > 1:
            one = core.compute(scene, cell, core.make_params(subpixel_runs=0))
            row.update(pvs_one_run=len(one), seconds_one_run=one.seconds)
        rows.append(row)
        print(row, flush=True)
    return rows


def report(rows: list[dict[str, Any]], command: str, wall: float) -> str:
    """The markdown page: the rows and what they say."""
    from visibility.cores.from_segment import SUBPIXEL_CANDIDATES

    table = md_table(
        ["scene", "cell (m)", "walk s", "candidates per triangle found", "runs", "PVS", "s",
         "one run: PVS", "one run: s"],
        [[r["scene"], f"{r['cell']} ({r['cell_size']:g})", f"{r['walk_seconds']:.2f}",
          f"{r['ratio']:.2f}", r["runs"],
          f"{r['pvs']:,}", f"{r['seconds']:.2f}",
          f"{r['pvs_one_run']:,}" if "pvs_one_run" in r else "",
          f"{r['seconds_one_run']:.2f}" if "seconds_one_run" in r else ""] for r in rows])
    taken = [r for r in rows if r["runs"] > 1]
    below = [r["ratio"] for r in rows if r["runs"] == 1]
    lines = [
        "# from_segment: where the sub-pixel run is taken", "",
        f"Command: `{command}`, {wall / 60:.1f} min; load average (1 min) "
        f"{os.getloadavg()[0]:.1f} at the end.  ", f"Machine: {machine()}", "",
        "Cells a seeded walk (seed 1) stands in, `from_segment` at its defaults: the first "
        "run's footprint candidates (triangles its footprint rule tested, once per tile and "
        "segment) per triangle of its answer, the runs taken (a second where that exceeds "
        f"`SUBPIXEL_CANDIDATES` = {SUBPIXEL_CANDIDATES:g}), the PVS and seconds; where a second "
        "run was taken, the same cell with `subpixel_runs=0`. Walk s: finding the outline of "
        "the cell's open floor that the core walks, once per cell (cached; not in either "
        "run's seconds).", "", *table, "",
        f"Reading: {len(taken)} of {len(rows)} cells took the second run"
        + (f" ({', '.join(sorted({r['scene'] for r in taken}))}: ratio "
           f"{min(r['ratio'] for r in taken):.1f}-{max(r['ratio'] for r in taken):.1f}, "
           f"{min(r['seconds'] / r['seconds_one_run'] for r in taken):.2f}-"
           f"{max(r['seconds'] / r['seconds_one_run'] for r in taken):.2f}x the one-run time)"
           if taken else "")
        + (f"; the others' ratio {min(below):.2f}-{max(below):.2f}." if below else "."), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", help="real scene names (default: every one)")
    ap.add_argument("--generated", nargs="*", default=list(GENERATED), metavar="NAME:TRIANGLES",
                    help="generated scenes (default: %(default)s; the flag alone: none)")
    ap.add_argument("--cells", type=int, default=2, help="walked cells per scene")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    from visibility.cores.base import get_core
    from visibility.generators import make_scene
    from visibility.loaders import load_scene
    from visibility.viewcells import ViewcellGrid

    t0 = time.perf_counter()
    # Load the compiled kernels on a small scene first: no measured cell pays for it.
    small = make_scene("rooms", triangles=2_000)
    get_core("from_segment").compute(small, ViewcellGrid.for_scene(small).cell(0))
    rows: list[dict[str, Any]] = []
    for path in sorted(SHARED_SCENES.glob("*.glb")):
        if args.scenes is None or path.stem in args.scenes:
            scene = load_scene(path)
            prepare(scene)
            rows += measure(scene, path.stem, args.cells)
    for name, n in (parse_generated(text) for text in args.generated):
        scene = make_scene(name, triangles=n)
        prepare(scene)
        rows += measure(scene, f"{name} {n // 1000}k (generated)", args.cells)
    given = sys.argv[1:] if argv is None else argv
    text = report(rows, command_line("benchmarks.bench_subpixel_runs", given),
                  time.perf_counter() - t0)
    write_report(args.out, "subpixel_runs", "benchmarks.bench_subpixel_runs", given, rows, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
