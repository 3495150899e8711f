"""cos's PVS draws what the full scene draws on lavaducts in 0.3 m cells, at the poses of the
published walk (benchmarks/results/walk_cos_lavaducts) where the client's frames differed by a
pixel: frames rendered straight from the PVS match the full scene in every pixel (ε = 0)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.visibility.real_scenes import SHARED_SCENES

WALK = Path(__file__).resolve().parents[4] / "benchmarks/results/walk_cos_lavaducts"


@pytest.mark.slow
def test_frames_from_the_pvs_match_the_full_scene_on_lavaducts():
    if not (SHARED_SCENES / "lavaducts.glb").exists():
        pytest.skip("../shared/scenes/lavaducts.glb is not here")
    from client.metrics import frame_metrics
    from client.render import OffscreenRenderer
    from visibility.cores.base import get_core
    from visibility.loaders import load_scene
    from visibility.viewcells import ViewcellGrid

    poses = json.loads((WALK / "walkthrough.json").read_text())["poses"]
    frames = json.loads((WALK / "summary.json").read_text())["frames"]
    odd = [i for i, f in enumerate(frames) if f["epsilon"] > 0] or [0]
    scene = load_scene(SHARED_SCENES / "lavaducts.glb")
    grid = ViewcellGrid.for_scene(scene, 0.3)
    core = get_core("cos")
    r = OffscreenRenderer(256, 256)
    try:
        for i in [*odd, len(poses) - 1]:
            eye, fwd = np.array(poses[i]["position"]), np.array(poses[i]["forward"])
            cid = grid.cell_of(eye)
            assert cid is not None
            ids = core.compute(scene, grid.cell(cid), core.make_params(resolution=32))
            frame = r.render(scene.vertices[scene.faces[ids.triangle_ids]],
                             scene.colors[ids.triangle_ids], eye, fwd)
            m = frame_metrics(frame, r.render_scene(scene, eye, fwd))
            assert m["epsilon"] == 0.0, (i, m)
    finally:
        r.close()
