"""The cos excess benchmark runs end to end (``--quick``) and writes what it says it writes."""

from __future__ import annotations

import json

from benchmarks.bench_cos_excess import main


def test_quick_run_writes_the_tables_and_the_data(tmp_path):
    main(["--quick", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "cos_excess.json").read_text())["results"]
    assert [r["scene"] for r in results] == ["lavaducts"]
    res = results[0]
    assert [r["subcells"] for r in res["rows"]] == [1, 2]
    assert res["rows"][0]["pvs"] == res["pvs"]
    a = res["aimed"]
    assert [s["eyes"] for s in a["steps"]] == [4, min(8, a["eyes_in_open_space"])]
    # The aimed rays see some of the PVS, and more eyes never see less.
    assert 0 < a["steps"][0]["seen_in_pvs"] <= a["steps"][-1]["seen_in_pvs"] <= res["pvs"]
    assert 0 < a["confirmed_in_pvs"] <= a["steps"][-1]["seen_in_pvs"]
    # cos promises no false negatives: nothing the aimed rays show is missing, confirmed.
    assert a["missed"] == 0
    md = (tmp_path / "cos_excess.md").read_text()
    assert "| lavaducts |" in md and "## Sub-cells" in md and "## Reading" in md
    # What faces away from the whole cell is part of the PVS, and the rays confirm some of it
    # seen at most.
    assert 0 <= a["facing_away_seen"] <= a["facing_away"] <= res["pvs"]
    assert res["pvs"] - a["facing_away"] <= a["pvs_without_unseen_away"] <= res["pvs"]
    assert 0.0 <= res["open_floor_share"] <= 1.0
    assert "facing away from the cell" in md


def test_facing_away_needs_every_corner_of_the_cell_behind_the_plane():
    import numpy as np

    from benchmarks.bench_cos_excess import facing_away
    from visibility.scene import Scene

    box = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    # Three triangles in planes x = 2 (front side +x: the cell behind), x = 2 wound the other
    # way (front side -x: facing the cell) and x = 0.5 through the cell (front side +x).
    v = np.array([[2, 0, 0], [2, 1, 0], [2, 0, 1],
                  [0.5, 0, 0], [0.5, 1, 0], [0.5, 0, 1]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 1], [3, 4, 5]])
    scene = Scene(vertices=v, faces=f)
    got = facing_away(scene, np.arange(3), box)
    assert got.tolist() == [True, False, False]
    # A scene wound clockwise (a game level's) faces the other way.
    scene.meta["winding"] = "cw"
    assert facing_away(scene, np.arange(3), box).tolist() == [False, True, False]
