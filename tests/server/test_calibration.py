"""``auto`` on a real server picks by a calibration: measured in the background on first use,
said in the welcome with its figures, kept in the cache folder across restarts, and measured
first by ``pvs precompute``."""

from __future__ import annotations

import time

import httpx
import pytest

from client.session import SyncSession
from tests.conftest import serving, wait_for

pytestmark = pytest.mark.usefixtures("registered_test_cores")

#: Small and quick: the generated village of the test settings, a tight time limit.
FAST = {"calibrate": True, "auto_budget": 0.5, "calibration_seconds": 20.0}


def test_auto_follows_the_calibration_once_it_is_measured(settings, tmp_path):
    with serving(settings, cache_dir=tmp_path, **FAST) as (url, app):
        auto = app.state.server.resolver.calibration
        with SyncSession.connect(url, "village", "auto", prefetch=False) as s:
            why = s.welcome.features["core_choice"]["why"]
            assert "calibration under way" in why
        wait_for(lambda: any(c is not None for c in auto.calibrations.values()), 120.0)
        cal = next(c for c in auto.calibrations.values() if c is not None)
        assert cal.trials and cal.seconds <= FAST["calibration_seconds"] + 30
        with SyncSession.connect(url, "village", "auto", prefetch=False) as s:
            choice = s.welcome.features["core_choice"]
            assert choice["why"].startswith("calibrated on")
            assert choice["core"] == s.welcome.core
            # The session runs the chosen trial: its core at its knob level.
            loaded = app.state.server.catalog.get("village")
            best = auto.decide(loaded.scene, loaded.grid.cell_size)
            assert best.calibrated and best.why == choice["why"] and best.core == s.welcome.core
            assert best.params and all(s.welcome.params[k] == v for k, v in best.params.items())
            welcome = s.welcome
        _every_report_agrees(url, welcome)
    assert list(tmp_path.glob("calibration-*.json"))
    # A restarted server with the same cache folder finds it: no measuring, the choice at once.
    with serving(settings, cache_dir=tmp_path, **FAST) as (url, app):
        auto = app.state.server.resolver.calibration
        loaded = app.state.server.catalog.get("village")
        t0 = time.perf_counter()
        cal2 = auto.calibration(loaded.scene, loaded.grid.cell_size, wait=True)
        assert time.perf_counter() - t0 < 5.0
        assert cal2 == cal
        # The restarted server's reports and sessions make the same choice.
        with SyncSession.connect(url, "village", "auto", prefetch=False) as s:
            assert (s.welcome.core, s.welcome.params) == (welcome.core, welcome.params)
            assert s.welcome.features["core_choice"] == welcome.features["core_choice"]
        _every_report_agrees(url, welcome)


def _every_report_agrees(url: str, welcome) -> None:
    """``GET /cores?scene=village`` and HTTP PVS answers with ``core=auto`` name the core,
    parameters and reason the session's ``welcome`` got."""
    choice = welcome.features["core_choice"]
    with httpx.Client(base_url=url, timeout=300) as http:
        fit = http.get("/cores", params={"scene": "village"}).json()["fit"]
        assert fit["auto"]["core"] == welcome.core and fit["auto"]["why"] == choice["why"]
        assert fit["auto"]["calibrated"] is True
        assert all(welcome.params[k] == v for k, v in fit["auto"]["params"].items())
        r = http.get("/scenes/village/cells/0/pvs", params={"core": "auto"})
        assert r.status_code == 200, r.text
        body = r.json()
        assert (body["core"], body["chosen_because"]) == (welcome.core, choice["why"])
        assert body["params"] == welcome.params
        r = http.get("/scenes/village/cells/0/pvs", params={"core": "auto"},
                     headers={"accept": "application/octet-stream"})
        assert r.headers["x-pvs-core"] == welcome.core
        reason = choice["why"].encode("ascii", "replace").decode()
        assert r.headers["x-pvs-core-reason"] == " ".join(reason.split())


def test_precompute_with_auto_calibrates_first(settings, tmp_path):
    from server.app import create_app
    from server.precompute import precompute

    app = create_app(settings.model_copy(update={"cache_dir": tmp_path, **FAST}))
    service = app.state.server.compute
    try:
        report = precompute(service, "village", "auto", cells=[0, 1], progress=False)
    finally:
        service.shutdown()
    assert report.why.startswith("calibrated on") and not report.failed
    assert list(tmp_path.glob("calibration-*.json"))


def test_pvs_cores_and_a_server_on_its_cache_folder_agree(settings, scenes_dir, tmp_path,
                                                          capsys):
    """``pvs cores --calibrate --cache-dir`` keeps its calibration where a server on that
    folder finds it; ``pvs cores --scene`` then reports as ``auto`` exactly what the server's
    ``GET /cores``, its sessions and its PVS answers get (one decision, ``decide_auto``)."""
    import json

    import pvs_cli

    cache = tmp_path / "cache"
    common = ["cores", "--scene", "box", "--scenes", str(scenes_dir), "--budget", "0.5",
              "--cache-dir", str(cache)]
    assert pvs_cli.main([*common, "--calibrate"]) == 0
    assert "calibrated on" in capsys.readouterr().out
    assert pvs_cli.main(common) == 0
    auto = json.loads(capsys.readouterr().out)["auto"]
    assert auto["calibrated"] is True and auto["why"].startswith("calibrated on")
    with serving(settings, cache_dir=cache, calibrate=True, auto_budget=0.5) as (url, app):
        loaded = app.state.server.catalog.get("box")
        t0 = time.perf_counter()
        # Read from the folder, not measured again.
        assert app.state.server.resolver.calibration.calibration(
            loaded.scene, loaded.grid.cell_size, wait=True) is not None
        assert time.perf_counter() - t0 < 5.0
        fit = httpx.get(url + "/cores", params={"scene": "box"}, timeout=120).json()["fit"]
        assert fit["auto"] == auto
        with SyncSession.connect(url, "box", "auto", prefetch=False) as s:
            assert s.welcome.core == auto["core"]
            assert s.welcome.features["core_choice"] == {"core": auto["core"],
                                                         "why": auto["why"]}
            assert all(s.welcome.params[k] == v for k, v in auto["params"].items())
            welcome = s.welcome
        body = httpx.get(url + "/scenes/box/cells/0/pvs", params={"core": "auto"},
                         timeout=300).json()
        assert (body["core"], body["chosen_because"]) == (auto["core"], auto["why"])
        assert body["params"] == welcome.params
