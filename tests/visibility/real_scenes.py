"""The real third-party scenes beside the repository (../shared/scenes), loaded once per run.

Every scene file there (``visibility.loaders.SCENE_EXTENSIONS``; its sidecar ``<stem>.json``
beside it) is found by listing the folder, so a scene dropped in is tested without editing this
module. Tests parametrize over ``REAL`` (the stems), which keeps their ids readable.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from visibility.loaders import SCENE_EXTENSIONS, load_scene
from visibility.raster.hierarchy import scene_hierarchy
from visibility.scene import Scene
from visibility.viewcells import ViewcellGrid

SHARED_SCENES = Path(__file__).resolve().parents[2].parent / "shared" / "scenes"


def discover(folder: Path = SHARED_SCENES) -> dict[str, Path]:
    """{stem: path} of every scene file in ``folder``, sorted by stem ({} when it is absent).
    Two files with one stem: the first in sorted order wins, as the server names scenes by stem."""
    if not folder.is_dir():
        return {}
    found: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in SCENE_EXTENSIONS:
            found.setdefault(p.stem, p)
    return found


REAL_PATHS = discover()
REAL = list(REAL_PATHS)


def real_path(name: str) -> Path:
    """The file of the real scene ``name``."""
    return REAL_PATHS[name]


@cache
def real_scene(name: str) -> Scene:
    """The scene ``name`` from ../shared/scenes, in metres (its sidecar applied), with its
    spatial hierarchy built, as a server has it shortly after loading the scene (the paths
    that cull then cull on every call, not only once a background build is done)."""
    scene = load_scene(real_path(name))
    scene_hierarchy(scene)
    return scene


@cache
def real_grid(name: str) -> ViewcellGrid:
    """Its viewcell grid at the scene's default cell size."""
    return ViewcellGrid.for_scene(real_scene(name))


def assert_pvs_frames_match(name: str, cell_size: float, core: str, params: dict,
                            walk_dir: Path, poses: list[int]) -> None:
    """Frames drawn from a core's PVS equal the full scene's in every pixel (ε = 0): for each
    index in ``poses`` of the walkthrough saved in ``walk_dir`` (``walkthrough.json``), the PVS
    of the cell of ``name`` (at ``cell_size`` m) holding the eye, rendered with the client's
    renderer against the whole scene."""
    import json

    import numpy as np

    from client.metrics import frame_metrics
    from client.render import OffscreenRenderer
    from visibility.cores.base import get_core

    walk = json.loads((walk_dir / "walkthrough.json").read_text())["poses"]
    scene = real_scene(name)
    grid = ViewcellGrid.for_scene(scene, cell_size)
    c = get_core(core)
    r = OffscreenRenderer(256, 256)
    try:
        for i in poses:
            eye, fwd = np.array(walk[i]["position"]), np.array(walk[i]["forward"])
            cid = grid.cell_of(eye)
            assert cid is not None, f"pose {i} lies in no cell"
            ids = c.compute(scene, grid.cell(cid), c.make_params(**params)).triangle_ids
            frame = r.render(scene.vertices[scene.faces[ids]], scene.colors[ids], eye, fwd)
            m = frame_metrics(frame, r.render_scene(scene, eye, fwd))
            assert m["epsilon"] == 0.0, (i, m)
    finally:
        r.close()
