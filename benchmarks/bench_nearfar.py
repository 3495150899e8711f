"""Near-far benchmark on ``city``: δ / ε / PSNR / SSIM of morphed vs conventional compositing,
cubemap bake time and bytes.

Command (from the repository root):
    NUMBA_CACHE_DIR=.numba_cache PYOPENGL_PLATFORM=osmesa \
        .venv/bin/python benchmarks/bench_nearfar.py [--triangles 20000] [--frames 6] [--size 256]

Three regimes: "cell" (O = the centre of the 4 m cell holding U, default radii: what the server
sends by default), "block4" (O = the centre of the anchor cell of U's 4 x 4-cell block, default
radii: the server with ``near_far_block`` 4) and "region" (O fixed at the walk's start while U
walks up to r1 away, r1 = 30 m, r2 = 60 m: the paper's user region).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from client.compose import compose_frame
from client.discontinuity import discontinuity
from client.metrics import PSNR_CAP_DB, frame_metrics
from client.render import OffscreenRenderer
from client.walkthrough import generate_walkthrough
from protocol.cubemap import encode_cubemap
from visibility.generators import make_scene
from visibility.nearfar import NearFarConfig, bake_cubemap, split_ids
from visibility.nearfar.cells import cubemap_anchors
from visibility.viewcells import ViewcellGrid


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=20_000)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    print("command:", " ".join([".venv/bin/python"] + sys.argv))
    city = make_scene("city", triangles=a.triangles, seed=0)
    grid = ViewcellGrid.for_scene(city, 4.0)
    walk = generate_walkthrough(grid, duration=20.0, fps=2.0, seed=a.seed)
    r = OffscreenRenderer(a.size, a.size)
    o0 = walk.positions[0]
    dist = np.linalg.norm((walk.positions - o0)[:, [0, 2]], axis=1)
    every = np.linspace(1, len(walk) - 1, a.frames).round().astype(int)
    anchors = cubemap_anchors(grid, 4)
    regimes = {
        "cell": (NearFarConfig(resolution=a.resolution), every),
        "block4": (NearFarConfig(resolution=a.resolution), every),
        "region": (NearFarConfig(r1=30.0, r2=60.0, resolution=a.resolution),
                   np.flatnonzero((dist > 5.0) & (dist < 28.0))),
    }
    print(f"city {city.n_triangles} triangles, frames {a.size}x{a.size}, "
          f"cubemap {a.resolution}^2 x 6")
    for name, (cfg, idx) in regimes.items():
        idx = idx[np.linspace(0, len(idx) - 1, min(a.frames, len(idx))).round().astype(int)]
        cubes: dict = {}
        rows = {True: [], False: []}
        bake_s, nbytes, offs = [], [], []
        for i in idx:
            U, fwd = walk.positions[i], walk.forwards[i]
            if name == "region":
                o = o0
            else:
                c = grid.cell_of(U)
                o = grid.boxes[c if name == "cell" else anchors[c]].mean(axis=0)
            key = tuple(np.round(o, 6))
            if key not in cubes:
                t = time.perf_counter()
                cube = bake_cubemap(city, o, cfg)
                bake_s.append(time.perf_counter() - t)
                nbytes.append(len(encode_cubemap(0, o, cube.colors, cube.ranges, cfg.r1, cfg.r2)))
                sp = split_ids(city, o, cfg)
                cubes[key] = (cube, city.triangles(sp.near_ids), city.colors[sp.near_ids])
            cube, tris, cols = cubes[key]
            offs.append(float(np.linalg.norm((U - o)[[0, 2]])))
            gt = r.render_scene(city, U, fwd)
            for morph in (True, False):
                f = compose_frame(r, tris, cols, cube, U, fwd, cfg.r1, cfg.r2, morph=morph)
                d = discontinuity(f.points, U, fwd, r.tan_x, r.tan_y)
                m = frame_metrics(f, gt)
                rows[morph].append([d.mean_abs, m["epsilon"], min(m["psnr"], PSNR_CAP_DB),
                                    m["ssim"]])
        print(f"\n[{name}] r1={cfg.r1} r2={cfg.r2}, {len(idx)} frames, |U-O| "
              f"{min(offs):.1f}-{max(offs):.1f} m; {len(cubes)} cubemaps: bake "
              f"{np.mean(bake_s) * 1e3:.0f} ms mean (first {bake_s[0] * 1e3:.0f} ms), "
              f"{np.mean(nbytes) / 1e3:.1f} kB encoded (zlib)")
        print(f"  {'compositing':<13}{'mean|δ|':>9}{'ε %':>8}{'PSNR dB':>9}{'SSIM':>8}")
        for morph in (True, False):
            v = np.mean(rows[morph], axis=0)
            label = "morph" if morph else "conventional"
            print(f"  {label:<13}{v[0]:>9.4f}{v[1]:>8.3f}{v[2]:>9.2f}{v[3]:>8.4f}")
    r.close()


if __name__ == "__main__":
    main()
