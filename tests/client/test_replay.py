"""Walkthrough replays: the real server on loopback, the real client rendering with pyrender.

These are the measuring instrument's own acceptance tests: a good PVS must give frames close to
ground truth, and a deliberately broken PVS must be caught by the same metrics.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest

from client.replay import ReplayOptions, replay, replay_cores, side_by_side
from visibility.cores import base as core_base
from visibility.cores.base import Core
from visibility.cores.sampling import SamplingCore

#: Sampling settings that stay fast on 2 cores yet find what matters in a 10k-triangle scene.
GOOD = {"resolution": 128, "samples": 24}


@dataclass
class BrokenParams(SamplingCore.Params):
    pass


class BrokenCore(Core):
    """The sampling core's answer with every other triangle dropped."""

    name = "test_broken"
    description = "sampling with half of the PVS dropped (tests that metrics catch it)"
    Params = BrokenParams

    def _compute(self, scene, cell, params):
        ids, stats = SamplingCore()._compute(scene, cell, params)
        ids = np.sort(np.asarray(ids))
        return ids[::2], stats


@pytest.fixture(scope="module")
def broken_core():
    core_base.register(BrokenCore)
    yield
    core_base.unregister(BrokenCore.name)


def options(live_server, tmp_path, scene, **kw):
    kw.setdefault("realtime", False)  # as fast as possible: the metrics do not depend on pace
    return ReplayOptions(server=live_server, scene=scene, params=dict(GOOD), out_dir=tmp_path,
                         duration=4.0, fps=5.0, width=128, height=128, quiet=True, **kw)


def test_replay_paces_in_real_time_by_default_as_the_cli_does():
    from pvs_cli import build_parser

    args = build_parser().parse_args(["walk"])
    assert ReplayOptions(server="http://x", scene="rooms").realtime is True
    assert args.realtime is True


def test_cli_takes_cores_and_budget():
    from pvs_cli import build_parser, walk_cores

    p = build_parser()
    args = p.parse_args(["walk", "--cores", "sampling, from_segment,cos", "--budget", "5000"])
    assert walk_cores(args) == ["sampling", "from_segment", "cos"] and args.budget == 5000
    # --core keeps working, comma list included; --cores wins over it.
    assert walk_cores(p.parse_args(["walk", "--core", "a,b"])) == ["a", "b"]
    assert walk_cores(p.parse_args(["walk", "--core", "a", "--cores", "b,c"])) == ["b", "c"]
    assert p.parse_args(["walk"]).budget is None
    with pytest.raises(SystemExit):
        walk_cores(p.parse_args(["walk", "--cores", ","]))
    demo = p.parse_args(["demo", "--scene", "city", "--near-far", "--r1", "10", "--cores", "x,y"])
    assert demo.near_far and demo.r1 == 10.0 and walk_cores(demo) == ["x", "y"]


def test_a_budget_bounds_what_the_client_holds_and_frames_stay_good(live_server, tmp_path):
    """With a budget a little over the largest cell PVS of the walk (but under what the client
    holds without one), the server's drops keep the store within it on every frame, and the
    frames still meet the bar."""
    free = replay(options(live_server, tmp_path / "free", "rooms"), "sampling", tmp_path / "free")
    largest = max(f["pvs_triangles"] for f in free["frames"] if "pvs_triangles" in f)
    held = max(f["triangles_held"] for f in free["frames"])
    budget = int(largest * 1.1) + 1
    assert budget < held, "the walk must need drops for this test to mean anything"
    s = replay(options(live_server, tmp_path / "b", "rooms", budget=budget), "sampling",
               tmp_path / "b")
    assert s["meta"]["budget"] == budget
    assert all(f["triangles_held"] <= budget for f in s["frames"]), [
        f["triangles_held"] for f in s["frames"]]
    assert s["meta"]["server_drops"] > 0
    assert s["epsilon"] <= 0.5, s["summary"]
    assert s["ssim"] >= 0.99, s["summary"]


@pytest.mark.parametrize("scene", ["rooms", "city"])
def test_sampling_pvs_frames_match_ground_truth(live_server, tmp_path, scene):
    summary = replay(options(live_server, tmp_path, scene), "sampling", tmp_path)
    assert summary["frames_rendered"] == len(summary["frames"]) > 10
    assert summary["epsilon"] <= 0.5, summary["summary"]
    assert summary["ssim"] >= 0.99, summary["summary"]
    # The report on disk holds the stable keys.
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    for key in ("epsilon", "psnr", "ssim", "stalls", "frames"):
        assert key in on_disk
    assert (tmp_path / "frames.csv").is_file() and (tmp_path / "metrics.png").is_file()
    assert list(tmp_path.glob("worst_*.png"))
    assert all(f["triangles_held"] > 0 for f in summary["frames"])
    # The first cell arrives during start-up, so frame 0 already has geometry and no stall.
    assert summary["meta"]["startup_seconds"] > 0
    assert not summary["frames"][0]["stalled"]


def test_a_broken_pvs_is_caught(live_server, tmp_path, broken_core):
    good = replay(options(live_server, tmp_path / "good", "rooms"), "sampling", tmp_path / "good")
    bad = replay(options(live_server, tmp_path / "bad", "rooms"), "test_broken", tmp_path / "bad")
    assert bad["epsilon"] > max(0.5, 5 * good["epsilon"])
    assert bad["ssim"] < good["ssim"]
    assert bad["psnr"] < good["psnr"]


def test_several_cores_replay_the_same_walk_side_by_side(live_server, tmp_path, capsys,
                                                         broken_core):
    opts = options(live_server, tmp_path, "rooms", cores=["sampling", "test_broken"])
    summaries = replay_cores(opts)
    assert [s["meta"]["core"] for s in summaries] == ["sampling", "test_broken"]
    walks = [json.loads((tmp_path / c / "summary.json").read_text())["meta"]["walkthrough"]
             for c in ("sampling", "test_broken")]
    assert walks[1] == str(tmp_path / "sampling" / "walkthrough.json")
    t0 = [f["t"] for f in summaries[0]["frames"]]
    assert t0 == [f["t"] for f in summaries[1]["frames"]]
    out = capsys.readouterr().out
    assert "test_broken" in out and "sampling" in out
    # The side-by-side table: one row per core, each core's mean epsilon in its column.
    table = out[out.rindex("core "):].splitlines()
    assert table[0].split()[:4] == ["core", "eps", "%", "PSNR"]
    rows = {line.split()[0]: line.split() for line in table[1:3]}
    for s in summaries:
        assert float(rows[s["meta"]["core"]][1]) == pytest.approx(s["epsilon"], abs=1e-3)
    assert "eps_c" not in table[0]  # no near-far columns without near-far


def test_file_scene_needs_its_folder(live_server, tmp_path, scenes_dir):
    from client.replay import local_scene
    from client.session import SyncSession

    s = SyncSession.connect(live_server, "box", "sampling", {"resolution": 32, "samples": 2})
    try:
        with pytest.raises(FileNotFoundError):
            local_scene(s.welcome.scene, None)
        scene = local_scene(s.welcome.scene, scenes_dir)
        assert scene.n_triangles == s.welcome.scene.triangles
    finally:
        s.close()


def test_near_far_stream_is_composed_and_measured(settings, server_app, tmp_path):
    """With near-far on, a city walk gets a cubemap per cell; the composed frames (near PVS
    geometry + far cubemap) are close to ground truth while the geometry-only frames lack the
    far field, and each frame reports the discontinuity of morphed and conventional composition.
    """
    from server.app import create_app
    from tests.conftest import LiveServer

    nf = settings.model_copy(update={"near_far": True, "near_far_r1": 20.0, "near_far_r2": 40.0,
                                     "near_far_resolution": 256})
    srv = LiveServer(create_app(nf), nf)
    srv.start()
    try:
        opts = options(srv.url, tmp_path, "city")
        summary = replay(opts, "sampling", tmp_path)
    finally:
        srv.stop()
    frames = summary["frames"]
    composed = [f for f in frames if "epsilon_composed" in f]
    assert len(composed) >= len(frames) - 1, "every frame after the first holds a cubemap"
    eps_c = np.mean([f["epsilon_composed"] for f in composed])
    eps_g = np.mean([f["epsilon"] for f in composed])
    assert eps_c < eps_g, "the cubemap must fill in what the near geometry leaves out"
    assert eps_c <= 2.0
    assert np.mean([f["ssim_composed"] for f in composed]) >= 0.95
    for f in composed:
        assert np.isfinite(f["delta_composed"]) and np.isfinite(f["delta_conventional"])
        assert f["compose_seconds"] > 0 and isinstance(f["frame"], int)
        # Per-cell cubemaps: the eye stays within half a cell's diagonal of the centre O.
        assert 0.0 <= f["eye_offset"] <= settings.cell_size_for(None) * 0.5 ** 0.5 + 1e-6
    # The report carries the composed means and delta; side by side shows them in columns.
    assert summary["delta_composed"] == pytest.approx(
        np.mean([f["delta_composed"] for f in composed]))
    head, row = side_by_side([summary]).splitlines()
    assert "eps_c" in head and "δ morph" in head and "δ conv" in head
    cells = row.split()
    assert float(cells[4]) == pytest.approx(summary["epsilon_composed"], abs=1e-3)
    assert float(cells[7]) == pytest.approx(summary["delta_composed"], abs=1e-4)


def test_progressive_frames_are_reported_by_answer(settings, tmp_path):
    """With progressive streams, frames drawn from a first answer and from the core's answer
    are counted and measured apart in the summary."""
    from tests.conftest import serving

    with serving(settings, progressive=True) as (url, _):
        opts = ReplayOptions(server=url, scene="rooms", params={"resolution": 256},
                             out_dir=tmp_path, duration=4.0, fps=5.0, width=128, height=128,
                             quiet=True, realtime=True)
        summary = replay(opts, "from_segment", tmp_path)
    answers = summary["answers"]
    frames = summary["frames"]
    assert "first" in answers, answers
    assert sum(a["frames"] for a in answers.values()) == len(frames)
    assert {f["answer"] for f in frames} == set(answers)
    first = [f["epsilon"] for f in frames if f["answer"] == "first"]
    assert answers["first"]["epsilon"] == pytest.approx(np.mean(first))
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert set(saved["answers"]) == set(answers)
    for a, st in answers.items():
        assert saved["answers"][a] == pytest.approx(st)


@pytest.mark.slow
def test_cos_walk_through_a_real_level_in_small_cells_draws_what_the_full_scene_does(
        settings, tmp_path):
    """The README's small-cell walk: lavaducts (a real Quake level) served in 0.3 m cells,
    replayed with cos at 32 px. A conservative PVS holds every triangle a frame shows, so the
    frames match the full scene's up to rasterization ties (a pixel or two)."""
    from server.app import create_app
    from tests.conftest import LiveServer
    from tests.visibility.real_scenes import SHARED_SCENES, real_path

    real_path("lavaducts")  # the real scene must be there: a KeyError, not a skip
    small = settings.model_copy(update={"scenes_dir": SHARED_SCENES, "cell_size": 0.3,
                                        "generated": {}, "max_frame_bytes": 1 << 20})
    srv = LiveServer(create_app(small), small)
    srv.start()
    try:
        opts = ReplayOptions(server=srv.url, scene="lavaducts", params={"resolution": 32},
                             out_dir=tmp_path, duration=3.0, fps=5.0, width=128, height=128,
                             quiet=True, realtime=False, scenes_dir=SHARED_SCENES)
        summary = replay(opts, "cos", tmp_path)
    finally:
        srv.stop()
    frames = summary["frames"]
    assert summary["meta"]["cells"] > 10_000  # 0.3 m cells, not the scene's own 2 m
    assert len({f["cell"] for f in frames}) >= 5  # the walk crossed cells
    # One pixel of 128^2 is 0.0061 %.
    assert max(f["epsilon"] for f in frames) <= 0.02
    assert min(f["ssim"] for f in frames) >= 0.999
