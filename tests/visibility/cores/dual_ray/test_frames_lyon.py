"""dual_ray's PVS draws what the full scene draws, on Lyon at 40 m cells, from poses of the
published walk (benchmarks/results/walk_dual_ray_lyon): every pixel of a frame rendered from the
PVS matches the full scene's (ε = 0), with the client's renderer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.visibility.real_scenes import assert_pvs_frames_match

WALK = Path(__file__).resolve().parents[4] / "benchmarks/results/walk_dual_ray_lyon"


@pytest.mark.slow
def test_frames_from_the_pvs_match_the_full_scene_on_lyon():
    n = len(json.loads((WALK / "walkthrough.json").read_text())["poses"])
    assert_pvs_frames_match("lyon_vilo3d", 40.0, "dual_ray", {}, WALK, [0, 96, n - 1])
