"""Where `cos`'s excess at the server's cells comes from (issue 29, item 2).

``bench_cos_tightness`` measures `cos` at 4-12x what ray frames see on 4 m cells of the real
scenes, and cannot say whether the frames miss what `cos` keeps (they never converge) or `cos`
keeps what no eye sees. This benchmark asks two questions of the same cells (the middle cell
of each scene's own grid, ``--size`` metres, the eye-height range tall):

* **Do aimed rays find the excess?** Rays from eyes stratified in the cell's open space go to
  random points of the triangles of `cos`'s PVS (``--aims`` per triangle on average, on top of
  64 random directions per eye; ``ray_reference`` with ``aim``, the clients' 5 cm near plane).
  A triangle of the PVS that is visible at all from the cell covers some solid angle seen from
  the eyes near it, and rays aimed at it find it where the frames' pixels may step over it. The
  eyes double from ``--eyes`` to ``--most-eyes``; each row gives what the aimed rays see and
  what float64 casts confirm. Misses: triangles they show that the PVS lacks (there must be
  none).
* **Does a smaller cell remove it?** The cell solved as n x n sub-cells across the ground
  (``cos_subcells``, n in ``--subcells``), the answers joined: the union's size against the
  whole cell's. If the excess came from the cell's size (offsets of metres smear every
  silhouette), small sub-cells would remove most of it.

Writes ``benchmarks/results/cos_excess.md`` and ``.json``.

Usage::

    python -m benchmarks.bench_cos_excess
    python -m benchmarks.bench_cos_excess --quick     # lavaducts, R 16, sub-cells 1 and 2
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_cos_tightness import SCENES, SHARED_SCENES, middle_cell
from benchmarks.common import command_line, header_lines, machine, md_table, write_report
from visibility.cell_walk import cell_walk
from visibility.cores.cos.core import DEFAULT_RESOLUTION, cos_pvs, cos_subcells
from visibility.ground_truth import sample_points
from visibility.loaders import load_scene
from visibility.raster.camera import DEFAULT_NEAR
from visibility.ray_frames import in_open_space
from visibility.ray_reference import confirm, front_normals, ray_reference
from visibility.scene import Scene

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
#: Random directions per eye beside the aimed rays (they find what lies outside the PVS).
RANDOM_DIRS = 64


def aimed(scene: Scene, box: np.ndarray, pvs: np.ndarray, first: int, most: int, aims: float,
          seed: int = 7) -> dict[str, Any]:
    """What rays aimed from the cell's open space at the PVS ``pvs`` triangles see, eyes
    doubled from ``first`` to ``most``: per step the triangles seen, and at the last step the
    seen triangles of the PVS confirmed in float64 and the confirmed ones it lacks."""
    rng = np.random.default_rng(seed)
    eyes = sample_points(np.asarray(box, dtype=np.float64), most, rng)
    eyes = eyes[in_open_space(scene, eyes)]
    tris = scene.vertices[scene.faces[np.asarray(pvs, dtype=np.int64)]]
    n_aim = max(1, int(round(aims * len(pvs))))
    seen = np.zeros(0, dtype=np.int64)
    steps = []
    done = 0
    target = min(first, len(eyes))
    samples = []
    while True:
        part = eyes[done:target]
        if len(part):
            s = ray_reference(scene, box, n_dirs=RANDOM_DIRS, seed=seed + done,
                              nears=(DEFAULT_NEAR,), aim=tris, n_aim=n_aim, eyes=part)
            samples.append(s)
            seen = np.union1d(seen, s.ids)
        done = target
        steps.append({"eyes": done, "seen": int(len(seen)),
                      "seen_in_pvs": int(np.isin(seen, pvs).sum())})
        print(f"  aimed rays: {done} eyes, {len(seen)} triangles seen", flush=True)
        if done >= len(eyes):
            break
        target = min(2 * done, len(eyes))
    outside = np.setdiff1d(seen, pvs)
    confirmed_out = np.unique(np.concatenate(
        [confirm(scene, s, outside) for s in samples])) if len(outside) else outside
    inside = np.intersect1d(seen, pvs)
    confirmed_in = np.unique(np.concatenate(
        [confirm(scene, s, inside) for s in samples])) if len(inside) else inside
    away = facing_away(scene, pvs, box)
    away_seen = int(np.isin(np.asarray(pvs)[away], confirmed_in).sum())
    return {"eyes_in_open_space": int(len(eyes)), "steps": steps,
            "confirmed_in_pvs": int(len(confirmed_in)), "missed": int(len(confirmed_out)),
            "aims_per_triangle": aims, "facing_away": int(away.sum()),
            "facing_away_seen": away_seen,
            # The PVS less what faces away from the cell and no aimed ray confirms seen.
            "pvs_without_unseen_away": int(len(pvs) - away.sum() + away_seen)}


def facing_away(scene: Scene, ids: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(len(ids),) bool: which triangles ``ids`` have every corner of the cell ``box`` (2, 3)
    strictly behind their plane (front side by the scene's winding, ``front_normals``): every
    eye of the cell looks at their back. Such a triangle is seen only where a ray reaches its
    back side: through a surface left open, or a near plane cutting one."""
    tri = np.asarray(scene.vertices, dtype=np.float64)[
        np.asarray(scene.faces)[np.asarray(ids, dtype=np.int64)]]
    n = front_normals(tri, scene)
    # The corner farthest along the normal decides.
    far = np.where(n > 0.0, box[1], box[0])
    return np.einsum("ij,ij->i", n, far - tri[:, 0]) < 0.0


def run_scene(name: str, size: float, resolution: int, subcells: list[int], first: int,
              most: int, aims: float) -> dict[str, Any]:
    """One scene's cell: cos whole and in sub-cells, and the aimed rays at its PVS."""
    scene = load_scene(SHARED_SCENES / f"{name}.glb")
    box = middle_cell(scene, size)
    print(f"{name}: cell {box.round(2).tolist()}", flush=True)
    cos_pvs(scene, box, 16)  # compile and per-scene builds
    rows = []
    pvs = None
    for n in subcells:
        t0 = time.perf_counter()
        if n == 1:
            ids, _ = cos_pvs(scene, box, resolution)
        else:
            ids, _ = cos_subcells(scene, box, n, resolution)
        seconds = time.perf_counter() - t0
        if n == 1:
            pvs = ids
        rows.append({"subcells": n, "side": size / n, "pvs": int(len(ids)), "seconds": seconds})
        print(f"  {n} x {n} sub-cells: {len(ids)} triangles, {seconds:.2f} s", flush=True)
    if pvs is None:
        pvs, _ = cos_pvs(scene, box, resolution)
    ref = aimed(scene, box, pvs, first, most, aims)
    # Where a person can stand in the cell (``cell_walk``): cos answers for every eye of the
    # box, the rest (a level's void, the inside of solids) included.
    floor = float(cell_walk(scene, box).open.mean())
    return {"scene": name, "triangles": scene.n_triangles, "box": box.tolist(),
            "resolution": resolution, "pvs": int(len(pvs)), "rows": rows, "aimed": ref,
            "open_floor_share": floor}


def _md(results: list[dict[str, Any]], args: argparse.Namespace, argv: list[str],
        elapsed: float) -> str:
    lines = ["# Where cos's excess at the server's cells comes from", ""]
    lines += header_lines(command_line("benchmarks.bench_cos_excess", argv), machine())
    lines += [f"Cell {args.size} m (the middle cell of each scene's own grid), cos at "
              f"{args.resolution} px. Aimed rays: from eyes stratified in the cell's open "
              f"space to random points of the PVS's triangles ({args.aims:g} per triangle on "
              f"average) plus {RANDOM_DIRS} random directions per eye, 5 cm near plane, Embree; "
              f"seen triangles of the PVS confirmed in float64 at the end. Sub-cells: the cell "
              f"solved as n x n parts across the ground, answers joined. One run; "
              f"{elapsed:.0f} s in all.", ""]
    head = ["scene", "cos PVS", "aimed rays see (eyes)", "confirmed", "PVS / confirmed",
            "missed", "facing away from the cell (confirmed seen)",
            "PVS / confirmed without unseen ones facing away", "open floor of the cell"]
    rows = []
    for res in results:
        a = res["aimed"]
        conf = max(a["confirmed_in_pvs"], 1)
        rest = a["pvs_without_unseen_away"]
        rows.append([res["scene"], f"{res['pvs']:,}",
                     ", ".join(f"{s['seen_in_pvs']:,} ({s['eyes']})" for s in a["steps"]),
                     f"{a['confirmed_in_pvs']:,}",
                     f"{res['pvs'] / conf:.1f}", a["missed"],
                     f"{a['facing_away']:,} ({a['facing_away_seen']:,})", f"{rest / conf:.1f}",
                     f"{100 * res['open_floor_share']:.0f} %"])
    lines += md_table(head, rows)
    lines += ["", "## Sub-cells", ""]
    head = ["scene", "sub-cells", "side, m", "PVS (union)", "x whole cell", "PVS / confirmed",
            "seconds"]
    rows = []
    for res in results:
        conf = max(res["aimed"]["confirmed_in_pvs"], 1)
        for r in res["rows"]:
            rows.append([res["scene"], f"{r['subcells']} x {r['subcells']}", f"{r['side']:g}",
                         f"{r['pvs']:,}", f"{r['pvs'] / max(res['pvs'], 1):.2f}",
                         f"{r['pvs'] / conf:.1f}", f"{r['seconds']:.2f}"])
    lines += md_table(head, rows)
    lines += ["", "## Reading", ""]
    for res in results:
        a = res["aimed"]
        last = res["rows"][-1]
        ratio = res["pvs"] / max(a["confirmed_in_pvs"], 1)
        rest = a["pvs_without_unseen_away"]
        lines.append(
            f"- {res['scene']}: aimed rays from {a['steps'][-1]['eyes']} eyes find "
            f"{a['confirmed_in_pvs']:,} of the {res['pvs']:,} triangles of cos's PVS "
            f"(confirmed in float64; {a['steps'][0]['seen_in_pvs']:,} from "
            f"{a['steps'][0]['eyes']} eyes), so cos keeps {ratio:.1f}x "
            f"what they show; {last['subcells']} x {last['subcells']} sub-cells of "
            f"{last['side']:g} m join to {last['pvs']:,} triangles "
            f"({last['pvs'] / max(res['pvs'], 1):.2f}x the whole cell's). Misses: "
            f"{a['missed']}. {a['facing_away']:,} triangles of the PVS "
            f"({100 * a['facing_away'] / max(res['pvs'], 1):.0f} %) face away from the "
            f"whole cell (every eye looks at their back), and the rays confirm "
            f"{a['facing_away_seen']:,} of those seen; without the others the PVS would "
            f"hold {rest / max(a['confirmed_in_pvs'], 1):.1f}x "
            f"what the rays show. A person can stand on "
            f"{100 * res['open_floor_share']:.0f} % of the cell's floor lattice "
            f"(`cell_walk`); cos answers for every eye of its box.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--size", type=float, default=4.0, help="cell size, metres")
    ap.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION)
    ap.add_argument("--subcells", default="1,2,4,8", help="n of the n x n sub-cell runs")
    ap.add_argument("--eyes", type=int, default=64, help="aimed-ray eyes to start from")
    ap.add_argument("--most-eyes", type=int, default=512, help="most aimed-ray eyes")
    ap.add_argument("--aims", type=float, default=8.0, help="aimed rays per PVS triangle")
    ap.add_argument("--quick", action="store_true", help="lavaducts, R 16, sub-cells 1 and 2")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.quick:
        args.scenes, args.resolution, args.subcells, args.eyes, args.most_eyes, args.aims = (
            ["lavaducts"], 16, "1,2", 4, 8, 2.0)
    subcells = [int(n) for n in str(args.subcells).split(",")]
    t0 = time.perf_counter()
    results = [run_scene(s, args.size, args.resolution, subcells, args.eyes, args.most_eyes,
                         args.aims) for s in args.scenes]
    elapsed = time.perf_counter() - t0
    write_report(args.out, "cos_excess", "benchmarks.bench_cos_excess", argv, results,
                 _md(results, args, argv, elapsed))


if __name__ == "__main__":
    main()
