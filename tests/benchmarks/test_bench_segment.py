"""Smoke test of the from-segment benchmark: every part runs on a small scene and the report says
what the parts measured (the real numbers live in benchmarks/results/from_segment.md)."""

from __future__ import annotations

import json

import numpy as np

from benchmarks import bench_segment as bs


def test_van_der_corput_prefixes_spread_and_reach_dense():
    v = bs.van_der_corput(8)
    assert v.tolist() == [0.0, 0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875]
    # Every prefix of length 2^k hits each of the 2^k equal bins once.
    for k in range(1, 4):
        n = 2 ** k
        assert sorted((v[:n] * n).astype(int).tolist()) == list(range(n))


def test_curve_lookups():
    hits = np.array([3, 5, 5, 9])
    secs = np.array([0.1, 0.2, 0.3, 0.4])
    assert bs._time_to_reach(hits, secs, 5) == (2, 0.2)
    assert bs._time_to_reach(hits, secs, 10) == (-1, float("inf"))
    assert bs._reached_at_time(hits, secs, 0.25) == (2, 5)
    assert bs._reached_at_time(hits, secs, 0.05) == (0, 0)


def test_kitchen_part_says_when_the_scene_is_missing(tmp_path, monkeypatch):
    import benchmarks.bench_matrix as bm

    monkeypatch.setattr(bm, "SHARED_SCENES", tmp_path)
    logs: list[str] = []
    assert bs.part_kitchen({}, logs.append) == []
    assert "kitchen part skipped" in logs[0]


def test_every_part_runs_and_reports(tmp_path):
    cfg = dict(bs.PRESETS["quick"], preset="smoke", load_start="0")
    cfg.update(scenes=["city:5000", "spheres:40"], resolutions=[16, 32], runs=[1, 2],
               gt_points=8, gt_resolution=32, segment_scenes=["city:5000"],
               segment_resolution=32, segment_points=64, cell_scenes=["city:5000"],
               cell_resolution=32, cell_runs=[1, 2], cell_points=16, rect_scenes=["city:5000"],
               orient_scenes=["city:5000"],
               city1m_triangles=5000,
               city1m_cells=1, repeats=1, max_seconds=5, grass_triangles=2000, grass_cells=1,
               part_resolution=32)
    logs: list[str] = []
    results = {"scenes": bs.part_scenes(cfg, logs.append),
               "segment": bs.part_segment(cfg, logs.append),
               "cell": bs.part_cell(cfg, logs.append),
               "rect": bs.part_rect(cfg, logs.append),
               "orient": bs.part_orient(cfg, logs.append),
               "city1m": bs.part_city1m(cfg, logs.append),
               "grass": bs.part_grass(cfg, logs.append)}
    scenes = [r for r in results["scenes"] if "skipped" not in r]
    assert {r["scene"] for r in scenes} >= {"city_5k"}
    for r in scenes:
        assert 0 <= r["fn"] <= 1 and 0 <= r["fp"] <= 1 and r["pvs"] > 0
    sph = [r for r in scenes if "spheres" in r]
    assert sph and all(r["sphere_pvs"] > 0 for r in sph)

    (seg,) = results["segment"]
    # The dense ground truth is the union of the views, so from-point reaches 100 % at the end;
    # from-segment (jitter 0 here) is exact at pixel centres along the segment: it holds nearly all.
    assert seg["curve_completeness"][-1] == 1.0
    assert seg["fs_completeness"] > 0.95
    assert np.all(np.diff(seg["curve_completeness"]) >= 0)

    (cell,) = results["cell"]
    assert cell["known"] >= cell["gt"]
    assert all(0 < r["completeness"] <= 1 for r in cell["fs"])

    (rect,) = results["rect"]
    # The view rectangle is flat at the cell's mid eye height; the cell part keeps the box.
    assert rect["flat"] and rect["box"][0][1] == rect["box"][1][1]
    assert not cell["flat"] and cell["box"][0][1] < cell["box"][1][1]
    assert all(0 < r["completeness"] <= 1 for r in rect["fs"])

    assert {(r["runs"], r["first"]) for r in results["orient"]} == {
        (1, "axis"), (1, "oblique"), (2, "axis"), (2, "oblique")}
    assert all(0 <= r["fn"] <= 1 for r in results["orient"])

    fs = [r for r in results["city1m"] if r["core"] == "from_segment"]
    assert {r["eye_levels"] for r in fs} == {1, 3}
    # Sampling at its defaults on the same cell, for scale.
    (samp,) = [r for r in results["city1m"] if r["core"] == "sampling"]
    assert samp["cell"] == fs[0]["cell"] and samp["pvs"] > 0
    # The default cut depth and the others beside it; a meadow is mostly seen, and later
    # segments skip tiles they can add nothing to; cuts never change the answer by more than
    # float residue at the seams.
    fs = [r for r in results["grass"] if r["core"] == "from_segment"]
    grass = {r["cuts"]: r for r in fs if r["scene"] == "grass"}
    (sway,) = [r for r in fs if r["scene"] == "swaying_grass"]
    assert sum(r["core"] == "sampling" for r in results["grass"]) == 2
    assert sway["pvs_pct"] > 50 and sway["counters"].get("splits", 0) == 0
    assert set(grass) == {bs._core().make_params().cuts, 0, 6}
    assert all(r["pvs_pct"] > 50 and r["counters"]["tiles_known"] > 0 for r in grass.values())
    assert max(r["pvs"] for r in grass.values()) - min(r["pvs"] for r in grass.values()) <= 2

    md = bs.write_report(results, cfg, "smoke", 1.0, tmp_path)
    text = md.read_text()
    for heading in ("One segment", "A cell", "view rectangle", "First orientation", "Per scene",
                    "One 4 x 4 m cell", "Cells of `grass`"):
        assert heading in text
    assert "32² per face" in text and "at 32 px" in text  # the parts' resolution is the cfg's
    for png in ("segment", "cell", "rect", "scenes"):
        assert (tmp_path / f"from_segment_{png}_smoke.png").stat().st_size > 1000
    raw = json.loads((tmp_path / "from_segment_smoke.json").read_text())
    assert raw["parts"]["segment"]["rows"][0]["points"] == 64
    assert raw["parts"]["segment"]["meta"]["command"] == "smoke"

    # A part rerun alone (e.g. the timing part on a quiet machine) replaces only itself.
    bs.write_report({"city1m": results["city1m"]}, cfg, "rerun", 2.0, tmp_path, merge=True)
    raw = json.loads((tmp_path / "from_segment_smoke.json").read_text())
    assert set(raw["parts"]) == {"scenes", "segment", "cell", "rect", "orient", "city1m",
                                 "grass"}
    assert raw["parts"]["city1m"]["meta"]["command"] == "rerun"
    assert raw["parts"]["segment"]["meta"]["command"] == "smoke"
    text = md.read_text()
    assert "Command: `rerun`" in text and "Command: `smoke`" in text
    # Without merge, the report holds just what it was given.
    bs.write_report({"city1m": results["city1m"]}, cfg, "alone", 2.0, tmp_path)
    assert set(json.loads((tmp_path / "from_segment_smoke.json").read_text())["parts"]) == {
        "city1m"}
