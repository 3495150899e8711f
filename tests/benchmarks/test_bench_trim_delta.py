"""The Δ benchmark of trim_regions: one sphere per random cube, a row per scene, bad input
refused."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_trim_delta as bench


@pytest.mark.slow
def test_a_smoke_run_writes_the_table_and_the_rows(tmp_path):
    from tests.visibility.real_scenes import REAL

    assert "lavaducts" in REAL, "the real scene lavaducts of ../shared/scenes is missing"
    assert bench.main(["--delta", "0.3", "--scenes", "lavaducts", "--cubes", "2",
                       "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "trim_delta_0.3.json").read_text())
    rows = data["rows"]
    assert data["delta"] == 0.3 and [r["cube"] for r in rows] == [0, 1]
    for r in rows:
        # max_delta is the cube's circumscribed radius: one sphere answers for it.
        assert r["spheres"] == 1 and r["frames"] > 0 and r["pvs"] >= r["gt"] > 0
        assert 0 <= r["fn_pixels_max"] <= 6 * 256 * 256
    text = (tmp_path / "trim_delta_0.3.md").read_text()
    assert "| lavaducts | 2 |" in text and "Δ 0.3 m" in text


@pytest.mark.parametrize("argv", [["--delta", "0"], ["--delta", "0.3", "--scenes", "nowhere"]])
def test_bad_arguments_are_refused(argv, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        bench.main([*argv, "--out", str(tmp_path)])
    assert e.value.code == 2
    assert "error" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
