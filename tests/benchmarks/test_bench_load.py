"""Smoke tests of the load benchmark: a few real protocol clients against a real ``pvs serve``
for a few seconds, on a small generated scene and on a small real file (lavaducts, in Quake
units scaled by its sidecar); the report's fields must agree with each other (the real numbers
live in benchmarks/results/load*.md). Also its parts: the ground check of walks on the real
city scenes, the percentiles, the tables, the hostile client."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import bench_load, common
from benchmarks.load import report, summary
from benchmarks.load.ground import ground_check
from benchmarks.load.scenes import load_bench_scene, plan_walks
from benchmarks.load.walkers import STALLED, ClientStats
from client.metrics import PSNR_CAP_DB
from protocol.messages import ANSWERS
from pvs_cli import DEFAULT_SCENES_DIR
from visibility.viewcells import MAX_STEP

CHEAP = '{"resolution": 64, "samples": 8}'


def json_runs(out: str) -> list[dict]:
    return [json.loads(line[6:]) for line in out.splitlines() if line.startswith("json: ")]


def check_consistent(r: dict) -> None:
    """The fields of one run's summary agree with each other."""
    fba = r["frames_by_answer"]
    assert r["frames"] > 0 and sum(fba.values()) == r["frames"]
    assert set(ANSWERS) | {STALLED} <= set(fba)
    assert fba[STALLED] == r["stalls"]
    core = sum(fba[a] for a in summary.CORE_ANSWERS)
    assert r["core_answer_share"] == pytest.approx(core / r["frames"], abs=1e-12)
    assert sum(r["answer_share"].values()) == pytest.approx(1.0, abs=1e-12)
    assert len(r["stalls_per_client"]) == r["clients"]
    assert sum(r["stalls_per_client"]) == r["stalls"]
    lat = [r[f"latency_p{q}_s"] for q in (50, 95, 99)]
    if None not in lat:
        assert lat == sorted(lat) and lat[-1] <= r["latency_max_s"]
    assert 0 < r["triangles_per_walker_mean"] <= r["triangles_per_walker_max"] <= r["triangles"]
    # Every triangle came with a stream of some answer.
    assert set(r["triangles_per_walker_by_answer"]) <= set(ANSWERS)
    assert sum(r["triangles_per_walker_by_answer"].values()) == pytest.approx(
        r["triangles_per_walker_mean"], rel=1e-9)
    assert r["computations_per_second"] == pytest.approx(
        r["computations"] / r["wall_seconds"], rel=1e-12)
    assert r["server_rss_peak_bytes"] > 0 and r["server_cpu_seconds"] > 0
    assert r["bytes_received"] > 0 and r["bytes_sent"] > 0
    # Each triangle once per session, nothing went wrong on the protocol, every pose walked
    # on the ground.
    assert r["duplicates"] == 0 and r["client_errors"] == 0
    assert r["walks"]["poses_off_ground"] == 0
    assert r["eps_by_answer"], "no frame was drawn"
    for answer, e in r["eps_by_answer"].items():
        assert fba[answer] >= e["frames"] > 0
        assert 0 < e["walkers"] <= r["clients"] and len(e["eps_per_walker"]) == e["walkers"]
        assert 0.0 <= e["eps_mean"] <= e["eps_worst"] <= 100.0
        assert e["eps_worst"] == pytest.approx(max(e["eps_per_walker"]), abs=1e-5)
        assert 0.0 <= e["ssim_mean"] <= 1.0 and e["psnr_mean"] <= PSNR_CAP_DB


def test_generated_scene_one_run_per_worker_count(tmp_path, capsys, monkeypatch):
    # `pvs warmup` itself is tested in tests/visibility/test_warmup.py; here, that the runs
    # come after it and the report says so.
    calls = []
    monkeypatch.setattr(bench_load, "compile_kernels", lambda: calls.append(1) or 1.6)
    rc = bench_load.main(["--clients", "3", "--workers", "1,2", "--duration", "3",
                          "--triangles", "5000", "--params", CHEAP, "--cache", "cold",
                          "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    assert out.startswith("command: python -m benchmarks.bench_load")
    for row in ("stalls", "frame latency p99", "frames by answer", "triangles per walker",
                "computations per second", "server RSS peak", "server CPU"):
        assert row in out
    runs = json_runs(out)
    assert [(r["workers"], r["clients"], r["cache"]) for r in runs] == [
        (1, 3, "cold"), (2, 3, "cold")]
    saved = json.loads((tmp_path / "load.json").read_text())["runs"]
    for r, s in zip(runs, saved, strict=True):
        assert r["scene_kind"] == "generated" and r["scene_source"]["triangles"] == 5000
        check_consistent(s)
        assert len(s["triangles_per_walker"]) == 3
        assert s["triangles_per_walker_max"] == max(s["triangles_per_walker"])
    md = (tmp_path / "load.md").read_text()
    assert "command: `python -m benchmarks.bench_load" in md and "machine:" in md
    assert "kernels compiled before the runs (`pvs warmup`): 2 s" in md and calls == [1]
    for section in ("## Capacity", "## Frames by answer", "## Image error by answer"):
        assert section in md
    assert "- 1 worker, cold cache:" in md and "- 2 workers, cold cache:" in md
    assert "| 1 | cold | 3 |" in md and "| 2 | cold | 3 |" in md
    assert (tmp_path / "load.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Re-rendering from the JSON measures nothing and keeps every number.
    (tmp_path / "load.md").unlink()
    assert bench_load.main(["--rerender", str(tmp_path / "load.json")]) == 0
    assert (tmp_path / "load.md").read_text() == md


def test_file_scene_served_from_the_scenes_folder(tmp_path, capsys):
    """lavaducts, a real file in Quake units: loaded as the server loads it (its sidecar's
    scale, its hint's 2 m cells), the server's grid checked against the benchmark's, walks on
    the ground."""
    assert (DEFAULT_SCENES_DIR / "lavaducts.glb").is_file(), "../shared/scenes is missing"
    rc = bench_load.main(["--scene", "lavaducts", "--scenes", str(DEFAULT_SCENES_DIR),
                          "--clients", "2", "--workers", "2", "--duration", "3",
                          "--params", CHEAP, "--cache", "cold", "--no-warmup",
                          "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    (r,) = json.loads((tmp_path / "load.json").read_text())["runs"]
    assert (r["scene"], r["scene_kind"], r["scene_source"]) == (
        "lavaducts", "file", {"file": "lavaducts.glb"})
    assert r["cell_size"] == 2.0 and r["triangles"] == 13350
    check_consistent(r)
    assert "file `lavaducts.glb`" in (tmp_path / "load.md").read_text()
    assert "lavaducts / file / 13350" in out


def test_triangles_do_not_size_a_file_scene():
    with pytest.raises(SystemExit, match="generated scene"):
        load_bench_scene("lavaducts", 5000, str(DEFAULT_SCENES_DIR), None)
    with pytest.raises(SystemExit, match="no scene 'nowhere'"):
        load_bench_scene("nowhere", None, str(DEFAULT_SCENES_DIR), None)


def test_warm_cache_serves_the_walks_without_computing(tmp_path, capsys):
    """The warm rows run after the PVS of every cell the walks pass through and of their
    neighbours was computed over HTTP with the walkers' core and parameters, so the walkers'
    sessions find them all in the cache: the HTTP and WebSocket paths share cache keys (a
    mismatch would show as computations here)."""
    rc = bench_load.main(["--clients", "1,2", "--workers", "2", "--duration", "2",
                          "--triangles", "5000", "--params", CHEAP, "--cache", "warm",
                          "--no-warmup", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    runs = json_runs(out)
    assert [(r["clients"], r["cache"]) for r in runs] == [(1, "warm"), (2, "warm")]
    for r in runs:
        assert r["computations"] == 0 and r["cache_hits"] >= 1
        assert r["client_errors"] == 0 and r["duplicates"] == 0
        assert 0 < r["warm_cells"] <= r["cells"]
    assert "| 2 | warm | 2 |" in (tmp_path / "load.md").read_text()


@pytest.mark.parametrize("name", ["denhaag", "lyon_vilo3d"])
def test_walks_on_the_city_scenes_stay_on_the_ground_in_the_open(name):
    """Streets are where buildings are not: every pose of the planned walks has no roof above
    it, lies in a cell, and has its eye at walking height over the ground; an eye put inside a
    building (under a roof crossed by its vertical line) is caught."""
    assert (DEFAULT_SCENES_DIR / f"{name}.glb").is_file(), "../shared/scenes is missing"
    bs = load_bench_scene(name, None, str(DEFAULT_SCENES_DIR), None)
    plan = plan_walks(bs, 20, duration=20.0, speed=1.4, fps=10.0, seed=0)
    grid, scene = bs.loaded.grid, bs.loaded.scene
    lo, hi = grid.walk.eye_range
    for w in plan.walks:
        g = ground_check(scene, grid, w.positions)
        assert g["ok"].all() and g["inside"] == g["outside_cells"] == 0
        assert lo - MAX_STEP <= g["eye_height_min_m"] <= g["eye_height_max_m"] <= hi + MAX_STEP
    assert plan.summary(20)["poses_off_ground"] == 0
    # A roof: the up-facing triangle whose centroid is highest above the lowest geometry.
    tris = scene.triangles()[scene.valid_faces]
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    up = n[:, 1] / np.linalg.norm(n, axis=1) > 0.9
    c = tris[up].mean(axis=1)
    roof = c[np.argmax(c[:, 1])]
    inside = roof - [0.0, 2.0, 0.0]
    g = ground_check(scene, grid, inside[None, :])
    assert g["inside"] == 1 and not g["ok"][0]


def test_latency_percentiles_count_frames_never_delivered():
    s = bench_load.latency_summary([0.0, 0.0, 0.0, 0.5], never=0)
    assert (s["latency_p50_s"], s["latency_p95_s"], s["latency_p99_s"], s["latency_max_s"]) == (
        0.0, 0.5, 0.5, 0.5)
    # 4 delivered, 6 never: the median frame was never delivered.
    s = bench_load.latency_summary([0.0, 0.0, 0.0, 0.5], never=6)
    assert s["latency_p50_s"] is None and s["latency_p99_s"] is None
    assert s["latency_max_s"] == 0.5
    s = bench_load.latency_summary([0.1] * 19, never=1)
    assert s["latency_p50_s"] == 0.1 and s["latency_p95_s"] == 0.1  # rank 19 of 20
    assert s["latency_p99_s"] is None  # rank 20 of 20: the never-delivered frame
    s = bench_load.latency_summary(list(np.arange(100) / 100), never=0)
    assert (s["latency_p50_s"], s["latency_p95_s"], s["latency_p99_s"]) == (0.49, 0.94, 0.98)
    assert bench_load.latency_summary([], never=0)["latency_p50_s"] is None


def test_a_new_answer_gets_its_own_column(monkeypatch):
    """Answers are iterated from the protocol's list: one it gains shows in the counts and
    the tables without touching the benchmark."""
    monkeypatch.setattr(summary, "ANSWERS", (*ANSWERS, "neighbours"))
    st = ClientStats(frames=4, stalls=1, answers={"full": 1, "neighbours": 2, STALLED: 1})
    fba = summary.frames_by_answer([st])
    assert list(fba) == [*ANSWERS, "neighbours", STALLED]
    assert fba["neighbours"] == 2 and sum(fba.values()) == 4
    run = {"workers": 1, "cache": "cold", "clients": 1, "frames": 4, "frames_by_answer": fba,
           "core_answer_share": 0.25, "triangles_per_walker_mean": 10.0,
           "triangles_per_walker_max": 10}
    head = report.answers_table([run])[0]
    assert "| neighbours % |" in head and "| stalled % |" in head


def test_capacity_is_the_most_walkers_without_a_stall():
    def run(workers: int, clients: int, stalls: int, cps: float, spc: float) -> dict:
        return {"workers": workers, "cache": "cold", "clients": clients, "frames": 100,
                "stalls": stalls, "frames_never_delivered": 0, "client_errors": 0,
                "computations_per_second": cps, "seconds_per_computation": spc}

    runs = [run(2, 5, 0, 3.0, 0.5), run(2, 20, 0, 8.0, 0.5), run(2, 50, 7, 9.0, 0.5),
            run(1, 5, 2, 2.0, 0.25)]
    two, one = summary.capacity(runs, cores=2)
    assert (two["workers"], two["most_walkers_without_stall"], two["fewest_walkers_stalled"]) \
        == (2, 20, 50)
    assert two["walkers_per_worker"] == 10 and two["walkers_per_cpu_core"] == 10
    assert two["computations_per_second_at_most"] == 8.0
    assert two["computations_per_second_peak"] == 9.0
    assert two["computations_per_worker_second"] == 2.0
    assert one["most_walkers_without_stall"] is None and one["fewest_walkers_stalled"] == 5
    lines = report.capacity_lines(runs, cores=2)
    assert lines[0].startswith("- 2 workers, cold cache: 20 walkers without a stall")
    assert lines[1].startswith("- 1 worker, cold cache: no run without a stall")


def test_common_helpers():
    assert common.md_table(["a", "b"], [[1, "x|y"]]) == [
        "| a | b |", "|---|---|", "| 1 | x\\|y |"]
    with pytest.raises(ValueError, match="row of 1"):
        common.md_table(["a", "b"], [[1]])
    line = common.command_line("benchmarks.bench_load", ["--params", '{"a": 1}'])
    assert line == "python -m benchmarks.bench_load --params '{\"a\": 1}'"
    assert common.prometheus_value('x{k="v"} 3\nx 4.5\n', "x") == 4.5
    assert np.isnan(common.prometheus_value("y 1\n", "x"))
    import os

    assert common.rss_bytes(os.getpid()) > 0 and common.cpu_seconds(os.getpid()) > 0
    assert common.rss_bytes(-1) == 0 and np.isnan(common.cpu_seconds(-1))
    assert 0 < common.free_port() < 65536
    assert "logical cores" in common.machine()


def test_the_hostile_client_counts_answers_and_comes_from_its_own_address():
    """Against a stub that refuses every request with 429, the hostile flood comes from
    127.0.0.2, counts every answer by status and says what was in flight when it stopped."""
    import asyncio

    peers: list[str] = []

    async def main() -> dict:
        async def answer(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            peers.append(writer.get_extra_info("peername")[0])
            try:
                while True:
                    head = await reader.readuntil(b"\r\n\r\n")
                    size = next((int(line.split(b":")[1]) for line in head.split(b"\r\n")
                                 if line.lower().startswith(b"content-length:")), 0)
                    await reader.readexactly(size)
                    writer.write(b"HTTP/1.1 429 Too Many Requests\r\ncontent-length: 0\r\n\r\n")
                    await writer.drain()
            except (asyncio.IncompleteReadError, ConnectionError):
                writer.close()

        server = await asyncio.start_server(answer, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        cells = np.array([[[0.0, 1.5, 0.0], [4.0, 1.9, 4.0]]])
        t_end = asyncio.get_running_loop().time() + 1.0
        async with server:
            return await bench_load.hostile_flood(
                f"http://127.0.0.1:{port}", "village", "sampling", {"samples": 100_000}, cells,
                concurrency=3, timeout=5.0, pause=0.05, seed=0,
                stop=lambda: asyncio.get_event_loop().time() > t_end, started=lambda: None)

    counts = asyncio.run(main())
    assert peers and set(peers) == {bench_load.HOSTILE_ADDRESS}
    assert counts["429"] >= 3 and counts["200"] == counts["503"] == counts["other"] == 0
    answered = sum(counts[k] for k in ("200", "422", "429", "503", "other", "refused",
                                       "timeout"))
    assert counts["sent"] == answered + counts["unfinished"]
    assert "429: " in bench_load.hostile_answers_text(counts)


def test_hostile_boxes_differ_and_stay_near_the_cells():
    import random

    cells = np.array([[[0.0, 1.5, 0.0], [4.0, 1.9, 4.0]], [[4.0, 1.5, 0.0], [8.0, 1.9, 4.0]]])
    rng = random.Random(0)
    boxes = [bench_load.hostile_box(cells, rng) for _ in range(50)]
    assert len({json.dumps(b) for b in boxes}) == 50
    for lo, hi in boxes:
        assert all(a <= b for a, b in zip(lo, hi, strict=True))
        assert -2.0 <= lo[0] and hi[0] <= 10.0 and 1.5 <= lo[1] and hi[1] <= 1.9


def test_abuse_mode_runs_each_row_without_and_with_the_hostile_client(tmp_path, capsys):
    """``--hostile`` in its quick form: a cold pair on a real server (cheap hostile parameters
    keep it short; the default ones are the expensive ``HOSTILE_PARAMS``)."""
    rc = bench_load.main(["--hostile", "--quick", "--clients", "2", "--workers", "2",
                          "--duration", "3", "--triangles", "5000", "--params", CHEAP,
                          "--hostile-params", '{"resolution": 128, "samples": 32}',
                          "--hostile-concurrency", "3", "--no-warmup", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    runs = json_runs(out)
    assert [(r["clients"], r["cache"], r["hostile"]) for r in runs] == [
        (2, "cold", False), (2, "cold", True)]
    quiet, flooded = runs
    assert "hostile_answers" not in quiet
    h = flooded["hostile_answers"]
    assert h["sent"] >= 1 and h["200"] >= 1
    assert flooded["hostile_params"] == {"resolution": 128, "samples": 32}
    for r in runs:
        assert r["frames"] > 0 and r["client_errors"] == 0 and r["duplicates"] == 0
    md = (tmp_path / "load.md").read_text()
    assert "## Abuse: the walkers with and without a hostile client" in md
    assert "| 2 | cold | 2 | yes |" in md and "| 2 | cold | 2 | no |" in md
    assert (tmp_path / "load.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
