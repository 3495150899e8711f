"""Smoke test of the cancellation benchmark: ``--quick`` runs both parts (checkpoints on a 5k
scene, a spawned worker killed and replaced) into a temporary folder; the files hold plausible
numbers (the real ones live in benchmarks/results/cancel.md)."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_cancel

#: One worker runs this module, so its costly module fixtures run once, not once per worker.
pytestmark = pytest.mark.xdist_group("bench_cancel")


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("cancel")
    assert bench_cancel.main(["--quick", "--out", str(out)]) == 0
    return out, json.loads((out / "cancel_quick.json").read_text())


def test_quick_run_writes_the_report_the_data_and_the_plot(quick):
    out, _ = quick
    md = (out / "cancel_quick.md").read_text()
    assert "Command (checkpoints part): `python -m benchmarks.bench_cancel --quick" in md
    assert "Machine: " in md and "load average" in md
    for heading in ("## Conclusion", "## Option 1: checkpoints", "### Stop latency",
                    "## Option 2: a worker process", "### Kill and replace"):
        assert heading in md
    assert "costs less" in md or "cost less" in md
    assert (out / "cancel_quick.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_checkpoint_numbers_are_plausible(quick):
    _, res = quick
    ck = res["checkpoints"]
    assert 0 < ck["check_cost"]["live_ns"] < 1e5
    requests = [r for r in ck["rows"] if r["kind"] == "request"]
    assert {r["core"] for r in requests} == {"sampling", "from_segment", "cos"}
    for r in requests:
        # Every core checks more than once per run, and a check costs far less than the run.
        assert r["timeline"]["checks"] > 1
        assert 0 <= r["overhead_estimated"] < 0.01
        assert 0 < r["timeline"]["gap_max_s"] <= r["timeline"]["run_s"]
        assert min(r["none_s"] + r["live_s"]) > 0
    for r in ck["rows"]:
        for c in r["cancels"]:
            assert c["outcome"] in ("cancelled", "completed after cancel", "finished first")
            if c["latency_s"] is not None:
                assert 0 <= c["latency_s"] < 30
    # The hostile request never ends by itself: its cancel stops it.
    (hostile,) = [r for r in ck["rows"] if r["kind"] == "hostile"]
    assert [c["outcome"] for c in hostile["cancels"]] == ["cancelled"]


def test_process_numbers_are_plausible(quick):
    _, res = quick
    pr = res["process"]
    (row,) = pr["rows"]
    assert row["method"] == "spawn" and row["core"] == "sampling"
    start = row["starts"][0]
    assert all(start[k] >= 0 for k in bench_cancel.PHASES)
    # The phases end at the worker's "warm" stamp; ready is when the parent heard of it.
    assert 0 < start["ready_s"] - sum(start[k] for k in bench_cancel.PHASES) < 0.1
    # Killing is quick; a replacement is not (an interpreter, numpy, numba, the cores).
    assert 0 < row["kill_median_s"] < row["ready_median_s"] < 120
    assert start["rss_mib"] > 20
    assert row["job_overhead_median_s"] >= 0
    (ship,) = pr["ship"]
    assert ship["pickle_bytes"] >= ship["arrays_bytes"] > 0 and ship["ship_s"] > 0


def test_a_part_rerun_alone_keeps_the_other(quick, tmp_path):
    out, res = quick
    (tmp_path / "cancel_quick.json").write_text(json.dumps(res))
    assert bench_cancel.main(["--quick", "--parts", "process", "--out", str(tmp_path)]) == 0
    again = json.loads((tmp_path / "cancel_quick.json").read_text())
    assert again["checkpoints"] == res["checkpoints"]
    assert again["process"]["meta"]["command"].endswith("--parts process --out " + str(tmp_path))
