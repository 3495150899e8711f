"""The cos tightness benchmark runs end to end (``--quick``) and writes what it says it writes."""

from __future__ import annotations

import json

from benchmarks.bench_cos_tightness import main
from visibility.cores.cos.core import REFINE_MAX


def test_quick_run_writes_the_table_the_data_and_the_plot(tmp_path):
    # A 1 m cell: the machinery is what runs here (the quick preset takes 4 m, as the
    # benchmark does).
    main(["--quick", "--size", "1", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "cos_tightness.json").read_text())["results"]
    assert [r["scene"] for r in results] == ["lavaducts"]
    rows = results[0]["rows"]
    cos = [r for r in rows if r["core"] == "cos"]
    assert [(r["resolution"], r["cover"], r["subcells"], r["fusion"], r["refine"])
            for r in cos] == [
        (16, "strict", 1, "edges", 0), (32, "strict", 1, "edges", 0),
        (32, "strict", 1, "groups", 0), (32, "strict", 2, "edges", 0),
        (32, "relaxed", 1, "edges", 0), (32, "relaxed", 2, "edges", 0),
        (32, "relaxed", 1, "groups", 0),
        (32, "strict", 1, "edges", 2), (32, "strict", 1, "edges", 4),
        (32, "strict", 1, "edges", REFINE_MAX), (32, "relaxed", 1, "groups", REFINE_MAX)]
    # Separate groups hiding together can only hide more than the paper's fusion.
    assert cos[2]["pvs"] <= cos[1]["pvs"] and cos[1]["fused"] == 0
    # Sub-pixels hide entries only where they are asked for, and some on this cell.
    assert cos[1]["refined"] == cos[1]["subpixels"] == 0
    assert cos[7]["refined"] > 0 and cos[7]["subpixels"] > cos[7]["refined"]
    # A seen entry's walk resolves a sub-pixel at each of its 2 levels, a hidden one at least
    # the 4 of the first: together no more than were resolved.
    assert cos[7]["subpixels_seen"] >= 2 * cos[7]["walks_seen"] > 0
    assert cos[7]["subpixels"] - cos[7]["subpixels_seen"] >= 4 * cos[7]["refined"]
    # A deeper walk splits only what a shallower one left unhidden: never a larger answer.
    assert cos[9]["pvs"] <= cos[8]["pvs"] <= cos[7]["pvs"] <= cos[1]["pvs"]
    assert [r["core"] for r in rows].count("sampling") == 2
    ref = results[0]["reference"]
    assert ref["triangles"] > 0 and ref["eyes"] == 8 and len(ref["steps"]) == 2
    aim = results[0]["aimed"]
    assert [a["rays_per_candidate"] for a in aim["rounds"]] == [16, 32][:len(aim["rounds"])]
    assert aim["triangles"] == aim["rounds"][-1]["total"] >= ref["triangles"]
    for r in rows:
        assert abs(r["ratio"] - r["pvs"] / ref["triangles"]) < 1e-12
        assert abs(r["aimed_ratio"] - r["pvs"] / aim["triangles"]) < 1e-12
    for r in cos:
        # cos promises no false negatives: nothing the rays show is missing, confirmed.
        assert r["missed"] == 0 and r["aimed_missed"] == 0
    md = (tmp_path / "cos_tightness.md").read_text()
    assert "| lavaducts |" in md and "## Reading" in md and "sub-cells" in md
    assert "relaxed cover" in md and "separate groups" in md and "sub-pixels" in md
    assert "walks that found their entry seen" in md
    assert "Rays aimed at the answers' other triangles" in md
    assert (tmp_path / "cos_tightness.png").stat().st_size > 0
