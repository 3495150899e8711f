"""The trim regions benchmark's leaf-size table scores each leaf size on one set of frames."""

from __future__ import annotations

from benchmarks import bench_trim_regions as bench


def test_leaf_sizes_score_every_size_on_the_same_frames(monkeypatch):
    monkeypatch.setattr(bench, "LEAF_SIZES", (256, 4096))
    rows = bench.leaf_sizes(quick=True, frames=2)
    assert [r["max_prims"] for r in rows] == [256, 4096]
    # The ground truth is the frames' triangles: one cast serves every leaf size.
    assert rows[0]["gt"] == rows[1]["gt"] > 0
    # Larger leaves peel fewer layers.
    assert rows[1]["layers"] < rows[0]["layers"]
    for r in rows:
        assert r["pvs"] > 0 and r["seconds"] > 0
        assert 0 <= r["fn_pixels_max"] <= 6 * 256 * 256
