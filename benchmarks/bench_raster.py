"""Throughput of the numba id-buffer rasterizer and convergence of the sampled ground truth.

Run ``python -m benchmarks.bench_raster [--quick]``. For the generated ``city`` scene at 100k and
1M triangles it renders cubemaps from the centre of the first viewcell and prints the median
time, triangles/s and pixels/s at 256 and 512 px per face; then it samples the ground-truth PVS
of that cell and prints and plots (benchmarks/results/) how many triangles each batch of
viewpoints adds. Wall times on a shared machine vary; the CPU time is printed alongside.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> str:
    """One line describing the machine and the numeric stack (runs a small parallel render
    first, which also compiles the kernels, to learn numba's threading layer)."""
    import numba

    from visibility.raster import render_ids

    rng = np.random.default_rng(0)
    v = rng.normal(size=(3 * 60_000, 3)) + [0.0, 0.0, -5.0]
    render_ids(v, np.arange(len(v), dtype=np.int32).reshape(-1, 3), np.zeros(3), np.eye(3),
               64, 64)
    try:
        layer = numba.threading_layer()
    except ValueError:
        layer = numba.config.THREADING_LAYER
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    wait = os.environ.get("OMP_WAIT_POLICY", "unset")
    return (
        f"{cpu}, {os.cpu_count()} CPUs; numba {numba.__version__} ({numba.get_num_threads()} "
        f"threads, {layer} layer, OMP_WAIT_POLICY {wait}); numpy {np.__version__}; "
        f"Python {platform.python_version()}; load average {load:.2f} at start"
    )


def time_cubemaps(scene, eye, resolution: int, repeats: int) -> dict:
    """Median wall and CPU seconds of ``render_cubemap`` over ``repeats`` runs (after a warm-up),
    with the raster counters of one run."""
    from visibility.raster import render_cubemap

    mask = scene.valid_faces
    render_cubemap(scene.vertices, scene.faces, eye, resolution, face_mask=mask)
    walls, cpus = [], []
    stats: dict = {}
    for k in range(repeats):
        run_stats: dict = {}
        t0, c0 = time.perf_counter(), time.process_time()
        _, ids = render_cubemap(scene.vertices, scene.faces, eye, resolution, face_mask=mask,
                                stats=run_stats)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        if k == 0:
            stats = run_stats
            stats["visible"] = int(len(np.unique(ids[ids >= 0])))
    return {"wall": float(np.median(walls)), "wall_min": float(np.min(walls)),
            "cpu": float(np.median(cpus)), **stats}


def convergence_plot(curves: dict[str, list[tuple[int, int, int]]], path: Path) -> None:
    """Triangles found vs viewpoints, one line per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    for label, conv in curves.items():
        x = [c[0] for c in conv]
        y = [c[1] for c in conv]
        ax.plot(x, y, marker="o", ms=3, label=label)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("viewpoints sampled in the cell")
    ax.set_ylabel("distinct triangles seen")
    ax.set_title("Sampled ground truth: convergence (city, cell 0)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="fewer repeats and viewpoints (a smoke run, about a minute)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000],
                        help="city sizes in triangles")
    parser.add_argument("--points", type=int, default=None,
                        help="ground-truth viewpoints (default 256, quick 32)")
    parser.add_argument("--gt-resolution", type=int, default=256)
    args = parser.parse_args(argv)

    from visibility.generators import make_scene
    from visibility.ground_truth import sample_pvs
    from visibility.viewcells import ViewcellGrid

    repeats = 3 if args.quick else 7
    points = args.points or (32 if args.quick else 256)
    sizes = [min(s, 100_000) for s in args.sizes] if args.quick else args.sizes
    print("command:", " ".join([Path(sys.executable).name, "-m", "benchmarks.bench_raster",
                                *(argv if argv is not None else sys.argv[1:])]))
    print("machine:", machine())
    print()

    curves: dict[str, list[tuple[int, int, int]]] = {}
    for size in dict.fromkeys(sizes):
        t0 = time.perf_counter()
        scene = make_scene("city", triangles=size, seed=0)
        build = time.perf_counter() - t0
        cell = ViewcellGrid.for_scene(scene).cell(0)
        eye = cell.center
        n_valid = int(np.count_nonzero(scene.valid_faces))
        print(f"city, {scene.n_triangles:,} triangles ({n_valid:,} valid), built in {build:.1f} s;"
              f" eye at the centre of cell 0 {np.round(eye, 2).tolist()}")
        print(f"  {'face px':>8} {'median ms':>10} {'min ms':>8} {'cpu ms':>8} "
              f"{'Mtri/s':>8} {'Mpx/s':>8} {'px tests':>10} {'visible':>8}")
        for res in (256, 512):
            r = time_cubemaps(scene, eye, res, repeats)
            tri_s = 6 * n_valid / r["wall"]
            px_s = 6 * res * res / r["wall"]
            print(f"  {res:>5}x6 {r['wall'] * 1e3:>10.1f} {r['wall_min'] * 1e3:>8.1f} "
                  f"{r['cpu'] * 1e3:>8.1f} {tri_s / 1e6:>8.1f} {px_s / 1e6:>8.2f} "
                  f"{r['pixel_tests']:>10,} {r['visible']:>8,}")
        gt = sample_pvs(scene, cell, n_points=points, resolution=args.gt_resolution, seed=0,
                        batch=1)
        # Report at powers of two (and the end) rather than every viewpoint.
        marks = {2**k for k in range(32)} | {points}
        conv = [c for c in gt.convergence if c[0] in marks]
        prev = 0
        table = []
        for n, total, _ in conv:
            table.append((n, total, total - prev))
            prev = total
        curves[f"{scene.n_triangles:,} triangles"] = table
        print(f"  ground truth: {points} viewpoints x 6 x {args.gt_resolution}^2 px in "
              f"{gt.seconds:.1f} s ({gt.seconds / points * 1e3:.0f} ms per viewpoint)")
        print(f"  {'samples':>8} {'found':>8} {'new':>8}")
        for n, total, new in table:
            print(f"  {n:>8} {total:>8} {new:>8}")
        print()
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / ("raster_convergence_quick.png" if args.quick else "raster_convergence.png")
    convergence_plot(curves, out)
    print(f"plot: {out.relative_to(Path.cwd()) if out.is_relative_to(Path.cwd()) else out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
