"""Conformance of the conservative cores (``cos``, ``dual_ray``) on the real scenes, scored
by dense random ray casting (``visibility.ray_reference``), never by our rasterizer.

For each real scene in ``../shared/scenes/`` (lavaducts, denhaag, lyon_vilo3d, and the
1M-triangle kitchen, whose ``cos`` cells cost the most: ``--heavy-cells`` cells there)
and each cell size (0.3 m and 1 m cubes), ``--cells`` cubes are centred on cells of the
scene's own viewcell grid (its walk area), drawn at random among those inside the scene's
bounds, each kept only when most of its eyes are in open space (``open_cells``). The reference
casts Embree rays from random eyes in the open space of each cell (``--eyes``, plus the 8
corners) in random directions (``--dirs`` each), seen with near planes 0 and the clients' 5 cm;
every triangle a core leaves out is cast again in float64 from its witness rays
(``ray_reference.confirm``), and a confirmed one is a miss. ``dual_ray`` runs on the 2.5D
scenes only; on the others its refusal is the row.

Writes ``benchmarks/results/conservative.md`` and ``.json``; prints each row as it goes.

Usage::

    python -m benchmarks.bench_conservative              # 3 scenes x 2 sizes x 3 cells + kitchen
    python -m benchmarks.bench_conservative --quick      # lavaducts, 1 cell, light rays
    python -m benchmarks.bench_conservative --scenes kitchen --sizes 0.3 --heavy-cells 1
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import command_line, header_lines, machine, md_table
from visibility.cores.base import get_core
from visibility.loaders import SCENE_EXTENSIONS, load_scene
from visibility.ray_reference import RaySample, confirm, describe, ray_reference
from visibility.scene import Scene
from visibility.viewcells import Viewcell, ViewcellGrid

ROOT = Path(__file__).resolve().parents[1]

SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = ROOT / "benchmarks" / "results"
SCENES = ("lavaducts", "denhaag", "lyon_vilo3d", "kitchen")
#: Scenes whose cells cost a core far more than the others': ``--heavy-cells`` cells each.
HEAVY = ("kitchen",)
SIZES = (0.3, 1.0)
CORES = ("cos", "dual_ray")


#: Share of a cell's eyes that must be in open space for the cell to be scored (a cube centred
#: on a grid cell of an interior can stand mostly inside a thick wall).
OPEN_SHARE = 0.75


def candidate_cells(scene: Scene, size: float, seed: int) -> list[tuple[int, np.ndarray]]:
    """(grid cell id, (2, 3) box) of cubes of side ``size`` metres centred on the cells of the
    scene's own viewcell grid (its walk area) whose cube lies inside the scene's bounds (the
    kitchen's grid reaches past its walls), in a random order drawn from ``seed``."""
    grid = ViewcellGrid.for_scene(scene)
    valid = scene.faces[scene.valid_faces]
    lo, hi = scene.vertices[valid].reshape(-1, 3).min(axis=0), \
        scene.vertices[valid].reshape(-1, 3).max(axis=0)
    order = np.random.default_rng(seed).permutation(len(grid))
    c = grid.centers()[order]
    boxes = np.stack([c - 0.5 * size, c + 0.5 * size], axis=1)
    inside = np.all(boxes[:, 0] >= lo, axis=1) & np.all(boxes[:, 1] <= hi, axis=1)
    return [(int(order[k]), boxes[k]) for k in np.flatnonzero(inside)]


def open_cells(scene: Scene, size: float, k: int, eyes: int, dirs: int, seed: int,
               ) -> list[tuple[int, np.ndarray, RaySample]]:
    """Up to ``k`` (grid cell id, box, reference) among ``candidate_cells``, in their order,
    whose reference (``ray_reference``: ``eyes`` random eyes, ``dirs`` directions each) keeps
    at least ``OPEN_SHARE`` of its eyes in open space."""
    out = []
    for n, (cid, box) in enumerate(candidate_cells(scene, size, seed)):
        if len(out) == k:
            break
        ref = ray_reference(scene, box, eyes, dirs, seed + n)
        if len(ref.eyes) >= OPEN_SHARE * (len(ref.eyes) + ref.dropped):
            out.append((cid, box, ref))
    return out


def run_cell(scene: Scene, box: np.ndarray, ref: RaySample, cores: tuple[str, ...]
             ) -> list[dict[str, Any]]:
    """Each core scored against the cell's reference (module docstring)."""
    rows = []
    for name in cores:
        core = get_core(name)
        row: dict[str, Any] = {"core": name, "reference": int(len(ref.ids)),
                               "eyes": int(len(ref.eyes)), "dropped": ref.dropped,
                               "rays": ref.rays}
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
    ap.add_argument("--heavy-cells", type=int, default=1,
                    help=f"cells per size of the heavy scenes {HEAVY}")
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
            t0 = time.perf_counter()
            want = args.heavy_cells if name in HEAVY else args.cells
            picked = open_cells(scene, size, want, args.eyes, args.dirs, args.seed)
            ref_s = (time.perf_counter() - t0) / max(1, len(picked))
            if len(picked) < want:
                print(f"{name} {size:g} m: only {len(picked)} cells in open space",
                      file=sys.stderr)
            for cid, box, ref in picked:
                for row in run_cell(scene, box, ref, tuple(args.cores)):
                    row.update(scene=name, size=size, cell=cid, box=box.tolist(),
                               reference_seconds=ref_s)
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
