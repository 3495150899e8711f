"""Conformance of the conservative cores (``cos``, ``dual_ray``) on the real scenes, scored
by dense random ray casting (``visibility.ray_reference``), never by our rasterizer.

For each real scene in ``../shared/scenes/`` (lavaducts, denhaag, lyon_vilo3d; the 1M-triangle
kitchen only when asked: ``cos`` takes about a minute on one of its 0.3 m cells) and each cell
size (0.3 m and 1 m cubes), ``--cells`` cells are centred on cells of the scene's own viewcell
grid spread evenly over it. The reference casts Embree rays from random eyes in the open space
of each cell (``--eyes``, plus the 8 corners) in random directions (``--dirs`` each), seen with
near planes 0 and the clients' 5 cm; every triangle a core leaves out is cast again in float64
from its witness rays (``ray_reference.confirm``), and a confirmed one is a miss. ``dual_ray``
runs on the 2.5D scenes only; on the others its refusal is the row.

Writes ``benchmarks/results/conservative.md`` and ``.json``; prints each row as it goes.

Usage::

    python -m benchmarks.bench_conservative                    # 3 scenes x 2 sizes x 3 cells
    python -m benchmarks.bench_conservative --quick            # lavaducts, 1 cell, light rays
    python -m benchmarks.bench_conservative --scenes kitchen --sizes 0.3 --cells 1
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.common import command_line, header_lines, machine, md_table  # noqa: E402
from visibility.cores.base import get_core  # noqa: E402
from visibility.loaders import SCENE_EXTENSIONS, load_scene  # noqa: E402
from visibility.ray_reference import confirm, describe, ray_reference  # noqa: E402
from visibility.scene import Scene  # noqa: E402
from visibility.viewcells import Viewcell, ViewcellGrid, spread_evenly  # noqa: E402

SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = ROOT / "benchmarks" / "results"
SCENES = ("lavaducts", "denhaag", "lyon_vilo3d")
SIZES = (0.3, 1.0)
CORES = ("cos", "dual_ray")


def cell_boxes(scene: Scene, size: float, k: int) -> list[tuple[int, np.ndarray]]:
    """(grid cell id, (2, 3) box) for ``k`` cubes of side ``size`` metres centred on cells of
    the scene's own viewcell grid, spread evenly over it."""
    grid = ViewcellGrid.for_scene(scene)
    ids = spread_evenly(np.arange(len(grid)), k)
    out = []
    for i in ids:
        c = grid.cell(i).center
        out.append((i, np.stack([c - 0.5 * size, c + 0.5 * size])))
    return out


def run_cell(scene: Scene, box: np.ndarray, eyes: int, dirs: int, seed: int,
             cores: tuple[str, ...]) -> list[dict[str, Any]]:
    """One reference for the cell, then each core scored against it (module docstring)."""
    t0 = time.perf_counter()
    ref = ray_reference(scene, box, eyes, dirs, seed)
    ref_s = time.perf_counter() - t0
    rows = []
    for name in cores:
        core = get_core(name)
        row: dict[str, Any] = {"core": name, "reference": int(len(ref.ids)),
                               "eyes": int(len(ref.eyes)), "dropped": ref.dropped,
                               "rays": ref.rays, "reference_seconds": ref_s}
        fit = core.fit(scene, float(np.max(box[1] - box[0])))
        if not fit.ok:
            row.update(pvs=None, missed=None, confirmed=None, seconds=None, note=fit.why)
            rows.append(row)
            continue
        t1 = time.perf_counter()
        pvs = core.compute(scene, Viewcell(box), core.make_params())
        row["seconds"] = time.perf_counter() - t1
        missed = np.setdiff1d(ref.ids, pvs.triangle_ids)
        sure = confirm(scene, ref, missed)
        row.update(pvs=int(len(pvs.triangle_ids)), missed=int(len(missed)),
                   confirmed=int(len(sure)), confirmed_ids=sure[:50].tolist(),
                   note=describe(scene, ref, sure, box, limit=3) if len(sure) else "")
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--sizes", nargs="+", type=float, default=list(SIZES))
    ap.add_argument("--cells", type=int, default=3, help="cells per scene and size")
    ap.add_argument("--eyes", type=int, default=128, help="random eyes per cell (+8 corners)")
    ap.add_argument("--dirs", type=int, default=4096, help="random directions per eye")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cores", nargs="+", default=list(CORES))
    ap.add_argument("--quick", action="store_true",
                    help="lavaducts, 0.3 m, one cell, 32 eyes x 1024 directions")
    ap.add_argument("--out", type=Path, default=RESULTS / "conservative.md")
    args = ap.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes, args.cells, args.eyes, args.dirs = (
            ["lavaducts"], [0.3], 1, 32, 1024)
    results = []
    head = ["scene", "size m", "cell", "core", "PVS", "seen by rays", "eyes (dropped)", "rays",
            "float32 misses", "misses", "core s", "note"]
    table = []
    for name in args.scenes:
        path = next((p for p in sorted(SHARED_SCENES.glob(f"{name}.*"))
                     if p.suffix.lower() in SCENE_EXTENSIONS), None)
        if path is None:
            print(f"{name}: no scene file in {SHARED_SCENES}", file=sys.stderr)
            return 2
        scene = load_scene(path)
        for size in args.sizes:
            for cid, box in cell_boxes(scene, size, args.cells):
                for row in run_cell(scene, box, args.eyes, args.dirs, args.seed,
                                    tuple(args.cores)):
                    row.update(scene=name, size=size, cell=cid, box=box.tolist())
                    results.append(row)
                    cells = [name, f"{size:g}", cid, row["core"], row["pvs"],
                             row["reference"], f"{row['eyes']} ({row['dropped']})",
                             row["rays"], row["missed"], row["confirmed"],
                             "" if row["seconds"] is None else f"{row['seconds']:.2f}",
                             row["note"].replace("\n", "; ")]
                    table.append(["-" if c is None else c for c in cells])
                    print(" | ".join(str(c) for c in table[-1]), flush=True)
    command = command_line("benchmarks.bench_conservative", argv)
    lines = ["# Conservative cores against dense random rays", ""]
    lines += header_lines(command, machine())
    lines += ["Misses are triangles the rays saw first, the core left out, and a float64 "
              "re-cast of the witness rays confirmed; a conservative core must have none.", ""]
    lines += md_table(head, table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    args.out.with_suffix(".json").write_text(json.dumps(
        {"command": command, "machine": machine(), "rows": results}, indent=1))
    bad = sum(r["confirmed"] or 0 for r in results)
    print(f"{len(results)} rows, {bad} confirmed misses; wrote {args.out}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
