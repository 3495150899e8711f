"""The trim regions benchmark's leaf-size table scores each leaf size on one set of frames."""

from __future__ import annotations

from benchmarks import bench_trim_regions as bench


def test_leaf_sizes_score_every_size_on_the_same_frames(monkeypatch):
    monkeypatch.setattr(bench, "LEAF_SIZES", (256, 4096))
    casts: dict = {}
    rows = bench.leaf_sizes(quick=True, frames=2, casts=casts)
    assert [r["max_prims"] for r in rows] == [256, 4096]
    # The ground truth is the frames' triangles: one cast serves every leaf size.
    assert rows[0]["gt"] == rows[1]["gt"] > 0
    # Larger leaves peel fewer layers.
    assert rows[1]["layers"] < rows[0]["layers"]
    for r in rows:
        assert r["pvs"] > 0 and r["seconds"] > 0
        assert 0 <= r["fn_pixels_max"] <= 6 * 256 * 256
    # The cast is kept for the quality table, which scores the same cell: taken, not recast.
    (key, cast), = casts.items()
    scene = bench.load("village", 20_000)
    box = bench.sphere_cell(scene, 0.2, 0)
    assert bench._cast(casts, "village", scene, box, 2, keep=False) is cast and not casts


def test_aimed_rays_grow_the_ground_truth_of_a_cell():
    from visibility.cores.base import get_core
    from visibility.ray_frames import seen_ids
    from visibility.viewcells import Viewcell

    scene = bench.load("village", 20_000)
    box = bench.sphere_cell(scene, 0.2, 0)
    cast = bench._cast({}, "village", scene, box, 2, keep=False)
    core = get_core("trim_regions")
    pvs = core.compute(scene, Viewcell(box), core.make_params(max_delta=0.2))
    got = bench.aimed_ground_truth(scene, box, pvs.triangle_ids, cast, most=32)
    # Two frames undercount: rays aimed at the answer's other triangles see more of them.
    assert got["gt_aimed"] > len(seen_ids(cast))
    assert got["aimed_rays"] == 32 and got["aimed_seconds"] > 0
    assert 0 <= got["aimed_missed"] <= got["gt_aimed"]


def test_side_by_side_answers_are_scored_against_rays_aimed_at_all_of_them():
    from visibility.cores.base import get_core
    from visibility.ray_frames import seen_ids
    from visibility.viewcells import Viewcell

    scene = bench.load("village", 20_000)
    box = bench.sphere_cell(scene, 0.2, 0)
    cast = bench._cast({}, "village", scene, box, 2, keep=False)
    cos = get_core("cos")
    ids = cos.compute(scene, Viewcell(box), cos.make_params()).triangle_ids
    rows = [{"core": "cos"}, {"core": "half of it"}]
    bench._side_aimed(rows, [ids, ids[::2]], scene, box, cast, most=32)
    assert rows[0]["gt_aimed"] == rows[1]["gt_aimed"] > len(seen_ids(cast))
    # cos misses nothing any eye of the cube sees; half its answer misses some of it.
    assert rows[0]["fn_aimed"] == 0 and rows[1]["fn_aimed"] > 0
    assert rows[0]["aimed_rays"] <= 32
