"""The cos benchmark's speed part runs end to end (``--quick``) and writes what it says."""

from __future__ import annotations

import json

from benchmarks.bench_cos import main
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
    md = (tmp_path / "cos_quick.md").read_text()
    assert "| tile items |" in md and "pixels of a tile per pair" in md
    assert "hidden by separate groups" in md
