"""The real-scene benchmark's instruments: the ray-cast reference and the missed-size measure."""

from __future__ import annotations

import platform
import sys

import numpy as np
import pytest

from benchmarks import bench_real_cells, peers
from visibility.cores import designed_scenes as ds
from visibility.generators import make_scene
from visibility.viewcells import Viewcell

#: embreex has wheels for Linux x86_64, the project's machines: there its absence is a broken
#: set-up and must fail these tests; elsewhere the set-up may lack it (scripts/setup.sh).
WHEELS = sys.platform == "linux" and platform.machine() == "x86_64"
pytestmark = pytest.mark.skipif(not peers.available() and not WHEELS,
                                reason="embreex has no wheel for this platform")


def test_the_ray_cast_reference_sees_through_the_door_and_not_behind_the_wall():
    scene, cell, known = ds.two_rooms_and_a_door()
    ref, seconds = bench_real_cells.reference(scene, cell, points=16, rays=96, seed=0)
    assert seconds > 0
    assert set(known["visible"]) <= set(ref.tolist())
    assert not set(known["hidden"]) & set(ref.tolist())


def test_missed_pixels_is_area_over_distance_in_pixels():
    scene, _, _ = ds.two_rooms_and_a_door()
    # The far wall's first triangle, 1 m^2 of it 10 m away from an eye at x = 2:
    eye = np.array([2.0, 1.5, 3.0])
    ids = np.array([ds.two_rooms_and_a_door()[2]["visible"][0]])
    tri = scene.triangles(ids)[0]
    area = 0.5 * np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0]))
    d2 = np.sum((tri.mean(axis=0) - eye) ** 2)
    px = bench_real_cells.missed_pixels(scene, ids, eye, 100)
    assert px == pytest.approx(area / d2 / (2.0 / 100) ** 2)
    assert bench_real_cells.missed_pixels(scene, ids[:0], eye, 100) == 0.0


def test_walk_cells_are_cells_of_the_grid_and_deterministic():
    scene = make_scene("rooms", triangles=5_000)
    a = bench_real_cells.walk_cells(scene, seed=3, k=2)
    assert a == bench_real_cells.walk_cells(scene, seed=3, k=2)
    assert 1 <= len(a) <= 2 and all(isinstance(c, int) and c >= 0 for c in a)


def test_parse_variant_reads_numbers_and_words():
    assert bench_real_cells.parse_variant("jitter=0,cuts=0") == {"jitter": 0, "cuts": 0}
    assert bench_real_cells.parse_variant("jitter=0.25, first_orientation=axis") == {
        "jitter": 0.25, "first_orientation": "axis"}
    with pytest.raises(SystemExit, match="NAME=VALUE"):
        bench_real_cells.parse_variant("jitter")


def test_frame_views_stand_on_the_open_floor_and_look_level_enough():
    from visibility.cell_walk import cell_walk
    from visibility.viewcells import ViewcellGrid

    scene = make_scene("rooms", triangles=5_000)
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(bench_real_cells.walk_cells(scene, seed=3, k=1)[0])
    views, has_open = bench_real_cells.frame_views(scene, cell, 64, seed=5)
    assert has_open and len(views) == 64
    box = np.asarray(cell.box)
    walk = cell_walk(scene, box)
    open_xz = {(x, z) for i, x in enumerate(walk.xs) for k, z in enumerate(walk.zs)
               if walk.open[i, k]}
    for eye, fwd in views:
        assert (eye[0], eye[2]) in open_xz
        assert box[0, 1] <= eye[1] <= box[1, 1]
        assert np.linalg.norm(fwd) == pytest.approx(1.0)
        assert abs(np.degrees(np.arcsin(fwd[1]))) <= bench_real_cells.MAX_PITCH + 1e-9
    again, _ = bench_real_cells.frame_views(scene, cell, 64, seed=5)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
               for a, b in zip(views, again, strict=True))
    # Different views, not one repeated: the eyes spread over the open floor.
    assert len({tuple(e) for e, _ in views}) > 32


def test_generated_specs_are_parsed_once_and_bad_ones_refused_with_the_names(tmp_path):
    assert bench_real_cells.parse_generated("city:100000") == ("city", 100_000)
    for bad in ("rooms", "rooms:x", "rooms:0", "nowhere:100"):
        with pytest.raises(SystemExit, match="NAME:TRIANGLES.*city"):
            bench_real_cells.parse_generated(bad)
    with pytest.raises(SystemExit, match="NAME:TRIANGLES"):
        bench_real_cells.main(["--scenes", "--generated", "rooms", "--out",
                               str(tmp_path / "x.md")])
    assert not (tmp_path / "x.md").exists()


def test_rays_aimed_at_every_triangle_see_through_the_door_and_score_each_answer():
    scene, cell, known = ds.two_rooms_and_a_door()
    every = np.arange(scene.n_triangles)
    got, seconds = bench_real_cells.aimed_reference(scene, cell, every, every[:0], seed=0)
    assert seconds > 0 and got.converged
    assert set(known["visible"]) <= set(got.ids.tolist())
    assert not set(known["hidden"]) & set(got.ids.tolist())
    # Two answers scored against what the rays saw: the visible set, and half of it.
    visible = np.asarray(known["visible"])
    rows = [{"method": "all"}, {"method": "half"}]
    bench_real_cells._score_aimed(rows, [every, visible[::2]], scene, cell, every[:0], 0,
                                  log=lambda *_: None)
    assert rows[0]["aimed"] == rows[1]["aimed"] == len(got.ids)
    assert rows[0]["aimed_fn"] == 0.0 and rows[0]["pvs_over_aimed"] > 1.0
    assert rows[1]["aimed_fn"] == pytest.approx(1 - len(visible[::2]) / len(got.ids))


def test_where_seen_counts_each_miss_at_the_first_eyes_that_see_it():
    from visibility.cores.base import get_core

    params = get_core("from_segment").make_params()
    scene, cell, known = ds.two_rooms_and_a_door()
    # Through the door from the walked segments; the box tucked behind the wall from nowhere.
    w = bench_real_cells.where_seen(scene, cell, np.array(known["visible"] + known["hidden"]),
                                    params, seed=0)
    assert w == {"segments": len(known["visible"]), "outline": 0, "inside": 0,
                 "none": len(known["hidden"])}
    # A horizontal slit 4 mm high at the eye range's middle height, 5 m away, and a square 30 m
    # away level with it: seen from the cell's outline near that height, but from none of the
    # segments, walked at its bottom, middle (1.7 m) and top heights.
    b = ds.Builder()
    b.quad((-5, 0, -5), (-5, 0, 6), (4, 0, 6), (4, 0, -5), 0)
    b.quad((5, 0, -10), (5, 1.598, -10), (5, 1.598, 10), (5, 0, 10), 1)
    b.quad((5, 1.602, -10), (5, 10, -10), (5, 10, 10), (5, 1.602, 10), 1)
    far = b.quad((30, 1.59, 0.4), (30, 1.61, 0.4), (30, 1.61, 0.6), (30, 1.59, 0.6), 2)
    slit = b.scene("slit")
    box = Viewcell(np.array([[0.0, 1.5, 0.0], [1.0, 1.9, 1.0]]))
    w = bench_real_cells.where_seen(slit, box, np.array(far), params, seed=0)
    assert w == {"segments": 0, "outline": len(far), "inside": 0, "none": 0}


def test_the_report_tables_from_segment_s_phases_and_work_beside_its_row():
    """Each ``from_segment`` row carries its phases and counters (``WORK``, from its stats)
    and the report lists them in a table of their own; rows of other cores do not."""
    from visibility.cores.base import get_core

    scene = make_scene("rooms", triangles=2000)
    cell = Viewcell(np.array([[1.0, 1.5, 1.0], [2.0, 1.9, 2.0]]))
    fs = get_core("from_segment")
    pvs = fs.compute(scene, cell, fs.make_params(resolution=32))
    work = {k: pvs.stats[k] for k in bench_real_cells.WORK if k in pvs.stats}
    assert set(work) == set(bench_real_cells.WORK)
    assert work["segments"] > 0 and work["final_pieces"] > 0 and work["envelope_seconds"] > 0
    base = {"scene": "rooms", "cell": 7, "cell_size": 1.0, "reference": 10, "seconds": 0.5,
            "pvs": 12, "fn": 0.0, "fp": 0.1, "missed": 0, "missed_median_px": 0.0,
            "eps_mean": 0.0, "eps_worst": 0.0, "psnr_mean": 90.0, "ssim_mean": 1.0}
    rows = [{**base, "method": "from_segment (defaults)", "work": work},
            {**base, "method": "sampling (defaults)"}]
    cfg = {"seed": 1, "points": 64, "rays": 183, "frames": 64, "frame_px": 256}
    text = bench_real_cells.report(rows, cfg, "python -m benchmarks.bench_real_cells", 60.0)
    table = text[text.index("`from_segment`'s phases and work"):]
    assert f"| {work['walk']} | {work['segments']} | {work['runs']} |" in table
    assert f"{work['final_pieces']:,} |" in table
    assert "sampling (defaults)" not in table
