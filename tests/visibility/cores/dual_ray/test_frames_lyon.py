"""dual_ray's PVS draws what the full scene draws, on Lyon at 40 m cells, from poses of the
published walk (benchmarks/results/walk_dual_ray_lyon): every pixel of a frame rendered from the
PVS matches the full scene's (ε = 0), with the client's renderer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.visibility.real_scenes import SHARED_SCENES

WALK = Path(__file__).resolve().parents[4] / "benchmarks/results/walk_dual_ray_lyon"


@pytest.mark.slow
def test_frames_from_the_pvs_match_the_full_scene_on_lyon():
    if not (SHARED_SCENES / "lyon_vilo3d.glb").exists():
        pytest.skip("../shared/scenes/lyon_vilo3d.glb is not here")
    from client.metrics import frame_metrics
    from client.render import OffscreenRenderer
    from visibility.cores.base import get_core
    from visibility.loaders import load_scene
    from visibility.viewcells import ViewcellGrid

    poses = json.loads((WALK / "walkthrough.json").read_text())["poses"]
    scene = load_scene(SHARED_SCENES / "lyon_vilo3d.glb")
    grid = ViewcellGrid.for_scene(scene, 40.0)
    core = get_core("dual_ray")
    r = OffscreenRenderer(256, 256)
    try:
        for i in (0, 96, len(poses) - 1):
            eye, fwd = np.array(poses[i]["position"]), np.array(poses[i]["forward"])
            cid = grid.cell_of(eye)
            assert cid is not None
            ids = core.compute(scene, grid.cell(cid), core.make_params()).triangle_ids
            frame = r.render(scene.vertices[scene.faces[ids]], scene.colors[ids], eye, fwd)
            m = frame_metrics(frame, r.render_scene(scene, eye, fwd))
            assert m["epsilon"] == 0.0, (i, m)
    finally:
        r.close()
