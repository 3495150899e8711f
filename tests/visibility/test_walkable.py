"""Walk-area detection from geometry alone (what loaded scenes get)."""

import numpy as np
import pytest

from tests.grouping import module_on_one_worker
from visibility.cores.designed_scenes import Builder
from visibility.viewcells import ViewcellGrid

pytestmark = module_on_one_worker("walkable")  # kernels of its own (tests/grouping.py)


def test_room_with_two_storeys_has_cells_on_each_floor():
    b = Builder()
    # Inward-facing shell: floor faces up, ceilings face down; a mezzanine floor at 4 m.
    b.quad((0, 0, 0), (0, 0, 16), (16, 0, 16), (16, 0, 0), 0)  # floor (up)
    b.quad((0, 4, 0), (0, 4, 16), (16, 4, 16), (16, 4, 0), 1)  # storey 2 floor (up)
    b.quad((0, 3.9, 0), (16, 3.9, 0), (16, 3.9, 16), (0, 3.9, 16), 1)  # its underside (down)
    b.quad((0, 8, 0), (16, 8, 0), (16, 8, 16), (0, 8, 16), 2)  # roof underside (down)
    grid = ViewcellGrid.for_scene(b.scene("storeys"), 4.0)
    levels = np.unique(np.round(grid.floor, 1))
    np.testing.assert_allclose(levels, [0.0, 4.0])
    assert len(grid) == 32
    assert np.all(grid.boxes[:, 1, 1] < grid.ceiling)


def test_city_without_terrain_walks_the_streets_not_the_roofs():
    b = Builder()
    # Two closed buildings (outward faces) and no ground at all, like the Lyon scene.
    b.box((0, 0, 0), (20, 15, 20), 0)
    b.box((32, 0, 0), (52, 12, 20), 1)
    b.box((0, 0, 32), (52, 18, 52), 2)
    grid = ViewcellGrid.for_scene(b.scene("city"), 4.0)
    assert len(grid) > 0
    assert np.all(np.abs(grid.floor) < 0.5), "cells must stand on the ground, not on roofs"
    # The street between the first two buildings is walkable; their insides are not.
    assert grid.cell_of([26, 1.7, 10]) is not None
    assert grid.cell_of([10, 1.7, 10]) is None
    assert grid.cell_of([42, 1.7, 10]) is None


def test_ground_with_a_building_keeps_cells_off_the_roof_and_out_of_the_inside():
    b = Builder()
    b.quad((-40, 0, -40), (-40, 0, 40), (40, 0, 40), (40, 0, -40), 0)  # ground (up)
    b.box((-10, 0, -10), (10, 12, 10), 1)  # closed building with a bottom face
    grid = ViewcellGrid.for_scene(b.scene("block"), 4.0)
    assert grid.cell_of([-30, 1.7, -30]) is not None
    assert grid.cell_of([0, 1.7, 0]) is None
    assert grid.cell_of([0, 13.7, 0]) is None
    assert np.all(grid.floor < 0.5)


def test_sidecar_walk_overrides_detection(tmp_path):
    import json

    import trimesh

    mesh = trimesh.creation.box(extents=(10, 1, 10))
    path = tmp_path / "slab.ply"
    mesh.export(path)
    (tmp_path / "slab.json").write_text(json.dumps({"walk": {"rects": [[0, 0, 8, 4, 0.5]]}}))
    from visibility.loaders import load_scene

    grid = ViewcellGrid.for_scene(load_scene(path), 4.0)
    assert len(grid) == 2
    np.testing.assert_allclose(grid.floor, 0.5)


def test_clockwise_winding_hint_flips_the_floors():
    b = Builder()
    # A room wound clockwise (as Quake levels are): the floor's computed normal points down.
    b.quad((0, 0, 0), (16, 0, 0), (16, 0, 16), (0, 0, 16), 0)
    b.quad((0, 5, 0), (0, 5, 16), (16, 5, 16), (16, 5, 0), 1)
    scene = b.scene("cw_room")
    assert len(ViewcellGrid.for_scene(scene, 4.0)) == 0
    scene.meta["winding"] = "cw"
    grid = ViewcellGrid.for_scene(scene, 4.0)
    assert len(grid) == 16 and np.allclose(grid.floor, 0.0)


# ----------------------------------------------------------------------------- bounded memory
_WIDE_PLY_CHILD = r"""
import json, resource, sys, time
import numpy as np
import pytest
from visibility.loaders import load_scene
from visibility.walkable import detect_walk_area
from visibility.viewcells import ViewcellGrid

small = load_scene(sys.argv[2])
detect_walk_area(small, 4.0)  # load the compiled kernels before measuring
scene = load_scene(sys.argv[1])
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
walk = detect_walk_area(scene, 4.0)
seconds = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:
    ViewcellGrid(walk, 4.0)
    grid = "built"
except ValueError as exc:
    grid = str(exc)
print(json.dumps({"triangles": scene.n_triangles, "extra_kb": peak - before, "seconds": seconds,
                  "rects": len(walk.rects), "square": float(walk.rects[0, 2] - walk.rects[0, 0]),
                  "grid": grid}))
"""


def _write_ply(path, tris: np.ndarray) -> None:
    v = tris.reshape(-1, 3)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x",
             "property float y", "property float z", f"element face {len(tris)}",
             "property list uchar int vertex_indices", "end_header"]
    lines += [f"{x:.3f} {y:.3f} {z:.3f}" for x, y, z in v]
    lines += [f"3 {3 * i} {3 * i + 1} {3 * i + 2}" for i in range(len(tris))]
    path.write_text("\n".join(lines) + "\n")


def _wide_scene(span: float) -> np.ndarray:
    """202 triangles: a ground square of ``span`` metres (2) and 50 pyramids' faces (200)."""
    rng = np.random.default_rng(0)
    g = [[0, 0, 0], [0, 0, span], [span, 0, span], [span, 0, 0]]
    tris = [[g[0], g[1], g[2]], [g[0], g[2], g[3]]]
    for cx, cz in rng.uniform(100, span - 100, size=(50, 2)):
        apex = [cx, 20.0, cz]
        base = [[cx - 10, 0, cz - 10], [cx + 10, 0, cz - 10], [cx + 10, 0, cz + 10],
                [cx - 10, 0, cz + 10]]
        tris += [[base[i], base[(i + 1) % 4], apex] for i in range(4)]
    return np.array(tris, dtype=np.float64)


def test_a_20_km_scene_is_detected_in_bounded_memory_and_time(tmp_path):
    """Issue 19: 202 triangles spanning 20 km drove the detection past 6 GB in 8 s."""
    import json
    import os
    import subprocess
    import sys

    from visibility.walkable import MAX_WALK_COLUMNS

    wide, small = tmp_path / "wide.ply", tmp_path / "small.ply"
    _write_ply(wide, _wide_scene(20_000.0))
    _write_ply(small, _wide_scene(300.0))
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, "PYTHONPATH": root}
    run = subprocess.run([sys.executable, "-c", _WIDE_PLY_CHILD, str(wide), str(small)],
                         capture_output=True, text=True, timeout=300, env=env, cwd=root)
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["triangles"] == 202
    assert out["extra_kb"] < 500 * 1024, out  # peak RSS growth during detection
    assert out["seconds"] < 60, out
    # Coarser squares, on the 4 m lattice, within the cap; the ground is found walkable.
    assert out["square"] > 4.0 and out["square"] % 4.0 == 0
    assert MAX_WALK_COLUMNS / 2 < out["rects"] <= MAX_WALK_COLUMNS
    assert "MAX_VIEWCELLS" in out["grid"]  # 20 km of 4 m viewcells: refused, clearly


def test_grid_shape_coarsens_on_the_lattice_then_refuses():
    from visibility.walkable import MAX_COARSENING, MAX_WALK_COLUMNS, _grid_shape

    assert _grid_shape(np.array([100.0, 50.0]), 4.0, "x") == (4.0, 25, 13)
    s, nx, nz = _grid_shape(np.array([20_000.0, 20_000.0]), 4.0, "x")
    assert s == 28.0 and nx * nz <= MAX_WALK_COLUMNS
    too_wide = 4.0 * MAX_COARSENING * np.sqrt(MAX_WALK_COLUMNS) * 1.5
    with pytest.raises(ValueError, match="MAX_WALK_COLUMNS"):
        _grid_shape(np.array([too_wide, too_wide]), 4.0, "x")
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError):
            _grid_shape(np.array([10.0, 10.0]), bad, "x")
    with pytest.raises(ValueError):
        _grid_shape(np.array([np.inf, 10.0]), 4.0, "x")


def test_scene_wide_triangles_grow_the_bins_within_their_cap(monkeypatch):
    """Bins only speed up the casts: forced to grow, they give the same walk area."""
    from visibility import walkable
    from visibility.scene import Scene

    tris = _wide_scene(600.0)
    scene = Scene(tris.reshape(-1, 3), np.arange(len(tris) * 3).reshape(-1, 3))
    fine = walkable.detect_walk_area(scene, 4.0)
    monkeypatch.setattr(walkable, "MAX_BIN_ITEMS", 1000)
    xz_min, xz_max = tris[:, :, [0, 2]].min(1), tris[:, :, [0, 2]].max(1)
    size, nbx, nbz = walkable._bins(xz_min, xz_max, np.zeros(2), 4.0, 150, 150)
    assert size > 4.0 and nbx < 150
    coarse = walkable.detect_walk_area(scene, 4.0)
    np.testing.assert_array_equal(fine.rects, coarse.rects)
    assert len(fine.rects) > 1000


def test_bin_triangles_puts_boxes_past_the_grid_in_its_border_bins():
    """Each box is in every bin it reaches and a box wholly outside the grid in the border
    bins a clamped query reads (``cell_walk.XZGrid`` pads its grid's box so), each bin's
    triangles ascending."""
    from visibility.walkable import bin_of, bin_triangles

    lo = np.array([[0.5, 0.5], [-9.0, 1.5], [1.5, 7.0], [-3.0, -3.0], [0.2, 0.2]])
    hi = np.array([[1.5, 0.7], [-8.0, 1.7], [1.7, 9.0], [9.0, 9.0], [0.3, 0.3]])
    starts, items = bin_triangles(lo, hi, np.zeros(2), 1.0, 3, 3)
    bins = [set(items[starts[b]:starts[b + 1]].tolist()) for b in range(9)]
    want = [set() for _ in range(9)]
    for t in range(len(lo)):
        for i in range(bin_of(lo[t, 0], 0.0, 1.0, 3), bin_of(hi[t, 0], 0.0, 1.0, 3) + 1):
            for k in range(bin_of(lo[t, 1], 0.0, 1.0, 3), bin_of(hi[t, 1], 0.0, 1.0, 3) + 1):
                want[i * 3 + k].add(t)
    assert bins == want
    assert 1 in bins[0 * 3 + 1] and 2 in bins[1 * 3 + 2]  # left of the grid; beyond its top
    assert all(3 in bins[b] for b in range(9))  # the box over the whole grid
    for b in range(9):
        assert list(items[starts[b]:starts[b + 1]]) == sorted(items[starts[b]:starts[b + 1]])
