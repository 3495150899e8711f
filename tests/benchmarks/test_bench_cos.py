"""The cos benchmark's speed part runs end to end (``--quick``) and writes what it says."""

from __future__ import annotations

import json

from benchmarks.bench_cos import main
from visibility.cores.cos.core import LEAF_LIST
from visibility.cores.cos.lists import TILE


def test_quick_speed_run_writes_the_counters(tmp_path):
    main(["--quick", "--parts", "speed", "--points", "8", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "cos_quick.json").read_text())["speed"]
    assert {r["resolution"] for r in rows} == {64, 128}
    for r in rows:
        # Each (primitive, tile) pair lists the primitive at no more than a tile's pixels.
        assert 0 < r["tile_items"] and r["list_entries"] <= TILE * TILE * r["tile_items"]
        # cos promises no false negatives.
        assert r["fn_count"] == 0
    # Each cell beside separate groups hiding together: they hide only more.
    for r in rows:
        if r["cell"].endswith(", fusion groups"):
            base = next(b for b in rows if b["cell"] == r["cell"][:-len(", fusion groups")]
                        and b["resolution"] == r["resolution"])
            assert (base["fusion"], r["fusion"]) == ("edges", "groups")
            assert r["pvs"] <= base["pvs"] and base["fused"] == 0
    # The 4 m cell beside no leaf boxes: the step tests none; where the default's lists
    # never reach LEAF_LIST it tests none either, for the same answer.
    step = next(r for r in rows if r["cell"].endswith(", without leaf boxes"))
    base = next(b for b in rows if b["cell"] == step["cell"][:-len(", without leaf boxes")]
                and b["resolution"] == step["resolution"])
    assert step["leaf_tests"] == step["leaf_skipped"] == 0
    assert base["leaf_hidden"] <= base["leaf_tests"]
    if base["longest_list"] < LEAF_LIST:
        assert base["leaf_tests"] == 0 and base["pvs"] == step["pvs"]
    md = (tmp_path / "cos_quick.md").read_text()
    assert "leaf box" in md
    assert "| tile items |" in md and "pixels of a tile per pair" in md
    assert "hidden by separate groups" in md


def test_the_fp_table_sets_sub_pixels_beside_the_defaults():
    # The fp part's table and reading, from one row (its cells take minutes; the speed run
    # above covers the measuring).
    from benchmarks.bench_cos import _md
    from visibility.cores.cos.core import REFINE_MAX

    row = {"scene": "city", "size": 0.3, "pvs": 1200, "reference": 1000, "fn_count": 0,
           "fp": 0.2, "overestimation": 0.2, "seconds": 0.1,
           "refined": {"pvs": 1100, "fn_count": 0, "fp": 0.1, "overestimation": 0.1,
                       "seconds": 0.2}}
    md = _md([], [row], 8, 1.0, [])
    assert ("| city | 0.3 m | 1,200 | 1,000 | 0 | 0.20 | 20 % | 0.10 | 1,100 | 0 | 10 % | 0.20 |"
            in md)
    assert f"with sub-pixels ({REFINE_MAX} levels) 10-10 % for 2.0-2.0x the time" in md


def test_the_coarse_pass_work_is_told_where_it_ran():
    from benchmarks.bench_cos import _coarse_work

    assert _coarse_work({"coarse_work": {"tested": 0}}) == ""
    told = _coarse_work({"coarse_work": {
        "tested": 3000, "silhouette_edges": 400000, "plane_tests": 300000,
        "cycles_test": 70, "cycles_insert": 25, "cycles_coverall": 1, "cycles_resolve": 100}})
    assert told == (" (testing 3,000 of them: 400,000 silhouette edges walked, 300,000 "
                    "occluder triangles depth-tested; 70 % of its cycles testing, 25 % making "
                    "occluders)")


def test_the_sub_sample_walks_are_told_by_how_they_ended():
    from benchmarks.bench_cos import _walks

    assert _walks({"sub_hidden": 0, "walks_seen": 0}) == ""
    told = _walks({"sub_hidden": 400, "walks_seen": 800, "subpixels_seen": 3000})
    assert told == (", in 1,200 walks: 800 found their entry seen, resolving 3,000 of them "
                    "(3.8 a walk)")


def test_the_cycle_split_names_each_part_of_testing_and_making_occluders():
    from benchmarks.bench_cos import _cycle_split

    assert _cycle_split({"cycles": {}}) == ""
    told = _cycle_split({"cycles": {
        "resolve": 1000, "test": 600, "insert": 300, "coverall": 20, "test_region": 90,
        "test_groups": 270, "test_subpixels": 200, "test_leaf": 30, "insert_setup": 100,
        "insert_slots": 60, "insert_fusion": 130}})
    assert told == ("; of the resolution's CPU cycles 60 % went to testing entries (their "
                    "regions K 9 %, cover and depth tests against single groups 27 %, against "
                    "separate groups and at sub-pixels or busy tiles' sub-samples 20 %, leaf "
                    "boxes 3 %), 30 % to making "
                    "occluders of them (set-up 10 %, edge slots 6 %, fusion along shared edges "
                    "and merges 13 %), 2 % to checking whether a group covers the whole pixel, "
                    "8 % to projecting entries and early z")
