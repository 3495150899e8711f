"""Smoke test of the dual-ray benchmark: ``--quick`` runs into a temporary folder and writes a
report whose reading is generated from its numbers (the real figures live in
benchmarks/results/dual_ray.md)."""

from __future__ import annotations

import json

from benchmarks import bench_dual_ray as bd


def test_quick_run_writes_the_report(tmp_path):
    result = bd.main(["--quick", "--out", str(tmp_path)])
    md = (tmp_path / "dual_ray_quick.md").read_text()
    data = json.loads((tmp_path / "dual_ray_quick.json").read_text())
    assert (tmp_path / "dual_ray_quick.png").stat().st_size > 0
    assert "python -m benchmarks.bench_dual_ray --quick" in md and "Load average" in md
    assert "## Reading" in md and "Table 1" in md
    grid = data["grid"]
    assert {r["size"] for r in grid} == set(bd.PRESETS["quick"]["sizes"])
    assert {r["resolution"] for r in grid} == set(bd.PRESETS["quick"]["resolutions"])
    for r in grid:
        assert r["fn_count"] == 0 and r["unsound"] == 0
        assert r["seconds"] > 0 and 0.0 <= r["overestimation_pct"] <= 100.0
    # What the reading says comes from the numbers.
    assert f"{len(grid)} runs" in md
    assert result["targets"] and all(t["seconds"] > 0 for t in result["targets"])
