"""The sub-pixel run benchmark: its rows and page on a small generated scene."""

from __future__ import annotations

import json

from benchmarks import bench_subpixel_runs
from visibility.cores.from_segment import SUBPIXEL_CANDIDATES


def test_rows_say_the_ratio_and_the_runs_it_chose(tmp_path):
    assert bench_subpixel_runs.main(["--scenes", "--generated", "rooms:3000", "--cells", "1",
                                     "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "subpixel_runs.json").read_text())["results"]
    assert rows and all(r["scene"] == "rooms 3k (generated)" for r in rows)
    for r in rows:
        assert r["runs"] == (2 if r["ratio"] > SUBPIXEL_CANDIDATES else 1)
        assert r["pvs"] > 0 and r["seconds"] > 0
    page = (tmp_path / "subpixel_runs.md").read_text()
    assert "--generated rooms:3000" in page and f"| {rows[0]['runs']} |" in page


def test_the_page_compares_the_cells_that_took_the_run():
    rows = [{"scene": "a", "cell": 1, "cell_size": 4.0, "ratio": 15.0, "runs": 2, "pvs": 110,
             "seconds": 2.0, "pvs_one_run": 100, "seconds_one_run": 1.0, "walk_seconds": 0.1},
            {"scene": "b", "cell": 2, "cell_size": 4.0, "ratio": 0.5, "runs": 1, "pvs": 50,
             "seconds": 0.5, "walk_seconds": 0.1}]
    page = bench_subpixel_runs.report(rows, "cmd", 60.0)
    assert "1 of 2 cells took the second run (a: ratio 15.0-15.0, 2.00-2.00x" in page
    assert "the others' ratio 0.50-0.50." in page
