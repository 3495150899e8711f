"""The ``cos`` core measured against its paper (Hladky et al. 2019, Table 1, Figs. 13-19).

Two parts, printed and written to ``benchmarks/results/cos.md`` (+ ``cos.json``, ``cos.png``):

``speed``  the issue's speed cells on this machine: a 0.3 m cell of the 100k ``city`` and
           ``village``, a 0.3 m cell of ``kitchen`` (1M triangles) and a 4 m cell of the 100k
           city, at the core's default resolution and at 64: seconds per phase (the Fig. 19
           breakdown: sort, list building, resolution), list entries, longest list, PVS size,
           FN/FP against a dense sampled reference, and the ratio to the paper's 35-220 ms.
``fp``     FP per scene and cell size (0.05, 0.1, 0.2, 0.3, 1, 4 m) on 20k-triangle rooms,
           village and city, next to the paper's 20-90 % overestimation.
``kitchen`` (with ``speed``, unless ``--skip-kitchen``) the 1M kitchen's cell at 5 and 10 cm
           besides 0.3 m (does a smaller cell buy the time back?), and how the sampled
           reference of the 0.3 m cell grows with its resolution (16 eyes at 256-2048 px):
           how much of the measured overestimation is the reference missing sub-pixel
           triangles, and whether the PVS holds every triangle the denser references see.

Tightness at the server's 4 m cells of the real scenes: ``benchmarks.bench_cos_tightness``.

The reference (``visibility.ray_frames``, Embree, never our rasterizer): every triangle some
pixel shows in frames of ``--points`` eyes stratified in the box's open space, a randomly turned
cube of 256 px per face each, with the clients' near plane; a triangle the PVS lacks counts as
missed only when the float64 cast of its pixel's ray confirms it. Usage:
``python -m benchmarks.bench_cos`` (with the kitchen about 10 minutes on 2 cores; or
``--skip-kitchen``), ``--quick`` for a smoke run. Times are the best of
``FAST_REPEATS`` runs after a warm-up compile (of 2 on the kitchen).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402

from benchmarks.bench_matrix import SHARED_SCENES  # noqa: E402
from visibility.cores.base import get_core  # noqa: E402
from visibility.cores.cos.core import BUSY_BLOCK, BUSY_MIN_ITEMS  # noqa: E402
from visibility.cores.cos.resolve import CYCLE_PARTS  # noqa: E402
from visibility.generators import make_scene  # noqa: E402
from visibility.ground_truth import cell_around, fn_fp_rates  # noqa: E402
from visibility.raster.camera import DEFAULT_NEAR  # noqa: E402
from visibility.ray_frames import missed_triangles, ray_frames, seen_ids  # noqa: E402
from visibility.viewcells import Viewcell  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
PAPER_MS = (35.0, 220.0)
PHASES = ("sort_seconds", "list_seconds", "coarse_seconds", "resolve_seconds")
#: The coarse pass's threshold in its step rows: busy tiles' (it is off by default).
COARSE_STEP = BUSY_MIN_ITEMS
#: Runs of each cell but the kitchen's, the best kept: the first runs right after the
#: reference's ray casting read up to a quarter slower than later ones on this machine.
FAST_REPEATS = 5


def _kitchen():
    from visibility.loaders import load_scene

    if (SHARED_SCENES / "kitchen.glb").exists():
        return load_scene(SHARED_SCENES / "kitchen.glb")
    return None


class Reference:
    """Ray frames of a cell (``ray_frames``, the clients' near plane) and the triangles they
    show; ``missed(ids)``: the confirmed ones a PVS lacks."""

    def __init__(self, scene, box: np.ndarray, eyes: int, resolution: int = 256,
                 seed: int = 0) -> None:
        self.scene = scene
        self.frames = ray_frames(scene, box, n_eyes=eyes, resolution=resolution, seed=seed,
                                 near=DEFAULT_NEAR)
        self.ids = seen_ids(self.frames)

    def missed(self, pvs_ids: np.ndarray) -> np.ndarray:
        return missed_triangles(self.scene, self.frames, pvs_ids)


def _run(scene, box, resolution: int, repeats: int = 2, **params: Any) -> Any:
    core = get_core("cos")
    best = None
    for _ in range(repeats):
        pvs = core.compute(scene, Viewcell(box),
                           core.make_params(resolution=resolution, **params))
        if best is None or pvs.seconds < best.seconds:
            best = pvs
    return best


def _row(label, scene, box, resolution, ref, keep: dict[str, Any] | None = None,
         repeats: int = 2, **params: Any) -> dict[str, Any]:
    """One measured cell (``params``: core parameters besides the resolution); ``keep``,
    when given, gets the PVS ids under ``"ids"``."""
    pvs = _run(scene, box, resolution, repeats, **params)
    if keep is not None:
        keep["ids"] = pvs.triangle_ids
    missed = int(len(ref.missed(pvs.triangle_ids)))
    fn = missed / max(1, len(ref.ids))
    fp = fn_fp_rates(pvs.triangle_ids, ref.ids)[1]
    st = pvs.stats
    row = {"cell": label, "resolution": resolution, "triangles": scene.n_triangles,
           "params": dict(params),
           "seconds": pvs.seconds, "pvs": len(pvs), "reference": int(len(ref.ids)), "fn": fn,
           "fn_count": missed, "fp": fp,
           "overestimation": (len(pvs) - len(ref.ids) + missed) / max(1, len(ref.ids)),
           "list_entries": st["list_entries"], "tile_items": st.get("tile_items", 0),
           "longest_list": st["longest_list"], "mean_list": st["list_entries"] / st["pixels"],
           "pixels": st["pixels"], "tested": st["tested"], "occluded": st["occluded"],
           "early_z_cut": st.get("early_z_cut", 0), "fill_cut": st.get("fill_cut", 0),
           "silhouette_edges": st.get("silhouette_edges", 0),
           "plane_tests": st.get("plane_tests", 0), "fusion": st.get("fusion", ""),
           "fused": st.get("fused", 0), "front_parts": st.get("front_parts", 0),
           "cycles": {k: st.get(f"cycles_{k}", 0)
                      for k in ("resolve", "test", "insert", "coverall", *CYCLE_PARTS)},
           "occluder_triangles": st.get("occluder_triangles", 0),
           "coarse_tiles": st.get("coarse_tiles", 0),
           "coarse_entries": st.get("coarse_entries", 0),
           "coarse_dropped": st.get("coarse_dropped", 0),
           "coarse_work": {k: st.get(f"coarse_{k}", 0)
                           for k in ("tested", "silhouette_edges", "plane_tests",
                                     "cycles_test", "cycles_insert", "cycles_coverall",
                                     "cycles_resolve")},
           "coarse_seconds": st.get("coarse_seconds", 0.0),
           "block_tiles": st.get("block_tiles", 0), "subpixels": st.get("subpixels", 0),
           "block_cycles": st.get("block_cycles", 0), "block_tested": st.get("block_tested", 0),
           "sub_hidden": st.get("refined", 0), "walks_seen": st.get("walks_seen", 0),
           "subpixels_seen": st.get("subpixels_seen", 0),
           "leaf_tests": st.get("leaf_tests", 0), "leaf_hidden": st.get("leaf_hidden", 0),
           "leaf_skipped": st.get("leaf_skipped", 0),
           "unseen_back_faces": st.get("unseen_back_faces", 0),
           "projected": st.get("projected", 0), "culled": st.get("culled", 0),
           "costliest_view": st.get("costliest_view")}
    for k in PHASES + ("weld_seconds", "topology_seconds"):
        row[k] = float(st[k])
    row["gpu_ratio"] = [pvs.seconds * 1e3 / PAPER_MS[1], pvs.seconds * 1e3 / PAPER_MS[0]]
    print(f"{label:24s} R={resolution:4d} {pvs.seconds:7.3f}s  sort {row['sort_seconds']:.3f} "
          f"lists {row['list_seconds']:.3f} resolve {row['resolve_seconds']:.3f}  "
          f"entries {row['list_entries']:9d} longest {row['longest_list']:5d}  PVS {len(pvs):7d} "
          f"ref {len(ref.ids):7d} FN {missed} FP {fp:.2f}", flush=True)
    return row


def speed(quick: bool, points: int, kitchen: bool = True,
          kitchen_rows: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """The speed cells; with the kitchen, ``kitchen_rows`` (when given) gets the kitchen
    part (``kitchen_part``)."""
    from visibility.cores.cos.core import DEFAULT_RESOLUTION

    n = 20_000 if quick else 100_000
    cells = []
    for name in ("city", "village"):
        sc = make_scene(name, triangles=n)
        cells.append((f"{name} {n // 1000}k 0.3 m", sc, cell_around(sc, 0.3, 0)))
    kitchen = _kitchen() if kitchen and not quick else None
    if kitchen is not None:
        from visibility.viewcells import ViewcellGrid

        grid = ViewcellGrid.for_scene(kitchen)
        c = grid.cell(len(grid) // 2).center
        cells.append(("kitchen 1M 0.3 m", kitchen, np.stack([c - 0.15, c + 0.15])))
    city = cells[0][1]
    cells.append((f"city {n // 1000}k 4 m", city, cell_around(city, 4.0, 0)))
    rows = []
    for label, sc, box in cells:
        ref = Reference(sc, box, points)
        for res in sorted({64, DEFAULT_RESOLUTION}):
            keep: dict[str, Any] = {}
            rows.append(_row(label, sc, box, res, ref, keep,
                             repeats=2 if sc is kitchen else FAST_REPEATS))
            if res == DEFAULT_RESOLUTION:
                rows[-1]["sampling"] = _sampling(sc, box, ref)
            if sc is kitchen and res == DEFAULT_RESOLUTION and kitchen_rows is not None:
                kitchen_rows.update(kitchen_part(sc, box, keep["ids"], rows[-1], points))
        if sc is kitchen or label.endswith("4 m"):
            # The steps on clutter's tiles (one run): every pixel of them sampled, the
            # coarse pass (off by default) before their samples, and no leaf boxes.
            rows.append(_row(f"{label}, busy tiles every pixel", sc, box, DEFAULT_RESOLUTION,
                             ref, repeats=1 if sc is kitchen else 2, busy_block=1))
            rows.append(_row(f"{label}, with the coarse pass", sc, box, DEFAULT_RESOLUTION,
                             ref, repeats=1 if sc is kitchen else 2,
                             coarse_items=COARSE_STEP))
            rows.append(_row(f"{label}, without leaf boxes", sc, box, DEFAULT_RESOLUTION,
                             ref, repeats=1 if sc is kitchen else 2, leaf_list=0))
        # Separate groups hiding together (``fusion="groups"``) as a step.
        rows.append(_row(f"{label}, fusion groups", sc, box, DEFAULT_RESOLUTION, ref,
                         repeats=1 if sc is kitchen else 2, fusion="groups"))
    return rows


def _sampling(scene, box: np.ndarray, ref: Reference) -> dict[str, Any]:
    """``sampling`` at its defaults on the same cell (best of 2): PVS size, seconds, and the
    triangles the reference shows that it lacks (unconfirmed: the float64 confirmation of
    thousands of misses over a 1M scene would cost more than the whole benchmark)."""
    core = get_core("sampling")
    best = None
    for _ in range(2):
        pvs = core.compute(scene, Viewcell(box), core.make_params())
        best = pvs if best is None or pvs.seconds < best.seconds else best
    missed = int(len(np.setdiff1d(ref.ids, best.triangle_ids)))
    print(f"  sampling at its defaults: {best.seconds:.3f}s PVS {len(best)} missed {missed}",
          flush=True)
    return {"seconds": best.seconds, "pvs": len(best), "missed": missed}


#: The kitchen part: smaller cells (same centre), and the sampled reference's resolutions.
KITCHEN_SIZES = (0.05, 0.1)
GROWTH_EYES = 16
GROWTH_RESOLUTIONS = (256, 512, 1024, 2048)


def kitchen_part(scene, box: np.ndarray, pvs_ids: np.ndarray, row: dict[str, Any],
                 points: int) -> dict[str, Any]:
    """The kitchen at smaller cells around the same centre (one run each, default
    resolution), and the reference of ``box`` from ``GROWTH_EYES`` stratified eyes at each of
    ``GROWTH_RESOLUTIONS``: triangles seen, and how many of them ``pvs_ids`` (the 0.3 m PVS)
    lacks."""
    from visibility.cores.cos.core import DEFAULT_RESOLUTION

    centre = 0.5 * (box[0] + box[1])
    sizes = []
    for size in KITCHEN_SIZES:
        b = np.stack([centre - 0.5 * size, centre + 0.5 * size])
        ref = Reference(scene, b, points)
        r = _row(f"kitchen 1M {100 * size:g} cm", scene, b, DEFAULT_RESOLUTION, ref, repeats=1)
        r.update(size=size)
        sizes.append(r)
    sizes.append(dict(row, size=float(box[1][0] - box[0][0])))
    growth = []
    for res in GROWTH_RESOLUTIONS:
        # One eye at a time: the frames of 16 eyes at 2048 px would take gigabytes.
        seen: set[int] = set()
        miss: set[int] = set()
        for k in range(GROWTH_EYES):
            ref = Reference(scene, box, 1, res, seed=1000 + k)
            seen.update(ref.ids.tolist())
            miss.update(ref.missed(pvs_ids).tolist())
        growth.append({"resolution": res, "seen": len(seen), "missed": len(miss)})
        print(f"kitchen reference {GROWTH_EYES} eyes at {res} px: {len(seen)} "
              f"triangles, {len(miss)} missing from the PVS", flush=True)
    return {"sizes": sizes, "growth": growth, "pvs": int(len(pvs_ids)),
            "triangles": scene.n_triangles}


def fp_table(quick: bool, points: int) -> list[dict[str, Any]]:
    from visibility.cores.cos.core import REFINE_MAX

    n = 5_000 if quick else 20_000
    sizes = (0.05, 0.3, 4.0) if quick else (0.05, 0.1, 0.2, 0.3, 1.0, 4.0)
    rows = []
    for name in ("rooms", "village", "city"):
        sc = make_scene(name, triangles=n)
        for size in sizes:
            box = cell_around(sc, size, 0)
            ref = Reference(sc, box, points)
            r = _row(f"{name} {n // 1000}k {size:g} m", sc, box, 128, ref)
            r.update(scene=name, size=size)
            # Beside it, occludees no group hides over a whole pixel tested again at its
            # sub-pixels (``refine``, its most levels): the same reference judges both.
            q = _row(f"{name} {n // 1000}k {size:g} m, sub-pixels", sc, box, 128, ref,
                     refine=REFINE_MAX)
            r["refined"] = {k: q[k] for k in ("pvs", "fn_count", "fp", "overestimation",
                                               "seconds")}
            rows.append(r)
    return rows


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Stacked time per phase; cells above 5 s (the kitchen) in a panel of their own, so the
    sub-second ones stay readable."""
    import matplotlib.pyplot as plt

    groups = [[r for r in rows if r["seconds"] < 5.0], [r for r in rows if r["seconds"] >= 5.0]]
    groups = [g for g in groups if g]
    fig, axes = plt.subplots(1, len(groups), figsize=(6 * len(groups), 4.5), squeeze=False)
    for i, (ax, group) in enumerate(zip(axes[0], groups, strict=True)):
        labels = [f"{r['cell']}\nR={r['resolution']}" for r in group]
        left = np.zeros(len(group))
        for k, colour in zip(PHASES, ("#8da0cb", "#66c2a5", "#e78ac3", "#fc8d62"),
                                 strict=True):
            vals = np.array([r[k] for r in group])
            ax.barh(labels, vals, left=left, color=colour, label=k.replace("_seconds", ""))
            left += vals
        ax.axvline(PAPER_MS[1] / 1e3, color="k", ls="--", lw=1, label="paper, GPU, 220 ms")
        ax.set_xlabel("seconds (2 CPU cores)")
        ax.invert_yaxis()
        if i == 0:
            ax.legend(loc="upper right")
    fig.suptitle("cos core: time per phase (paper Fig. 19 breakdown)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _reading(speed_rows, fp_rows) -> list[str]:
    """What the tables say, in sentences built from the measured rows."""
    from visibility.cores.cos.core import DEFAULT_RESOLUTION, REFINE_MAX

    out = ["## Reading", ""]
    rows = [r for r in speed_rows if r["resolution"] == DEFAULT_RESOLUTION]
    if rows:
        out.append(f"Speed cells at the default resolution (R = {DEFAULT_RESOLUTION}), time "
                   "per phase (the paper's Fig. 19 breakdown) and the ratio to the paper's "
                   "35-220 ms per cell on a GPU:")
        out.append("")
        for r in rows:
            s = max(r["seconds"], 1e-9)
            out.append(
                f"- {r['cell']}: {r['seconds']:.2f} s = closed surfaces "
                f"{r['topology_seconds']:.2f} + sort {r['sort_seconds']:.2f} + lists "
                f"{r['list_seconds']:.2f} + coarse pass {r['coarse_seconds']:.2f} + resolve "
                f"{r['resolve_seconds']:.2f} s "
                f"({100 * r['resolve_seconds'] / s:.0f} % resolving), "
                f"{r['gpu_ratio'][0]:.1f}-{r['gpu_ratio'][1]:.1f} x the paper's times; "
                f"{r.get('projected', 0):,} footprints projected over the views, "
                f"{r.get('culled', 0):,} more spared by the scene hierarchy (no ray of the "
                "view meets them), "
                f"{r['unseen_back_faces']:,} back faces of closed surfaces left out "
                "(facing away from the whole cell), "
                + (f"the coarse pass on {r['coarse_tiles']:,} screen tiles left "
                   f"{r['coarse_dropped']:,} of their {r['coarse_entries']:,} items out of "
                   "the pixels' lists" + _coarse_work(r) + ", " if r.get("coarse_tiles")
                   else "no tile took the coarse pass, ")
                + (f"{r['block_tiles']:,} busy screen tiles sampled per {_block(r)} pixels "
                   f"({r['subpixels']:,} sub-samples resolved where a sample saw an entry"
                   f"{_walks(r)}, {r['sub_hidden']:,} entries hidden there; "
                   f"{_block_share(r)}), "
                   if r.get("block_tiles")
                   else "")
                + (f"{r['leaf_tests']:,} leaf boxes tested after a primitive of theirs was "
                   f"hidden, {r['leaf_hidden']:,} found hidden, sparing "
                   f"{r['leaf_skipped']:,} list entries their pixel, " if r.get("leaf_tests")
                   else "no leaf box tested, ") +
                f"{r['list_entries']:,} list entries (longest {r['longest_list']:,}) from "
                f"{r.get('tile_items', 0):,} (primitive, screen tile) pairs, "
                f"{r['list_entries'] / max(1, r.get('tile_items', 0)):.1f} pixels of a tile "
                "per pair, "
                f"{100 * r.get('early_z_cut', 0) / max(1, r['list_entries']):.0f} % of them "
                "cut by early z behind surfaces covering a pixel's offsets, "
                f"{r.get('fill_cut', 0):,} (primitive, pixel) pairs never listed, behind a "
                "triangle or a pair of them holding the pixel's offsets"
                + (f", {r['silhouette_edges']:,} silhouette edges walked and "
                   f"{r['plane_tests']:,} occluder triangles depth-tested to resolve them"
                   if r.get("silhouette_edges") else "") + _cycle_split(r)
                + (f"; {r['fused']:,} entries hidden by separate groups together, "
                   f"{r.get('front_parts', 0):,} by a group's part in front of them"
                   if r.get("fusion") == "groups" else "; the paper's fusion (edges only)")
                + f"; FN {r['fn_count']}, overestimation "
                f"{100 * r['overestimation']:.0f} % (paper: 20-90 %)." + _costliest(r))
        out.append("")
    if fp_rows:
        out.append("Overestimation against the dense reference, per scene (paper: 20-90 %):")
        out.append("")
        for scene in dict.fromkeys(r["scene"] for r in fp_rows):
            rs = [r for r in fp_rows if r["scene"] == scene]
            small = [100 * r["overestimation"] for r in rs if r["size"] <= 0.3]
            big = ", ".join(f"{100 * r['overestimation']:.0f} % at {r['size']:g} m"
                            for r in rs if r["size"] > 0.3)
            fn = sum(r["fn_count"] + r["refined"]["fn_count"] for r in rs)
            line = f"- {scene}: "
            if small:
                line += f"{min(small):.0f}-{max(small):.0f} % for cells up to 0.3 m"
            line += f"; {big}" if big else ""
            sub = [100 * r["refined"]["overestimation"] for r in rs]
            slow = [r["refined"]["seconds"] / max(r["seconds"], 1e-9) for r in rs]
            line += (f"; with sub-pixels ({REFINE_MAX} levels) {min(sub):.0f}-{max(sub):.0f} % "
                     f"for {min(slow):.1f}-{max(slow):.1f}x the time; FN {fn} in all.")
            out.append(line)
        out.append("")
    return out


def _cycle_split(r: dict) -> str:
    """Where the resolution's CPU cycles went (``cos_pvs``'s ``cycles_*``), for a row that
    spent some."""
    c = r.get("cycles") or {}
    tot = c.get("resolve", 0)
    if not tot:
        return ""
    share = {k: 100.0 * c.get(k, 0) / tot for k in ("test", "insert", "coverall")}
    part = {k: 100.0 * c.get(k, 0) / tot for k in CYCLE_PARTS}
    return (f"; of the resolution's CPU cycles {share['test']:.0f} % went to testing entries "
            f"(their regions K {part['test_region']:.0f} %, cover and depth tests against "
            f"single groups {part['test_groups']:.0f} %, against separate groups and at "
            f"sub-pixels or busy tiles' sub-samples {part['test_subpixels']:.0f} %, leaf "
            f"boxes {part['test_leaf']:.0f} %), "
            f"{share['insert']:.0f} % to making occluders of them (set-up "
            f"{part['insert_setup']:.0f} %, edge slots {part['insert_slots']:.0f} %, fusion "
            f"along shared edges and merges {part['insert_fusion']:.0f} %), "
            f"{share['coverall']:.0f} % to checking whether a group covers the whole pixel, "
            f"{100 - sum(share.values()):.0f} % to projecting entries and early z")


def _block(r: dict[str, Any]) -> str:
    """The busy tiles' sample size of a row: its own ``busy_block`` or the default."""
    b = r.get("params", {}).get("busy_block", BUSY_BLOCK)
    return f"{b} x {b}"


def _block_share(r: dict[str, Any]) -> str:
    """What the busy tiles' samples cost: their share of the resolution's CPU cycles and of
    its tested entries, and the cycles per entry tested there and elsewhere."""
    cyc = r["cycles"]["resolve"]
    bc, bt = r.get("block_cycles", 0), r.get("block_tested", 0)
    rest_c, rest_t = cyc - bc, r["tested"] - bt
    return (f"{100 * bc / max(1, cyc):.0f} % of the resolution's cycles and "
            f"{100 * bt / max(1, r['tested']):.0f} % of its tested entries, "
            f"{bc / max(1, bt):,.0f} cycles per entry tested there against "
            f"{rest_c / max(1, rest_t):,.0f} in the other tiles")


def _coarse_work(r: dict[str, Any]) -> str:
    """The coarse pass's work (``cos_pvs``'s ``coarse_*`` counters), for a row that took it."""
    w = r.get("coarse_work") or {}
    if not w.get("tested"):
        return ""
    tot = max(1, w["cycles_resolve"])
    return (f" (testing {w['tested']:,} of them: {w['silhouette_edges']:,} silhouette edges "
            f"walked, {w['plane_tests']:,} occluder triangles depth-tested; "
            f"{100 * w['cycles_test'] / tot:.0f} % of its cycles testing, "
            f"{100 * w['cycles_insert'] / tot:.0f} % making occluders)")


def _walks(r: dict[str, Any]) -> str:
    """How the sub-sample walks ended (``cos_pvs``'s ``walks_seen`` and ``subpixels_seen``;
    the other walks hid their entry, ``sub_hidden``): a walk that finds its entry seen
    resolves at least one sub-sample a level, one that hides it every one."""
    seen = r.get("walks_seen", 0)
    n = r.get("sub_hidden", 0) + seen
    if not n:
        return ""
    return (f", in {n:,} walks: {seen:,} found their entry seen, resolving "
            f"{r['subpixels_seen']:,} of them ({r['subpixels_seen'] / max(1, seen):.1f} a "
            "walk)")


def _costliest(r: dict[str, Any]) -> str:
    """The view the time went to, when one of the 30 took more than a third of it."""
    v = r.get("costliest_view")
    if not v or v["seconds"] < r["seconds"] / 3:
        return ""
    return (f" One view of the 30 took {100 * v['seconds'] / r['seconds']:.0f} % of the time: "
            f"the {v['frustum']} frustum of the {v['plane']} side plane, {v['list_entries']:,} "
            f"list entries (longest {v['longest_list']:,}).")


def _kitchen_md(k: dict[str, Any]) -> list[str]:
    """The kitchen part's tables and what they say."""
    if not k:
        return []
    out = ["## The kitchen: smaller cells, and the reference's resolution", "",
           "Cells around the same centre at the default resolution (5 and 10 cm: one run; "
           "0.3 m: the speed row above). Edges walked and plane tests are the resolution's "
           "work: occluder silhouette edges walked by the cover tests, occluder triangles "
           "put through the depth test.", "",
           "| cell | s | resolve | entries | edges walked | plane tests | PVS | ref | FN |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in k["sizes"]:
        out.append(f"| {100 * r['size']:g} cm | {r['seconds']:.2f} | "
                   f"{r['resolve_seconds']:.2f} | {r['list_entries']:,} | "
                   f"{r['silhouette_edges']:,} | {r['plane_tests']:,} | {r['pvs']:,} | "
                   f"{r['reference']:,} | {r['fn_count']} |")
    out += ["", f"The 0.3 m cell's reference from {GROWTH_EYES} stratified eyes (random cube "
            "orientation each) at rising resolution, against the PVS of the speed row "
            f"({k['pvs']:,} triangles of {k['triangles']:,}):", "",
            "| px per face | triangles seen | missing from the PVS |", "|---|---|---|"]
    for g in k["growth"]:
        out.append(f"| {g['resolution']} | {g['seen']:,} | {g['missed']} |")
    g0, g1 = k["growth"][0], k["growth"][-1]
    s = {r["size"]: r for r in k["sizes"]}
    small = s[min(s)]
    out += ["", f"Reading: each doubling of the reference's resolution finds more triangles "
            f"({g0['seen']:,} at {g0['resolution']} px, {g1['seen']:,} at "
            f"{g1['resolution']} px, {g1['seen'] / max(1, g0['seen']):.1f}x) and the PVS "
            f"holds {'all' if all(g['missed'] == 0 for g in k['growth']) else 'not all'} of "
            "them: the kitchen's clutter is finer than any of these pixels, so the sampled "
            "reference has not converged and much of the overestimation measured against it "
            "is triangles a denser reference sees. A smaller cell does not buy the time "
            f"back: at {100 * min(s):g} cm the cell takes {small['seconds']:.1f} s with a PVS "
            f"of {small['pvs']:,}.", ""]
    return out


def _md(speed_rows, fp_rows, points, elapsed, argv, load=None, kitchen=None) -> str:
    from visibility.cores.cos.core import REFINE_MAX

    cmd = " ".join(["python -m benchmarks.bench_cos", *argv])
    loadavg = ""
    if load:
        loadavg = (f" Load average (1 min) {load[0]:.2f} at the start, {load[1]:.2f} at the "
                   "end.")
    out = ["# cos core (camera offset space, Hladky et al. 2019)", "",
           f"Command: `{cmd}`; {platform.machine()}, "
           f"{os.cpu_count()} CPU cores, {elapsed:.0f} s in all.{loadavg} Times: best of "
           f"{FAST_REPEATS} runs (of 2 on the kitchen) after a warm-up compile. "
           "Reference: every triangle some pixel shows in Embree ray frames from "
           f"{points} eyes stratified in the box's open space (a randomly turned cube of "
           "256 px per face each, the clients' 5 cm near plane, `visibility/ray_frames.py`); "
           "FN counts the triangles it shows that the PVS lacks, each confirmed by a float64 "
           "cast, FP is the share of the PVS the reference did not see, overestimation is "
           "(PVS - true positives) / reference (the paper's 20-90 % measure).", "",
           "## Speed cells", "",
           "| cell | R | s | µs / px | closed | sort | lists | coarse | resolve | "
           "footprints | culled by tree | unseen back faces | coarse tiles | "
           "left out by coarse | entries | tile items | "
           "longest | mean list | cut while filling | early z cut | occluders | "
           "edges walked | plane tests | fusion | hidden by separate groups | PVS | ref | "
           "FN | FP | overest. | x paper (220 / 35 ms) |",
           "|" + "---|" * 31]
    for r in speed_rows:
        out.append(f"| {r['cell']} | {r['resolution']} | {r['seconds']:.2f} | "
                   f"{1e6 * r['seconds'] / max(1, r['pixels']):.1f} | "
                   f"{r['topology_seconds']:.2f} | {r['sort_seconds']:.2f} | "
                   f"{r['list_seconds']:.2f} | {r['coarse_seconds']:.2f} | "
                   f"{r['resolve_seconds']:.2f} | {r.get('projected', 0):,} | "
                   f"{r.get('culled', 0):,} | {r['unseen_back_faces']:,} | "
                   f"{r['coarse_tiles']:,} | {r['coarse_dropped']:,} | "
                   f"{r['list_entries']:,} | {r.get('tile_items', 0):,} | "
                   f"{r['longest_list']} | "
                   f"{r['mean_list']:.1f} | {r.get('fill_cut', 0):,} | "
                   f"{r.get('early_z_cut', 0):,} | "
                   f"{r.get('occluder_triangles', 0):,} | {r.get('silhouette_edges', 0):,} | "
                   f"{r.get('plane_tests', 0):,} | {r.get('fusion', '')} | "
                   f"{r.get('fused', 0):,} | {r['pvs']:,} | {r['reference']:,} | "
                   f"{r['fn_count']} | "
                   f"{r['fp']:.2f} | {100 * r['overestimation']:.0f} % | "
                   f"{r['gpu_ratio'][0]:.1f}-{r['gpu_ratio'][1]:.1f} |")
    out += ["", "![time per phase](cos.png)", ""]
    side = [r for r in speed_rows if r.get("sampling")]
    if side:
        out += ["## Beside `sampling`", "",
                "The same cells and reference, `sampling` at its defaults (best of 2; its "
                "missed triangles are not confirmed in float64, so a few may be float32 "
                "noise).", "",
                "| cell | cos s | cos PVS | cos FN | sampling s | sampling PVS | sampling "
                "missed | ref |", "|---|---|---|---|---|---|---|---|"]
        for r in side:
            sm = r["sampling"]
            out.append(f"| {r['cell']} | {r['seconds']:.2f} | {r['pvs']:,} | {r['fn_count']} | "
                       f"{sm['seconds']:.2f} | {sm['pvs']:,} | {sm['missed']:,} | "
                       f"{r['reference']:,} |")
        out += ["", "Reading: " + "; ".join(
            f"{r['cell']}: cos {r['seconds'] / max(r['sampling']['seconds'], 1e-9):.1f}x "
            f"sampling's time for {r['pvs'] / max(1, r['sampling']['pvs']):.1f}x its PVS, "
            f"missing {r['fn_count']} where sampling misses {r['sampling']['missed']:,} of "
            f"{r['reference']:,}" for r in side) + ".", ""]
    out += _reading(speed_rows, fp_rows)
    out += _kitchen_md(kitchen or {})
    out += ["## FP per scene and cell size (R = 128)", "",
            f"Each cell at the defaults and with sub-pixels (`refine={REFINE_MAX}`), judged by "
            "the same reference.", "",
            "| scene | cell | PVS | ref | FN | FP | overestimation (paper: 20-90 %) | s | "
            "sub-pixels: PVS | FN | overestimation | s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in fp_rows:
        q = r["refined"]
        out.append(f"| {r['scene']} | {r['size']:g} m | {r['pvs']:,} | {r['reference']:,} | "
                   f"{r['fn_count']} | {r['fp']:.2f} | {100 * r['overestimation']:.0f} % | "
                   f"{r['seconds']:.2f} | {q['pvs']:,} | {q['fn_count']} | "
                   f"{100 * q['overestimation']:.0f} % | {q['seconds']:.2f} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder the results go to")
    ap.add_argument("--points", type=int, default=64,
                    help="reference eyes per cell (ray frames of 256 px per face)")
    ap.add_argument("--parts", nargs="+", default=["speed", "fp"])
    ap.add_argument("--skip-kitchen", action="store_true",
                    help="leave out the 1M-triangle kitchen cell (its dense clutter makes "
                         "long lists: about a minute per run at R = 128 on 2 cores, see the "
                         "report)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    load0 = os.getloadavg()[0]
    # Warm-up compile.
    warm = make_scene("city", triangles=2000)
    _run(warm, cell_around(warm, 0.3, 0), 16, repeats=1)
    kitchen: dict[str, Any] = {}
    speed_rows = (speed(args.quick, args.points, not args.skip_kitchen, kitchen)
                  if "speed" in args.parts else [])
    fp_rows = fp_table(args.quick, args.points) if "fp" in args.parts else []
    elapsed = time.perf_counter() - t0
    load = (load0, os.getloadavg()[0])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = "cos_quick" if args.quick else "cos"
    (out / f"{stem}.json").write_text(json.dumps(
        {"speed": speed_rows, "fp": fp_rows, "kitchen": kitchen, "points": args.points,
         "seconds": elapsed, "loadavg": load},
        indent=1))
    if speed_rows:
        _plot(speed_rows, out / f"{stem}.png")
    import sys

    md = _md(speed_rows, fp_rows, args.points, elapsed, sys.argv[1:] if argv is None else argv,
             load, kitchen)
    (out / f"{stem}.md").write_text(md.replace("(cos.png)", f"({stem}.png)"))
    print(md)


if __name__ == "__main__":
    main()
