"""Smoke test of ``pvs bench`` in a tiny mode, plus the ground-truth cache and the ray peer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import bench_matrix, gt_cache, peers
from visibility.cores import designed_scenes as ds
from visibility.cores.base import available_cores, get_core
from visibility.ground_truth import sample_pvs
from visibility.viewcells import Viewcell

TINY = ["--quick", "--scenes", "rooms:1500", "--levels", "1", "--gt-points", "8",
        "--gt-resolution", "32", "--views", "1", "--view-size", "32", "--resolution", "32"]


def test_tiny_matrix_runs_every_core_and_writes_tables_and_plots(tmp_path):
    out = tmp_path / "BENCH.md"
    argv = TINY + ["--out", str(out), "--results-dir", str(tmp_path),
                   "--cache-dir", str(tmp_path / "cache")]
    assert bench_matrix.main(argv) == 0
    text = out.read_text()
    assert "pvs bench --quick" in text and "Machine:" in text
    rows = json.loads((tmp_path / "bench_quick.json").read_text())["rows"]
    cores = {r["core"] for r in rows}
    assert set(available_cores()) <= cores
    if peers.available():
        assert peers.NAME in cores
    for r in rows:
        assert "error" not in r, r
        if "refused" in r:
            # A core made for other scenes (a 2.5D-only core on rooms) is named, not run.
            assert get_core(r["core"]).requires_2_5d, r
            assert r["refused"] and f"`{r['core']}` does not fit" in text
            continue
        assert 0.0 <= r["fn"] <= 1.0 and 0.0 <= r["fp"] <= 1.0
        assert r["seconds_min"] <= r["seconds_median"] <= r["seconds_max"]
        assert 0.0 <= r["eps_mean"] <= r["eps_worst"] <= 100.0
        assert r["peak_mib"] is None or r["peak_mib"] >= 0
        assert f"| {r['core']} |" in text
    png = tmp_path / "quick_rooms_1k.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "quick_rooms_1k.md").is_file()


def test_medium_preset_scenes_all_load_under_distinct_labels():
    """The published run must not die half an hour in on a size a generator refuses."""
    specs = bench_matrix.GENERATOR_SCENES_MEDIUM
    loaded = bench_matrix.load_scenes(specs)
    labels = [label for label, _ in loaded]
    assert len(set(labels)) == len(labels) == len(specs)
    for label, load in loaded:
        scene = load()
        assert scene.n_triangles > 0, label


def test_a_scene_that_fails_to_load_is_skipped_and_reported(tmp_path):
    out = tmp_path / "BENCH.md"
    i = TINY.index("rooms:1500")
    argv = TINY[:i] + ["rooms:999"] + TINY[i:]
    argv += ["--out", str(out), "--results-dir", str(tmp_path),
             "--cache-dir", str(tmp_path / "cache")]
    assert "rooms:999" in argv
    assert bench_matrix.main(argv) == 0
    text = out.read_text()
    assert "NOT measured" in text and "rooms_999" in text and "## rooms_1k" in text


def test_bad_arguments_are_clear_errors(capsys):
    assert bench_matrix.main(["--cells", "0"]) == 2
    assert bench_matrix.main(["--cores", "no_such_core"]) == 2
    assert "no_such_core" in capsys.readouterr().err


def test_knob_and_levels_are_the_cores_declaration():
    core = get_core("sampling")
    assert bench_matrix.knob_levels(core, {}, 3) == list(core.knob_levels)
    # A preset may replace a knob's levels by name for a cheaper run.
    assert bench_matrix.knob_levels(core, {core.knob: [4, 16]}, 3) == [4, 16]

    class NoKnob:
        knob = None

    assert bench_matrix.knob_levels(NoKnob(), {}, 3) == [None]


def test_ground_truth_is_computed_once_then_read_from_disk(tmp_path):
    scene, cell, _ = ds.two_rooms_and_a_door()
    ids, rec = gt_cache.cached_ground_truth(scene, cell, 8, 32, seed=1, cache_dir=tmp_path)
    assert rec["cached"] is False
    again, rec2 = gt_cache.cached_ground_truth(scene, cell, 8, 32, seed=1, cache_dir=tmp_path)
    assert rec2["cached"] is True
    np.testing.assert_array_equal(ids, again)
    np.testing.assert_array_equal(ids, sample_pvs(scene, cell, 8, 32, seed=1).triangle_ids)
    # Other parameters, another cell or changed geometry: another entry.
    _, rec3 = gt_cache.cached_ground_truth(scene, cell, 8, 64, seed=1, cache_dir=tmp_path)
    assert rec3["cached"] is False
    moved, mcell, _ = ds.two_rooms_and_a_door(offset=(0.0, 0.0, 1e-3))
    assert gt_cache.scene_fingerprint(moved) != gt_cache.scene_fingerprint(scene)
    assert gt_cache.cache_key(moved, cell, 8, 32, 1) != gt_cache.cache_key(scene, cell, 8, 32, 1)
    assert gt_cache.cache_key(scene, mcell, 8, 32, 1) != gt_cache.cache_key(scene, cell, 8, 32, 1)


@pytest.mark.skipif(not peers.available(), reason="embreex is not installed")
def test_ray_peer_agrees_with_the_rasterizer_and_respects_occlusion():
    scene, cell, known = ds.two_rooms_and_a_door(offset=(1e5, 0.0, -1e5))
    res = peers.embree_pvs(scene, cell, samples=16, resolution=64, seed=3)
    found = set(res.triangle_ids.tolist())
    assert known["visible"][0] in found
    assert not set(known["hidden"]) & found
    assert np.all(np.diff(res.triangle_ids) > 0)
    # Same points, same cube orientations, same pixel centres as the sampling core.
    ras = get_core("sampling").compute(scene, cell, get_core("sampling").make_params(
        samples=16, resolution=64, seed=3))
    a, b = found, set(ras.triangle_ids.tolist())
    assert len(a ^ b) <= 0.1 * len(a | b)
    budget = peers.embree_pvs(scene, cell, samples=10_000, resolution=16, time_budget=0.0)
    assert budget.stats["samples"] == 1


def test_raster_peer_is_the_sampling_core_and_stops_at_a_target():
    """The ``raster`` engine draws the same points and cubes as the ``sampling`` core, so with
    the same seed it finds exactly the same triangles; with a target it stops as soon as it has
    found that share of the reference, and says whether it got there."""
    scene, cell, _ = ds.two_rooms_and_a_door()
    core = get_core("sampling")
    ras = peers.from_point_pvs(scene, cell, "raster", samples=12, resolution=48, seed=5)
    ref = core.compute(scene, cell, core.make_params(samples=12, resolution=48, seed=5))
    np.testing.assert_array_equal(ras.triangle_ids, ref.triangle_ids)
    target = ref.triangle_ids
    half = peers.from_point_pvs(scene, cell, "raster", samples=1000, resolution=48, seed=5,
                                target_ids=target, target_share=0.5)
    assert half.stats["reached"] and half.stats["samples"] < 12
    assert np.isin(target, half.triangle_ids).mean() >= 0.5
    impossible = peers.from_point_pvs(scene, cell, "raster", samples=3, resolution=8, seed=5,
                                      target_ids=target, target_share=1.0)
    assert not impossible.stats["reached"] and impossible.stats["samples"] == 3
    with pytest.raises(ValueError):
        peers.from_point_pvs(scene, cell, "optix")


def test_tiny_matrix_has_equal_time_and_equal_completeness_rows(tmp_path):
    argv = TINY + ["--out", str(tmp_path / "B.md"), "--results-dir", str(tmp_path),
                   "--cache-dir", str(tmp_path / "cache"), "--cores", "from_segment", "sampling",
                   "--no-peer"]
    assert bench_matrix.main(argv) == 0
    rows = json.loads((tmp_path / "bench_quick.json").read_text())["rows"]
    ref = [r for r in rows if r["core"] == "from_segment"][-1]
    et = [r for r in rows if r["knob"] == "budget"]
    ec = [r for r in rows if r["knob"] == "completeness"]
    assert [r["core"] for r in et] == ["sampling"] and [r["core"] for r in ec] == ["sampling"]
    # Equal time: stops at the first viewpoint past the budget.
    assert et[0]["peer_samples"] >= 1
    assert ec[0]["target_pct"] == pytest.approx(100 * (1 - ref["fn"]))
    if ec[0]["reached"]:
        assert 1 - ec[0]["fn"] >= 1 - ref["fn"] - 1e-9
    text = (tmp_path / "B.md").read_text()
    assert "equal time to from_segment" in text and "equal completeness to from_segment" in text


def test_medium_preset_is_the_published_run():
    """``pvs bench --preset medium`` alone covers every generator but ``stress`` at two sizes and
    every real scene, with a ground truth at least as fine as the finest core level."""
    from visibility.generators import GENERATORS

    cfg = bench_matrix.config_from_args(bench_matrix.build_parser().parse_args(
        ["--preset", "medium"]))
    names = [s.partition(":")[0] for s in cfg["scenes"] if s != "real"]
    for gen in set(GENERATORS) - {"stress"}:
        assert names.count(gen) == 2, gen
    assert "stress" not in names and "real" in cfg["scenes"]
    assert cfg["repeats"] == 3
    assert cfg["gt_resolution"] >= 2 * bench_matrix.top_core_resolution(cfg)
    assert cfg["gt_points"] >= 4 * max(cfg["knob_levels"]["samples"])
    real = [label for label, _ in bench_matrix.load_scenes(["real"])]
    assert real == sorted(p.stem for p in bench_matrix.SHARED_SCENES.glob("*.glb"))
    with pytest.raises(ValueError, match="gt-resolution"):
        bench_matrix.config_from_args(bench_matrix.build_parser().parse_args(
            ["--preset", "medium", "--gt-resolution", "32"]))


def test_views_look_where_the_geometry_is():
    # A wall on the -Z side only, and the cell's eyes in front of it: every view faces it.
    b = ds.Builder()
    b.quad((-10, 0, -6), (-10, 5, -6), (10, 5, -6), (10, 0, -6), 0)
    scene = b.scene("one_wall")
    cell = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]))
    views = bench_matrix.view_set(scene, cell, 3)
    assert len(views) == 3
    for eye, fwd in views:
        assert np.all(eye >= cell.box[0]) and np.all(eye <= cell.box[1])
        # Within 45 degrees of -Z (the scoring cube has a random yaw), pitched slightly down.
        assert fwd[2] < -0.69 * np.linalg.norm(fwd)
    again = bench_matrix.view_set(scene, cell, 3)  # deterministic: the same views every run
    for (e0, f0), (e1, f1) in zip(views, again, strict=True):
        np.testing.assert_array_equal(e0, e1)
        np.testing.assert_array_equal(f0, f1)


def test_memory_peak_sees_reused_numpy_memory():
    def work():
        a = np.ones(8 * 2**20 // 8)  # 8 MiB, freed, then the same size again
        del a
        return np.ones(8 * 2**20 // 8).sum()

    out, rss, traced = bench_matrix.measure_peak(work)
    assert out == 2**20
    assert traced is not None and traced >= 8.0
    assert rss is None or rss >= 0.0
    _, _, off = bench_matrix.measure_peak(work, traced=False)
    assert off is None


def test_gpu_is_detected_through_nvidia_smi(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    assert bench_matrix.gpu_description() == "no GPU"
    smi = tmp_path / "nvidia-smi"
    smi.write_text("#!/bin/sh\necho 'NVIDIA H100 80GB HBM3, 81559 MiB'\n")
    smi.chmod(0o755)
    assert bench_matrix.gpu_description() == "GPU: NVIDIA H100 80GB HBM3, 81559 MiB"
    assert "GPU: NVIDIA H100" in bench_matrix.machine_description()


def test_spheres_are_counted_and_sphere_blind_cores_read_n_a(tmp_path):
    argv = TINY[:2] + ["spheres:12"] + TINY[3:] + [
        "--out", str(tmp_path / "B.md"), "--results-dir", str(tmp_path),
        "--cache-dir", str(tmp_path / "cache"), "--cores", "from_segment", "sampling",
        "--no-peer", "--reference", "none"]
    assert bench_matrix.main(argv) == 0
    rows = json.loads((tmp_path / "bench_quick.json").read_text())["rows"]
    by_core = {r["core"]: r for r in rows}
    assert all(r["spheres"] == 12 and r["gt_spheres"] >= 1 for r in rows)
    seg = by_core["from_segment"]
    assert seg["sphere_fn"] is not None and 0.0 <= seg["sphere_fn"] <= 1.0
    if by_core["sampling"]["pvs_spheres"] is None:
        assert by_core["sampling"]["sphere_fn"] is None
    text = (tmp_path / "B.md").read_text()
    assert "| sphere FN % | sphere FP % |" in text
    assert "of 12 spheres" in text and "last batch of 8 points added" in text


def test_merge_adds_a_core_to_an_earlier_run_and_replaces_its_own_rows():
    def row(cell, core, level, fn):
        return {"scene": "s", "cell_size": 4.0, "cell": cell, "core": core,
                "knob": "resolution", "level": level, "fn": fn}

    old = [row(1, "a", 32, 0.1), row(1, "b", 32, 0.2), row(2, "a", 32, 0.3)]
    new = [row(1, "c", 32, 0.0), row(2, "c", 32, 0.0), row(1, "b", 32, 0.9),
           row(3, "c", 32, 0.0)]
    out = bench_matrix.merge_rows(old, new)
    assert [(r["cell"], r["core"], r["fn"]) for r in out] == [
        (1, "a", 0.1), (1, "b", 0.9), (1, "c", 0.0), (2, "a", 0.3), (2, "c", 0.0),
        (3, "c", 0.0)]


def test_merge_drops_a_cores_rows_on_cells_the_grid_no_longer_picks():
    def row(cell, core):
        return {"scene": "s", "cell_size": 4.0, "cell": cell, "core": core,
                "knob": "resolution", "level": 32, "fn": 0.0}

    old = [row(7, "a"), row(7, "b"), row(9, "a")]
    out = bench_matrix.merge_rows(old, [row(8, "a")])
    # Core a now measures cell 8 at this size: its rows on 7 and 9 go; b's row on 7 stays.
    assert [(r["cell"], r["core"]) for r in out] == [(7, "b"), (8, "a")]


def test_merged_report_names_every_run_and_a_point_deadline_is_a_row(tmp_path):
    argv = TINY + ["--out", str(tmp_path / "B.md"), "--results-dir", str(tmp_path),
                   "--cache-dir", str(tmp_path / "cache"), "--no-peer", "--reference", "none"]
    assert bench_matrix.main(argv + ["--cores", "sampling"]) == 0
    # cos on a deadline it cannot meet: the row says so, and sampling's rows stay.
    assert bench_matrix.main(argv + ["--cores", "cos", "--merge",
                                     "--point-deadline", "0.000001"]) == 0
    data = json.loads((tmp_path / "bench_quick.json").read_text())
    cores = [r["core"] for r in data["rows"]]
    assert "sampling" in cores and "cos" in cores
    assert all("deadline" in r["error"] for r in data["rows"] if r["core"] == "cos")
    text = (tmp_path / "B.md").read_text()
    assert "--cores sampling" in text and "--cores cos --merge" in text
    # Only the last run's machine is known: the report says so.
    assert "Machine of the last run: " in text and "may differ" in text
    (tmp_path / "B.md").unlink()
    assert bench_matrix.main(argv + ["--report-only"]) == 0  # rewritten from the JSON alone
    assert (tmp_path / "B.md").read_text() == text
    empty = tmp_path / "none"
    assert bench_matrix.main(TINY + ["--report-only", "--results-dir", str(empty)]) == 2


def test_a_core_that_does_not_fit_a_scene_is_named_once_not_run(tmp_path):
    from visibility.cores import base as core_base
    from visibility.cores.sampling import SamplingCore

    class _Picky(SamplingCore):
        name = "test_picky"

        def supports(self, scene):
            return False, "made for no scene at all"

    core_base.register(_Picky)
    try:
        argv = TINY + ["--out", str(tmp_path / "B.md"), "--results-dir", str(tmp_path),
                       "--cache-dir", str(tmp_path / "cache"), "--no-peer", "--reference",
                       "none", "--cores", "sampling", "test_picky"]
        assert bench_matrix.main(argv) == 0
    finally:
        core_base.unregister(_Picky.name)
    rows = json.loads((tmp_path / "bench_quick.json").read_text())["rows"]
    picky = [r for r in rows if r["core"] == "test_picky"]
    assert len(picky) == 1 and "made for no scene" in picky[0]["refused"]
    text = (tmp_path / "B.md").read_text()
    assert "Not run here: `test_picky` does not fit this scene (made for no scene at all)" in text
    assert "| sampling |" in text and "| test_picky |" not in text
