"""``auto`` on a real server picks by a calibration: measured in the background on first use,
said in the welcome with its figures, kept in the cache folder across restarts, and measured
first by ``pvs precompute``."""

from __future__ import annotations

import time

import pytest

from client.session import SyncSession
from tests.conftest import serving, wait_for

pytestmark = pytest.mark.usefixtures("registered_test_cores")

#: Small and quick: the generated village of the test settings, a tight time limit.
FAST = {"calibrate": True, "auto_budget": 0.5, "calibration_seconds": 20.0}


def test_auto_follows_the_calibration_once_it_is_measured(settings, tmp_path):
    with serving(settings, cache_dir=tmp_path, **FAST) as (url, app):
        compute = app.state.server.compute
        with SyncSession.connect(url, "village", "auto", prefetch=False) as s:
            why = s.welcome.features["core_choice"]["why"]
            assert "calibration under way" in why
        wait_for(lambda: any(c is not None for c in compute.calibrations.values()), 120.0)
        cal = next(c for c in compute.calibrations.values() if c is not None)
        assert cal.trials and cal.seconds <= FAST["calibration_seconds"] + 30
        with SyncSession.connect(url, "village", "auto", prefetch=False) as s:
            choice = s.welcome.features["core_choice"]
            assert choice["why"].startswith("calibrated on")
            assert choice["core"] == s.welcome.core
            # The session runs the chosen trial: its core at its knob level.
            scene = app.state.server.catalog.get("village").scene
            best, why = compute._calibrated_choice(scene, compute.cell_size_of(scene))
            assert why == choice["why"] and best.core == s.welcome.core
            assert all(s.welcome.params[k] == v for k, v in best.params.items())
    assert list(tmp_path.glob("calibration-*.json"))
    # A restarted server with the same cache folder finds it: no measuring, the choice at once.
    with serving(settings, cache_dir=tmp_path, **FAST) as (url, app):
        compute = app.state.server.compute
        scene = app.state.server.catalog.get("village").scene
        t0 = time.perf_counter()
        cal2 = compute.calibration(scene, compute.cell_size_of(scene), wait=True)
        assert time.perf_counter() - t0 < 5.0
        assert cal2 == cal


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
