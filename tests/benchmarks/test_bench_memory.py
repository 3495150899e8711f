"""Smoke test of the memory benchmark: a small city through the real catalogue, core and
/proc readings in a child process, and a report that says what it measured (the real numbers
live in benchmarks/results/memory.md)."""

from __future__ import annotations

import json

from benchmarks import bench_memory as bm
from tests.conftest import write_scene_files


def test_a_small_city_and_a_file_are_measured_stage_by_stage(tmp_path):
    write_scene_files(tmp_path / "scenes")
    box = tmp_path / "scenes" / "box.obj"
    assert bm.main(["--sizes", "20000", "--files", str(box), "--cells", "2", "--out",
                    str(tmp_path), "--tag", "smoke"]) == 0
    text = (tmp_path / "smoke.md").read_text()
    assert text.startswith("`python -m benchmarks.bench_memory --sizes 20000")
    data = json.loads((tmp_path / "smoke.json").read_text())
    res, from_file = data["results"]
    # The file is served from its folder with its sidecar's walk area (a 6 x 6 m room, 3 m cells).
    assert from_file["generator"] == "box.obj" and from_file["triangles"] == 12
    assert from_file["cells"] == 4 and from_file["pvs"] > 0
    assert "| box.obj 12 |" in text
    n, nv = res["triangles"], res["vertices"]
    assert abs(n - 20000) < 0.2 * 20000 and res["pvs"] > 0 and res["cells"] > 0
    assert [r["stage"] for r in res["stages"]] == ["runtime", "load", "server", "hierarchy",
                                                   "sampling", "sampling 2"]
    assert len(set(res["cell"])) == 2
    for r in res["stages"]:
        # A stage's peak is at least what it left resident; resident = anon + file + shmem.
        assert r["peak"] >= r["rss"] > 0
        assert r["rss"] == r["anon"] + r["file"] + r["shmem"]
    assert res["peak_reset"] is True
    assert res["process_peak"] == max(r["peak"] for r in res["stages"])
    arrays = res["arrays"]
    assert arrays["scene.vertices"] == 24 * nv and arrays["scene.faces"] == 12 * n
    assert arrays["scene.valid"] == n and arrays["server.centroids"] == 24 * n
    d = res["derived"]
    assert d["kept_arrays_bytes"] == sum(arrays.values())
    assert d["peak_per_triangle"] >= d["served_rss_per_triangle"]
    assert "| scene.vertices |" in text and "| city 20,000 |" in text
