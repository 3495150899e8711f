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
