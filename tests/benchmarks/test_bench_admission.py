"""The estimate-against-measurement benchmark runs end to end (``--quick``)."""

from __future__ import annotations

import json

from benchmarks.bench_admission import main


def test_quick_run_writes_estimates_and_measurements(tmp_path):
    assert main(["--quick", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "admission.json").read_text())["rows"]
    assert {r["core"] for r in rows} == {"sampling", "from_segment", "cos"}
    assert all(r["estimated_s"] > 0 and r["measured_s"] > 0 for r in rows)
    assert "| village 2k | cos |" in (tmp_path / "admission.md").read_text()
