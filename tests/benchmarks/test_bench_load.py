"""Smoke test of the load benchmark: 3 real protocol clients against a real ``pvs serve`` for a
few seconds; the printed table, the JSON line and the written files carry every field (the
real numbers live in benchmarks/results/load.md)."""

from __future__ import annotations

import json

from benchmarks import bench_load

FIELDS = ("clients", "frames", "stalls", "latency_p50_s", "latency_p95_s", "bytes_received",
          "bytes_sent", "server_rss_peak_bytes", "computations", "server_cpu_seconds",
          "duplicates", "client_errors", "stalls_per_client")


def test_three_clients_report_every_field(tmp_path, capsys):
    rc = bench_load.main(["--clients", "3", "--duration", "3", "--triangles", "5000",
                          "--params", '{"resolution": 64, "samples": 8}', "--cache", "cold",
                          "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    assert out.startswith("command: python -m benchmarks.bench_load")
    for row in ("stalls", "frame latency p50", "frame latency p95", "bytes sent",
                "server RSS peak", "server CPU"):
        assert row in out
    r = json.loads(next(line for line in out.splitlines() if line.startswith("json: "))[6:])
    assert set(FIELDS) <= set(r)
    assert r["clients"] == 3 and len(r["stalls_per_client"]) == 3
    assert r["frames"] > 0 and r["bytes_received"] > 0 and r["bytes_sent"] > 0
    assert r["server_rss_peak_bytes"] > 0 and r["computations"] >= 1
    # Each triangle once per session, and nothing went wrong on the protocol.
    assert r["duplicates"] == 0 and r["client_errors"] == 0
    # Frames by the answer their cell held, and the error of sampled frames per answer.
    assert sum(r["frames_by_answer"].values()) == r["frames"]
    assert 0.0 <= r["first_answer_share"] <= 1.0
    for answer, err in r["frame_error_by_answer"].items():
        assert answer in r["frames_by_answer"] and err["frames"] > 0
        assert 0.0 <= err["eps_mean"] <= err["eps_worst"] <= 100.0
    md = (tmp_path / "load.md").read_text()
    assert "command: `python -m benchmarks.bench_load" in md and "machine:" in md
    assert (tmp_path / "load.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "load.json").read_text())["runs"][0]["frames"] == r["frames"]
    # Re-rendering from the JSON measures nothing and keeps every number.
    (tmp_path / "load.md").unlink()
    assert bench_load.main(["--rerender", str(tmp_path / "load.json")]) == 0
    assert (tmp_path / "load.md").read_text() == md


def test_latency_percentiles_count_frames_never_delivered():
    s = bench_load.latency_summary([0.0, 0.0, 0.0, 0.5], never=0)
    assert (s["latency_p50_s"], s["latency_p95_s"], s["latency_max_s"]) == (0.0, 0.5, 0.5)
    # 4 delivered, 6 never: the median frame was never delivered.
    s = bench_load.latency_summary([0.0, 0.0, 0.0, 0.5], never=6)
    assert s["latency_p50_s"] is None and s["latency_p95_s"] is None
    assert s["latency_max_s"] == 0.5
    s = bench_load.latency_summary([0.1] * 19, never=1)
    assert s["latency_p50_s"] == 0.1 and s["latency_p95_s"] == 0.1  # rank 19 of 20
    assert bench_load.latency_summary([], never=0)["latency_p50_s"] is None


def test_warm_cache_serves_every_cell_without_computing(tmp_path, capsys):
    """The warm rows run after every cell's PVS was computed over HTTP with the walkers' core
    and parameters, so the walkers' sessions find them all in the cache: the HTTP and WebSocket
    paths share cache keys (a mismatch would show as computations here)."""
    rc = bench_load.main(["--clients", "1,2", "--duration", "2", "--triangles", "5000",
                          "--params", '{"resolution": 64, "samples": 8}', "--cache", "warm",
                          "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    runs = [json.loads(line[6:]) for line in out.splitlines() if line.startswith("json: ")]
    assert [(r["clients"], r["cache"]) for r in runs] == [(1, "warm"), (2, "warm")]
    for r in runs:
        assert r["computations"] == 0 and r["cache_hits"] >= 1
        assert r["client_errors"] == 0 and r["duplicates"] == 0
    assert "| warm | 2 |" in (tmp_path / "load.md").read_text()


def test_the_hostile_client_counts_answers_and_comes_from_its_own_address():
    """Against a stub that refuses every request with 429, the hostile flood comes from
    127.0.0.2, counts every answer by status and says what was in flight when it stopped."""
    import asyncio

    import numpy as np

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

    import numpy as np

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
    rc = bench_load.main(["--hostile", "--quick", "--clients", "2", "--duration", "3",
                          "--triangles", "5000", "--params", '{"resolution": 64, "samples": 8}',
                          "--hostile-params", '{"resolution": 128, "samples": 32}',
                          "--hostile-concurrency", "3", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0
    runs = [json.loads(line[6:]) for line in out.splitlines() if line.startswith("json: ")]
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
    assert "| cold | 2 | yes |" in md and "| cold | 2 | no |" in md
    assert (tmp_path / "load.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
