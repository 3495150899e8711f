"""The cos tightness benchmark runs end to end (``--quick``) and writes what it says it writes."""

from __future__ import annotations

import json

from benchmarks.bench_cos_tightness import main


def test_quick_run_writes_the_table_the_data_and_the_plot(tmp_path):
    main(["--quick", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "cos_tightness.json").read_text())["results"]
    assert [r["scene"] for r in results] == ["lavaducts"]
    rows = results[0]["rows"]
    assert [r["resolution"] for r in rows] == [16, 32]
    ref = results[0]["reference"]["triangles"]
    assert ref > 0
    for r in rows:
        # cos promises no false negatives: the reference's triangles are all in its PVS.
        assert r["missed"] == 0
        assert r["pvs"] >= ref and abs(r["ratio"] - r["pvs"] / ref) < 1e-12
    md = (tmp_path / "cos_tightness.md").read_text()
    assert "| lavaducts |" in md and "## Reading" in md
    assert (tmp_path / "cos_tightness.png").stat().st_size > 0
