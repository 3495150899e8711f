"""Calibration of ``auto``: measured trials, the choice among them, the JSON kept on disk."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.calibration import (
    Calibration,
    Trial,
    calibrate,
    calibration_path,
    choose,
    load_calibration,
    pick,
    save_calibration,
)
from visibility.generators import make_scene
from visibility.viewcells import ViewcellGrid


@pytest.fixture(scope="module")
def village():
    return make_scene("village", triangles=5_000)


@pytest.fixture(scope="module")
def measured(village):
    lines: list[str] = []
    cal = calibrate(village, 4.0, cells=2, reference_points=32, reference_resolution=128,
                    cores=["sampling", "from_segment", "dual_ray"], progress=lines.append)
    return cal, lines


def test_trials_measure_time_and_misses_against_a_dense_sample(measured, village):
    cal, lines = measured
    assert len(cal.cells) == 2 and all(r > 0 for r in cal.reference_triangles)
    assert {t.core for t in cal.trials} == {"sampling", "from_segment"}
    assert len(lines) == len(cal.trials)
    for t in cal.trials:
        assert t.seconds > 0 and 0.0 <= t.fn <= 1.0 and t.overestimation > 0
    # Each core's ladder: more of its knob misses no more (up to sampling noise).
    samp = [t for t in cal.trials if t.core == "sampling"]
    assert samp[-1].fn <= samp[0].fn + 0.02
    # The core that does not fit is named with its reason, not measured.
    assert "2.5D" in cal.skipped["dual_ray"]
    assert cal.fingerprint and cal.scene == village.name


def test_choose_takes_the_fewest_misses_within_the_budget():
    cal = Calibration("f", "s", 4.0, [1, 2], [100, 100], 1.0, trials=[
        Trial("a", {"resolution": 64}, 0.2, 0.10, 1.0),
        Trial("a", {"resolution": 128}, 0.9, 0.02, 1.1),
        Trial("b", {}, 0.5, 0.00, 6.0),          # misses nothing, but a PVS too large
        Trial("c", {"samples": 8}, 3.0, 0.00, 1.0),  # misses nothing, but too slow
    ])
    best, why = choose(cal)
    assert (best.core, best.params) == ("a", {"resolution": 128})
    assert "missed 2.00 %" in why and "0.900 s" in why and "PVS 1.1x" in why
    # A tighter budget: no lean trial is complete enough (a at 64 px misses 10 %), so the
    # fewest misses win, large PVS and all.
    best, why = choose(cal, budget_seconds=0.5)
    assert best.core == "b" and "the fewest misses win" in why
    # A looser miss limit keeps the lean one.
    assert choose(cal, budget_seconds=0.5, max_fn=0.2)[0].params == {"resolution": 64}
    # A core that no longer fits is not taken.
    best, why = choose(cal, allowed=lambda n: n != "a")
    assert best.core == "b"
    # Nothing within the budget: the fastest, and the reason says so.
    best, why = choose(cal, budget_seconds=0.1)
    assert best.seconds == 0.2 and "no core met the budget" in why
    assert choose(cal, allowed=lambda n: False) is None


def test_kept_on_disk_by_content_hash_and_cell_size(measured, tmp_path):
    cal, _ = measured
    path = save_calibration(tmp_path, cal)
    assert path == calibration_path(tmp_path, cal.fingerprint, cal.cell_size)
    back = load_calibration(tmp_path, cal.fingerprint, cal.cell_size)
    assert back == cal
    assert load_calibration(tmp_path, "another-scene", cal.cell_size) is None
    assert load_calibration(tmp_path, cal.fingerprint, 8.0) is None
    path.write_text("{not json")
    assert load_calibration(tmp_path, cal.fingerprint, cal.cell_size) is None


def test_the_time_limit_bounds_it(village):
    cal = calibrate(village, 4.0, cells=1, reference_points=8, reference_resolution=64,
                    cores=["sampling"], time_limit=0.0)
    assert not cal.trials and any("time limit" in why for why in cal.skipped.values())


def test_pick_spreads_cells_over_the_grid(village):
    grid = ViewcellGrid.for_scene(village, 4.0)
    ids = pick(grid, 3)
    assert len(ids) == 3 and ids == sorted(ids) and 0 < ids[0] and ids[-1] < len(grid) - 1
    assert np.all(np.diff(ids) > 0)
