"""The real third-party scenes beside the repository (../shared/scenes), loaded once per run."""

from __future__ import annotations

from functools import cache
from pathlib import Path

from visibility.loaders import load_scene
from visibility.scene import Scene
from visibility.viewcells import ViewcellGrid

SHARED_SCENES = Path(__file__).resolve().parents[2].parent / "shared" / "scenes"
REAL = ["lavaducts", "denhaag", "lyon_vilo3d", "kitchen"]


@cache
def real_scene(name: str) -> Scene:
    """The scene ``name`` from ../shared/scenes, in metres."""
    return load_scene(SHARED_SCENES / f"{name}.glb")


@cache
def real_grid(name: str) -> ViewcellGrid:
    """Its viewcell grid at the scene's default cell size."""
    return ViewcellGrid.for_scene(real_scene(name))
