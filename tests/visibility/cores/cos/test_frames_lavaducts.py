"""cos's PVS draws what the full scene draws on lavaducts in 0.3 m cells, at the poses of the
published walk (benchmarks/results/walk_cos_lavaducts) where the client's frames differed by a
pixel: frames rendered straight from the PVS match the full scene in every pixel (ε = 0)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.visibility.real_scenes import assert_pvs_frames_match

WALK = Path(__file__).resolve().parents[4] / "benchmarks/results/walk_cos_lavaducts"


@pytest.mark.slow
def test_frames_from_the_pvs_match_the_full_scene_on_lavaducts():
    frames = json.loads((WALK / "summary.json").read_text())["frames"]
    odd = [i for i, f in enumerate(frames) if f["epsilon"] > 0]
    assert_pvs_frames_match("lavaducts", 0.3, "cos", {"resolution": 32}, WALK,
                            [*odd, len(frames) - 1])
